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
#include "dmrCudaBackend.h"

#include "dmrCudaUtils.cuh"
#include <cuda_runtime.h>
#include <mutex>
#include <sstream>
#include <sys/resource.h> // getrlimit (POSIX)

namespace itk
{
namespace dmr
{
namespace cuda
{
namespace
{
/** Queries the runtime once; every failure becomes a reason string, never an exit. */
struct DeviceQuery
{
  bool        available{ false };
  std::string reason;
  std::string description;
  DeviceQuery()
  {
    int               count = 0;
    const cudaError_t status = cudaGetDeviceCount(&count);
    if (status != cudaSuccess)
    {
      reason = std::string("no usable CUDA device (") + cudaGetErrorString(status) + ")";
      cudaGetLastError(); // clear the sticky error
      // Under a limit on virtual memory (ulimit -v; a cluster's h_vmem) the runtime cannot reserve its address space
      // and reports "out of memory", or even "CUDA driver version is insufficient": say that the limit may be why.
      rlimit limit{};
      if (getrlimit(RLIMIT_AS, &limit) == 0 && limit.rlim_cur != RLIM_INFINITY)
      {
        reason += "; the process's virtual memory is limited to " + std::to_string(limit.rlim_cur >> 20) +
                  " MiB (ulimit -v), and the CUDA runtime reserves more address space than that, which gives such "
                  "errors: lift the limit to use the GPU";
      }
      return;
    }
    if (count == 0)
    {
      reason = "no CUDA device present";
      return;
    }
    cudaDeviceProp prop{};
    if (cudaGetDeviceProperties(&prop, 0) != cudaSuccess)
    {
      reason = "cudaGetDeviceProperties failed";
      return;
    }
    std::ostringstream os;
    os << prop.name << ", " << (prop.totalGlobalMem >> 20) << " MiB, sm_" << prop.major << prop.minor;
    description = os.str();
    available = true;
  }
};

const DeviceQuery &
Query()
{
  static const DeviceQuery query;
  return query;
}
} // namespace

bool
DeviceAvailable()
{
  return Query().available;
}

std::string
UnavailableReason()
{
  return Query().available ? std::string() : Query().reason;
}

std::string
DeviceDescription()
{
  return Query().available ? Query().description : Query().reason;
}

Status
CreateContext()
{
  if (!Query().available)
  {
    return Status::Error(Query().reason);
  }
  const cudaError_t status = cudaFree(nullptr); // the runtime's documented way to create the primary context
  if (status != cudaSuccess)
  {
    return Status::Error(std::string("CUDA context creation failed (") + cudaGetErrorString(status) + ")");
  }
  return Status::Success();
}

namespace
{
/** The allocator's counters (DeviceBuffer reports every cudaMalloc and cudaFree here). */
struct MemoryCounters
{
  std::mutex       mutex;
  MemoryStatistics statistics;
};

MemoryCounters &
Counters()
{
  static MemoryCounters counters;
  return counters;
}
} // namespace

void
RecordDeviceAllocation(size_t bytes)
{
  MemoryCounters &            c = Counters();
  std::lock_guard<std::mutex> lock(c.mutex);
  c.statistics.allocatedBytes += bytes;
  if (c.statistics.allocatedBytes > c.statistics.peakAllocatedBytes)
  {
    c.statistics.peakAllocatedBytes = c.statistics.allocatedBytes;
    size_t freeBytes = 0, totalBytes = 0;
    if (cudaMemGetInfo(&freeBytes, &totalBytes) == cudaSuccess)
    {
      c.statistics.deviceUsedAtPeakBytes = totalBytes - freeBytes;
    }
    else
    {
      cudaGetLastError(); // a statistic only: never a sticky error for the next launcher
    }
  }
}

void
RecordDeviceFree(size_t bytes) noexcept
{
  MemoryCounters &            c = Counters();
  std::lock_guard<std::mutex> lock(c.mutex);
  c.statistics.allocatedBytes -= std::min(bytes, c.statistics.allocatedBytes);
}

MemoryStatistics
GetMemoryStatistics()
{
  MemoryCounters &            c = Counters();
  std::lock_guard<std::mutex> lock(c.mutex);
  return c.statistics;
}

void
ResetMemoryPeak()
{
  MemoryCounters &            c = Counters();
  std::lock_guard<std::mutex> lock(c.mutex);
  c.statistics.peakAllocatedBytes = c.statistics.allocatedBytes;
  c.statistics.deviceUsedAtPeakBytes = 0; // sampled by the next allocation that raises the peak (no CUDA call here:
                                          // it would create the context on this thread)
}
} // namespace cuda
} // namespace dmr
} // namespace itk
