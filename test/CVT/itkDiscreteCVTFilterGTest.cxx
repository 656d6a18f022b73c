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
#include "itkDiscreteCVTFilter.h"
#include "itkCastImageFilter.h"
#include "itkCommand.h"
#include "dmrCVTBackend.h"
#include "dmrObjectChecks.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"
#include <algorithm>
#include <cmath>

namespace
{
using ImageType = itk::Image<float, 2>;
using LabelImageType = itk::Image<int32_t, 2>;
using FilterType = itk::DiscreteCVTFilter<ImageType>;

/** 48x40 random positive density, spacing 1.0 x 1.7, rotated by 30 degrees, origin (12, -7). */
ImageType::Pointer
MakeDensity(uint32_t seed = 7u)
{
  const ImageType::SizeType    size{ { 48, 40 } };
  const ImageType::SpacingType spacing(std::array<double, 2>{ { 1.0, 1.7 } }.data());
  const auto                   values = itk::dmr::test::RandomDensity(size[0] * size[1], seed);
  auto                         image = itk::dmr::test::ImageFromBuffer<ImageType>(size, spacing, values);
  image->SetDirection(itk::dmr::test::RotationDirection2D<ImageType>(0.5235987755982988));
  ImageType::PointType origin;
  origin[0] = 12.0;
  origin[1] = -7.0;
  image->SetOrigin(origin);
  return image;
}

std::vector<int32_t>
LabelsOf(const LabelImageType * image)
{
  const size_t n = image->GetLargestPossibleRegion().GetNumberOfPixels();
  return std::vector<int32_t>(image->GetBufferPointer(), image->GetBufferPointer() + n);
}

TEST(DiscreteCVTFilter, BasicObjectMethodsAndPrintCoverEveryMember)
{
  auto filter = FilterType::New();
  EXPECT_TRUE(itk::dmr::test::BasicObjectMethods(filter.GetPointer(), "DiscreteCVTFilter", "ImageToImageFilter"));
  EXPECT_TRUE(itk::dmr::test::PrintMentions(filter.GetPointer(),
                                            { "NumberOfCells",
                                              "BlockSize",
                                              "Epsilon",
                                              "MaximumNumberOfSweeps",
                                              "SwapOptimization",
                                              "Backend",
                                              "BackendUsed",
                                              "InitialEnergy",
                                              "Energy",
                                              "NumberOfSweeps",
                                              "NumberOfSwaps",
                                              "InitializationTime",
                                              "OptimizationTime" }));
}

TEST(DiscreteCVTFilter, SetGetRoundTripsAndClamps)
{
  auto filter = FilterType::New();
  DMR_EXPECT_SET_GET(filter, NumberOfCells, itk::SizeValueType{ 37 });
  DMR_EXPECT_SET_GET(filter, BlockSize, 3u);
  DMR_EXPECT_SET_GET(filter, Epsilon, 0.01);
  DMR_EXPECT_SET_GET(filter, MaximumNumberOfSweeps, itk::SizeValueType{ 17 });
  EXPECT_TRUE(filter->GetSwapOptimization());
  DMR_EXPECT_SET_GET(filter, SwapOptimization, false);
  filter->SwapOptimizationOn();
  EXPECT_TRUE(filter->GetSwapOptimization());
  DMR_EXPECT_SET_GET(filter, Backend, FilterType::BackendEnum::CPU);
  DMR_EXPECT_SET_GET(filter, Backend, FilterType::BackendEnum::Auto);
  filter->SetNumberOfCells(1);
  EXPECT_EQ(filter->GetNumberOfCells(), 4u);
  filter->SetBlockSize(0);
  EXPECT_EQ(filter->GetBlockSize(), 1u);
  filter->SetEpsilon(2.0);
  EXPECT_EQ(filter->GetEpsilon(), 1.0);
  filter->SetMaximumNumberOfSweeps(0);
  EXPECT_EQ(filter->GetMaximumNumberOfSweeps(), 1u);
  auto labels = LabelImageType::New();
  filter->SetInitialLabels(labels);
  EXPECT_EQ(filter->GetInitialLabels(), labels.GetPointer());
}

TEST(DiscreteCVTFilter, BadInputThrows)
{
  {
    auto filter = FilterType::New();
    filter->SetInput(MakeDensity());
    filter->SetNumberOfCells(48 * 40 + 1);
    EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  }
  {
    auto density = MakeDensity();
    density->GetBufferPointer()[100] = 0.0f;
    auto filter = FilterType::New();
    filter->SetInput(density);
    filter->SetNumberOfCells(12);
    EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  }
  {
    auto density = MakeDensity();
    auto filter = FilterType::New();
    filter->SetInput(density);
    filter->SetNumberOfCells(12);
    auto wrong = LabelImageType::New();
    wrong->CopyInformation(density); // the same physical space, another size
    wrong->SetRegions(LabelImageType::SizeType{ { 10, 10 } });
    wrong->Allocate(true);
    filter->SetInitialLabels(wrong);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      filter, { "InitialLabels must lie on the density image's grid", "differs from the density image size" }));
  }
  {
    // the density's size but another region start: the same pixels would belong to other points
    auto density = MakeDensity();
    auto filter = FilterType::New();
    filter->SetInput(density);
    filter->SetNumberOfCells(12);
    auto shifted = LabelImageType::New();
    shifted->CopyInformation(density);
    auto region = density->GetLargestPossibleRegion();
    region.SetIndex(0, 5);
    shifted->SetRegions(region);
    shifted->Allocate(true);
    filter->SetInitialLabels(shifted);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(filter, { "its region starts at [5, 0]" }));
  }
  {
    // a NaN epsilon passes the clamping setter and stopped no sweep
    auto filter = FilterType::New();
    filter->SetInput(MakeDensity());
    filter->SetNumberOfCells(12);
    filter->SetEpsilon(std::nan(""));
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(filter, { "Epsilon must be a number in [0, 1], not NaN" }));
  }
  {
    // a sheared direction: the CVT's distances are the grid's scaled by the spacing, physical only for a rotation
    auto density = MakeDensity();
    auto direction = density->GetDirection();
    direction[0][1] = 0.4;
    density->SetDirection(direction);
    auto filter = FilterType::New();
    filter->SetInput(density);
    filter->SetNumberOfCells(12);
    EXPECT_TRUE(
      itk::dmr::test::UpdateThrowsMentioning(filter, { "the density image's direction matrix is not orthonormal" }));
  }
}

