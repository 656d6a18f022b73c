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
#include "dmrFieldOps.h"
#include "dmrTestHelpers.h"
#include "itkMultiThreaderBase.h"
#include "gtest/gtest.h"

#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <set>

namespace
{
/** v = amplitude * (1, -0.75) * exp(-|i - c|^2 / (2 sigma^2)) pixels (i the pixel index, c the grid centre),
 * stored in mm (times the spacing) on a 64x64 grid; below 1e-3 px at the border for sigma = 8. */
std::vector<float>
GaussianBump(const itk::dmr::Grid<2> & grid, double amplitude, double sigma)
{
  std::vector<float> v(grid.numberOfPixels * 2);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto   i = grid.Index(p);
    const double g =
      amplitude * std::exp(-((i[0] - 31.5) * (i[0] - 31.5) + (i[1] - 31.5) * (i[1] - 31.5)) / (2 * sigma * sigma));
    v[2 * p] = static_cast<float>(g * grid.spacing[0]);
    v[2 * p + 1] = static_cast<float>(-0.75 * g * grid.spacing[1]);
  }
  return v;
}

/** Checks exp(v) o exp(-v) = Id and det > 0; returns exp(v) in pixel units. */
std::vector<double>
CheckExpInverse(const itk::dmr::Grid<2> & grid)
{
  auto               threader = itk::dmr::test::Threader(2, 2);
  const auto         v = GaussianBump(grid, 3.0, 8.0); // 3 px peak, < 1e-3 px at the border
  std::vector<float> minusV(v.size());
  for (size_t i = 0; i < v.size(); ++i)
  {
    minusV[i] = -v[i];
  }
  EXPECT_NEAR(itk::dmr::FieldBoundsInPixels<2>(grid, v.data()).displacement, 3.0, 0.05); // peak between pixels
  std::vector<float> expV(v.size()), expMinusV(v.size()), scratch, composed(v.size());
  // halved until below half a pixel: 3 -> 1.5 -> 0.75 -> 0.375
  EXPECT_EQ(itk::dmr::ExponentialField<2>(grid, v.data(), expV.data(), scratch, threader), 3u);
  EXPECT_EQ(itk::dmr::ExponentialField<2>(grid, minusV.data(), expMinusV.data(), scratch, threader), 3u);
  // exp(v) o exp(-v) = identity, up to the scaling-and-squaring error: with the 0.5 px stopping rule each
  // exponential is off by about |v| |grad v| / 16 (3 px x 0.23 / 16 = 0.045 px here), so the composition by about
  // twice that; measured 0.090 px (0.068 px for a field along one axis). A wrong composition order, scale or
  // squaring count gives errors of whole pixels.
  itk::dmr::ComposeFields<2>(grid, expV.data(), expMinusV.data(), composed.data(), threader);
  EXPECT_LT(itk::dmr::FieldBoundsInPixels<2>(grid, composed.data()).displacement, 0.1);
  itk::dmr::ComposeFields<2>(grid, expMinusV.data(), expV.data(), composed.data(), threader);
  EXPECT_LT(itk::dmr::FieldBoundsInPixels<2>(grid, composed.data()).displacement, 0.1);
  // and exp(v) really moves pixels: the test is not trivially satisfied
  EXPECT_GT(itk::dmr::FieldBoundsInPixels<2>(grid, expV.data()).displacement, 2.5);
  // diffeomorphic: positive Jacobian everywhere; it stretches somewhere and compresses elsewhere
  std::vector<float> jac(grid.numberOfPixels);
  const auto         range = itk::dmr::JacobianDeterminant<2>(grid, expV.data(), jac.data(), threader);
  EXPECT_GT(range.first, 0.0);
  EXPECT_LT(range.first, 0.95);
  EXPECT_GT(range.second, 1.05);
  EXPECT_EQ(*std::min_element(jac.begin(), jac.end()), static_cast<float>(range.first));
  std::vector<double> inPixels(expV.size());
  for (size_t i = 0; i < expV.size(); ++i)
  {
    inPixels[i] = expV[i] / grid.spacing[i % 2];
  }
  return inPixels;
}

TEST(ExponentialField, ExpOfVComposedWithExpOfMinusVIsTheIdentity)
{
  CheckExpInverse(itk::dmr::Grid<2>(std::array<size_t, 2>{ 64, 64 }, std::array<double, 2>{ 1.0, 1.0 }));
}

