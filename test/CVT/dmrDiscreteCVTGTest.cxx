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
#include "dmrDiscreteCVT.h"
#include "dmrTestHelpers.h"
#include "itkMultiThreaderBase.h"
#include "gtest/gtest.h"
#include <cmath>
#include <fstream>
#include <iostream>
#include <limits>

#include <numeric>
#include <random>
#include <set>
#include <sys/resource.h>
#include <sys/wait.h>
#include <system_error>
#include <thread>
#include <unistd.h>
#include <utility>
#include <condition_variable>
#include <mutex>

namespace
{
using itk::dmr::test::CellsAreFaceConnected;
using itk::dmr::test::ComputeCellStatistics;
using itk::dmr::test::LabelsAreCompact;

/** A weighted point set in 2D: weights w, positions x (2 interleaved). */
struct Cluster
{
  std::vector<double> w;
  std::vector<double> x;

  double
  Mass() const
  {
    double m = 0.0;
    for (double v : w)
    {
      m += v;
    }
    return m;
  }
  std::array<double, 2>
  Centroid() const
  {
    std::array<double, 2> r{ 0.0, 0.0 };
    for (size_t i = 0; i < w.size(); ++i)
    {
      r[0] += w[i] * x[2 * i];
      r[1] += w[i] * x[2 * i + 1];
    }
    r[0] /= Mass();
    r[1] /= Mass();
    return r;
  }
  /** Paper Eq. 10 for one cluster with its site at the centroid, summed point by point. */
  double
  Energy() const
  {
    const auto r = Centroid();
    double     e = 0.0;
    for (size_t i = 0; i < w.size(); ++i)
    {
      e += w[i] * ((x[2 * i] - r[0]) * (x[2 * i] - r[0]) + (x[2 * i + 1] - r[1]) * (x[2 * i + 1] - r[1]));
    }
    return e;
  }
};

/** Splits random distinct pixels of a 48x40 grid (spacing 1.0 x 1.7) into two clusters with random densities. */
void
RandomClusterPair(std::mt19937 & engine, Cluster & a, Cluster & b)
{
  std::uniform_int_distribution<int>     countDist(1, 40);
  std::uniform_int_distribution<int>     pixelDist(0, 48 * 40 - 1);
  std::uniform_real_distribution<double> weightDist(0.01, 10.0);
  const int                              na = countDist(engine), nb = countDist(engine);
  std::set<int>                          used;
  auto                                   fill = [&](Cluster & c, int n) {
    c.w.clear();
    c.x.clear();
    while (static_cast<int>(c.w.size()) < n)
    {
      const int p = pixelDist(engine);
      if (!used.insert(p).second)
      {
        continue;
      }
      c.w.push_back(weightDist(engine));
      c.x.push_back((p % 48) * 1.0);
      c.x.push_back((p / 48) * 1.7);
    }
  };
  fill(a, na);
  fill(b, nb);
}

TEST(ContractionCost, EqualsBruteForceEnergyChangeOfTheMerge)
{
  std::mt19937 engine(20150141u);
  for (int trial = 0; trial < 200; ++trial)
  {
    Cluster a, b;
    RandomClusterPair(engine, a, b);
    Cluster merged = a;
    merged.w.insert(merged.w.end(), b.w.begin(), b.w.end());
    merged.x.insert(merged.x.end(), b.x.begin(), b.x.end());
    const double bruteForce = merged.Energy() - a.Energy() - b.Energy();
    const auto   ra = a.Centroid(), rb = b.Centroid();
    const double cost = itk::dmr::ContractionCost<2>(a.Mass(), ra.data(), b.Mass(), rb.data());
    ASSERT_GT(bruteForce, 0.0);
    EXPECT_NEAR(cost, bruteForce, 1e-9 * bruteForce + 1e-12 * merged.Energy()) << "trial " << trial;
    // symmetric in its two clusters
    EXPECT_DOUBLE_EQ(cost, itk::dmr::ContractionCost<2>(b.Mass(), rb.data(), a.Mass(), ra.data()));
  }
}

TEST(SwapEnergyChange, EqualsBruteForceEnergyChangeOfMovingOnePixel)
{
  std::mt19937 engine(10161u);
  int          negative = 0, positive = 0;
  for (int trial = 0; trial < 300; ++trial)
  {
    Cluster a, b;
    RandomClusterPair(engine, a, b);
    if (a.w.size() < 2)
    {
      continue; // moving the only pixel would empty the cluster
    }
    const size_t moved = std::uniform_int_distribution<size_t>(0, a.w.size() - 1)(engine);
    const double w = a.w[moved];
    const double x[2] = { a.x[2 * moved], a.x[2 * moved + 1] };
    Cluster      a2 = a, b2 = b;
    a2.w.erase(a2.w.begin() + moved);
    a2.x.erase(a2.x.begin() + 2 * moved, a2.x.begin() + 2 * moved + 2);
    b2.w.push_back(w);
    b2.x.insert(b2.x.end(), x, x + 2);
    const double bruteForce = (a2.Energy() + b2.Energy()) - (a.Energy() + b.Energy());
    const auto   ra = a.Centroid(), rb = b.Centroid();
    const double change = itk::dmr::SwapEnergyChange<2>(w, x, a.Mass(), ra.data(), b.Mass(), rb.data());
    EXPECT_NEAR(change, bruteForce, 1e-9 * std::abs(bruteForce) + 1e-12 * (a.Energy() + b.Energy()))
      << "trial " << trial;
    (bruteForce < 0 ? negative : positive)++;
  }
  // both signs were exercised
  EXPECT_GT(negative, 0);
  EXPECT_GT(positive, 0);
}

/** Runs Optimize one sweep at a time and checks the per-sweep properties; returns the number of sweeps. */
template <unsigned int D>
size_t
SweepUntilConverged(itk::dmr::DiscreteCVT<D> & cvt,
                    const itk::dmr::Grid<D> &  grid,
                    const std::vector<float> & density,
                    size_t                     numberOfCells,
                    size_t                     maximumSweeps)
{
  size_t sweeps = 0;
  size_t lastSwaps = 1;
  double previous = cvt.GetEnergy();
  size_t totalSwaps = 0;
  while (sweeps < maximumSweeps && lastSwaps > 0)
  {
    const auto result = cvt.Optimize(0.0, 1);
    ++sweeps;
    lastSwaps = result.swaps;
    totalSwaps += result.swaps;
    EXPECT_EQ(result.sweeps, 1u);
    EXPECT_DOUBLE_EQ(result.energyBefore, previous);
    EXPECT_DOUBLE_EQ(result.energyAfter, cvt.GetEnergy());
    EXPECT_LE(cvt.GetEnergy(), previous * (1.0 + 1e-12)) << "sweep " << sweeps;
    if (result.swaps > 0)
    {
      EXPECT_LT(cvt.GetEnergy(), previous) << "sweep " << sweeps << " swapped without lowering the energy";
    }
    // the incrementally tracked energy, masses and centroids are the ones of the labels
    const auto reference = ComputeCellStatistics<D>(grid, density.data(), cvt.GetLabels(), numberOfCells);
    EXPECT_NEAR(cvt.GetEnergy(), cvt.BruteForceEnergy(), 1e-9 * cvt.BruteForceEnergy()) << "sweep " << sweeps;
    EXPECT_NEAR(cvt.GetEnergy(), reference.energy, 1e-9 * reference.energy) << "sweep " << sweeps;
    for (size_t c = 0; c < numberOfCells; ++c)
    {
      EXPECT_NEAR(cvt.GetMasses()[c], reference.mass[c], 1e-9 * reference.mass[c]);
      for (unsigned int k = 0; k < D; ++k)
      {
        EXPECT_NEAR(cvt.GetCentroids()[c * D + k], reference.centroid[c * D + k], 1e-7);
      }
    }
    EXPECT_TRUE(CellsAreFaceConnected<D>(grid, cvt.GetLabels())) << "after sweep " << sweeps;
    EXPECT_TRUE(LabelsAreCompact(cvt.GetLabels(), numberOfCells)) << "after sweep " << sweeps;
    if (::testing::Test::HasFailure())
    {
      break;
    }
    previous = cvt.GetEnergy();
  }
  EXPECT_EQ(lastSwaps, 0u) << "no converged sweep within " << maximumSweeps << " sweeps";
  EXPECT_GT(totalSwaps, 0u) << "the optimiser never moved a pixel: the test exercised nothing";
  return sweeps;
}

const std::array<size_t, 2> size2D{ 48, 40 };
const std::array<double, 2> spacing2D{ 1.0, 1.7 };

TEST(DiscreteCVT, ContractionGivesCompactConnectedCells)
{
  const itk::dmr::Grid<2>  grid(size2D, spacing2D);
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 7u);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(12, 1);
  EXPECT_EQ(cvt.GetNumberOfCells(), 12u);
  EXPECT_TRUE(LabelsAreCompact(cvt.GetLabels(), 12));
  EXPECT_TRUE(CellsAreFaceConnected<2>(grid, cvt.GetLabels()));
  const auto reference = ComputeCellStatistics<2>(grid, density.data(), cvt.GetLabels(), 12);
  EXPECT_NEAR(cvt.GetEnergy(), reference.energy, 1e-9 * reference.energy);
  EXPECT_NEAR(cvt.BruteForceEnergy(), reference.energy, 1e-9 * reference.energy);
}

