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
#ifndef dmrDualMeshBuilder_h
#define dmrDualMeshBuilder_h

#include "dmrLabelSummary.h"
#include "dmrDelaunay2D.h"
#include "dmrDelaunay3D.h"
#include "dmrGrid.h"
#include "dmrSimplexMesh.h"
#include "itkMacro.h"
#include <algorithm>
#include <array>
#include <cstdint>
#include <vector>

namespace itk
{
namespace dmr
{
/** The dual mesh in two steps, so that a caller whose labels live elsewhere (the CUDA back-end keeps them on the
 * device) never needs the label image on the host:
 * 1. SummarizeLabels(): the LabelSummary of a label image (CPU; dmr::cuda::SummarizeLabels computes the same summary
 *    on the device);
 * 2. BuildDualMesh(): the mesh from the grid, the summary and the sites (itk::DualMeshFilter documents the rules). */

/** Summary of a label image with labels 0..numberOfCells-1 (see LabelSummary). Parallel over rows through the
 * threader (nullptr: serial); deterministic (integer sums, sorted pairs) whatever the number of work units. Throws an
 * itk::ExceptionObject for a label outside [0, numberOfCells). */
template <unsigned int D, typename TLabel>
LabelSummary
SummarizeLabels(const Grid<D> & grid, const TLabel * labels, size_t numberOfCells, MultiThreaderBase * threader)
{
  static_assert(D == 2 || D == 3, "the label summary is defined in 2D and 3D");
  if (numberOfCells >= (size_t{ 1 } << 31))
  {
    itkGenericExceptionMacro("SummarizeLabels: " << numberOfCells << " cells do not fit 32-bit labels");
  }
  LabelSummary summary;
  summary.Reset(D, grid.size.data(), numberOfCells);
  if (grid.numberOfPixels == 0)
  {
    return summary;
  }
  const size_t sx = grid.size[0];
  const size_t nRows = grid.numberOfPixels / sx;

  // Bulk pass over rows along axis 0: voxel count and index sums per cell, and the pairs of different cells that
  // share a voxel face (deduplicated on the fly through a small direct-mapped cache, then sorted).
  struct Chunk
  {
    std::vector<int64_t>  stats;
    std::vector<uint64_t> pairs;
    int64_t               badPixel{ -1 };
  };
  const size_t       workUnits = threader ? std::max<size_t>(1, threader->GetNumberOfWorkUnits()) : 1;
  const size_t       nChunks = std::min<size_t>(nRows, workUnits);
  std::vector<Chunk> chunks(nChunks);
  auto               scanRows = [&](size_t chunkId) {
    Chunk & chunk = chunks[chunkId];
    chunk.stats.assign((D + 1) * numberOfCells, 0);
    constexpr unsigned int cacheBits = 14;
    std::vector<uint64_t>  cache(size_t{ 1 } << cacheBits, ~uint64_t{ 0 });
    auto                   addPair = [&](uint64_t key) {
      uint64_t & slot = cache[(key * 0x9e3779b97f4a7c15ULL) >> (64 - cacheBits)];
      if (slot != key)
      {
        slot = key;
        chunk.pairs.push_back(key);
      }
    };
    const size_t r0 = nRows * chunkId / nChunks, r1 = nRows * (chunkId + 1) / nChunks;
    for (size_t r = r0; r < r1; ++r)
    {
      int64_t idx[D];
      bool    hasNext[D];
      size_t  rem = r;
      for (unsigned int k = 1; k < D; ++k)
      {
        idx[k] = static_cast<int64_t>(rem % grid.size[k]);
        rem /= grid.size[k];
        hasNext[k] = static_cast<size_t>(idx[k]) + 1 < grid.size[k];
      }
      const TLabel * row = labels + r * sx;
      for (size_t x = 0; x < sx; ++x)
      {
        const auto c = static_cast<int64_t>(row[x]);
        if (c < 0 || static_cast<uint64_t>(c) >= numberOfCells)
        {
          if (chunk.badPixel < 0)
          {
            chunk.badPixel = static_cast<int64_t>(r * sx + x);
          }
          continue;
        }
        int64_t * st = &chunk.stats[(D + 1) * static_cast<size_t>(c)];
        st[0] += 1;
        st[1] += static_cast<int64_t>(x);
        for (unsigned int k = 1; k < D; ++k)
        {
          st[1 + k] += idx[k];
        }
        if (x + 1 < sx && row[x + 1] != row[x])
        {
          addPair(LabelSummary::PairKey(static_cast<uint32_t>(c), static_cast<uint32_t>(row[x + 1])));
        }
        for (unsigned int k = 1; k < D; ++k)
        {
          if (hasNext[k] && row[x + grid.stride[k]] != row[x])
          {
            addPair(LabelSummary::PairKey(static_cast<uint32_t>(c), static_cast<uint32_t>(row[x + grid.stride[k]])));
          }
        }
      }
    }
  };
  ParallelForChunkIds(threader, nChunks, scanRows);
  for (const auto & chunk : chunks)
  {
    if (chunk.badPixel >= 0)
    {
      itkGenericExceptionMacro("SummarizeLabels: label " << static_cast<int64_t>(labels[chunk.badPixel]) << " at pixel "
                                                         << chunk.badPixel << " is outside [0, " << numberOfCells
                                                         << ")");
    }
  }
  for (const auto & chunk : chunks)
  {
    for (size_t i = 0; i < chunk.stats.size(); ++i)
    {
      summary.cellStats[i] += chunk.stats[i];
    }
    summary.adjacentPairs.insert(summary.adjacentPairs.end(), chunk.pairs.begin(), chunk.pairs.end());
  }
  chunks.clear();
  std::sort(summary.adjacentPairs.begin(), summary.adjacentPairs.end());
  summary.adjacentPairs.erase(std::unique(summary.adjacentPairs.begin(), summary.adjacentPairs.end()),
                              summary.adjacentPairs.end());

  // Border parts (few pixels, serial): faces (2D: whole border lines; 3D: inner face voxels), 3D edge lines, corners.
  const size_t faceLo = D == 2 ? 0 : 1;
  for (unsigned int f = 0; f < 2 * D; ++f)
  {
    const unsigned int k = f / 2, a = (k + 1) % D, b = (k + 2) % D;
    const size_t       base = (f % 2 ? grid.size[k] - 1 : 0) * grid.stride[k];
    const size_t       bLo = D == 2 ? 0 : 1, bHi = D == 2 ? 1 : grid.size[b] - 1; // 2D: one line, no axis b
    const size_t       aHi = D == 2 ? grid.size[a] : grid.size[a] - 1;
    for (size_t ib = bLo; ib < bHi; ++ib)
    {
      for (size_t ia = faceLo; ia < aHi; ++ia)
      {
        const size_t p = base + ia * grid.stride[a] + (D == 2 ? 0 : ib * grid.stride[b]);
        int64_t *    st = &summary.faceStats[D * (2 * D * static_cast<size_t>(labels[p]) + f)];
        st[0] += 1;
        st[1] += static_cast<int64_t>(ia);
        if constexpr (D == 3)
        {
          st[2] += static_cast<int64_t>(ib);
        }
      }
    }
  }
  if constexpr (D == 3)
  {
    for (unsigned int e = 0; e < LabelSummary::NumberOfEdges3D; ++e)
    {
      const unsigned int a = e / 4, b = (a + 1) % 3, c3 = (a + 2) % 3;
      const size_t       base =
        ((e >> 1) & 1u ? grid.size[b] - 1 : 0) * grid.stride[b] + (e & 1u ? grid.size[c3] - 1 : 0) * grid.stride[c3];
      for (size_t ia = 1; ia + 1 < grid.size[a]; ++ia)
      {
        int64_t * st =
          &summary
             .edgeStats[2 *
                        (LabelSummary::NumberOfEdges3D * static_cast<size_t>(labels[base + ia * grid.stride[a]]) + e)];
        st[0] += 1;
        st[1] += static_cast<int64_t>(ia);
      }
    }
  }
  for (unsigned int q = 0; q < (1u << D); ++q)
  {
    size_t p = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      p += ((q >> k) & 1u ? grid.size[k] - 1 : 0) * grid.stride[k];
    }
    summary.cornerLabels[q] = static_cast<int32_t>(labels[p]);
  }
  return summary;
}

/** The 2^D image corners (grid frame) in the order of LabelSummary::cornerLabels: first(cell, x) for the first corner
 * a cell holds (the cell's node goes there), extra(x) for each further corner of a cell that already has one (an
 * extra node). */
template <unsigned int D, typename TFirst, typename TExtra>
void
ForEachImageCorner(const Grid<D> & grid, const LabelSummary & summary, TFirst && first, TExtra && extra)
{
  std::vector<bool> cornerTaken(summary.numberOfCells, false);
  for (unsigned int corner = 0; corner < (1u << D); ++corner)
  {
    double x[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t i = (corner >> k) & 1u ? grid.size[k] - 1 : 0;
      x[k] = static_cast<double>(i) * grid.spacing[k];
    }
    const auto c = static_cast<size_t>(summary.cornerLabels[corner]);
    if (!cornerTaken[c])
    {
      cornerTaken[c] = true;
      first(c, x);
    }
    else
    {
      extra(x);
    }
  }
}

/** Number of node pairs (a, b) that are not an edge of any element. Linear time: the elements around every node (an
 * incidence list), and for the pairs of one node (the summary's pairs come grouped by their smaller node) its mesh
 * neighbours are stamped once. */
template <size_t VVertices>
size_t
CountEdgesNotInMesh(const std::vector<std::array<int32_t, 2>> &         pairs,
                    const std::vector<std::array<int32_t, VVertices>> & elements)
{
  int32_t nNodes = 0;
  for (const auto & e : elements)
  {
    for (const int32_t v : e)
    {
      nNodes = std::max(nNodes, v + 1);
    }
  }
  std::vector<int32_t> start, incident;
  ElementsAroundNodes(elements, static_cast<size_t>(nNodes), start, incident);
  std::vector<int32_t> stamp(static_cast<size_t>(nNodes), -1);
  int32_t              stamped = -1;
  size_t               missing = 0;
  for (const auto & p : pairs)
  {
    const int32_t a = std::min(p[0], p[1]), b = std::max(p[0], p[1]);
    if (a == b || a < 0 || b >= nNodes)
    {
      ++missing;
      continue;
    }
    if (a != stamped)
    {
      stamped = a;
      for (int32_t k = start[a]; k < start[a + 1]; ++k)
      {
        for (const int32_t v : elements[incident[k]])
        {
          stamp[v] = a;
        }
      }
    }
    missing += stamp[b] == a ? 0 : 1;
  }
  return missing;
}

/** What BuildDualMesh reports besides the mesh (itk::DualMeshFilter's getters of the same names). */
struct DualMeshStatistics
{
  size_t numberOfSkippedConstraints{ 0 };
  size_t numberOfBoundaryNodes{ 0 };
  size_t numberOfInnerAdjacencyEdges{ 0 };
  size_t numberOfMissingAdjacencyEdges{ 0 };
  size_t numberOfPerturbedNodes{ 0 };
  bool   repairedFromWarmStart{ false }; // 3D: the tetrahedralization came from the warm start (RepairDelaunay3D)
};

/** Compacts the used nodes, orients the elements, marks the border nodes and checks that the elements tile the
 * box. */
template <unsigned int D>
SimplexMesh<D>
CompactDualMesh(const Grid<D> &                                 grid,
                const std::vector<double> &                     nodes,
                const std::vector<std::array<int32_t, D + 1>> & elements)
{
  const size_t         nNodes = nodes.size() / D;
  std::vector<int32_t> newIndex(nNodes, -1);
  SimplexMesh<D>       mesh;
  mesh.elements.reserve(elements.size());
  for (const auto & t : elements)
  {
    std::array<int32_t, D + 1> e;
    for (unsigned int v = 0; v <= D; ++v)
    {
      if (newIndex[t[v]] < 0)
      {
        newIndex[t[v]] = static_cast<int32_t>(mesh.nodes.size() / D);
        mesh.nodes.insert(mesh.nodes.end(), &nodes[t[v] * D], &nodes[t[v] * D] + D);
      }
      e[v] = newIndex[t[v]];
    }
    mesh.elements.push_back(e);
  }
  mesh.OrientPositively();
  mesh.MarkBorderNodes(grid);

  double total = 0.0, box = 1.0;
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    total += mesh.SignedMeasure(e);
  }
  for (unsigned int k = 0; k < D; ++k)
  {
    box *= static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
  }
  if (std::abs(total - box) > 1e-6 * box)
  {
    itkGenericExceptionMacro("the dual mesh does not cover the image box: element measures sum to "
                             << total << ", box is " << box);
  }
  return mesh;
}

