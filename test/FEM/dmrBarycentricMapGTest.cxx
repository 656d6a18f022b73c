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
#include "dmrBarycentricMap.h"
#include "dmrDualMeshPhantom.h"
#include "dmrTestHelpers.h"
#include "itkMultiThreaderBase.h"
#include "gtest/gtest.h"

#include <cmath>
#include <cstring>
#include <limits>
#include <random>

namespace
{
/** Barycentric coordinates of point x in element e, computed independently (Cramer's rule on the D+1 system). */
template <unsigned int D>
std::array<double, D + 1>
ReferenceBarycentric(const itk::dmr::SimplexMesh<D> & mesh, size_t e, const std::array<double, D> & x)
{
  // solve [x_1-x_0 ... x_D-x_0] l = x - x_0 by Gaussian elimination with partial pivoting
  double a[D][D + 1];
  for (unsigned int r = 0; r < D; ++r)
  {
    for (unsigned int c = 0; c < D; ++c)
    {
      a[r][c] = mesh.nodes[mesh.elements[e][c + 1] * D + r] - mesh.nodes[mesh.elements[e][0] * D + r];
    }
    a[r][D] = x[r] - mesh.nodes[mesh.elements[e][0] * D + r];
  }
  for (unsigned int c = 0; c < D; ++c)
  {
    unsigned int pivot = c;
    for (unsigned int r = c + 1; r < D; ++r)
    {
      if (std::abs(a[r][c]) > std::abs(a[pivot][c]))
      {
        pivot = r;
      }
    }
    for (unsigned int k = 0; k <= D; ++k)
    {
      std::swap(a[c][k], a[pivot][k]);
    }
    for (unsigned int r = 0; r < D; ++r)
    {
      if (r != c)
      {
        const double f = a[r][c] / a[c][c];
        for (unsigned int k = 0; k <= D; ++k)
        {
          a[r][k] -= f * a[c][k];
        }
      }
    }
  }
  std::array<double, D + 1> l;
  l[0] = 1.0;
  for (unsigned int r = 0; r < D; ++r)
  {
    l[r + 1] = a[r][D] / a[r][r];
    l[0] -= l[r + 1];
  }
  return l;
}

template <unsigned int D>
void
CheckEveryPixelLiesInOneElement(const itk::dmr::Grid<D> & grid, const itk::dmr::SimplexMesh<D> & mesh)
{
  auto                        threader = itk::dmr::test::Threader(2, 2);
  itk::dmr::BarycentricMap<D> map;
  map.Build(grid, mesh, threader);
  const auto & elements = map.GetElements();
  const auto & weights = map.GetWeights();
  ASSERT_EQ(elements.size(), grid.numberOfPixels);
  ASSERT_EQ(weights.size(), grid.numberOfPixels * (D + 1));
  size_t sharedPixels = 0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const int32_t e = elements[p];
    ASSERT_GE(e, 0) << "pixel " << p;
    ASSERT_LT(static_cast<size_t>(e), mesh.elements.size());
    const auto x = itk::dmr::test::PixelPosition<D>(grid, p);
    double     sum = 0.0;
    double     y[D] = {};
    for (unsigned int v = 0; v < D + 1; ++v)
    {
      const double w = weights[p * (D + 1) + v];
      EXPECT_GE(w, 0.0);
      EXPECT_LE(w, 1.0);
      sum += w;
      for (unsigned int k = 0; k < D; ++k)
      {
        y[k] += w * mesh.nodes[mesh.elements[e][v] * D + k];
      }
    }
    EXPECT_NEAR(sum, 1.0, 1e-5) << "pixel " << p;
    for (unsigned int k = 0; k < D; ++k)
    {
      EXPECT_NEAR(y[k], x[k], 1e-4) << "pixel " << p << " axis " << k << ": the weights do not reproduce it";
    }
    // the owner is the lowest-id element that contains the pixel (the documented tie rule)
    size_t containing = 0;
    for (size_t f = 0; f < mesh.elements.size(); ++f)
    {
      const auto l = ReferenceBarycentric<D>(mesh, f, x);
      const bool inside = *std::min_element(l.begin(), l.end()) >= -1e-9;
      if (inside)
      {
        EXPECT_GE(static_cast<int32_t>(f), e) << "pixel " << p << " lies in element " << f << " < owner " << e;
        ++containing;
      }
      if (static_cast<int32_t>(f) == e)
      {
        EXPECT_TRUE(inside) << "pixel " << p << " is not inside its owner " << e;
      }
    }
    sharedPixels += containing > 1;
    if (::testing::Test::HasFailure())
    {
      return;
    }
  }
  EXPECT_GT(sharedPixels, 0u) << "no pixel on a shared edge/face: the tie rule was not exercised";
}

