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
// GPU label summary (dmr::cuda::LabelSummarizer) against the CPU one (dmr::SummarizeLabels): every field identical.
#include "dmrDualMeshBackend.h"
#include "dmrDualMeshBuilder.h"
#include "dmrDualMeshPhantom.h"
#include "dmrLabelSummaryHelpers.h"
#include "gtest/gtest.h"

#include <chrono>
#include <iostream>

namespace
{
using itk::dmr::Grid;
using itk::dmr::LabelSummary;
using itk::dmr::test::SameSummary;

template <unsigned int D>
Grid<D>
MakeGrid(std::array<size_t, D> size)
{
  std::array<double, D> spacing;
  spacing.fill(1.0);
  return Grid<D>(size, spacing);
}

/** GPU summary (through the given summarizer, or the shared one) of host labels against the CPU summary. */
template <unsigned int D>
::testing::AssertionResult
GpuSummaryIsTheCpuSummary(const Grid<D> &                   grid,
                          const std::vector<int32_t> &      labels,
                          size_t                            nCells,
                          itk::dmr::cuda::LabelSummarizer * summarizer = nullptr)
{
  auto               threader = itk::MultiThreaderBase::New();
  const LabelSummary cpu = itk::dmr::SummarizeLabels<D>(grid, labels.data(), nCells, threader);
  LabelSummary       gpu;
  const auto status = summarizer ? summarizer->SummarizeHostLabels(D, grid.size.data(), labels.data(), nCells, gpu)
                                 : itk::dmr::cuda::SummarizeHostLabels(D, grid.size.data(), labels.data(), nCells, gpu);
  if (!status.Ok())
  {
    return ::testing::AssertionFailure() << "GPU summary failed: " << status.message;
  }
  return SameSummary(gpu, cpu);
}

template <typename TPhantom>
std::vector<int32_t>
PhantomLabels(const TPhantom & phantom)
{
  const auto * L = phantom.cvt->GetOutput()->GetBufferPointer();
  return std::vector<int32_t>(L, L + phantom.GetGrid().numberOfPixels);
}

TEST(DualMeshCuda, SummaryOf2DPhantomMatchesCpu)
{
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom(40);
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<2>(phantom.GetGrid(), PhantomLabels(phantom), 40));
}

TEST(DualMeshCuda, SummaryOf3DPhantomMatchesCpu)
{
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom3D(200);
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<3>(phantom.GetGrid(), PhantomLabels(phantom), 200));
}

TEST(DualMeshCuda, SummaryOfRandomLabelsMatchesCpu)
{
  // no spatial coherence: the block-local tables overflow into global memory and the key list is regrown
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  const auto grid2 = MakeGrid<2>({ { 300, 200 } });
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<2>(grid2, itk::dmr::test::RandomLabels(grid2.numberOfPixels, 5000, 1), 5000));
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<2>(grid2, itk::dmr::test::RandomLabels(grid2.numberOfPixels, 7, 2), 7));
  const auto grid3 = MakeGrid<3>({ { 64, 48, 40 } });
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<3>(grid3, itk::dmr::test::RandomLabels(grid3.numberOfPixels, 20000, 3), 20000));
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<3>(grid3, itk::dmr::test::RandomLabels(grid3.numberOfPixels, 3, 4), 3));
}

TEST(DualMeshCuda, SummaryOfVoronoiLabelsMatchesCpu)
{
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  const auto grid2 = MakeGrid<2>({ { 333, 251 } });
  EXPECT_TRUE(
    GpuSummaryIsTheCpuSummary<2>(grid2, itk::dmr::test::LatticeVoronoiLabels<2>(grid2, { { 21, 17 } }, 5), 21 * 17));
  const auto grid3 = MakeGrid<3>({ { 97, 61, 45 } });
  EXPECT_TRUE(
    GpuSummaryIsTheCpuSummary<3>(grid3, itk::dmr::test::LatticeVoronoiLabels<3>(grid3, { { 9, 7, 5 } }, 6), 9 * 7 * 5));
}

TEST(DualMeshCuda, SummaryOfThinAndOddSizesMatchesCpu)
{
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  for (const auto & size : { std::array<size_t, 2>{ { 1, 1 } },
                             std::array<size_t, 2>{ { 5, 1 } },
                             std::array<size_t, 2>{ { 1, 7 } },
                             std::array<size_t, 2>{ { 2, 2 } },
                             std::array<size_t, 2>{ { 1001, 3 } },
                             std::array<size_t, 2>{ { 3, 1001 } } })
  {
    const auto grid = MakeGrid<2>(size);
    const auto n = std::min<size_t>(5, grid.numberOfPixels);
    EXPECT_TRUE(GpuSummaryIsTheCpuSummary<2>(grid, itk::dmr::test::RandomLabels(grid.numberOfPixels, n, 8), n))
      << size[0] << "x" << size[1];
  }
  for (const auto & size : { std::array<size_t, 3>{ { 1, 1, 1 } },
                             std::array<size_t, 3>{ { 2, 2, 2 } },
                             std::array<size_t, 3>{ { 3, 1, 5 } },
                             std::array<size_t, 3>{ { 17, 3, 1 } },
                             std::array<size_t, 3>{ { 1, 9, 13 } },
                             std::array<size_t, 3>{ { 33, 2, 19 } } })
  {
    const auto grid = MakeGrid<3>(size);
    const auto n = std::min<size_t>(6, grid.numberOfPixels);
    EXPECT_TRUE(GpuSummaryIsTheCpuSummary<3>(grid, itk::dmr::test::RandomLabels(grid.numberOfPixels, n, 9), n))
      << size[0] << "x" << size[1] << "x" << size[2];
  }
}

