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

#include <cuda_runtime.h>
#include <sstream>

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
} // namespace cuda
} // namespace dmr
} // namespace itk