/** The contraction as the paper states it, with nothing kept between merges: every block's sums in pixel order, then
 * merges of the adjacent pair with the least (cost, lower id, higher id) over all pairs, found by a scan of them all;
 * the cluster with more neighbours (ties: the lower id) absorbs the other; labels numbered by first appearance in
 * block order. */
template <unsigned int D>
std::vector<int32_t>
ReferenceContraction(const itk::dmr::Grid<D> & grid, const std::vector<float> & density, size_t cells, size_t block)
{
  std::array<size_t, D> nb;
  size_t                blocks = 1;
  for (unsigned int k = 0; k < D; ++k)
  {
    nb[k] = (grid.size[k] + block - 1) / block;
    blocks *= nb[k];
  }
  std::vector<size_t>            blockOf(grid.numberOfPixels);
  std::vector<double>            mass(blocks, 0.0), centroid(blocks * D, 0.0);
  std::vector<std::set<int32_t>> adjacent(blocks);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    size_t rest = p, b = 0, bstride = 1;
    double x[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t ik = rest % grid.size[k];
      rest /= grid.size[k];
      x[k] = static_cast<double>(ik) * grid.spacing[k];
      b += (ik / block) * bstride;
      bstride *= nb[k];
    }
    blockOf[p] = b;
    const double w = density[p];
    mass[b] += w;
    for (unsigned int k = 0; k < D; ++k)
    {
      centroid[b * D + k] += w * x[k];
    }
  }
  for (size_t b = 0; b < blocks; ++b)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      centroid[b * D + k] /= mass[b];
    }
    size_t rest = b, bstride = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t ik = rest % nb[k];
      rest /= nb[k];
      if (ik + 1 < nb[k])
      {
        adjacent[b].insert(static_cast<int32_t>(b + bstride));
        adjacent[b + bstride].insert(static_cast<int32_t>(b));
      }
      bstride *= nb[k];
    }
  }
  std::vector<int32_t> parent(blocks);
  std::iota(parent.begin(), parent.end(), 0);
  for (size_t clusters = blocks; clusters > cells; --clusters)
  {
    double  best = std::numeric_limits<double>::infinity();
    int32_t lo = -1, hi = -1;
    for (int32_t a = 0; a < static_cast<int32_t>(blocks); ++a)
    {
      for (const int32_t b : adjacent[a])
      {
        if (b > a)
        {
          const double c = itk::dmr::ContractionCost<D>(mass[a], &centroid[a * D], mass[b], &centroid[b * D]);
          if (c < best || (c == best && (a < lo || (a == lo && b < hi))))
          {
            best = c;
            lo = a;
            hi = b;
          }
        }
      }
    }
    int32_t keep = lo, gone = hi;
    if (adjacent[gone].size() > adjacent[keep].size())
    {
      std::swap(keep, gone);
    }
    const double m = mass[keep] + mass[gone];
    for (unsigned int k = 0; k < D; ++k)
    {
      centroid[keep * D + k] = (mass[keep] * centroid[keep * D + k] + mass[gone] * centroid[gone * D + k]) / m;
    }
    mass[keep] = m;
    for (const int32_t n : adjacent[gone])
    {
      adjacent[n].erase(gone);
      if (n != keep)
      {
        adjacent[n].insert(keep);
        adjacent[keep].insert(n);
      }
    }
    adjacent[keep].erase(gone);
    adjacent[gone].clear();
    parent[gone] = keep;
  }
  std::vector<int32_t> compact(blocks, -1), labels(grid.numberOfPixels);
  int32_t              next = 0;
  std::vector<int32_t> blockLabel(blocks);
  for (size_t b = 0; b < blocks; ++b)
  {
    int32_t root = static_cast<int32_t>(b);
    while (parent[root] != root)
    {
      root = parent[root];
    }
    if (compact[root] < 0)
    {
      compact[root] = next++;
    }
    blockLabel[b] = compact[root];
  }
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    labels[p] = blockLabel[blockOf[p]];
  }
  return labels;
}

