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
#include "dmrDualMeshPhantom.h"
#include "dmrObjectChecks.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"

#include <cmath>
#include <map>

namespace
{
using itk::dmr::test::DualMeshPhantom;
using itk::dmr::test::MakeDualMeshPhantom;
using LabelImageType = DualMeshPhantom::CVTFilterType::LabelImageType;
using FilterType = DualMeshPhantom::DualMeshFilterType;

bool
HasNodeAt(const itk::dmr::SimplexMesh<2> & mesh, double x, double y, double tolerance)
{
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    if (std::abs(mesh.nodes[2 * i] - x) <= tolerance && std::abs(mesh.nodes[2 * i + 1] - y) <= tolerance)
    {
      return true;
    }
  }
  return false;
}

TEST(DualMeshFilter, BasicObjectMethodsAndPrint)
{
  auto filter = FilterType::New();
  EXPECT_TRUE(itk::dmr::test::BasicObjectMethods(filter.GetPointer(), "DualMeshFilter", "ImageToMeshFilter"));
  EXPECT_TRUE(itk::dmr::test::PrintMentions(
    filter.GetPointer(),
    { "NumberOfNodes", "NumberOfElements", "NumberOfBoundaryNodes", "NumberOfSkippedConstraints" }));
  auto sites = FilterType::SitesType::New();
  filter->SetSites(sites);
  EXPECT_EQ(filter->GetSites(), sites.GetPointer());
}

TEST(DualMeshFilter, ElementsArePositiveAndTileTheImageBox)
{
  const auto   phantom = MakeDualMeshPhantom();
  const auto   grid = phantom.GetGrid();
  const auto & mesh = phantom.GetMesh();
  ASSERT_GT(mesh.elements.size(), 0u);
  EXPECT_TRUE(itk::dmr::test::MeshTilesTheBox<2>(grid, mesh));
  // every element refers to existing nodes, and every node is used
  std::vector<int> used(mesh.NumberOfNodes(), 0);
  for (const auto & e : mesh.elements)
  {
    for (int32_t v : e)
    {
      ASSERT_GE(v, 0);
      ASSERT_LT(static_cast<size_t>(v), mesh.NumberOfNodes());
      used[v] = 1;
    }
  }
  EXPECT_EQ(std::count(used.begin(), used.end(), 1), static_cast<long>(mesh.NumberOfNodes()));
}

TEST(DualMeshFilter, TriangulationIsConforming)
{
  // positive areas summing to the box area could still overlap and leave gaps; in a conforming triangulation every
  // edge is used by one triangle (box border) or by two with opposite orientations (interior)
  const auto                                 phantom = MakeDualMeshPhantom();
  const auto                                 grid = phantom.GetGrid();
  const auto &                               mesh = phantom.GetMesh();
  std::map<std::pair<int32_t, int32_t>, int> directed;
  for (const auto & e : mesh.elements)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      const auto key = std::make_pair(e[k], e[(k + 1) % 3]);
      EXPECT_EQ(directed[key]++, 0) << "directed edge " << key.first << "->" << key.second << " used twice";
    }
  }
  const double hx = (grid.size[0] - 1) * grid.spacing[0], hy = (grid.size[1] - 1) * grid.spacing[1];
  auto         onSameBorderSide = [&](int32_t a, int32_t b) {
    const double ax = mesh.nodes[2 * a], ay = mesh.nodes[2 * a + 1], bx = mesh.nodes[2 * b], by = mesh.nodes[2 * b + 1];
    const double t = 1e-9;
    return (std::abs(ax) < t && std::abs(bx) < t) || (std::abs(ax - hx) < t && std::abs(bx - hx) < t) ||
           (std::abs(ay) < t && std::abs(by) < t) || (std::abs(ay - hy) < t && std::abs(by - hy) < t);
  };
  for (const auto & entry : directed)
  {
    const bool hasTwin = directed.count({ entry.first.second, entry.first.first }) > 0;
    if (!hasTwin)
    {
      EXPECT_TRUE(onSameBorderSide(entry.first.first, entry.first.second))
        << "edge " << entry.first.first << "-" << entry.first.second << " has one triangle but is not on the border";
    }
  }
  // Euler's formula for a triangulated disc: V - E + F = 1
  const long borderEdges = std::count_if(directed.begin(), directed.end(), [&](const auto & entry) {
    return directed.count({ entry.first.second, entry.first.first }) == 0;
  });
  const long edges = (static_cast<long>(directed.size()) - borderEdges) / 2 + borderEdges;
  EXPECT_EQ(static_cast<long>(mesh.NumberOfNodes()) - edges + static_cast<long>(mesh.elements.size()), 1);
}

