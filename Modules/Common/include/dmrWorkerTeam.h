/*=========================================================================
 *
 *  DynamicMeshRegistration
 *
 *  Licensed under the Apache License, Version 2.0 (the "License");
 *  you may not use this file except in compliance with the License.
 *  You may obtain a copy of the License at
 *
 *         http://www.apache.org/licenses/LICENSE-2.0.txt
 *
 *  Unless required by applicable law or agreed to in writing, software
 *  distributed under the License is distributed on an "AS IS" BASIS,
 *  WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
 *  See the License for the specific language governing permissions and
 *  limitations under the License.
 *
 *=========================================================================*/
#ifndef dmrWorkerTeam_h
#define dmrWorkerTeam_h

#include "dmrGrid.h" // ParallelForChunkIds
#include "itkMultiThreaderBase.h"
#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <memory>
#include <mutex>
#include <system_error>
#include <thread>
#include <type_traits>
#include <vector>
#if defined(__x86_64__) || defined(_M_X64) || defined(__i386__)
#include <immintrin.h>
#endif

namespace itk
{
namespace dmr
{
/** A team of threads for many short parallel loops in a row, such as the CVT's sub-sweeps (tens of thousands of loops
 * of tens of microseconds each in a 2D registration). ITK's pool hands every loop to its threads through queued tasks
 * and futures, which costs about 20-35 us per loop on a 2-core machine; here the calling thread takes part and the
 * other threads wait between loops by spinning for a short while (then by yielding, then on a condition variable),
 * so a loop that follows closely on the last one starts within about a microsecond.
 *
 * The number of threads comes from ITK's threader (ThreadsOf), so ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS and the
 * filters' work-unit settings keep control. Run(n, body) calls body(c) once for every chunk c in [0, n), the chunks
 * claimed by the threads in turn: callers that need deterministic results combine per-chunk outputs in chunk order,
 * as with ParallelForChunkIds. A loop of n chunks wakes at most n - 1 of the other threads. The first exception
 * thrown by a body is rethrown by Run after all chunks ended. One Run at a time (the team is not meant to be shared
 * between threads that call Run). */
class WorkerTeam
{
public:
  /** The threads of a team for `threader`: its work units, at most its maximum number of threads; 1 without one. */
  static unsigned int
  ThreadsOf(const MultiThreaderBase * threader)
  {
    if (threader == nullptr)
    {
      return 1;
    }
    const auto units = static_cast<unsigned int>(threader->GetNumberOfWorkUnits());
    const auto threads = static_cast<unsigned int>(threader->GetMaximumNumberOfThreads());
    return std::max(1u, std::min(units, threads));
  }

  /** numberOfThreads counts the calling thread; the other threads start here and end in the destructor. */
  explicit WorkerTeam(unsigned int numberOfThreads)
  {
    const unsigned int workers =
      numberOfThreads > 1 ? static_cast<unsigned int>(std::min<uint64_t>(numberOfThreads - 1, HelperMask)) : 0;
    m_Workers.reserve(workers);
    try
    {
      for (unsigned int t = 0; t < workers; ++t)
      {
        m_Workers.emplace_back([this, t] { this->WorkerLoop(t); });
      }
    }
    catch (...)
    {
      this->Stop(); // a thread that cannot start: end the started ones, then report it
      throw;
    }
  }

  ~WorkerTeam() { this->Stop(); }

  WorkerTeam(const WorkerTeam &) = delete;
  WorkerTeam &
  operator=(const WorkerTeam &) = delete;

  unsigned int
  GetNumberOfThreads() const
  {
    return static_cast<unsigned int>(m_Workers.size()) + 1;
  }