template <unsigned int D>
void
ExpectContractionEqualsTheReference(const itk::dmr::Grid<D> &  grid,
                                    const std::vector<float> & density,
                                    size_t                     cells,
                                    unsigned int               block)
{
  SCOPED_TRACE(std::to_string(D) + "D, " + std::to_string(cells) + " cells from blocks of " + std::to_string(block));
  const auto               threader = itk::dmr::test::Threader(2, 2);
  itk::dmr::DiscreteCVT<D> cvt;
  cvt.SetDensity(grid, density.data(), threader);
  cvt.ContractionInitialize(cells, block);
  const auto   reference = ReferenceContraction<D>(grid, density, cells, block);
  const auto & labels = cvt.GetLabels();
  EXPECT_TRUE(std::equal(labels.begin(), labels.end(), reference.begin(), reference.end()));
}

TEST(DiscreteCVT, ContractionMergesTheLeastPairOfAllFirst)
{
  // random densities, a flat one (every cost ties with its mirror image: the ids decide) and one of a few levels
  const itk::dmr::Grid<2> grid2(std::array<size_t, 2>{ 23, 19 }, std::array<double, 2>{ 1.0, 1.7 });
  const itk::dmr::Grid<3> grid3(std::array<size_t, 3>{ 9, 8, 7 }, std::array<double, 3>{ 1.0, 1.0, 2.0 });
  for (uint32_t seed = 1; seed <= 3; ++seed)
  {
    const auto random2 = itk::dmr::test::RandomDensity(grid2.numberOfPixels, seed);
    const auto random3 = itk::dmr::test::RandomDensity(grid3.numberOfPixels, seed + 10);
    for (const size_t cells : { size_t{ 1 }, size_t{ 7 }, size_t{ 40 } })
    {
      ExpectContractionEqualsTheReference<2>(grid2, random2, cells, 1);
      ExpectContractionEqualsTheReference<3>(grid3, random3, cells, 1);
    }
    ExpectContractionEqualsTheReference<2>(grid2, random2, 12, 2);
    ExpectContractionEqualsTheReference<3>(grid3, random3, 12, 2);
  }
  for (const bool flat : { true, false })
  {
    std::vector<float> d2(grid2.numberOfPixels, 0.5f), d3(grid3.numberOfPixels, 0.5f);
    if (!flat)
    {
      for (size_t p = 0; p < d2.size(); ++p)
      {
        d2[p] = 0.25f + 0.25f * static_cast<float>((p / 5) % 3);
      }
      for (size_t p = 0; p < d3.size(); ++p)
      {
        d3[p] = 0.25f + 0.25f * static_cast<float>((p / 4) % 3);
      }
    }
    for (const size_t cells : { size_t{ 5 }, size_t{ 30 } })
    {
      ExpectContractionEqualsTheReference<2>(grid2, d2, cells, 1);
      ExpectContractionEqualsTheReference<3>(grid3, d3, cells, 1);
    }
    ExpectContractionEqualsTheReference<2>(grid2, d2, 9, 2);
    ExpectContractionEqualsTheReference<3>(grid3, d3, 9, 2);
  }
}

// The contraction's block sums (ContractionInitialize contracts them; the CUDA back-end compares its own with them bit
// for bit before it takes the host's merges of iteration 1): every block's mass and centroid, the last blocks of an
// axis cut at the grid's end, the same whatever the threads
template <unsigned int D>
void
ExpectBlockSumsOfEveryBlock(const itk::dmr::Grid<D> & grid, const std::vector<float> & density, unsigned int block)
{
  SCOPED_TRACE(std::to_string(D) + "D, blocks of " + std::to_string(block));
  const size_t             cells = 5;
  const auto               threader = itk::dmr::test::Threader(4, 4);
  itk::dmr::DiscreteCVT<D> threaded, serial;
  threaded.SetDensity(grid, density.data(), threader);
  serial.SetDensity(grid, density.data(), nullptr);
  std::vector<double> mass, centroid, serialMass, serialCentroid;
  const auto          blocks = threaded.ContractionBlockSums(cells, block, mass, centroid);
  serial.ContractionBlockSums(cells, block, serialMass, serialCentroid);
  EXPECT_EQ(mass, serialMass);
  EXPECT_EQ(centroid, serialCentroid);
  ASSERT_EQ(blocks.size, block);
  size_t numberOfBlocks = 1;
  for (unsigned int k = 0; k < D; ++k)
  {
    EXPECT_EQ(blocks.perAxis[k], (grid.size[k] + block - 1) / block);
    numberOfBlocks *= blocks.perAxis[k];
  }
  std::vector<double> referenceMass(numberOfBlocks, 0.0), moment(numberOfBlocks * D, 0.0);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    size_t     b = 0, stride = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      b += (static_cast<size_t>(idx[k]) / block) * stride;
      stride *= blocks.perAxis[k];
    }
    double x[D];
    threaded.Position(p, x);
    referenceMass[b] += density[p];
    for (unsigned int k = 0; k < D; ++k)
    {
      moment[b * D + k] += density[p] * x[k];
    }
  }
  ASSERT_EQ(mass.size(), numberOfBlocks);
  ASSERT_EQ(centroid.size(), numberOfBlocks * D);
  for (size_t b = 0; b < numberOfBlocks; ++b)
  {
    EXPECT_NEAR(mass[b], referenceMass[b], 1e-12 * referenceMass[b]) << "block " << b;
    for (unsigned int k = 0; k < D; ++k)
    {
      EXPECT_NEAR(centroid[b * D + k], moment[b * D + k] / referenceMass[b], 1e-9) << "block " << b << ", axis " << k;
    }
  }
}

TEST(DiscreteCVT, ContractionBlockSumsAreEveryBlocksMassAndCentroid)
{
  const itk::dmr::Grid<2> grid2(std::array<size_t, 2>{ 23, 19 }, std::array<double, 2>{ 1.0, 1.7 });
  const itk::dmr::Grid<3> grid3(std::array<size_t, 3>{ 9, 8, 7 }, std::array<double, 3>{ 1.0, 1.0, 2.0 });
  const auto              density2 = itk::dmr::test::RandomDensity(grid2.numberOfPixels, 5);
  const auto              density3 = itk::dmr::test::RandomDensity(grid3.numberOfPixels, 6);
  for (const unsigned int block : { 1u, 2u, 4u })
  {
    ExpectBlockSumsOfEveryBlock<2>(grid2, density2, block);
    ExpectBlockSumsOfEveryBlock<3>(grid3, density3, block);
  }
}

