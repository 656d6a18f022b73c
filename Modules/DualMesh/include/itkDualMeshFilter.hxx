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
#ifndef itkDualMeshFilter_hxx
#define itkDualMeshFilter_hxx

#include "itkDualMeshFilter.h"
#include "dmrDelaunay2D.h"
#include "dmrDelaunay3D.h"
#include <map>

namespace itk
{
namespace dmr
{
/** The 2^D image corners (grid frame): first(cell, x) for the first corner a cell holds (the cell's node goes
 * there), extra(x) for each further corner of a cell that already has one (an extra node). */
template <unsigned int D, typename TLabel, typename TFirst, typename TExtra>
void
ForEachImageCorner(const Grid<D> & grid, const TLabel * L, size_t nCells, TFirst && first, TExtra && extra)
{
  std::vector<bool> cornerTaken(nCells, false);
  for (unsigned int corner = 0; corner < (1u << D); ++corner)
  {
    size_t p = 0;
    double x[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t i = (corner >> k) & 1u ? grid.size[k] - 1 : 0;
      p += i * grid.stride[k];
      x[k] = static_cast<double>(i) * grid.spacing[k];
    }
    const auto c = static_cast<size_t>(L[p]);
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

/** Number of node pairs (a, b) that are not an edge of any element. */
template <size_t VVertices>
size_t
CountEdgesNotInMesh(const std::vector<std::array<int32_t, 2>> &         pairs,
                    const std::vector<std::array<int32_t, VVertices>> & elements)
{
  std::vector<uint64_t> edges;
  edges.reserve(elements.size() * VVertices * (VVertices - 1) / 2);
  for (const auto & e : elements)
  {
    for (size_t a = 0; a < VVertices; ++a)
    {
      for (size_t b = a + 1; b < VVertices; ++b)
      {
        const auto lo = static_cast<uint32_t>(std::min(e[a], e[b])), hi = static_cast<uint32_t>(std::max(e[a], e[b]));
        edges.push_back((static_cast<uint64_t>(lo) << 32) | hi);
      }
    }
  }
  std::sort(edges.begin(), edges.end());
  edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
  size_t missing = 0;
  for (const auto & p : pairs)
  {
    const auto lo = static_cast<uint32_t>(std::min(p[0], p[1])), hi = static_cast<uint32_t>(std::max(p[0], p[1]));
    missing += std::binary_search(edges.begin(), edges.end(), (static_cast<uint64_t>(lo) << 32) | hi) ? 0 : 1;
  }
  return missing;
}
} // namespace dmr

template <typename TLabelImage, typename TOutputMesh>
DualMeshFilter<TLabelImage, TOutputMesh>::DualMeshFilter()
{
  this->SetPrimaryInputName("LabelImage");
  this->AddOptionalInputName("Sites");
}

template <typename TLabelImage, typename TOutputMesh>
void
DualMeshFilter<TLabelImage, TOutputMesh>::GenerateInputRequestedRegion()
{
  auto * labels = const_cast<LabelImageType *>(this->GetInput());
  if (labels)
  {
    labels->SetRequestedRegionToLargestPossibleRegion();
  }
}

template <typename TLabelImage, typename TOutputMesh>
void
DualMeshFilter<TLabelImage, TOutputMesh>::GenerateData()
{
  constexpr unsigned int D = ImageDimension;
  const LabelImageType * labels = this->GetInput();
  if (labels == nullptr)
  {
    itkExceptionMacro("no label image");
  }
  if (D != 2 && D != 3)
  {
    itkExceptionMacro("the dual mesh is defined in 2D (triangles) and 3D (tetrahedra), not in " << D << "D");
  }
  const auto   grid = dmr::Grid<D>::FromImage(labels);
  const auto * L = labels->GetBufferPointer();
  int64_t      maxLabel = -1;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    if (L[p] < 0)
    {
      itkExceptionMacro("negative label " << L[p] << " at pixel " << p);
    }
    maxLabel = std::max<int64_t>(maxLabel, static_cast<int64_t>(L[p]));
  }
  const size_t nCells = static_cast<size_t>(maxLabel + 1);
  m_NumberOfSkippedConstraints = 0;
  m_NumberOfPerturbedNodes = 0;
  if constexpr (D == 2)
  {
    this->GenerateData2D(grid, nCells);
  }
  else if constexpr (D == 3)
  {
    this->GenerateData3D(grid, nCells);
  }
}

template <typename TLabelImage, typename TOutputMesh>
void
DualMeshFilter<TLabelImage, TOutputMesh>::GenerateData2D(const dmr::Grid<ImageDimension> & grid, size_t nCells)
{
  constexpr unsigned int D = ImageDimension;
  const LabelImageType * labels = this->GetInput();
  const auto *           L = labels->GetBufferPointer();
  constexpr unsigned int nSides = 2 * D;
  // per-cell pixel counts and sums (unweighted centroid), border pixels per side
  std::vector<double> count(nCells, 0.0), sum(nCells * D, 0.0);
  std::vector<double> sideCount(nCells * nSides, 0.0), sideSum(nCells * nSides * D, 0.0);
  std::vector<std::pair<int64_t, int64_t>> adjacency;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto    idx = grid.Index(p);
    const int64_t c = L[p];
    count[c] += 1.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double x = static_cast<double>(idx[k]) * grid.spacing[k];
      sum[c * D + k] += x;
      for (unsigned int s = 0; s < 2; ++s)
      {
        const bool onSide = s == 0 ? idx[k] == 0 : idx[k] == static_cast<int64_t>(grid.size[k]) - 1;
        if (onSide)
        {
          const size_t side = 2 * k + s;
          sideCount[c * nSides + side] += 1.0;
          for (unsigned int j = 0; j < D; ++j)
          {
            sideSum[(c * nSides + side) * D + j] += static_cast<double>(idx[j]) * grid.spacing[j];
          }
        }
      }
      if (idx[k] + 1 < static_cast<int64_t>(grid.size[k]))
      {
        const int64_t o = L[p + grid.stride[k]];
        if (o != c)
        {
          adjacency.emplace_back(std::min(c, o), std::max(c, o));
        }
      }
    }
  }
  std::sort(adjacency.begin(), adjacency.end());
  adjacency.erase(std::unique(adjacency.begin(), adjacency.end()), adjacency.end());
  for (size_t c = 0; c < nCells; ++c)
  {
    if (count[c] == 0)
    {
      itkExceptionMacro("cell " << c << " has no pixel: labels must be 0..N-1 without gaps");
    }
  }

