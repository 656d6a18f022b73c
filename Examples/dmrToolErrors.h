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
#ifndef dmrToolErrors_h
#define dmrToolErrors_h

// Error reporting shared by the command-line tools: every failure is one line on stderr and a non-zero exit code
// (2 for bad input, 1 for a failure while running).
#include "itkMacro.h"
#include "itkMultiThreaderBase.h"
#include "itkObject.h"
#include <condition_variable>
#include <cstdio>
#include <csignal>
#include <signal.h> // sigaction (POSIX)
#include <time.h>   // clock_gettime (POSIX)
#include <unistd.h> // dup, dup2 (POSIX)
#include <iostream>
#include <mutex>
#include <new>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

namespace dmrtools
{
/** A bad-input error: reported as one line, exit code 2. */
struct UsageError : std::runtime_error
{
  using std::runtime_error::runtime_error;
};

/** The message on one line (ITK's exception texts can span several), without runs of spaces. */
inline std::string
OneLine(std::string message)
{
  for (char & c : message)
  {
    if (c == '\n' || c == '\r' || c == '\t')
    {
      c = ' ';
    }
  }
  std::string out;
  for (char c : message)
  {
    if (!(c == ' ' && !out.empty() && out.back() == ' '))
    {
      out += c;
    }
  }
  while (!out.empty() && out.back() == ' ')
  {
    out.pop_back();
  }
  return out;
}

/** text without ITK's "ITK ERROR: " prefixes and without the object's address in "Class(0x55d0c0ffee00): " after one
 * (ITK's exception descriptions carry both, also inside a message that quotes one; they are meant for developers). */
inline std::string
WithoutItkPrefix(std::string text)
{
  const std::string prefix = "ITK ERROR: ";
  for (auto at = text.find(prefix); at != std::string::npos; at = text.find(prefix, at))
  {
    text.erase(at, prefix.size());
    const auto open = text.find("(0x", at);
    const auto close = open == std::string::npos ? open : text.find("): ", open);
    if (close != std::string::npos && text.find(' ', at) > open)
    {
      text.erase(open, close + 1 - open);
    }
  }
  return text;
}

/** The number of the interrupting signal (SIGINT, SIGTERM, SIGHUP) a tool received, 0 while none. */
inline volatile std::sig_atomic_t &
InterruptSignal()
{
  static volatile std::sig_atomic_t signalNumber = 0;
  return signalNumber;
}

/** Thrown where a tool notices an interruption; not a std::exception, so that no handler of errors rewraps it. */
struct Interrupted
{
  int signalNumber;
};

/** Throws Interrupted once an interrupting signal arrived. The tools call it between their steps (the registration
 * tool also stops the registration at the next iteration), so that the staged outputs are removed on the way out. */
inline void
ThrowIfInterrupted()
{
  if (InterruptSignal() != 0)
  {
    throw Interrupted{ static_cast<int>(InterruptSignal()) };
  }
}

/** Milliseconds on the monotonic clock (clock_gettime may be called in a signal handler). */
inline long long
MonotonicMilliseconds()
{
  struct timespec now = {};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return static_cast<long long>(now.tv_sec) * 1000 + now.tv_nsec / 1000000;
}

/** The time of the first interrupting signal (written only by the handler, which blocks the others while it runs). */
inline long long &
FirstInterruptMilliseconds()
{
  static long long milliseconds = 0;
  return milliseconds;
}

/** Records the first interrupting signal. A later one ends the process at once (the default action) if it comes at
 * least a second after the first: one that comes sooner is the same request delivered twice, which `timeout` does
 * (to the process, then to its process group) and which ended the process before it had removed its staged outputs. */
extern "C" inline void
RecordInterruptSignal(int signalNumber)
{
  const long long now = MonotonicMilliseconds();
  if (InterruptSignal() == 0)
  {
    FirstInterruptMilliseconds() = now;
    InterruptSignal() = signalNumber;
  }
  else if (now - FirstInterruptMilliseconds() >= 1000)
  {
    std::signal(signalNumber, SIG_DFL);
    std::raise(signalNumber); // delivered when the handler returns (the signal is blocked while it runs)
  }
}

/** Catches SIGINT, SIGTERM and SIGHUP: the first one is recorded for ThrowIfInterrupted, which the tool must then call
 * (Staging::Commit does); another one a second or more later ends the process at once (RecordInterruptSignal). A signal
 * that is ignored when the tool starts (a background job of a non-interactive shell ignores SIGINT) stays ignored. */
inline void
CatchInterruptSignals()
{
  for (int signalNumber : { SIGINT, SIGTERM, SIGHUP })
  {
    struct sigaction current = {};
    if (sigaction(signalNumber, nullptr, &current) != 0 || current.sa_handler == SIG_IGN)
    {
      continue;
    }
    struct sigaction action = {};
    action.sa_handler = RecordInterruptSignal;
    sigemptyset(&action.sa_mask);
    for (int blocked : { SIGINT, SIGTERM, SIGHUP })
    {
      sigaddset(&action.sa_mask, blocked);
    }
    action.sa_flags = SA_RESTART;
    sigaction(signalNumber, &action, nullptr);
  }
}

/** Ends the process by the signal that interrupted it, as if it had not been caught (the calling shell or scheduler
 * sees the signal, not an exit code), after a one-line message; returns 128 + the signal number if that fails. */
inline int
EndByInterruptSignal(const char * tool, int signalNumber)
{
  const char * name = signalNumber == SIGINT ? "SIGINT" : signalNumber == SIGTERM ? "SIGTERM" : "SIGHUP";
  std::cerr << tool << ": interrupted (" << name << "); the run's outputs were not written\n";
  std::cerr.flush();
  std::signal(signalNumber, SIG_DFL);
  std::raise(signalNumber);
  return 128 + signalNumber;
}

/** Captures what is written to the process's standard error (file descriptor 2, so C's stderr and std::cerr alike)
 * from its construction to Release(): NIfTI's and MetaIO's readers print their own lines about a bad header ("** ERROR:
 * nifti_convert_nhdr2nim: bad dim[0]", four lines of MetaIO) before ITK throws, which broke the tools' one-line errors.
 * What other threads write meanwhile is captured too, so keep it short. Captures nothing when no temporary file can be
 * made. */
class StandardErrorCapture
{
public:
  StandardErrorCapture()
  {
    std::fflush(stderr);
    std::cerr.flush();
    m_File = std::tmpfile();
    if (m_File != nullptr)
    {
      m_Saved = ::dup(2);
      if (m_Saved < 0 || ::dup2(::fileno(m_File), 2) < 0)
      {
        if (m_Saved >= 0)
        {
          ::close(m_Saved);
        }
        std::fclose(m_File);
        m_File = nullptr;
      }
    }
  }
  StandardErrorCapture(const StandardErrorCapture &) = delete;
  StandardErrorCapture &
  operator=(const StandardErrorCapture &) = delete;
  ~StandardErrorCapture() { Release(); }

