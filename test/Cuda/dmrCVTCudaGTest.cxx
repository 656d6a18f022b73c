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
/** GPU agreement of the CVT swap optimisation (dmr::cuda::CVTSwapOptimizer) with the CPU reference
 * dmr::DiscreteCVT<D>: same contraction labels in, same labels out, sweep by sweep. */
#include "dmrCVTBackend.h"
#include "dmrDiscreteCVT.h"
#include "dmrTestHelpers.h"
#include "itkDiscreteCVTFilter.h"
#include "itkMultiThreaderBase.h"
#include "gtest/gtest.h"

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <limits>
#include <string>
#include <random>

namespace
{
using itk::dmr::cuda::CVTSwapOptimizer;
using itk::dmr::cuda::CVTSwapResult;
using itk::dmr::test::CellsAreFaceConnected;
using itk::dmr::test::ComputeCellStatistics;
using itk::dmr::test::LabelsAreCompact;

#define DMR_SKIP_WITHOUT_DEVICE()                                                                                      \
  if (!itk::dmr::cuda::DeviceAvailable())                                                                              \
  GTEST_SKIP() << "no CUDA device"

/** A non-uniform positive density: background + Gaussian bump at `centre` + a ring (shell in 3D) around the grid
 * centre, in grid-frame mm. */
template <unsigned int D>
std::vector<float>
BumpAndRing(const itk::dmr::Grid<D> & grid, const std::array<double, D> & centre)
{
  std::vector<float>    density(grid.numberOfPixels);
  std::array<double, D> middle;
  double                extent = 0.0;
  for (unsigned int k = 0; k < D; ++k)
  {
    middle[k] = 0.5 * static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
    extent = std::max(extent, middle[k]);
  }
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = itk::dmr::test::PixelPosition<D>(grid, p);
    double     b2 = 0.0, r2 = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      b2 += (x[k] - centre[k]) * (x[k] - centre[k]);
      r2 += (x[k] - middle[k]) * (x[k] - middle[k]);
    }
    const double s = 0.15 * extent, ring = std::sqrt(r2) - 0.6 * extent;
    density[p] = static_cast<float>(0.05 + 2.0 * std::exp(-b2 / (2.0 * s * s)) +
                                    std::exp(-ring * ring / (2.0 * 0.05 * extent * 0.05 * extent)));
  }
  return density;
}

size_t
CountDifferent(const std::vector<int32_t> & a, const std::vector<int32_t> & b)
{
  size_t n = 0;
  for (size_t i = 0; i < a.size(); ++i)
  {
    n += a[i] != b[i] ? 1u : 0u;
  }
  return n;
}

::testing::AssertionResult
Ok(const itk::dmr::cuda::Status & status)
{
  if (status.Ok())
  {
    return ::testing::AssertionSuccess();
  }
  return ::testing::AssertionFailure() << status.message;
}

/** Labels, masses and centroids of the GPU equal the CPU's (masses/centroids: the number of values not bit-equal
 * is reported, their relative difference must stay below 1e-12). */
template <unsigned int D>
void
ExpectSameState(const itk::dmr::DiscreteCVT<D> & cpu, const CVTSwapOptimizer & gpu, const std::string & when)
{
  std::vector<int32_t> labels(cpu.GetLabels().size());
  ASSERT_TRUE(Ok(gpu.DownloadLabels(labels.data())));
  const size_t different = CountDifferent(labels, cpu.GetLabels());
  EXPECT_EQ(different, 0u) << when << ": " << different << " of " << labels.size() << " labels differ ("
                           << 100.0 * static_cast<double>(different) / static_cast<double>(labels.size()) << " %)";
  std::vector<double> masses, centroids;
  ASSERT_TRUE(Ok(gpu.GetCells(masses, centroids)));
  ASSERT_EQ(masses.size(), cpu.GetMasses().size());
  size_t notBitEqual = 0;
  double worst = 0.0;
  for (size_t i = 0; i < masses.size(); ++i)
  {
    notBitEqual += masses[i] != cpu.GetMasses()[i] ? 1u : 0u;
    worst = std::max(worst, std::abs(masses[i] - cpu.GetMasses()[i]) / cpu.GetMasses()[i]);
  }
  for (size_t i = 0; i < centroids.size(); ++i)
  {
    notBitEqual += centroids[i] != cpu.GetCentroids()[i] ? 1u : 0u;
    worst = std::max(worst, std::abs(centroids[i] - cpu.GetCentroids()[i]) / (1.0 + std::abs(cpu.GetCentroids()[i])));
  }
  EXPECT_LE(worst, 1e-12) << when;
  EXPECT_EQ(notBitEqual, 0u) << when << ": masses/centroids not bit-equal (worst relative difference " << worst << ")";
  EXPECT_NEAR(gpu.Energy(), cpu.GetEnergy(), 1e-10 * cpu.GetEnergy()) << when;
}