  template <typename TBody>
  void
  Run(size_t numberOfChunks, TBody && body)
  {
    if (m_Workers.empty() || numberOfChunks <= 1)
    {
      for (size_t c = 0; c < numberOfChunks; ++c)
      {
        body(c);
      }
      return;
    }
    using BodyType = std::remove_reference_t<TBody>;
    m_Body = const_cast<void *>(static_cast<const void *>(&body));
    m_Invoke = [](void * b, size_t c) { (*static_cast<BodyType *>(b))(c); };
    m_NumberOfChunks = numberOfChunks;
    m_NextChunk.store(0, std::memory_order_relaxed);
    m_Finished.store(0, std::memory_order_relaxed);
    m_Error = nullptr;
    m_Failed.store(false, std::memory_order_relaxed);
    // workers 0 .. helpers - 1 take part; the loop's number and its helper count are published in one word, so that a
    // worker that reads it late (after this loop ended and the next began) sees the next loop's pair, never a mix
    const auto helpers = static_cast<unsigned int>(std::min<size_t>(m_Workers.size(), numberOfChunks - 1));
    ++m_Loop;
    {
      // under the mutex, so that a worker that is about to sleep either sees the new loop or gets the notification
      std::lock_guard<std::mutex> lock(m_Mutex);
      m_Word.store(m_Loop << HelperBits | helpers, std::memory_order_release);
    }
    m_Wake.notify_all();
    this->Work();
    WaitUntil([&] { return m_Finished.load(std::memory_order_acquire) == helpers; });
    if (m_Error)
    {
      std::exception_ptr error = m_Error;
      m_Error = nullptr;
      std::rethrow_exception(error);
    }
  }

private:
  /** Spins 256 pause instructions (a few microseconds), yields up to 200 us, then sleeps 50 us at a time until done()
   * holds (the caller's wait for the other threads' last chunks, which are as short as its own). */
  template <typename TDone>
  static void
  WaitUntil(TDone && done)
  {
    for (unsigned int i = 0; i < 256; ++i)
    {
      if (done())
      {
        return;
      }
      Pause();
    }
    const auto start = std::chrono::steady_clock::now();
    while (!done())
    {
      if (std::chrono::steady_clock::now() - start < std::chrono::microseconds(200))
      {
        std::this_thread::yield();
      }
      else
      {
        std::this_thread::sleep_for(std::chrono::microseconds(50));
      }
    }
  }

  static void
  Pause()
  {
#if defined(__x86_64__) || defined(_M_X64) || defined(__i386__)
    _mm_pause();
#else
    std::this_thread::yield();
#endif
  }

  void
  Work()
  {
    for (;;)
    {
      const size_t c = m_NextChunk.fetch_add(1, std::memory_order_relaxed);
      if (c >= m_NumberOfChunks)
      {
        return;
      }
      if (m_Failed.load(std::memory_order_relaxed))
      {
        continue; // an earlier chunk threw: claim the rest without running them
      }
      try
      {
        m_Invoke(m_Body, c);
      }
      catch (...)
      {
        std::lock_guard<std::mutex> lock(m_ErrorMutex);
        if (!m_Error)
        {
          m_Error = std::current_exception();
        }
        m_Failed.store(true, std::memory_order_relaxed);
      }
    }
  }

  void
  WorkerLoop(unsigned int id)
  {
    uint64_t seen = 0; // the last loop this worker saw
    for (;;)
    {
      uint64_t   word = m_Word.load(std::memory_order_acquire);
      const auto start = std::chrono::steady_clock::now();
      for (unsigned int i = 0; (word >> HelperBits) == seen && !m_Stop.load(std::memory_order_acquire); ++i)
      {
        // spin (1024 pause instructions, 5-40 us by the CPU), then yield up to 300 us, then sleep on the condition
        // variable: the CVT's loops follow each other within tens of microseconds while a sweep lasts, and not at
        // all between the registration's iterations
        if (i < 1024)
        {
          Pause();
        }
        else if (std::chrono::steady_clock::now() - start < std::chrono::microseconds(300))
        {
          std::this_thread::yield();
        }
        else
        {
          std::unique_lock<std::mutex> lock(m_Mutex);
          m_Wake.wait(lock, [&] {
            return (m_Word.load(std::memory_order_relaxed) >> HelperBits) != seen ||
                   m_Stop.load(std::memory_order_relaxed);
          });
        }
        word = m_Word.load(std::memory_order_acquire);
      }
      if ((word >> HelperBits) == seen)
      {
        return; // stopped
      }
      seen = word >> HelperBits;
      if (id < (word & HelperMask))
      {
        this->Work();
        m_Finished.fetch_add(1, std::memory_order_release);
      }
    }
  }

