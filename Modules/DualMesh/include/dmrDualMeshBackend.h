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
#ifndef dmrDualMeshBackend_h
#define dmrDualMeshBackend_h

#include "DynamicMeshRegistrationExport.h"
#include "dmrCudaBackend.h"
#include "dmrLabelSummary.h"
#include <cstddef>
#include <cstdint>

/** Plain C++ launcher API of the dual mesh stage's CUDA back-end (no CUDA or ITK types): see STYLE.md section 4.
 * The GPU registration keeps the CVT labels on the device; the dual mesh (CGAL/TetGen, on the CPU) only needs their
 * LabelSummary, which is computed on the device and downloaded (a few hundred bytes per cell plus the adjacency
 * pairs) instead of the label volume. The summary is identical, field for field, to dmr::SummarizeLabels on the CPU
 * (integer atomics only), so dmr::BuildDualMesh gives the same mesh from either.
 * Kernels in DualMesh/cuda/dmrDualMeshBackend.cu; without CUDA, DualMesh/src/dmrDualMeshCudaStub.cxx returns
 * "built without CUDA". */
namespace itk
{
namespace dmr
{
namespace cuda
{
/** Computes label summaries on the device and keeps its scratch buffers (statistics, adjacency keys, sort storage,
 * pinned staging memory) between calls, since the registration calls it every iteration. Not thread-safe: one
 * summarizer per thread (the registration owns one). Uses the default stream, so labels written by earlier work on
 * the default stream are complete when it reads them. */
class DynamicMeshRegistration_EXPORT LabelSummarizer
{
public:
  LabelSummarizer();
  ~LabelSummarizer();
  LabelSummarizer(const LabelSummarizer &) = delete;
  LabelSummarizer &
  operator=(const LabelSummarizer &) = delete;

  /** Summary of a dimension-D (2 or 3) label image of size[0] x ... x size[D-1] voxels (x fastest) held on the
   * DEVICE at deviceLabels, with labels 0..numberOfCells-1 (a label outside that range gives an error status).
   * The statistics take about 46 x 8 bytes per cell (3D) on the device and the host. */
  Status
  Summarize(unsigned int    dimension,
            const size_t *  size,
            const int32_t * deviceLabels,
            size_t          numberOfCells,
            LabelSummary &  out);

  /** Whether Summarize finds the pairs of adjacent cells (LabelSummary::adjacentPairs; on by default). The 2D dual
   * mesh needs them (its constraints); the 3D dual mesh reads them only for its statistics, so the registration turns
   * them off in 3D: the summary is then the same except that adjacentPairs is empty, and the call does without the
   * neighbour comparisons, the sort and two of its three downloads. */
  void
  SetFindAdjacentPairs(bool find)
  {
    m_FindAdjacentPairs = find;
  }
  bool
  GetFindAdjacentPairs() const
  {
    return m_FindAdjacentPairs;
  }

  /** Test hook: copies host labels into a device buffer owned by this summarizer (kept until the next upload). */
  Status
  UploadLabels(const int32_t * hostLabels, size_t numberOfPixels);
  /** The device copy of the last UploadLabels (nullptr before the first). */
  const int32_t *
  UploadedLabels() const;
  /** Device memory held by the summariser's buffers (bytes; they grow to the largest input and are kept). */
  size_t
  AllocatedBytes() const;

  /** UploadLabels, then Summarize on the uploaded copy. */
  Status
  SummarizeHostLabels(unsigned int    dimension,
                      const size_t *  size,
                      const int32_t * hostLabels,
                      size_t          numberOfCells,
                      LabelSummary &  out);

private:
  struct Impl;
  Impl * m_Impl;
  bool   m_FindAdjacentPairs{ true };
};

/** LabelSummarizer::Summarize through one process-wide summarizer (serialised by a mutex); a caller that summarizes
 * every iteration should own its LabelSummarizer instead. */
DynamicMeshRegistration_EXPORT Status
SummarizeLabels(unsigned int    dimension,
                const size_t *  size,
                const int32_t * deviceLabels,
                size_t          numberOfCells,
                LabelSummary &  out);

/** Convenience/test hook: the summary of HOST labels (uploaded, then summarized on the device). */
DynamicMeshRegistration_EXPORT Status
SummarizeHostLabels(unsigned int    dimension,
                    const size_t *  size,
                    const int32_t * hostLabels,
                    size_t          numberOfCells,
                    LabelSummary &  out);
} // namespace cuda
} // namespace dmr
} // namespace itk

#endif