/** The GPU energy is the brute-force energy of the GPU labels; cells are compact and face-connected. */
template <unsigned int D>
void
ExpectConsistentLabels(const itk::dmr::Grid<D> &  grid,
                       const std::vector<float> & density,
                       const CVTSwapOptimizer &   gpu,
                       size_t                     numberOfCells)
{
  std::vector<int32_t> labels(grid.numberOfPixels);
  ASSERT_TRUE(Ok(gpu.DownloadLabels(labels.data())));
  EXPECT_TRUE(LabelsAreCompact(labels, numberOfCells));
  EXPECT_TRUE(CellsAreFaceConnected<D>(grid, labels));
  const auto reference = ComputeCellStatistics<D>(grid, density.data(), labels, numberOfCells);
  EXPECT_NEAR(gpu.Energy(), reference.energy, 1e-9 * reference.energy);
}

/** How the GPU optimiser lays out its work (the settings that must not change its results). */
struct SweepLayout
{
  bool         shortLabels;     // SetShortLabels
  unsigned int slots;           // SetCellSlots
  unsigned int pixelsPerThread; // SetPixelsPerProposalThread
  std::string
  Name() const
  {
    return std::string(shortLabels ? "16-bit labels" : "32-bit labels") + ", " +
           (slots == std::numeric_limits<unsigned int>::max() ? std::string("default") : std::to_string(slots)) +
           " slots per cell, " + std::to_string(pixelsPerThread) + " pixels per proposal thread (0: automatic)";
  }
};

/** The layouts the label tests run: the defaults on both label widths, two slots per cell (most batches overflow
 * them) with two pixels per proposal thread, and the allocation pass without slots with one pixel per thread. */
constexpr unsigned int defaultSlots = std::numeric_limits<unsigned int>::max(); // SetCellSlots' default
const SweepLayout      sweepLayouts[] = { { true, defaultSlots, 0 },
                                          { false, defaultSlots, 0 },
                                          { true, 2, 2 },
                                          { true, 0, 1 } };

/** Contraction on the CPU, then sweep by sweep (Optimize with one sweep, epsilon 0) on both back-ends from the same
 * state, up to `sweeps` sweeps or convergence; then a warm start with `changed` the same way. The cells whose
 * entries overflowed their slots are counted in slotOverflows. */