TEST(ExponentialField, AnisotropicSpacingGivesTheSameMapInPixels)
{
  // the same field in pixels on a 1.5 x 0.75 mm grid: the spacing is a pure change of units, so exp(v) in pixels
  // is the isotropic one (float rounding aside)
  const auto isotropic =
    CheckExpInverse(itk::dmr::Grid<2>(std::array<size_t, 2>{ 64, 64 }, std::array<double, 2>{ 1.0, 1.0 }));
  const auto anisotropic =
    CheckExpInverse(itk::dmr::Grid<2>(std::array<size_t, 2>{ 64, 64 }, std::array<double, 2>{ 1.5, 0.75 }));
  ASSERT_EQ(isotropic.size(), anisotropic.size());
  for (size_t i = 0; i < isotropic.size(); ++i)
  {
    ASSERT_NEAR(anisotropic[i], isotropic[i], 1e-4) << "component " << i;
  }
}

TEST(ExponentialField, SmallFieldIsNotSquaredAndConstantFieldIsATranslation)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 24, 20 }, std::array<double, 2>{ 1.0, 2.0 });
  std::vector<float>      v(grid.numberOfPixels * 2), out(v.size()), scratch;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    v[2 * p] = 0.3f;
    v[2 * p + 1] = -0.8f; // 0.4 px
  }
  EXPECT_EQ(itk::dmr::ExponentialField<2>(grid, v.data(), out.data(), scratch, nullptr), 0u);
  EXPECT_EQ(out, v);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    v[2 * p] = 2.5f;
    v[2 * p + 1] = -3.0f; // 2.5 px and 1.5 px
  }
  EXPECT_EQ(itk::dmr::ExponentialField<2>(grid, v.data(), out.data(), scratch, nullptr), 3u);
  for (size_t i = 0; i < v.size(); ++i)
  {
    EXPECT_NEAR(out[i], v[i], 1e-5);
  }
}

TEST(ComposeFields, ComposingWithZeroGivesTheField)
{
  const itk::dmr::Grid<2>               grid(std::array<size_t, 2>{ 32, 28 }, std::array<double, 2>{ 1.0, 1.7 });
  std::mt19937                          engine(8u);
  std::uniform_real_distribution<float> u(-2.0f, 2.0f);
  std::vector<float>                    w(grid.numberOfPixels * 2), zero(w.size(), 0.0f), out(w.size());
  for (auto & x : w)
  {
    x = u(engine);
  }
  // W o Id = W
  itk::dmr::ComposeFields<2>(grid, w.data(), zero.data(), out.data(), nullptr);
  EXPECT_EQ(out, w);
  // Id o V = V
  itk::dmr::ComposeFields<2>(grid, zero.data(), w.data(), out.data(), nullptr);
  EXPECT_EQ(out, w);
}

/** out(x) = v(x) + w(x + v(x)) at one pixel, ComposeFields' definition written out (multilinear w, clamped). */
template <unsigned int D>
void
ComposeOnePixel(const itk::dmr::Grid<D> & grid, const float * w, const float * v, size_t p, float * out)
{
  const auto idx = grid.Index(p);
  double     c[D], s[D] = {};
  for (unsigned int k = 0; k < D; ++k)
  {
    c[k] = static_cast<double>(idx[k]) + static_cast<double>(v[p * D + k]) / grid.spacing[k];
  }
  itk::dmr::InterpolateAdd<D, D>(grid, w, c, 1.0, s);
  for (unsigned int k = 0; k < D; ++k)
  {
    out[k] = static_cast<float>(static_cast<double>(v[p * D + k]) + s[k]);
  }
}

/** ComposeFields against ComposeOnePixel at every pixel, bit for bit (the CPU loop takes two pixels of a row at once
 * where it can), into a separate output and in place (out = v), on 1 and 3 work units. */
template <unsigned int D>
void
ExpectComposeEqualsOnePixelAtATime(const itk::dmr::Grid<D> &  grid,
                                   const std::vector<float> & w,
                                   const std::vector<float> & v)
{
  std::vector<float> expected(v.size());
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    ComposeOnePixel<D>(grid, w.data(), v.data(), p, &expected[p * D]);
  }
  auto threader = itk::dmr::test::Threader(3, 3);
  for (itk::MultiThreaderBase * t : { static_cast<itk::MultiThreaderBase *>(nullptr), threader.GetPointer() })
  {
    std::vector<float> out(v.size()), inPlace = v;
    itk::dmr::ComposeFields<D>(grid, w.data(), v.data(), out.data(), t);
    itk::dmr::ComposeFields<D>(grid, w.data(), inPlace.data(), inPlace.data(), t);
    EXPECT_EQ(0, std::memcmp(out.data(), expected.data(), out.size() * sizeof(float)))
      << (t ? "3 work units" : "serial");
    EXPECT_EQ(0, std::memcmp(inPlace.data(), expected.data(), out.size() * sizeof(float)))
      << (t ? "3 work units" : "serial") << ", in place";
  }
}

