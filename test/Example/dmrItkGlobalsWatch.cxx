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

// A library preloaded (LD_PRELOAD) into a tool by the smoke test "run-itk-globals": it watches where ITK creates its
// process-wide globals. ITK 5.2 creates each of them (the default threader, the thread pool, the release-data flag,
// ...) on first use and registers it in the std::map of itk::SingletonIndex, without a lock; two threads that do so
// side by side can corrupt the map (seen as a crash during a run or a hang in ~SingletonIndex at exit). The tools
// therefore create them on the main thread before they start threads (dmrtools::InitializeItkGlobals).
//
// This library defines itk::SingletonIndex::SetGlobalInstancePrivate, the one function through which every global is
// registered; being preloaded, its definition is the one the ITK libraries call. It counts the calls, forwards them to
// ITK's own definition (the next one in the lookup order) and ends the process with exit code 97 and one line on
// stderr when a call comes from a thread other than the main one. At exit it writes how many globals it saw, so that a
// test can tell that it was active (a watch that is never called would let any tool pass).
#include "itkSingleton.h"
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <dlfcn.h>
#include <sys/syscall.h>
#include <unistd.h>

namespace
{
std::atomic<int> g_Registrations{ 0 };

struct ReportAtExit
{
  ~ReportAtExit()
  {
    std::fprintf(stderr, "itk-globals-watch: %d globals, all on the main thread\n", g_Registrations.load());
  }
} g_Report;
} // namespace

bool
itk::SingletonIndex::SetGlobalInstancePrivate(const char *                globalName,
                                              void *                      global,
                                              std::function<void(void *)> func,
                                              std::function<void(void)>   deleteFunc)
{
  if (syscall(SYS_gettid) != getpid())
  {
    std::fprintf(
      stderr, "itk-globals-watch: ITK global '%s' created on a thread other than the main thread\n", globalName);
    std::fflush(stderr);
    std::_Exit(97);
  }
  ++g_Registrations;
  using Function =
    bool (*)(itk::SingletonIndex *, const char *, void *, std::function<void(void *)>, std::function<void(void)>);
  static const auto next = reinterpret_cast<Function>(
    dlsym(RTLD_NEXT, "_ZN3itk14SingletonIndex24SetGlobalInstancePrivateEPKcPvSt8functionIFvS3_EES4_IFvvEE"));
  if (next == nullptr)
  {
    std::fprintf(stderr, "itk-globals-watch: ITK's SetGlobalInstancePrivate not found\n");
    std::_Exit(98);
  }
  return next(this, globalName, global, std::move(func), std::move(deleteFunc));
}