template <unsigned int D>
void
ExpectGpuFollowsCpu(const itk::dmr::Grid<D> &  grid,
                    const std::vector<float> & density,
                    const std::vector<float> & changed,
                    size_t                     numberOfCells,
                    unsigned int               blockSize,
                    size_t                     sweeps,
                    const SweepLayout &        layout,
                    size_t &                   slotOverflows)
{
  const bool shortLabels = layout.shortLabels;
  slotOverflows = 0;
  itk::dmr::DiscreteCVT<D> cpu;
  cpu.SetDensity(grid, density.data(), nullptr);
  cpu.ContractionInitialize(numberOfCells, blockSize);
  ASSERT_EQ(cpu.GetNumberOfCells(), numberOfCells);

  CVTSwapOptimizer gpu;
  gpu.SetShortLabels(shortLabels);
  gpu.SetCellSlots(layout.slots);
  gpu.SetPixelsPerProposalThread(layout.pixelsPerThread);
  ASSERT_TRUE(Ok(gpu.SetGrid(D, grid.size.data(), grid.spacing.data())));
  ASSERT_TRUE(Ok(gpu.SetDensity(density.data(), false)));
  ASSERT_TRUE(Ok(gpu.SetLabels(cpu.GetLabels().data(), numberOfCells, false)));
  EXPECT_EQ(gpu.NumberOfCells(), numberOfCells);
  // the memory it reports holds at least the labels, their sort keys and pixel lists, and the 16-bit copy
  EXPECT_GE(gpu.AllocatedBytes(), grid.numberOfPixels * (4 * sizeof(int32_t) + (shortLabels ? sizeof(uint16_t) : 0)));
  ExpectSameState<D>(cpu, gpu, "after SetLabels");

  auto run = [&](const char * phase) {
    size_t totalSwaps = 0, totalRejected = 0;
    for (size_t s = 0; s < sweeps && !::testing::Test::HasFailure(); ++s)
    {
      const auto    c = cpu.Optimize(0.0, 1);
      CVTSwapResult g;
      ASSERT_TRUE(Ok(gpu.Optimize(0.0, 1, g)));
      const std::string when = std::string(phase) + ", sweep " + std::to_string(s);
      EXPECT_EQ(g.sweeps, c.sweeps) << when;
      EXPECT_EQ(g.swaps, c.swaps) << when;
      EXPECT_EQ(g.rejectedBatches, c.rejectedBatches) << when;
      EXPECT_LE(g.energyAfter, g.energyBefore) << when << ": the energy rose";
      ExpectSameState<D>(cpu, gpu, when);
      slotOverflows += g.slotOverflows;
      totalSwaps += g.swaps;
      totalRejected += g.rejectedBatches;
      if (g.swaps == 0)
      {
        break;
      }
    }
    std::cout << phase << ": " << totalSwaps << " swaps, " << totalRejected << " rejected batches, energy "
              << gpu.Energy() << std::endl;
    EXPECT_GT(totalSwaps, 0u) << phase;
  };
  run("from the contraction");
  ExpectConsistentLabels<D>(grid, density, gpu, numberOfCells);

  // warm start (paper 4.7): new density, same labels
  cpu.SetDensity(grid, changed.data(), nullptr);
  const std::vector<int32_t> previous = cpu.GetLabels();
  cpu.SetLabels(previous.data(), numberOfCells);
  ASSERT_TRUE(Ok(gpu.SetDensity(changed.data(), false)));
  ASSERT_TRUE(Ok(gpu.KeepLabels(numberOfCells)));
  ExpectSameState<D>(cpu, gpu, "after KeepLabels");
  run("warm start");
  ExpectConsistentLabels<D>(grid, changed, gpu, numberOfCells);

  // one Optimize call with many sweeps agrees too (the sweep loop and its stopping rule on the device)
  const auto    c = cpu.Optimize(0.0, 1000);
  CVTSwapResult g;
  ASSERT_TRUE(Ok(gpu.Optimize(0.0, 1000, g)));
  EXPECT_EQ(g.sweeps, c.sweeps);
  EXPECT_EQ(g.swaps, c.swaps);
  EXPECT_LE(g.energyAfter, g.energyBefore);
  ExpectSameState<D>(cpu, gpu, "converged");
  ExpectConsistentLabels<D>(grid, changed, gpu, numberOfCells);
  slotOverflows += g.slotOverflows;
}

/** ExpectGpuFollowsCpu on every layout; the slots must overflow where there are two per cell (so that the overflow
 * list, from which a full cell collects its other entries, is exercised) and never where there are none. */
template <unsigned int D>
void
ExpectGpuFollowsCpuInEveryLayout(const itk::dmr::Grid<D> &  grid,
                                 const std::vector<float> & density,
                                 const std::vector<float> & changed,
                                 size_t                     numberOfCells,
                                 unsigned int               blockSize,
                                 size_t                     sweeps)
{
  for (const auto & layout : sweepLayouts)
  {
    SCOPED_TRACE(layout.Name());
    size_t overflows = 0;
    ExpectGpuFollowsCpu<D>(grid, density, changed, numberOfCells, blockSize, sweeps, layout, overflows);
    std::cout << layout.Name() << ": " << overflows << " cells overflowed their slots" << std::endl;
    if (layout.slots == 0)
    {
      EXPECT_EQ(overflows, 0u);
    }
    if (layout.slots == 2)
    {
      EXPECT_GT(overflows, 0u);
    }
  }
}

