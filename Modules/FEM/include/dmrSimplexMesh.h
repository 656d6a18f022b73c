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
#ifndef dmrSimplexMesh_h
#define dmrSimplexMesh_h

#include "dmrGrid.h"
#include "itkMesh.h"
#include "itkTriangleCell.h"
#include "itkTetrahedronCell.h"
#include "itkMacro.h"
#include <array>
#include <vector>
#include <numeric>
#include <algorithm>

namespace itk
{
namespace dmr
{
/** \brief Flat simplex mesh in the grid frame (mm along the image axes, origin at the first pixel centre), the form
 * the FEM stage and the barycentric rasterisation work on. Elements have positive orientation. A node is fixed
 * (Dirichlet u = 0, paper 3) when it lies on the border of the image box [0, (size-1) spacing].
 * \ingroup DynamicMeshRegistration */
template <unsigned int D>
struct SimplexMesh
{
  std::vector<double>                     nodes; // D interleaved
  std::vector<std::array<int32_t, D + 1>> elements;
  std::vector<uint8_t>                    fixed;

  size_t
  NumberOfNodes() const
  {
    return nodes.size() / D;
  }

  /** Edge matrix J = [x_1 - x_0, ..., x_D - x_0] of element e: writes x_0 and, when inv is given and det != 0,
   * J^-1 (whose rows are the gradients of the barycentric coordinates lambda_1..lambda_D). Returns det J. */
  double
  EdgeMatrix(size_t e, double (&x0)[D], double (*inv)[D][D] = nullptr) const
  {
    double v[D + 1][D];
    for (unsigned int i = 0; i <= D; ++i)
    {
      std::copy_n(&nodes[static_cast<size_t>(elements[e][i]) * D], D, v[i]);
    }
    return SimplexEdgeInverse<D>(v, x0, inv);
  }

  /** Signed measure (area/volume) of element e, positive for positive orientation. */
  double
  SignedMeasure(size_t e) const
  {
    double x0[D];
    return EdgeMatrix(e, x0) / (D == 2 ? 2.0 : 6.0);
  }

  /** Orient every element positively; throws on a degenerate one. */
  void
  OrientPositively()
  {
    for (size_t e = 0; e < elements.size(); ++e)
    {
      const double v = SignedMeasure(e);
      if (v < 0)
      {
        std::swap(elements[e][0], elements[e][1]);
      }
      else if (!(v > 0))
      {
        itkGenericExceptionMacro("SimplexMesh: element " << e << " is degenerate (zero measure)");
      }
    }
  }

  /** True when a node can move: not every node is marked fixed (a mesh without fixed flags has only free nodes). */
  bool
  HasFreeNode() const
  {
    return fixed.size() != NumberOfNodes() || std::find(fixed.begin(), fixed.end(), 0) != fixed.end();
  }

  /** Mark nodes on the border of the grid's box as fixed. */
  void
  MarkBorderNodes(const Grid<D> & grid)
  {
    fixed.assign(NumberOfNodes(), 0);
    for (size_t i = 0; i < NumberOfNodes(); ++i)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        const double hi = static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
        const double tol = 1e-6 * grid.spacing[k];
        if (std::abs(nodes[i * D + k]) <= tol || std::abs(nodes[i * D + k] - hi) <= tol)
        {
          fixed[i] = 1;
        }
      }
    }
  }
};

/** The elements around every node, in element order: those of node a are incident[start[a]] .. incident[start[a+1]-1]
 * (compressed rows; start has nNodes + 1 entries). Every vertex id must be below nNodes. */
template <size_t VVertices, typename TIndex>
void
ElementsAroundNodes(const std::vector<std::array<int32_t, VVertices>> & elements,
                    size_t                                              nNodes,
                    std::vector<TIndex> &                               start,
                    std::vector<TIndex> &                               incident)
{
  start.assign(nNodes + 1, 0);
  for (const auto & e : elements)
  {
    for (const int32_t v : e)
    {
      ++start[v + 1];
    }
  }
  for (size_t a = 0; a < nNodes; ++a)
  {
    start[a + 1] += start[a];
  }
  incident.resize(elements.size() * VVertices);
  std::vector<TIndex> fill(start.begin(), start.end() - 1);
  for (size_t e = 0; e < elements.size(); ++e)
  {
    for (const int32_t v : elements[e])
    {
      incident[fill[v]++] = static_cast<TIndex>(e);
    }
  }
}