// An input that is the output of a filter not yet run has no size until the pipeline's information pass reaches it.
TEST(DiscreteCVTFilter, RunsDownstreamOfAFilterThatHasNotRun)
{
  using CastType = itk::CastImageFilter<ImageType, ImageType>;
  const auto density = MakeDensity();
  auto       direct = FilterType::New();
  direct->SetInput(density);
  direct->SetNumberOfCells(12);
  direct->Update();

  auto stage = CastType::New();
  stage->SetInput(density);
  auto filter = FilterType::New();
  filter->SetInput(stage->GetOutput());
  filter->SetNumberOfCells(12);
  ASSERT_NO_THROW(filter->Update());
  EXPECT_EQ(LabelsOf(filter->GetOutput()), LabelsOf(direct->GetOutput()));

  // the checks on the input's size still hold once the pipeline has run
  auto bad = FilterType::New();
  auto badStage = CastType::New();
  badStage->SetInput(density);
  bad->SetInput(badStage->GetOutput());
  bad->SetNumberOfCells(48 * 40 + 1);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(bad, { "exceeds the number of pixels (1920)" }));
}

TEST(DiscreteCVTFilter, LabelPixelTypeMustHoldEveryCell)
{
  // unsigned char labels (a type the ITK Python wrapping offers) hold 256 cells: 0 .. 255
  using ByteLabelsFilterType = itk::DiscreteCVTFilter<ImageType, itk::Image<unsigned char, 2>>;
  auto density = MakeDensity();
  {
    auto filter = ByteLabelsFilterType::New();
    filter->SetInput(density);
    filter->SetNumberOfCells(257);
    EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  }
  auto filter = ByteLabelsFilterType::New();
  filter->SetInput(density);
  filter->SetNumberOfCells(256);
  filter->SetMaximumNumberOfSweeps(2);
  filter->Update();
  const auto *         output = filter->GetOutput();
  const size_t         n = output->GetLargestPossibleRegion().GetNumberOfPixels();
  std::vector<int32_t> labels(output->GetBufferPointer(), output->GetBufferPointer() + n);
  EXPECT_TRUE(itk::dmr::test::LabelsAreCompact(labels, 256));
}

