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
#include "itkDualMeshFilter.h"
#include "dmrBarycentricMap.h"
#include "dmrDelaunay3D.h"
#include "dmrDualMeshPhantom.h"
#include "dmrObjectChecks.h"
#include "gtest/gtest.h"
#include "vnl/algo/vnl_determinant.h"

#include <functional>
#include <map>

namespace
{
using itk::dmr::test::DualMeshPhantom3D;
using itk::dmr::test::MakeDualMeshPhantom3D;
using LabelImageType = DualMeshPhantom3D::CVTFilterType::LabelImageType;
using FilterType = DualMeshPhantom3D::DualMeshFilterType;
using Mesh3D = itk::dmr::SimplexMesh<3>;
using Grid3D = itk::dmr::Grid<3>;

/** The phantom is built once: its CVT is the slow part (about a second). */
const DualMeshPhantom3D &
Phantom()
{
  static const DualMeshPhantom3D phantom = MakeDualMeshPhantom3D();
  return phantom;
}

std::array<double, 3>
BoxHigh(const Grid3D & grid)
{
  return { (grid.size[0] - 1) * grid.spacing[0],
           (grid.size[1] - 1) * grid.spacing[1],
           (grid.size[2] - 1) * grid.spacing[2] };
}

bool
HasNodeAt(const Mesh3D & mesh, const double * x, double tolerance)
{
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    if (std::abs(mesh.nodes[3 * i] - x[0]) <= tolerance && std::abs(mesh.nodes[3 * i + 1] - x[1]) <= tolerance &&
        std::abs(mesh.nodes[3 * i + 2] - x[2]) <= tolerance)
    {
      return true;
    }
  }
  return false;
}

/** Which box faces (bit 2k + side) a node lies on exactly; -1 when it is within 1e-6 voxel of a face plane without
 * lying on it (a rounding miss, which would make sliver tetrahedra along the border). */
int
ExactFaces(const Grid3D & grid, const Mesh3D & mesh, size_t i)
{
  const auto hi = BoxHigh(grid);
  int        faces = 0;
  for (unsigned int k = 0; k < 3; ++k)
  {
    const double x = mesh.nodes[3 * i + k], tol = 1e-6 * grid.spacing[k];
    if (x == 0.0)
    {
      faces |= 1 << (2 * k);
    }
    else if (x == hi[k])
    {
      faces |= 1 << (2 * k + 1);
    }
    else if (std::abs(x) <= tol || std::abs(x - hi[k]) <= tol)
    {
      return -1;
    }
  }
  return faces;
}

/** Properties every 3D dual mesh must have, whatever its input. */
::testing::AssertionResult
IsValidDualMesh(const Grid3D & grid, const Mesh3D & mesh)
{
  if (mesh.elements.empty())
  {
    return ::testing::AssertionFailure() << "no tetrahedron";
  }
  auto tiles = itk::dmr::test::MeshTilesTheBox<3>(grid, mesh);
  if (!tiles)
  {
    return tiles;
  }
  auto fixed = itk::dmr::test::FixedNodesAreTheBorderNodes<3>(grid, mesh);
  if (!fixed)
  {
    return fixed;
  }
  std::vector<int> used(mesh.NumberOfNodes(), 0);
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    for (int32_t v : mesh.elements[e])
    {
      if (v < 0 || static_cast<size_t>(v) >= mesh.NumberOfNodes())
      {
        return ::testing::AssertionFailure() << "element " << e << " refers to node " << v;
      }
      used[v] = 1;
    }
    const auto & t = mesh.elements[e];
    const double shape = itk::dmr::TetrahedronShape(
      &mesh.nodes[3 * t[0]], &mesh.nodes[3 * t[1]], &mesh.nodes[3 * t[2]], &mesh.nodes[3 * t[3]]);
    if (!(shape >= itk::dmr::DefaultMinimumTetrahedronShape))
    {
      return ::testing::AssertionFailure() << "element " << e << " is flat: shape " << shape;
    }
  }
  if (std::count(used.begin(), used.end(), 1) != static_cast<long>(mesh.NumberOfNodes()))
  {
    return ::testing::AssertionFailure() << "unused nodes";
  }
  const auto hi = BoxHigh(grid);
  for (unsigned int corner = 0; corner < 8; ++corner)
  {
    const double x[3] = { corner & 1u ? hi[0] : 0.0, corner & 2u ? hi[1] : 0.0, corner & 4u ? hi[2] : 0.0 };
    if (!HasNodeAt(mesh, x, 0.0))
    {
      return ::testing::AssertionFailure() << "corner " << corner << " is not a node";
    }
  }
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    if (ExactFaces(grid, mesh, i) < 0)
    {
      return ::testing::AssertionFailure() << "node " << i << " lies next to a box face plane but not on it";
    }
  }
  return ::testing::AssertionSuccess();
}