TEST(DualMeshFilter, CornersAreNodesAndFixedNodesLieOnTheBorder)
{
  const auto   phantom = MakeDualMeshPhantom();
  const auto   grid = phantom.GetGrid();
  const auto & mesh = phantom.GetMesh();
  const double hx = (grid.size[0] - 1) * grid.spacing[0], hy = (grid.size[1] - 1) * grid.spacing[1];
  EXPECT_TRUE(HasNodeAt(mesh, 0.0, 0.0, 1e-12));
  EXPECT_TRUE(HasNodeAt(mesh, hx, 0.0, 1e-12));
  EXPECT_TRUE(HasNodeAt(mesh, 0.0, hy, 1e-12));
  EXPECT_TRUE(HasNodeAt(mesh, hx, hy, 1e-12));
  EXPECT_TRUE(itk::dmr::test::FixedNodesAreTheBorderNodes<2>(grid, mesh));
  const auto fixedCount = std::count(mesh.fixed.begin(), mesh.fixed.end(), uint8_t{ 1 });
  EXPECT_EQ(static_cast<size_t>(fixedCount), phantom.dual->GetNumberOfBoundaryNodes());
  EXPECT_GE(fixedCount, 4);
  EXPECT_GT(mesh.NumberOfNodes() - static_cast<size_t>(fixedCount), 0u) << "no free node";
}

TEST(DualMeshFilter, InnerCellNodesAreTheSites)
{
  // an inner cell (no pixel on the border) is represented by its site: the CVT centroid in the grid frame, which
  // reaches the dual mesh through physical space (rotated, shifted, anisotropic image)
  const auto           phantom = MakeDualMeshPhantom();
  const auto           grid = phantom.GetGrid();
  const auto &         mesh = phantom.GetMesh();
  const auto *         labels = phantom.cvt->GetOutput()->GetBufferPointer();
  const auto &         centroids = phantom.cvt->GetCore().GetCentroids();
  std::vector<uint8_t> touchesBorder(20, 0);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    if (grid.OnBorder(grid.Index(p)))
    {
      touchesBorder[labels[p]] = 1;
    }
  }
  size_t inner = 0;
  for (size_t c = 0; c < 20; ++c)
  {
    if (!touchesBorder[c])
    {
      ++inner;
      // the sites travel as float physical coordinates (PointSet default traits): 1e-4 mm
      EXPECT_TRUE(HasNodeAt(mesh, centroids[2 * c], centroids[2 * c + 1], 1e-4)) << "cell " << c;
    }
  }
  EXPECT_GT(inner, 0u) << "the phantom has no inner cell: the test exercised nothing";
  EXPECT_GE(mesh.NumberOfNodes(), 20u);
}

