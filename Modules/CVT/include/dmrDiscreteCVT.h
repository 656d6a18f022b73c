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
#ifndef dmrDiscreteCVT_h
#define dmrDiscreteCVT_h

#include "dmrGrid.h"
#include "itkMacro.h"
#include <vector>
#include <queue>
#include <numeric>
#include <algorithm>
#include <cstdint>

namespace itk
{
namespace dmr
{
/** Ward cost of contracting clusters (m_i, r_i) and (m_j, r_j): paper Eq. 18,
 * m_i |r_i - r_k|^2 + m_j |r_j - r_k|^2 with r_k the merged centroid, which equals m_i m_j / (m_i + m_j) |r_i - r_j|^2. */
template <unsigned int D>
inline double
ContractionCost(double mi, const double * ri, double mj, const double * rj)
{
  double d2 = 0.0;
  for (unsigned int k = 0; k < D; ++k)
  {
    const double d = ri[k] - rj[k];
    d2 += d * d;
  }
  return mi * mj / (mi + mj) * d2;
}

/** Energy change of moving one pixel (weight w at x) from cluster (mi, ri) to cluster (mj, rj), with the sites kept
 * at the centroids: paper Eq. 23 (the "energy increase rule"), written in a cancellation-free form:
 * w [ mj/(mj+w) |x - rj|^2 - mi/(mi-w) |x - ri|^2 ]. */
template <unsigned int D>
inline double
SwapEnergyChange(double w, const double * x, double mi, const double * ri, double mj, const double * rj)
{
  double di = 0.0, dj = 0.0;
  for (unsigned int k = 0; k < D; ++k)
  {
    di += (x[k] - ri[k]) * (x[k] - ri[k]);
    dj += (x[k] - rj[k]) * (x[k] - rj[k]);
  }
  return w * (mj / (mj + w) * dj - mi / (mi - w) * di);
}

/** \brief Discrete centroidal Voronoi tessellation of a density on a pixel grid (CPU reference path).
 *
 * Minimises paper Eq. 10, E = sum_i sum_{x in C_i} d(x) |x - z_i|^2 with z_i the centroid of C_i, over N
 * face-connected cells of pixels. Positions are in the grid frame (mm).
 *
 * Initial tessellation (paper 4.4, A.1): greedy least-cost contraction of neighbouring clusters, starting from
 * BlockSize^D blocks, with a binary heap and lazy deletion (each entry carries the two clusters' versions).
 *
 * Optimisation (paper 4.5, Algorithm 1, A.2), two-phase like the CUDA kernel:
 *  - the pixels are split into 2^D parity colours (index mod 2 per axis); a sub-sweep treats one colour. No two
 *    pixels of one colour lie in each other's 3^D neighbourhood, so the proposal phase, run in parallel against the
 *    frozen labels, sees exactly the labels that hold when its swap is committed;
 *  - propose: every boundary pixel picks the neighbouring cell with the most negative single-swap energy change
 *    (Eq. 23) and keeps it only if removing the pixel leaves its cell locally connected (the cell's pixels in the
 *    3^D neighbourhood that touch the pixel by a face stay face-connected without it). Since the neighbourhoods of
 *    same-colour pixels never contain each other, the local test stays valid when all of them are committed
 *    together, so every cell stays connected;
 *  - commit: swaps committed together interact through the shared masses and centroids, so the single-swap
 *    change is not the joint change and the energy could rise (METHOD-NOTES). The exact joint change is computed
 *    from per-cluster sums (A' = A + dQ - |dS|^2/(m+dm), with dS, dQ the weighted first and second moments of the
 *    moved pixels about the old centroid). If it is not negative, only the better half of the proposals (by
 *    single-swap gain, ties by pixel index) is kept and the test repeated; a single swap is exact, so this ends.
 *    Hence the energy never increases, and the result is deterministic for a given input.
 * Sweeps repeat until a sweep lowers the energy by no more than Epsilon x E (Epsilon = 0: until no swap is
 * accepted), or MaximumNumberOfSweeps is reached.
 * \ingroup DynamicMeshRegistration */
template <unsigned int D>
class DiscreteCVT
{
public:
  using GridType = Grid<D>;
  using LabelType = int32_t;

  struct Proposal
  {
    uint64_t  pixel;
    LabelType to;
    double    gain; // -(single-swap energy change) > 0
  };

  struct OptimizeResult
  {
    size_t sweeps{ 0 };
    size_t swaps{ 0 };
    size_t rejectedBatches{ 0 };
    double energyBefore{ 0 };
    double energyAfter{ 0 };
  };