TEST(ComposeFields, EveryPixelGetsTheValueItGetsAlone)
{
  std::mt19937                          engine(21u);
  std::uniform_real_distribution<float> u(-3.0f, 3.0f);
  // odd row length (one pixel alone at the end of every row), anisotropic spacing; v runs out of the grid (clamping)
  // and is exactly 0 in a band (positions on the grid: corners of weight 0)
  {
    const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 37, 29 }, std::array<double, 2>{ 1.3, 0.7 });
    std::vector<float>      w(grid.numberOfPixels * 2), v(w.size());
    for (size_t i = 0; i < w.size(); ++i)
    {
      w[i] = u(engine);
      v[i] = (i / 2) % 37 < 9 ? 0.0f : 2.0f * u(engine);
    }
    SCOPED_TRACE("2D");
    ExpectComposeEqualsOnePixelAtATime<2>(grid, w, v);
    // a non-finite value of w at corners of weight 0 of their row neighbours: those pixels stay finite
    std::vector<float> wInf = w;
    for (size_t p : { size_t(5 * 37 + 9), size_t(12 * 37 + 4), size_t(20 * 37 + 9) })
    {
      wInf[2 * p] = std::numeric_limits<float>::infinity();
      wInf[2 * p + 1] = std::numeric_limits<float>::quiet_NaN();
    }
    SCOPED_TRACE("2D, non-finite values of w");
    ExpectComposeEqualsOnePixelAtATime<2>(grid, wInf, v);
  }
  {
    const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 15, 12, 9 }, std::array<double, 3>{ 1.0, 1.5, 2.5 });
    std::vector<float>      w(grid.numberOfPixels * 3), v(w.size());
    for (size_t i = 0; i < w.size(); ++i)
    {
      w[i] = u(engine);
      v[i] = (i / 3) % 15 > 11 ? 0.0f : 2.5f * u(engine);
    }
    SCOPED_TRACE("3D");
    ExpectComposeEqualsOnePixelAtATime<3>(grid, w, v);
  }
}

TEST(ComposeFields, ComposesTranslationsAndSamplesAtTheDisplacedPoint)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 32, 28 }, std::array<double, 2>{ 2.0, 0.5 });
  // w linear in x: w(x) = (0.1 x0, 0) mm; v constant (2 mm, 0.5 mm) = (1 px, 1 px)
  std::vector<float> w(grid.numberOfPixels * 2), v(w.size()), out(w.size());
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = itk::dmr::test::PixelPosition<2>(grid, p);
    w[2 * p] = static_cast<float>(0.1 * x[0]);
    w[2 * p + 1] = 0.0f;
    v[2 * p] = 2.0f;
    v[2 * p + 1] = 0.5f;
  }
  itk::dmr::ComposeFields<2>(grid, w.data(), v.data(), out.data(), nullptr);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    if (idx[0] + 1 >= static_cast<int64_t>(grid.size[0]) || idx[1] + 1 >= static_cast<int64_t>(grid.size[1]))
    {
      continue; // x + v leaves the grid: w is clamped there
    }
    const auto x = itk::dmr::test::PixelPosition<2>(grid, p);
    EXPECT_NEAR(out[2 * p], 2.0 + 0.1 * (x[0] + 2.0), 1e-5) << "pixel " << p;
    EXPECT_NEAR(out[2 * p + 1], 0.5, 1e-6) << "pixel " << p;
  }
}

