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
/** CVT swap optimiser of a build without CUDA (DMR_USE_CUDA=OFF): every call fails with "built without CUDA". */
#include "dmrCVTBackend.h"
#include <stdexcept>

namespace itk
{
namespace dmr
{
namespace cuda
{
namespace
{
Status
Unavailable()
{
  return Status::Error("CVTSwapOptimizer: the library was built without CUDA (DMR_USE_CUDA=OFF)");
}
} // namespace

struct CVTSwapOptimizer::Impl
{
};

CVTSwapOptimizer::CVTSwapOptimizer() = default;

CVTSwapOptimizer::~CVTSwapOptimizer() = default;

Status
CVTSwapOptimizer::SetGrid(unsigned int, const size_t *, const double *)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::SetDensity(const float *, bool)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::SetLabels(const int32_t *, size_t, bool)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::KeepLabels(size_t)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::ContractionBlockSums(unsigned int, std::vector<double> &, std::vector<double> &)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::SetBlockLabels(unsigned int, const int32_t *, size_t)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::Optimize(double, size_t, CVTSwapResult &)
{
  return Unavailable();
}

Status
CVTSwapOptimizer::DownloadLabels(int32_t *) const
{
  return Unavailable();
}

const int32_t *
CVTSwapOptimizer::DeviceLabels() const
{
  return nullptr;
}

Status
CVTSwapOptimizer::GetCells(std::vector<double> &, std::vector<double> &) const
{
  return Unavailable();
}

void
CVTSwapOptimizer::SetDeviceLoop(bool)
{
}

void
CVTSwapOptimizer::SetShortLabels(bool)
{
}

void
CVTSwapOptimizer::SetCellSlots(unsigned int)
{
}

void
CVTSwapOptimizer::SetPixelsPerProposalThread(unsigned int pixels)
{
  if (pixels > 2)
  {
    throw std::invalid_argument("CVTSwapOptimizer::SetPixelsPerProposalThread: 0 (automatic), 1 or 2");
  }
}

double
CVTSwapOptimizer::Energy() const
{
  return 0.0;
}

size_t
CVTSwapOptimizer::AllocatedBytes() const
{
  return 0;
}

size_t
CVTSwapOptimizer::NumberOfCells() const
{
  return 0;
}
} // namespace cuda
} // namespace dmr
} // namespace itk