/** Static regular mesh: nodesPerAxis^D nodes spread evenly over the image box, each grid cube split into D!
 * simplices (Kuhn/Freudenthal split, conforming across cubes): 2 triangles per square, 6 tetrahedra per cube. */
template <unsigned int D>
SimplexMesh<D>
MakeRegularMesh(const Grid<D> & grid, const std::array<size_t, D> & nodesPerAxis)
{
  SimplexMesh<D>        mesh;
  size_t                count = 1;
  std::array<size_t, D> stride;
  for (unsigned int k = 0; k < D; ++k)
  {
    if (nodesPerAxis[k] < 2)
    {
      itkGenericExceptionMacro("MakeRegularMesh: at least 2 nodes per axis are needed");
    }
    stride[k] = count;
    count *= nodesPerAxis[k];
  }
  mesh.nodes.resize(count * D);
  for (size_t i = 0; i < count; ++i)
  {
    size_t rest = i;
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t ik = rest % nodesPerAxis[k];
      rest /= nodesPerAxis[k];
      mesh.nodes[i * D + k] = static_cast<double>(grid.size[k] - 1) * grid.spacing[k] * static_cast<double>(ik) /
                              static_cast<double>(nodesPerAxis[k] - 1);
    }
  }
  std::array<unsigned int, D> perm;
  size_t                      cubes = 1;
  for (unsigned int k = 0; k < D; ++k)
  {
    cubes *= nodesPerAxis[k] - 1;
  }
  for (size_t c = 0; c < cubes; ++c)
  {
    size_t rest = c, base = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      base += (rest % (nodesPerAxis[k] - 1)) * stride[k];
      rest /= nodesPerAxis[k] - 1;
    }
    std::iota(perm.begin(), perm.end(), 0u);
    do
    {
      std::array<int32_t, D + 1> e;
      size_t                     v = base;
      e[0] = static_cast<int32_t>(v);
      for (unsigned int k = 0; k < D; ++k)
      {
        v += stride[perm[k]];
        e[k + 1] = static_cast<int32_t>(v);
      }
      mesh.elements.push_back(e);
    } while (std::next_permutation(perm.begin(), perm.end()));
  }
  mesh.OrientPositively();
  mesh.MarkBorderNodes(grid);
  return mesh;
}

