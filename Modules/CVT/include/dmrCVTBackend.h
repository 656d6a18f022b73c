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
#ifndef dmrCVTBackend_h
#define dmrCVTBackend_h

#include "dmrCudaBackend.h"
#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

/** Plain C++ launcher API of the CVT swap optimisation on the GPU (STYLE.md section 4): no CUDA or ITK types.
 * Kernels in CVT/cuda/dmrCVTBackend.cu (DMR_USE_CUDA=ON), stub in CVT/src/dmrCVTCudaStub.cxx (every call fails
 * with "built without CUDA"). */
namespace itk
{
namespace dmr
{
namespace cuda
{
/** Statistics of one Optimize call (the fields of dmr::DiscreteCVT<D>::OptimizeResult). */
struct CVTSwapResult
{
  size_t sweeps{ 0 };
  size_t swaps{ 0 };
  size_t rejectedBatches{ 0 };
  double energyBefore{ 0 };
  double energyAfter{ 0 };
  size_t slotOverflows{ 0 }; // GPU only: cells whose entries of a batch outnumbered their slots (SetCellSlots)
};

/** \brief The swap optimisation of dmr::DiscreteCVT<D> (paper Algorithm 1 with the parity-colour two-phase rule)
 * on the GPU, with the labels, masses and centroids kept on the device between calls.
 *
 * The rule and the arithmetic are those of the CPU reference (see the class comment of dmr::DiscreteCVT): the
 * proposals of one colour are made against the frozen labels in double precision without fused multiply-add, in
 * the same candidate order with the same tie rule, rounding guard and local connectivity test; they are committed
 * in pixel order; the per-cell deltas of a batch (mass, first moment about the old centroid, second moment) are
 * summed in proposal order, and the masses and centroids of SetLabels/KeepLabels are summed in pixel order, so the
 * labels equal the CPU's. Only the order in which the per-cell terms of the energy are added differs (the energy
 * agrees to rounding, about 1e-15 relative). A rejected batch is halved on the host (rare).
 *
 * Typical use: SetGrid, SetDensity, SetLabels (e.g. from the CPU contraction), Optimize; for the next registration
 * iteration SetDensity with the new density and KeepLabels (warm start), Optimize. The work runs on the object's own
 * CUDA stream (the sweeps of an Optimize call are one replayed CUDA graph looping on the device, see SetDeviceLoop):
 * device memory passed in must hold its final values when it is passed (the producer's stream synchronised), and every
 * call returns with its work finished, so DeviceLabels() can be read by any stream afterwards. Not thread-safe. */
class DynamicMeshRegistration_EXPORT CVTSwapOptimizer
{
public:
  CVTSwapOptimizer();
  ~CVTSwapOptimizer();
  CVTSwapOptimizer(const CVTSwapOptimizer &) = delete;
  CVTSwapOptimizer &
  operator=(const CVTSwapOptimizer &) = delete;

  /** Grid of dimension 2 or 3 (size and spacing per axis, axis 0 fastest); fewer than 2^31 pixels. Discards the
   * labels and the density. */
  Status
  SetGrid(unsigned int dimension, const size_t * size, const double * spacing);
  /** Density, one positive value per pixel. devicePointer: borrowed device memory of the caller that must stay
   * valid and unchanged while this object uses it; else copied to the device. Cell statistics are recomputed only by
   * SetLabels/KeepLabels. */
  Status
  SetDensity(const float * density, bool devicePointer);
  /** Labels 0..numberOfCells-1 (host or device memory), copied; recomputes masses, centroids and the energy. */
  Status
  SetLabels(const int32_t * labels, size_t numberOfCells, bool devicePointer);
  /** Warm start: keeps the labels already on the device and recomputes the statistics (for a new density). */
  Status
  KeepLabels(size_t numberOfCells);
  /** The data-parallel ends of the contraction (dmr::DiscreteCVT::ContractionInitialize) on the device, around its
   * merges on the host (dmr::DiscreteCVT::ContractBlocks): the masses and centroids (grid frame, D interleaved) of the
   * blockSize^D blocks of the density (axis 0 fastest, the last ones cut at the grid's end), each summed in pixel order
   * as the CPU sums it; then the labels from one label per block, with the statistics as SetLabels. The density and
   * the labels stay on the device. */
  Status
  ContractionBlockSums(unsigned int blockSize, std::vector<double> & masses, std::vector<double> & centroids);
  Status
  SetBlockLabels(unsigned int blockSize, const int32_t * blockLabels, size_t numberOfCells);
  /** Sweeps until a sweep commits nothing or lowers the energy by no more than epsilon x E, or
   * maximumNumberOfSweeps sweeps (dmr::DiscreteCVT<D>::Optimize). */
  Status
  Optimize(double epsilon, size_t maximumNumberOfSweeps, CVTSwapResult & result);
  /** Whether Optimize runs its sweeps as one loop on the device (a CUDA graph with a conditional while node around a
   * sweep and the stopping rule; the host steps in only to halve a rejected batch), where the driver supports
   * conditional nodes; otherwise one graph launch and one host check per sweep. Same results. Default on. */
  void
  SetDeviceLoop(bool enabled);
  /** Whether the sweeps read a 16-bit copy of the labels (kept by the commits; half the memory traffic of the
   * proposals) when every label fits, i.e. with at most 65536 cells; from the next SetLabels or KeepLabels on.
   * Same results. Default on. */
  void
  SetShortLabels(bool enabled);
  /** The entries of a sweep's batch are placed in `capacity` slots per cell as the proposals are made, at most as
   * many in all as a batch can have entries (two per pixel of the largest colour): with the default (the largest
   * unsigned value), that many. The entries beyond a cell's slots go to a list of the batch, which is scanned for the
   * cells that have more (CVTSwapResult::slotOverflows counts those). 0: every batch goes through an allocation pass
   * (two more kernels per colour). From the next SetLabels or KeepLabels on. Same results. */
  void
  SetCellSlots(unsigned int capacity);
  /** Pixels per thread of the proposal kernel: 1 or 2, or 0 (default) for 2 on the colours large enough to give the
   * device two full rounds of blocks that way, 1 on the others. Same results. Throws std::invalid_argument above 2. */
  void
  SetPixelsPerProposalThread(unsigned int pixels);

  /** Copies the labels to host memory (one value per pixel). */
  Status
  DownloadLabels(int32_t * host) const;
  /** The labels on the device (valid until the next SetGrid or destruction); nullptr before SetGrid. */
  const int32_t *
  DeviceLabels() const;
  /** Masses and centroids (grid frame, D interleaved) of the cells. */
  Status
  GetCells(std::vector<double> & masses, std::vector<double> & centroids) const;
  /** Energy (paper Eq. 10) of the current labels, kept up to date by Optimize. */
  double
  Energy() const;
  size_t
  NumberOfCells() const;
  /** Device memory held by the optimiser's buffers (bytes; they grow to the largest input and are kept). */
  size_t
  AllocatedBytes() const;

private:
  struct Impl;
  std::unique_ptr<Impl> m_Impl;
};
} // namespace cuda
} // namespace dmr
} // namespace itk

#endif