/** Every voxel centre lies in at least one tetrahedron (barycentric coordinates >= -1e-9) and, when it lies strictly
 * inside one (all coordinates > 1e-9), in no other: checked by brute force over every tetrahedron's bounding box,
 * independently of dmr::BarycentricMap. Returns the number of voxels strictly inside a tetrahedron. */
::testing::AssertionResult
EveryVoxelIsInExactlyOneTetrahedron(const Grid3D & grid, const Mesh3D & mesh, size_t & strictlyInside)
{
  std::vector<uint16_t> containing(grid.numberOfPixels, 0), strictly(grid.numberOfPixels, 0);
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    double inv[3][3], x0[3];
    mesh.EdgeMatrix(e, x0, &inv);
    int64_t lo[3], hi[3];
    for (unsigned int k = 0; k < 3; ++k)
    {
      double mn = 1e300, mx = -1e300;
      for (int32_t v : mesh.elements[e])
      {
        mn = std::min(mn, mesh.nodes[3 * v + k] / grid.spacing[k]);
        mx = std::max(mx, mesh.nodes[3 * v + k] / grid.spacing[k]);
      }
      lo[k] = std::max<int64_t>(0, static_cast<int64_t>(std::ceil(mn - 1e-6)));
      hi[k] = std::min<int64_t>(grid.size[k] - 1, static_cast<int64_t>(std::floor(mx + 1e-6)));
    }
    for (int64_t z = lo[2]; z <= hi[2]; ++z)
    {
      for (int64_t y = lo[1]; y <= hi[1]; ++y)
      {
        for (int64_t x = lo[0]; x <= hi[0]; ++x)
        {
          const double d[3] = { x * grid.spacing[0] - x0[0], y * grid.spacing[1] - x0[1], z * grid.spacing[2] - x0[2] };
          double       lambda[4], rest = 1.0;
          for (unsigned int r = 0; r < 3; ++r)
          {
            lambda[r + 1] = inv[r][0] * d[0] + inv[r][1] * d[1] + inv[r][2] * d[2];
            rest -= lambda[r + 1];
          }
          lambda[0] = rest;
          const double smallest = *std::min_element(lambda, lambda + 4);
          const size_t p = x + y * grid.stride[1] + z * grid.stride[2];
          containing[p] += smallest >= -1e-9 ? 1 : 0;
          strictly[p] += smallest > 1e-9 ? 1 : 0;
        }
      }
    }
  }
  strictlyInside = 0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    if (containing[p] == 0)
    {
      return ::testing::AssertionFailure() << "voxel " << p << " lies in no tetrahedron";
    }
    if (strictly[p] > 0 && containing[p] != 1)
    {
      return ::testing::AssertionFailure()
             << "voxel " << p << " lies inside one tetrahedron and in " << containing[p] - 1 << " more";
    }
    strictlyInside += strictly[p];
  }
  return ::testing::AssertionSuccess();
}

/** Conforming: every triangle is shared by two tetrahedra with opposite orientations, or lies on one box face with
 * one tetrahedron; and V - E + F - T = 1 (a 3-ball). */