// a cell of zero mass has no centroid (the contraction's costs would be NaN): such a density is refused up front
TEST(DiscreteCVT, DensityThatIsNotPositiveAndFiniteThrows)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 5, 4 }, std::array<double, 2>{ 1.0, 1.0 });
  for (const float bad :
       { 0.0f, -1.0f, std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity() })
  {
    std::vector<float> density(grid.numberOfPixels, 1.0f);
    density[13] = bad;
    itk::dmr::DiscreteCVT<2> cvt;
    try
    {
      cvt.SetDensity(grid, density.data(), nullptr);
      ADD_FAILURE() << "density " << bad << " accepted";
    }
    catch (const itk::ExceptionObject & e)
    {
      EXPECT_NE(std::string(e.GetDescription()).find("pixel 13"), std::string::npos) << e.GetDescription();
    }
  }
  const std::vector<float> zeros(grid.numberOfPixels, 0.0f);
  itk::dmr::DiscreteCVT<2> cvt;
  EXPECT_THROW(cvt.SetDensity(grid, zeros.data(), nullptr), itk::ExceptionObject);
}

TEST(DiscreteCVT, TooManyOrZeroCellsThrow)
{
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 4, 3 }, std::array<double, 2>{ 1.0, 1.0 });
  const std::vector<float> density(grid.numberOfPixels, 1.0f);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  EXPECT_THROW(cvt.ContractionInitialize(13, 1), itk::ExceptionObject);
  EXPECT_THROW(cvt.ContractionInitialize(0, 1), itk::ExceptionObject);
  EXPECT_NO_THROW(cvt.ContractionInitialize(12, 1));
  // blocks of 2 give only 4 blocks: falls back to single pixels
  EXPECT_NO_THROW(cvt.ContractionInitialize(12, 2));
  EXPECT_TRUE(LabelsAreCompact(cvt.GetLabels(), 12));
}

TEST(DiscreteCVT, SetLabelsAndSetStateRejectOutOfRangeAndEmptyCells)
{
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 4, 3 }, std::array<double, 2>{ 1.0, 1.0 });
  const std::vector<float> density(grid.numberOfPixels, 1.0f);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  std::vector<int32_t> labels(grid.numberOfPixels, 0);
  labels[5] = 3;
  EXPECT_THROW(cvt.SetLabels(labels.data(), 3), itk::ExceptionObject); // label 3 outside [0,3)
  EXPECT_THROW(cvt.SetLabels(labels.data(), 5), itk::ExceptionObject); // cells 1, 2 and 4 are empty
  labels[5] = 1;
  EXPECT_NO_THROW(cvt.SetLabels(labels.data(), 2));
  EXPECT_EQ(cvt.GetNumberOfCells(), 2u);

  // SetState checks what it takes as given, and a refused state leaves the current one in place
  const std::vector<double> masses{ 11.0, 1.0 }, centroids{ 1.5, 1.0, 1.0, 1.0 };
  const auto                state = cvt.GetCentroids();
  labels[5] = 2;
  EXPECT_THROW(cvt.SetState(labels.data(), 2, masses.data(), centroids.data(), 1.0), itk::ExceptionObject);
  labels[5] = 1;
  const std::vector<double> zeroMass{ 11.0, 0.0 }, nanCentroid{ 1.5, 1.0, std::nan(""), 1.0 };
  EXPECT_THROW(cvt.SetState(labels.data(), 2, zeroMass.data(), centroids.data(), 1.0), itk::ExceptionObject);
  EXPECT_THROW(cvt.SetState(labels.data(), 2, masses.data(), nanCentroid.data(), 1.0), itk::ExceptionObject);
  EXPECT_THROW(cvt.SetState(labels.data(), 2, masses.data(), centroids.data(), std::nan("")), itk::ExceptionObject);
  EXPECT_EQ(cvt.GetCentroids(), state);
  EXPECT_NO_THROW(cvt.SetState(labels.data(), 2, masses.data(), centroids.data(), 1.0));
  EXPECT_EQ(cvt.GetCentroids(), centroids);
}

// SetLabels sums every cell's mass and first moment in pixel order (the order the CUDA back-end reproduces): the
// result must be that of the plain loop, bit for bit, also where a cell's pixels come in many interleaved runs; a
// label outside the range is reported at its first pixel.
template <unsigned int D>
void
CheckSetLabelsSumsInPixelOrder(const itk::dmr::Grid<D> & grid)
{
  const auto           density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 17u);
  const size_t         nCells = 7;
  std::vector<int32_t> labels(grid.numberOfPixels);
  std::mt19937         rng(5);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    // runs of random length, every cell present
    labels[p] =
      p < nCells ? static_cast<int32_t>(p) : (rng() % 4 == 0 ? static_cast<int32_t>(rng() % nCells) : labels[p - 1]);
  }
  itk::dmr::DiscreteCVT<D> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.SetLabels(labels.data(), nCells);
  std::vector<double> mass(nCells, 0.0), moment(nCells * D, 0.0);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    mass[labels[p]] += density[p];
    for (unsigned int k = 0; k < D; ++k)
    {
      moment[labels[p] * D + k] += density[p] * (static_cast<double>(idx[k]) * grid.spacing[k]);
    }
  }
  for (size_t c = 0; c < nCells; ++c)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      moment[c * D + k] /= mass[c];
    }
  }
  EXPECT_EQ(cvt.GetMasses(), mass);
  EXPECT_EQ(cvt.GetCentroids(), moment);

  labels[grid.numberOfPixels / 3] = -1;
  labels[grid.numberOfPixels / 2] = static_cast<int32_t>(nCells);
  try
  {
    cvt.SetLabels(labels.data(), nCells);
    ADD_FAILURE() << "no exception";
  }
  catch (const itk::ExceptionObject & e)
  {
    const std::string expected = "label -1 at pixel " + std::to_string(grid.numberOfPixels / 3) + " ";
    EXPECT_NE(std::string(e.GetDescription()).find(expected), std::string::npos) << e.GetDescription();
  }
}

TEST(DiscreteCVT, SetLabelsSumsEveryCellInPixelOrder)
{
  CheckSetLabelsSumsInPixelOrder<2>(
    itk::dmr::Grid<2>(std::array<size_t, 2>{ 37, 29 }, std::array<double, 2>{ 0.7, 1.3 }));
  CheckSetLabelsSumsInPixelOrder<3>(
    itk::dmr::Grid<3>(std::array<size_t, 3>{ 13, 11, 9 }, std::array<double, 3>{ 1.1, 0.9, 2.5 }));
}

TEST(DiscreteCVT, SweepsNeverRaiseEnergyAndKeepCellsConnected)
{
  const itk::dmr::Grid<2>  grid(size2D, spacing2D);
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 7u);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(12, 1);
  const double initial = cvt.GetEnergy();
  SweepUntilConverged<2>(cvt, grid, density, 12, 500);
  EXPECT_LT(cvt.GetEnergy(), initial);
}