  // node of every cell (grid frame)
  std::vector<double> nodes(nCells * D);
  std::vector<int>    kind(nCells, 0); // 0 inner, 1 boundary, 2 corner
  const SitesType *   sites = this->GetSites();
  const auto          start = labels->GetLargestPossibleRegion().GetIndex();
  for (size_t c = 0; c < nCells; ++c)
  {
    size_t bestSide = nSides;
    double bestCount = 0.0;
    for (unsigned int s = 0; s < nSides; ++s)
    {
      if (sideCount[c * nSides + s] > bestCount)
      {
        bestCount = sideCount[c * nSides + s];
        bestSide = s;
      }
    }
    if (bestSide < nSides)
    {
      kind[c] = 1;
      for (unsigned int k = 0; k < D; ++k)
      {
        nodes[c * D + k] = sideSum[(c * nSides + bestSide) * D + k] / bestCount;
      }
      // exactly on the side (the mean of equal coordinates can round off the border line, which would make CGAL
      // see border nodes as not collinear and create sliver triangles along the border)
      const unsigned int axis = bestSide / 2;
      nodes[c * D + axis] =
        bestSide % 2 == 0 ? 0.0 : static_cast<double>(grid.size[axis] - 1) * grid.spacing[axis];
    }
    else if (sites && sites->GetNumberOfPoints() == nCells)
    {
      const auto ci = labels->template TransformPhysicalPointToContinuousIndex<double, double>(sites->GetPoint(c));
      for (unsigned int k = 0; k < D; ++k)
      {
        nodes[c * D + k] = (ci[k] - static_cast<double>(start[k])) * grid.spacing[k];
      }
    }
    else
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        nodes[c * D + k] = sum[c * D + k] / count[c];
      }
    }
  }
  dmr::ForEachImageCorner<D>(
    grid,
    L,
    nCells,
    [&](size_t c, const double * x) {
      kind[c] = 2;
      std::copy(x, x + D, &nodes[c * D]);
    },
    [&](const double * x) { nodes.insert(nodes.end(), x, x + D); });
  // constraints: edges between adjacent inner cells (paper 4.6)
  std::vector<std::array<int32_t, 2>> constraints;
  for (const auto & a : adjacency)
  {
    if (kind[a.first] == 0 && kind[a.second] == 0)
    {
      constraints.push_back({ static_cast<int32_t>(a.first), static_cast<int32_t>(a.second) });
    }
  }
  std::vector<std::array<int32_t, 3>> triangles;
  m_NumberOfSkippedConstraints = dmr::ConstrainedDelaunay2D(nodes, constraints, triangles);

  m_NumberOfInnerAdjacencyEdges = static_cast<SizeValueType>(constraints.size());
  m_NumberOfMissingAdjacencyEdges = static_cast<SizeValueType>(dmr::CountEdgesNotInMesh(constraints, triangles));
  this->BuildOutputMesh(grid, nodes, triangles);
}