TEST(JacobianDeterminant, LinearFieldGivesDetOfIPlusA)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 20, 16 }, std::array<double, 2>{ 1.3, 0.7 });
  const double            A[2][2] = { { 0.2, -0.1 }, { 0.3, -0.25 } };
  std::vector<float>      u(grid.numberOfPixels * 2), jac(grid.numberOfPixels);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = itk::dmr::test::PixelPosition<2>(grid, p);
    u[2 * p] = static_cast<float>(A[0][0] * x[0] + A[0][1] * x[1]);
    u[2 * p + 1] = static_cast<float>(A[1][0] * x[0] + A[1][1] * x[1]);
  }
  const double expected = (1 + A[0][0]) * (1 + A[1][1]) - A[0][1] * A[1][0];
  const auto   range = itk::dmr::JacobianDeterminant<2>(grid, u.data(), jac.data(), nullptr);
  EXPECT_NEAR(range.first, expected, 1e-5);
  EXPECT_NEAR(range.second, expected, 1e-5);
  for (float j : jac)
  {
    EXPECT_NEAR(j, expected, 1e-5);
  }
  // 3D: a folding field (u = -2 x along axis 0) has a negative determinant
  const itk::dmr::Grid<3> grid3(std::array<size_t, 3>{ 6, 5, 4 }, std::array<double, 3>{ 1.0, 2.0, 0.5 });
  std::vector<float>      u3(grid3.numberOfPixels * 3, 0.0f);
  for (size_t p = 0; p < grid3.numberOfPixels; ++p)
  {
    u3[3 * p] = static_cast<float>(-2.0 * itk::dmr::test::PixelPosition<3>(grid3, p)[0]);
    u3[3 * p + 2] = static_cast<float>(0.5 * itk::dmr::test::PixelPosition<3>(grid3, p)[2]);
  }
  const auto range3 = itk::dmr::JacobianDeterminant<3>(grid3, u3.data(), nullptr, nullptr);
  EXPECT_NEAR(range3.first, -1.5, 1e-5);
  EXPECT_NEAR(range3.second, -1.5, 1e-5);
}
} // namespace

// InterpolateAddPair computes the corner weights once for two images; each output must be its InterpolateAdd, bit for
// bit (the density filter's force relies on it to give the same floats as before)
TEST(InterpolateAddPair, EqualsTwoInterpolateAddsBitForBit)
{
  const itk::dmr::Grid<3>                grid(std::array<size_t, 3>{ 7, 5, 4 }, std::array<double, 3>{ 0.7, 1.1, 2.5 });
  std::mt19937                           rng(11);
  std::uniform_real_distribution<float>  value(-3.0f, 3.0f);
  std::uniform_real_distribution<double> position(-1.5, 8.5); // inside, on and outside the border
  std::vector<float>                     a(grid.numberOfPixels), b(grid.numberOfPixels * 3);
  for (auto & x : a)
  {
    x = value(rng);
  }
  for (auto & x : b)
  {
    x = value(rng);
  }
  for (int trial = 0; trial < 2000; ++trial)
  {
    double c[3];
    for (double & x : c)
    {
      x = trial % 7 == 0 ? std::floor(position(rng)) : position(rng); // whole indices too (zero weights)
    }
    const double w = trial % 2 ? 1.0 : 0.37;
    double       sa = 0.25, sb[3] = { -1.0, 0.0, 2.0 }, pa = 0.25, pb[3] = { -1.0, 0.0, 2.0 };
    itk::dmr::InterpolateAdd<3, 1>(grid, a.data(), c, w, &sa);
    itk::dmr::InterpolateAdd<3, 3>(grid, b.data(), c, w, sb);
    itk::dmr::InterpolateAddPair<3, 1, 3>(grid, a.data(), b.data(), c, w, &pa, pb);
    ASSERT_EQ(std::memcmp(&pa, &sa, sizeof(double)), 0) << "trial " << trial;
    ASSERT_EQ(std::memcmp(pb, sb, sizeof(sb)), 0) << "trial " << trial;
  }
}

// the parallel maxima are the sequential ones
TEST(FieldMaxima, ParallelEqualsSequential)
{
  const itk::dmr::Grid<2>               grid(std::array<size_t, 2>{ 301, 157 }, std::array<double, 2>{ 0.8, 1.3 });
  std::mt19937                          rng(5);
  std::uniform_real_distribution<float> value(-4.0f, 4.0f);
  std::vector<float>                    v(grid.numberOfPixels * 2);
  for (auto & x : v)
  {
    x = value(rng);
  }
  v[2 * 40000 + 1] = 60.0f; // one large value in a middle chunk
  auto threader = itk::MultiThreaderBase::New();
  threader->SetNumberOfWorkUnits(4);
  // the definitions, pixel by pixel
  double displacement = 0.0, neighbourDifference = 0.0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    for (unsigned int k = 0; k < 2; ++k)
    {
      displacement = std::max(displacement, std::abs(static_cast<double>(v[p * 2 + k])) / grid.spacing[k]);
      if (idx[k] + 1 < static_cast<int64_t>(grid.size[k]))
      {
        const size_t q = p + grid.stride[k];
        for (unsigned int r = 0; r < 2; ++r)
        {
          neighbourDifference =
            std::max(neighbourDifference, std::abs(static_cast<double>(v[q * 2 + r]) - v[p * 2 + r]) / grid.spacing[r]);
        }
      }
    }
  }
  EXPECT_EQ(displacement, 60.0 / 1.3);
  EXPECT_GT(neighbourDifference, 50.0 / 1.3);
  // both in one pass: the same values, with or without the threader
  for (itk::MultiThreaderBase * t : std::array<itk::MultiThreaderBase *, 2>{ threader.GetPointer(), nullptr })
  {
    const auto bounds = itk::dmr::FieldBoundsInPixels<2>(grid, v.data(), t);
    EXPECT_EQ(bounds.displacement, displacement);
    EXPECT_EQ(bounds.neighbourDifference, neighbourDifference);
  }
}

