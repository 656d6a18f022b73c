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

#include <algorithm>
#include <cmath>
#include <iostream>
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

/** Whether the closed segments (a, b) and (c, d) of integer points meet as ConstrainedDelaunay2D refuses: segments
 * that share an endpoint only where they overlap along a line, others wherever they meet. */
bool
MeetsAsRefused(const std::array<int64_t, 2> & a,
               const std::array<int64_t, 2> & b,
               const std::array<int64_t, 2> & c,
               const std::array<int64_t, 2> & d)
{
  auto orient =
    [](const std::array<int64_t, 2> & p, const std::array<int64_t, 2> & q, const std::array<int64_t, 2> & r) {
      const int64_t v = (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]);
      return (v > 0) - (v < 0);
    };
  auto within =
    [](const std::array<int64_t, 2> & p, const std::array<int64_t, 2> & q, const std::array<int64_t, 2> & r) {
      return std::min(p[0], q[0]) <= r[0] && r[0] <= std::max(p[0], q[0]) && std::min(p[1], q[1]) <= r[1] &&
             r[1] <= std::max(p[1], q[1]);
    };
  if (a == c || a == d || b == c || b == d)
  {
    if (orient(c, d, a) != 0 || orient(c, d, b) != 0)
    {
      return false;
    }
    const auto & common = (a == c || a == d) ? a : b;
    const auto & mine = common == a ? b : a;
    const auto & other = common == c ? d : c;
    return (mine[0] - common[0]) * (other[0] - common[0]) + (mine[1] - common[1]) * (other[1] - common[1]) > 0;
  }
  const int o1 = orient(a, b, c), o2 = orient(a, b, d), o3 = orient(c, d, a), o4 = orient(c, d, b);
  if (o1 != o2 && o3 != o4)
  {
    return true;
  }
  return (o1 == 0 && within(a, b, c)) || (o2 == 0 && within(a, b, d)) || (o3 == 0 && within(c, d, a)) ||
         (o4 == 0 && within(c, d, b));
}

TEST(ConstrainedDelaunay2D, SkipsExactlyTheConstraintsThatMeetAnAcceptedOne)
{
  // Integer nodes (exact arithmetic for the reference), many of them on common lines; constraints short and long
  // (some across the whole box), repeated, reversed, with shared endpoints and overlaps along lines.
  size_t skippedInAll = 0, acceptedInAll = 0;
  for (uint32_t seed = 1; seed <= 12; ++seed)
  {
    std::mt19937                           engine(seed);
    const int64_t                          width = 60 + 20 * (seed % 3), height = 40 + 30 * (seed % 2);
    std::uniform_int_distribution<int64_t> ux(0, width), uy(0, height);
    std::set<std::array<int64_t, 2>>       taken{ { 0, 0 }, { width, 0 }, { width, height }, { 0, height } };
    std::vector<std::array<int64_t, 2>>    p(taken.begin(), taken.end());
    while (p.size() < 300)
    {
      const std::array<int64_t, 2> q{ ux(engine), uy(engine) };
      if (taken.insert(q).second)
      {
        p.push_back(q);
      }
    }
    std::vector<double> xy;
    for (const auto & q : p)
    {
      xy.push_back(static_cast<double>(q[0]));
      xy.push_back(static_cast<double>(q[1]));
    }
    std::uniform_int_distribution<int32_t> node(0, static_cast<int32_t>(p.size()) - 1);
    std::vector<std::array<int32_t, 2>>    constraints;
    while (constraints.size() < 900)
    {
      const int32_t a = node(engine);
      const int     kind = static_cast<int>(engine() % 20);
      int32_t       b = node(engine);
      if (kind < 16) // short: to the nearest of a few random nodes
      {
        for (int t = 0; t < 12; ++t)
        {
          const int32_t c = node(engine);
          auto          d2 = [&](int32_t i) {
            return (p[i][0] - p[a][0]) * (p[i][0] - p[a][0]) + (p[i][1] - p[a][1]) * (p[i][1] - p[a][1]);
          };
          b = (b == a || (c != a && d2(c) < d2(b))) ? c : b;
        }
      }
      else if (kind == 16 && !constraints.empty()) // repeated or reversed
      {
        const auto & e = constraints[engine() % constraints.size()];
        constraints.push_back(engine() % 2 ? e : std::array<int32_t, 2>{ e[1], e[0] });
        continue;
      }
      else if (kind == 17)
      {
        b = a; // a single node: skipped
      }
      constraints.push_back({ a, b });
    }
    // the reference: each constraint against every accepted one before it
    std::vector<std::array<int32_t, 2>> accepted;
    size_t                              skipped = 0;
    for (const auto & c : constraints)
    {
      bool meets = c[0] == c[1];
      for (size_t k = 0; k < accepted.size() && !meets; ++k)
      {
        meets = MeetsAsRefused(p[c[0]], p[c[1]], p[accepted[k][0]], p[accepted[k][1]]);
      }
      if (meets)
      {
        ++skipped;
      }
      else
      {
        accepted.push_back(c);
      }
    }
    TriangleList triangles;
    ASSERT_EQ(itk::dmr::ConstrainedDelaunay2D(xy, constraints, triangles), skipped) << "seed " << seed;
    // an accepted constraint with no node inside is an edge of the triangulation
    for (const auto & c : accepted)
    {
      bool nodeInside = false;
      for (size_t i = 0; i < p.size() && !nodeInside; ++i)
      {
        nodeInside = static_cast<int32_t>(i) != c[0] && static_cast<int32_t>(i) != c[1] &&
                     MeetsAsRefused(p[c[0]], p[c[1]], p[i], p[i]);
      }
      if (!nodeInside)
      {
        EXPECT_TRUE(HasEdge(triangles, c[0], c[1])) << "seed " << seed << ": " << c[0] << "-" << c[1];
      }
    }
    double area = 0.0;
    for (const auto & t : triangles)
    {
      EXPECT_GT(SignedArea(xy, t), 0.0);
      area += SignedArea(xy, t);
    }
    EXPECT_EQ(area, static_cast<double>(width * height)) << "seed " << seed;
    if (seed % 4 == 0)
    {
      // the same nodes moved and scaled exactly (by powers of two) so far apart that the spans of their
      // coordinates overflow: the same constraints skipped
      std::vector<double> far(xy.size());
      double              lowest = 0.0, highest = 0.0;
      for (size_t i = 0; i < xy.size(); ++i)
      {
        // x - width / 2 in [-width / 2, width / 2], whose ends become at least 2^1023 (the spans at least 2^1024)
        const double half = i % 2 == 0 ? 0.5 * static_cast<double>(width) : 0.5 * static_cast<double>(height);
        far[i] = std::ldexp(xy[i] - half, 1023 - std::ilogb(half));
        lowest = i % 2 == 0 ? std::min(lowest, far[i]) : lowest;
        highest = i % 2 == 0 ? std::max(highest, far[i]) : highest;
      }
      ASSERT_TRUE(std::isinf(highest - lowest));
      TriangleList farTriangles;
      EXPECT_EQ(itk::dmr::ConstrainedDelaunay2D(far, constraints, farTriangles), skipped) << "seed " << seed;
      EXPECT_EQ(farTriangles.size(), triangles.size()) << "seed " << seed;
    }
    skippedInAll += skipped;
    acceptedInAll += accepted.size();
  }
  std::cout << "accepted " << acceptedInAll << ", skipped " << skippedInAll << " of 12 x 900 constraints" << std::endl;
  EXPECT_GT(skippedInAll, 1000u);
  EXPECT_GT(acceptedInAll, 1000u);
}
} // namespace