/** Converts an itk::Mesh of triangles/tetrahedra in physical space into the grid frame of an image. */
template <unsigned int D, typename TMesh, typename TImage>
SimplexMesh<D>
FromItkMesh(const TMesh * mesh, const TImage * image)
{
  SimplexMesh<D> out;
  const auto     start = image->GetLargestPossibleRegion().GetIndex();
  const auto &   spacing = image->GetSpacing();
  const size_t   n = mesh->GetNumberOfPoints();
  out.nodes.resize(n * D);
  size_t i = 0;
  for (auto it = mesh->GetPoints()->Begin(); it != mesh->GetPoints()->End(); ++it, ++i)
  {
    const auto ci = image->template TransformPhysicalPointToContinuousIndex<double, double>(it.Value());
    for (unsigned int k = 0; k < D; ++k)
    {
      out.nodes[i * D + k] = (ci[k] - static_cast<double>(start[k])) * spacing[k];
    }
  }
  std::vector<typename TMesh::PointIdentifier> ids;
  for (auto it = mesh->GetPoints()->Begin(); it != mesh->GetPoints()->End(); ++it)
  {
    ids.push_back(it.Index());
  }
  for (auto c = mesh->GetCells()->Begin(); c != mesh->GetCells()->End(); ++c)
  {
    const auto * cell = c.Value();
    if (cell->GetNumberOfPoints() != D + 1)
    {
      continue; // vertices, lines, faces of lower dimension are not elements
    }
    std::array<int32_t, D + 1> e;
    unsigned int               k = 0;
    for (auto p = cell->PointIdsBegin(); p != cell->PointIdsEnd(); ++p, ++k)
    {
      const auto found = std::lower_bound(ids.begin(), ids.end(), *p);
      if (found == ids.end() || *found != *p)
      {
        itkGenericExceptionMacro("mesh cell refers to point " << *p << " which does not exist");
      }
      e[k] = static_cast<int32_t>(found - ids.begin());
    }
    out.elements.push_back(e);
  }
  if (out.elements.empty())
  {
    itkGenericExceptionMacro("the mesh has no " << (D == 2 ? "triangles" : "tetrahedra"));
  }
  // The mesh must lie in the image box, whose border nodes are fixed: from the first to the last pixel centre. Nodes
  // within 1e-3 pixel of the border (a mesh stored in float) are put on it, so that they are found fixed; a node
  // further out is refused (e.g. a mesh of the pixel edges, half a pixel out, would have no fixed node at all).
  const auto grid = Grid<D>::FromImage(image);
  for (size_t a = 0; a < n; ++a)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      double &     x = out.nodes[a * D + k];
      const double hi = static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
      const double tol = 1e-3 * grid.spacing[k];
      x = std::abs(x) <= tol ? 0.0 : (std::abs(x - hi) <= tol ? hi : x);
      if (x < 0.0 || x > hi)
      {
        itkGenericExceptionMacro("mesh node " << a
                                              << " lies outside the image box (the pixel centres from the first to "
                                                 "the last) by "
                                              << (x < 0.0 ? -x : x - hi) / grid.spacing[k] << " pixel along axis "
                                              << k);
      }
    }
  }
  out.OrientPositively();
  // inside the box and covering it (every pixel centre lies in an element, checked by the barycentric map), the
  // elements tile it exactly when their measures add up to the box's: more means elements that overlap
  double total = 0.0, box = 1.0;
  for (size_t e = 0; e < out.elements.size(); ++e)
  {
    total += out.SignedMeasure(e);
  }
  for (unsigned int k = 0; k < D; ++k)
  {
    box *= static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
  }
  if (total > box * (1.0 + 1e-6))
  {
    itkGenericExceptionMacro("the mesh's elements overlap: their " << (D == 2 ? "areas" : "volumes") << " add up to "
                                                                   << total / box << " times the image box's");
  }
  out.MarkBorderNodes(grid);
  return out;
}

/** Converts a grid-frame simplex mesh into an itk::Mesh in physical space (point data: 1 for fixed nodes). */
template <unsigned int D, typename TMesh, typename TImage>
typename TMesh::Pointer
ToItkMesh(const SimplexMesh<D> & in, const TImage * image)
{
  using CellType = typename TMesh::CellType;
  using SimplexCellType = std::conditional_t<D == 2, TriangleCell<CellType>, TetrahedronCell<CellType>>;
  auto         mesh = TMesh::New();
  const auto   start = image->GetLargestPossibleRegion().GetIndex();
  const auto & spacing = image->GetSpacing();
  for (size_t i = 0; i < in.NumberOfNodes(); ++i)
  {
    ContinuousIndex<double, D> ci;
    for (unsigned int k = 0; k < D; ++k)
    {
      ci[k] = static_cast<double>(start[k]) + in.nodes[i * D + k] / spacing[k];
    }
    typename TMesh::PointType p;
    image->TransformContinuousIndexToPhysicalPoint(ci, p);
    mesh->SetPoint(i, p);
    mesh->SetPointData(i, in.fixed.empty() ? 0.0 : static_cast<double>(in.fixed[i]));
  }
  for (size_t e = 0; e < in.elements.size(); ++e)
  {
    typename CellType::CellAutoPointer cell;
    cell.TakeOwnership(new SimplexCellType);
    for (unsigned int k = 0; k <= D; ++k)
    {
      cell->SetPointId(k, in.elements[e][k]);
    }
    mesh->SetCell(e, cell);
  }
  return mesh;
}
} // namespace dmr
} // namespace itk

#endif