TEST(DiscreteCVTFilter, OutputIsConnectedAndEnergyIsTheLabelsEnergy)
{
  auto density = MakeDensity();
  auto filter = FilterType::New();
  filter->SetInput(density);
  filter->SetNumberOfCells(12);
  filter->Update();
  const LabelImageType * output = filter->GetOutput();
  EXPECT_EQ(output->GetLargestPossibleRegion(), density->GetLargestPossibleRegion());
  EXPECT_EQ(output->GetSpacing(), density->GetSpacing());
  EXPECT_EQ(output->GetOrigin(), density->GetOrigin());
  EXPECT_EQ(output->GetDirection(), density->GetDirection());

  const auto grid = itk::dmr::Grid<2>::FromImage(density);
  const auto labels = LabelsOf(output);
  EXPECT_TRUE(itk::dmr::test::LabelsAreCompact(labels, 12));
  EXPECT_TRUE(itk::dmr::test::CellsAreFaceConnected<2>(grid, labels));
  const auto reference = itk::dmr::test::ComputeCellStatistics<2>(grid, density->GetBufferPointer(), labels, 12);
  EXPECT_NEAR(filter->GetEnergy(), reference.energy, 1e-9 * reference.energy);
  EXPECT_LE(filter->GetEnergy(), filter->GetInitialEnergy());
  EXPECT_GE(filter->GetNumberOfSweeps(), 1u);
  EXPECT_LT(filter->GetNumberOfSweeps(), filter->GetMaximumNumberOfSweeps());
  EXPECT_EQ(filter->GetBackendUsed(), FilterType::BackendEnum::CPU);
}

TEST(DiscreteCVTFilter, SitesArePhysicalWeightedCentroids)
{
  auto density = MakeDensity();
  auto filter = FilterType::New();
  filter->SetInput(density);
  filter->SetNumberOfCells(12);
  filter->Update();
  const auto   labels = LabelsOf(filter->GetOutput());
  const auto * sites = filter->GetSites();
  ASSERT_NE(sites, nullptr);
  ASSERT_EQ(sites->GetNumberOfPoints(), 12u);
  // density-weighted mean of the physical pixel positions, computed independently of the grid frame
  std::vector<double>                               mass(12, 0.0), sum(24, 0.0);
  itk::ImageRegionConstIteratorWithIndex<ImageType> it(density, density->GetLargestPossibleRegion());
  size_t                                            p = 0;
  for (it.GoToBegin(); !it.IsAtEnd(); ++it, ++p)
  {
    ImageType::PointType x;
    density->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    mass[labels[p]] += it.Get();
    sum[labels[p] * 2] += it.Get() * x[0];
    sum[labels[p] * 2 + 1] += it.Get() * x[1];
  }
  for (unsigned int c = 0; c < 12; ++c)
  {
    const auto site = sites->GetPoint(c);
    // SitesType = PointSet<double, D> has the default mesh traits, whose coordinates are float: allow one float
    // rounding of the physical coordinate (reported: double coordinates would keep the centroids exact)
    const double x0 = sum[c * 2] / mass[c], x1 = sum[c * 2 + 1] / mass[c];
    EXPECT_NEAR(site[0], x0, 1.2e-7 * std::abs(x0) + 1e-9) << "cell " << c;
    EXPECT_NEAR(site[1], x1, 1.2e-7 * std::abs(x1) + 1e-9) << "cell " << c;
    double data = 0.0;
    ASSERT_TRUE(sites->GetPointData(c, &data));
    EXPECT_NEAR(data, mass[c], 1e-9 * mass[c]);
  }
}