TEST(CVTCuda, GpuLabelsEqualCpuLabels2D)
{
  DMR_SKIP_WITHOUT_DEVICE();
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 128, 96 }, std::array<double, 2>{ 1.0, 1.3 });
  const auto              density = BumpAndRing<2>(grid, { 40.0, 50.0 });
  const auto              changed = BumpAndRing<2>(grid, { 43.0, 52.0 });
  ExpectGpuFollowsCpuInEveryLayout<2>(grid, density, changed, 40, 1, 60);
}

TEST(CVTCuda, GpuLabelsEqualCpuLabels3D)
{
  DMR_SKIP_WITHOUT_DEVICE();
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 48, 40, 32 }, std::array<double, 3>{ 1.0, 1.2, 1.5 });
  const auto              density = BumpAndRing<3>(grid, { 18.0, 20.0, 24.0 });
  const auto              changed = BumpAndRing<3>(grid, { 20.0, 21.0, 23.0 });
  ExpectGpuFollowsCpuInEveryLayout<3>(grid, density, changed, 200, 2, 40);
}

TEST(CVTCuda, HalvedBatchesGiveTheCpuLabels)
{
  DMR_SKIP_WITHOUT_DEVICE();
  // heavy-tailed densities make joint commits raise the energy now and then (see the CPU test of the same name)
  std::mt19937 engine(2015u);
  size_t       rejected = 0;
  for (int trial = 0; trial < 30 && !::testing::Test::HasFailure(); ++trial)
  {
    const itk::dmr::Grid<2> grid(
      std::array<size_t, 2>{ 12 + static_cast<size_t>(trial % 20), 10 + static_cast<size_t>(trial % 15) },
      std::array<double, 2>{ 1.0, 1.0 });
    std::vector<float> density(grid.numberOfPixels);
    for (auto & d : density)
    {
      const double u = static_cast<double>(engine() >> 8) / 16777216.0;
      d = static_cast<float>(100.0 * u * u * u * u + 0.01);
    }
    const size_t             numberOfCells = 2 + static_cast<size_t>(trial % 6);
    itk::dmr::DiscreteCVT<2> cpu;
    cpu.SetDensity(grid, density.data(), nullptr);
    cpu.ContractionInitialize(numberOfCells, 1);
    const std::vector<int32_t> initial = cpu.GetLabels();
    const auto                 c = cpu.Optimize(0.0, 1000);
    // both ways of running the sweeps (the device-side loop; one launch plus host check per sweep), the second with
    // the 32-bit labels
    for (const bool deviceLoop : { true, false })
    {
      const std::string when = "trial " + std::to_string(trial) + (deviceLoop ? ", device loop" : ", host loop");
      CVTSwapOptimizer  gpu;
      gpu.SetDeviceLoop(deviceLoop);
      gpu.SetShortLabels(deviceLoop);
      ASSERT_TRUE(Ok(gpu.SetGrid(2, grid.size.data(), grid.spacing.data())));
      ASSERT_TRUE(Ok(gpu.SetDensity(density.data(), false)));
      ASSERT_TRUE(Ok(gpu.SetLabels(initial.data(), numberOfCells, false)));
      CVTSwapResult g;
      ASSERT_TRUE(Ok(gpu.Optimize(0.0, 1000, g)));
      EXPECT_EQ(g.rejectedBatches, c.rejectedBatches) << when;
      EXPECT_EQ(g.swaps, c.swaps) << when;
      EXPECT_EQ(g.sweeps, c.sweeps) << when;
      EXPECT_LE(g.energyAfter, g.energyBefore);
      ExpectSameState<2>(cpu, gpu, when);
      ExpectConsistentLabels<2>(grid, density, gpu, numberOfCells);
      rejected += deviceLoop ? g.rejectedBatches : 0;
    }
  }
  EXPECT_GT(rejected, 0u) << "no batch was halved: the test did not exercise the halving";
}

