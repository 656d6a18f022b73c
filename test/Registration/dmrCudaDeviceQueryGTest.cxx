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
// Why the CUDA back-end is unavailable, under a limit on virtual memory (ulimit -v; a cluster's h_vmem): the runtime
// cannot reserve its address space and says "out of memory" or even "CUDA driver version is insufficient" (seen on
// the H100 machine under 1 to 8 GB), so the reason names the limit. Runs without a GPU too: the query fails there for
// its own reason, and the limit is named all the same.
#include "dmrConfigure.h"
#include "dmrCudaBackend.h"
#include "gtest/gtest.h"
#include <fstream>
#include <string>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

TEST(CudaDeviceQuery, AVirtualMemoryLimitIsNamedAsAPossibleReason)
{
#ifndef DMR_USE_CUDA
  GTEST_SKIP() << "built without CUDA: the reason is the build's";
#else
  char      pattern[] = "/tmp/dmr-cuda-query-XXXXXX";
  const int descriptor = ::mkstemp(pattern);
  ASSERT_GE(descriptor, 0);
  ::close(descriptor);
  const std::string reasonFile = pattern;
  // the query runs once per process: in a child whose address space is limited to 1 GiB from the start
  const pid_t child = ::fork();
  if (child == 0)
  {
    const rlimit limit{ rlim_t(1) << 30, rlim_t(1) << 30 };
    ::setrlimit(RLIMIT_AS, &limit);
    const bool available = itk::dmr::cuda::DeviceAvailable();
    std::ofstream(reasonFile) << (available ? std::string("available") : itk::dmr::cuda::UnavailableReason());
    std::_Exit(0);
  }
  int status = 0;
  ::waitpid(child, &status, 0);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  std::string reason;
  std::getline(std::ifstream(reasonFile), reason);
  ::unlink(reasonFile.c_str());
  if (reason == "available")
  {
    GTEST_SKIP() << "the CUDA runtime started within 1 GiB of address space";
  }
  EXPECT_NE(reason.find("no usable CUDA device ("), std::string::npos) << reason;
  EXPECT_NE(reason.find("limited to 1024 MiB (ulimit -v)"), std::string::npos) << reason;
#endif
}

TEST(CudaDeviceQuery, WithoutALimitTheReasonIsTheRuntimesAlone)
{
  rlimit limit{};
  ASSERT_EQ(::getrlimit(RLIMIT_AS, &limit), 0);
  if (limit.rlim_cur != RLIM_INFINITY)
  {
    GTEST_SKIP() << "this process's virtual memory is limited";
  }
  EXPECT_EQ(itk::dmr::cuda::UnavailableReason().find("ulimit -v"), std::string::npos)
    << itk::dmr::cuda::UnavailableReason();
}
