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
#include "dmrDelaunay3D.h"
#include "itkMacro.h"
#include "itkMultiThreaderBase.h"
#include "gtest/gtest.h"

#include <algorithm>
#include <cmath>
#include <iostream>
#include <map>
#include <random>

namespace
{
using Tetrahedra = std::vector<std::array<int32_t, 4>>;
constexpr double       flatShape = itk::dmr::DefaultMinimumTetrahedronShape;
constexpr unsigned int rounds = 12;

double
Volume(const std::vector<double> & xyz, const std::array<int32_t, 4> & t)
{
  double m[3][3];
  for (unsigned int r = 0; r < 3; ++r)
  {
    for (unsigned int c = 0; c < 3; ++c)
    {
      m[r][c] = xyz[3 * t[c + 1] + r] - xyz[3 * t[0] + r];
    }
  }
  return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
          m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])) /
         6.0;
}

/** The first node strictly inside the circumsphere of tetrahedron t (to 1e-9 of its squared radius), or -1. */
int64_t
NodeInsideCircumsphere(const std::vector<double> & xyz, const std::array<int32_t, 4> & t)
{
  // circumcentre c solves 2 (p_i - p_0) . c = |p_i|^2 - |p_0|^2 (Cramer's rule)
  double m[3][3], rhs[3], centre[3];
  for (unsigned int r = 0; r < 3; ++r)
  {
    rhs[r] = 0.0;
    for (unsigned int k = 0; k < 3; ++k)
    {
      m[r][k] = 2.0 * (xyz[3 * t[r + 1] + k] - xyz[3 * t[0] + k]);
      rhs[r] += xyz[3 * t[r + 1] + k] * xyz[3 * t[r + 1] + k] - xyz[3 * t[0] + k] * xyz[3 * t[0] + k];
    }
  }
  auto det3 = [](const double(&q)[3][3]) {
    return q[0][0] * (q[1][1] * q[2][2] - q[1][2] * q[2][1]) - q[0][1] * (q[1][0] * q[2][2] - q[1][2] * q[2][0]) +
           q[0][2] * (q[1][0] * q[2][1] - q[1][1] * q[2][0]);
  };
  const double det = det3(m);
  for (unsigned int col = 0; col < 3; ++col)
  {
    double mc[3][3];
    for (unsigned int r = 0; r < 3; ++r)
    {
      for (unsigned int k = 0; k < 3; ++k)
      {
        mc[r][k] = k == col ? rhs[r] : m[r][k];
      }
    }
    centre[col] = det3(mc) / det;
  }
  auto distance2 = [&](size_t i) {
    double s = 0.0;
    for (unsigned int k = 0; k < 3; ++k)
    {
      s += (xyz[3 * i + k] - centre[k]) * (xyz[3 * i + k] - centre[k]);
    }
    return s;
  };
  const double radius2 = distance2(static_cast<size_t>(t[0]));
  for (size_t i = 0; i < xyz.size() / 3; ++i)
  {
    if (distance2(i) < radius2 * (1.0 - 1e-9))
    {
      return static_cast<int64_t>(i);
    }
  }
  return -1;
}

/** Box [0,a] x [0,b] x [0,c] corners followed by random inner points. */
std::vector<double>
BoxWithInnerPoints(double a, double b, double c, size_t inner, uint32_t seed)
{
  std::vector<double> xyz;
  for (unsigned int corner = 0; corner < 8; ++corner)
  {
    xyz.push_back(corner & 1u ? a : 0.0);
    xyz.push_back(corner & 2u ? b : 0.0);
    xyz.push_back(corner & 4u ? c : 0.0);
  }
  std::mt19937                           rng(seed);
  std::uniform_real_distribution<double> u(0.05, 0.95);
  for (size_t i = 0; i < inner; ++i)
  {
    xyz.push_back(a * u(rng));
    xyz.push_back(b * u(rng));
    xyz.push_back(c * u(rng));
  }
  return xyz;
}

/** 10 x 10 x 10 lattice (step 1, inside [0, 11]^3) with each coordinate off by up to 'noise', plus the 8 corners of
 * [0, 11]^3: for tiny noise the Delaunay tetrahedralization is full of near-flat tetrahedra. */
std::vector<double>
NoisyLattice(double noise)
{
  std::vector<double>                    xyz = BoxWithInnerPoints(11.0, 11.0, 11.0, 0, 1);
  std::mt19937                           rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < 10; ++i)
  {
    for (int j = 0; j < 10; ++j)
    {
      for (int k = 0; k < 10; ++k)
      {
        xyz.push_back(1.0 + k + noise * u(rng));
        xyz.push_back(1.0 + j + noise * u(rng));
        xyz.push_back(1.0 + i + noise * u(rng));
      }
    }
  }
  return xyz;
}

size_t
CountFlat(const std::vector<double> & xyz, const Tetrahedra & tetrahedra)
{
  size_t flat = 0;
  for (const auto & t : tetrahedra)
  {
    flat += itk::dmr::TetrahedronShape(&xyz[3 * t[0]], &xyz[3 * t[1]], &xyz[3 * t[2]], &xyz[3 * t[3]]) <
                itk::dmr::DefaultMinimumTetrahedronShape
              ? 1
              : 0;
  }
  return flat;
}

TEST(Delaunay3D, FillsTheConvexHullWithPositiveTetrahedra)
{
  const auto xyz = BoxWithInnerPoints(3.0, 4.5, 7.5, 300, 11);
  Tetrahedra tetrahedra;
  EXPECT_EQ(itk::dmr::Delaunay3D(xyz, tetrahedra), 0u);
  ASSERT_GT(tetrahedra.size(), 300u);
  double total = 0.0;
  for (const auto & t : tetrahedra)
  {
    const double v = Volume(xyz, t);
    EXPECT_GT(v, 0.0);
    total += v;
  }
  EXPECT_NEAR(total, 3.0 * 4.5 * 7.5, 1e-9);
}

TEST(Delaunay3D, IsEmptyCircumsphere)
{
  // the defining property: no node lies strictly inside a tetrahedron's circumsphere
  const auto xyz = BoxWithInnerPoints(2.0, 3.0, 5.0, 80, 3);
  Tetrahedra tetrahedra;
  itk::dmr::Delaunay3D(xyz, tetrahedra);
  for (const auto & t : tetrahedra)
  {
    EXPECT_EQ(NodeInsideCircumsphere(xyz, t), -1) << "a node inside a circumsphere";
  }
}

