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
#include "dmrDualMeshBuilder.h"
#include "dmrDualMeshPhantom.h"
#include "dmrLabelSummaryHelpers.h"
#include "gtest/gtest.h"
#include <algorithm>
#include <random>

namespace
{
using itk::dmr::Grid;
using itk::dmr::LabelSummary;
using itk::dmr::test::BruteForceSummary;
using itk::dmr::test::SameSummary;

itk::MultiThreaderBase::Pointer
Threader(unsigned int workUnits)
{
  auto threader = itk::MultiThreaderBase::New();
  threader->SetNumberOfWorkUnits(workUnits);
  return threader;
}

/** CPU summary against the brute-force definition, serial, with one work unit and with several. */
template <unsigned int D>
::testing::AssertionResult
SummaryIsTheDefinition(const Grid<D> & grid, const std::vector<int32_t> & labels, size_t nCells)
{
  const LabelSummary reference = BruteForceSummary<D>(grid, labels, nCells);
  for (unsigned int workUnits : { 0u, 1u, 7u })
  {
    auto               threader = workUnits ? Threader(workUnits) : itk::MultiThreaderBase::Pointer();
    const LabelSummary summary = itk::dmr::SummarizeLabels<D>(grid, labels.data(), nCells, threader.GetPointer());
    auto               same = SameSummary(summary, reference);
    if (!same)
    {
      return same << " (" << workUnits << " work units)";
    }
  }
  return ::testing::AssertionSuccess();
}

template <unsigned int D>
Grid<D>
MakeGrid(std::array<size_t, D> size)
{
  std::array<double, D> spacing;
  for (unsigned int k = 0; k < D; ++k)
  {
    spacing[k] = 0.5 + 0.25 * k;
  }
  return Grid<D>(size, spacing);
}

TEST(LabelSummary, MatchesTheDefinitionOnRandomLabels)
{
  const auto grid2 = MakeGrid<2>({ { 13, 9 } });
  EXPECT_TRUE(SummaryIsTheDefinition<2>(grid2, itk::dmr::test::RandomLabels(grid2.numberOfPixels, 11, 3), 11));
  const auto grid3 = MakeGrid<3>({ { 7, 6, 5 } });
  EXPECT_TRUE(SummaryIsTheDefinition<3>(grid3, itk::dmr::test::RandomLabels(grid3.numberOfPixels, 11, 4), 11));
  EXPECT_TRUE(SummaryIsTheDefinition<3>(grid3, itk::dmr::test::RandomLabels(grid3.numberOfPixels, 150, 5), 150));
}

TEST(LabelSummary, MatchesTheDefinitionOnVoronoiLabels)
{
  const auto grid2 = MakeGrid<2>({ { 70, 45 } });
  EXPECT_TRUE(SummaryIsTheDefinition<2>(grid2, itk::dmr::test::LatticeVoronoiLabels<2>(grid2, { { 7, 5 } }, 11), 35));
  const auto grid3 = MakeGrid<3>({ { 31, 24, 17 } });
  EXPECT_TRUE(
    SummaryIsTheDefinition<3>(grid3, itk::dmr::test::LatticeVoronoiLabels<3>(grid3, { { 5, 4, 3 } }, 12), 60));
}

TEST(LabelSummary, MatchesTheDefinitionOnThinImages)
{
  // one pixel along an axis: both faces of that axis are the same pixels; 3D faces and edges may be empty
  for (const auto & size : { std::array<size_t, 2>{ { 5, 1 } },
                             std::array<size_t, 2>{ { 1, 4 } },
                             std::array<size_t, 2>{ { 1, 1 } },
                             std::array<size_t, 2>{ { 2, 2 } } })
  {
    const auto grid = MakeGrid<2>(size);
    const auto n = std::min<size_t>(3, grid.numberOfPixels);
    EXPECT_TRUE(SummaryIsTheDefinition<2>(grid, itk::dmr::test::RandomLabels(grid.numberOfPixels, n, 6), n))
      << size[0] << "x" << size[1];
  }
  for (const auto & size : { std::array<size_t, 3>{ { 4, 4, 1 } },
                             std::array<size_t, 3>{ { 1, 1, 1 } },
                             std::array<size_t, 3>{ { 2, 2, 2 } },
                             std::array<size_t, 3>{ { 3, 1, 5 } },
                             std::array<size_t, 3>{ { 2, 3, 4 } } })
  {
    const auto grid = MakeGrid<3>(size);
    const auto n = std::min<size_t>(4, grid.numberOfPixels);
    EXPECT_TRUE(SummaryIsTheDefinition<3>(grid, itk::dmr::test::RandomLabels(grid.numberOfPixels, n, 7), n))
      << size[0] << "x" << size[1] << "x" << size[2];
  }
}

TEST(LabelSummary, LabelOutsideTheCellRangeThrows)
{
  const auto           grid = MakeGrid<3>({ { 6, 5, 4 } });
  std::vector<int32_t> labels(grid.numberOfPixels, 1);
  labels[0] = 0;
  EXPECT_NO_THROW(itk::dmr::SummarizeLabels<3>(grid, labels.data(), 2, nullptr));
  labels[17] = 2;
  EXPECT_THROW(itk::dmr::SummarizeLabels<3>(grid, labels.data(), 2, nullptr), itk::ExceptionObject);
  labels[17] = -1;
  EXPECT_THROW(itk::dmr::SummarizeLabels<3>(grid, labels.data(), 2, Threader(3).GetPointer()), itk::ExceptionObject);
}

/** The sites of a phantom's CVT in the grid frame, as the filter converts them. */
template <typename TPhantom>
std::vector<double>
SitesInTheGridFrame(const TPhantom & phantom)
{
  constexpr unsigned int D = TPhantom::ImageType::ImageDimension;
  const auto *           labels = phantom.cvt->GetOutput();
  const auto *           sites = phantom.cvt->GetSites();
  const auto             grid = phantom.GetGrid();
  const auto             start = labels->GetLargestPossibleRegion().GetIndex();
  std::vector<double>    out(sites->GetNumberOfPoints() * D);
  for (size_t c = 0; c < sites->GetNumberOfPoints(); ++c)
  {
    const auto ci = labels->template TransformPhysicalPointToContinuousIndex<double, double>(sites->GetPoint(c));
    for (unsigned int k = 0; k < D; ++k)
    {
      out[c * D + k] = (ci[k] - static_cast<double>(start[k])) * grid.spacing[k];
    }
  }
  return out;
}

/** The summary-based builder gives exactly the filter's mesh and statistics. */
template <typename TPhantom>
void
ExpectBuilderGivesTheFilterMesh(const TPhantom & phantom, bool withSites, bool snapToBoxEdges)
{
  constexpr unsigned int D = TPhantom::ImageType::ImageDimension;
  auto                   filter = TPhantom::DualMeshFilterType::New();
  filter->SetInput(phantom.cvt->GetOutput());
  if (withSites)
  {
    filter->SetSites(phantom.cvt->GetSites());
  }
  filter->SetSnapToBoxEdges(snapToBoxEdges);
  filter->Update();

  const auto                   grid = phantom.GetGrid();
  const auto *                 labels = phantom.cvt->GetOutput()->GetBufferPointer();
  const size_t                 nCells = phantom.cvt->GetSites()->GetNumberOfPoints();
  const auto                   summary = itk::dmr::SummarizeLabels<D>(grid, labels, nCells, nullptr);
  const auto                   sites = SitesInTheGridFrame(phantom);
  itk::dmr::DualMeshStatistics statistics;
  const auto                   mesh =
    itk::dmr::BuildDualMesh<D>(grid, summary, withSites ? sites.data() : nullptr, snapToBoxEdges, &statistics);
  const auto & expected = filter->GetSimplexMesh();
  EXPECT_EQ(mesh.nodes, expected.nodes);
  EXPECT_EQ(mesh.elements, expected.elements);
  EXPECT_EQ(mesh.fixed, expected.fixed);
  EXPECT_EQ(statistics.numberOfSkippedConstraints, filter->GetNumberOfSkippedConstraints());
  EXPECT_EQ(statistics.numberOfBoundaryNodes, filter->GetNumberOfBoundaryNodes());
  EXPECT_EQ(statistics.numberOfInnerAdjacencyEdges, filter->GetNumberOfInnerAdjacencyEdges());
  EXPECT_EQ(statistics.numberOfMissingAdjacencyEdges, filter->GetNumberOfMissingAdjacencyEdges());
  EXPECT_EQ(statistics.numberOfPerturbedNodes, filter->GetNumberOfPerturbedNodes());
  EXPECT_GT(statistics.numberOfInnerAdjacencyEdges, 0u);
}

TEST(DualMeshBuilder, GivesTheFilterMesh2D)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom(40);
  ExpectBuilderGivesTheFilterMesh(phantom, true, true);
  ExpectBuilderGivesTheFilterMesh(phantom, false, true);
  // the summary of the filter's labels is the brute-force one
  const auto   grid = phantom.GetGrid();
  const auto * L = phantom.cvt->GetOutput()->GetBufferPointer();
  EXPECT_TRUE(SummaryIsTheDefinition<2>(grid, std::vector<int32_t>(L, L + grid.numberOfPixels), 40));
}