TEST(DualMeshCuda, OneSummarizerServesChangingInputsFromDeviceLabels)
{
  // the scratch buffers are reused and regrown across calls of different sizes and dimensions
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  itk::dmr::cuda::LabelSummarizer summarizer;
  const auto                      big = MakeGrid<3>({ { 80, 70, 30 } });
  const auto                      small = MakeGrid<2>({ { 40, 30 } });
  const auto                      bigLabels = itk::dmr::test::LatticeVoronoiLabels<3>(big, { { 8, 7, 3 } }, 10);
  const auto                      smallLabels = itk::dmr::test::LatticeVoronoiLabels<2>(small, { { 4, 3 } }, 11);
  for (int round = 0; round < 2; ++round)
  {
    EXPECT_TRUE(GpuSummaryIsTheCpuSummary<3>(big, bigLabels, 168, &summarizer));
    EXPECT_TRUE(GpuSummaryIsTheCpuSummary<2>(small, smallLabels, 12, &summarizer));
  }
  // the device-pointer entry point on labels that are already on the device
  ASSERT_TRUE(summarizer.UploadLabels(bigLabels.data(), bigLabels.size()).Ok());
  LabelSummary fromDevice, shared;
  ASSERT_TRUE(summarizer.Summarize(3, big.size.data(), summarizer.UploadedLabels(), 168, fromDevice).Ok());
  ASSERT_TRUE(itk::dmr::cuda::SummarizeLabels(3, big.size.data(), summarizer.UploadedLabels(), 168, shared).Ok());
  const auto cpu = itk::dmr::SummarizeLabels<3>(big, bigLabels.data(), 168, nullptr);
  EXPECT_TRUE(SameSummary(fromDevice, cpu));
  EXPECT_TRUE(SameSummary(shared, cpu));
}

TEST(DualMeshCuda, SummaryWithoutAdjacentPairsIsTheRestOfTheCpuSummary)
{
  // SetFindAdjacentPairs(false), as the 3D registration calls it: every other field as the CPU's, no pairs; turned
  // on again, the pairs are back
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  itk::dmr::cuda::LabelSummarizer summarizer;
  EXPECT_TRUE(summarizer.GetFindAdjacentPairs());
  auto withoutPairs = [&](auto grid, const std::vector<int32_t> & labels, size_t nCells) {
    constexpr unsigned int D = decltype(grid)::Dimension;
    LabelSummary           cpu = itk::dmr::SummarizeLabels<D>(grid, labels.data(), nCells, nullptr), gpu;
    EXPECT_FALSE(cpu.adjacentPairs.empty());
    cpu.adjacentPairs.clear();
    summarizer.SetFindAdjacentPairs(false);
    EXPECT_TRUE(summarizer.SummarizeHostLabels(D, grid.size.data(), labels.data(), nCells, gpu).Ok());
    EXPECT_TRUE(SameSummary(gpu, cpu));
    summarizer.SetFindAdjacentPairs(true);
    EXPECT_TRUE(GpuSummaryIsTheCpuSummary<D>(grid, labels, nCells, &summarizer));
  };
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom3D(200);
  withoutPairs(phantom.GetGrid(), PhantomLabels(phantom), 200);
  const auto grid3 = MakeGrid<3>({ { 64, 48, 40 } });
  withoutPairs(grid3, itk::dmr::test::RandomLabels(grid3.numberOfPixels, 20000, 3), 20000);
  const auto grid2 = MakeGrid<2>({ { 333, 251 } });
  withoutPairs(grid2, itk::dmr::test::LatticeVoronoiLabels<2>(grid2, { { 21, 17 } }, 5), 21 * 17);
  // a label out of range is still found
  std::vector<int32_t> bad = itk::dmr::test::RandomLabels(grid3.numberOfPixels, 7, 4);
  bad[1234] = 7;
  LabelSummary out;
  summarizer.SetFindAdjacentPairs(false);
  const auto status = summarizer.SummarizeHostLabels(3, grid3.size.data(), bad.data(), 7, out);
  EXPECT_FALSE(status.Ok());
  EXPECT_NE(status.message.find("outside"), std::string::npos) << status.message;
}