TEST(DiscreteCVTFilter, WarmStartFromItsOwnOutputDoesNotRaiseEnergy)
{
  auto density = MakeDensity();
  auto first = FilterType::New();
  first->SetInput(density);
  first->SetNumberOfCells(12);
  first->SetMaximumNumberOfSweeps(2); // stop early: the warm start has work left to do
  first->Update();
  ASSERT_EQ(first->GetNumberOfSweeps(), 2u);

  LabelImageType::Pointer initial = first->GetOutput();
  initial->DisconnectPipeline();
  auto warm = FilterType::New();
  warm->SetInput(density);
  warm->SetNumberOfCells(12);
  warm->SetInitialLabels(initial);
  warm->Update();
  EXPECT_EQ(warm->GetInitializationTime(), 0.0); // no contraction on a warm start
  EXPECT_NEAR(warm->GetInitialEnergy(), first->GetEnergy(), 1e-9 * first->GetEnergy());
  EXPECT_LT(warm->GetEnergy(), warm->GetInitialEnergy());
  EXPECT_GT(warm->GetNumberOfSwaps(), 0u);
  const auto grid = itk::dmr::Grid<2>::FromImage(density);
  EXPECT_TRUE(itk::dmr::test::CellsAreFaceConnected<2>(grid, LabelsOf(warm->GetOutput())));

  // a converged labelling is a fixed point of the warm start
  LabelImageType::Pointer converged = warm->GetOutput();
  converged->DisconnectPipeline();
  auto again = FilterType::New();
  again->SetInput(density);
  again->SetNumberOfCells(12);
  again->SetInitialLabels(converged);
  again->Update();
  EXPECT_EQ(again->GetNumberOfSwaps(), 0u);
  EXPECT_NEAR(again->GetEnergy(), warm->GetEnergy(), 1e-9 * warm->GetEnergy());
  EXPECT_EQ(LabelsOf(again->GetOutput()), LabelsOf(converged));
}

// SwapOptimization off: the output is the contraction's tessellation (the CUDA registration contracts through the
// filter and sweeps on its own device optimiser); the optimised filter starts from it and lowers the energy.
TEST(DiscreteCVTFilter, WithoutSwapOptimizationTheOutputIsTheContraction)
{
  auto density = MakeDensity(11u);
  auto contraction = FilterType::New();
  contraction->SetInput(density);
  contraction->SetNumberOfCells(14);
  contraction->SwapOptimizationOff();
  contraction->Update();
  EXPECT_EQ(contraction->GetNumberOfSweeps(), 0u);
  EXPECT_EQ(contraction->GetNumberOfSwaps(), 0u);
  EXPECT_EQ(contraction->GetEnergy(), contraction->GetInitialEnergy());

  const auto               grid = itk::dmr::Grid<2>::FromImage(density);
  itk::dmr::DiscreteCVT<2> core;
  core.SetDensity(grid, density->GetBufferPointer(), nullptr);
  core.ContractionInitialize(14, contraction->GetBlockSize());
  EXPECT_EQ(LabelsOf(contraction->GetOutput()), core.GetLabels());
  EXPECT_EQ(contraction->GetCore().GetCentroids(), core.GetCentroids());
  EXPECT_EQ(contraction->GetEnergy(), core.GetEnergy());

  auto optimised = FilterType::New();
  optimised->SetInput(density);
  optimised->SetNumberOfCells(14);
  optimised->Update();
  EXPECT_EQ(optimised->GetInitialEnergy(), contraction->GetEnergy());
  EXPECT_LT(optimised->GetEnergy(), contraction->GetEnergy());
  EXPECT_GT(optimised->GetNumberOfSwaps(), 0u);
}