TEST(BarycentricMap, EveryPixelLiesInOneElementOfARegularMesh2D)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 25, 21 }, std::array<double, 2>{ 1.0, 1.5 });
  const auto              mesh = itk::dmr::MakeRegularMesh<2>(grid, { 7, 6 });
  CheckEveryPixelLiesInOneElement<2>(grid, mesh);
}

TEST(BarycentricMap, EveryPixelLiesInOneElementOfARegularMesh3D)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 13, 10, 9 }, std::array<double, 3>{ 1.0, 1.2, 0.9 });
  const auto              mesh = itk::dmr::MakeRegularMesh<3>(grid, { 5, 4, 5 });
  CheckEveryPixelLiesInOneElement<3>(grid, mesh);
}

TEST(BarycentricMap, EveryPixelLiesInOneElementOfTheDualMesh)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom();
  CheckEveryPixelLiesInOneElement<2>(phantom.GetGrid(), phantom.GetMesh());
}

// An irregular tetrahedral mesh (TetGen dual of a 3D CVT, anisotropic spacing): the row-span rasterisation must give
// the owner of the brute-force rule at every voxel.
TEST(BarycentricMap, EveryVoxelLiesInOneElementOfTheDualMesh3D)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom3D(60);
  CheckEveryPixelLiesInOneElement<3>(phantom.GetGrid(), phantom.GetMesh());
}

// The threads rasterise bands of planes; the owners and weights must not depend on how many bands there are.
template <unsigned int D>
void
CheckBuildDoesNotDependOnTheThreads(const itk::dmr::Grid<D> & grid, const itk::dmr::SimplexMesh<D> & mesh)
{
  itk::dmr::BarycentricMap<D> serial;
  serial.Build(grid, mesh, nullptr);
  for (unsigned int units : { 2u, 3u, 7u, 64u })
  {
    auto threader = itk::MultiThreaderBase::New();
    threader->SetMaximumNumberOfThreads(std::min(units, 8u));
    threader->SetNumberOfWorkUnits(units);
    itk::dmr::BarycentricMap<D> map;
    map.Build(grid, mesh, threader);
    EXPECT_EQ(map.GetElements(), serial.GetElements()) << units << " work units";
    ASSERT_EQ(map.GetWeights().size(), serial.GetWeights().size());
    EXPECT_EQ(
      0, std::memcmp(map.GetWeights().data(), serial.GetWeights().data(), serial.GetWeights().size() * sizeof(float)))
      << units << " work units";
  }
}

TEST(BarycentricMap, BuildDoesNotDependOnTheThreads)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom();
  CheckBuildDoesNotDependOnTheThreads<2>(phantom.GetGrid(), phantom.GetMesh());
  const auto phantom3 = itk::dmr::test::MakeDualMeshPhantom3D(60);
  CheckBuildDoesNotDependOnTheThreads<3>(phantom3.GetGrid(), phantom3.GetMesh());
}

template <unsigned int D>
void
CheckLinearFieldIsReproduced(const itk::dmr::Grid<D> & grid, const itk::dmr::SimplexMesh<D> & mesh)
{
  itk::dmr::BarycentricMap<D> map;
  map.Build(grid, mesh, nullptr);
  // u(x) = A x + b
  double A[D][D], b[D];
  for (unsigned int r = 0; r < D; ++r)
  {
    b[r] = 1.5 - r;
    for (unsigned int c = 0; c < D; ++c)
    {
      A[r][c] = 0.1 * (r + 1) - 0.07 * c + (r == c ? 0.3 : 0.0);
    }
  }
  std::vector<double> nodal(mesh.NumberOfNodes() * D);
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    for (unsigned int r = 0; r < D; ++r)
    {
      nodal[i * D + r] = b[r];
      for (unsigned int c = 0; c < D; ++c)
      {
        nodal[i * D + r] += A[r][c] * mesh.nodes[i * D + c];
      }
    }
  }
  std::vector<float> field(grid.numberOfPixels * D);
  map.Interpolate(nodal, 2.0, field.data(), nullptr);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = itk::dmr::test::PixelPosition<D>(grid, p);
    for (unsigned int r = 0; r < D; ++r)
    {
      double expected = b[r];
      for (unsigned int c = 0; c < D; ++c)
      {
        expected += A[r][c] * x[c];
      }
      ASSERT_NEAR(field[p * D + r], 2.0 * expected, 1e-4 * (1.0 + std::abs(expected))) << "pixel " << p;
    }
  }
}

