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

namespace itk
{
namespace dmr
{
namespace cuda
{
bool
DeviceAvailable()
{
  return false;
}

std::string
UnavailableReason()
{
  return "the library was built without CUDA (DMR_USE_CUDA=OFF)";
}

std::string
DeviceDescription()
{
  return UnavailableReason();
}

Status
CreateContext()
{
  return Status::Error(UnavailableReason());
}

MemoryStatistics
GetMemoryStatistics()
{
  return MemoryStatistics{};
}

void
ResetMemoryPeak()
{
}
} // namespace cuda
} // namespace dmr
} // namespace itk