TEST(DualMeshBuilder, GivesTheFilterMesh3D)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom3D(120);
  ExpectBuilderGivesTheFilterMesh(phantom, true, true);
  ExpectBuilderGivesTheFilterMesh(phantom, false, false);
  const auto   grid = phantom.GetGrid();
  const auto * L = phantom.cvt->GetOutput()->GetBufferPointer();
  EXPECT_TRUE(SummaryIsTheDefinition<3>(grid, std::vector<int32_t>(L, L + grid.numberOfPixels), 120));
}

TEST(DualMeshBuilder, RejectsAnInconsistentSummary)
{
  const auto           grid = MakeGrid<3>({ { 6, 5, 4 } });
  std::vector<int32_t> labels(grid.numberOfPixels, 0);
  auto                 summary = itk::dmr::SummarizeLabels<3>(grid, labels.data(), 1, nullptr);
  EXPECT_NO_THROW(itk::dmr::BuildDualMesh<3>(grid, summary, nullptr));
  const auto other = MakeGrid<3>({ { 6, 5, 5 } });
  EXPECT_THROW(itk::dmr::BuildDualMesh<3>(other, summary, nullptr), itk::ExceptionObject);
  auto twoCells = itk::dmr::SummarizeLabels<3>(grid, labels.data(), 2, nullptr); // cell 1 has no voxel
  EXPECT_THROW(itk::dmr::BuildDualMesh<3>(grid, twoCells, nullptr), itk::ExceptionObject);
  const auto grid2 = MakeGrid<2>({ { 6, 5 } });
  EXPECT_THROW(itk::dmr::BuildDualMesh<2>(grid2, summary, nullptr), itk::ExceptionObject);
}
} // namespace