// ExponentialField's squarings alternate between out and scratch: the result is that of scaling, then composing the
// field with itself squarings times, bit for bit, for odd and even counts, also when scratch holds v (the registration
// passes the update's own storage), and the bounds it reports are FieldBoundsInPixels
TEST(ExponentialField, SquaringsWithoutCopiesGiveTheSquaredField)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 53, 41 }, std::array<double, 2>{ 1.2, 0.9 });
  auto                    threader = itk::MultiThreaderBase::New();
  threader->SetNumberOfWorkUnits(3);
  std::set<unsigned int> counts;
  for (const float amplitude : { 0.3f, 0.9f, 1.7f, 3.1f, 6.5f })
  {
    std::vector<float> v(grid.numberOfPixels * 2);
    for (size_t p = 0; p < grid.numberOfPixels; ++p)
    {
      const auto idx = grid.Index(p);
      v[2 * p] = amplitude * static_cast<float>(std::sin(0.11 * idx[0] + 0.07 * idx[1]));
      v[2 * p + 1] = amplitude * static_cast<float>(std::cos(0.05 * idx[0] - 0.13 * idx[1]));
    }
    // reference: the loop of scale, copy and compose
    const auto   expected = itk::dmr::FieldBoundsInPixels<2>(grid, v.data());
    const double maxNorm = std::max(expected.displacement, expected.neighbourDifference);
    unsigned int squarings = 0;
    while (maxNorm / std::ldexp(1.0, static_cast<int>(squarings)) > 0.5 && squarings < 30)
    {
      ++squarings;
    }
    std::vector<float> reference(v.size()), copy(v.size());
    const float        scale = static_cast<float>(std::ldexp(1.0, -static_cast<int>(squarings)));
    for (size_t i = 0; i < v.size(); ++i)
    {
      reference[i] = v[i] * scale;
    }
    for (unsigned int s = 0; s < squarings; ++s)
    {
      copy = reference;
      itk::dmr::ComposeFields<2>(grid, copy.data(), copy.data(), reference.data(), nullptr);
    }

    std::vector<float>    out(v.size()), scratch;
    itk::dmr::FieldBounds bounds;
    EXPECT_EQ(itk::dmr::ExponentialField<2>(grid, v.data(), out.data(), scratch, threader, &bounds), squarings);
    EXPECT_EQ(out, reference) << "amplitude " << amplitude;
    EXPECT_EQ(bounds.displacement, expected.displacement);
    EXPECT_EQ(bounds.neighbourDifference, expected.neighbourDifference);
    std::vector<float> inScratch = v, out2(v.size());
    EXPECT_EQ(itk::dmr::ExponentialField<2>(grid, inScratch.data(), out2.data(), inScratch, threader), squarings);
    EXPECT_EQ(out2, reference) << "amplitude " << amplitude << ", v in scratch";
    counts.insert(squarings);
  }
  EXPECT_TRUE(counts.count(2) && counts.count(3)) << "odd and even numbers of squarings";
}

// the index advanced pixel by pixel is grid.Index(p), from any start, across rows and slices
TEST(ForEachPixel, GivesEveryPixelOfTheRangeWithItsIndex)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 7, 5, 4 }, std::array<double, 3>{ 1.0, 1.0, 1.0 });
  for (const std::array<size_t, 2> range : { std::array<size_t, 2>{ 0, 140 },
                                             std::array<size_t, 2>{ 3, 41 },
                                             std::array<size_t, 2>{ 34, 36 },
                                             std::array<size_t, 2>{ 139, 140 },
                                             std::array<size_t, 2>{ 20, 20 } })
  {
    size_t next = range[0];
    itk::dmr::ForEachPixel(grid, range[0], range[1], [&](size_t p, const std::array<int64_t, 3> & idx) {
      EXPECT_EQ(p, next++);
      EXPECT_EQ(idx, grid.Index(p)) << "pixel " << p;
    });
    EXPECT_EQ(next, range[1]);
  }
}