TEST(Delaunay3D, MergesNodesAtTheSamePosition)
{
  auto         xyz = BoxWithInnerPoints(1.0, 1.0, 1.0, 20, 5);
  const size_t n = xyz.size() / 3;
  // node n repeats node 9, node n + 1 repeats corner 0
  xyz.insert(xyz.end(), &xyz[27], &xyz[30]);
  xyz.insert(xyz.end(), { 0.0, 0.0, 0.0 });
  Tetrahedra tetrahedra;
  EXPECT_EQ(itk::dmr::Delaunay3D(xyz, tetrahedra), 2u);
  bool uses9 = false;
  for (const auto & t : tetrahedra)
  {
    for (int32_t v : t)
    {
      EXPECT_LT(static_cast<size_t>(v), n) << "a tetrahedron refers to a merged node";
      uses9 = uses9 || v == 9;
    }
  }
  EXPECT_TRUE(uses9);
}

TEST(Delaunay3D, DegenerateNodeSetsGiveNoTetrahedra)
{
  Tetrahedra tetrahedra;
  EXPECT_EQ(itk::dmr::Delaunay3D({}, tetrahedra), 0u);
  EXPECT_TRUE(tetrahedra.empty());
  EXPECT_EQ(itk::dmr::Delaunay3D({ 0, 0, 0, 1, 0, 0, 0, 1, 0 }, tetrahedra), 0u);
  EXPECT_TRUE(tetrahedra.empty());
  // coplanar (TetGen 1.5 itself would crash): in a tilted plane and in an axis plane
  EXPECT_EQ(itk::dmr::Delaunay3D({ 1, 0, 0, 0, 1, 0, 0, 0, 1, 0.5, 0.5, 0, 0.2, 0.3, 0.5 }, tetrahedra), 0u);
  EXPECT_TRUE(tetrahedra.empty());
  EXPECT_EQ(itk::dmr::Delaunay3D({ 0, 0, 2, 1, 0, 2, 0, 1, 2, 1, 1, 2 }, tetrahedra), 0u);
  EXPECT_TRUE(tetrahedra.empty());
  // collinear, and the same point four times
  EXPECT_EQ(itk::dmr::Delaunay3D({ 0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3 }, tetrahedra), 0u);
  EXPECT_TRUE(tetrahedra.empty());
  EXPECT_EQ(itk::dmr::Delaunay3D({ 1, 2, 3, 1, 2, 3, 1, 2, 3, 1, 2, 3 }, tetrahedra), 3u);
  EXPECT_TRUE(tetrahedra.empty());
  // but a single tetrahedron is fine
  EXPECT_EQ(itk::dmr::Delaunay3D({ 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1 }, tetrahedra), 0u);
  EXPECT_EQ(tetrahedra.size(), 1u);
}

TEST(Delaunay3D, TetrahedronShape)
{
  const double a[3] = { 1, 1, 1 }, b[3] = { 1, -1, -1 }, c[3] = { -1, 1, -1 }, d[3] = { -1, -1, 1 };
  const double regular = itk::dmr::TetrahedronShape(a, b, c, d);
  EXPECT_NEAR(std::abs(regular), 1.0, 1e-12);
  EXPECT_NEAR(itk::dmr::TetrahedronShape(b, a, c, d), -regular, 1e-12);
  const double p[3] = { 0, 0, 0 }, q[3] = { 1, 0, 0 }, r[3] = { 0, 1, 0 }, s[3] = { 1, 1, 0 };
  EXPECT_EQ(itk::dmr::TetrahedronShape(p, q, r, s), 0.0);
  EXPECT_EQ(itk::dmr::TetrahedronShape(p, p, p, p), 0.0);
}

TEST(Delaunay3D, NearDegenerateNodesGiveFlatTetrahedra)
{
  // why NonDegenerateDelaunay3D exists: round-off sized noise on a lattice
  const auto xyz = NoisyLattice(1e-13);
  Tetrahedra tetrahedra;
  itk::dmr::Delaunay3D(xyz, tetrahedra);
  EXPECT_GT(CountFlat(xyz, tetrahedra), 100u);
  // an exact lattice is degenerate too, but exactly: TetGen's exact predicates give no flat tetrahedron
  const auto exact = NoisyLattice(0.0);
  itk::dmr::Delaunay3D(exact, tetrahedra);
  EXPECT_EQ(CountFlat(exact, tetrahedra), 0u);
}

TEST(Delaunay3D, NudgingRemovesFlatTetrahedraAndKeepsPinnedNodes)
{
  const auto           original = NoisyLattice(1e-13);
  const size_t         n = original.size() / 3;
  std::vector<uint8_t> freeAxes(n, 7u);
  std::fill(freeAxes.begin(), freeAxes.begin() + 8, uint8_t{ 0 }); // corners pinned
  for (size_t i = 8; i < n; i += 5)
  {
    freeAxes[i] = 1u; // some nodes may move along x only
  }
  auto       xyz = original;
  Tetrahedra tetrahedra;
  const auto moved = itk::dmr::NonDegenerateDelaunay3D(xyz, freeAxes, 0.05, tetrahedra, flatShape, rounds);
  EXPECT_GT(moved, 0u);
  EXPECT_EQ(CountFlat(xyz, tetrahedra), 0u);
  double total = 0.0;
  for (const auto & t : tetrahedra)
  {
    total += Volume(xyz, t);
  }
  EXPECT_NEAR(total, 11.0 * 11.0 * 11.0, 1e-9);
  size_t changed = 0;
  for (size_t i = 0; i < n; ++i)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      const double shift = xyz[3 * i + k] - original[3 * i + k];
      if ((freeAxes[i] >> k & 1u) == 0)
      {
        EXPECT_EQ(shift, 0.0) << "node " << i << " moved along pinned axis " << k;
      }
      EXPECT_LE(std::abs(shift), 0.05 + 1e-12) << "node " << i; // at most maximumStep in all
    }
    changed += std::equal(&xyz[3 * i], &xyz[3 * i] + 3, &original[3 * i]) ? 0 : 1;
  }
  EXPECT_EQ(changed, moved);
  // deterministic
  auto       again = original;
  Tetrahedra tetrahedraAgain;
  EXPECT_EQ(itk::dmr::NonDegenerateDelaunay3D(again, freeAxes, 0.05, tetrahedraAgain, flatShape, rounds), moved);
  EXPECT_EQ(again, xyz);
  EXPECT_EQ(tetrahedraAgain, tetrahedra);
}

