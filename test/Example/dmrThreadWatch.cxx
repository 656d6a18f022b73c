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
// A library preloaded (LD_PRELOAD) into a tool by the smoke test "run-thread-watch": it counts the threads the process
// starts, and those that TBB starts. Debian's VTK runs its SMP loops (e.g. the ranges of the arrays its XML writer
// stores) on TBB, which starts a worker per core on first use; a worker that fails to start (a limit on threads or on
// virtual memory) ends the process by std::terminate from inside TBB, with no message. The registration tool therefore
// sets VTK's sequential back-end, and the test checks that TBB starts no thread.
//
// This library defines pthread_create; being preloaded, its definition is the one the other libraries call. It
// forwards every call to the C library's and counts it, by caller: the library that holds the calling code (dladdr of
// the return address). At exit it writes one line, "thread-watch: T threads, B by TBB", so that a test can also tell
// that it was active (T > 0: the tool starts threads of its own).
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <dlfcn.h>
#include <pthread.h>

namespace
{
std::atomic<int> g_Threads{ 0 };
std::atomic<int> g_TbbThreads{ 0 };

struct ReportAtExit
{
  ~ReportAtExit()
  {
    std::fprintf(stderr, "thread-watch: %d threads, %d by TBB\n", g_Threads.load(), g_TbbThreads.load());
  }
} g_Report;
} // namespace

extern "C" int
pthread_create(pthread_t * thread, const pthread_attr_t * attributes, void * (*start)(void *), void * argument)
{
  using Function = int (*)(pthread_t *, const pthread_attr_t *, void * (*)(void *), void *);
  static const auto next = reinterpret_cast<Function>(dlsym(RTLD_NEXT, "pthread_create"));
  if (next == nullptr)
  {
    std::fprintf(stderr, "thread-watch: the C library's pthread_create not found\n");
    std::_Exit(98);
  }
  Dl_info caller{};
  if (dladdr(__builtin_return_address(0), &caller) != 0 && caller.dli_fname != nullptr &&
      std::strstr(caller.dli_fname, "libtbb") != nullptr)
  {
    ++g_TbbThreads;
  }
  ++g_Threads;
  return next(thread, attributes, start, argument);
}