namespace
{
/** The corner loop as it was written with std::floor (before the truncation that replaced it), the reference for
 * InterpolateAdd's sums. */
template <unsigned int D, unsigned int NComp>
void
InterpolateAddWithFloor(const itk::dmr::Grid<D> & grid, const float * data, const double * cidx, double w, double * out)
{
  size_t base = 0, step[D];
  double frac[D];
  for (unsigned int k = 0; k < D; ++k)
  {
    const double hi = static_cast<double>(grid.size[k] - 1);
    const double c = cidx[k] < 0.0 ? 0.0 : (cidx[k] > hi ? hi : cidx[k]);
    double       f = std::floor(c);
    size_t       i = static_cast<size_t>(f);
    if (i >= grid.size[k] - 1)
    {
      i = grid.size[k] > 1 ? grid.size[k] - 2 : 0;
      f = static_cast<double>(i);
    }
    base += i * grid.stride[k];
    step[k] = grid.size[k] > 1 ? grid.stride[k] : 0;
    frac[k] = c - f;
  }
  for (unsigned int corner = 0; corner < (1u << D); ++corner)
  {
    double weight = w;
    size_t offset = base;
    for (unsigned int k = 0; k < D; ++k)
    {
      weight *= (corner & (1u << k)) ? frac[k] : 1.0 - frac[k];
      offset += (corner & (1u << k)) ? step[k] : 0;
    }
    if (weight != 0.0)
    {
      for (unsigned int c = 0; c < NComp; ++c)
      {
        out[c] += weight * static_cast<double>(data[offset * NComp + c]);
      }
    }
  }
}
} // namespace

// The interpolation finds its cell by truncating the clamped continuous index, not by std::floor (which baseline x86-64
// code evaluates slowly): the sums must be those of the floor version bit for bit, inside, on whole and half indices,
// at -0, on and beyond the border, on axes of size 1 and 2
TEST(InterpolateAdd, TruncationGivesTheFloorVersionsSumsBitForBit)
{
  std::mt19937                           rng(23);
  std::uniform_real_distribution<float>  value(-3.0f, 3.0f);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const itk::dmr::Grid<3>                grids[] = {
                   itk::dmr::Grid<3>(std::array<size_t, 3>{ 9, 6, 5 }, std::array<double, 3>{ 0.7, 1.1, 2.5 }),
                   itk::dmr::Grid<3>(std::array<size_t, 3>{ 4, 1, 2 }, std::array<double, 3>{ 1.0, 1.0, 3.0 })
  };
  size_t compared = 0, onWholeIndex = 0;
  for (const auto & grid : grids)
  {
    std::vector<float> data(grid.numberOfPixels * 3);
    for (auto & x : data)
    {
      x = value(rng);
    }
    for (int trial = 0; trial < 20000; ++trial)
    {
      double c[3];
      for (unsigned int k = 0; k < 3; ++k)
      {
        const double hi = static_cast<double>(grid.size[k] - 1);
        const double x = -2.0 + (hi + 4.0) * unit(rng);
        switch (trial % 6)
        {
          case 0:
            c[k] = std::floor(x); // whole indices: zero weights
            break;
          case 1:
            c[k] = std::floor(x) + 0.5;
            break;
          case 2:
            c[k] = k == 0 ? -0.0 : x;
            break;
          case 3:
            c[k] = k == 1 ? hi : x; // the last index, where the cell is clamped
            break;
          default:
            c[k] = x;
        }
      }
      onWholeIndex += trial % 6 == 0;
      const double w = trial % 2 ? 1.0 : 0.37;
      double       got[3] = { 0.25, -1.0, 0.0 }, expected[3] = { 0.25, -1.0, 0.0 };
      itk::dmr::InterpolateAdd<3, 3>(grid, data.data(), c, w, got);
      InterpolateAddWithFloor<3, 3>(grid, data.data(), c, w, expected);
      ASSERT_EQ(std::memcmp(got, expected, sizeof(got)), 0)
        << "trial " << trial << " at " << c[0] << ", " << c[1] << ", " << c[2];
      ++compared;
    }
  }
  EXPECT_EQ(compared, 40000u);
  EXPECT_GT(onWholeIndex, 6000u);
}