TEST(CVTCuda, DeviceLabelsFeedAnotherOptimizerAndBadLabelsAreReported)
{
  DMR_SKIP_WITHOUT_DEVICE();
  const itk::dmr::Grid<2>  grid(std::array<size_t, 2>{ 40, 30 }, std::array<double, 2>{ 1.0, 1.0 });
  const auto               density = BumpAndRing<2>(grid, { 12.0, 10.0 });
  itk::dmr::DiscreteCVT<2> cpu;
  cpu.SetDensity(grid, density.data(), nullptr);
  cpu.ContractionInitialize(10, 1);
  CVTSwapOptimizer a, b;
  ASSERT_TRUE(Ok(a.SetGrid(2, grid.size.data(), grid.spacing.data())));
  ASSERT_TRUE(Ok(a.SetDensity(density.data(), false)));
  ASSERT_TRUE(Ok(a.SetLabels(cpu.GetLabels().data(), 10, false)));
  CVTSwapResult r;
  ASSERT_TRUE(Ok(a.Optimize(0.0, 1000, r)));
  ASSERT_NE(a.DeviceLabels(), nullptr);
  ASSERT_TRUE(Ok(b.SetGrid(2, grid.size.data(), grid.spacing.data())));
  ASSERT_TRUE(Ok(b.SetDensity(density.data(), false)));
  ASSERT_TRUE(Ok(b.SetLabels(a.DeviceLabels(), 10, true))); // device-to-device
  EXPECT_NEAR(b.Energy(), a.Energy(), 1e-12 * a.Energy());
  ASSERT_TRUE(Ok(b.Optimize(0.0, 1000, r)));
  EXPECT_EQ(r.swaps, 0u) << "a converged labelling is a fixed point";

  std::vector<int32_t> labels = cpu.GetLabels();
  labels[77] = 10;
  const auto outside = b.SetLabels(labels.data(), 10, false);
  ASSERT_FALSE(outside.Ok());
  EXPECT_NE(outside.message.find("outside"), std::string::npos) << outside.message;
  EXPECT_NE(outside.message.find("77"), std::string::npos) << outside.message;
  labels = cpu.GetLabels();
  for (auto & l : labels)
  {
    l = l == 9 ? 0 : l; // cell 9 empty
  }
  const auto empty = b.SetLabels(labels.data(), 10, false);
  ASSERT_FALSE(empty.Ok());
  EXPECT_NE(empty.message.find("empty"), std::string::npos) << empty.message;
  EXPECT_FALSE(b.Optimize(0.0, 10, r).Ok()) << "no valid labels after a failed SetLabels";
  EXPECT_FALSE(b.KeepLabels(10).Ok());
  CVTSwapOptimizer fresh;
  EXPECT_FALSE(fresh.Optimize(0.0, 10, r).Ok());
  EXPECT_EQ(fresh.DeviceLabels(), nullptr);
}

/** The contraction with its block sums and labels on the device and its merges on the host (as the registration's
 * CUDA path makes it) against DiscreteCVT::ContractionInitialize: the same labels, masses and centroids, bit for bit
 * (the energy is summed in another order on each side). Sizes that are not multiples of the block size cut the last
 * blocks. */