template <typename TLabelImage, typename TOutputMesh>
void
DualMeshFilter<TLabelImage, TOutputMesh>::GenerateData3D(const dmr::Grid<ImageDimension> & grid, size_t nCells)
{
  constexpr unsigned int D = ImageDimension;
  const LabelImageType * labels = this->GetInput();
  const auto *           L = labels->GetBufferPointer();
  for (unsigned int k = 0; k < D; ++k)
  {
    if (grid.size[k] < 2)
    {
      itkExceptionMacro("the 3D dual mesh needs at least 2 voxels along every axis; axis " << k << " has "
                                                                                           << grid.size[k]);
    }
  }
  const size_t sx = grid.size[0], sy = grid.size[1], sz = grid.size[2], sxy = sx * sy;

  // One flat pass over all voxels: voxel count and index sums per cell (integers, so the result does not depend on
  // how the slabs are split into work units) and the pairs of different cells that share a voxel face (the CVT
  // adjacency, deduplicated on the fly through a small direct-mapped cache, then sorted).
  struct Chunk
  {
    std::vector<int64_t>  stats; // count, sum x, sum y, sum z per cell
    std::vector<uint64_t> pairs;
  };
  const size_t       nChunks = std::min<size_t>(sz, std::max<size_t>(1, this->GetNumberOfWorkUnits()));
  std::vector<Chunk> chunks(nChunks);
  auto               scanSlabs = [&](size_t chunkId)
  {
    Chunk & chunk = chunks[chunkId];
    chunk.stats.assign(4 * nCells, 0);
    constexpr unsigned int cacheBits = 14;
    std::vector<uint64_t>  cache(size_t{ 1 } << cacheBits, ~uint64_t{ 0 });
    auto                   addPair = [&](int64_t a, int64_t b)
    {
      const uint64_t key = (static_cast<uint64_t>(std::min(a, b)) << 32) | static_cast<uint64_t>(std::max(a, b));
      uint64_t &     slot = cache[(key * 0x9e3779b97f4a7c15ULL) >> (64 - cacheBits)];
      if (slot != key)
      {
        slot = key;
        chunk.pairs.push_back(key);
      }
    };
    const size_t z0 = sz * chunkId / nChunks, z1 = sz * (chunkId + 1) / nChunks;
    for (size_t z = z0; z < z1; ++z)
    {
      for (size_t y = 0; y < sy; ++y)
      {
        const auto *  row = L + z * sxy + y * sx;
        const bool    hasY = y + 1 < sy, hasZ = z + 1 < sz;
        const int64_t yz[2] = { static_cast<int64_t>(y), static_cast<int64_t>(z) };
        for (size_t x = 0; x < sx; ++x)
        {
          const int64_t c = row[x];
          int64_t *     st = &chunk.stats[4 * c];
          st[0] += 1;
          st[1] += static_cast<int64_t>(x);
          st[2] += yz[0];
          st[3] += yz[1];
          if (x + 1 < sx && row[x + 1] != row[x])
          {
            addPair(c, row[x + 1]);
          }
          if (hasY && row[x + sx] != row[x])
          {
            addPair(c, row[x + sx]);
          }
          if (hasZ && row[x + sxy] != row[x])
          {
            addPair(c, row[x + sxy]);
          }
        }
      }
    }
  };
  dmr::ParallelForChunkIds(this->GetMultiThreader(), nChunks, scanSlabs);
  std::vector<int64_t>  stats(4 * nCells, 0);
  std::vector<uint64_t> pairs;
  for (const auto & chunk : chunks)
  {
    for (size_t i = 0; i < stats.size(); ++i)
    {
      stats[i] += chunk.stats[i];
    }
    pairs.insert(pairs.end(), chunk.pairs.begin(), chunk.pairs.end());
  }
  chunks.clear();
  std::sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  for (size_t c = 0; c < nCells; ++c)
  {
    if (stats[4 * c] == 0)
    {
      itkExceptionMacro("cell " << c << " has no voxel: labels must be 0..N-1 without gaps");
    }
  }

  // The box border's voxels split into 8 corner voxels, the inner voxels of the 12 edge lines and the inner voxels
  // of the 6 faces. Face f = 2 k + side (normal axis k, side 0 at index 0, 1 at size - 1), in-plane axes k + 1, k + 2
  // (mod 3); edge e = 4 a + 2 sb + sc runs along axis a, with axis a + 1 at side sb and axis a + 2 at side sc.
  std::vector<int64_t> faceCount(6 * nCells, 0), faceSum(12 * nCells, 0);
  std::vector<int64_t> edgeCount(12 * nCells, 0), edgeSum(12 * nCells, 0);
  for (unsigned int f = 0; f < 6; ++f)
  {
    const unsigned int k = f / 2, a = (k + 1) % 3, b = (k + 2) % 3;
    const size_t       base = (f % 2 ? grid.size[k] - 1 : 0) * grid.stride[k];
    for (size_t ib = 1; ib + 1 < grid.size[b]; ++ib)
    {
      for (size_t ia = 1; ia + 1 < grid.size[a]; ++ia)
      {
        const size_t c = static_cast<size_t>(L[base + ia * grid.stride[a] + ib * grid.stride[b]]);
        faceCount[6 * c + f] += 1;
        faceSum[2 * (6 * c + f)] += static_cast<int64_t>(ia);
        faceSum[2 * (6 * c + f) + 1] += static_cast<int64_t>(ib);
      }
    }
  }
  for (unsigned int e = 0; e < 12; ++e)
  {
    const unsigned int a = e / 4, b = (a + 1) % 3, c3 = (a + 2) % 3;
    const size_t       base =
      ((e >> 1) & 1u ? grid.size[b] - 1 : 0) * grid.stride[b] + (e & 1u ? grid.size[c3] - 1 : 0) * grid.stride[c3];
    for (size_t ia = 1; ia + 1 < grid.size[a]; ++ia)
    {
      const size_t c = static_cast<size_t>(L[base + ia * grid.stride[a]]);
      edgeCount[12 * c + e] += 1;
      edgeSum[12 * c + e] += static_cast<int64_t>(ia);
    }
  }

  // Node of every cell (grid frame, paper 4.6 generalised to 3D). A cell's node goes onto the lowest-dimensional
  // part of the box border it touches, as the 2D corner rule does: a corner cell at its corner, otherwise a cell
  // with voxels on a box edge line at the centre of its voxels on the edge line where it has most, otherwise a cell
  // with voxels on a face at the centre of its voxels on the face where it has most, otherwise (inner cell) at its
  // site. Snapped coordinates are set exactly (not averaged), so nodes on one face are exactly coplanar and nodes on
  // one edge exactly collinear: TetGen then never puts a flat tetrahedron on the border.
  double hi[D];
  for (unsigned int k = 0; k < D; ++k)
  {
    hi[k] = static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
  }
  std::vector<double>  nodes(nCells * D);
  std::vector<uint8_t> freeAxes(nCells, 7u); // the axes along which a node may be nudged off a flat tetrahedron
  std::vector<uint8_t> inner(nCells, 0);
  const SitesType *    sites = this->GetSites();
  const auto           start = labels->GetLargestPossibleRegion().GetIndex();
  for (size_t c = 0; c < nCells; ++c)
  {
    unsigned int bestEdge = 12, bestFace = 6;
    for (unsigned int e = 0; e < 12; ++e)
    {
      if (edgeCount[12 * c + e] > (bestEdge < 12 ? edgeCount[12 * c + bestEdge] : 0))
      {
        bestEdge = e;
      }
    }
    for (unsigned int f = 0; f < 6; ++f)
    {
      if (faceCount[6 * c + f] > (bestFace < 6 ? faceCount[6 * c + bestFace] : 0))
      {
        bestFace = f;
      }
    }
    double * x = &nodes[c * D];
    // with edge snapping off, a cell on an edge line still goes there when it has no face voxel to average
    if (bestEdge < 12 && (m_SnapToBoxEdges || bestFace == 6))
    {
      const unsigned int a = bestEdge / 4, b = (a + 1) % 3, c3 = (a + 2) % 3;
      x[a] = static_cast<double>(edgeSum[12 * c + bestEdge]) / static_cast<double>(edgeCount[12 * c + bestEdge]) *
             grid.spacing[a];
      x[b] = (bestEdge >> 1) & 1u ? hi[b] : 0.0;
      x[c3] = bestEdge & 1u ? hi[c3] : 0.0;
      freeAxes[c] = static_cast<uint8_t>(1u << a);
    }
    else if (bestFace < 6)
    {
      const unsigned int k = bestFace / 2, a = (k + 1) % 3, b = (k + 2) % 3;
      const double       count = static_cast<double>(faceCount[6 * c + bestFace]);
      x[a] = static_cast<double>(faceSum[2 * (6 * c + bestFace)]) / count * grid.spacing[a];
      x[b] = static_cast<double>(faceSum[2 * (6 * c + bestFace) + 1]) / count * grid.spacing[b];
      x[k] = bestFace % 2 ? hi[k] : 0.0;
      freeAxes[c] = static_cast<uint8_t>(7u & ~(1u << k));
    }
    else
    {
      inner[c] = 1;
      if (sites && sites->GetNumberOfPoints() == nCells)
      {
        const auto ci = labels->template TransformPhysicalPointToContinuousIndex<double, double>(sites->GetPoint(c));
        for (unsigned int k = 0; k < D; ++k)
        {
          x[k] = (ci[k] - static_cast<double>(start[k])) * grid.spacing[k];
        }
      }
      else
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          x[k] = static_cast<double>(stats[4 * c + 1 + k]) / static_cast<double>(stats[4 * c]) * grid.spacing[k];
        }
      }
    }
  }
  dmr::ForEachImageCorner<D>(
    grid,
    L,
    nCells,
    [&](size_t c, const double * x) {
      std::copy(x, x + D, &nodes[c * D]);
      freeAxes[c] = 0;
    },
    [&](const double * x) {
      nodes.insert(nodes.end(), x, x + D);
      freeAxes.push_back(0);
    });

  // Delaunay tetrahedralization of all nodes (no constraints: see dmrDelaunay3D.h). The corners are nodes, so the
  // convex hull is the box. Near-flat tetrahedra are removed by nudging their nodes, never more than a quarter voxel
  // (inner, face and edge nodes are at least one voxel away from any face, edge or corner they are not on).
  double minimumSpacing = grid.spacing[0];
  for (unsigned int k = 1; k < D; ++k)
  {
    minimumSpacing = std::min(minimumSpacing, grid.spacing[k]);
  }
  std::vector<std::array<int32_t, 4>> tetrahedra;
  m_NumberOfPerturbedNodes = static_cast<SizeValueType>(dmr::NonDegenerateDelaunay3D(
    nodes, freeAxes, 0.25 * minimumSpacing, tetrahedra, dmr::DefaultMinimumTetrahedronShape, 12));

  // how much of the CVT adjacency between inner cells the tetrahedralization holds
  std::vector<std::array<int32_t, 2>> innerPairs;
  for (const uint64_t key : pairs)
  {
    const auto a = static_cast<int32_t>(key >> 32), b = static_cast<int32_t>(key & 0xffffffffu);
    if (inner[a] && inner[b])
    {
      innerPairs.push_back({ a, b });
    }
  }
  m_NumberOfInnerAdjacencyEdges = static_cast<SizeValueType>(innerPairs.size());
  m_NumberOfMissingAdjacencyEdges = static_cast<SizeValueType>(dmr::CountEdgesNotInMesh(innerPairs, tetrahedra));
  this->BuildOutputMesh(grid, nodes, tetrahedra);
}