TEST(Delaunay3D, NudgingLeavesGenericInputAlone)
{
  const auto           original = BoxWithInnerPoints(3.0, 4.0, 5.0, 200, 9);
  auto                 xyz = original;
  std::vector<uint8_t> freeAxes(xyz.size() / 3, 7u);
  Tetrahedra           nudged, plain;
  EXPECT_EQ(itk::dmr::NonDegenerateDelaunay3D(xyz, freeAxes, 0.1, nudged, flatShape, rounds), 0u);
  EXPECT_EQ(xyz, original);
  itk::dmr::Delaunay3D(original, plain);
  EXPECT_EQ(nudged, plain);
}

TEST(Delaunay3D, NudgingThrowsWhenNothingMayMove)
{
  auto                 xyz = NoisyLattice(1e-13);
  std::vector<uint8_t> freeAxes(xyz.size() / 3, 0u);
  Tetrahedra           tetrahedra;
  EXPECT_THROW(itk::dmr::NonDegenerateDelaunay3D(xyz, freeAxes, 0.05, tetrahedra, flatShape, rounds),
               itk::ExceptionObject);
  std::vector<uint8_t> wrongSize(3, 7u);
  EXPECT_THROW(itk::dmr::NonDegenerateDelaunay3D(xyz, wrongSize, 0.05, tetrahedra, flatShape, rounds),
               itk::ExceptionObject);
}

/** Nodes like the dual mesh's in the box [0,a] x [0,b] x [0,c]: its corners, jittered lattices of spacing h inside,
 * on every face (exactly coplanar) and on every edge; `graded`: the lattice coordinate t in [0, 1] is mapped to t^1.6,
 * so the nodes crowd towards one corner as where a registration needs them. `random`: uniform inner and face nodes
 * instead (slivers with large circumspheres along the edges and faces). */
std::vector<double>
DualMeshLikeNodes(double a, double b, double c, double h, bool graded, bool random, uint32_t seed)
{
  std::vector<double>                    xyz = BoxWithInnerPoints(a, b, c, 0, 1);
  std::mt19937                           rng(seed);
  std::uniform_real_distribution<double> jitter(-0.3, 0.3), u(0.02, 0.98);
  const double                           side[3] = { a, b, c };
  int                                    count[3];
  for (unsigned int k = 0; k < 3; ++k)
  {
    count[k] = std::max(1, static_cast<int>(side[k] / h));
  }
  // coordinate of lattice position i (of count[k]) along axis k, jittered unless on the box
  auto at = [&](unsigned int k, int i) {
    const double t = random ? u(rng) : (i + 0.5 + jitter(rng)) / count[k];
    return side[k] * (graded ? std::pow(t, 1.6) : t);
  };
  // every node whose lattice index along each axis is in [-1, count]: -1 is the lower plane, count the upper one
  for (int i = -1; i <= count[2]; ++i)
  {
    for (int j = -1; j <= count[1]; ++j)
    {
      for (int k = -1; k <= count[0]; ++k)
      {
        const int index[3] = { k, j, i };
        int       onPlanes = 0;
        double    x[3];
        for (unsigned int m = 0; m < 3; ++m)
        {
          const bool lower = index[m] < 0, upper = index[m] >= count[m];
          onPlanes += lower || upper ? 1 : 0;
          x[m] = lower ? 0.0 : (upper ? side[m] : at(m, index[m]));
        }
        if (onPlanes < 3) // the corners are in already
        {
          xyz.insert(xyz.end(), x, x + 3);
        }
      }
    }
  }
  return xyz;
}

/** The defining properties of the Delaunay tetrahedralization of nodes whose hull is the box [0,a] x [0,b] x [0,c]:
 * positive tetrahedra filling the box, every inner face shared by two of them, no node inside a circumsphere. */
void
ExpectDelaunayOfBox(const std::vector<double> & xyz, const Tetrahedra & tetrahedra, double a, double b, double c)
{
  double                                   total = 0.0;
  std::vector<std::array<int32_t, 3>>      faces;
  const std::vector<std::array<double, 3>> none;
  for (const auto & t : tetrahedra)
  {
    const double v = Volume(xyz, t);
    ASSERT_GT(v, 0.0);
    total += v;
    for (unsigned int f = 0; f < 4; ++f)
    {
      std::array<int32_t, 3> face;
      for (unsigned int v2 = 0, m = 0; v2 < 4; ++v2)
      {
        if (v2 != f)
        {
          face[m++] = t[v2];
        }
      }
      std::sort(face.begin(), face.end());
      faces.push_back(face);
    }
  }
  EXPECT_NEAR(total, a * b * c, 1e-9 * a * b * c);
  std::sort(faces.begin(), faces.end());
  size_t single = 0, shared = 0;
  for (size_t i = 0; i < faces.size();)
  {
    size_t j = i;
    while (j < faces.size() && faces[j] == faces[i])
    {
      ++j;
    }
    ASSERT_LE(j - i, 2u) << "a face of more than two tetrahedra";
    if (j - i == 2)
    {
      ++shared;
    }
    else
    {
      // a face of one tetrahedron lies on the box
      bool         onBox = false;
      const double side[3] = { a, b, c };
      for (unsigned int k = 0; k < 3 && !onBox; ++k)
      {
        for (const double plane : { 0.0, side[k] })
        {
          onBox = onBox || (xyz[3 * faces[i][0] + k] == plane && xyz[3 * faces[i][1] + k] == plane &&
                            xyz[3 * faces[i][2] + k] == plane);
        }
      }
      EXPECT_TRUE(onBox) << "an inner face of only one tetrahedron";
      ++single;
    }
    i = j;
  }
  EXPECT_GT(shared, single);
  // empty circumspheres (every node against every sphere)
  for (const auto & t : tetrahedra)
  {
    const int64_t inside = NodeInsideCircumsphere(xyz, t);
    if (inside >= 0)
    {
      ADD_FAILURE() << "node " << inside << " inside the circumsphere of a tetrahedron";
      return;
    }
  }
}

itk::MultiThreaderBase::Pointer
Threader(unsigned int workUnits)
{
  auto threader = itk::MultiThreaderBase::New();
  threader->SetMaximumNumberOfThreads(workUnits);
  threader->SetNumberOfWorkUnits(workUnits);
  return threader;
}
} // namespace