TEST(DiscreteCVT, PeakedDensityKeepsEnergyMonotoneAndCellsConnected)
{
  const itk::dmr::Grid<2> grid(size2D, spacing2D);
  auto                    density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 11u, 0.5f, 1.0f);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto   x = itk::dmr::test::PixelPosition<2>(grid, p);
    const double r2 = (x[0] - 30.0) * (x[0] - 30.0) + (x[1] - 25.0) * (x[1] - 25.0);
    density[p] += static_cast<float>(2000.0 * std::exp(-r2 / (2.0 * 3.0 * 3.0)));
  }
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(12, 1);
  EXPECT_TRUE(CellsAreFaceConnected<2>(grid, cvt.GetLabels()));
  SweepUntilConverged<2>(cvt, grid, density, 12, 500);
  // cells concentrate where the density is: the cell holding the peak is smaller than the average cell
  const size_t peakPixel = 30 + 48 * static_cast<size_t>(std::lround(25.0 / 1.7));
  const auto   peakLabel = cvt.GetLabels()[peakPixel];
  const auto   peakCount = std::count(cvt.GetLabels().begin(), cvt.GetLabels().end(), peakLabel);
  EXPECT_LT(static_cast<double>(peakCount), static_cast<double>(grid.numberOfPixels) / 12.0);
}

TEST(DiscreteCVT, ThreeDimensionalSweepsAreMonotoneAndSixConnected)
{
  const itk::dmr::Grid<3>  grid(std::array<size_t, 3>{ 12, 10, 8 }, std::array<double, 3>{ 1.0, 1.3, 0.8 });
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 3u);
  itk::dmr::DiscreteCVT<3> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(6, 2);
  EXPECT_TRUE(LabelsAreCompact(cvt.GetLabels(), 6));
  EXPECT_TRUE(CellsAreFaceConnected<3>(grid, cvt.GetLabels()));
  SweepUntilConverged<3>(cvt, grid, density, 6, 500);
}

TEST(DiscreteCVT, ConvergedLabellingIsAFixedPoint)
{
  const itk::dmr::Grid<2>  grid(size2D, spacing2D);
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 5u);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(12, 1);
  const auto converged = cvt.Optimize(0.0, 1000);
  EXPECT_LT(converged.sweeps, 1000u);
  const auto labels = cvt.GetLabels();
  // warm start (paper 4.7) from the converged labels: energy recomputed from scratch equals the tracked one, and
  // no further swap is accepted
  itk::dmr::DiscreteCVT<2> warm;
  warm.SetDensity(grid, density.data(), nullptr);
  warm.SetLabels(labels.data(), 12);
  EXPECT_NEAR(warm.GetEnergy(), converged.energyAfter, 1e-9 * converged.energyAfter);
  const auto again = warm.Optimize(0.0, 10);
  EXPECT_EQ(again.swaps, 0u);
  EXPECT_EQ(again.sweeps, 1u);
  EXPECT_EQ(warm.GetLabels(), labels);
}

// SetState takes a state as it is (the CUDA filter hands the GPU's over): from a copy of an optimiser's state part way
// through, a second optimiser continues exactly as the first does, bit for bit. SetLabels sums the masses and
// centroids again from the pixels, which rounds differently from the sweeps' incremental updates.
TEST(DiscreteCVT, SetStateContinuesTheSweepsOfTheStateItTakes)
{
  const itk::dmr::Grid<2>  grid(size2D, spacing2D);
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 9u);
  itk::dmr::DiscreteCVT<2> first;
  first.SetDensity(grid, density.data(), nullptr);
  first.ContractionInitialize(15, 1);
  first.Optimize(0.0, 3);
  itk::dmr::DiscreteCVT<2> second;
  second.SetDensity(grid, density.data(), nullptr);
  second.SetState(
    first.GetLabels().data(), 15, first.GetMasses().data(), first.GetCentroids().data(), first.GetEnergy());
  EXPECT_EQ(second.GetMasses(), first.GetMasses());
  EXPECT_EQ(second.GetCentroids(), first.GetCentroids());
  EXPECT_EQ(second.GetEnergy(), first.GetEnergy());
  itk::dmr::DiscreteCVT<2> summed; // the same labels, statistics summed again from the pixels
  summed.SetDensity(grid, density.data(), nullptr);
  summed.SetLabels(first.GetLabels().data(), 15);
  size_t notBitEqual = 0;
  for (size_t i = 0; i < first.GetCentroids().size(); ++i)
  {
    notBitEqual += summed.GetCentroids()[i] != first.GetCentroids()[i] ? 1u : 0u;
  }
  std::cout << notBitEqual << " of " << first.GetCentroids().size()
            << " centroid coordinates summed again from the pixels differ from the swept ones in the last bits"
            << std::endl;

  const auto a = first.Optimize(0.0, 1000);
  const auto b = second.Optimize(0.0, 1000);
  EXPECT_GT(a.swaps, 0u);
  EXPECT_EQ(b.swaps, a.swaps);
  EXPECT_EQ(b.sweeps, a.sweeps);
  EXPECT_EQ(second.GetLabels(), first.GetLabels());
  EXPECT_EQ(second.GetMasses(), first.GetMasses());
  EXPECT_EQ(second.GetCentroids(), first.GetCentroids());
  EXPECT_EQ(second.GetEnergy(), first.GetEnergy());
}

TEST(DiscreteCVT, ResultDoesNotDependOnTheThreader)
{
  // 160x160, 40 cells, 5 sweeps: the proposal and energy loops are split into several chunks. 320x320, 150 cells, to
  // convergence: the active scan lists (about 4000 pixels per colour at first, fewer later) are split in two while
  // they hold at least 2048 pixels, and scanned in one piece below that.
  for (const auto & [side, cells, sweeps] :
       { std::tuple<size_t, size_t, size_t>{ 160, 40, 5 }, std::tuple<size_t, size_t, size_t>{ 320, 150, 1000 } })
  {
    SCOPED_TRACE(std::to_string(side) + " x " + std::to_string(side));
    const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ side, side }, std::array<double, 2>{ 1.0, 1.0 });
    const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 9u);
    auto                     threader = itk::dmr::test::Threader(2, 2);
    itk::dmr::DiscreteCVT<2> serial, parallel;
    serial.SetDensity(grid, density.data(), nullptr);
    parallel.SetDensity(grid, density.data(), threader);
    serial.ContractionInitialize(cells, 4);
    parallel.ContractionInitialize(cells, 4);
    const auto a = serial.Optimize(0.0, sweeps);
    const auto b = parallel.Optimize(0.0, sweeps);
    EXPECT_GT(a.swaps, 0u);
    EXPECT_EQ(a.sweeps, b.sweeps);
    EXPECT_EQ(a.swaps, b.swaps);
    EXPECT_EQ(serial.GetLabels(), parallel.GetLabels());
    EXPECT_EQ(serial.GetEnergy(), parallel.GetEnergy());
  }
}