TEST(DualMeshFilter, OutputMeshIsInPhysicalSpace)
{
  const auto   phantom = MakeDualMeshPhantom();
  const auto * labels = phantom.cvt->GetOutput();
  const auto & mesh = phantom.GetMesh();
  const auto * output = phantom.dual->GetOutput();
  ASSERT_EQ(output->GetNumberOfPoints(), mesh.NumberOfNodes());
  ASSERT_EQ(output->GetNumberOfCells(), mesh.elements.size());
  // every point is its grid-frame node mapped through the label image's geometry
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    itk::ContinuousIndex<double, 2> ci;
    ci[0] = mesh.nodes[2 * i] / labels->GetSpacing()[0];
    ci[1] = mesh.nodes[2 * i + 1] / labels->GetSpacing()[1];
    LabelImageType::PointType expected;
    labels->TransformContinuousIndexToPhysicalPoint(ci, expected);
    const auto point = output->GetPoint(i);
    EXPECT_NEAR(point[0], expected[0], 1e-9);
    EXPECT_NEAR(point[1], expected[1], 1e-9);
    double fixed = -1.0;
    ASSERT_TRUE(output->GetPointData(i, &fixed));
    EXPECT_EQ(fixed, static_cast<double>(mesh.fixed[i]));
  }
  // the far corner pixel (63, 47) is a mesh point, at the physical point of that pixel
  LabelImageType::PointType corner;
  labels->TransformIndexToPhysicalPoint(LabelImageType::IndexType{ { 63, 47 } }, corner);
  bool found = false;
  for (auto it = output->GetPoints()->Begin(); it != output->GetPoints()->End(); ++it)
  {
    found = found || it.Value().EuclideanDistanceTo(corner) < 1e-9;
  }
  EXPECT_TRUE(found) << "no mesh point at the physical position of the corner pixel " << corner;
  // cells are triangles with the elements' point ids
  size_t e = 0;
  for (auto c = output->GetCells()->Begin(); c != output->GetCells()->End(); ++c, ++e)
  {
    ASSERT_EQ(c.Value()->GetNumberOfPoints(), 3u);
    unsigned int k = 0;
    for (auto p = c.Value()->PointIdsBegin(); p != c.Value()->PointIdsEnd(); ++p, ++k)
    {
      EXPECT_EQ(*p, static_cast<itk::IdentifierType>(mesh.elements[e][k]));
    }
  }
  // back to the grid frame: FromItkMesh(ToItkMesh(mesh)) is the mesh
  EXPECT_TRUE(itk::dmr::test::ItkMeshConvertsBackTo<2>(output, labels, mesh));
}

TEST(DualMeshFilter, WorksWithoutSitesAndWithUnitGeometry)
{
  using ImageType = DualMeshPhantom::ImageType;
  ImageType::SpacingType spacing;
  spacing.Fill(1.0);
  ImageType::PointType origin;
  origin.Fill(0.0);
  ImageType::DirectionType direction;
  direction.SetIdentity();
  DualMeshPhantom phantom(
    itk::dmr::test::SmoothDensity2D(ImageType::SizeType{ { 40, 36 } }, spacing, origin, direction), 16);
  auto noSites = FilterType::New();
  noSites->SetInput(phantom.cvt->GetOutput());
  noSites->Update();
  EXPECT_TRUE(itk::dmr::test::MeshTilesTheBox<2>(phantom.GetGrid(), noSites->GetSimplexMesh()));
  EXPECT_TRUE(itk::dmr::test::FixedNodesAreTheBorderNodes<2>(phantom.GetGrid(), noSites->GetSimplexMesh()));
  EXPECT_TRUE(itk::dmr::test::MeshTilesTheBox<2>(phantom.GetGrid(), phantom.GetMesh()));
}

