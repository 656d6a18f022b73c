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
#include <map>

namespace itk
{
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
  if (D != 2)
  {
    itkExceptionMacro("the " << D << "D dual mesh (tetrahedralisation) is not part of this version; only 2D");
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
  // corners: the cell that holds a corner pixel gets its node there; further corners of the same cell are extra nodes
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
    const int64_t c = L[p];
    if (!cornerTaken[c])
    {
      cornerTaken[c] = true;
      kind[c] = 2;
      for (unsigned int k = 0; k < D; ++k)
      {
        nodes[c * D + k] = x[k];
      }
    }
    else
    {
      nodes.insert(nodes.end(), x, x + D);
    }
  }
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

  // compact the used nodes
  const size_t         nNodes = nodes.size() / D;
  std::vector<int32_t> newIndex(nNodes, -1);
  m_SimplexMesh = SimplexMeshType();
  for (const auto & t : triangles)
  {
    std::array<int32_t, D + 1> e;
    for (unsigned int v = 0; v < 3; ++v)
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
  os << indent << "NumberOfBoundaryNodes: " << m_NumberOfBoundaryNodes << std::endl;
  os << indent << "NumberOfSkippedConstraints: " << m_NumberOfSkippedConstraints << std::endl;
}
} // namespace itk

#endif