TEST(DiscreteCVT, SweepsRunOnTheThreaderWhereNoMoreThreadsMayStart)
{
  // The sub-sweeps' team adds threads to ITK's pool. In a child process whose virtual memory limit leaves no room for
  // another thread's stack (8 MiB; like ulimit -v or a container's limits), the team cannot start: the sweeps run on
  // ITK's threader instead (its threads were started before the limit), with the labels of a run with the team.
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "a sanitizer's shadow memory does not fit under a virtual memory limit";
#endif
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 320, 320 }, std::array<double, 2>{ 1.0, 1.0 });
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 9u);
  auto                     threader = itk::dmr::test::Threader(2, 2);
  itk::dmr::DiscreteCVT<2> reference;
  reference.SetDensity(grid, density.data(), threader);
  reference.ContractionInitialize(150, 4);
  const auto referenceResult = reference.Optimize(0.0, 1000); // scans of 2048 or more pixels take two chunks
  ASSERT_GT(referenceResult.swaps, 0u);

  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0)
  {
    // exit codes: 0 same labels, 1 other labels, 2 the limit did not stop a thread, 3 no limit could be set, 4 threw
    long          pages = 0;
    std::ifstream statm("/proc/self/statm");
    if (!(statm >> pages))
    {
      ::_exit(3);
    }
    const rlim_t bytes = static_cast<rlim_t>(pages) * static_cast<rlim_t>(::sysconf(_SC_PAGESIZE)) + (rlim_t(4) << 20);
    const rlimit limit{ bytes, bytes };
    if (::setrlimit(RLIMIT_AS, &limit) != 0)
    {
      ::_exit(3);
    }
    // glibc keeps the stacks of ended threads for new ones (the reference run's team ended in this process): hold
    // threads until no more may start, so that the team needs a new stack
    std::mutex               mutex;
    std::condition_variable  released;
    bool                     release = false;
    std::vector<std::thread> held;
    try
    {
      while (held.size() < 64)
      {
        held.emplace_back([&] {
          std::unique_lock<std::mutex> lock(mutex);
          released.wait(lock, [&] { return release; });
        });
      }
      ::_exit(2);
    }
    catch (const std::system_error &)
    {
    }
    try
    {
      itk::dmr::DiscreteCVT<2> limited;
      limited.SetDensity(grid, density.data(), threader);
      limited.ContractionInitialize(150, 4);
      const auto result = limited.Optimize(0.0, 1000);
      const bool same = result.sweeps == referenceResult.sweeps && result.swaps == referenceResult.swaps &&
                        limited.GetLabels() == reference.GetLabels() && limited.GetEnergy() == reference.GetEnergy();
      ::_exit(same ? 0 : 1);
    }
    catch (...)
    {
      ::_exit(4);
    }
  }
  int status = 0;
  ASSERT_EQ(::waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status)) << "the child ended by signal " << (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
  EXPECT_EQ(WEXITSTATUS(status), 0) << "0 same labels, 1 other labels, 2 the limit did not stop a thread, 3 no limit, "
                                       "4 an exception";
}

/** A density like the registration's: a sharp ridge along a sphere (a circle in 2D) of the given radius, centred in
 * the grid and moved by shift x (k + 1) along axis k, on a random floor. */
template <unsigned int D>
std::vector<float>
RidgeDensity(const itk::dmr::Grid<D> & grid, double radius, double shift, uint32_t seed)
{
  auto density = itk::dmr::test::RandomDensity(grid.numberOfPixels, seed, 0.05f, 0.15f);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = itk::dmr::test::PixelPosition<D>(grid, p);
    double     r2 = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double c = 0.5 * grid.spacing[k] * static_cast<double>(grid.size[k] - 1) + shift * (k + 1);
      r2 += (x[k] - c) * (x[k] - c);
    }
    const double d = std::sqrt(r2) - radius;
    density[p] += static_cast<float>(20.0 * std::exp(-d * d / (2.0 * 1.5 * 1.5)));
  }
  return density;
}

/** Runs Optimize(0, sweepsPerCall) callCount times from the same labels in every sweep mode; expects the active-list
 * modes to give the full scan's labels, energy and statistics exactly. The gather modes run twice more with chunks of
 * 16 gather-list entries, so that their parallel gather (GatherChangedCells in chunks, with atomic Queued bits) runs
 * on these small grids too. Returns the full scan's totals. */
template <unsigned int D>
typename itk::dmr::DiscreteCVT<D>::OptimizeResult
ExpectModesAgree(const itk::dmr::Grid<D> &    grid,
                 const std::vector<float> &   density,
                 const std::vector<int32_t> & start,
                 size_t                       numberOfCells,
                 size_t                       sweepsPerCall,
                 size_t                       callCount,
                 itk::MultiThreaderBase *     threader)
{
  using CVTType = itk::dmr::DiscreteCVT<D>;
  using ModeType = typename CVTType::SweepMode;
  const std::pair<ModeType, size_t>  modes[] = { { ModeType::FullScan, 0 },      { ModeType::Auto, 0 },
                                                 { ModeType::ActiveScan, 0 },    { ModeType::ActiveGather, 0 },
                                                 { ModeType::ActiveGather, 16 }, { ModeType::Auto, 16 } };
  std::vector<std::vector<int32_t>>  labels;
  std::vector<std::vector<double>>   energies;
  std::vector<std::array<size_t, 3>> counts;
  for (const auto & [mode, chunkWork] : modes)
  {
    CVTType cvt;
    cvt.SetSweepMode(mode);
    EXPECT_EQ(cvt.GetSweepMode(), mode);
    if (chunkWork > 0)
    {
      cvt.SetGatherChunkWork(chunkWork);
      EXPECT_EQ(cvt.GetGatherChunkWork(), chunkWork);
    }
    cvt.SetDensity(grid, density.data(), threader);
    cvt.SetLabels(start.data(), numberOfCells);
    std::vector<double>   energy;
    std::array<size_t, 3> total{ 0, 0, 0 };
    for (size_t call = 0; call < callCount; ++call)
    {
      const auto result = cvt.Optimize(0.0, sweepsPerCall);
      energy.push_back(result.energyAfter);
      total[0] += result.sweeps;
      total[1] += result.swaps;
      total[2] += result.rejectedBatches;
    }
    labels.push_back(cvt.GetLabels());
    energies.push_back(energy);
    counts.push_back(total);
  }
  for (size_t m = 1; m < labels.size(); ++m)
  {
    EXPECT_TRUE(labels[m] == labels[0]) << "mode " << m << " gives other labels than the full scan";
    EXPECT_EQ(energies[m], energies[0]) << "mode " << m; // bit for bit: same swaps, committed in the same order
    EXPECT_EQ(counts[m], counts[0]) << "mode " << m << " (sweeps, swaps, rejected batches)";
  }
  typename CVTType::OptimizeResult full;
  full.sweeps = counts[0][0];
  full.swaps = counts[0][1];
  full.rejectedBatches = counts[0][2];
  return full;
}

