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
#include "dmrDelaunay2D.h"
#include "gtest/gtest.h"

#include <cmath>
#include <random>
#include <set>

namespace
{
using TriangleList = std::vector<std::array<int32_t, 3>>;

double
SignedArea(const std::vector<double> & xy, const std::array<int32_t, 3> & t)
{
  const double ax = xy[2 * t[0]], ay = xy[2 * t[0] + 1];
  return 0.5 * ((xy[2 * t[1]] - ax) * (xy[2 * t[2] + 1] - ay) - (xy[2 * t[2]] - ax) * (xy[2 * t[1] + 1] - ay));
}

bool
HasEdge(const TriangleList & triangles, int32_t a, int32_t b)
{
  for (const auto & t : triangles)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      if ((t[k] == a && t[(k + 1) % 3] == b) || (t[k] == b && t[(k + 1) % 3] == a))
      {
        return true;
      }
    }
  }
  return false;
}

TEST(ConstrainedDelaunay2D, SquareWithCentreGivesFourCounterClockwiseTriangles)
{
  const std::vector<double> xy{ 0, 0, 4, 0, 4, 3, 0, 3, 2, 1.5 };
  TriangleList              triangles;
  EXPECT_EQ(itk::dmr::ConstrainedDelaunay2D(xy, {}, triangles), 0u);
  ASSERT_EQ(triangles.size(), 4u);
  double area = 0.0;
  for (const auto & t : triangles)
  {
    EXPECT_GT(SignedArea(xy, t), 0.0);
    EXPECT_TRUE(std::find(t.begin(), t.end(), 4) != t.end()) << "every triangle uses the centre";
    area += SignedArea(xy, t);
  }
  EXPECT_NEAR(area, 12.0, 1e-12);
}

TEST(ConstrainedDelaunay2D, DuplicateNodesAreMergedIntoTheFirst)
{
  const std::vector<double> xy{ 0, 0, 4, 0, 4, 3, 0, 3, 2, 1.5, 2, 1.5 };
  TriangleList              triangles;
  itk::dmr::ConstrainedDelaunay2D(xy, {}, triangles);
  ASSERT_EQ(triangles.size(), 4u);
  for (const auto & t : triangles)
  {
    EXPECT_TRUE(std::find(t.begin(), t.end(), 5) == t.end()) << "the duplicate node 5 is used";
  }
}

TEST(ConstrainedDelaunay2D, CrossingConstraintIsSkippedAndTheFirstIsKept)
{
  // a unit square: Delaunay alone may pick either diagonal; the constraints decide
  const std::vector<double> xy{ 0, 0, 1, 0, 1, 1.0001, 0, 1 };
  for (int first = 0; first < 2; ++first)
  {
    const std::array<int32_t, 2>        d02{ 0, 2 }, d13{ 1, 3 };
    std::vector<std::array<int32_t, 2>> constraints =
      first == 0 ? std::vector<std::array<int32_t, 2>>{ d02, d13 } : std::vector<std::array<int32_t, 2>>{ d13, d02 };
    TriangleList triangles;
    EXPECT_EQ(itk::dmr::ConstrainedDelaunay2D(xy, constraints, triangles), 1u);
    ASSERT_EQ(triangles.size(), 2u);
    const auto & kept = constraints[0];
    const auto & skipped = constraints[1];
    EXPECT_TRUE(HasEdge(triangles, kept[0], kept[1]));
    EXPECT_FALSE(HasEdge(triangles, skipped[0], skipped[1]));
  }
}

TEST(ConstrainedDelaunay2D, RandomPointsGiveAnEmptyCircumcircleTriangulationOfTheBox)
{
  std::mt19937                           engine(42u);
  std::uniform_real_distribution<double> ux(0.0, 50.0), uy(0.0, 30.0);
  std::vector<double>                    xy{ 0, 0, 50, 0, 50, 30, 0, 30 };
  for (int i = 0; i < 60; ++i)
  {
    xy.push_back(ux(engine));
    xy.push_back(uy(engine));
  }
  TriangleList triangles;
  itk::dmr::ConstrainedDelaunay2D(xy, {}, triangles);
  const size_t n = xy.size() / 2;
  // Euler: a triangulation of n points with h = 4 on the hull has 2n - h - 2 triangles
  EXPECT_EQ(triangles.size(), 2 * n - 4 - 2);
  double area = 0.0;
  for (const auto & t : triangles)
  {
    const double a = SignedArea(xy, t);
    EXPECT_GT(a, 0.0);
    area += a;
    // circumcircle of t contains no other node (Delaunay)
    const double ax = xy[2 * t[0]], ay = xy[2 * t[0] + 1], bx = xy[2 * t[1]], by = xy[2 * t[1] + 1];
    const double cx = xy[2 * t[2]], cy = xy[2 * t[2] + 1];
    const double d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by));
    const double ox =
      ((ax * ax + ay * ay) * (by - cy) + (bx * bx + by * by) * (cy - ay) + (cx * cx + cy * cy) * (ay - by)) / d;
    const double oy =
      ((ax * ax + ay * ay) * (cx - bx) + (bx * bx + by * by) * (ax - cx) + (cx * cx + cy * cy) * (bx - ax)) / d;
    const double r2 = (ax - ox) * (ax - ox) + (ay - oy) * (ay - oy);
    for (size_t i = 0; i < n; ++i)
    {
      if (static_cast<int32_t>(i) == t[0] || static_cast<int32_t>(i) == t[1] || static_cast<int32_t>(i) == t[2])
      {
        continue;
      }
      const double q2 = (xy[2 * i] - ox) * (xy[2 * i] - ox) + (xy[2 * i + 1] - oy) * (xy[2 * i + 1] - oy);
      EXPECT_GE(q2, r2 * (1.0 - 1e-9)) << "node " << i << " inside the circumcircle of a triangle";
    }
  }
  EXPECT_NEAR(area, 1500.0, 1e-9);
}
} // namespace