::testing::AssertionResult
IsConforming(const Grid3D & grid, const Mesh3D & mesh)
{
  // oriented faces: (a, b, c) seen from outside the tetrahedron, stored as the sorted triple plus a parity
  std::map<std::array<int32_t, 3>, std::vector<int>> faces;
  std::map<std::pair<int32_t, int32_t>, int>         edges;
  static const int opposite[4][3] = { { 1, 2, 3 }, { 0, 3, 2 }, { 0, 1, 3 }, { 0, 2, 1 } };
  for (const auto & t : mesh.elements)
  {
    for (const auto & f : opposite)
    {
      std::array<int32_t, 3> tri = { t[f[0]], t[f[1]], t[f[2]] };
      // parity of the permutation that sorts tri
      int parity = 0;
      for (int i = 0; i < 3; ++i)
      {
        for (int j = i + 1; j < 3; ++j)
        {
          parity ^= tri[i] > tri[j] ? 1 : 0;
        }
      }
      std::sort(tri.begin(), tri.end());
      faces[tri].push_back(parity);
    }
    for (int a = 0; a < 4; ++a)
    {
      for (int b = a + 1; b < 4; ++b)
      {
        edges[{ std::min(t[a], t[b]), std::max(t[a], t[b]) }] = 1;
      }
    }
  }
  for (const auto & entry : faces)
  {
    if (entry.second.size() == 2)
    {
      if (entry.second[0] == entry.second[1])
      {
        return ::testing::AssertionFailure() << "two tetrahedra on the same side of a triangle";
      }
      continue;
    }
    if (entry.second.size() > 2)
    {
      return ::testing::AssertionFailure() << "a triangle is shared by " << entry.second.size() << " tetrahedra";
    }
    int common = ~0;
    for (int32_t v : entry.first)
    {
      common &= ExactFaces(grid, mesh, static_cast<size_t>(v));
    }
    if (common <= 0)
    {
      return ::testing::AssertionFailure() << "a triangle with one tetrahedron is not on a box face";
    }
  }
  const long euler = static_cast<long>(mesh.NumberOfNodes()) - static_cast<long>(edges.size()) +
                     static_cast<long>(faces.size()) - static_cast<long>(mesh.elements.size());
  if (euler != 1)
  {
    return ::testing::AssertionFailure() << "V - E + F - T = " << euler;
  }
  return ::testing::AssertionSuccess();
}

itk::ContinuousIndex<double, 3>
GridToContinuousIndex(const LabelImageType * image, const double * x)
{
  itk::ContinuousIndex<double, 3> ci;
  for (unsigned int k = 0; k < 3; ++k)
  {
    ci[k] = x[k] / image->GetSpacing()[k];
  }
  return ci;
}

LabelImageType::Pointer
MakeLabels(const LabelImageType::SizeType &                                  size,
           const std::function<int32_t(const LabelImageType::IndexType &)> & label)
{
  auto image = LabelImageType::New();
  image->SetRegions(size);
  LabelImageType::SpacingType spacing;
  spacing[0] = 0.9;
  spacing[1] = 1.1;
  spacing[2] = 1.7;
  image->SetSpacing(spacing);
  image->Allocate();
  itk::ImageRegionIteratorWithIndex<LabelImageType> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    it.Set(label(it.GetIndex()));
  }
  return image;
}

TEST(DualMeshFilter3D, BasicObjectMethodsAndPrint)
{
  auto filter = FilterType::New();
  EXPECT_TRUE(itk::dmr::test::BasicObjectMethods(filter.GetPointer(), "DualMeshFilter", "ImageToMeshFilter"));
  EXPECT_TRUE(itk::dmr::test::PrintMentions(filter.GetPointer(),
                                            { "NumberOfNodes",
                                              "NumberOfElements",
                                              "SnapToBoxEdges",
                                              "NumberOfSkippedConstraints",
                                              "NumberOfBoundaryNodes",
                                              "NumberOfInnerAdjacencyEdges",
                                              "NumberOfMissingAdjacencyEdges",
                                              "NumberOfPerturbedNodes" }));
  EXPECT_TRUE(filter->GetSnapToBoxEdges());
  filter->SnapToBoxEdgesOff();
  EXPECT_FALSE(filter->GetSnapToBoxEdges());
  filter->SetSnapToBoxEdges(true);
  EXPECT_TRUE(filter->GetSnapToBoxEdges());
}

TEST(DualMeshFilter3D, TetrahedraArePositiveAndTileTheImageBox)
{
  const auto & phantom = Phantom();
  const auto & mesh = phantom.GetMesh();
  EXPECT_TRUE(IsValidDualMesh(phantom.GetGrid(), mesh));
  EXPECT_GE(mesh.NumberOfNodes(), 200u);
  // generic input: no node had to be nudged, so the nodes are exactly the cells' nodes (and the extra corners)
  EXPECT_EQ(phantom.dual->GetNumberOfPerturbedNodes(), 0u);
  EXPECT_EQ(phantom.dual->GetNumberOfSkippedConstraints(), 0u);
}

