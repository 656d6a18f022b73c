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
#include "dmrRegistrationBackend.h"

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
  return Status::Error("the library was built without CUDA (DMR_USE_CUDA=OFF)");
}
} // namespace

struct RegistrationContext::Impl
{
};

RegistrationContext::RegistrationContext() = default;
RegistrationContext::~RegistrationContext() = default;

Status
RegistrationContext::Initialize(unsigned int,
                                const size_t *,
                                const double *,
                                const std::vector<PyramidLevelView> &,
                                const uint8_t *)
{
  return Unavailable();
}
Status
RegistrationContext::ComputeForce(ForceStatistics &, bool)
{
  return Unavailable();
}
Status
RegistrationContext::RevertUpdate()
{
  return Unavailable();
}
Status
RegistrationContext::AddToDensity(double)
{
  return Unavailable();
}
const float *
RegistrationContext::DeviceDensity() const
{
  return nullptr;
}
Status
RegistrationContext::DownloadDensity(float *) const
{
  return Unavailable();
}
Status
RegistrationContext::DownloadForce(float *) const
{
  return Unavailable();
}
Status
RegistrationContext::DownloadLevel(unsigned int, float *, float *, float *) const
{
  return Unavailable();
}
Status
RegistrationContext::SetMesh(const double *, size_t, const int32_t *, size_t)
{
  return Unavailable();
}
Status
RegistrationContext::DownloadElementRaster(double *, int64_t *) const
{
  return Unavailable();
}
Status
RegistrationContext::SetElasticity(double, double, const uint8_t *)
{
  return Unavailable();
}
Status
RegistrationContext::SolveElasticity(const double *, double *, double, size_t, size_t &, bool &)
{
  return Unavailable();
}
Status
RegistrationContext::ElasticEnergy(const double *, double &)
{
  return Unavailable();
}
Status
RegistrationContext::DownloadElementOfPixels(int32_t *) const
{
  return Unavailable();
}
Status
RegistrationContext::GatherForce(double, double *)
{
  return Unavailable();
}
Status
RegistrationContext::SampleFieldAtNodes(double *)
{
  return Unavailable();
}
Status
RegistrationContext::ApplyUpdate(const double *, double, double &, unsigned int &)
{
  return Unavailable();
}
Status
RegistrationContext::DownloadPhysicalField(const double *, float *) const
{
  return Unavailable();
}
Status
RegistrationContext::DownloadField(float *) const
{
  return Unavailable();
}
Status
RegistrationContext::EnableInverse(const float *)
{
  return Unavailable();
}
Status
RegistrationContext::ApplyInverseUpdate(const double *, double)
{
  return Unavailable();
}
Status
RegistrationContext::DownloadInverse(float *) const
{
  return Unavailable();
}
Status
RegistrationContext::UploadField(const float *)
{
  return Unavailable();
}
void
RegistrationContext::SetCooperativeSolve(bool)
{
}

size_t
RegistrationContext::AllocatedBytes() const
{
  return 0;
}
} // namespace cuda
} // namespace dmr
} // namespace itk