TEST(DiscreteCVTFilter, RepeatedRunsGiveIdenticalLabels)
{
  auto density = MakeDensity(21u);
  auto a = FilterType::New();
  a->SetInput(density);
  a->SetNumberOfCells(15);
  a->Update();
  auto b = FilterType::New();
  b->SetInput(density);
  b->SetNumberOfCells(15);
  b->SetNumberOfWorkUnits(1);
  b->Update();
  EXPECT_EQ(LabelsOf(a->GetOutput()), LabelsOf(b->GetOutput()));
  EXPECT_EQ(a->GetEnergy(), b->GetEnergy());
  // re-running the same filter after a modification gives the same result again
  a->Modified();
  a->Update();
  EXPECT_EQ(LabelsOf(a->GetOutput()), LabelsOf(b->GetOutput()));
}

// The contraction and the CPU sweeps report progress from inside their loops, and an observer's AbortGenerateData stops
// them there with ProcessAborted (ITK's convention); before, the filter noticed neither until it had finished, which
// took minutes on a CT. A later Update runs normally and gives the labels of a filter that was never stopped.
TEST(DiscreteCVTFilter, AbortGenerateDataStopsTheContractionAndTheSweepsFromWithin)
{
  // 400 x 300 pixels: the contraction passes its checkpoint (every 65536 merges) twice, then the sweeps each once
  const ImageType::SizeType size{ { 400, 300 } };
  auto                      density = itk::dmr::test::ImageFromBuffer<ImageType>(
    size, ImageType::SpacingType(1.0), itk::dmr::test::RandomDensity(size[0] * size[1], 3u));
  for (const int abortAtEvent : { 1, 3, -1 }) // in the contraction, in the sweeps, never
  {
    auto filter = FilterType::New();
    filter->SetInput(density);
    filter->SetNumberOfCells(40);
    filter->SetBlockSize(1);
    struct Context
    {
      FilterType *       filter;
      int                events;
      int                abortAt;
      int                workAfterAbort; // reports of further work after the abort was set
      std::vector<float> progress;
    } context{ filter.GetPointer(), 0, abortAtEvent, 0, {} };
    auto observer = itk::CStyleCommand::New();
    observer->SetClientData(&context);
    observer->SetCallback([](itk::Object *, const itk::EventObject &, void * data) {
      auto *      c = static_cast<Context *>(data);
      const float p = c->filter->GetProgress();
      if (c->filter->GetAbortGenerateData())
      {
        // more work reports progress beyond the last report; ITK's unwinding reports that again, or 1
        c->workAfterAbort += p > c->progress.back() && p < 1.0f ? 1 : 0;
        return;
      }
      c->progress.push_back(p);
      if (++c->events == c->abortAt)
      {
        c->filter->AbortGenerateDataOn();
      }
    });
    filter->AddObserver(itk::ProgressEvent(), observer);
    if (abortAtEvent > 0)
    {
      EXPECT_THROW(filter->Update(), itk::ProcessAborted) << abortAtEvent;
      EXPECT_EQ(context.workAfterAbort, 0); // stopped at the checkpoint that saw the abort
      EXPECT_LT(context.progress.back(), abortAtEvent == 1 ? 1.0f / 3.0f : 2.0f / 3.0f); // within that stage
      // a later update runs to the end and gives a fresh filter's labels
      filter->RemoveAllObservers();
      filter->Modified();
      filter->Update();
      auto fresh = FilterType::New();
      fresh->SetInput(density);
      fresh->SetNumberOfCells(40);
      fresh->SetBlockSize(1);
      fresh->Update();
      EXPECT_EQ(LabelsOf(filter->GetOutput()), LabelsOf(fresh->GetOutput()));
    }
    else
    {
      filter->Update();
      // progress from within both stages, in order
      EXPECT_GE(
        std::count_if(context.progress.begin(), context.progress.end(), [](float p) { return p < 1.0f / 3.0f; }), 2);
      EXPECT_GE(std::count_if(context.progress.begin(),
                              context.progress.end(),
                              [](float p) { return p > 1.0f / 3.0f && p < 2.0f / 3.0f; }),
                1);
      EXPECT_TRUE(std::is_sorted(context.progress.begin(), context.progress.end()));
      EXPECT_EQ(context.progress.back(), 1.0f);
    }
  }
}