TEST(Delaunay3D, BlocksGiveTheDelaunayTetrahedralizationWhateverTheWorkUnits)
{
  for (const bool graded : { false, true })
  {
    const auto xyz = DualMeshLikeNodes(300.0, 260.0, 180.0, 16.0, graded, false, graded ? 5u : 4u);
    Tetrahedra reference;
    ASSERT_TRUE(itk::dmr::BlockDelaunay3D(xyz, reference, Threader(1)));
    ExpectDelaunayOfBox(xyz, reference, 300.0, 260.0, 180.0);
    // other threads, other layouts, the same list
    std::vector<unsigned int> layouts;
    for (const unsigned int workUnits : { 2u, 7u, 16u })
    {
      Tetrahedra                        t;
      itk::dmr::BlockDelaunayStatistics statistics;
      ASSERT_TRUE(itk::dmr::BlockDelaunay3D(xyz, t, Threader(workUnits), itk::dmr::DefaultBlockMargin, &statistics));
      EXPECT_EQ(t, reference) << workUnits << " work units";
      // the default margin is wide enough for dual-mesh-like nodes, graded ones too: no block is redone (1.5 fails
      // here)
      EXPECT_EQ(statistics.numberOfRuns, statistics.numberOfBlocks) << workUnits << " work units";
      layouts.push_back(statistics.numberOfBlocks);
    }
    EXPECT_NE(layouts.front(), layouts.back()) << "the layouts did not differ";
    // Delaunay3D takes this path
    Tetrahedra t;
    EXPECT_EQ(itk::dmr::Delaunay3D(xyz, t, Threader(2)), 0u);
    EXPECT_EQ(t, reference);
    // and one TetGen run gives the same list (no cospherical nodes here), as does Delaunay3D without threads
    Tetrahedra tetgen;
    EXPECT_EQ(itk::dmr::TetGenDelaunay3D(xyz, tetgen), 0u);
    EXPECT_EQ(tetgen, reference);
    EXPECT_EQ(itk::dmr::Delaunay3D(xyz, t), 0u);
    EXPECT_EQ(t, reference);
  }
}

/** Nodes with many cospherical subsets (a lattice, its face and edge nodes exactly on the box, as near-regular dual
 * meshes of small images have them): their Delaunay tetrahedralization is not unique. Delaunay3D still gives one list
 * whatever the threads: the blocks and the one-run path are both CGAL's, whose symbolic perturbation depends on the
 * nodes only. (TetGen perturbs otherwise and may pick another tetrahedralization of a cospherical set.) */
TEST(Delaunay3D, CosphericalNodesGiveOneTetrahedralizationWhateverTheThreads)
{
  std::vector<double> xyz;
  const int           count[3] = { 14, 12, 10 };
  const double        h[3] = { 2.0, 2.0, 3.0 };
  for (int k = 0; k < count[2]; ++k)
  {
    for (int j = 0; j < count[1]; ++j)
    {
      for (int i = 0; i < count[0]; ++i)
      {
        xyz.insert(xyz.end(), { i * h[0], j * h[1], k * h[2] });
      }
    }
  }
  const double a = (count[0] - 1) * h[0], b = (count[1] - 1) * h[1], c = (count[2] - 1) * h[2];
  Tetrahedra   reference;
  EXPECT_EQ(itk::dmr::Delaunay3D(xyz, reference, Threader(1)), 0u);
  ExpectDelaunayOfBox(xyz, reference, a, b, c);
  Tetrahedra none;
  EXPECT_EQ(itk::dmr::Delaunay3D(xyz, none), 0u);
  EXPECT_EQ(none, reference) << "without a threader";
  size_t byBlocks = 0;
  for (const unsigned int workUnits : { 2u, 3u, 7u, 16u })
  {
    Tetrahedra t;
    EXPECT_EQ(itk::dmr::Delaunay3D(xyz, t, Threader(workUnits)), 0u);
    EXPECT_EQ(t, reference) << workUnits << " work units";
    Tetrahedra blocks;
    byBlocks += itk::dmr::BlockDelaunay3D(xyz, blocks, Threader(workUnits)) ? 1 : 0;
    EXPECT_TRUE(blocks.empty() || blocks == reference) << workUnits << " work units";
  }
  EXPECT_GT(byBlocks, 0u) << "the blocks never vouched for their result: the one-run path alone was compared";
  // TetGen's tetrahedralization is a Delaunay one too, but another: the choice this test is about is real here
  Tetrahedra tetgen;
  itk::dmr::TetGenDelaunay3D(xyz, tetgen);
  ExpectDelaunayOfBox(xyz, tetgen, a, b, c);
  EXPECT_NE(tetgen, reference);
}

TEST(Delaunay3D, BlocksRefuseWhatTheyCannotVouchFor)
{
  const auto xyz = DualMeshLikeNodes(300.0, 260.0, 180.0, 16.0, true, false, 6u);
  Tetrahedra reference;
  ASSERT_TRUE(itk::dmr::BlockDelaunay3D(xyz, reference, Threader(2)));
  // smaller margins: blocks that cannot vouch for their tetrahedra are redone with larger ones; the result is either
  // refused or the same tetrahedralization, never another one
  size_t redone = 0;
  for (const double margin : { 0.05, 0.2, 0.4, 0.7, 1.0 })
  {
    Tetrahedra                        t;
    itk::dmr::BlockDelaunayStatistics statistics;
    if (itk::dmr::BlockDelaunay3D(xyz, t, Threader(2), margin, &statistics))
    {
      EXPECT_EQ(t, reference) << "margin " << margin;
    }
    else
    {
      EXPECT_TRUE(t.empty());
    }
    EXPECT_GT(statistics.numberOfBlocks, 1u);
    redone += statistics.numberOfRuns - statistics.numberOfBlocks;
  }
  EXPECT_GT(redone, 0u) << "no margin was too small: the check was not exercised";
  // uniform random nodes: slivers along the box with large circumspheres; refused or right, never wrong
  const auto random = DualMeshLikeNodes(300.0, 260.0, 180.0, 16.0, false, true, 8u);
  Tetrahedra t;
  if (itk::dmr::BlockDelaunay3D(random, t, Threader(2)))
  {
    ExpectDelaunayOfBox(random, t, 300.0, 260.0, 180.0);
  }
  // not the box as hull (a corner missing), or too few nodes for two blocks
  std::vector<double> noCorner(xyz.begin() + 3, xyz.end());
  EXPECT_FALSE(itk::dmr::BlockDelaunay3D(noCorner, t, Threader(2)));
  EXPECT_TRUE(t.empty());
  EXPECT_FALSE(itk::dmr::BlockDelaunay3D(BoxWithInnerPoints(3.0, 3.0, 3.0, 100, 11), t, Threader(2)));
  // Delaunay3D falls back to TetGen there, with the same defining properties
  EXPECT_EQ(itk::dmr::Delaunay3D(noCorner, t, Threader(2)), 0u);
  ASSERT_FALSE(t.empty());
}

