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
#include "dmrDualMeshBuilder.h"

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
  if (D != 2 && D != 3)
  {
    itkExceptionMacro("the dual mesh is defined in 2D (triangles) and 3D (tetrahedra), not in " << D << "D");
  }
  if constexpr (D == 2 || D == 3)
  {
    // the mesh is a Delaunay mesh of the grid frame scaled by the spacing, the physical frame only for a rotation
    const std::string skew = dmr::DirectionNotOrthonormal<D>(labels, "label image");
    if (!skew.empty())
    {
      itkExceptionMacro(<< skew);
    }
    // the nodes are placed and triangulated in physical coordinates
    const std::string far = dmr::CoordinatesDoNotResolvePixels<D>(labels, "label image");
    if (!far.empty())
    {
      itkExceptionMacro(<< far);
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

    // the summary (everything the mesh needs from the labels), then the mesh from it and the sites (grid frame)
    const dmr::LabelSummary summary = dmr::SummarizeLabels<D>(grid, L, nCells, this->GetMultiThreader());
    const SitesType *       sites = this->GetSites();
    std::vector<double>     sitesGridFrame;
    if (sites && sites->GetNumberOfPoints() == nCells)
    {
      const auto start = labels->GetLargestPossibleRegion().GetIndex();
      sitesGridFrame.resize(nCells * D);
      for (size_t c = 0; c < nCells; ++c)
      {
        const auto ci = labels->template TransformPhysicalPointToContinuousIndex<double, double>(sites->GetPoint(c));
        for (unsigned int k = 0; k < D; ++k)
        {
          sitesGridFrame[c * D + k] = (ci[k] - static_cast<double>(start[k])) * grid.spacing[k];
        }
      }
    }
    dmr::DualMeshStatistics statistics;
    m_SimplexMesh = dmr::BuildDualMesh<D>(grid,
                                          summary,
                                          sitesGridFrame.empty() ? nullptr : sitesGridFrame.data(),
                                          m_SnapToBoxEdges,
                                          &statistics,
                                          this->GetMultiThreader());
    m_NumberOfSkippedConstraints = static_cast<SizeValueType>(statistics.numberOfSkippedConstraints);
    m_NumberOfBoundaryNodes = static_cast<SizeValueType>(statistics.numberOfBoundaryNodes);
    m_NumberOfInnerAdjacencyEdges = static_cast<SizeValueType>(statistics.numberOfInnerAdjacencyEdges);
    m_NumberOfMissingAdjacencyEdges = static_cast<SizeValueType>(statistics.numberOfMissingAdjacencyEdges);
    m_NumberOfPerturbedNodes = static_cast<SizeValueType>(statistics.numberOfPerturbedNodes);

    auto       built = dmr::ToItkMesh<D, MeshType>(m_SimplexMesh, labels);
    MeshType * output = this->GetOutput();
    output->Graft(built);
  }
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