template <typename TLabelImage, typename TOutputMesh>
void
DualMeshFilter<TLabelImage, TOutputMesh>::BuildOutputMesh(
  const dmr::Grid<ImageDimension> &                            grid,
  const std::vector<double> &                                  nodes,
  const std::vector<std::array<int32_t, ImageDimension + 1>> & elements)
{
  constexpr unsigned int D = ImageDimension;
  const LabelImageType * labels = this->GetInput();
  // compact the used nodes
  const size_t         nNodes = nodes.size() / D;
  std::vector<int32_t> newIndex(nNodes, -1);
  m_SimplexMesh = SimplexMeshType();
  for (const auto & t : elements)
  {
    std::array<int32_t, D + 1> e;
    for (unsigned int v = 0; v <= D; ++v)
    {
      if (newIndex[t[v]] < 0)
      {
        newIndex[t[v]] = static_cast<int32_t>(m_SimplexMesh.nodes.size() / D);
        m_SimplexMesh.nodes.insert(m_SimplexMesh.nodes.end(), &nodes[t[v] * D], &nodes[t[v] * D] + D);
      }
      e[v] = newIndex[t[v]];
    }
    m_SimplexMesh.elements.push_back(e);
  }
  m_SimplexMesh.OrientPositively();
  m_SimplexMesh.MarkBorderNodes(grid);
  m_NumberOfBoundaryNodes = static_cast<SizeValueType>(
    std::count(m_SimplexMesh.fixed.begin(), m_SimplexMesh.fixed.end(), static_cast<uint8_t>(1)));

  double total = 0.0, box = 1.0;
  for (size_t e = 0; e < m_SimplexMesh.elements.size(); ++e)
  {
    total += m_SimplexMesh.SignedMeasure(e);
  }
  for (unsigned int k = 0; k < D; ++k)
  {
    box *= static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
  }
  if (std::abs(total - box) > 1e-6 * box)
  {
    itkExceptionMacro("the dual mesh does not cover the image box: element measures sum to " << total << ", box is "
                                                                                            << box);
  }

  auto built = dmr::ToItkMesh<D, MeshType>(m_SimplexMesh, labels);
  MeshType * output = this->GetOutput();
  output->Graft(built);
}

template <typename TLabelImage, typename TOutputMesh>
void
DualMeshFilter<TLabelImage, TOutputMesh>::PrintSelf(std::ostream & os, Indent indent) const
{
  Superclass::PrintSelf(os, indent);
  os << indent << "NumberOfNodes: " << m_SimplexMesh.NumberOfNodes() << std::endl;
  os << indent << "NumberOfElements: " << m_SimplexMesh.elements.size() << std::endl;
  os << indent << "SnapToBoxEdges: " << (m_SnapToBoxEdges ? "On" : "Off") << std::endl;
  os << indent << "NumberOfSkippedConstraints: " << m_NumberOfSkippedConstraints << std::endl;
  os << indent << "NumberOfBoundaryNodes: " << m_NumberOfBoundaryNodes << std::endl;
  os << indent << "NumberOfInnerAdjacencyEdges: " << m_NumberOfInnerAdjacencyEdges << std::endl;
  os << indent << "NumberOfMissingAdjacencyEdges: " << m_NumberOfMissingAdjacencyEdges << std::endl;
  os << indent << "NumberOfPerturbedNodes: " << m_NumberOfPerturbedNodes << std::endl;
}
} // namespace itk

#endif
