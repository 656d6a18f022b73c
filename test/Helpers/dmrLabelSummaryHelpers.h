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
#ifndef dmrLabelSummaryHelpers_h
#define dmrLabelSummaryHelpers_h

#include "dmrGrid.h"
#include "dmrLabelSummary.h"
#include "gtest/gtest.h"

#include <algorithm>
#include <array>
#include <limits>
#include <random>
#include <set>
#include <vector>

namespace itk
{
namespace dmr
{
namespace test
{
/** The LabelSummary straight from its definition (dmrLabelSummary.h), one voxel at a time: the reference of the CPU
 * and GPU summaries. */
template <unsigned int D>
LabelSummary
BruteForceSummary(const Grid<D> & grid, const std::vector<int32_t> & labels, size_t numberOfCells)
{
  LabelSummary s;
  s.Reset(D, grid.size.data(), numberOfCells);
  std::set<uint64_t> pairs;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto    idx = grid.Index(p);
    const int32_t c = labels[p];
    s.cellStats[(D + 1) * c] += 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      s.cellStats[(D + 1) * c + 1 + k] += idx[k];
      if (idx[k] + 1 < static_cast<int64_t>(grid.size[k]) && labels[p + grid.stride[k]] != c)
      {
        pairs.insert(
          LabelSummary::PairKey(static_cast<uint32_t>(c), static_cast<uint32_t>(labels[p + grid.stride[k]])));
      }
    }
    auto atSide = [&](unsigned int k, unsigned int side) {
      return idx[k] == (side ? static_cast<int64_t>(grid.size[k]) - 1 : 0);
    };
    auto strictlyInner = [&](unsigned int k) { return idx[k] > 0 && idx[k] + 1 < static_cast<int64_t>(grid.size[k]); };
    for (unsigned int f = 0; f < 2 * D; ++f)
    {
      const unsigned int k = f / 2;
      bool               onFace = atSide(k, f % 2);
      for (unsigned int j = 1; j < D && D == 3; ++j)
      {
        onFace = onFace && strictlyInner((k + j) % D);
      }
      if (onFace)
      {
        s.faceStats[D * (2 * D * c + f)] += 1;
        for (unsigned int j = 1; j < D; ++j)
        {
          s.faceStats[D * (2 * D * c + f) + j] += idx[(k + j) % D];
        }
      }
    }
    if (D == 3)
    {
      for (unsigned int e = 0; e < 12; ++e)
      {
        const unsigned int a = e / 4, b = (a + 1) % 3, c3 = (a + 2) % 3;
        if (strictlyInner(a) && atSide(b, (e >> 1) & 1u) && atSide(c3, e & 1u))
        {
          s.edgeStats[2 * (12 * c + e)] += 1;
          s.edgeStats[2 * (12 * c + e) + 1] += idx[a];
        }
      }
    }
    for (unsigned int q = 0; q < (1u << D); ++q)
    {
      bool atCorner = true;
      for (unsigned int k = 0; k < D; ++k)
      {
        atCorner = atCorner && idx[k] == ((q >> k) & 1u ? static_cast<int64_t>(grid.size[k]) - 1 : 0);
      }
      if (atCorner)
      {
        s.cornerLabels[q] = c;
      }
    }
  }
  s.adjacentPairs.assign(pairs.begin(), pairs.end());
  return s;
}

/** Field-by-field comparison with the first difference in the message. */
inline ::testing::AssertionResult
SameSummary(const LabelSummary & a, const LabelSummary & b)
{
  if (a.dimension != b.dimension || a.size != b.size || a.numberOfCells != b.numberOfCells)
  {
    return ::testing::AssertionFailure() << "geometry differs: " << a.dimension << "D " << a.numberOfCells
                                         << " cells vs " << b.dimension << "D " << b.numberOfCells << " cells";
  }
  auto firstDifference = [](const char * name, const auto & x, const auto & y) -> ::testing::AssertionResult {
    if (x.size() != y.size())
    {
      return ::testing::AssertionFailure() << name << ": " << x.size() << " vs " << y.size() << " entries";
    }
    for (size_t i = 0; i < x.size(); ++i)
    {
      if (x[i] != y[i])
      {
        return ::testing::AssertionFailure() << name << "[" << i << "]: " << x[i] << " vs " << y[i];
      }
    }
    return ::testing::AssertionSuccess();
  };
  for (auto r : { firstDifference("cellStats", a.cellStats, b.cellStats),
                  firstDifference("faceStats", a.faceStats, b.faceStats),
                  firstDifference("edgeStats", a.edgeStats, b.edgeStats),
                  firstDifference("cornerLabels", a.cornerLabels, b.cornerLabels),
                  firstDifference("adjacentPairs", a.adjacentPairs, b.adjacentPairs) })
  {
    if (!r)
    {
      return r;
    }
  }
  if (a != b)
  {
    return ::testing::AssertionFailure() << "operator== disagrees with the field comparison";
  }
  return ::testing::AssertionSuccess();
}

/** Independent uniform random labels in [0, numberOfCells), every label used at least once (numberOfCells <= size):
 * no spatial coherence at all, the worst case for the GPU's block-local aggregation. */
inline std::vector<int32_t>
RandomLabels(size_t numberOfPixels, size_t numberOfCells, uint32_t seed)
{
  std::mt19937         rng(seed);
  std::vector<int32_t> labels(numberOfPixels);
  for (size_t p = 0; p < numberOfPixels; ++p)
  {
    labels[p] = static_cast<int32_t>(p < numberOfCells ? p : rng() % numberOfCells);
  }
  std::shuffle(labels.begin(), labels.end(), rng);
  return labels;
}

/** A discrete Voronoi diagram (a cheap stand-in for a CVT) of one site per box of a cellsPerAxis lattice, each site at
 * a random voxel of its box; a voxel takes the nearest site among its own and the neighbouring boxes (physical
 * distance with the grid's spacing). Every cell holds at least its site's voxel; cells are numbered box by box. */
template <unsigned int D>
std::vector<int32_t>
LatticeVoronoiLabels(const Grid<D> & grid, const std::array<size_t, D> & cellsPerAxis, uint32_t seed)
{
  std::mt19937 rng(seed);
  size_t       nCells = 1;
  for (unsigned int k = 0; k < D; ++k)
  {
    nCells *= cellsPerAxis[k];
  }
  auto boxLo = [&](unsigned int k, size_t b) { return grid.size[k] * b / cellsPerAxis[k]; };
  std::vector<std::array<int64_t, D>> sites(nCells);
  for (size_t c = 0; c < nCells; ++c)
  {
    size_t rem = c;
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t b = rem % cellsPerAxis[k];
      rem /= cellsPerAxis[k];
      const size_t lo = boxLo(k, b), hi = boxLo(k, b + 1);
      sites[c][k] = static_cast<int64_t>(lo + rng() % (hi - lo));
    }
  }
  std::vector<int32_t> labels(grid.numberOfPixels);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    int64_t    box[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      box[k] = static_cast<int64_t>(static_cast<size_t>(idx[k]) * cellsPerAxis[k] / grid.size[k]);
      while (box[k] + 1 < static_cast<int64_t>(cellsPerAxis[k]) && static_cast<int64_t>(boxLo(k, box[k] + 1)) <= idx[k])
      {
        ++box[k];
      }
      while (box[k] > 0 && static_cast<int64_t>(boxLo(k, box[k])) > idx[k])
      {
        --box[k];
      }
    }
    double  best = std::numeric_limits<double>::max();
    int32_t bestCell = 0;
    for (unsigned int n = 0; n < (D == 2 ? 9u : 27u); ++n)
    {
      size_t cell = 0, mult = 1;
      bool   inside = true;
      int    code = static_cast<int>(n);
      for (unsigned int k = 0; k < D; ++k)
      {
        const int64_t b = box[k] + code % 3 - 1;
        code /= 3;
        inside = inside && b >= 0 && b < static_cast<int64_t>(cellsPerAxis[k]);
        cell += static_cast<size_t>(b) * mult;
        mult *= cellsPerAxis[k];
      }
      if (!inside)
      {
        continue;
      }
      double d = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        const double t = static_cast<double>(idx[k] - sites[cell][k]) * grid.spacing[k];
        d += t * t;
      }
      if (d < best || (d == best && static_cast<int32_t>(cell) < bestCell))
      {
        best = d;
        bestCell = static_cast<int32_t>(cell);
      }
    }
    labels[p] = bestCell;
  }
  return labels;
}
} // namespace test
} // namespace dmr
} // namespace itk

#endif
