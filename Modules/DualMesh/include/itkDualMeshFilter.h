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
#include "dmrDualMeshBuilder.h"
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
 * holds an image corner pixel) gets its node exactly at the corner. Corners are always nodes (a cell holding several
 * corners adds the further ones as extra nodes). Nodes at the same position are merged.
 *
 * 2D: adjacent inner cells are joined by constrained edges (skipped when one would cross an edge already
 * constrained), and all nodes are triangulated by CGAL's constrained Delaunay triangulation, which re-triangulates
 * the boundary band.
 *
 * 3D: the box border has 8 corners, 12 edge lines and 6 faces, and a cell's node goes onto the lowest-dimensional
 * of them it touches: a cell holding a corner voxel at that corner; else (SnapToBoxEdges, the default) a cell with
 * voxels on an edge line at the centre of its voxels on the edge line where it has most of them, the two other
 * coordinates exactly on the edge; else a cell with face voxels at the centre of its voxels on the face where it has
 * most, exactly on that face plane; else the site. Edge snapping spreads nodes along the 12 box edges instead of
 * leaving long corner-to-corner hull edges with thin tetrahedra along them. All nodes are tetrahedralized by their
 * Delaunay tetrahedralization without constraints (TetGen 1.5 cannot take free inner segments as constraints without
 * Steiner points; the Delaunay tetrahedralization of the sites is the dual of their Voronoi diagram and so holds most
 * of the CVT adjacency: GetNumberOfMissingAdjacencyEdges() says how much it misses), computed by blocks on the
 * filter's work units (CGAL) where the nodes allow it, else by one TetGen run (dmr::Delaunay3D).
 * A tetrahedron flatter than dmr::DefaultMinimumTetrahedronShape (6 sqrt(2) V / L^3 < 1e-6, which only a
 * near-degenerate node set gives, e.g. a symmetric CVT with rounded centroids) is removed by nudging its non-corner
 * nodes (inner ones freely, face nodes within their face, edge nodes along their edge) by a deterministic step of
 * at most a quarter voxel and tetrahedralizing again; no Steiner point is added, so nodes stay one per cell plus the
 * extra corners. GetNumberOfPerturbedNodes() counts the nodes moved (0 for generic input).
 *
 * Because every corner and boundary node lies on the image box, the mesh covers the box spanned by the pixel centres
 * exactly, with no inverted or zero-measure element (checked: element measures sum to the box measure).
 *
 * The work is split in two (dmrDualMeshBuilder.h): the label image is reduced to a dmr::LabelSummary (cell voxel
 * counts and index sums, border face/edge statistics, corner labels, adjacent cell pairs) by dmr::SummarizeLabels,
 * and the mesh is built from the summary and the sites by dmr::BuildDualMesh. The GPU registration computes the
 * same summary on the device (dmr::cuda::LabelSummarizer, dmrDualMeshBackend.h) and calls the builder directly, so
 * the labels never leave the device.
 *
 * Output: an itk::Mesh in physical space with TriangleCells (2D) or TetrahedronCells (3D); point data 1 marks nodes
 * on the image border, which the FEM stage fixes.
 *
 * \par References
 * Y. Cai, X. Guo, Z. Zhong, W. Mao, "Dynamic meshing for deformable image registration", Computer-Aided Design 58
 * (2015) 141-150, doi:10.1016/j.cad.2014.08.009.
 * \ingroup DynamicMeshRegistration */
template <typename TLabelImage,
          typename TOutputMesh =
            Mesh<double,
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
  using SitesType =
    PointSet<double, ImageDimension, DefaultStaticMeshTraits<double, ImageDimension, ImageDimension, double, double>>;
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
  /** 3D only: put the node of a cell that touches a box edge line (but no corner) onto that edge (default on);
   * off, such a cell is treated like any other boundary cell (its face with most voxels), unless it has no voxel
   * inside a face. On a CVT, edge snapping gives better tetrahedra next to the box edges. */
  itkSetMacro(SnapToBoxEdges, bool);
  itkGetConstMacro(SnapToBoxEdges, bool);
  itkBooleanMacro(SnapToBoxEdges);

  /** 2D: inner-cell adjacency edges that could not be constrained (they crossed an earlier one). 3D: 0 (nothing is
   * constrained). */
  itkGetConstMacro(NumberOfSkippedConstraints, SizeValueType);
  itkGetConstMacro(NumberOfBoundaryNodes, SizeValueType);
  /** Pairs of adjacent inner cells (sharing a pixel edge / voxel face) in the label image. */
  itkGetConstMacro(NumberOfInnerAdjacencyEdges, SizeValueType);
  /** Of those, the pairs whose nodes are not joined by a mesh edge. */
  itkGetConstMacro(NumberOfMissingAdjacencyEdges, SizeValueType);
  /** 3D: nodes moved off near-flat tetrahedra (see the class comment); 0 in 2D. */
  itkGetConstMacro(NumberOfPerturbedNodes, SizeValueType);

protected:
  DualMeshFilter();
  ~DualMeshFilter() override = default;
  void
  PrintSelf(std::ostream & os, Indent indent) const override;
  void
  GenerateOutputInformation() override
  {
  }
  void
  GenerateInputRequestedRegion() override;
  void
  GenerateData() override;

private:
  SimplexMeshType m_SimplexMesh;
  bool            m_SnapToBoxEdges{ dmr::DefaultSnapToBoxEdges };
  SizeValueType   m_NumberOfSkippedConstraints{ 0 };
  SizeValueType   m_NumberOfBoundaryNodes{ 0 };
  SizeValueType   m_NumberOfInnerAdjacencyEdges{ 0 };
  SizeValueType   m_NumberOfMissingAdjacencyEdges{ 0 };
  SizeValueType   m_NumberOfPerturbedNodes{ 0 };
};
} // namespace itk

#ifndef ITK_MANUAL_INSTANTIATION
#include "itkDualMeshFilter.hxx"
#endif

#endif