template <unsigned int D>
void
ExpectDeviceContractionEqualsTheCpu(const itk::dmr::Grid<D> & grid, size_t cells, unsigned int blockSize)
{
  SCOPED_TRACE(std::to_string(D) + "D, " + std::to_string(cells) + " cells from blocks of " +
               std::to_string(blockSize));
  std::array<double, D> centre;
  for (unsigned int k = 0; k < D; ++k)
  {
    centre[k] = 0.3 * static_cast<double>(grid.size[k]) * grid.spacing[k];
  }
  const auto               density = BumpAndRing<D>(grid, centre);
  itk::dmr::DiscreteCVT<D> cpu;
  cpu.SetDensity(grid, density.data(), nullptr);
  cpu.ContractionInitialize(cells, blockSize);

  CVTSwapOptimizer gpu;
  ASSERT_TRUE(Ok(gpu.SetGrid(D, grid.size.data(), grid.spacing.data())));
  ASSERT_TRUE(Ok(gpu.SetDensity(density.data(), false)));
  std::vector<double> blockMass, blockCentroid;
  ASSERT_TRUE(Ok(gpu.ContractionBlockSums(blockSize, blockMass, blockCentroid)));
  std::array<size_t, D> nb;
  size_t                blocks = 1;
  for (unsigned int k = 0; k < D; ++k)
  {
    nb[k] = (grid.size[k] + blockSize - 1) / blockSize;
    blocks *= nb[k];
  }
  ASSERT_EQ(blockMass.size(), blocks);
  ASSERT_EQ(blockCentroid.size(), blocks * D);
  size_t     made = 0;
  const auto blockLabel =
    itk::dmr::DiscreteCVT<D>::ContractBlocks(nb, blockMass.data(), blockCentroid.data(), cells, {}, made);
  EXPECT_EQ(made, cells);
  ASSERT_TRUE(Ok(gpu.SetBlockLabels(blockSize, blockLabel.data(), cells)));
  std::vector<int32_t> labels(grid.numberOfPixels);
  ASSERT_TRUE(Ok(gpu.DownloadLabels(labels.data())));
  EXPECT_EQ(CountDifferent(labels, cpu.GetLabels()), 0u);
  std::vector<double> masses, centroids;
  ASSERT_TRUE(Ok(gpu.GetCells(masses, centroids)));
  EXPECT_EQ(masses, cpu.GetMasses());
  EXPECT_EQ(centroids, cpu.GetCentroids());
  EXPECT_NEAR(gpu.Energy(), cpu.GetEnergy(), 1e-10 * cpu.GetEnergy());
}

TEST(CVTCuda, ContractionWithDeviceBlockSumsEqualsTheCpuContraction)
{
  DMR_SKIP_WITHOUT_DEVICE();
  const itk::dmr::Grid<2> grid2(std::array<size_t, 2>{ 61, 45 }, std::array<double, 2>{ 1.0, 1.7 });
  const itk::dmr::Grid<3> grid3(std::array<size_t, 3>{ 30, 27, 13 }, std::array<double, 3>{ 0.9, 1.0, 2.5 });
  for (const unsigned int blockSize : { 1u, 2u, 4u })
  {
    ExpectDeviceContractionEqualsTheCpu<2>(grid2, 25, blockSize);
    ExpectDeviceContractionEqualsTheCpu<3>(grid3, 40, blockSize);
  }
  CVTSwapOptimizer    gpu;
  std::vector<double> m, c;
  EXPECT_FALSE(gpu.ContractionBlockSums(4, m, c).Ok()) << "no grid";
  ASSERT_TRUE(Ok(gpu.SetGrid(2, grid2.size.data(), grid2.spacing.data())));
  EXPECT_FALSE(gpu.ContractionBlockSums(4, m, c).Ok()) << "no density";
  EXPECT_FALSE(gpu.SetBlockLabels(1, nullptr, 3).Ok());
}