TEST(BarycentricMap, InterpolateReproducesALinearField)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom();
  CheckLinearFieldIsReproduced<2>(phantom.GetGrid(), phantom.GetMesh());
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 13, 10, 9 }, std::array<double, 3>{ 1.0, 1.2, 0.9 });
  const auto              mesh = itk::dmr::MakeRegularMesh<3>(grid, { 4, 4, 3 });
  CheckLinearFieldIsReproduced<3>(grid, mesh);
}

TEST(BarycentricMap, GatherConservesTheTotalLoad)
{
  // the shape functions are a partition of unity: sum_a f_a = scale sum_x f(x), per component
  const auto                            phantom = itk::dmr::test::MakeDualMeshPhantom();
  const auto                            grid = phantom.GetGrid();
  const auto &                          mesh = phantom.GetMesh();
  std::mt19937                          engine(3u);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float>                    field(grid.numberOfPixels * 2);
  double                                total[2] = {};
  for (size_t i = 0; i < field.size(); ++i)
  {
    field[i] = u(engine);
    total[i % 2] += field[i];
  }
  itk::dmr::BarycentricMap<2> map;
  map.Build(grid, mesh, nullptr);
  std::vector<double> nodal;
  map.Gather(field.data(), 0.5, nodal, nullptr);
  ASSERT_EQ(nodal.size(), mesh.NumberOfNodes() * 2);
  double sum[2] = {};
  for (size_t i = 0; i < nodal.size(); ++i)
  {
    sum[i % 2] += nodal[i];
  }
  EXPECT_NEAR(sum[0], 0.5 * total[0], 1e-4);
  EXPECT_NEAR(sum[1], 0.5 * total[1], 1e-4);
  // a field that is 1 at one pixel only loads exactly the vertices of its element with its weights
  std::vector<float> single(grid.numberOfPixels * 2, 0.0f);
  const size_t       pixel = 17 + 23 * grid.size[0];
  single[pixel * 2] = 1.0f;
  map.Gather(single.data(), 1.0, nodal, nullptr);
  const auto & element = mesh.elements[map.GetElements()[pixel]];
  for (unsigned int v = 0; v < 3; ++v)
  {
    EXPECT_NEAR(nodal[element[v] * 2], map.GetWeights()[pixel * 3 + v], 1e-7);
  }
}