namespace
{
/** The nodes moved by up to `step` along the axes where they are not on the box (face nodes stay on their face, edge
 * nodes on their edge, corners where they are); a move that would leave the box is not made. */
std::vector<double>
MoveNodes(std::vector<double> xyz, const double (&side)[3], double step, uint32_t seed)
{
  std::mt19937                           rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (size_t i = 0; i < xyz.size(); ++i)
  {
    const unsigned int k = i % 3;
    if (xyz[i] != 0.0 && xyz[i] != side[k])
    {
      const double x = xyz[i] + step * u(rng);
      xyz[i] = x > 0.0 && x < side[k] ? x : xyz[i];
    }
  }
  return xyz;
}
} // namespace

/** The registration's nodes move a little from one iteration to the next: RepairDelaunay3D flips the last
 * tetrahedralization into the new one. Whenever it vouches for its result, that is Delaunay3D's list exactly; over a
 * sequence of moves it must both untangle inverted tetrahedra and flip non-Delaunay faces (2-3 and 3-2) at least once.
 */
TEST(Delaunay3D, RepairFromMovedNodesGivesDelaunay3DsList)
{
  const double side[3] = { 300.0, 260.0, 180.0 };
  const double h = 16.0;
  auto         xyz = DualMeshLikeNodes(side[0], side[1], side[2], h, false, false, 9u);
  Tetrahedra   previous;
  itk::dmr::Delaunay3D(xyz, previous, Threader(2));
  // unmoved nodes: the same list, nothing flipped
  Tetrahedra                         t;
  itk::dmr::DelaunayRepairStatistics statistics;
  ASSERT_TRUE(itk::dmr::RepairDelaunay3D(xyz, previous, t, Threader(2), &statistics));
  EXPECT_EQ(t, previous);
  EXPECT_EQ(statistics.flips23 + statistics.flips32 + statistics.flips22 + statistics.tangledTetrahedra, 0u);

  size_t repaired = 0, untangled = 0, flipped23 = 0, flipped32 = 0, flippedOnBox = 0;
  for (uint32_t move = 0; move < 24; ++move)
  {
    const double step = h * (move % 3 == 0 ? 0.003 : (move % 3 == 1 ? 0.01 : 0.03));
    xyz = MoveNodes(xyz, side, step, 100 + move);
    Tetrahedra reference;
    itk::dmr::Delaunay3D(xyz, reference, Threader(2));
    for (const unsigned int workUnits : { 1u, 2u, 5u })
    {
      if (itk::dmr::RepairDelaunay3D(xyz, previous, t, Threader(workUnits), &statistics))
      {
        ASSERT_EQ(t, reference) << "move " << move << ", " << workUnits << " work units";
        repaired += workUnits == 1 ? 1 : 0;
        untangled += statistics.tangledTetrahedra > 0 ? 1 : 0;
        flipped23 += statistics.flips23;
        flipped32 += statistics.flips32;
        flippedOnBox += statistics.flips22;
      }
      else
      {
        EXPECT_TRUE(t.empty());
      }
    }
    previous = reference;
  }
  std::cout << "repaired " << repaired << " of 24 moves; untangled " << untangled << "; flips 2-3 " << flipped23
            << ", 3-2 " << flipped32 << ", 2-2 on the box " << flippedOnBox << std::endl;
  EXPECT_GE(repaired, 12u);
  EXPECT_GT(untangled, 0u);
  EXPECT_GT(flipped23, 0u);
  EXPECT_GT(flipped32, 0u);
  EXPECT_GT(flippedOnBox, 0u);
}