namespace
{
/** The definition: the pairs whose two nodes are not both vertices of one element. */
template <size_t V>
size_t
BruteForceMissingEdges(const std::vector<std::array<int32_t, 2>> & pairs,
                       const std::vector<std::array<int32_t, V>> & elements)
{
  size_t missing = 0;
  for (const auto & p : pairs)
  {
    bool found = false;
    for (const auto & e : elements)
    {
      const bool hasA = std::find(e.begin(), e.end(), p[0]) != e.end();
      const bool hasB = std::find(e.begin(), e.end(), p[1]) != e.end();
      found = found || (p[0] != p[1] && hasA && hasB);
    }
    missing += found ? 0 : 1;
  }
  return missing;
}

template <size_t V>
void
MissingEdgesMatchTheDefinition(unsigned int seed)
{
  std::mt19937                           random(seed);
  const int32_t                          nNodes = 60;
  std::uniform_int_distribution<int32_t> node(0, nNodes - 1);
  std::vector<std::array<int32_t, V>>    elements(90);
  for (auto & e : elements)
  {
    for (size_t v = 0; v < V; ++v)
    {
      do
      {
        e[v] = node(random);
      } while (std::find(e.begin(), e.begin() + v, e[v]) != e.begin() + v);
    }
  }
  std::vector<std::array<int32_t, 2>> pairs;
  for (int i = 0; i < 400; ++i)
  {
    pairs.push_back({ node(random), node(random) }); // any order, self pairs included
  }
  pairs.push_back({ 3, nNodes + 5 });            // a node no element has
  std::sort(pairs.begin(), pairs.begin() + 200); // a grouped run, then an ungrouped one
  const size_t expected = BruteForceMissingEdges(pairs, elements);
  EXPECT_GT(expected, 0u);
  EXPECT_LT(expected, pairs.size());
  EXPECT_EQ(itk::dmr::CountEdgesNotInMesh(pairs, elements), expected) << "seed " << seed;
}
} // namespace

TEST(DualMeshBuilder, CountEdgesNotInMeshMatchesTheDefinition)
{
  for (unsigned int seed = 1; seed <= 5; ++seed)
  {
    MissingEdgesMatchTheDefinition<3>(seed);
    MissingEdgesMatchTheDefinition<4>(seed);
  }
}