TEST(DualMeshFilter, BadLabelsThrow)
{
  auto labels = LabelImageType::New();
  labels->SetRegions(LabelImageType::SizeType{ { 8, 6 } });
  labels->Allocate();
  for (size_t p = 0; p < 48; ++p)
  {
    labels->GetBufferPointer()[p] = (p % 8) < 4 ? 0 : 2; // label 1 missing
  }
  auto filter = FilterType::New();
  filter->SetInput(labels);
  EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  labels->GetBufferPointer()[10] = -1;
  labels->Modified();
  EXPECT_THROW(filter->Update(), itk::ExceptionObject);

  using Label3DType = itk::Image<int32_t, 3>;
  auto labels3D = Label3DType::New();
  labels3D->SetRegions(Label3DType::SizeType{ { 4, 4, 1 } });
  labels3D->Allocate(true);
  auto filter3D = itk::DualMeshFilter<Label3DType>::New();
  filter3D->SetInput(labels3D);
  EXPECT_THROW(filter3D->Update(), itk::ExceptionObject); // a flat 3D image has no volume to tetrahedralize

  // a sheared direction: the mesh is built in the grid frame scaled by the spacing, which is the physical frame only
  // for a rotation or reflection
  for (size_t p = 0; p < 48; ++p)
  {
    labels->GetBufferPointer()[p] = (p % 8) < 4 ? 0 : 1;
  }
  LabelImageType::DirectionType sheared;
  sheared.SetIdentity();
  sheared[0][1] = 0.4;
  labels->SetDirection(sheared);
  labels->Modified();
  EXPECT_TRUE(
    itk::dmr::test::UpdateThrowsMentioning(filter, { "the label image's direction matrix is not orthonormal" }));
  sheared.SetIdentity();
  labels->SetDirection(sheared);
  labels->Modified();
  EXPECT_NO_THROW(filter->Update());

  // nodes in physical coordinates that double precision cannot tell apart (an origin of 1e16 mm with 1 mm pixels), or
  // not numbers at all
  for (const double far : { 1e16, std::nan("") })
  {
    LabelImageType::PointType origin;
    origin[0] = far;
    origin[1] = 0.0;
    labels->SetOrigin(origin);
    labels->Modified();
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      filter,
      { std::isnan(far) ? "the label image's physical coordinates are not finite numbers"
                        : "the label image's physical coordinates reach 1e+16 mm" }))
      << far;
  }
}
/** Nodes on the box border, checked for exact placement and for sliver elements. */
::testing::AssertionResult
BorderNodesAreExactAndElementsAreNotSlivers(const itk::dmr::Grid<2> & grid, const itk::dmr::SimplexMesh<2> & mesh)
{
  const double hi[2] = { (grid.size[0] - 1) * grid.spacing[0], (grid.size[1] - 1) * grid.spacing[1] };
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    for (unsigned int k = 0; k < 2; ++k)
    {
      const double x = mesh.nodes[2 * i + k];
      const double tol = 1e-6 * grid.spacing[k];
      if ((std::abs(x) <= tol && x != 0.0) || (std::abs(x - hi[k]) <= tol && x != hi[k]))
      {
        return ::testing::AssertionFailure() << "node " << i << " is " << (x - (std::abs(x) <= tol ? 0.0 : hi[k]))
                                             << " mm off the border along axis " << k;
      }
    }
  }
  const double box = hi[0] * hi[1];
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    if (mesh.SignedMeasure(e) < 1e-6 * box / static_cast<double>(mesh.elements.size()))
    {
      return ::testing::AssertionFailure() << "element " << e << " is a sliver: area " << mesh.SignedMeasure(e);
    }
  }
  return ::testing::AssertionSuccess();
}

TEST(DualMeshFilter, BorderNodesLieExactlyOnTheBoxWithUnitSpacing)
{
  const auto phantom = itk::dmr::test::MakeUnitSpacingDualMeshPhantom();
  EXPECT_TRUE(BorderNodesAreExactAndElementsAreNotSlivers(phantom.GetGrid(), phantom.GetMesh()));
}

// Regression test (a fixed bug): a boundary cell's node is the mean of
// its border pixels' positions (itkDualMeshFilter.hxx, sideSum / bestCount), which rounds off the border line for
// non-integer spacing (50.399999999999999 instead of 50.400000000000006). CGAL then sees the border nodes as not
// collinear and adds sliver triangles of area ~2e-13 spanning a whole side of the box.
TEST(DualMeshFilter, BorderNodesLieExactlyOnTheBox)
{
  const auto phantom = MakeDualMeshPhantom();
  EXPECT_TRUE(BorderNodesAreExactAndElementsAreNotSlivers(phantom.GetGrid(), phantom.GetMesh()));
}
} // namespace