TEST(CVTCuda, FilterDispatchesToTheGpuWithTheCpuResult)
{
  DMR_SKIP_WITHOUT_DEVICE();
  using ImageType = itk::Image<float, 2>;
  using FilterType = itk::DiscreteCVTFilter<ImageType>;
  const itk::dmr::Grid<2>       grid(std::array<size_t, 2>{ 64, 50 }, std::array<double, 2>{ 1.0, 1.7 });
  const auto                    values = BumpAndRing<2>(grid, { 20.0, 30.0 });
  const ImageType::SizeType     size{ { 64, 50 } };
  const ImageType::SpacingType  spacing(std::array<double, 2>{ { 1.0, 1.7 } }.data());
  auto                          density = itk::dmr::test::ImageFromBuffer<ImageType>(size, spacing, values);
  FilterType::Pointer           filters[3];
  const FilterType::BackendEnum backends[3] = { FilterType::BackendEnum::CPU,
                                                FilterType::BackendEnum::CUDA,
                                                FilterType::BackendEnum::Auto };
  for (int i = 0; i < 3; ++i)
  {
    filters[i] = FilterType::New();
    filters[i]->SetInput(density);
    filters[i]->SetNumberOfCells(25);
    filters[i]->SetBackend(backends[i]);
    ASSERT_NO_THROW(filters[i]->Update());
  }
  EXPECT_EQ(filters[0]->GetBackendUsed(), FilterType::BackendEnum::CPU);
  for (int i = 1; i < 3; ++i)
  {
    EXPECT_EQ(filters[i]->GetBackendUsed(), FilterType::BackendEnum::CUDA);
    const auto * a = filters[0]->GetOutput();
    const auto * b = filters[i]->GetOutput();
    const size_t n = grid.numberOfPixels;
    EXPECT_TRUE(std::equal(a->GetBufferPointer(), a->GetBufferPointer() + n, b->GetBufferPointer()));
    EXPECT_EQ(filters[i]->GetNumberOfSweeps(), filters[0]->GetNumberOfSweeps());
    EXPECT_EQ(filters[i]->GetNumberOfSwaps(), filters[0]->GetNumberOfSwaps());
    EXPECT_NEAR(filters[i]->GetEnergy(), filters[0]->GetEnergy(), 1e-10 * filters[0]->GetEnergy());
    // the sites too, bit for bit: the core takes the GPU's masses and centroids, which the sweeps updated like the
    // CPU's (summed again from the labels, they would differ in the last bits)
    EXPECT_EQ(filters[i]->GetCore().GetMasses(), filters[0]->GetCore().GetMasses());
    EXPECT_EQ(filters[i]->GetCore().GetCentroids(), filters[0]->GetCore().GetCentroids());
    for (unsigned int c = 0; c < 25; ++c)
    {
      const auto p = filters[0]->GetSites()->GetPoint(c), q = filters[i]->GetSites()->GetPoint(c);
      EXPECT_EQ(p[0], q[0]);
      EXPECT_EQ(p[1], q[1]);
    }
  }
}