namespace
{
/** Which of the box's planes a node lies on (as a bit set). */
unsigned int
PlanesOf(const double * x, const double (&side)[3])
{
  // written with ifs: GCC 12 at -O2 with -fsanitize=undefined compiled `planes |= (x[k] == side[k] ? 1u : 0u) <<
  // (2 * k + 1)` so that (300, 10, 180) in a 300 x 260 x 180 box gave 2 instead of 34 (a standalone program shows
  // it), which made the sanitizer build draw other test moves
  unsigned int planes = 0;
  for (unsigned int k = 0; k < 3; ++k)
  {
    if (x[k] == 0.0)
    {
      planes |= 1u << (2 * k);
    }
    if (x[k] == side[k])
    {
      planes |= 2u << (2 * k);
    }
  }
  return planes;
}

/** The dual mesh's big moves: `count` inner nodes within h of a box face snap onto it, `count` face nodes leave
 * their face for the inside (0.5-1 h in), and `count` inner nodes jump by 1-2 h (staying inside). */
std::vector<double>
JumpNodes(std::vector<double> xyz, const double (&side)[3], double h, int count, uint32_t seed)
{
  std::mt19937                           rng(seed);
  std::uniform_int_distribution<size_t>  pick(8, xyz.size() / 3 - 1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int                                    snapped = 0, left = 0, jumped = 0;
  for (int attempt = 0; attempt < 100000 && (snapped < count || left < count || jumped < count); ++attempt)
  {
    double *           x = &xyz[3 * pick(rng)];
    const unsigned int planes = PlanesOf(x, side);
    if (planes == 0)
    {
      // inner: snap to the nearest face when within h, else (sometimes) jump
      unsigned int nearest = 0;
      double       distance = side[0];
      for (unsigned int k = 0; k < 3; ++k)
      {
        for (const double plane : { 0.0, side[k] })
        {
          if (std::abs(x[k] - plane) < distance)
          {
            distance = std::abs(x[k] - plane);
            nearest = 2 * k + (plane == 0.0 ? 0 : 1);
          }
        }
      }
      if (distance < h && snapped < count)
      {
        x[nearest / 2] = nearest % 2 ? side[nearest / 2] : 0.0;
        ++snapped;
      }
      else if (distance >= 2.5 * h && jumped < count)
      {
        for (unsigned int k = 0; k < 3; ++k)
        {
          // two draws in two statements: in one expression their order is unspecified, and the test's input would
          // depend on the compiler and its flags
          const double length = 1.0 + std::abs(u(rng));
          const double sign = u(rng) < 0.0 ? -1.0 : 1.0;
          x[k] += h * length * sign / std::sqrt(3.0);
        }
        ++jumped;
      }
    }
    else if ((planes & (planes - 1)) == 0 && left < count)
    {
      // on one face: into the inside
      unsigned int k = 0;
      while (!((planes >> (2 * k)) & 3u))
      {
        ++k;
      }
      const double depth = h * (0.75 + 0.25 * u(rng));
      x[k] = x[k] == 0.0 ? depth : side[k] - depth;
      ++left;
    }
  }
  return xyz;
}
} // namespace

/** The dual mesh snaps a cell's node to the box border when the cell reaches it and takes it back when it leaves;
 * nodes also jump where cells change much. With the earlier positions, RepairDelaunay3D moves such nodes by removal
 * and insertion (and sets aside the nodes of tetrahedra it cannot untangle), and its result is still Delaunay3D's list;
 * without them it must refuse a node that left the box. */
TEST(Delaunay3D, RepairMovesNodesOntoAndOffTheBoxFromTheirEarlierPositions)
{
  const double side[3] = { 300.0, 260.0, 180.0 };
  const double h = 16.0;
  auto         xyz = DualMeshLikeNodes(side[0], side[1], side[2], h, false, false, 13u);
  Tetrahedra   previous;
  itk::dmr::Delaunay3D(xyz, previous, Threader(2));
  size_t repaired = 0, removals = 0, secondRounds = 0;
  for (uint32_t move = 0; move < 12; ++move)
  {
    const auto earlier = xyz;
    xyz = JumpNodes(MoveNodes(xyz, side, 0.01 * h, 300 + move), side, h, 1 + move % 3, 400 + move);
    size_t changed = 0;
    for (size_t i = 0; i < xyz.size() / 3; ++i)
    {
      changed += PlanesOf(&xyz[3 * i], side) != PlanesOf(&earlier[3 * i], side) ? 1 : 0;
    }
    ASSERT_GE(changed, 2u) << "move " << move;
    Tetrahedra reference, t;
    itk::dmr::Delaunay3D(xyz, reference, Threader(2));
    EXPECT_FALSE(itk::dmr::RepairDelaunay3D(xyz, previous, t, Threader(2))) << "move " << move;
    for (const unsigned int workUnits : { 1u, 2u, 5u })
    {
      itk::dmr::DelaunayRepairStatistics statistics;
      if (itk::dmr::RepairDelaunay3D(xyz, previous, t, Threader(workUnits), &statistics, &earlier))
      {
        ASSERT_EQ(t, reference) << "move " << move << ", " << workUnits << " work units";
        EXPECT_GE(statistics.movedByRemoval, changed) << "move " << move;
        repaired += workUnits == 1 ? 1 : 0;
        removals += workUnits == 1 ? statistics.movedByRemoval : 0;
        secondRounds += workUnits == 1 && statistics.rounds > 1 ? 1 : 0;
      }
      else
      {
        EXPECT_TRUE(t.empty());
      }
    }
    previous = reference;
  }
  std::cout << "repaired " << repaired << " of 12 moves; " << removals << " nodes moved by removal and insertion; "
            << secondRounds << " moves needed a second untangling round" << std::endl;
  EXPECT_GE(repaired, 9u);
  EXPECT_GT(secondRounds, 0u);
}

namespace
{
/** The neighbours RepairDelaunay3D gives are those of the list: opposite node m of tetrahedron k lies the one that
 * holds the other three nodes of k (found by brute force over the faces), -1 where no other one does. */
void
ExpectNeighboursOf(const Tetrahedra & t, const std::vector<std::array<int32_t, 4>> & neighbours)
{
  ASSERT_EQ(neighbours.size(), t.size());
  std::map<std::array<int32_t, 3>, std::vector<int32_t>> holders;
  for (size_t k = 0; k < t.size(); ++k)
  {
    for (int m = 0; m < 4; ++m)
    {
      std::array<int32_t, 3> face = { t[k][(m + 1) % 4], t[k][(m + 2) % 4], t[k][(m + 3) % 4] };
      std::sort(face.begin(), face.end());
      holders[face].push_back(static_cast<int32_t>(k));
    }
  }
  for (size_t k = 0; k < t.size(); ++k)
  {
    for (int m = 0; m < 4; ++m)
    {
      std::array<int32_t, 3> face = { t[k][(m + 1) % 4], t[k][(m + 2) % 4], t[k][(m + 3) % 4] };
      std::sort(face.begin(), face.end());
      const auto &  h = holders[face];
      const int32_t other = h.size() == 2 ? (h[0] == static_cast<int32_t>(k) ? h[1] : h[0]) : -1;
      ASSERT_EQ(neighbours[k][m], other) << "tetrahedron " << k << ", node " << m;
    }
  }
}
} // namespace

/** The neighbours of a repair, carried to the next one, spare finding them again and give the same lists; neighbours
 * that do not fit the tetrahedra are refused, not trusted. */
TEST(Delaunay3D, RepairCarriesTheNeighboursToTheNextOne)
{
  const double                side[3] = { 300.0, 260.0, 180.0 };
  const double                h = 16.0;
  itk::dmr::DelaunayWarmStart warm;
  warm.nodes = DualMeshLikeNodes(side[0], side[1], side[2], h, true, false, 14u);
  itk::dmr::Delaunay3D(warm.nodes, warm.tetrahedra, Threader(2));
  size_t withNeighbours = 0;
  for (uint32_t move = 0; move < 10; ++move)
  {
    const auto xyz = JumpNodes(MoveNodes(warm.nodes, side, 0.01 * h, 500 + move), side, h, move % 2, 600 + move);
    Tetrahedra reference, t;
    itk::dmr::Delaunay3D(xyz, reference, Threader(2));
    std::vector<std::array<int32_t, 4>> neighbours;
    const bool repaired = itk::dmr::RepairDelaunay3D(xyz, warm, t, Threader(2), nullptr, &neighbours);
    withNeighbours += repaired && !warm.neighbours.empty() ? 1 : 0;
    if (repaired)
    {
      ASSERT_EQ(t, reference) << "move " << move;
      ExpectNeighboursOf(t, neighbours);
      // the same without them
      itk::dmr::DelaunayWarmStart bare = warm;
      bare.neighbours.clear();
      Tetrahedra again;
      ASSERT_TRUE(itk::dmr::RepairDelaunay3D(xyz, bare, again, Threader(2)));
      EXPECT_EQ(again, t);
    }
    else
    {
      EXPECT_TRUE(neighbours.empty());
    }
    // neighbours that do not fit: one entry pointing at another tetrahedron, two swapped, one freed, one reversed
    // tetrahedron
    if (!warm.neighbours.empty())
    {
      for (int corruption = 0; corruption < 4; ++corruption)
      {
        itk::dmr::DelaunayWarmStart bad = warm;
        const size_t                k = 97 % bad.tetrahedra.size();
        int                         m = 0;
        while (bad.neighbours[k][m] < 0)
        {
          ++m;
        }
        switch (corruption)
        {
          case 0:
            bad.neighbours[k][m] = static_cast<int32_t>((bad.neighbours[k][m] + 1) % bad.tetrahedra.size());
            break;
          case 1:
            std::swap(bad.neighbours[k][m], bad.neighbours[k][(m + 1) % 4]);
            break;
          case 2:
            bad.neighbours[bad.neighbours[k][m]] = { -1, -1, -1, -1 };
            bad.neighbours[k][m] = -1;
            break;
          default:
            std::swap(bad.tetrahedra[k][0], bad.tetrahedra[k][1]);
            std::swap(bad.neighbours[k][0], bad.neighbours[k][1]);
            break;
        }
        Tetrahedra out{ { 0, 1, 2, 3 } };
        EXPECT_FALSE(itk::dmr::RepairDelaunay3D(xyz, bad, out, Threader(2))) << "corruption " << corruption;
        EXPECT_TRUE(out.empty());
      }
    }
    warm.nodes = xyz;
    warm.tetrahedra = reference;
    warm.neighbours = repaired ? neighbours : std::vector<std::array<int32_t, 4>>{};
  }
  EXPECT_GE(withNeighbours, 6u);
}

/** The earlier tetrahedra need not be Delaunay3D's canonical sorted list: the same tiling in another order, each
 * tetrahedron's nodes rotated evenly (the orientation kept), gives the same result and neighbours. */
TEST(Delaunay3D, RepairTakesTheEarlierTetrahedraInAnyOrder)
{
  const double side[3] = { 300.0, 260.0, 180.0 };
  const double h = 16.0;
  auto         xyz = DualMeshLikeNodes(side[0], side[1], side[2], h, false, false, 21u);
  Tetrahedra   previous;
  itk::dmr::Delaunay3D(xyz, previous, Threader(2));
  size_t repaired = 0;
  for (uint32_t move = 0; move < 6; ++move)
  {
    // (a, b, c, d) -> (b, c, a, d): an even permutation; the list reversed
    Tetrahedra shuffled(previous.rbegin(), previous.rend());
    for (auto & t : shuffled)
    {
      t = { t[1], t[2], t[0], t[3] };
    }
    xyz = MoveNodes(xyz, side, h * 0.005, 300 + move);
    Tetrahedra reference;
    itk::dmr::Delaunay3D(xyz, reference, Threader(2));
    Tetrahedra                          fromSorted, fromShuffled;
    std::vector<std::array<int32_t, 4>> sortedNeighbours, shuffledNeighbours;
    itk::dmr::DelaunayWarmStart         sorted, other;
    sorted.tetrahedra = previous;
    other.tetrahedra = shuffled;
    const bool a = itk::dmr::RepairDelaunay3D(xyz, sorted, fromSorted, Threader(2), nullptr, &sortedNeighbours);
    const bool b = itk::dmr::RepairDelaunay3D(xyz, other, fromShuffled, Threader(2), nullptr, &shuffledNeighbours);
    EXPECT_EQ(a, b) << "move " << move;
    if (a && b)
    {
      ++repaired;
      ASSERT_EQ(fromShuffled, reference) << "move " << move;
      EXPECT_EQ(fromShuffled, fromSorted) << "move " << move;
      EXPECT_EQ(shuffledNeighbours, sortedNeighbours) << "move " << move;
      ExpectNeighboursOf(fromShuffled, shuffledNeighbours);
    }
    previous = reference;
  }
  EXPECT_GE(repaired, 3u);
}

/** What RepairDelaunay3D refuses (false, no tetrahedra): lists that do not tile the box with the nodes as they are (or
 * are not consistently oriented), and cospherical nodes, whose Delaunay tetrahedralization is not unique (Delaunay3D's
 * CGAL run decides there). */
TEST(Delaunay3D, RepairRefusesWhatItCannotVouchFor)
{
  const double side[3] = { 300.0, 260.0, 180.0 };
  const auto   xyz = DualMeshLikeNodes(side[0], side[1], side[2], 16.0, false, false, 10u);
  Tetrahedra   reference, t;
  itk::dmr::Delaunay3D(xyz, reference, Threader(2));
  ASSERT_TRUE(itk::dmr::RepairDelaunay3D(xyz, reference, t));
  EXPECT_EQ(t, reference);
  auto expectRefused = [&](const std::vector<double> & nodes, const Tetrahedra & previous, const char * what) {
    Tetrahedra out{ { 0, 1, 2, 3 } };
    EXPECT_FALSE(itk::dmr::RepairDelaunay3D(nodes, previous, out, Threader(2))) << what;
    EXPECT_TRUE(out.empty()) << what;
  };
  expectRefused(xyz, Tetrahedra{}, "no earlier tetrahedra");
  Tetrahedra bad = reference;
  bad[5][2] = static_cast<int32_t>(xyz.size() / 3);
  expectRefused(xyz, bad, "a node index out of range");
  bad = reference;
  bad.pop_back();
  expectRefused(xyz, bad, "a tetrahedron missing");
  bad = reference;
  bad.push_back(reference.front());
  expectRefused(xyz, bad, "a tetrahedron twice");
  bad = reference;
  std::swap(bad[7][2], bad[7][3]);
  expectRefused(xyz, bad, "a tetrahedron reversed (on the same side of a face as its neighbour)");
  // one more node, in no tetrahedron
  std::vector<double> more = xyz;
  more.insert(more.end(), { 0.5 * side[0], 0.5 * side[1], 0.5 * side[2] });
  expectRefused(more, reference, "a node in no tetrahedron");
  // a face node moved off its face: the free faces no longer lie on the box
  std::vector<double> off = xyz;
  for (size_t i = 8; i < off.size() / 3; ++i)
  {
    if (off[3 * i + 2] == 0.0 && off[3 * i] != 0.0 && off[3 * i] != side[0] && off[3 * i + 1] != 0.0 &&
        off[3 * i + 1] != side[1])
    {
      off[3 * i + 2] = 3.0;
      break;
    }
  }
  expectRefused(off, reference, "a face node off its face");
  // earlier positions in another box (a corner moved): not where these tetrahedra were Delaunay
  std::vector<double> otherBox = xyz;
  for (size_t i = 0; i < otherBox.size(); i += 3)
  {
    otherBox[i] = otherBox[i] == side[0] ? side[0] + 1.0 : otherBox[i];
  }
  Tetrahedra out{ { 0, 1, 2, 3 } };
  EXPECT_FALSE(itk::dmr::RepairDelaunay3D(off, reference, out, Threader(2), nullptr, &otherBox));
  EXPECT_TRUE(out.empty());
  // with the right ones, the face node that left its face is moved by removal and insertion
  itk::dmr::DelaunayRepairStatistics statistics;
  ASSERT_TRUE(itk::dmr::RepairDelaunay3D(off, reference, out, Threader(2), &statistics, &xyz));
  Tetrahedra offReference;
  itk::dmr::Delaunay3D(off, offReference, Threader(2));
  EXPECT_EQ(out, offReference);
  EXPECT_EQ(statistics.movedByRemoval, 1u);
  // a lattice: cospherical nodes everywhere
  std::vector<double> lattice;
  for (int k = 0; k < 6; ++k)
  {
    for (int j = 0; j < 6; ++j)
    {
      for (int i = 0; i < 6; ++i)
      {
        lattice.insert(lattice.end(), { 2.0 * i, 2.0 * j, 3.0 * k });
      }
    }
  }
  Tetrahedra latticeTetrahedra;
  itk::dmr::Delaunay3D(lattice, latticeTetrahedra);
  ASSERT_FALSE(latticeTetrahedra.empty());
  expectRefused(lattice, latticeTetrahedra, "cospherical nodes");
}

/** NonDegenerateDelaunay3D from a warm start gives what it gives without one, nudged nodes included. */
TEST(Delaunay3D, NudgingFromAWarmStartGivesTheSameResult)
{
  const double         side[3] = { 300.0, 260.0, 180.0 };
  const auto           start = DualMeshLikeNodes(side[0], side[1], side[2], 16.0, false, false, 12u);
  std::vector<uint8_t> freeAxes(start.size() / 3, 7u);
  for (size_t i = 0; i < freeAxes.size(); ++i)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      if (start[3 * i + k] == 0.0 || start[3 * i + k] == side[k])
      {
        freeAxes[i] &= static_cast<uint8_t>(~(1u << k));
      }
    }
  }
  itk::dmr::DelaunayWarmStart warm;
  warm.nodes = start;
  itk::dmr::NonDegenerateDelaunay3D(warm.nodes, freeAxes, 0.25, warm.tetrahedra, flatShape, rounds, Threader(2));
  size_t repairedCount = 0;
  for (uint32_t move = 0; move < 6; ++move)
  {
    const auto                          moved = MoveNodes(start, side, 0.05 * (move + 1), 200 + move);
    std::vector<double>                 a = moved, b = moved;
    Tetrahedra                          fromWarm, fresh;
    bool                                repaired = false;
    std::vector<std::array<int32_t, 4>> neighbours;
    const size_t                        nudgedWarm = itk::dmr::NonDegenerateDelaunay3D(
      a, freeAxes, 0.25, fromWarm, flatShape, rounds, Threader(2), &warm, &repaired, &neighbours);
    const size_t nudgedFresh =
      itk::dmr::NonDegenerateDelaunay3D(b, freeAxes, 0.25, fresh, flatShape, rounds, Threader(2));
    EXPECT_EQ(fromWarm, fresh) << "move " << move;
    EXPECT_EQ(a, b) << "move " << move;
    EXPECT_EQ(nudgedWarm, nudgedFresh);
    repairedCount += repaired ? 1 : 0;
    if (!neighbours.empty())
    {
      ExpectNeighboursOf(fromWarm, neighbours);
    }
    warm.tetrahedra = fromWarm;
    warm.nodes = a;
    warm.neighbours = neighbours;
  }
  EXPECT_GT(repairedCount, 0u) << "the warm start was never used";
  // near-flat tetrahedra (a lattice with tiny noise), warm-started from the tetrahedralization of a noisier one: the
  // nodes are nudged as without the warm start
  std::vector<double>  noisy = NoisyLattice(1e-2), a = NoisyLattice(1e-13), b = a;
  std::vector<uint8_t> latticeAxes(a.size() / 3, 7u);
  std::fill(latticeAxes.begin(), latticeAxes.begin() + 8, uint8_t{ 0 });
  itk::dmr::DelaunayWarmStart noisyWarm;
  noisyWarm.nodes = noisy;
  itk::dmr::Delaunay3D(noisy, noisyWarm.tetrahedra, Threader(2));
  Tetrahedra   fromWarm, fresh;
  const size_t nudged =
    itk::dmr::NonDegenerateDelaunay3D(a, latticeAxes, 0.05, fromWarm, flatShape, rounds, Threader(2), &noisyWarm);
  EXPECT_GT(nudged, 0u);
  EXPECT_EQ(nudged, itk::dmr::NonDegenerateDelaunay3D(b, latticeAxes, 0.05, fresh, flatShape, rounds, Threader(2)));
  EXPECT_EQ(a, b);
  EXPECT_EQ(fromWarm, fresh);
  // the same without the earlier positions
  a = NoisyLattice(1e-13);
  noisyWarm.nodes.clear();
  EXPECT_EQ(
    nudged,
    itk::dmr::NonDegenerateDelaunay3D(a, latticeAxes, 0.05, fromWarm, flatShape, rounds, Threader(2), &noisyWarm));
  EXPECT_EQ(a, b);
  EXPECT_EQ(fromWarm, fresh);
}