  /** Ends the capture (standard error goes where it went before) and returns what was written, on one line (lines
   * joined by "; ", at most 400 characters). */
  std::string
  Release()
  {
    if (m_File == nullptr)
    {
      return m_Text;
    }
    std::fflush(stderr);
    std::cerr.flush();
    ::dup2(m_Saved, 2);
    ::close(m_Saved);
    std::rewind(m_File);
    char         buffer[400];
    const size_t got = std::fread(buffer, 1, sizeof(buffer), m_File);
    std::fclose(m_File);
    m_File = nullptr;
    std::string text(buffer, got);
    while (!text.empty() && (text.back() == '\n' || text.back() == ' '))
    {
      text.pop_back();
    }
    for (size_t at = text.find('\n'); at != std::string::npos; at = text.find('\n', at))
    {
      text.replace(at, 1, "; ");
    }
    m_Text = OneLine(text);
    return m_Text;
  }

private:
  std::FILE * m_File{ nullptr };
  int         m_Saved{ -1 };
  std::string m_Text;
};

/** Starts `count` threads that all run at once, then ends them; throws a std::runtime_error (exit code 1) that says so
 * when the process may not start that many: a limit on its threads or on its virtual memory (each thread reserves a
 * stack). */
inline void
RequireThreads(unsigned int count)
{
  std::mutex               mutex;
  std::condition_variable  released;
  bool                     release = false;
  std::vector<std::thread> threads;
  threads.reserve(count);
  std::string failure;
  try
  {
    while (threads.size() < count)
    {
      threads.emplace_back([&] {
        std::unique_lock<std::mutex> lock(mutex);
        released.wait(lock, [&] { return release; });
      });
    }
  }
  catch (const std::system_error & e)
  {
    failure = e.what();
  }
  {
    std::lock_guard<std::mutex> lock(mutex);
    release = true;
  }
  released.notify_all();
  for (auto & t : threads)
  {
    t.join();
  }
  if (!failure.empty())
  {
    throw std::runtime_error("cannot start " + std::to_string(count) + " threads, only " +
                             std::to_string(threads.size()) + " (" + failure +
                             "): the process's limit on threads or on virtual memory (ulimit -u, ulimit -v, a "
                             "container's pids limit) is lower; run with fewer threads (--threads, or "
                             "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS)");
  }
}

/** Makes ITK's thread pool on the calling thread once the process is known to be able to start its threads. ITK 5.2's
 * pool cannot recover from a thread that fails to start: the process then ended by std::terminate with no message,
 * or crashed at exit after its error message. Call it before anything else uses ITK's threader. */
inline void
StartItkThreadPool()
{
  RequireThreads(itk::MultiThreaderBase::GetGlobalDefaultNumberOfThreads());
  itk::MultiThreaderBase::New();
}

/** Runs a tool's body and turns every exception into "<tool>: error: <one line>" on stderr and an exit code; an
 * Interrupted exception (after CatchInterruptSignals) ends the process by its signal once the body has cleaned up. */
template <typename TBody>
int
RunReportingErrors(const char * tool, TBody && body)
{
  itk::Object::GlobalWarningDisplayOff(); // warnings (e.g. GDCM's "no series found") would break one-line errors
  try
  {
    return body();
  }
  catch (const Interrupted & e)
  {
    return EndByInterruptSignal(tool, e.signalNumber);
  }
  catch (const UsageError & e)
  {
    std::cerr << tool << ": error: " << OneLine(WithoutItkPrefix(e.what())) << '\n';
    return 2;
  }
  catch (const itk::MemoryAllocationError & e)
  {
    std::cerr << tool << ": error: out of memory: " << OneLine(WithoutItkPrefix(e.GetDescription())) << '\n';
    return 1;
  }
  catch (const itk::ExceptionObject & e)
  {
    std::cerr << tool << ": error: " << OneLine(WithoutItkPrefix(e.GetDescription())) << '\n';
    return 1;
  }
  catch (const std::bad_alloc & e)
  {
    std::cerr << tool << ": error: out of memory (" << e.what()
              << "): the run needs more memory than the process may use\n";
    return 1;
  }
  catch (const std::system_error & e)
  {
    std::cerr << tool << ": error: " << OneLine(WithoutItkPrefix(e.what()));
    if (e.code() == std::errc::resource_unavailable_try_again)
    {
      std::cerr << " (a thread could not start: the process's limit on threads or on virtual memory is lower than "
                   "the run needs; run with fewer threads)";
    }
    std::cerr << '\n';
    return 1;
  }
  catch (const std::exception & e)
  {
    std::cerr << tool << ": error: " << OneLine(WithoutItkPrefix(e.what())) << '\n';
    return 1;
  }
}
} // namespace dmrtools

#endif