TEST(DualMeshFilter3D, TetrahedralizationIsConforming)
{
  const auto & phantom = Phantom();
  EXPECT_TRUE(IsConforming(phantom.GetGrid(), phantom.GetMesh()));
}

TEST(DualMeshFilter3D, EveryVoxelCentreLiesInExactlyOneTetrahedron)
{
  const auto & phantom = Phantom();
  const auto   grid = phantom.GetGrid();
  const auto & mesh = phantom.GetMesh();
  size_t       strictlyInside = 0;
  EXPECT_TRUE(EveryVoxelIsInExactlyOneTetrahedron(grid, mesh, strictlyInside));
  EXPECT_GT(strictlyInside, grid.numberOfPixels / 2);
  // the FEM stage's barycentric map works on tetrahedra: every voxel gets one element, weights in [0, 1] summing to 1,
  // and the weights reproduce the voxel position (linear precision)
  itk::dmr::BarycentricMap<3> map;
  ASSERT_NO_THROW(map.Build(grid, mesh, phantom.dual->GetMultiThreader()));
  const auto & element = map.GetElements();
  const auto & weights = map.GetWeights();
  ASSERT_EQ(element.size(), grid.numberOfPixels);
  double worstPosition = 0.0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    ASSERT_GE(element[p], 0);
    ASSERT_LT(static_cast<size_t>(element[p]), mesh.elements.size());
    double sum = 0.0, x[3] = { 0.0, 0.0, 0.0 };
    for (unsigned int v = 0; v < 4; ++v)
    {
      const double w = weights[4 * p + v];
      ASSERT_GE(w, 0.0);
      ASSERT_LE(w, 1.0);
      sum += w;
      for (unsigned int k = 0; k < 3; ++k)
      {
        x[k] += w * mesh.nodes[3 * mesh.elements[element[p]][v] + k];
      }
    }
    EXPECT_NEAR(sum, 1.0, 1e-6);
    const auto idx = grid.Index(p);
    for (unsigned int k = 0; k < 3; ++k)
    {
      worstPosition = std::max(worstPosition, std::abs(x[k] - idx[k] * grid.spacing[k]) / grid.spacing[k]);
    }
  }
  EXPECT_LT(worstPosition, 1e-4) << "barycentric weights do not reproduce the voxel positions (voxels)";
}

TEST(DualMeshFilter3D, CornersEdgesAndFacesCarryTheFixedNodes)
{
  const auto & phantom = Phantom();
  const auto   grid = phantom.GetGrid();
  const auto & mesh = phantom.GetMesh();
  EXPECT_TRUE(itk::dmr::test::FixedNodesAreTheBorderNodes<3>(grid, mesh));
  const auto fixedCount = std::count(mesh.fixed.begin(), mesh.fixed.end(), uint8_t{ 1 });
  EXPECT_EQ(static_cast<size_t>(fixedCount), phantom.dual->GetNumberOfBoundaryNodes());
  EXPECT_GT(mesh.NumberOfNodes() - static_cast<size_t>(fixedCount), 0u) << "no free node";
  // every box edge line carries nodes between its corners (edge snapping), every face nodes inside it
  int nodesOnEdge[12] = {}, nodesOnFace[6] = {};
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    const int faces = ExactFaces(grid, mesh, i);
    ASSERT_GE(faces, 0);
    const int count = __builtin_popcount(static_cast<unsigned int>(faces));
    if (count == 1)
    {
      ++nodesOnFace[__builtin_ctz(static_cast<unsigned int>(faces))];
    }
    else if (count == 2)
    {
      for (unsigned int a = 0; a < 3; ++a)
      {
        const unsigned int b = (a + 1) % 3, c = (a + 2) % 3;
        const int          sb = faces >> (2 * b) & 3, sc = faces >> (2 * c) & 3;
        if ((faces >> (2 * a) & 3) == 0 && sb && sc)
        {
          ++nodesOnEdge[4 * a + 2 * (sb >> 1) + (sc >> 1)];
        }
      }
    }
  }
  for (int e = 0; e < 12; ++e)
  {
    EXPECT_GT(nodesOnEdge[e], 0) << "box edge " << e << " has no node between its corners";
  }
  for (int f = 0; f < 6; ++f)
  {
    EXPECT_GT(nodesOnFace[f], 0) << "box face " << f << " has no node inside it";
  }
}