  /** Bind the grid and the density (not copied; must outlive the optimisation). */
  void
  SetDensity(const GridType & grid, const float * density, MultiThreaderBase * threader)
  {
    m_Grid = grid;
    m_Density = density;
    m_Threader = threader;
    m_Labels.resize(grid.numberOfPixels);
    BuildNeighbourhood();
  }

  const std::vector<LabelType> &
  GetLabels() const
  {
    return m_Labels;
  }
  size_t
  GetNumberOfCells() const
  {
    return m_Mass.size();
  }
  const std::vector<double> &
  GetMasses() const
  {
    return m_Mass;
  }
  /** Centroids in the grid frame, D interleaved. */
  const std::vector<double> &
  GetCentroids() const
  {
    return m_Centroid;
  }
  double
  GetEnergy() const
  {
    return m_Energy;
  }

  void
  Position(size_t p, double * x) const
  {
    const auto idx = m_Grid.Index(p);
    for (unsigned int k = 0; k < D; ++k)
    {
      x[k] = static_cast<double>(idx[k]) * m_Grid.spacing[k];
    }
  }

  /** Greedy least-cost pair contraction (paper 4.4) down to numberOfCells clusters. */
  void
  ContractionInitialize(size_t numberOfCells, unsigned int blockSize)
  {
    blockSize = std::max(1u, blockSize);
    std::array<size_t, D> nb;
    std::array<size_t, D> bstride;
    size_t                numberOfBlocks = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      nb[k] = (m_Grid.size[k] + blockSize - 1) / blockSize;
      bstride[k] = numberOfBlocks;
      numberOfBlocks *= nb[k];
    }
    if (numberOfCells > numberOfBlocks && blockSize > 1)
    {
      ContractionInitialize(numberOfCells, 1);
      return;
    }
    if (numberOfCells < 1 || numberOfCells > numberOfBlocks)
    {
      itkGenericExceptionMacro("DiscreteCVT: cannot make " << numberOfCells << " cells from " << numberOfBlocks
                                                           << " pixels/blocks");
    }
    auto blockOf = [&](size_t p) {
      const auto idx = m_Grid.Index(p);
      size_t     b = 0;
      for (unsigned int k = 0; k < D; ++k)
      {
        b += (static_cast<size_t>(idx[k]) / blockSize) * bstride[k];
      }
      return b;
    };
    std::vector<double> mass(numberOfBlocks, 0.0), moment(numberOfBlocks * D, 0.0);
    for (size_t p = 0; p < m_Grid.numberOfPixels; ++p)
    {
      const size_t b = blockOf(p);
      double       x[D];
      Position(p, x);
      const double w = m_Density[p];
      mass[b] += w;
      for (unsigned int k = 0; k < D; ++k)
      {
        moment[b * D + k] += w * x[k];
      }
    }
    std::vector<double> r(numberOfBlocks * D);
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        r[b * D + k] = moment[b * D + k] / mass[b];
      }
    }
    // Cluster adjacency (face neighbours of blocks).
    std::vector<std::vector<int32_t>> adjacency(numberOfBlocks);
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      size_t rest = b;
      for (unsigned int k = 0; k < D; ++k)
      {
        const size_t ik = rest % nb[k];
        rest /= nb[k];
        if (ik + 1 < nb[k])
        {
          adjacency[b].push_back(static_cast<int32_t>(b + bstride[k]));
          adjacency[b + bstride[k]].push_back(static_cast<int32_t>(b));
        }
      }
    }
    struct Entry
    {
      double   cost;
      int32_t  a, b;
      uint32_t va, vb;
      bool
      operator>(const Entry & o) const
      {
        if (cost != o.cost)
        {
          return cost > o.cost;
        }
        if (a != o.a)
        {
          return a > o.a;
        }
        return b > o.b;
      }
    };
    std::vector<uint32_t> version(numberOfBlocks, 0);
    std::vector<int32_t>  parent(numberOfBlocks);
    std::iota(parent.begin(), parent.end(), 0);
    std::vector<Entry> storage;
    storage.reserve(numberOfBlocks * D * 2);
    std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> heap(std::greater<Entry>(),
                                                                               std::move(storage));
    auto push = [&](int32_t a, int32_t b) {
      const int32_t lo = std::min(a, b), hi = std::max(a, b);
      heap.push({ ContractionCost<D>(mass[lo], &r[lo * D], mass[hi], &r[hi * D]), lo, hi, version[lo], version[hi] });
    };
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      for (int32_t n : adjacency[b])
      {
        if (n > static_cast<int32_t>(b))
        {
          push(static_cast<int32_t>(b), n);
        }
      }
    }
    size_t clusters = numberOfBlocks;
    while (clusters > numberOfCells && !heap.empty())
    {
      const Entry e = heap.top();
      heap.pop();
      if (parent[e.a] != e.a || parent[e.b] != e.b || version[e.a] != e.va || version[e.b] != e.vb)
      {
        continue; // stale entry (lazy deletion)
      }
      // keep the cluster with the longer adjacency list, merge the other into it
      int32_t keep = e.a, gone = e.b;
      if (adjacency[gone].size() > adjacency[keep].size())
      {
        std::swap(keep, gone);
      }
      const double m = mass[keep] + mass[gone]; // Eq. 19
      for (unsigned int k = 0; k < D; ++k)     // Eq. 20
      {
        r[keep * D + k] = (mass[keep] * r[keep * D + k] + mass[gone] * r[gone * D + k]) / m;
      }
      mass[keep] = m;
      parent[gone] = keep;
      auto & ak = adjacency[keep];
      ak.erase(std::remove(ak.begin(), ak.end(), gone), ak.end());
      for (int32_t n : adjacency[gone])
      {
        if (n == keep)
        {
          continue;
        }
        auto & an = adjacency[n];
        const bool hasKeep = std::find(an.begin(), an.end(), keep) != an.end();
        if (hasKeep)
        {
          an.erase(std::remove(an.begin(), an.end(), gone), an.end());
        }
        else
        {
          std::replace(an.begin(), an.end(), gone, keep);
          ak.push_back(n);
        }
      }
      std::vector<int32_t>().swap(adjacency[gone]);
      ++version[keep];
      ++version[gone];
      for (int32_t n : ak)
      {
        push(keep, n);
      }
      --clusters;
    }
    // Compact labels, numbered by first appearance in block order (deterministic).
    auto find = [&](int32_t b) {
      while (parent[b] != b)
      {
        parent[b] = parent[parent[b]];
        b = parent[b];
      }
      return b;
    };
    std::vector<int32_t> compact(numberOfBlocks, -1);
    int32_t              next = 0;
    std::vector<int32_t> blockLabel(numberOfBlocks);
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      const int32_t root = find(static_cast<int32_t>(b));
      if (compact[root] < 0)
      {
        compact[root] = next++;
      }
      blockLabel[b] = compact[root];
    }
    for (size_t p = 0; p < m_Grid.numberOfPixels; ++p)
    {
      m_Labels[p] = blockLabel[blockOf(p)];
    }
    RecomputeStatistics(static_cast<size_t>(next));
  }

  /** Warm start (paper 4.7): take a given labelling with labels 0..numberOfCells-1. */
  void
  SetLabels(const LabelType * labels, size_t numberOfCells)
  {
    std::copy(labels, labels + m_Grid.numberOfPixels, m_Labels.begin());
    RecomputeStatistics(numberOfCells);
  }

  /** Masses, centroids and energy from scratch (per-chunk sums combined in chunk order). */
  void
  RecomputeStatistics(size_t numberOfCells)
  {
    m_Mass.assign(numberOfCells, 0.0);
    m_Centroid.assign(numberOfCells * D, 0.0);
    for (size_t p = 0; p < m_Grid.numberOfPixels; ++p)
    {
      const LabelType l = m_Labels[p];
      if (l < 0 || static_cast<size_t>(l) >= numberOfCells)
      {
        itkGenericExceptionMacro("DiscreteCVT: label " << l << " at pixel " << p << " is outside [0, " << numberOfCells
                                                      << ")");
      }
      double x[D];
      Position(p, x);
      m_Mass[l] += m_Density[p];
      for (unsigned int k = 0; k < D; ++k)
      {
        m_Centroid[l * D + k] += m_Density[p] * x[k];
      }
    }
    for (size_t c = 0; c < numberOfCells; ++c)
    {
      if (!(m_Mass[c] > 0.0))
      {
        itkGenericExceptionMacro("DiscreteCVT: cell " << c << " is empty or has zero mass");
      }
      for (unsigned int k = 0; k < D; ++k)
      {
        m_Centroid[c * D + k] /= m_Mass[c];
      }
    }
    m_Energy = BruteForceEnergy();
  }

  /** Paper Eq. 10 with sites at the centroids, summed pixel by pixel. */
  double
  BruteForceEnergy() const
  {
    const size_t        nChunks = 64;
    const size_t        chunk = (m_Grid.numberOfPixels + nChunks - 1) / nChunks;
    std::vector<double> partial(nChunks, 0.0);
    ParallelForChunkIds(m_Threader, nChunks, [&](size_t c) {
      double       e = 0.0;
      const size_t end = std::min(m_Grid.numberOfPixels, (c + 1) * chunk);
      for (size_t p = c * chunk; p < end; ++p)
      {
        double x[D];
        Position(p, x);
        const double * r = &m_Centroid[m_Labels[p] * D];
        double         d2 = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          d2 += (x[k] - r[k]) * (x[k] - r[k]);
        }
        e += m_Density[p] * d2;
      }
      partial[c] = e;
    });
    return std::accumulate(partial.begin(), partial.end(), 0.0);
  }

  /** True when removing pixel p from its cell keeps the cell locally face-connected (see class comment). */
  bool
  RemovalKeepsCellConnected(size_t p) const
  {
    const LabelType label = m_Labels[p];
    const auto      idx = m_Grid.Index(p);
    constexpr unsigned int N = NeighbourhoodSize;
    bool                   member[N];
    for (unsigned int q = 0; q < N; ++q)
    {
      member[q] = false;
      if (q == Centre)
      {
        continue;
      }
      int64_t offset = 0;
      bool    inside = true;
      for (unsigned int k = 0; k < D; ++k)
      {
        const int64_t c = idx[k] + m_Offsets[q][k];
        if (c < 0 || c >= static_cast<int64_t>(m_Grid.size[k]))
        {
          inside = false;
          break;
        }
        offset += m_Offsets[q][k] * static_cast<int64_t>(m_Grid.stride[k]);
      }
      member[q] = inside && m_Labels[static_cast<size_t>(static_cast<int64_t>(p) + offset)] == label;
    }
    // flood fill from the first face neighbour in the cell, through face adjacency inside the neighbourhood
    int start = -1;
    for (unsigned int f = 0; f < 2 * D; ++f)
    {
      if (member[m_FaceNeighbours[f]])
      {
        start = static_cast<int>(m_FaceNeighbours[f]);
        break;
      }
    }
    if (start < 0)
    {
      return false; // the pixel is its cell's last link (or its only pixel)
    }
    bool         seen[N] = {};
    unsigned int stack[N];
    unsigned int top = 0;
    stack[top++] = static_cast<unsigned int>(start);
    seen[start] = true;
    while (top > 0)
    {
      const unsigned int q = stack[--top];
      for (unsigned int a = 0; a < m_AdjacencyCount[q]; ++a)
      {
        const unsigned int nq = m_Adjacency[q][a];
        if (member[nq] && !seen[nq])
        {
          seen[nq] = true;
          stack[top++] = nq;
        }
      }
    }
    for (unsigned int f = 0; f < 2 * D; ++f)
    {
      if (member[m_FaceNeighbours[f]] && !seen[m_FaceNeighbours[f]])
      {
        return false;
      }
    }
    return true;
  }

  /** Best swap for pixel p against the current (frozen) state; false when none lowers the energy. */
  bool
  ProposeSwap(size_t p, Proposal & out) const
  {
    const LabelType      own = m_Labels[p];
    const auto           idx = m_Grid.Index(p);
    LabelType            candidates[2 * D];
    unsigned int         nc = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      for (int s = -1; s <= 1; s += 2)
      {
        const int64_t c = idx[k] + s;
        if (c < 0 || c >= static_cast<int64_t>(m_Grid.size[k]))
        {
          continue;
        }
        const LabelType l = m_Labels[static_cast<size_t>(static_cast<int64_t>(p) + s * static_cast<int64_t>(m_Grid.stride[k]))];
        if (l != own && std::find(candidates, candidates + nc, l) == candidates + nc)
        {
          candidates[nc++] = l;
        }
      }
    }
    if (nc == 0)
    {
      return false; // interior pixel
    }
    double x[D];
    Position(p, x);
    const double w = m_Density[p];
    const double mi = m_Mass[own];
    if (!(mi - w > 0.0))
    {
      return false;
    }
    double    best = -m_SwapTolerance * w;
    LabelType bestLabel = own;
    for (unsigned int c = 0; c < nc; ++c)
    {
      const LabelType j = candidates[c];
      const double    dE = SwapEnergyChange<D>(w, x, mi, &m_Centroid[own * D], m_Mass[j], &m_Centroid[j * D]);
      if (dE < best || (dE == best && bestLabel != own && j < bestLabel))
      {
        best = dE;
        bestLabel = j;
      }
    }
    if (bestLabel == own || !RemovalKeepsCellConnected(p))
    {
      return false;
    }
    out = { static_cast<uint64_t>(p), bestLabel, -best };
    return true;
  }

  /** Paper Algorithm 1 with the parity-colour two-phase rule (see class comment). */
  OptimizeResult
  Optimize(double epsilon, size_t maximumNumberOfSweeps)
  {
    OptimizeResult result;
    result.energyBefore = m_Energy;
    const size_t nCells = m_Mass.size();
    m_DeltaMass.assign(nCells, 0.0);
    m_DeltaMoment.assign(nCells * D, 0.0);
    m_DeltaSecond.assign(nCells, 0.0);
    m_Touched.assign(nCells, 0);
    m_TouchedList.clear(); // labels of an earlier labelling may exceed the new cell count
    // smallest energy change worth a swap, relative to a pixel's mass times the squared pixel size (rounding guard)
    double h2 = m_Grid.spacing[0] * m_Grid.spacing[0];
    for (unsigned int k = 1; k < D; ++k)
    {
      h2 = std::min(h2, m_Grid.spacing[k] * m_Grid.spacing[k]);
    }
    m_SwapTolerance = 1e-9 * h2;

    for (size_t sweep = 0; sweep < maximumNumberOfSweeps; ++sweep)
    {
      const double before = m_Energy;
      size_t       swapsThisSweep = 0;
      for (unsigned int colour = 0; colour < (1u << D); ++colour)
      {
        CollectProposals(colour);
        swapsThisSweep += CommitProposals(result);
      }
      ++result.sweeps;
      result.swaps += swapsThisSweep;
      if (swapsThisSweep == 0 || before - m_Energy <= epsilon * before)
      {
        break;
      }
    }
    result.energyAfter = m_Energy;
    return result;
  }