TEST(DiscreteCVTFilter, FewerCellsOnASecondUpdate)
{
  // the filter keeps its core between updates; a second update with fewer cells must start clean
  auto density = MakeDensity();
  auto filter = FilterType::New();
  filter->SetInput(density);
  filter->SetNumberOfCells(20);
  filter->Update();
  filter->SetNumberOfCells(6);
  filter->Update();
  const auto labels = LabelsOf(filter->GetOutput());
  EXPECT_TRUE(itk::dmr::test::LabelsAreCompact(labels, 6));
  EXPECT_TRUE(itk::dmr::test::CellsAreFaceConnected<2>(itk::dmr::Grid<2>::FromImage(density), labels));
  auto fresh = FilterType::New();
  fresh->SetInput(density);
  fresh->SetNumberOfCells(6);
  fresh->Update();
  EXPECT_EQ(labels, LabelsOf(fresh->GetOutput()));
}
TEST(DiscreteCVTFilter, CudaWithoutDeviceThrowsAndAutoFallsBackToTheCpu)
{
  if (itk::dmr::cuda::DeviceAvailable())
  {
    GTEST_SKIP() << "a CUDA device is present: the CUDA dispatch is tested in dmrCudaGTests";
  }
  auto density = MakeDensity(5u);
  auto cuda = FilterType::New();
  cuda->SetInput(density);
  cuda->SetNumberOfCells(12);
  cuda->SetBackend(FilterType::BackendEnum::CUDA);
  EXPECT_TRUE(
    itk::dmr::test::UpdateThrowsMentioning(cuda, { "CUDA back-end requested", itk::dmr::cuda::UnavailableReason() }));

  auto automatic = FilterType::New();
  automatic->SetInput(density);
  automatic->SetNumberOfCells(12);
  automatic->SetBackend(FilterType::BackendEnum::Auto);
  automatic->Update();
  EXPECT_EQ(automatic->GetBackendUsed(), FilterType::BackendEnum::CPU);
  auto cpu = FilterType::New();
  cpu->SetInput(density);
  cpu->SetNumberOfCells(12);
  cpu->SetBackend(FilterType::BackendEnum::CPU);
  cpu->Update();
  EXPECT_EQ(LabelsOf(automatic->GetOutput()), LabelsOf(cpu->GetOutput()));
  EXPECT_EQ(automatic->GetEnergy(), cpu->GetEnergy());
  EXPECT_EQ(automatic->GetNumberOfSweeps(), cpu->GetNumberOfSweeps());

  // the launcher API itself reports the missing device (stub or no device) as a failed Status, never a crash
  itk::dmr::cuda::CVTSwapOptimizer optimizer;
  const size_t                     size[2] = { 8, 8 };
  const double                     spacing[2] = { 1.0, 1.0 };
  const auto                       status = optimizer.SetGrid(2, size, spacing);
  EXPECT_FALSE(status.Ok());
  EXPECT_FALSE(status.message.empty());
  itk::dmr::cuda::CVTSwapResult result;
  EXPECT_FALSE(optimizer.Optimize(0.0, 10, result).Ok());
  EXPECT_EQ(optimizer.DeviceLabels(), nullptr);
}
} // namespace