TEST(DualMeshFilter3D, InnerCellNodesAreTheSites)
{
  const auto &         phantom = Phantom();
  const auto           grid = phantom.GetGrid();
  const auto &         mesh = phantom.GetMesh();
  const auto *         labels = phantom.cvt->GetOutput()->GetBufferPointer();
  const auto &         centroids = phantom.cvt->GetCore().GetCentroids();
  const size_t         cells = centroids.size() / 3;
  std::vector<uint8_t> touchesBorder(cells, 0);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    if (grid.OnBorder(grid.Index(p)))
    {
      touchesBorder[labels[p]] = 1;
    }
  }
  size_t inner = 0;
  for (size_t c = 0; c < cells; ++c)
  {
    if (!touchesBorder[c])
    {
      ++inner;
      EXPECT_TRUE(HasNodeAt(mesh, &centroids[3 * c], 1e-6)) << "cell " << c;
    }
  }
  EXPECT_GT(inner, 20u) << "the phantom has few inner cells: the test exercised little";
  // the Delaunay tetrahedralization holds most of the CVT adjacency between inner cells
  const auto adjacent = phantom.dual->GetNumberOfInnerAdjacencyEdges();
  const auto missing = phantom.dual->GetNumberOfMissingAdjacencyEdges();
  EXPECT_GT(adjacent, inner);
  EXPECT_LT(missing, adjacent / 5) << missing << " of " << adjacent << " inner adjacency edges are not mesh edges";
  RecordProperty("InnerAdjacencyEdges", static_cast<int>(adjacent));
  RecordProperty("MissingAdjacencyEdges", static_cast<int>(missing));
}

TEST(DualMeshFilter3D, OutputMeshIsInPhysicalSpace)
{
  const auto & phantom = Phantom();
  const auto * labels = phantom.cvt->GetOutput();
  const auto & mesh = phantom.GetMesh();
  const auto * output = phantom.dual->GetOutput();
  ASSERT_EQ(output->GetNumberOfPoints(), mesh.NumberOfNodes());
  ASSERT_EQ(output->GetNumberOfCells(), mesh.elements.size());
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    LabelImageType::PointType expected;
    labels->TransformContinuousIndexToPhysicalPoint(GridToContinuousIndex(labels, &mesh.nodes[3 * i]), expected);
    const auto point = output->GetPoint(i);
    for (unsigned int k = 0; k < 3; ++k)
    {
      EXPECT_NEAR(point[k], expected[k], 1e-9);
    }
    double fixed = -1.0;
    ASSERT_TRUE(output->GetPointData(i, &fixed));
    EXPECT_EQ(fixed, static_cast<double>(mesh.fixed[i]));
  }
  // the 8 corner voxels are mesh points, at their physical positions
  for (unsigned int corner = 0; corner < 8; ++corner)
  {
    LabelImageType::IndexType index;
    for (unsigned int k = 0; k < 3; ++k)
    {
      index[k] = (corner >> k) & 1u ? static_cast<long>(labels->GetLargestPossibleRegion().GetSize()[k]) - 1 : 0;
    }
    LabelImageType::PointType point;
    labels->TransformIndexToPhysicalPoint(index, point);
    bool found = false;
    for (auto it = output->GetPoints()->Begin(); it != output->GetPoints()->End(); ++it)
    {
      found = found || it.Value().EuclideanDistanceTo(point) < 1e-9;
    }
    EXPECT_TRUE(found) << "no mesh point at the corner voxel " << index << " (" << point << ")";
  }
  // cells are tetrahedra with the elements' point ids, positively oriented in the grid frame; in physical space
  // their volume is the same up to the sign of det(Direction)
  size_t e = 0;
  double physicalVolume = 0.0;
  for (auto c = output->GetCells()->Begin(); c != output->GetCells()->End(); ++c, ++e)
  {
    ASSERT_EQ(c.Value()->GetType(), itk::CellGeometryEnum::TETRAHEDRON_CELL);
    ASSERT_EQ(c.Value()->GetNumberOfPoints(), 4u);
    unsigned int                    k = 0;
    FilterType::MeshType::PointType p[4];
    for (auto id = c.Value()->PointIdsBegin(); id != c.Value()->PointIdsEnd(); ++id, ++k)
    {
      EXPECT_EQ(*id, static_cast<itk::IdentifierType>(mesh.elements[e][k]));
      p[k] = output->GetPoint(*id);
    }
    const auto a = p[1] - p[0], b = p[2] - p[0], d = p[3] - p[0];
    physicalVolume +=
      (a[0] * (b[1] * d[2] - b[2] * d[1]) - a[1] * (b[0] * d[2] - b[2] * d[0]) + a[2] * (b[0] * d[1] - b[1] * d[0])) /
      6.0;
  }
  const auto   grid = phantom.GetGrid();
  const auto   hi = BoxHigh(grid);
  const double det = vnl_determinant(labels->GetDirection().GetVnlMatrix());
  EXPECT_NEAR(physicalVolume, det * hi[0] * hi[1] * hi[2], 1e-9 * hi[0] * hi[1] * hi[2]);
  // back to the grid frame
  EXPECT_TRUE(itk::dmr::test::ItkMeshConvertsBackTo<3>(output, labels, mesh));
}