// FieldBoundsInPixels divides the largest values by the spacing once instead of at every pixel; division by a positive
// number keeps the order, so the bounds must equal the per-pixel definition exactly, for fields whose values span many
// binades and spacings that are not powers of two, in 2D and 3D
TEST(FieldMaxima, DividingOnceEqualsDividingAtEveryPixel)
{
  std::mt19937                           rng(29);
  std::uniform_real_distribution<double> mantissa(-1.0, 1.0);
  std::uniform_int_distribution<int>     binade(-20, 12);
  auto                                   threader = itk::dmr::test::Threader(2, 2);
  auto                                   check = [&](const auto & grid, const std::vector<float> & v) {
    constexpr unsigned int D = std::remove_reference_t<decltype(grid)>::Dimension;
    double                 displacement = 0.0, neighbourDifference = 0.0;
    for (size_t p = 0; p < grid.numberOfPixels; ++p)
    {
      const auto idx = grid.Index(p);
      for (unsigned int k = 0; k < D; ++k)
      {
        displacement = std::max(displacement, std::abs(static_cast<double>(v[p * D + k])) / grid.spacing[k]);
        if (idx[k] + 1 < static_cast<int64_t>(grid.size[k]))
        {
          for (unsigned int r = 0; r < D; ++r)
          {
            neighbourDifference =
              std::max(neighbourDifference,
                       std::abs(static_cast<double>(v[(p + grid.stride[k]) * D + r]) - v[p * D + r]) / grid.spacing[r]);
          }
        }
      }
    }
    const auto bounds = itk::dmr::FieldBoundsInPixels<D>(grid, v.data(), threader);
    EXPECT_EQ(bounds.displacement, displacement);
    EXPECT_EQ(bounds.neighbourDifference, neighbourDifference);
  };
  for (int trial = 0; trial < 40; ++trial)
  {
    const itk::dmr::Grid<2> grid2(std::array<size_t, 2>{ 37, 29 }, std::array<double, 2>{ 0.703125, 1.0 / 3.0 });
    const itk::dmr::Grid<3> grid3(std::array<size_t, 3>{ 11, 9, 7 }, std::array<double, 3>{ 0.977, 2.5, 1.0 / 7.0 });
    std::vector<float>      v2(grid2.numberOfPixels * 2), v3(grid3.numberOfPixels * 3);
    for (auto * v : { &v2, &v3 })
    {
      for (auto & x : *v)
      {
        const double m = mantissa(rng); // drawn before the exponent: argument order is unspecified
        x = static_cast<float>(std::ldexp(m, binade(rng)));
      }
    }
    check(grid2, v2);
    check(grid3, v3);
  }
}

// the rasterisation's floor and ceil by truncation are std::floor and std::ceil (up to the sign of a zero result) for
// whole and fractional values of every magnitude, both signs, around 2^52 and 2^63, infinities and NaN
TEST(FloorByTruncation, EqualsStdFloorAndCeil)
{
  std::mt19937                           rng(37);
  std::uniform_real_distribution<double> mantissa(-1.0, 1.0);
  std::uniform_int_distribution<int>     binade(-30, 70);
  std::vector<double>                    values = { 0.0,
                                                    -0.0,
                                                    0.5,
                                                    -0.5,
                                                    -1.0,
                                                    1e-300,
                                                    -1e-300,
                                                    4503599627370495.5,
                                                    -4503599627370495.5,
                                                    4503599627370496.0,
                                                    -4503599627370497.0,
                                                    9223372036854775808.0,
                                                    -9223372036854775808.0,
                                                    1e300,
                                                    std::numeric_limits<double>::infinity(),
                                                    -std::numeric_limits<double>::infinity() };
  for (int i = 0; i < 100000; ++i)
  {
    const double m = mantissa(rng); // drawn before the exponent: argument order is unspecified
    const double x = std::ldexp(m, binade(rng));
    values.push_back(i % 3 == 0 ? std::floor(x) : x);
  }
  for (const double x : values)
  {
    ASSERT_EQ(itk::dmr::FloorByTruncation(x), std::floor(x)) << x;
    ASSERT_EQ(itk::dmr::CeilByTruncation(x), std::ceil(x)) << x;
  }
  EXPECT_TRUE(std::isnan(itk::dmr::FloorByTruncation(std::nan(""))));
  EXPECT_TRUE(std::isnan(itk::dmr::CeilByTruncation(std::nan(""))));
}

