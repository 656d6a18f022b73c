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
#include "dmrWorkerTeam.h"

#include "gtest/gtest.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <mutex>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace
{
using itk::dmr::WorkerTeam;

TEST(WorkerTeam, EveryChunkRunsOnceInManyLoopsInARow)
{
  // the CVT's pattern: tens of thousands of short loops, each read back before the next one starts
  for (unsigned int threads : { 1u, 2u, 3u, 7u })
  {
    SCOPED_TRACE(std::to_string(threads) + " threads");
    WorkerTeam team(threads);
    EXPECT_EQ(team.GetNumberOfThreads(), threads);
    std::vector<std::atomic<unsigned>> runs(64);
    std::vector<unsigned>              value(64);
    size_t                             wrong = 0;
    const unsigned int loops = threads == 2 ? 20000 : 4000; // fewer where the threads may outnumber the cores
    for (unsigned int loop = 0; loop < loops; ++loop)
    {
      const size_t chunks = loop % 9; // 0 and 1 chunk too
      for (size_t c = 0; c < chunks; ++c)
      {
        runs[c].store(0);
      }
      team.Run(chunks, [&](size_t c) {
        runs[c].fetch_add(1);
        value[c] = loop * 64 + static_cast<unsigned>(c); // a plain write, read below: Run must publish it
      });
      for (size_t c = 0; c < chunks; ++c)
      {
        wrong += runs[c].load() != 1 || value[c] != loop * 64 + c;
      }
    }
    EXPECT_EQ(wrong, 0u);
  }
}

/** One loop of n chunks in which every chunk waits (up to 20 s) until all n have started: it ends at once only if n
 * threads take part. Returns the threads that ran a chunk; `started` receives how many chunks started. */
std::set<std::thread::id>
RunChunksThatWaitForEachOther(WorkerTeam & team, unsigned int n, unsigned int & started)
{
  std::atomic<unsigned>     entered{ 0 };
  std::set<std::thread::id> ids;
  std::mutex                mutex;
  team.Run(n, [&](size_t) {
    {
      std::lock_guard<std::mutex> lock(mutex);
      ids.insert(std::this_thread::get_id());
    }
    entered.fetch_add(1);
    const auto start = std::chrono::steady_clock::now();
    while (entered.load() < n && std::chrono::steady_clock::now() - start < std::chrono::seconds(20))
    {
      std::this_thread::yield();
    }
  });
  started = entered.load();
  return ids;
}

TEST(WorkerTeam, UsesItsThreads)
{
  WorkerTeam   team(3);
  unsigned int started = 0;
  const auto   ids = RunChunksThatWaitForEachOther(team, 3, started);
  EXPECT_EQ(started, 3u);
  EXPECT_EQ(ids.size(), 3u);
  EXPECT_EQ(ids.count(std::this_thread::get_id()), 1u); // the calling thread takes part
}

TEST(WorkerTeam, ALoopOfNChunksRunsOnAtMostNThreads)
{
  // the CVT's 2D lists take two chunks: on a team of five, the other three threads stay out
  WorkerTeam                team(5);
  std::set<std::thread::id> ids;
  std::mutex                mutex;
  for (unsigned int loop = 0; loop < 2000; ++loop)
  {
    team.Run(2, [&](size_t) {
      std::lock_guard<std::mutex> lock(mutex);
      ids.insert(std::this_thread::get_id());
    });
  }
  EXPECT_LE(ids.size(), 2u);
  EXPECT_EQ(ids.count(std::this_thread::get_id()), 1u);
}

TEST(WorkerTeam, WakesSleepingThreads)
{
  // pauses longer than the spinning and yielding phases: the other threads sleep on the condition variable between
  // loops and must be woken for each
  WorkerTeam team(2);
  for (unsigned int loop = 0; loop < 5; ++loop)
  {
    std::this_thread::sleep_for(std::chrono::milliseconds(3));
    unsigned int started = 0;
    EXPECT_EQ(RunChunksThatWaitForEachOther(team, 2, started).size(), 2u);
    EXPECT_EQ(started, 2u);
  }
}

TEST(WorkerTeam, RethrowsTheFirstExceptionAndStaysUsable)
{
  WorkerTeam            team(4);
  std::atomic<unsigned> ran{ 0 };
  try
  {
    team.Run(40, [&](size_t c) {
      ran.fetch_add(1);
      if (c == 5)
      {
        throw std::runtime_error("chunk 5 failed");
      }
    });
    FAIL() << "no exception";
  }
  catch (const std::runtime_error & e)
  {
    EXPECT_STREQ(e.what(), "chunk 5 failed");
  }
  EXPECT_GE(ran.load(), 1u);
  EXPECT_LE(ran.load(), 40u);
  std::vector<int> out(100, 0);
  team.Run(out.size(), [&](size_t c) { out[c] = static_cast<int>(c); });
  for (size_t c = 0; c < out.size(); ++c)
  {
    EXPECT_EQ(out[c], static_cast<int>(c));
  }
}

TEST(WorkerTeam, TakesItsThreadsFromTheThreader)
{
  EXPECT_EQ(WorkerTeam::ThreadsOf(nullptr), 1u);
  auto threader = itk::MultiThreaderBase::New();
  threader->SetMaximumNumberOfThreads(2);
  threader->SetNumberOfWorkUnits(8);
  // ITK's pool threader reports the pool's size, which only grows: an earlier test of the same process may have
  // asked for more threads (e.g. 4), so the threader's maximum is at least 2, not necessarily 2
  const auto maximum = static_cast<unsigned int>(threader->GetMaximumNumberOfThreads());
  EXPECT_GE(maximum, 2u);
  EXPECT_EQ(WorkerTeam::ThreadsOf(threader), std::min(maximum, 8u));
  threader->SetMaximumNumberOfThreads(4);
  threader->SetNumberOfWorkUnits(3);
  EXPECT_EQ(WorkerTeam::ThreadsOf(threader), 3u);
  threader->SetNumberOfWorkUnits(1);
  EXPECT_EQ(WorkerTeam::ThreadsOf(threader), 1u);
}
} // namespace