  void
  Stop()
  {
    {
      std::lock_guard<std::mutex> lock(m_Mutex);
      m_Stop.store(true, std::memory_order_release);
    }
    m_Wake.notify_all();
    for (auto & t : m_Workers)
    {
      if (t.joinable())
      {
        t.join();
      }
    }
    m_Workers.clear();
  }

  static constexpr unsigned int HelperBits = 24;
  static constexpr uint64_t     HelperMask = (uint64_t(1) << HelperBits) - 1;

  std::vector<std::thread> m_Workers;
  std::mutex               m_Mutex;
  std::condition_variable  m_Wake;
  uint64_t                 m_Loop{ 0 }; // loops run so far (the caller's count)
  std::atomic<uint64_t>    m_Word{ 0 }; // m_Loop << HelperBits | the loop's number of helping workers
  std::atomic<bool>        m_Stop{ false };
  std::atomic<size_t>      m_NextChunk{ 0 };
  std::atomic<unsigned>    m_Finished{ 0 };
  std::atomic<bool>        m_Failed{ false };
  size_t                   m_NumberOfChunks{ 0 };
  void *                   m_Body{ nullptr };
  void (*m_Invoke)(void *, size_t){ nullptr };
  std::mutex         m_ErrorMutex;
  std::exception_ptr m_Error;
};

/** The parallel loops of one call (a CVT Optimize, a conjugate-gradient solve) on a WorkerTeam made at the first loop
 * with more than one chunk, with as many threads as that loop has chunks (at most the threader's,
 * WorkerTeam::ThreadsOf) and made larger when a later loop has more. Its threads come on top of ITK's pool: where the
 * process may not start them (a limit on threads or on virtual memory), this and the later loops until Release() run on
 * the threader instead, with the same chunks. Release() (or the destructor) ends the team's threads. Callers that need
 * deterministic results combine per-chunk outputs in chunk order, as with WorkerTeam::Run. */
class TeamRunner
{
public:
  TeamRunner() = default;
  TeamRunner(const TeamRunner &) = delete;
  TeamRunner &
  operator=(const TeamRunner &) = delete;
  TeamRunner(TeamRunner &&) = default;
  TeamRunner &
  operator=(TeamRunner &&) = default;

  /** body(c) for every chunk c in [0, numberOfChunks), in parallel on the team (or the threader), serially without a
   * threader or with one thread. */
  template <typename TBody>
  void
  Run(MultiThreaderBase * threader, size_t numberOfChunks, TBody && body)
  {
    const auto threads = static_cast<unsigned int>(std::min<size_t>(WorkerTeam::ThreadsOf(threader), numberOfChunks));
    if (threads <= 1)
    {
      for (size_t c = 0; c < numberOfChunks; ++c)
      {
        body(c);
      }
      return;
    }
    if (!m_Unavailable && (!m_Team || m_Team->GetNumberOfThreads() < threads))
    {
      m_Team.reset(); // its threads end before the larger team's start
      try
      {
        m_Team = std::make_unique<WorkerTeam>(threads);
      }
      catch (const std::system_error &)
      {
        m_Unavailable = true;
      }
    }
    if (m_Unavailable)
    {
      ParallelForChunkIds(threader, numberOfChunks, body);
      return;
    }
    m_Team->Run(numberOfChunks, body);
  }

  /** Ends the team's threads; the next loop may try to start a team again. */
  void
  Release()
  {
    m_Team.reset();
    m_Unavailable = false;
  }

private:
  std::unique_ptr<WorkerTeam> m_Team;
  bool                        m_Unavailable{ false }; // its threads could not start (until Release)
};
} // namespace dmr
} // namespace itk

#endif