TEST(DualMeshFilter3D, IsDeterministic)
{
  const auto & phantom = Phantom();
  for (int threads : { 1, 2, 3 })
  {
    auto again = FilterType::New();
    again->SetInput(phantom.cvt->GetOutput());
    again->SetSites(phantom.cvt->GetSites());
    again->SetNumberOfWorkUnits(threads);
    again->Update();
    EXPECT_EQ(again->GetSimplexMesh().nodes, phantom.GetMesh().nodes);
    EXPECT_EQ(again->GetSimplexMesh().elements, phantom.GetMesh().elements);
    EXPECT_EQ(again->GetNumberOfMissingAdjacencyEdges(), phantom.dual->GetNumberOfMissingAdjacencyEdges());
  }
}

TEST(DualMeshFilter3D, WorksWithoutSitesAndWithoutEdgeSnapping)
{
  const auto & phantom = Phantom();
  const auto   grid = phantom.GetGrid();
  auto         noSites = FilterType::New();
  noSites->SetInput(phantom.cvt->GetOutput());
  noSites->Update();
  EXPECT_TRUE(IsValidDualMesh(grid, noSites->GetSimplexMesh()));
  EXPECT_TRUE(IsConforming(grid, noSites->GetSimplexMesh()));
  auto noEdges = FilterType::New();
  noEdges->SetInput(phantom.cvt->GetOutput());
  noEdges->SetSites(phantom.cvt->GetSites());
  noEdges->SnapToBoxEdgesOff();
  noEdges->Update();
  EXPECT_TRUE(IsValidDualMesh(grid, noEdges->GetSimplexMesh()));
  EXPECT_TRUE(IsConforming(grid, noEdges->GetSimplexMesh()));
  EXPECT_EQ(noEdges->GetSimplexMesh().NumberOfNodes(), phantom.GetMesh().NumberOfNodes());
  size_t strictlyInside = 0;
  EXPECT_TRUE(EveryVoxelIsInExactlyOneTetrahedron(grid, noEdges->GetSimplexMesh(), strictlyInside));
}

TEST(DualMeshFilter3D, TinyImageWithEightCells)
{
  // 5 x 5 x 5 voxels, 8 cells from a real CVT: every cell holds a corner, so the mesh is the box split by the corners
  using ImageType = DualMeshPhantom3D::ImageType;
  ImageType::SpacingType spacing;
  spacing[0] = 0.7;
  spacing[1] = 1.3;
  spacing[2] = 2.0;
  ImageType::PointType origin;
  origin.Fill(4.0);
  DualMeshPhantom3D phantom(
    itk::dmr::test::RidgeDensity3D(ImageType::SizeType{ { 5, 5, 5 } },
                                   spacing,
                                   origin,
                                   itk::dmr::test::RotationDirection3D<ImageType>({ 0.0, 0.0, 1.0 }, 0.4)),
    8);
  const auto   grid = phantom.GetGrid();
  const auto & mesh = phantom.GetMesh();
  EXPECT_TRUE(IsValidDualMesh(grid, mesh));
  EXPECT_TRUE(IsConforming(grid, mesh));
  size_t strictlyInside = 0;
  EXPECT_TRUE(EveryVoxelIsInExactlyOneTetrahedron(grid, mesh, strictlyInside));
  itk::dmr::BarycentricMap<3> map;
  EXPECT_NO_THROW(map.Build(grid, mesh, nullptr));
}