/** Whether the 3D dual mesh snaps boundary nodes to the box edges unless told otherwise (DualMeshFilter's default,
 * and the registration's). */
constexpr bool DefaultSnapToBoxEdges = true;

/** The dual mesh (grid frame) of a label image given by its summary; itk::DualMeshFilter documents the node rules.
 * sitesGridFrame: D coordinates per cell (the site of cell c at D c, grid frame), used for the inner cells; nullptr
 * uses the cells' unweighted centroids. snapToBoxEdges: 3D edge snapping (DualMeshFilter::SetSnapToBoxEdges).
 * threader: the work units of the 3D Delaunay tetrahedralization (Delaunay3D; nullptr: serial); the mesh does not
 * depend on it. warmStart (3D, optional, in and out): the tetrahedra (node = cell indices, before compaction) and
 * node positions of an earlier call, e.g. the last iteration's; when the nodes moved little, RepairDelaunay3D turns
 * them into this call's tetrahedralization instead of a new one, with the same result. Replaced by this call's.
 * Throws an itk::ExceptionObject for a cell without voxels, a summary of another grid, a 3D grid thinner than 2
 * voxels, or a mesh that does not tile the box. */
template <unsigned int D>
SimplexMesh<D>
BuildDualMesh(const Grid<D> &      grid,
              const LabelSummary & summary,
              const double *       sitesGridFrame,
              bool                 snapToBoxEdges = DefaultSnapToBoxEdges,
              DualMeshStatistics * statistics = nullptr,
              MultiThreaderBase *  threader = nullptr,
              DelaunayWarmStart *  warmStart = nullptr)
{
  static_assert(D == 2 || D == 3, "the dual mesh is defined in 2D (triangles) and 3D (tetrahedra)");
  if (summary.dimension != D)
  {
    itkGenericExceptionMacro("BuildDualMesh: a " << summary.dimension << "D label summary for a " << D << "D grid");
  }
  for (unsigned int k = 0; k < D; ++k)
  {
    if (summary.size[k] != grid.size[k])
    {
      itkGenericExceptionMacro("BuildDualMesh: the label summary has " << summary.size[k] << " pixels along axis " << k
                                                                       << ", the grid " << grid.size[k]);
    }
    if (D == 3 && grid.size[k] < 2)
    {
      itkGenericExceptionMacro("the 3D dual mesh needs at least 2 voxels along every axis; axis " << k << " has "
                                                                                                  << grid.size[k]);
    }
  }
  const size_t nCells = summary.numberOfCells;
  if (nCells == 0)
  {
    itkGenericExceptionMacro("BuildDualMesh: no cell");
  }
  for (size_t c = 0; c < nCells; ++c)
  {
    if (summary.CellCount(c) == 0)
    {
      itkGenericExceptionMacro("cell " << c << " has no pixel: labels must be 0..N-1 without gaps");
    }
  }
  DualMeshStatistics stats;
  double             hi[D];
  for (unsigned int k = 0; k < D; ++k)
  {
    hi[k] = static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
  }
  auto innerNode = [&](size_t c, double * x) {
    for (unsigned int k = 0; k < D; ++k)
    {
      x[k] = sitesGridFrame ? sitesGridFrame[c * D + k]
                            : static_cast<double>(summary.CellIndexSum(c, k)) /
                                static_cast<double>(summary.CellCount(c)) * grid.spacing[k];
    }
  };
  std::vector<double>                     nodes(nCells * D);
  std::vector<std::array<int32_t, 2>>     innerPairs;
  std::vector<std::array<int32_t, D + 1>> elements;

  if constexpr (D == 2)
  {
    // A boundary cell's node is the centre of its border pixels on the side where it has most of them, exactly on
    // that side (the mean of equal coordinates can round off the border line, which would make CGAL see border nodes
    // as not collinear and create sliver triangles along the border); a corner cell's node is its corner.
    constexpr unsigned int nSides = 2 * D;
    std::vector<int>       kind(nCells, 0); // 0 inner, 1 boundary, 2 corner
    for (size_t c = 0; c < nCells; ++c)
    {
      unsigned int bestSide = nSides;
      int64_t      bestCount = 0;
      for (unsigned int s = 0; s < nSides; ++s)
      {
        if (summary.FaceCount(c, s) > bestCount)
        {
          bestCount = summary.FaceCount(c, s);
          bestSide = s;
        }
      }
      double * x = &nodes[c * D];
      if (bestSide < nSides)
      {
        kind[c] = 1;
        const unsigned int axis = bestSide / 2, along = (axis + 1) % D;
        x[along] = static_cast<double>(summary.FaceIndexSum(c, bestSide, 1)) / static_cast<double>(bestCount) *
                   grid.spacing[along];
        x[axis] = bestSide % 2 == 0 ? 0.0 : hi[axis];
      }
      else
      {
        innerNode(c, x);
      }
    }
    ForEachImageCorner<D>(
      grid,
      summary,
      [&](size_t c, const double * x) {
        kind[c] = 2;
        std::copy(x, x + D, &nodes[c * D]);
      },
      [&](const double * x) { nodes.insert(nodes.end(), x, x + D); });
    // constraints: edges between adjacent inner cells (paper 4.6)
    for (const uint64_t key : summary.adjacentPairs)
    {
      const auto pair = LabelSummary::PairOfKey(key);
      if (kind[pair[0]] == 0 && kind[pair[1]] == 0)
      {
        innerPairs.push_back(pair);
      }
    }
    stats.numberOfSkippedConstraints = ConstrainedDelaunay2D(nodes, innerPairs, elements);
  }
  else
  {
    // A cell's node goes onto the lowest-dimensional part of the box border it touches: a corner cell at its corner,
    // otherwise a cell with voxels on a box edge line at the centre of its voxels on the edge line where it has most,
    // otherwise a cell with voxels on a face at the centre of its voxels on the face where it has most, otherwise
    // (inner cell) at its site. Snapped coordinates are set exactly (not averaged), so nodes on one face are exactly
    // coplanar and nodes on one edge exactly collinear: TetGen then never puts a flat tetrahedron on the border.
    std::vector<uint8_t> freeAxes(nCells, 7u); // the axes along which a node may be nudged off a flat tetrahedron
    std::vector<uint8_t> inner(nCells, 0);
    for (size_t c = 0; c < nCells; ++c)
    {
      unsigned int bestEdge = 12, bestFace = 6;
      for (unsigned int e = 0; e < 12; ++e)
      {
        if (summary.EdgeCount(c, e) > (bestEdge < 12 ? summary.EdgeCount(c, bestEdge) : 0))
        {
          bestEdge = e;
        }
      }
      for (unsigned int f = 0; f < 6; ++f)
      {
        if (summary.FaceCount(c, f) > (bestFace < 6 ? summary.FaceCount(c, bestFace) : 0))
        {
          bestFace = f;
        }
      }
      double * x = &nodes[c * D];
      // with edge snapping off, a cell on an edge line still goes there when it has no face voxel to average
      if (bestEdge < 12 && (snapToBoxEdges || bestFace == 6))
      {
        const unsigned int a = bestEdge / 4, b = (a + 1) % 3, c3 = (a + 2) % 3;
        x[a] = static_cast<double>(summary.EdgeIndexSum(c, bestEdge)) /
               static_cast<double>(summary.EdgeCount(c, bestEdge)) * grid.spacing[a];
        x[b] = (bestEdge >> 1) & 1u ? hi[b] : 0.0;
        x[c3] = bestEdge & 1u ? hi[c3] : 0.0;
        freeAxes[c] = static_cast<uint8_t>(1u << a);
      }
      else if (bestFace < 6)
      {
        const unsigned int k = bestFace / 2, a = (k + 1) % 3, b = (k + 2) % 3;
        const double       count = static_cast<double>(summary.FaceCount(c, bestFace));
        x[a] = static_cast<double>(summary.FaceIndexSum(c, bestFace, 1)) / count * grid.spacing[a];
        x[b] = static_cast<double>(summary.FaceIndexSum(c, bestFace, 2)) / count * grid.spacing[b];
        x[k] = bestFace % 2 ? hi[k] : 0.0;
        freeAxes[c] = static_cast<uint8_t>(7u & ~(1u << k));
      }
      else
      {
        inner[c] = 1;
        innerNode(c, x);
      }
    }
    ForEachImageCorner<D>(
      grid,
      summary,
      [&](size_t c, const double * x) {
        std::copy(x, x + D, &nodes[c * D]);
        freeAxes[c] = 0;
      },
      [&](const double * x) {
        nodes.insert(nodes.end(), x, x + D);
        freeAxes.push_back(0);
      });

    // Delaunay tetrahedralization of all nodes (no constraints: see dmrDelaunay3D.h). The corners are nodes, so the
    // convex hull is the box. Near-flat tetrahedra are removed by nudging their nodes, never more than a quarter
    // voxel (inner, face and edge nodes are at least one voxel away from any face, edge or corner they are not on).
    double minimumSpacing = grid.spacing[0];
    for (unsigned int k = 1; k < D; ++k)
    {
      minimumSpacing = std::min(minimumSpacing, grid.spacing[k]);
    }
    const bool                          warm = warmStart && !warmStart->empty();
    std::vector<std::array<int32_t, 4>> neighbours;
    stats.numberOfPerturbedNodes = NonDegenerateDelaunay3D(nodes,
                                                           freeAxes,
                                                           0.25 * minimumSpacing,
                                                           elements,
                                                           DefaultMinimumTetrahedronShape,
                                                           12,
                                                           threader,
                                                           warm ? warmStart : nullptr,
                                                           &stats.repairedFromWarmStart,
                                                           warmStart ? &neighbours : nullptr);
    if (warmStart)
    {
      warmStart->tetrahedra = elements;
      warmStart->neighbours = std::move(neighbours);
      warmStart->nodes = nodes; // where NonDegenerateDelaunay3D left them
    }
    // how much of the CVT adjacency between inner cells the tetrahedralization holds (when asked for)
    for (size_t k = 0; statistics && k < summary.adjacentPairs.size(); ++k)
    {
      const auto pair = LabelSummary::PairOfKey(summary.adjacentPairs[k]);
      if (inner[pair[0]] && inner[pair[1]])
      {
        innerPairs.push_back(pair);
      }
    }
  }
  stats.numberOfInnerAdjacencyEdges = innerPairs.size();
  stats.numberOfMissingAdjacencyEdges = statistics ? CountEdgesNotInMesh(innerPairs, elements) : 0;
  SimplexMesh<D> mesh = CompactDualMesh<D>(grid, nodes, elements);
  stats.numberOfBoundaryNodes =
    static_cast<size_t>(std::count(mesh.fixed.begin(), mesh.fixed.end(), static_cast<uint8_t>(1)));
  if (statistics)
  {
    *statistics = stats;
  }
  return mesh;
}
} // namespace dmr
} // namespace itk

#endif