/** Timing on the paper's scale (256x256x132, 3000 cells): set DMR_CVT_BENCHMARK=1 to run. */
TEST(CVTCuda, BenchmarkWarmStart256x256x132)
{
  DMR_SKIP_WITHOUT_DEVICE();
  if (!std::getenv("DMR_CVT_BENCHMARK"))
  {
    GTEST_SKIP() << "set DMR_CVT_BENCHMARK=1 to run";
  }
  using Clock = std::chrono::steady_clock;
  auto ms = [](Clock::time_point a, Clock::time_point b) {
    return std::chrono::duration<double, std::milli>(b - a).count();
  };
  const itk::dmr::Grid<3>  grid(std::array<size_t, 3>{ 256, 256, 132 }, std::array<double, 3>{ 1.0, 1.0, 2.0 });
  const auto               density = BumpAndRing<3>(grid, { 100.0, 120.0, 130.0 });
  const auto               changed = BumpAndRing<3>(grid, { 101.0, 121.0, 131.0 });
  const size_t             cells = 3000;
  auto                     threader = itk::MultiThreaderBase::New();
  auto                     t0 = Clock::now();
  itk::dmr::DiscreteCVT<3> cpu;
  cpu.SetDensity(grid, density.data(), threader);
  cpu.ContractionInitialize(cells, 4);
  auto t1 = Clock::now();
  std::cout << "contraction (CPU): " << ms(t0, t1) << " ms" << std::endl;
  CVTSwapOptimizer gpu;
  ASSERT_TRUE(Ok(gpu.SetGrid(3, grid.size.data(), grid.spacing.data())));
  ASSERT_TRUE(Ok(gpu.SetDensity(density.data(), false)));
  t0 = Clock::now();
  ASSERT_TRUE(Ok(gpu.SetLabels(cpu.GetLabels().data(), cells, false)));
  t1 = Clock::now();
  CVTSwapResult r;
  ASSERT_TRUE(Ok(gpu.Optimize(0.0, 100000, r)));
  auto t2 = Clock::now();
  std::cout << "GPU SetLabels " << ms(t0, t1) << " ms; cold Optimize " << ms(t1, t2) << " ms, " << r.sweeps
            << " sweeps, " << r.swaps << " swaps, " << r.rejectedBatches << " rejected, " << r.slotOverflows
            << " slot overflows, E " << r.energyBefore << " -> " << r.energyAfter << std::endl;
  std::vector<int32_t> converged(grid.numberOfPixels);
  ASSERT_TRUE(Ok(gpu.DownloadLabels(converged.data())));
  const auto upload = changed; // host density of the next iteration (the registration passes a device pointer)
  for (int repeat = 0; repeat < 3; ++repeat)
  {
    ASSERT_TRUE(Ok(gpu.SetDensity(density.data(), false)));
    ASSERT_TRUE(Ok(gpu.SetLabels(converged.data(), cells, false)));
    t0 = Clock::now();
    ASSERT_TRUE(Ok(gpu.SetDensity(upload.data(), false)));
    t1 = Clock::now();
    ASSERT_TRUE(Ok(gpu.KeepLabels(cells)));
    t2 = Clock::now();
    ASSERT_TRUE(Ok(gpu.Optimize(0.0, 100000, r)));
    auto t3 = Clock::now();
    std::cout << "warm start " << repeat << ": density upload " << ms(t0, t1) << " ms, KeepLabels " << ms(t1, t2)
              << " ms, Optimize " << ms(t2, t3) << " ms (" << r.sweeps << " sweeps, " << r.swaps << " swaps, "
              << r.rejectedBatches << " rejected, " << r.slotOverflows << " slot overflows, "
              << ms(t2, t3) / std::max<size_t>(1, r.sweeps) << " ms/sweep)" << std::endl;
  }
  {
    t0 = Clock::now();
    CVTSwapResult idle;
    ASSERT_TRUE(Ok(gpu.Optimize(0.0, 1, idle)));
    t1 = Clock::now();
    EXPECT_EQ(idle.swaps, 0u);
    std::cout << "one sweep of a converged labelling (fixed cost per sweep): " << ms(t0, t1) << " ms" << std::endl;
    std::vector<int32_t> after(grid.numberOfPixels);
    ASSERT_TRUE(Ok(gpu.DownloadLabels(after.data())));
    for (const double epsilon : { 1e-5, 1e-4 })
    {
      ASSERT_TRUE(Ok(gpu.SetDensity(density.data(), false)));
      ASSERT_TRUE(Ok(gpu.SetLabels(converged.data(), cells, false)));
      ASSERT_TRUE(Ok(gpu.SetDensity(upload.data(), false)));
      t0 = Clock::now();
      ASSERT_TRUE(Ok(gpu.KeepLabels(cells)));
      CVTSwapResult e;
      ASSERT_TRUE(Ok(gpu.Optimize(epsilon, 100000, e)));
      t1 = Clock::now();
      std::cout << "warm start, epsilon " << epsilon << ": KeepLabels + Optimize " << ms(t0, t1) << " ms (" << e.sweeps
                << " sweeps, " << e.swaps << " swaps, E " << e.energyBefore << " -> " << e.energyAfter << ")"
                << std::endl;
    }
    // back to the epsilon-0 result for the comparison with the CPU below
    ASSERT_TRUE(Ok(gpu.SetLabels(after.data(), cells, false)));
  }
  // the CPU on the same warm start, for the speed-up and one agreement check at scale
  cpu.SetDensity(grid, changed.data(), threader);
  cpu.SetLabels(converged.data(), cells);
  t0 = Clock::now();
  const auto c = cpu.Optimize(0.0, 100000);
  t1 = Clock::now();
  std::cout << "CPU warm start Optimize (" << threader->GetNumberOfWorkUnits() << " threads): " << ms(t0, t1) << " ms, "
            << c.sweeps << " sweeps" << std::endl;
  std::vector<int32_t> labels(grid.numberOfPixels);
  ASSERT_TRUE(Ok(gpu.DownloadLabels(labels.data())));
  const size_t different = CountDifferent(labels, cpu.GetLabels());
  std::cout << "labels different from the CPU: " << different << "; energy GPU " << gpu.Energy() << " CPU "
            << cpu.GetEnergy() << std::endl;
  EXPECT_EQ(different, 0u);
  EXPECT_EQ(r.sweeps, c.sweeps);
}
} // namespace