TEST(DualMeshCuda, BadInputGivesAnErrorStatus)
{
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  itk::dmr::cuda::LabelSummarizer summarizer;
  const auto                      grid = MakeGrid<3>({ { 20, 10, 6 } });
  auto                            labels = itk::dmr::test::RandomLabels(grid.numberOfPixels, 4, 12);
  LabelSummary                    out;
  labels[77] = 4;
  auto status = summarizer.SummarizeHostLabels(3, grid.size.data(), labels.data(), 4, out);
  EXPECT_FALSE(status.Ok());
  EXPECT_NE(status.message.find("outside"), std::string::npos) << status.message;
  labels[77] = -3;
  EXPECT_FALSE(summarizer.SummarizeHostLabels(3, grid.size.data(), labels.data(), 4, out).Ok());
  EXPECT_FALSE(summarizer.SummarizeHostLabels(4, grid.size.data(), labels.data(), 4, out).Ok());
  EXPECT_FALSE(summarizer.Summarize(3, grid.size.data(), nullptr, 4, out).Ok());
  EXPECT_FALSE(summarizer.SummarizeHostLabels(3, grid.size.data(), labels.data(), 0, out).Ok());
  // the summarizer still works after the errors
  labels[77] = 1;
  EXPECT_TRUE(GpuSummaryIsTheCpuSummary<3>(grid, labels, 4, &summarizer));
}

TEST(DualMeshCuda, MeshFromTheGpuSummaryIsTheFilterMesh)
{
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  const auto   phantom = itk::dmr::test::MakeDualMeshPhantom3D(200);
  const auto   grid = phantom.GetGrid();
  const auto   labels = PhantomLabels(phantom);
  LabelSummary gpu;
  ASSERT_TRUE(itk::dmr::cuda::SummarizeHostLabels(3, grid.size.data(), labels.data(), 200, gpu).Ok());
  // the filter was run with the CVT sites; without sites both use the cells' centroids
  auto filter = itk::dmr::test::DualMeshPhantom3D::DualMeshFilterType::New();
  filter->SetInput(phantom.cvt->GetOutput());
  filter->Update();
  itk::dmr::DualMeshStatistics statistics;
  const auto                   mesh = itk::dmr::BuildDualMesh<3>(grid, gpu, nullptr, true, &statistics);
  EXPECT_EQ(mesh.nodes, filter->GetSimplexMesh().nodes);
  EXPECT_EQ(mesh.elements, filter->GetSimplexMesh().elements);
  EXPECT_EQ(statistics.numberOfMissingAdjacencyEdges, filter->GetNumberOfMissingAdjacencyEdges());
}

TEST(DualMeshCuda, SummaryTiming256x256x132With3150Cells)
{
  // the registration's size: the summary replaces downloading 256 x 256 x 132 labels (35 MB) every iteration
  if (!itk::dmr::cuda::DeviceAvailable())
    GTEST_SKIP() << "no CUDA device";
  Grid<3>      grid(std::array<size_t, 3>{ { 256, 256, 132 } }, std::array<double, 3>{ { 1.0, 1.0, 2.0 } });
  const auto   labels = itk::dmr::test::LatticeVoronoiLabels<3>(grid, { { 15, 15, 14 } }, 2024);
  const size_t nCells = 15 * 15 * 14;

  itk::dmr::cuda::LabelSummarizer summarizer;
  ASSERT_TRUE(summarizer.UploadLabels(labels.data(), labels.size()).Ok());
  LabelSummary gpu;
  for (int i = 0; i < 3; ++i) // warm-up: allocations, CUB temporary storage, pinned staging
  {
    ASSERT_TRUE(summarizer.Summarize(3, grid.size.data(), summarizer.UploadedLabels(), nCells, gpu).Ok());
  }
  constexpr int runs = 50;
  double        total = 0.0, best = 1e30;
  for (int i = 0; i < runs; ++i)
  {
    const auto start = std::chrono::steady_clock::now();
    ASSERT_TRUE(summarizer.Summarize(3, grid.size.data(), summarizer.UploadedLabels(), nCells, gpu).Ok());
    const double us = std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - start).count();
    total += us;
    best = std::min(best, us);
  }
  auto         threader = itk::MultiThreaderBase::New();
  const auto   cpuStart = std::chrono::steady_clock::now();
  const auto   cpu = itk::dmr::SummarizeLabels<3>(grid, labels.data(), nCells, threader);
  const double cpuMs = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - cpuStart).count();
  EXPECT_TRUE(SameSummary(gpu, cpu));
  std::cout << "[ TIMING   ] GPU label summary 256x256x132, " << nCells << " cells, " << gpu.adjacentPairs.size()
            << " adjacent pairs on " << itk::dmr::cuda::DeviceDescription() << ": mean " << total / runs << " us, min "
            << best << " us over " << runs << " calls (device labels, summary downloaded); CPU " << cpuMs << " ms with "
            << threader->GetNumberOfWorkUnits() << " work units" << std::endl;
  RecordProperty("gpu_mean_us", std::to_string(total / runs));
}
} // namespace