TEST(DiscreteCVT, ActiveListGivesTheFullScanLabels2D)
{
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 96, 80 }, std::array<double, 2>{ 1.0, 1.3 });
  const auto               density = RidgeDensity<2>(grid, 30.0, 0.0, 21u);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(40, 1);
  const auto contracted = cvt.GetLabels();
  // from the contraction to convergence, in one call and one sweep per call
  const auto cold = ExpectModesAgree<2>(grid, density, contracted, 40, 1000, 1, nullptr);
  EXPECT_GT(cold.swaps, 1000u);
  ExpectModesAgree<2>(grid, density, contracted, 40, 1, 60, nullptr);
  // warm starts (paper 4.7) on a moving ridge, as the registration does
  cvt.Optimize(0.0, 1000);
  auto   labels = cvt.GetLabels();
  size_t swaps = 0;
  for (int step = 1; step <= 4; ++step)
  {
    const auto moved = RidgeDensity<2>(grid, 30.0 + 0.7 * step, 0.6 * step, 21u + step);
    swaps += ExpectModesAgree<2>(grid, moved, labels, 40, 1000, 1, nullptr).swaps;
    itk::dmr::DiscreteCVT<2> next;
    next.SetDensity(grid, moved.data(), nullptr);
    next.SetLabels(labels.data(), 40);
    next.Optimize(0.0, 1000);
    labels = next.GetLabels();
  }
  EXPECT_GT(swaps, 0u);
}

TEST(DiscreteCVT, ActiveListGivesTheFullScanLabelsWhenBatchesAreHalved)
{
  // heavy-tailed densities (a few pixels carry most of the mass) make joint commits raise the energy now and then,
  // so batches are halved and proposals rejected, which the active lists must re-evaluate
  std::mt19937 engine(2015u);
  size_t       rejected = 0;
  for (int trial = 0; trial < 60 && !::testing::Test::HasFailure(); ++trial)
  {
    const itk::dmr::Grid<2> grid(
      std::array<size_t, 2>{ 12 + static_cast<size_t>(trial % 20), 10 + static_cast<size_t>(trial % 15) },
      std::array<double, 2>{ 1.0, 1.0 });
    std::vector<float> density(grid.numberOfPixels);
    for (auto & d : density)
    {
      const double u = static_cast<double>(engine() >> 8) / 16777216.0; // portable uniform [0, 1)
      d = static_cast<float>(100.0 * u * u * u * u + 0.01);
    }
    const size_t             numberOfCells = 2 + static_cast<size_t>(trial % 6);
    itk::dmr::DiscreteCVT<2> cvt;
    cvt.SetDensity(grid, density.data(), nullptr);
    cvt.ContractionInitialize(numberOfCells, 1);
    const auto contracted = cvt.GetLabels();
    rejected += ExpectModesAgree<2>(grid, density, contracted, numberOfCells, 1000, 1, nullptr).rejectedBatches;
  }
  EXPECT_GT(rejected, 0u) << "no batch was halved: the test did not exercise the rejected proposals";
}

TEST(DiscreteCVT, ActiveListGivesTheFullScanLabels3D)
{
  const itk::dmr::Grid<3>  grid(std::array<size_t, 3>{ 28, 24, 20 }, std::array<double, 3>{ 1.0, 1.2, 1.5 });
  const auto               density = RidgeDensity<3>(grid, 9.0, 0.0, 31u);
  itk::dmr::DiscreteCVT<3> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(30, 2);
  const auto contracted = cvt.GetLabels();
  const auto cold = ExpectModesAgree<3>(grid, density, contracted, 30, 1000, 1, nullptr);
  EXPECT_GT(cold.swaps, 1000u);
  ExpectModesAgree<3>(grid, density, contracted, 30, 1, 40, nullptr);
  cvt.Optimize(0.0, 1000);
  const auto labels = cvt.GetLabels();
  const auto moved = RidgeDensity<3>(grid, 9.5, 0.7, 32u);
  const auto warm = ExpectModesAgree<3>(grid, moved, labels, 30, 1000, 1, nullptr);
  EXPECT_GT(warm.swaps, 0u);
}

TEST(DiscreteCVT, ActiveListGivesTheFullScanLabelsWithThreadsAndManyChunks)
{
  // 2000 cells on 384x320: each colour's scan list is long enough to be split into several chunks
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 384, 320 }, std::array<double, 2>{ 1.0, 1.0 });
  const auto               density = RidgeDensity<2>(grid, 100.0, 0.0, 41u);
  auto                     threader = itk::dmr::test::Threader(2, 2);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(2000, 1);
  const auto contracted = cvt.GetLabels();
  const auto result = ExpectModesAgree<2>(grid, density, contracted, 2000, 12, 1, threader);
  EXPECT_GT(result.swaps, 10000u);
}

TEST(DiscreteCVT, LocalRemovalTestImpliesTheCellStaysConnected)
{
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 24, 20 }, spacing2D);
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 13u);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(10, 1);
  cvt.Optimize(0.0, 2);
  const auto & labels = cvt.GetLabels();
  size_t       accepted = 0, refused = 0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    auto removed = labels;
    removed[p] = -1; // the pixel leaves its cell
    const bool globallyConnected = CellsAreFaceConnected<2>(grid, removed);
    if (cvt.RemovalKeepsCellConnected(p))
    {
      ++accepted;
      EXPECT_TRUE(globallyConnected) << "pixel " << p << " was accepted but its removal splits cell " << labels[p];
    }
    else
    {
      ++refused;
    }
  }
  EXPECT_GT(accepted, 0u);
  EXPECT_GT(refused, 0u);
}
// Regression test (a fixed bug): Optimize() resets m_Touched,
// m_DeltaMass, ... to the new number of cells but keeps m_TouchedList from the previous optimisation, so
// JointEnergyChange() indexes those arrays with labels of the old, larger labelling (out of bounds; caught by
// _GLIBCXX_ASSERTIONS, which this executable is built with).
TEST(DiscreteCVT, ReinitialisingWithFewerCellsStaysInBounds)
{
  const itk::dmr::Grid<2>  grid(size2D, spacing2D);
  const auto               density = itk::dmr::test::RandomDensity(grid.numberOfPixels, 7u);
  itk::dmr::DiscreteCVT<2> cvt;
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(20, 1);
  cvt.Optimize(0.0, 1000);
  cvt.SetDensity(grid, density.data(), nullptr);
  cvt.ContractionInitialize(2, 1);
  const auto result = cvt.Optimize(0.0, 1000);
  EXPECT_TRUE(LabelsAreCompact(cvt.GetLabels(), 2));
  EXPECT_TRUE(CellsAreFaceConnected<2>(grid, cvt.GetLabels()));
  EXPECT_LE(result.energyAfter, result.energyBefore);
}
} // namespace

