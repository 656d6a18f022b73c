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
#ifndef dmrLabelSummary_h
#define dmrLabelSummary_h

#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace itk
{
namespace dmr
{
/** \brief Everything the dual mesh construction reads from a cell-label image (plain C++, no ITK or CUDA types, so
 * that the CPU path (dmr::SummarizeLabels in dmrDualMeshBuilder.h) and the CUDA launcher (dmrDualMeshBackend.h) fill
 * the same struct). All sums are exact integer sums of voxel indices (not of positions), so the two back-ends agree
 * bit for bit and the result does not depend on how the work is split.
 *
 * Frame: voxel indices i_k in [0, size[k]) relative to the start of the largest possible region; axis k has stride
 * prod_{j<k} size[j] (x fastest). Labels are 0..numberOfCells-1.
 *
 * Border parts of the image box:
 * - face f = 2 k + s (k the normal axis, s = 0 for i_k = 0, s = 1 for i_k = size[k] - 1), in-plane axes
 *   (k + j) mod D for j = 1..D-1. In 2D a face is a whole border line, its two corner pixels included; in 3D it is
 *   the face's inner voxels only (its edge lines and corners excluded: they are the edges and corners below).
 * - 3D edge line e = 4 a + 2 sb + sc runs along axis a, axis b = (a + 1) mod 3 at side sb, axis c = (a + 2) mod 3 at
 *   side sc; its inner voxels only (1 <= i_a <= size[a] - 2).
 * - corner q (0 <= q < 2^D): bit k of q set means i_k = size[k] - 1, else 0.
 * \ingroup DynamicMeshRegistration */
struct LabelSummary
{
  static constexpr unsigned int NumberOfEdges3D = 12;

  unsigned int          dimension{ 0 };
  std::array<size_t, 3> size{ { 0, 0, 0 } }; // unused axes are 1
  size_t                numberOfCells{ 0 };
  /** Per cell c, dimension + 1 values at (D + 1) c: voxel count, then the sum of index k for k = 0..D-1. */
  std::vector<int64_t> cellStats;
  /** Per cell c and face f, D values at D (2 D c + f): voxel count on the face, then the sums of the in-plane
   * indices in the order j = 1..D-1. */
  std::vector<int64_t> faceStats;
  /** 3D only (empty in 2D): per cell c and edge line e, 2 values at 2 (12 c + e): voxel count on the edge line, sum
   * of the index along it. */
  std::vector<int64_t> edgeStats;
  /** Label of the voxel at corner q (the first 2^D entries are used). */
  std::array<int32_t, 8> cornerLabels{ { 0, 0, 0, 0, 0, 0, 0, 0 } };
  /** Every pair of different cells holding two face-sharing voxels, as (lo << 32) | hi with lo < hi, sorted
   * ascending, without duplicates. */
  std::vector<uint64_t> adjacentPairs;

  static unsigned int
  NumberOfFaces(unsigned int dim)
  {
    return 2 * dim;
  }
  /** Sizes the arrays for the given geometry and sets every statistic to zero (adjacentPairs emptied). */
  void
  Reset(unsigned int dim, const size_t * gridSize, size_t cells)
  {
    dimension = dim;
    numberOfCells = cells;
    size = { { 1, 1, 1 } };
    for (unsigned int k = 0; k < dim && k < 3; ++k)
    {
      size[k] = gridSize[k];
    }
    cellStats.assign(cells * (dim + 1), 0);
    faceStats.assign(cells * NumberOfFaces(dim) * dim, 0);
    edgeStats.assign(dim == 3 ? cells * NumberOfEdges3D * 2 : 0, 0);
    cornerLabels.fill(0);
    adjacentPairs.clear();
  }

  int64_t
  CellCount(size_t c) const
  {
    return cellStats[(dimension + 1) * c];
  }
  int64_t
  CellIndexSum(size_t c, unsigned int k) const
  {
    return cellStats[(dimension + 1) * c + 1 + k];
  }
  int64_t
  FaceCount(size_t c, unsigned int f) const
  {
    return faceStats[dimension * (NumberOfFaces(dimension) * c + f)];
  }
  /** Sum of the index along in-plane axis (k + j) mod D, j = 1..D-1, of the cell's voxels on face f = 2 k + s. */
  int64_t
  FaceIndexSum(size_t c, unsigned int f, unsigned int j) const
  {
    return faceStats[dimension * (NumberOfFaces(dimension) * c + f) + j];
  }
  int64_t
  EdgeCount(size_t c, unsigned int e) const
  {
    return edgeStats[2 * (NumberOfEdges3D * c + e)];
  }
  int64_t
  EdgeIndexSum(size_t c, unsigned int e) const
  {
    return edgeStats[2 * (NumberOfEdges3D * c + e) + 1];
  }

  static uint64_t
  PairKey(uint32_t a, uint32_t b)
  {
    return a < b ? (static_cast<uint64_t>(a) << 32) | b : (static_cast<uint64_t>(b) << 32) | a;
  }
  static std::array<int32_t, 2>
  PairOfKey(uint64_t key)
  {
    return { { static_cast<int32_t>(key >> 32), static_cast<int32_t>(key & 0xffffffffu) } };
  }

  bool
  operator==(const LabelSummary & o) const
  {
    return dimension == o.dimension && size == o.size && numberOfCells == o.numberOfCells && cellStats == o.cellStats &&
           faceStats == o.faceStats && edgeStats == o.edgeStats && cornerLabels == o.cornerLabels &&
           adjacentPairs == o.adjacentPairs;
  }
  bool
  operator!=(const LabelSummary & o) const
  {
    return !(*this == o);
  }
};
} // namespace dmr
} // namespace itk

#endif