TEST(DualMeshFilter3D, OneCellGivesTheEightCorners)
{
  auto labels =
    MakeLabels(LabelImageType::SizeType{ { 6, 5, 4 } }, [](const LabelImageType::IndexType &) { return 0; });
  auto filter = FilterType::New();
  filter->SetInput(labels);
  ASSERT_NO_THROW(filter->Update());
  const auto & mesh = filter->GetSimplexMesh();
  const auto   grid = Grid3D::FromImage(labels.GetPointer());
  EXPECT_EQ(mesh.NumberOfNodes(), 8u);
  EXPECT_TRUE(IsValidDualMesh(grid, mesh));
  EXPECT_TRUE(IsConforming(grid, mesh));
  EXPECT_EQ(filter->GetNumberOfBoundaryNodes(), 8u);
  EXPECT_EQ(filter->GetNumberOfInnerAdjacencyEdges(), 0u);
}

TEST(DualMeshFilter3D, SmallAndDegenerateInputs)
{
  // 2 x 2 x 2 voxels, one cell each: only corners
  auto eight = MakeLabels(LabelImageType::SizeType{ { 2, 2, 2 } }, [](const LabelImageType::IndexType & i) {
    return static_cast<int32_t>(i[0] + 2 * i[1] + 4 * i[2]);
  });
  auto filter = FilterType::New();
  filter->SetInput(eight);
  ASSERT_NO_THROW(filter->Update());
  EXPECT_EQ(filter->GetSimplexMesh().NumberOfNodes(), 8u);
  EXPECT_TRUE(IsValidDualMesh(Grid3D::FromImage(eight.GetPointer()), filter->GetSimplexMesh()));

  // two slabs: each cell holds four corners
  auto slabs = MakeLabels(LabelImageType::SizeType{ { 7, 3, 9 } },
                          [](const LabelImageType::IndexType & i) { return static_cast<int32_t>(i[2] >= 4); });
  filter->SetInput(slabs);
  ASSERT_NO_THROW(filter->Update());
  EXPECT_EQ(filter->GetSimplexMesh().NumberOfNodes(), 8u);
  EXPECT_TRUE(IsValidDualMesh(Grid3D::FromImage(slabs.GetPointer()), filter->GetSimplexMesh()));

  // one inner cell inside one outer cell (a cube in a cube): corners plus one inner node
  auto nested = MakeLabels(LabelImageType::SizeType{ { 6, 6, 6 } }, [](const LabelImageType::IndexType & i) {
    return static_cast<int32_t>(i[0] > 0 && i[0] < 5 && i[1] > 0 && i[1] < 5 && i[2] > 0 && i[2] < 5);
  });
  filter->SetInput(nested);
  ASSERT_NO_THROW(filter->Update());
  EXPECT_EQ(filter->GetSimplexMesh().NumberOfNodes(), 9u);
  EXPECT_TRUE(IsValidDualMesh(Grid3D::FromImage(nested.GetPointer()), filter->GetSimplexMesh()));

  // a flat image has no volume to mesh
  auto flat = MakeLabels(LabelImageType::SizeType{ { 4, 4, 1 } }, [](const LabelImageType::IndexType &) { return 0; });
  filter->SetInput(flat);
  EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  // labels with a gap
  auto gap = MakeLabels(LabelImageType::SizeType{ { 4, 4, 4 } },
                        [](const LabelImageType::IndexType & i) { return static_cast<int32_t>(i[0] < 2 ? 0 : 2); });
  filter->SetInput(gap);
  EXPECT_THROW(filter->Update(), itk::ExceptionObject);
}

