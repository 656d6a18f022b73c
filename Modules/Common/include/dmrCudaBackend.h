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
#ifndef dmrCudaBackend_h
#define dmrCudaBackend_h

#include "DynamicMeshRegistrationExport.h"
#include <string>
#include <utility>

/** Plain C++ launcher API of the CUDA back-end (no CUDA or ITK types): see STYLE.md section 4.
 * Compiled from Common/cuda/dmrCudaDevice.cu when DMR_USE_CUDA=ON, from Common/src/dmrCudaStub.cxx otherwise. */
namespace itk
{
namespace dmr
{
namespace cuda
{
/** Outcome of a launcher call: an empty message means success. Launchers never exit or print; the filters turn a
 * failed Status into an itk::ExceptionObject. */
struct Status
{
  std::string message;
  bool
  Ok() const
  {
    return message.empty();
  }
  static Status
  Success()
  {
    return Status{};
  }
  static Status
  Error(std::string text)
  {
    return Status{ text.empty() ? std::string("unknown CUDA error") : std::move(text) };
  }
};

/** True when the library was built with CUDA and a usable device is present. */
DynamicMeshRegistration_EXPORT bool
DeviceAvailable();

/** Why DeviceAvailable() is false (empty when it is true). */
DynamicMeshRegistration_EXPORT std::string
                               UnavailableReason();

/** One-line description of the device (name, memory), or the reason it is unavailable. */
DynamicMeshRegistration_EXPORT std::string
                               DeviceDescription();

/** Creates the device's primary context now (it is otherwise created by the first launcher call, which then takes
 * about 0.1 s longer). Thread-safe: the registration calls it on a helper thread while the host prepares its data. */
DynamicMeshRegistration_EXPORT Status
CreateContext();

/** Device memory of the back-end: every device buffer of the library goes through one allocator, which counts it. */
struct MemoryStatistics
{
  size_t allocatedBytes{ 0 };        // held now
  size_t peakAllocatedBytes{ 0 };    // the most held at once since the last ResetMemoryPeak()
  size_t deviceUsedAtPeakBytes{ 0 }; // the whole device's use (total - free: the CUDA context, other processes and
                                     // ours) when that peak was reached
};

/** The statistics of this process (all zero without CUDA). */
DynamicMeshRegistration_EXPORT MemoryStatistics
GetMemoryStatistics();

/** Starts a new peak from what is held now (FEMRegistrationMethod calls it when a GPU run starts; two GPU runs at the
 * same time in one process share the peak). */
DynamicMeshRegistration_EXPORT void
ResetMemoryPeak();
} // namespace cuda
} // namespace dmr
} // namespace itk

#endif