namespace
{
/** Reference for Neighbourhood<D>::RemovalKeepsConnected on explicit coordinates: the positions of `member` that touch
 * the centre by a face are reached from one another by face steps through member positions (never the centre). */
template <unsigned int D>
bool
FaceNeighboursStayConnected(uint32_t member)
{
  constexpr unsigned int N = D == 2 ? 9 : 27;
  auto                   coordinates = [](unsigned int q, int(&c)[3]) {
    for (unsigned int k = 0; k < 3; ++k)
    {
      c[k] = k < D ? static_cast<int>(q % 3) : 1;
      q /= k < D ? 3u : 1u;
    }
  };
  auto isMember = [&](unsigned int q) { return q != N / 2 && ((member >> q) & 1u); };
  auto touchesCentre = [&](unsigned int q) {
    int c[3];
    coordinates(q, c);
    return std::abs(c[0] - 1) + std::abs(c[1] - 1) + std::abs(c[2] - 1) == 1;
  };
  std::vector<unsigned int> faces;
  for (unsigned int q = 0; q < N; ++q)
  {
    if (isMember(q) && touchesCentre(q))
    {
      faces.push_back(q);
    }
  }
  if (faces.empty())
  {
    return false;
  }
  std::vector<bool>         seen(N, false);
  std::vector<unsigned int> stack{ faces[0] };
  seen[faces[0]] = true;
  while (!stack.empty())
  {
    const unsigned int q = stack.back();
    stack.pop_back();
    int a[3];
    coordinates(q, a);
    for (unsigned int o = 0; o < N; ++o)
    {
      int b[3];
      coordinates(o, b);
      if (!seen[o] && isMember(o) && std::abs(a[0] - b[0]) + std::abs(a[1] - b[1]) + std::abs(a[2] - b[2]) == 1)
      {
        seen[o] = true;
        stack.push_back(o);
      }
    }
  }
  for (unsigned int q : faces)
  {
    if (!seen[q])
    {
      return false;
    }
  }
  return true;
}
} // namespace

// The bit-set connectivity test that the CPU sweeps and the CUDA kernels share, against a flood fill on coordinates:
// every 2D neighbourhood, and in 3D random ones (each position in the cell with probability 1/4 to 3/4) plus every
// neighbourhood whose 18 face and edge positions are all in the cell or all not (the corners varied).
TEST(Neighbourhood, RemovalTestEqualsAFloodFillOnCoordinates)
{
  size_t connected = 0, split = 0;
  for (uint32_t member = 0; member < (1u << 9); ++member)
  {
    const bool expected = FaceNeighboursStayConnected<2>(member);
    ASSERT_EQ(itk::dmr::Neighbourhood<2>::RemovalKeepsConnected(member), expected) << "2D member set " << member;
    (expected ? connected : split) += 1;
  }
  std::mt19937 random(7u);
  for (unsigned int n = 0; n < 200000; ++n)
  {
    const double p = 0.25 + 0.5 * static_cast<double>(n % 3) / 2.0;
    uint32_t     member = 0;
    for (unsigned int q = 0; q < 27; ++q)
    {
      member |= std::bernoulli_distribution(p)(random) ? 1u << q : 0u;
    }
    const bool expected = FaceNeighboursStayConnected<3>(member);
    ASSERT_EQ(itk::dmr::Neighbourhood<3>::RemovalKeepsConnected(member), expected) << "3D member set " << member;
    (expected ? connected : split) += 1;
  }
  constexpr uint32_t corners =
    (1u << 0) | (1u << 2) | (1u << 6) | (1u << 8) | (1u << 18) | (1u << 20) | (1u << 24) | (1u << 26);
  for (uint32_t bits = 0; bits < 256; ++bits)
  {
    uint32_t cornerSet = 0;
    for (unsigned int c = 0, q = 0; q < 27; ++q)
    {
      if ((corners >> q) & 1u)
      {
        cornerSet |= ((bits >> c++) & 1u) << q;
      }
    }
    for (const uint32_t rest : { 0u, ((1u << 27) - 1u) & ~corners })
    {
      const uint32_t member = rest | cornerSet;
      ASSERT_EQ(itk::dmr::Neighbourhood<3>::RemovalKeepsConnected(member), FaceNeighboursStayConnected<3>(member))
        << "3D member set " << member;
    }
  }
  // both outcomes occur often: the comparison is not a comparison of constants
  EXPECT_GT(connected, 10000u);
  EXPECT_GT(split, 10000u);
}

// The division-free index of the CVT's active lists equals Grid::Index, on grids at the 32-bit limit and on those it
// leaves to Grid::Index (an axis of size 1, more than 2^32 - 1 pixels).
TEST(GridIndexer, EqualsGridIndex)
{
  auto check = [](const auto & grid, bool byMultiplication) {
    using GridType = std::decay_t<decltype(grid)>;
    const itk::dmr::GridIndexer<GridType::Dimension> indexer(grid);
    EXPECT_EQ(indexer.GetByMultiplication(), byMultiplication);
    std::mt19937_64     random(11u);
    std::vector<size_t> pixels{ 0, 1, grid.numberOfPixels - 1, grid.numberOfPixels / 2 };
    for (unsigned int k = 0; k < GridType::Dimension; ++k)
    {
      pixels.push_back(grid.stride[k] * (grid.size[k] - 1));
      pixels.push_back(grid.stride[k] - (grid.stride[k] > 0 ? 1 : 0));
    }
    for (unsigned int n = 0; n < 100000; ++n)
    {
      pixels.push_back(std::uniform_int_distribution<size_t>(0, grid.numberOfPixels - 1)(random));
    }
    for (const size_t p : pixels)
    {
      ASSERT_EQ(indexer.Index(p), grid.Index(p)) << "pixel " << p;
    }
  };
  const std::array<double, 2> s2{ 1.0, 1.0 };
  const std::array<double, 3> s3{ 1.0, 1.0, 1.0 };
  check(itk::dmr::Grid<2>(std::array<size_t, 2>{ 512, 512 }, s2), true);
  check(itk::dmr::Grid<2>(std::array<size_t, 2>{ 65535, 65537 }, s2), true); // 2^32 - 1 pixels
  check(itk::dmr::Grid<2>(std::array<size_t, 2>{ 65536, 65536 }, s2), false);
  check(itk::dmr::Grid<3>(std::array<size_t, 3>{ 256, 256, 132 }, s3), true);
  check(itk::dmr::Grid<3>(std::array<size_t, 3>{ 4093, 1031, 1017 }, s3), true);
  check(itk::dmr::Grid<3>(std::array<size_t, 3>{ 3, 1, 7 }, s3), false);
  check(itk::dmr::Grid<3>(std::array<size_t, 3>{ 1, 5, 2 }, s3), false);
}