TEST(DualMeshFilter3D, SymmetricCellsAreNudgedOffFlatTetrahedra)
{
  // 4 x 4 x 4 equal blocks: the inner block centres form a lattice, 8 at a time on a sphere and 4 at a time on a
  // circle. Sites off the lattice by round-off (1e-12 voxel, as a rotated physical round trip gives) make the exact
  // degeneracies near-degenerate: the Delaunay tetrahedralization then has flat tetrahedra unless nodes are nudged.
  auto labels = MakeLabels(LabelImageType::SizeType{ { 24, 24, 24 } }, [](const LabelImageType::IndexType & i) {
    return static_cast<int32_t>(i[0] / 6 + 4 * (i[1] / 6) + 16 * (i[2] / 6));
  });
  labels->SetDirection(itk::dmr::test::RotationDirection3D<LabelImageType>({ 3.0, -1.0, 2.0 }, 1.1));
  LabelImageType::PointType origin;
  origin[0] = 13.1;
  origin[1] = -7.3;
  origin[2] = 0.9;
  labels->SetOrigin(origin);
  auto sites = FilterType::SitesType::New();
  for (int32_t c = 0; c < 64; ++c)
  {
    itk::ContinuousIndex<double, 3> ci;
    ci[0] = 6.0 * (c % 4) + 2.5 + 1e-12 * ((c * 7) % 5 - 2);
    ci[1] = 6.0 * ((c / 4) % 4) + 2.5 + 1e-12 * ((c * 3) % 7 - 3);
    ci[2] = 6.0 * (c / 16) + 2.5 + 1e-12 * ((c * 5) % 3 - 1);
    FilterType::SitesType::PointType point;
    labels->TransformContinuousIndexToPhysicalPoint(ci, point);
    sites->SetPoint(c, point);
  }
  auto filter = FilterType::New();
  filter->SetInput(labels);
  filter->SetSites(sites);
  ASSERT_NO_THROW(filter->Update());
  const auto   grid = Grid3D::FromImage(labels.GetPointer());
  const auto & mesh = filter->GetSimplexMesh();
  EXPECT_TRUE(IsValidDualMesh(grid, mesh));
  EXPECT_TRUE(IsConforming(grid, mesh));
  size_t strictlyInside = 0;
  EXPECT_TRUE(EveryVoxelIsInExactlyOneTetrahedron(grid, mesh, strictlyInside));
  EXPECT_GT(filter->GetNumberOfPerturbedNodes(), 0u) << "the input was not near-degenerate: the test exercised nothing";
  RecordProperty("PerturbedNodes", static_cast<int>(filter->GetNumberOfPerturbedNodes()));
  // the 8 inner cells (blocks 1..2 along every axis) are the only nodes that are not snapped: they moved by less than
  // a quarter voxel, if at all
  for (int32_t c = 0; c < 64; ++c)
  {
    const int bx = c % 4, by = (c / 4) % 4, bz = c / 16;
    if (bx % 3 == 0 || by % 3 == 0 || bz % 3 == 0)
    {
      continue;
    }
    const double site[3] = { (6.0 * bx + 2.5) * 0.9, (6.0 * by + 2.5) * 1.1, (6.0 * bz + 2.5) * 1.7 };
    EXPECT_TRUE(HasNodeAt(mesh, site, 0.25 * 0.9 + 1e-9)) << "block " << c;
  }
}
} // namespace

// The density -> CVT -> dual mesh pipeline on the same volume indexed from another start (as CropImageFilter leaves
// it): the same labels, the same mesh points in physical space.
TEST(DualMeshFilter3D, RegionThatDoesNotStartAtZeroGivesTheSameMesh)
{
  using ImageType = itk::Image<float, 3>;
  const auto & reference = Phantom();
  auto         density = ImageType::New();
  density->Graft(reference.density);
  ImageType::IndexType start;
  start[0] = 5;
  start[1] = -2;
  start[2] = 3;
  itk::dmr::test::ShiftRegionStart(density.GetPointer(), start);
  const itk::dmr::test::DualMeshPhantom3D shifted(density, 200);
  const auto *                            a = reference.cvt->GetOutput();
  const auto *                            b = shifted.cvt->GetOutput();
  ASSERT_EQ(b->GetLargestPossibleRegion(), density->GetLargestPossibleRegion());
  EXPECT_TRUE(std::equal(a->GetBufferPointer(),
                         a->GetBufferPointer() + a->GetLargestPossibleRegion().GetNumberOfPixels(),
                         b->GetBufferPointer()));
  const auto * meshA = reference.dual->GetOutput();
  const auto * meshB = shifted.dual->GetOutput();
  ASSERT_EQ(meshB->GetNumberOfPoints(), meshA->GetNumberOfPoints());
  ASSERT_EQ(meshB->GetNumberOfCells(), meshA->GetNumberOfCells());
  double largest = 0.0;
  for (itk::IdentifierType i = 0; i < meshA->GetNumberOfPoints(); ++i)
  {
    largest = std::max(largest, meshA->GetPoint(i).EuclideanDistanceTo(meshB->GetPoint(i)));
  }
  EXPECT_LT(largest, 1e-9);
}