TEST(BarycentricMap, GatherIsTheSameHoweverThePixelsAreSplitAndWithinItsRounding)
{
  // the fixed-point sums (dmrFixedPointGather.h) do not depend on the order of the additions: the one-thread gather
  // and the threaded one agree bit for bit, also on a grid large enough for 32 chunks; each nodal value is within the
  // rounding of its terms (half a quantum each) of the exact sum, computed here in long double
  const itk::dmr::Grid<2>               grid(std::array<size_t, 2>{ 640, 480 }, std::array<double, 2>{ 0.7, 1.1 });
  const auto                            mesh = itk::dmr::MakeRegularMesh<2>(grid, { 9, 7 });
  std::mt19937                          engine(11u);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float>                    field(grid.numberOfPixels * 2);
  for (auto & f : field)
  {
    f = u(engine) * std::pow(10.0f, static_cast<float>(static_cast<int>(engine() % 9)) - 4.0f); // 8 decades
  }
  itk::dmr::BarycentricMap<2> map;
  map.Build(grid, mesh, nullptr);
  auto                threader = itk::dmr::test::Threader(3, 3);
  const double        scale = 0.77;
  std::vector<double> one, threaded;
  map.Gather(field.data(), scale, one, nullptr);
  map.Gather(field.data(), scale, threaded, threader);
  ASSERT_EQ(one.size(), threaded.size());
  EXPECT_EQ(std::memcmp(one.data(), threaded.data(), one.size() * sizeof(double)), 0);

  float maxAbs = 0.0f;
  for (const float f : field)
  {
    maxAbs = std::max(maxAbs, std::abs(f));
  }
  const double             quantum = itk::dmr::GatherQuantum(maxAbs, static_cast<long long>(grid.numberOfPixels));
  std::vector<long double> exact(one.size(), 0.0L);
  std::vector<size_t>      terms(one.size(), 0);
  const auto &             weights = map.GetWeights();
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto & element = mesh.elements[map.GetElements()[p]];
    for (unsigned int v = 0; v < 3; ++v)
    {
      for (unsigned int k = 0; k < 2; ++k)
      {
        exact[element[v] * 2 + k] += static_cast<long double>(weights[p * 3 + v]) * field[p * 2 + k];
        ++terms[element[v] * 2 + k];
      }
    }
  }
  for (size_t i = 0; i < one.size(); ++i)
  {
    const long double bound = scale * (0.5L * quantum * terms[i]) * (1.0L + 1e-12L) + 1e-15L * std::abs(exact[i]);
    EXPECT_LE(std::abs(static_cast<long double>(one[i]) - scale * exact[i]), bound) << "node value " << i;
  }

  // no force: zeros; a value that is not a number: NaN everywhere, as on the GPU
  std::vector<float> zero(field.size(), 0.0f);
  map.Gather(zero.data(), scale, one, threader);
  EXPECT_EQ(one, std::vector<double>(one.size(), 0.0));
  field[12345] = std::numeric_limits<float>::quiet_NaN();
  map.Gather(field.data(), scale, one, threader);
  for (const double value : one)
  {
    EXPECT_TRUE(std::isnan(value));
  }
}

TEST(BarycentricMap, MeshThatDoesNotCoverTheImageThrows)
{
  const itk::dmr::Grid<2>     grid(std::array<size_t, 2>{ 24, 20 }, std::array<double, 2>{ 1.0, 1.0 });
  const itk::dmr::Grid<2>     half(std::array<size_t, 2>{ 12, 20 }, std::array<double, 2>{ 1.0, 1.0 });
  const auto                  mesh = itk::dmr::MakeRegularMesh<2>(half, { 4, 5 });
  itk::dmr::BarycentricMap<2> map;
  EXPECT_THROW(map.Build(grid, mesh, nullptr), itk::ExceptionObject);
  // the message names the first pixel outside the mesh (x = 12, y = 0), whatever the threads
  auto threader = itk::dmr::test::Threader(2, 3);
  try
  {
    map.Build(grid, mesh, threader);
    ADD_FAILURE() << "no exception";
  }
  catch (const itk::ExceptionObject & e)
  {
    EXPECT_NE(std::string(e.GetDescription()).find("pixel 12 is not covered"), std::string::npos) << e.GetDescription();
  }
}
} // namespace

// GatherTerm rounds by the processor's conversion instruction where there is one: the same integers as llrint for
// ties (to even), negative values, tiny and large terms up to the 2^62 that GatherQuantum allows
TEST(BarycentricMap, GatherTermRoundsAsLlrint)
{
  std::mt19937                          rng(31);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::uniform_real_distribution<float> force(-1000.0f, 1000.0f);
  std::uniform_int_distribution<int>    exponent(-70, 50);
  size_t                                ties = 0;
  for (int trial = 0; trial < 200000; ++trial)
  {
    const bool   tie = trial % 7 == 0; // 1 x (k + 1/2) x 1
    const float  w = tie ? 1.0f : unit(rng);
    const float  f = tie ? std::floor(force(rng)) + 0.5f : force(rng);
    const double inverse = std::ldexp(1.0, tie ? 0 : exponent(rng)); // a power of two, as GatherQuantum's
    const double term = static_cast<double>(w) * static_cast<double>(f) * inverse;
    ASSERT_EQ(itk::dmr::GatherTerm(w, f, inverse), llrint(term)) << w << " x " << f << " x " << inverse;
    ties += term == std::floor(term) + 0.5;
  }
  EXPECT_GT(ties, 10000u);
  for (const double big : { std::ldexp(1.0, 62) - 1024.0, -std::ldexp(1.0, 62) + 1024.0, 0.5, -0.5, 1.5, -2.5, -0.0 })
  {
    EXPECT_EQ(itk::dmr::GatherTerm(1.0f, 1.0f, big), llrint(big)) << big;
  }
}