namespace
{
/** w = amplitude * (sin(2 pi i_1 / 64), cos(2 pi i_0 / 48)) pixels (stored in mm): smooth, |grad w| up to about
 * amplitude * 2 pi / 48 per pixel. */
std::vector<float>
Waves(const itk::dmr::Grid<2> & grid, double amplitude)
{
  std::vector<float> w(grid.numberOfPixels * 2);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto i = grid.Index(p);
    w[p * 2] =
      static_cast<float>(amplitude * std::sin(2.0 * M_PI * static_cast<double>(i[1]) / 64.0) * grid.spacing[0]);
    w[p * 2 + 1] =
      static_cast<float>(amplitude * std::cos(2.0 * M_PI * static_cast<double>(i[0]) / 48.0) * grid.spacing[1]);
  }
  return w;
}
} // namespace

// The inverse of a translation is the opposite translation, exactly (the clamped interpolation of a constant field).
TEST(InvertField, ATranslationGivesTheOppositeTranslation)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 9, 8, 7 }, std::array<double, 3>{ 0.5, 1.25, 2.0 });
  std::vector<float>      w(grid.numberOfPixels * 3), v(w.size());
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    w[p * 3] = 1.75f;
    w[p * 3 + 1] = -3.5f;
    w[p * 3 + 2] = 0.25f;
  }
  const auto result = itk::dmr::InvertField<3>(grid, w.data(), v.data(), nullptr);
  EXPECT_LE(result.residual, 1e-12);
  for (size_t i = 0; i < w.size(); ++i)
  {
    ASSERT_EQ(v[i], -w[i]) << i;
  }
}

// A smooth field with |grad w| up to 0.33 per pixel: the residual |v(y) + w(y + v(y))| reaches the tolerance, and v
// undoes w where w moves the pixel centres (v(x + w(x)) = -w(x) up to the interpolation of v between pixels, away from
// the border); the result does not depend on the threads.
TEST(InvertField, ASmoothFieldIsUndone)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 96, 80 }, std::array<double, 2>{ 0.8, 1.3 });
  const auto              w = Waves(grid, 2.5);
  std::vector<float>      v(w.size());
  const auto              result = itk::dmr::InvertField<2>(grid, w.data(), v.data(), nullptr);
  EXPECT_LE(result.residual, 1e-3);
  EXPECT_GT(result.iterations, 1u);
  std::cout << "smooth field: residual " << result.residual << " pixel after " << result.iterations << " iterations"
            << std::endl;
  double largest = 0.0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto i = grid.Index(p);
    double     at[2], back[2] = { w[p * 2], w[p * 2 + 1] };
    bool       inside = true;
    for (unsigned int k = 0; k < 2; ++k)
    {
      // away from the border, where the fixed points of the neighbouring pixels fall outside the grid and the
      // clamped interpolation stands in for w there
      at[k] = static_cast<double>(i[k]) + w[p * 2 + k] / grid.spacing[k];
      inside = inside && at[k] >= 4.0 && at[k] <= static_cast<double>(grid.size[k] - 5);
    }
    if (!inside)
    {
      continue;
    }
    itk::dmr::InterpolateAdd<2, 2>(grid, v.data(), at, 1.0, back); // w(x) + v(x + w(x))
    for (unsigned int k = 0; k < 2; ++k)
    {
      largest = std::max(largest, std::abs(back[k]) / grid.spacing[k]);
    }
  }
  std::cout << "largest |w(x) + v(x + w(x))|: " << largest << " pixel" << std::endl;
  EXPECT_LT(largest, 0.05);
  auto               threader = itk::dmr::test::Threader(2, 3);
  std::vector<float> threaded(w.size());
  const auto         again = itk::dmr::InvertField<2>(grid, w.data(), threaded.data(), threader);
  EXPECT_EQ(again.iterations, result.iterations);
  EXPECT_EQ(0, std::memcmp(threaded.data(), v.data(), v.size() * sizeof(float)));
}

// A strongly folded field (|grad w| up to 1.6 per pixel: det(I + grad w) < 0 in places) has no inverse, and here the
// iteration does not find preimages either: the residual stays far above the tolerance. (A milder fold can give a
// small residual; InverseDisplacementField refuses folded fields by det J first.)
TEST(InvertField, AFoldedFieldKeepsALargeResidual)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 96, 80 }, std::array<double, 2>{ 1.0, 1.0 });
  const auto              w = Waves(grid, 12.0);
  std::vector<float>      v(w.size());
  const auto              result = itk::dmr::InvertField<2>(grid, w.data(), v.data(), nullptr);
  EXPECT_EQ(result.iterations, 200u);
  EXPECT_GT(result.residual, 0.1);
}