private:
  static constexpr unsigned int NeighbourhoodSize = D == 2 ? 9 : 27;
  static constexpr unsigned int Centre = NeighbourhoodSize / 2;

  void
  BuildNeighbourhood()
  {
    for (unsigned int q = 0; q < NeighbourhoodSize; ++q)
    {
      unsigned int rest = q;
      for (unsigned int k = 0; k < D; ++k)
      {
        m_Offsets[q][k] = static_cast<int>(rest % 3) - 1;
        rest /= 3;
      }
    }
    unsigned int f = 0;
    for (unsigned int q = 0; q < NeighbourhoodSize; ++q)
    {
      m_AdjacencyCount[q] = 0;
      int manhattan = 0;
      for (unsigned int k = 0; k < D; ++k)
      {
        manhattan += std::abs(m_Offsets[q][k]);
      }
      if (manhattan == 1)
      {
        m_FaceNeighbours[f++] = q;
      }
      for (unsigned int o = 0; o < NeighbourhoodSize; ++o)
      {
        int diff = 0;
        for (unsigned int k = 0; k < D; ++k)
        {
          diff += std::abs(m_Offsets[q][k] - m_Offsets[o][k]);
        }
        if (diff == 1 && o != Centre && q != Centre)
        {
          m_Adjacency[q][m_AdjacencyCount[q]++] = o;
        }
      }
    }
  }

  /** Phase 1: proposals of all pixels of one parity colour against the frozen labels (parallel, deterministic
   * order: per-chunk lists concatenated in chunk order). */
  void
  CollectProposals(unsigned int colour)
  {
    std::array<size_t, D> sub;
    std::array<size_t, D> origin;
    size_t                count = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      origin[k] = (colour >> k) & 1u;
      sub[k] = m_Grid.size[k] > origin[k] ? (m_Grid.size[k] - origin[k] + 1) / 2 : 0;
      count *= sub[k];
    }
    const size_t nChunks = std::max<size_t>(1, std::min<size_t>(64, count / 2048));
    const size_t chunk = count > 0 ? (count + nChunks - 1) / nChunks : 0;
    m_ChunkProposals.resize(nChunks);
    ParallelForChunkIds(m_Threader, nChunks, [&](size_t c) {
      auto & list = m_ChunkProposals[c];
      list.clear();
      const size_t end = std::min(count, (c + 1) * chunk);
      for (size_t q = c * chunk; q < end; ++q)
      {
        size_t rest = q, p = 0;
        for (unsigned int k = 0; k < D; ++k)
        {
          p += (origin[k] + 2 * (rest % sub[k])) * m_Grid.stride[k];
          rest /= sub[k];
        }
        Proposal prop;
        if (ProposeSwap(p, prop))
        {
          list.push_back(prop);
        }
      }
    });
    m_Proposals.clear();
    for (size_t c = 0; c < nChunks; ++c)
    {
      m_Proposals.insert(m_Proposals.end(), m_ChunkProposals[c].begin(), m_ChunkProposals[c].end());
    }
  }

  /** Exact energy change of committing proposals [0, count) together. Leaves the per-cluster deltas in place. */
  double
  JointEnergyChange(size_t count)
  {
    for (LabelType c : m_TouchedList)
    {
      m_Touched[c] = 0;
      m_DeltaMass[c] = 0.0;
      m_DeltaSecond[c] = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        m_DeltaMoment[c * D + k] = 0.0;
      }
    }
    m_TouchedList.clear();
    auto add = [&](LabelType c, double w, const double * x) {
      if (!m_Touched[c])
      {
        m_Touched[c] = 1;
        m_TouchedList.push_back(c);
      }
      double d2 = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        const double d = x[k] - m_Centroid[c * D + k];
        m_DeltaMoment[c * D + k] += w * d;
        d2 += d * d;
      }
      m_DeltaMass[c] += w;
      m_DeltaSecond[c] += w * d2;
    };
    for (size_t i = 0; i < count; ++i)
    {
      const Proposal & prop = m_Proposals[i];
      double           x[D];
      Position(prop.pixel, x);
      const double w = m_Density[prop.pixel];
      add(m_Labels[prop.pixel], -w, x);
      add(prop.to, w, x);
    }
    double dE = 0.0;
    for (LabelType c : m_TouchedList)
    {
      double s2 = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        s2 += m_DeltaMoment[c * D + k] * m_DeltaMoment[c * D + k];
      }
      dE += m_DeltaSecond[c] - s2 / (m_Mass[c] + m_DeltaMass[c]);
    }
    return dE;
  }

  /** Phase 2: commit the proposals whose joint energy change is negative (halving on failure). */
  size_t
  CommitProposals(OptimizeResult & result)
  {
    size_t count = m_Proposals.size();
    if (count == 0)
    {
      return 0;
    }
    bool   sorted = false;
    double dE = JointEnergyChange(count);
    while (!(dE < 0.0))
    {
      ++result.rejectedBatches;
      if (count == 1)
      {
        return 0;
      }
      if (!sorted)
      {
        std::sort(m_Proposals.begin(), m_Proposals.end(), [](const Proposal & a, const Proposal & b) {
          return a.gain != b.gain ? a.gain > b.gain : a.pixel < b.pixel;
        });
        sorted = true;
      }
      count /= 2;
      dE = JointEnergyChange(count);
    }
    for (LabelType c : m_TouchedList)
    {
      const double m = m_Mass[c] + m_DeltaMass[c];
      for (unsigned int k = 0; k < D; ++k)
      {
        m_Centroid[c * D + k] += m_DeltaMoment[c * D + k] / m;
      }
      m_Mass[c] = m;
    }
    for (size_t i = 0; i < count; ++i)
    {
      m_Labels[m_Proposals[i].pixel] = m_Proposals[i].to;
    }
    m_Energy += dE;
    return count;
  }

  GridType                             m_Grid;
  const float *                        m_Density{ nullptr };
  MultiThreaderBase *                  m_Threader{ nullptr };
  std::vector<LabelType>               m_Labels;
  std::vector<double>                  m_Mass;
  std::vector<double>                  m_Centroid;
  double                               m_Energy{ 0.0 };
  double                               m_SwapTolerance{ 0.0 };
  int                                  m_Offsets[NeighbourhoodSize][D];
  unsigned int                         m_FaceNeighbours[2 * D];
  unsigned int                         m_Adjacency[NeighbourhoodSize][2 * D];
  unsigned int                         m_AdjacencyCount[NeighbourhoodSize];
  std::vector<std::vector<Proposal>>   m_ChunkProposals;
  std::vector<Proposal>                m_Proposals;
  std::vector<double>                  m_DeltaMass;
  std::vector<double>                  m_DeltaMoment;
  std::vector<double>                  m_DeltaSecond;
  std::vector<uint8_t>                 m_Touched;
  std::vector<LabelType>               m_TouchedList;
};
} // namespace dmr
} // namespace itk

#endif
