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
#include "dmrSimplexMesh.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"

#include <map>

namespace
{
TEST(MakeRegularMesh, TwoDimensionalMeshTilesTheBoxWithBorderNodesFixed)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 24, 20 }, std::array<double, 2>{ 1.0, 1.5 });
  const auto              mesh = itk::dmr::MakeRegularMesh<2>(grid, { 6, 5 });
  EXPECT_EQ(mesh.NumberOfNodes(), 30u);
  EXPECT_EQ(mesh.elements.size(), 2u * 5u * 4u);
  EXPECT_TRUE(itk::dmr::test::MeshTilesTheBox<2>(grid, mesh));
  EXPECT_TRUE(itk::dmr::test::FixedNodesAreTheBorderNodes<2>(grid, mesh));
  EXPECT_EQ(std::count(mesh.fixed.begin(), mesh.fixed.end(), uint8_t{ 0 }), 4 * 3);
}

TEST(MakeRegularMesh, ThreeDimensionalMeshIsAConformingTilingOfTheBox)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 10, 9, 8 }, std::array<double, 3>{ 1.0, 1.2, 0.9 });
  const auto              mesh = itk::dmr::MakeRegularMesh<3>(grid, { 5, 4, 4 });
  EXPECT_EQ(mesh.NumberOfNodes(), 80u);
  EXPECT_EQ(mesh.elements.size(), 6u * 4u * 3u * 3u);
  EXPECT_TRUE(itk::dmr::test::MeshTilesTheBox<3>(grid, mesh));
  EXPECT_TRUE(itk::dmr::test::FixedNodesAreTheBorderNodes<3>(grid, mesh));
  // conforming: every triangular face is shared by at most two tetrahedra
  std::map<std::array<int32_t, 3>, int> faces;
  for (const auto & e : mesh.elements)
  {
    for (unsigned int skip = 0; skip < 4; ++skip)
    {
      std::array<int32_t, 3> f;
      unsigned int           k = 0;
      for (unsigned int v = 0; v < 4; ++v)
      {
        if (v != skip)
        {
          f[k++] = e[v];
        }
      }
      std::sort(f.begin(), f.end());
      EXPECT_LE(++faces[f], 2);
    }
  }
  // boundary faces: 2 per boundary square, 2 (4x3 + 4x3 + 3x3) squares
  const auto single = std::count_if(faces.begin(), faces.end(), [](const auto & f) { return f.second == 1; });
  EXPECT_EQ(single, 2 * 2 * (4 * 3 + 4 * 3 + 3 * 3));
}

TEST(MakeRegularMesh, FewerThanTwoNodesPerAxisThrows)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 24, 20 }, std::array<double, 2>{ 1.0, 1.0 });
  EXPECT_THROW(itk::dmr::MakeRegularMesh<2>(grid, { 1, 5 }), itk::ExceptionObject);
}

TEST(SimplexMesh, OrientPositivelyFlipsNegativeAndRejectsDegenerateElements)
{
  itk::dmr::SimplexMesh<2> mesh;
  mesh.nodes = { 0, 0, 2, 0, 0, 3, 4, 0 };
  mesh.elements = { { 0, 2, 1 } };
  EXPECT_DOUBLE_EQ(mesh.SignedMeasure(0), -3.0);
  mesh.OrientPositively();
  EXPECT_DOUBLE_EQ(mesh.SignedMeasure(0), 3.0);
  mesh.elements.push_back({ 0, 1, 3 }); // collinear
  EXPECT_THROW(mesh.OrientPositively(), itk::ExceptionObject);

  itk::dmr::SimplexMesh<3> tet;
  tet.nodes = { 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3 };
  tet.elements = { { 0, 2, 1, 3 } };
  EXPECT_DOUBLE_EQ(tet.SignedMeasure(0), -1.0);
  tet.OrientPositively();
  EXPECT_DOUBLE_EQ(tet.SignedMeasure(0), 1.0);
}
} // namespace
