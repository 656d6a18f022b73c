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
#ifndef itkDualMeshFilter_h
#define itkDualMeshFilter_h

#include "itkImageToMeshFilter.h"
#include "itkMesh.h"
#include "itkPointSet.h"
#include "dmrSimplexMesh.h"

namespace itk
{
/** \class DualMeshFilter
 * \brief Dual triangulation of a cell-label image (a discrete CVT): the mesh the FEM registration solves on.
 *
 * Input 0: label image with labels 0..N-1, every cell connected (output of DiscreteCVTFilter). Optional input
 * "Sites": a PointSet whose point i is the site of cell i (physical); without it the unweighted centroids are used.
 *
 * Nodes (paper 4.6): an inner cell's node is its site; a boundary cell (one that has pixels on the image border)
 * gets its node at the centre of its border pixels on the side where it has most of them; a corner cell (one that
 * holds an image corner pixel) gets its node exactly at the corner. Corners are always nodes. Edges: adjacent inner
 * cells are joined by constrained edges (skipped when one would cross an edge already constrained), and all nodes
 * are triangulated by CGAL's constrained Delaunay triangulation, which re-triangulates the boundary band. Because
 * every corner and boundary node lies on the image box, the mesh covers the box spanned by the pixel centres
 * exactly, with no inverted or zero-area triangle (checked: element measures sum to the box measure).
 *
 * Output: an itk::Mesh in physical space with TriangleCells (2D); point data 1 marks nodes on the image border,
 * which the FEM stage fixes. 3D (tetrahedra through TetGen) is not part of this version.
 *
 * \par References
 * Y. Cai, X. Guo, Z. Zhong, W. Mao, "Dynamic meshing for deformable image registration", Computer-Aided Design 58
 * (2015) 141-150, doi:10.1016/j.cad.2014.08.009.
 * \ingroup DynamicMeshRegistration */
template <typename TLabelImage,
          typename TOutputMesh = Mesh<double,
                                      TLabelImage::ImageDimension,
                                      DefaultStaticMeshTraits<double, TLabelImage::ImageDimension, TLabelImage::ImageDimension, double>>>
class ITK_TEMPLATE_EXPORT DualMeshFilter : public ImageToMeshFilter<TLabelImage, TOutputMesh>
{
public:
  ITK_DISALLOW_COPY_AND_MOVE(DualMeshFilter);
  using Self = DualMeshFilter;
  using Superclass = ImageToMeshFilter<TLabelImage, TOutputMesh>;
  using Pointer = SmartPointer<Self>;
  using ConstPointer = SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(DualMeshFilter, ImageToMeshFilter);

  static constexpr unsigned int ImageDimension = TLabelImage::ImageDimension;
  using LabelImageType = TLabelImage;
  using MeshType = TOutputMesh;
  using SitesType = PointSet<double, ImageDimension, DefaultStaticMeshTraits<double, ImageDimension, ImageDimension, double, double>>;
  using SimplexMeshType = dmr::SimplexMesh<ImageDimension>;

  using Superclass::SetInput;
  void
  SetInput(const LabelImageType * labels)
  {
    this->ProcessObject::SetNthInput(0, const_cast<LabelImageType *>(labels));
  }
  const LabelImageType *
  GetInput() const
  {
    return itkDynamicCastInDebugMode<const LabelImageType *>(this->ProcessObject::GetInput(0));
  }
  itkSetInputMacro(Sites, SitesType);
  itkGetInputMacro(Sites, SitesType);

  /** The mesh of the last update in the grid frame (what the FEM stage uses). */
  const SimplexMeshType &
  GetSimplexMesh() const
  {
    return m_SimplexMesh;
  }
  /** Inner-cell adjacency edges that could not be constrained (they crossed an earlier one). */
  itkGetConstMacro(NumberOfSkippedConstraints, SizeValueType);
  itkGetConstMacro(NumberOfBoundaryNodes, SizeValueType);

protected:
  DualMeshFilter();
  ~DualMeshFilter() override = default;
  void
  PrintSelf(std::ostream & os, Indent indent) const override;
  void
  GenerateOutputInformation() override
  {}
  void
  GenerateInputRequestedRegion() override;
  void
  GenerateData() override;

private:
  SimplexMeshType m_SimplexMesh;
  SizeValueType   m_NumberOfSkippedConstraints{ 0 };
  SizeValueType   m_NumberOfBoundaryNodes{ 0 };
};
} // namespace itk

#ifndef ITK_MANUAL_INSTANTIATION
#  include "itkDualMeshFilter.hxx"
#endif

#endif
