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

#include "dmrContractionSums.h"
#include "dmrGrid.h"
#include "dmrNeighbourhood.h"
#include "dmrWorkerTeam.h"
#include "itkMacro.h"
#include <vector>
#include <numeric>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <system_error>

namespace itk
{
namespace dmr
{
/** Ward cost of contracting clusters (m_i, r_i) and (m_j, r_j): paper Eq. 18,
 * m_i |r_i - r_k|^2 + m_j |r_j - r_k|^2 with r_k the merged centroid, which equals m_i m_j / (m_i + m_j) |r_i - r_j|^2.
 */
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
 * BlockSize^D blocks, with an indexed heap of the clusters keyed by their least-cost pair (see ContractionInitialize).
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
 *
 * Active lists (which pixels a sub-sweep evaluates). A pixel's proposal is a function of the labels of its 3^D
 * neighbourhood and of the masses and centroids of its own cell and of its face neighbours' cells; interior pixels
 * (no face neighbour in another cell) never propose. A sub-sweep therefore evaluates only the boundary pixels of
 * its colour whose inputs may have changed since the colour's previous sub-sweep, i.e. that are
 *  - Changed: a label of the 3^D neighbourhood changed (set around every committed swap), or the pixel proposed a
 *    swap last time (committed or rejected by the halving), or
 *  - next to a changed cell: its own or a face neighbour's cell has a stamp (the sub-sweep of the last commit
 *    that changed the cell's mass or centroid) in the window since that sub-sweep's commit.
 * A pixel whose last evaluation found its removal disconnecting its cell (Blocked) is skipped until it is Changed:
 * the local connectivity test depends on the neighbourhood's labels only. Every skipped pixel would repeat its
 * last outcome, no proposal, so the proposals are those of the full scan; they are committed in pixel order like
 * the full scan's, so the labels and the energy are identical to it, bit for bit (SweepMode::FullScan runs the
 * reference rule; the tests compare the modes). Two ways to find those pixels, picked per sub-sweep by their
 * estimated work:
 *  - scan: each colour keeps a sorted list of its boundary pixels; every entry is checked (Changed, cell stamps),
 *    in parallel; entries found interior leave the list. Cheapest when many cells changed;
 *  - gather: each cell keeps a list of its boundary pixels per colour. For every changed cell, its own pixels of
 *    the colour and the pixels face-adjacent to its pixels of the colours that differ in one axis are queued
 *    (with the Changed pixels, always queued), then the queue is evaluated in parallel. Cheapest when few changed.
 * After each commit, the moved pixels' neighbourhoods are queued as Changed and the moved pixels and their face
 * neighbours, the only pixels whose boundary status can change, are listed where they are boundary pixels and not
 * listed yet (a colour's new entries wait in a pending list, merged in sorted before its next scan). Stale entries
 * (pixels that left the cell or the boundary) are dropped by the scan, and from a gather list when it has doubled
 * since it was last compacted. Memory: one state byte per pixel, two 4-byte entries per boundary pixel (and the
 * stale ones), one stamp per cell.
 * \ingroup DynamicMeshRegistration */
template <unsigned int D>
class DiscreteCVT
{
public:
  using GridType = Grid<D>;
  using IndexType = std::array<int64_t, D>;
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

  /** Bind the grid and the density (not copied; must outlive the optimisation). Throws for a density that is not
   * positive and finite everywhere: a cell of zero mass has no centroid, and the contraction's costs would be NaN. */
  void
  SetDensity(const GridType & grid, const float * density, MultiThreaderBase * threader)
  {
    const size_t p = FirstIndexWhere(
      threader, grid.numberOfPixels, [&](size_t i) { return !(density[i] > 0.0f) || !std::isfinite(density[i]); });
    if (p < grid.numberOfPixels)
    {
      itkGenericExceptionMacro("DiscreteCVT: the density must be positive and finite everywhere; pixel " << p << " has "
                                                                                                         << density[p]);
    }
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

  /** A function called on the calling thread between steps of the long loops: every 65536 merges of the contraction
   * (with the share of merges done) and after every sweep of Optimize (with the share of the sweep limit used). It may
   * throw to stop the work (DiscreteCVTFilter throws ProcessAborted there when its AbortGenerateData is set); the state
   * is then incomplete until the next ContractionInitialize or SetLabels. */
  void
  SetCheckpoint(std::function<void(double)> checkpoint)
  {
    m_Checkpoint = std::move(checkpoint);
  }

  /** Which pixels a sub-sweep evaluates; every mode gives the same proposals, hence the same labels and energy
   * (see class comment). Auto (default): the active list, scanned or gathered from the changed cells, whichever
   * is estimated cheaper for the sub-sweep; ActiveScan, ActiveGather: always that one; FullScan: every pixel of
   * the colour, the reference rule. The forced modes are for tests and benchmarks. */
  enum class SweepMode
  {
    Auto,
    ActiveScan,
    ActiveGather,
    FullScan
  };
  void
  SetSweepMode(SweepMode mode)
  {
    m_SweepMode = mode;
  }
  SweepMode
  GetSweepMode() const
  {
    return m_SweepMode;
  }

  /** The gather mode's parallel step (GatherChangedCells) splits the changed cells into chunks of at least this many
   * gather-list entries (default GatherChunkWork; at least 1). Smaller values are for tests, which then exercise the
   * parallel gather on small grids; the labels are the same whatever the value. */
  void
  SetGatherChunkWork(size_t work)
  {
    m_GatherChunkWork = std::max<size_t>(1, work);
  }
  size_t
  GetGatherChunkWork() const
  {
    return m_GatherChunkWork;
  }

  void
  Position(size_t p, double * x) const
  {
    Position(PixelIndex(p), x);
  }

  /** The blocks the contraction starts from: blockSize pixels per axis (at least 1), nb per axis (the last ones cut at
   * the grid's end), or single pixels where there would be fewer blocks than numberOfCells. */
  struct ContractionBlockGrid
  {
    unsigned int          size;
    std::array<size_t, D> perAxis;
  };
  static ContractionBlockGrid
  ContractionBlocks(const std::array<size_t, D> & gridSize, size_t numberOfCells, unsigned int blockSize)
  {
    ContractionBlockGrid blocks{ std::max(1u, blockSize), {} };
    for (;;)
    {
      size_t numberOfBlocks = 1;
      for (unsigned int k = 0; k < D; ++k)
      {
        blocks.perAxis[k] = (gridSize[k] + blocks.size - 1) / blocks.size;
        numberOfBlocks *= blocks.perAxis[k];
      }
      if (numberOfCells <= numberOfBlocks || blocks.size == 1)
      {
        return blocks;
      }
      blocks.size = 1;
    }
  }

  /** Greedy least-cost pair contraction (paper 4.4) down to numberOfCells clusters.
   *
   * Starts from the BlockSize^D blocks and repeatedly merges the adjacent pair of clusters with the least
   * (cost, lower id, higher id), the cluster with more neighbours (ties: the lower id) absorbing the other. Each
   * cluster holds the least key over its pairs (the costs of the pairs are kept in its adjacency list), and an
   * indexed 4-ary heap over the clusters gives the least of those: the global least pair, as a heap of all the pairs
   * would, with one node per cluster and no stale entries. After a merge, the costs of the kept cluster's pairs are
   * computed again, and a neighbour's key is updated where the new pair is less than it, or taken again from its list
   * where it was a pair with one of the two merged clusters (the other keys are unchanged). */
  void
  ContractionInitialize(size_t numberOfCells, unsigned int blockSize)
  {
    std::vector<double> masses, centroids;
    const auto          blocks = ContractionBlockSums(numberOfCells, blockSize, masses, centroids);
    size_t              next = 0;
    const auto          blockLabel =
      ContractBlocks(blocks.perAxis, masses.data(), centroids.data(), numberOfCells, m_Checkpoint, next);
    ParallelForChunkIds(m_Threader, NumberOfBlockSlabs(blocks), [&](size_t slab) {
      ForEachBlockRun(blocks, slab, [&](size_t b, const IndexType &, size_t rowStart, size_t i, size_t end) {
        std::fill(m_Labels.begin() + rowStart + i, m_Labels.begin() + rowStart + end, blockLabel[b]);
      });
    });
    RecomputeStatistics(next);
  }

  /** The contraction's start (see ContractionInitialize): the blocks of ContractionBlocks(grid size, numberOfCells,
   * blockSize), and the mass and centroid (grid frame, D interleaved) of each block of the current density, in block
   * order. ContractionInitialize contracts these sums; the CUDA back-end's block sums (CVTSwapOptimizer::
   * ContractionBlockSums) are the same, bit for bit. */
  ContractionBlockGrid
  ContractionBlockSums(size_t                numberOfCells,
                       unsigned int          blockSize,
                       std::vector<double> & masses,
                       std::vector<double> & centroids) const
  {
    const auto blocks = ContractionBlocks(m_Grid.size, numberOfCells, blockSize);
    size_t     numberOfBlocks = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      numberOfBlocks *= blocks.perAxis[k];
    }
    // first moments until the blocks are summed
    masses.assign(numberOfBlocks, 0.0);
    centroids.assign(numberOfBlocks * D, 0.0);
    // The pixels are visited row by row (a row: the size[0] pixels along axis 0, in runs of one block each), with no
    // division per pixel. A slab (blockSize pixel planes across the last axis) holds whole rows and whole blocks, so
    // the slabs are summed in parallel; within a block the pixels are added in increasing order as by a plain scan,
    // so the sums are the same, bit for bit, whatever the threads.
    const size_t numberOfSlabs = NumberOfBlockSlabs(blocks);
    const size_t slabBlocks = numberOfBlocks / numberOfSlabs;
    ParallelForChunkIds(m_Threader, numberOfSlabs, [&](size_t slab) {
      ForEachBlockRun(blocks, slab, [&](size_t b, const IndexType & idx, size_t rowStart, size_t i, size_t end) {
        double x[D];
        Position(idx, x);
        double mass = masses[b];
        double moment[D];
        std::copy_n(&centroids[b * D], D, moment);
        AddRowToBlockSums<D>(m_Density + rowStart, i, end, m_Grid.spacing[0], x, mass, moment);
        masses[b] = mass;
        std::copy_n(moment, D, &centroids[b * D]);
      });
      for (size_t b = slab * slabBlocks; b < (slab + 1) * slabBlocks; ++b)
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          centroids[b * D + k] /= masses[b];
        }
      }
    });
    return blocks;
  }

  /** The merges of the greedy least-cost pair contraction (see ContractionInitialize) on a grid of nb blocks per axis
   * (axis 0 fastest), from their masses and centroids (grid frame, D interleaved; masses positive): the label of every
   * block, 0..numberOfCells-1 numbered by first appearance in block order, and in numberOfLabels how many there are
   * (numberOfCells, or fewer where the blocks do not connect). checkpoint (may be empty) is called with the fraction
   * of the merges done before every 65536th merge. Used by ContractionInitialize, and by the CUDA back-end with block
   * sums made on the device. */
  static std::vector<int32_t>
  ContractBlocks(const std::array<size_t, D> &       nb,
                 const double *                      masses,
                 const double *                      centroids,
                 size_t                              numberOfCells,
                 const std::function<void(double)> & checkpoint,
                 size_t &                            numberOfLabels)
  {
    std::array<size_t, D> bstride;
    size_t                numberOfBlocks = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      bstride[k] = numberOfBlocks;
      numberOfBlocks *= nb[k];
    }
    if (numberOfCells < 1 || numberOfCells > numberOfBlocks)
    {
      itkGenericExceptionMacro("DiscreteCVT: cannot make " << numberOfCells << " cells from " << numberOfBlocks
                                                           << " pixels/blocks");
    }
    struct Cluster
    {
      double   mass;
      double   centroid[D];
      size_t   first; // its links are link[first, first + count), with room for capacity
      uint32_t count;
      uint32_t capacity;
    };
    struct Link
    {
      double  cost;
      int32_t to;
    };
    std::vector<Cluster> cluster(numberOfBlocks);
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      cluster[b].mass = masses[b];
      std::copy_n(centroids + b * D, D, cluster[b].centroid);
    }
    auto cost = [&](int32_t a, int32_t b) {
      const Cluster & lo = cluster[std::min(a, b)];
      const Cluster & hi = cluster[std::max(a, b)];
      return ContractionCost<D>(lo.mass, lo.centroid, hi.mass, hi.centroid);
    };

    // Cluster adjacency (face neighbours of blocks) with the cost of each pair, in one pool; a list that outgrows its
    // room moves to the end of the pool with twice the room. Only the sizes of the lists matter (which cluster is
    // kept), not their order.
    std::vector<Link> link(numberOfBlocks * 2 * D);
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      cluster[b].first = b * 2 * D;
      cluster[b].count = 0;
      cluster[b].capacity = 2 * D;
    }
    auto appendLink = [&](int32_t a, int32_t b, double c) {
      Cluster & ca = cluster[a];
      if (ca.count == ca.capacity)
      {
        const size_t first = link.size();
        link.resize(first + 2 * size_t{ ca.capacity });
        std::copy_n(link.begin() + ca.first, ca.count, link.begin() + first);
        ca.first = first;
        ca.capacity *= 2;
      }
      link[ca.first + ca.count++] = { c, b };
    };
    for (size_t b = 0; b < numberOfBlocks; ++b)
    {
      size_t rest = b;
      for (unsigned int k = 0; k < D; ++k)
      {
        const size_t ik = rest % nb[k];
        rest /= nb[k];
        if (ik + 1 < nb[k])
        {
          const int32_t a = static_cast<int32_t>(b), n = static_cast<int32_t>(b + bstride[k]);
          const double  c = cost(a, n);
          appendLink(a, n, c);
          appendLink(n, a, c);
        }
      }
    }

    // Indexed 4-ary min-heap of the clusters that have neighbours, keyed by their least pair; node[c]: c's node (a
    // small array of its own: every move in the heap writes it).
    std::vector<ContractionKey> heap;
    std::vector<uint32_t>       node(numberOfBlocks);
    auto                        place = [&](size_t i, const ContractionKey & key) {
      heap[i] = key;
      node[key.Holder()] = static_cast<uint32_t>(i);
    };
    auto siftUp = [&](size_t i, ContractionKey key) {
      while (i > 0)
      {
        const size_t up = (i - 1) / 4;
        if (!(key < heap[up]))
        {
          break;
        }
        place(i, heap[up]);
        i = up;
      }
      place(i, key);
    };
    auto siftDown = [&](size_t i, ContractionKey key) {
      const size_t n = heap.size();
      for (;;)
      {
        const size_t first = 4 * i + 1;
        if (first >= n)
        {
          break;
        }
        size_t       least = first;
        const size_t last = std::min(n, first + 4);
        for (size_t j = first + 1; j < last; ++j)
        {
          if (heap[j] < heap[least])
          {
            least = j;
          }
        }
        if (!(heap[least] < key))
        {
          break;
        }
        place(i, heap[least]);
        i = least;
      }
      place(i, key);
    };
    auto update = [&](size_t i, ContractionKey key) {
      if (key < heap[i])
      {
        siftUp(i, key);
      }
      else
      {
        siftDown(i, key);
      }
    };
    auto remove = [&](int32_t c) {
      const size_t         i = node[c];
      const ContractionKey last = heap.back();
      heap.pop_back();
      if (i < heap.size())
      {
        update(i, last);
      }
    };
    // c's least key: for one holder, the order of the keys is that of (cost, partner), as both the pairs with a
    // lower partner (lower id: the partner) and those with a higher one (lower id: c) come by increasing partner.
    auto leastPair = [&](int32_t c) {
      const Link * l = &link[cluster[c].first];
      const Link * end = l + cluster[c].count;
      const Link * least = l;
      for (++l; l < end; ++l)
      {
        if (l->cost != least->cost ? l->cost < least->cost : l->to < least->to)
        {
          least = l;
        }
      }
      return ContractionKey::Make(least->cost, c, least->to);
    };
    heap.resize(numberOfBlocks > 1 ? numberOfBlocks : 0);
    for (size_t i = 0; i < heap.size(); ++i)
    {
      heap[i] = leastPair(static_cast<int32_t>(i));
    }
    for (size_t i = heap.size() / 4 + 1; i-- > 0;)
    {
      if (i < heap.size())
      {
        siftDown(i, heap[i]);
      }
    }
    for (size_t i = 0; i < heap.size(); ++i)
    {
      node[heap[i].Holder()] = static_cast<uint32_t>(i);
    }

    std::vector<int32_t> parent(numberOfBlocks);
    std::iota(parent.begin(), parent.end(), 0);
    size_t       clusters = numberOfBlocks;
    const size_t merges = numberOfBlocks - numberOfCells;
    while (clusters > numberOfCells && !heap.empty())
    {
      if (checkpoint && ((numberOfBlocks - clusters) & 0xFFFF) == 0)
      {
        checkpoint(static_cast<double>(numberOfBlocks - clusters) / static_cast<double>(merges));
      }
      // keep the cluster with the longer adjacency list, merge the other into it
      int32_t keep = heap[0].Low(), gone = heap[0].High();
      if (cluster[gone].count > cluster[keep].count)
      {
        std::swap(keep, gone);
      }
      Cluster &       ck = cluster[keep];
      const Cluster & cg = cluster[gone];
      const double    m = ck.mass + cg.mass; // Eq. 19
      for (unsigned int k = 0; k < D; ++k)   // Eq. 20
      {
        ck.centroid[k] = (ck.mass * ck.centroid[k] + cg.mass * cg.centroid[k]) / m;
      }
      ck.mass = m;
      parent[gone] = keep;
      {
        Link * l = &link[ck.first];
        while (l->to != gone)
        {
          ++l;
        }
        *l = link[ck.first + --ck.count];
      }
      // gone's neighbours become keep's: each drops gone, or links to keep instead where it did not already
      for (size_t j = cg.first; j < cg.first + cg.count; ++j)
      {
        const int32_t n = link[j].to;
        if (n == keep)
        {
          continue;
        }
        Cluster & cn = cluster[n];
        Link *    l = &link[cn.first];
        Link *    end = l + cn.count;
        Link *    at = l;
        bool      hasKeep = false;
        for (; l < end; ++l)
        {
          at = l->to == gone ? l : at;
          hasKeep |= l->to == keep;
        }
        if (hasKeep)
        {
          *at = link[cn.first + --cn.count];
        }
        else
        {
          at->to = keep;
          appendLink(keep, n, 0.0); // the cost follows
        }
      }
      cluster[gone].count = 0;
      remove(gone);
      // the costs of keep's pairs changed, hence maybe the keys of its neighbours and its own
      for (size_t j = ck.first; j < ck.first + ck.count; ++j)
      {
        const int32_t n = link[j].to;
        const double  c = cost(keep, n);
        link[j].cost = c;
        const Cluster & cn = cluster[n];
        Link *          l = &link[cn.first];
        while (l->to != keep)
        {
          ++l;
        }
        l->cost = c;
        const ContractionKey key = ContractionKey::Make(c, n, keep);
        const size_t         s = node[n];
        const int32_t        partner = heap[s].Partner();
        if (key < heap[s])
        {
          siftUp(s, key);
        }
        else if (partner == keep || partner == gone)
        {
          update(s, leastPair(n));
        }
      }
      if (ck.count > 0)
      {
        update(node[keep], leastPair(keep));
      }
      else
      {
        remove(keep);
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
    numberOfLabels = static_cast<size_t>(next);
    return blockLabel;
  }

  /** Warm start (paper 4.7): take a given labelling with labels 0..numberOfCells-1. */
  void
  SetLabels(const LabelType * labels, size_t numberOfCells)
  {
    std::copy(labels, labels + m_Grid.numberOfPixels, m_Labels.begin());
    RecomputeStatistics(numberOfCells);
  }

  /** Takes a state carried on elsewhere (the GPU optimiser's, which updates the masses and centroids with this
   * class's formulas in its order): labels 0..numberOfCells-1 with their masses, centroids (grid frame, D
   * interleaved) and energy, kept as given. SetLabels would sum them again from the pixels, which rounds differently
   * from the incremental updates of the sweeps. Throws, keeping the current state, for a label outside
   * [0, numberOfCells), a mass that is not positive and finite or a centroid or energy that is not finite. */
  void
  SetState(const LabelType * labels,
           size_t            numberOfCells,
           const double *    masses,
           const double *    centroids,
           double            energy)
  {
    for (size_t p = 0; p < m_Grid.numberOfPixels; ++p)
    {
      if (labels[p] < 0 || static_cast<size_t>(labels[p]) >= numberOfCells)
      {
        ThrowLabelOutsideRange(labels[p], p, numberOfCells);
      }
    }
    for (size_t c = 0; c < numberOfCells; ++c)
    {
      bool finite = masses[c] > 0.0 && std::isfinite(masses[c]);
      for (unsigned int k = 0; k < D; ++k)
      {
        finite = finite && std::isfinite(centroids[c * D + k]);
      }
      if (!finite)
      {
        itkGenericExceptionMacro("DiscreteCVT: cell " << c << " of the given state has mass " << masses[c]
                                                      << " or a centroid that is not finite");
      }
    }
    if (!std::isfinite(energy))
    {
      itkGenericExceptionMacro("DiscreteCVT: the given state's energy " << energy << " is not finite");
    }
    std::copy(labels, labels + m_Grid.numberOfPixels, m_Labels.begin());
    m_Mass.assign(masses, masses + numberOfCells);
    m_Centroid.assign(centroids, centroids + numberOfCells * D);
    m_Energy = energy;
  }

  /** Masses, centroids and energy from scratch: every cell's sums in pixel order. */
  void
  RecomputeStatistics(size_t numberOfCells)
  {
    m_Mass.assign(numberOfCells, 0.0);
    m_Centroid.assign(numberOfCells * D, 0.0);
    // Every cell's sums in pixel order (the CUDA back-end's order too), in one pass on this thread (splitting the
    // cells among threads makes each of them read every pixel, which was slower on two cores). The sums of the
    // current run of one label stay in registers (the same additions in the same order, without a store and reload
    // per pixel); a label is checked where a run starts, so the first pixel with a label outside [0, numberOfCells) is
    // the one reported.
    LabelType run = -1;
    double    mass = 0.0, moment[D] = {};
    auto      flush = [&] {
      if (run >= 0)
      {
        m_Mass[run] = mass;
        std::copy(moment, moment + D, &m_Centroid[run * D]);
      }
    };
    ForEachPosition(0, m_Grid.numberOfPixels, [&](size_t p, const double * x) {
      const LabelType l = m_Labels[p];
      if (l != run)
      {
        if (l < 0 || static_cast<size_t>(l) >= numberOfCells)
        {
          ThrowLabelOutsideRange(l, p, numberOfCells);
        }
        flush();
        run = l;
        mass = m_Mass[l];
        std::copy(&m_Centroid[l * D], &m_Centroid[l * D] + D, moment);
      }
      mass += m_Density[p];
      for (unsigned int k = 0; k < D; ++k)
      {
        moment[k] += m_Density[p] * x[k];
      }
    });
    flush();
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
      const size_t begin = std::min(m_Grid.numberOfPixels, c * chunk);
      const size_t end = std::min(m_Grid.numberOfPixels, (c + 1) * chunk);
      ForEachPosition(begin, end, [&](size_t p, const double * x) {
        const double * r = &m_Centroid[m_Labels[p] * D];
        double         d2 = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          d2 += (x[k] - r[k]) * (x[k] - r[k]);
        }
        e += m_Density[p] * d2;
      });
      partial[c] = e;
    });
    return std::accumulate(partial.begin(), partial.end(), 0.0);
  }

  /** True when removing pixel p from its cell keeps the cell locally face-connected (see class comment). */
  bool
  RemovalKeepsCellConnected(size_t p) const
  {
    return RemovalKeepsCellConnected(p, PixelIndex(p));
  }
  /** The same, with p's grid index given. */
  bool
  RemovalKeepsCellConnected(size_t p, const IndexType & idx) const
  {
    const LabelType label = m_Labels[p];
    uint32_t        member = 0;
    for (unsigned int q = 0; q < NeighbourhoodSize; ++q)
    {
      bool inside = true;
      for (unsigned int k = 0; k < D; ++k)
      {
        const int64_t c = idx[k] + m_Offsets[q][k];
        inside = inside && c >= 0 && c < static_cast<int64_t>(m_Grid.size[k]);
      }
      if (inside && m_Labels[static_cast<size_t>(static_cast<int64_t>(p) + m_LinearOffsets[q])] == label)
      {
        member |= 1u << q;
      }
    }
    // the flood fill through face adjacency inside the neighbourhood, on bit sets (the CUDA kernels call it too)
    return Neighbourhood<D>::RemovalKeepsConnected(member);
  }

  /** Best swap for pixel p against the current (frozen) state; false when none lowers the energy. */
  bool
  ProposeSwap(size_t p, Proposal & out) const
  {
    const auto      idx = PixelIndex(p);
    const LabelType own = m_Labels[p];
    LabelType       candidates[2 * D];
    const unsigned  nc = NeighbourCells(p, idx, own, candidates);
    return nc > 0 && BestSwap(p, idx, own, candidates, nc, out); // nc == 0: interior pixel
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
    // the active lists hold 32-bit pixel indices; a larger grid (beyond any use here) takes the full scan
    const bool active =
      m_SweepMode != SweepMode::FullScan && m_Grid.numberOfPixels <= std::numeric_limits<uint32_t>::max();
    if (active)
    {
      BuildActiveLists();
    }
    // the sub-sweeps' threads (SweepChunks) live for this call only
    struct TeamRelease
    {
      TeamRunner & runner;
      ~TeamRelease() { runner.Release(); }
    } teamRelease{ m_Runner };

    for (size_t sweep = 0; sweep < maximumNumberOfSweeps; ++sweep)
    {
      const double before = m_Energy;
      size_t       swapsThisSweep = 0;
      for (unsigned int colour = 0; colour < NumberOfColours; ++colour)
      {
        if (active)
        {
          CollectActiveProposals(colour);
        }
        else
        {
          CollectProposals(colour);
        }
        const size_t committed = CommitProposals(result);
        if (active && committed > 0)
        {
          UpdateActiveLists(committed);
        }
        swapsThisSweep += committed;
        ++m_SubSweep;
      }
      ++result.sweeps;
      result.swaps += swapsThisSweep;
      if (swapsThisSweep == 0 || before - m_Energy <= epsilon * before)
      {
        break;
      }
      if (m_Checkpoint)
      {
        m_Checkpoint(static_cast<double>(sweep + 1) / static_cast<double>(maximumNumberOfSweeps));
      }
    }
    result.energyAfter = m_Energy;
    return result;
  }

private:
  /** The slabs of the contraction's blocks: blocks.size pixel planes across the last axis each (one slab in 1D). */
  static size_t
  NumberOfBlockSlabs(const ContractionBlockGrid & blocks)
  {
    return D > 1 ? blocks.perAxis[D - 1] : 1;
  }

  /** body(block, index of the row's first pixel, row start, i, end) for every run of a row of the slab that lies in one
   * block (pixels rowStart + [i, end)), row by row in pixel order. */
  template <typename TBody>
  void
  ForEachBlockRun(const ContractionBlockGrid & blocks, size_t slab, TBody && body) const
  {
    const size_t blockSize = blocks.size;
    const size_t rowLength = m_Grid.size[0];
    const size_t planeSize = D > 1 ? m_Grid.stride[D - 1] : 0;
    const size_t begin = D > 1 ? slab * blockSize * planeSize : 0;
    const size_t end = D > 1 ? std::min(m_Grid.size[D - 1], (slab + 1) * blockSize) * planeSize : m_Grid.numberOfPixels;
    for (size_t rowStart = begin; rowStart < end; rowStart += rowLength)
    {
      const IndexType idx = m_Grid.Index(rowStart);
      size_t          b = 0, blockStride = 1;
      for (unsigned int k = 1; k < D; ++k)
      {
        blockStride *= blocks.perAxis[k - 1];
        b += (static_cast<size_t>(idx[k]) / blockSize) * blockStride;
      }
      for (size_t i = 0; i < rowLength; i += blockSize, ++b)
      {
        body(b, idx, rowStart, i, std::min(rowLength, i + blockSize));
      }
    }
  }

  static constexpr unsigned int NeighbourhoodSize = Neighbourhood<D>::Size;

  static constexpr unsigned int NumberOfColours = 1u << D;

  /** The least number of gather-list entries per chunk of a parallel GatherChangedCells. */
  static constexpr size_t GatherChunkWork = 32768;

  /** A cluster's least pair in the contraction (see ContractionInitialize), ordered like the merges: by cost, then by
   * the lower and the higher id of the pair. The lowest bit of pair tells which of the two clusters holds the key,
   * so that the two holders of one pair have distinct keys and the order of the heap's keys is total. */
  struct ContractionKey
  {
    double   cost;
    uint64_t pair; // lower id << 33 | higher id << 1 | (the holder is the higher id)

    static ContractionKey
    Make(double cost, int32_t holder, int32_t partner)
    {
      const uint64_t lo = static_cast<uint64_t>(std::min(holder, partner));
      const uint64_t hi = static_cast<uint64_t>(std::max(holder, partner));
      return { cost, lo << 33 | hi << 1 | (holder > partner ? 1u : 0u) };
    }
    int32_t
    Low() const
    {
      return static_cast<int32_t>(pair >> 33);
    }
    int32_t
    High() const
    {
      return static_cast<int32_t>((pair >> 1) & 0xffffffffu);
    }
    int32_t
    Holder() const
    {
      return (pair & 1) ? High() : Low();
    }
    int32_t
    Partner() const
    {
      return (pair & 1) ? Low() : High();
    }
    bool
    operator<(const ContractionKey & o) const
    {
      if (cost != o.cost)
      {
        return cost < o.cost;
      }
      return pair < o.pair;
    }
  };
  // m_PixelState bits
  static constexpr uint8_t InColourList = 1; // in its colour's scan list (or pending list)
  static constexpr uint8_t InCellList = 2;   // in its cell's gather list of its colour
  static constexpr uint8_t Queued = 4;       // in its colour's queue
  static constexpr uint8_t Changed = 8;      // a label of its 3^D neighbourhood changed, or it proposed (queued)
  static constexpr uint8_t Blocked = 16;     // its removal disconnects its cell (valid while not Changed)
  static constexpr uint8_t Seen = 32;        // scratch: de-duplicates a gather list while it is compacted
  // a scan visits every entry of its colour's list (in parallel, in memory order), a gathering the gather-list
  // entries of the changed cells in 1 + D colours (one thread), then evaluates what it queued (in parallel).
  // Measured per sub-sweep on the 3D benchmark (benchmarks/cvt): a scan costs about the same whatever it
  // evaluates, a gathering about as much as a scan when it visits as many entries: gather below that.

  void
  Position(const IndexType & idx, double * x) const
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      x[k] = static_cast<double>(idx[k]) * m_Grid.spacing[k];
    }
  }

  /** Out of line, so that the per-pixel loop that checks the labels stays small. */
  [[noreturn]] static void
  ThrowLabelOutsideRange(LabelType l, size_t p, size_t numberOfCells)
  {
    itkGenericExceptionMacro("DiscreteCVT: label " << l << " at pixel " << p << " is outside [0, " << numberOfCells
                                                   << ")");
  }

  /** Calls body(p, x) for the pixels p in [begin, end) in increasing order, x[D] the position of p, row by row with no
   * division per pixel (the positions are those of Position). */
  template <typename TBody>
  void
  ForEachPosition(size_t begin, size_t end, TBody && body) const
  {
    if (begin >= end)
    {
      return;
    }
    IndexType idx = m_Grid.Index(begin);
    double    x[D];
    Position(idx, x);
    for (size_t p = begin; p < end;)
    {
      const size_t rowEnd = std::min(end, p + m_Grid.size[0] - static_cast<size_t>(idx[0]));
      for (; p < rowEnd; ++p, ++idx[0])
      {
        x[0] = static_cast<double>(idx[0]) * m_Grid.spacing[0];
        body(p, static_cast<const double *>(x));
      }
      idx[0] = 0;
      for (unsigned int k = 1; k < D; ++k)
      {
        if (++idx[k] < static_cast<int64_t>(m_Grid.size[k]))
        {
          break;
        }
        idx[k] = 0;
      }
      Position(idx, x);
    }
  }

  static unsigned int
  Colour(const IndexType & idx)
  {
    unsigned int colour = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      colour |= static_cast<unsigned int>(idx[k] & 1) << k;
    }
    return colour;
  }

  /** The distinct labels other than own among the face neighbours of p (at idx), in a fixed order; returns their
   * number (0: p is an interior pixel). */
  unsigned int
  NeighbourCells(size_t p, const IndexType & idx, LabelType own, LabelType * candidates) const
  {
    // branch-free: the order of the labels is data, a neighbour outside the grid reads p's own label
    unsigned int nc = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t stride = m_Grid.stride[k];
      const size_t lower = idx[k] > 0 ? p - stride : p;
      const size_t upper = idx[k] + 1 < static_cast<int64_t>(m_Grid.size[k]) ? p + stride : p;
      for (const size_t q : { lower, upper })
      {
        const LabelType l = m_Labels[q];
        bool            known = l == own;
        for (unsigned int j = 0; j < nc; ++j)
        {
          known |= candidates[j] == l;
        }
        candidates[nc] = l;
        nc += known ? 0u : 1u;
      }
    }
    return nc;
  }

  /** True when a face neighbour of p (at idx) has another label. */
  bool
  IsBoundary(size_t p, const IndexType & idx) const
  {
    const LabelType own = m_Labels[p];
    for (unsigned int k = 0; k < D; ++k)
    {
      if ((idx[k] > 0 && m_Labels[p - m_Grid.stride[k]] != own) ||
          (idx[k] + 1 < static_cast<int64_t>(m_Grid.size[k]) && m_Labels[p + m_Grid.stride[k]] != own))
      {
        return true;
      }
    }
    return false;
  }

  /** The most negative single-swap change (Eq. 23) of p over its candidate cells, if below the rounding guard and
   * the removal keeps p's cell connected. */
  bool
  BestSwap(size_t            p,
           const IndexType & idx,
           LabelType         own,
           const LabelType * candidates,
           unsigned int      nc,
           Proposal &        out,
           bool *            disconnects = nullptr) const
  {
    double x[D];
    Position(idx, x);
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
    if (bestLabel == own)
    {
      return false;
    }
    if (!RemovalKeepsCellConnected(p, idx))
    {
      if (disconnects)
      {
        *disconnects = true;
      }
      return false;
    }
    out = { static_cast<uint64_t>(p), bestLabel, -best };
    return true;
  }

  void
  BuildNeighbourhood()
  {
    for (unsigned int q = 0; q < NeighbourhoodSize; ++q)
    {
      int manhattan = 0;
      m_LinearOffsets[q] = 0;
      for (unsigned int k = 0; k < D; ++k)
      {
        m_Offsets[q][k] = Neighbourhood<D>::Offset(q, k);
        manhattan += std::abs(m_Offsets[q][k]);
        m_LinearOffsets[q] += m_Offsets[q][k] * static_cast<int64_t>(m_Grid.stride[k]);
      }
      m_FaceOrCentre[q] = manhattan <= 1;
    }
    m_Indexer = GridIndexer<D>(m_Grid);
  }

  /** m_Grid.Index(p), without divisions (the active lists visit pixels out of order). */
  IndexType
  PixelIndex(size_t p) const
  {
    return m_Indexer.Index(p);
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
    SweepChunks(nChunks, [&](size_t c) {
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

  /** body(c) for every chunk c of a sub-sweep, in parallel on the team of this Optimize call (TeamRunner): a sub-sweep
   * lasts tens of microseconds in 2D, about what a loop through ITK's pool costs to start. The team is made at the
   * first sub-sweep with more than one chunk (2D lists take two chunks: a many-core machine keeps two threads busy, not
   * all); where its threads may not start, the sub-sweeps run on ITK's threader with the same result. Chunk outputs are
   * combined in chunk order by the callers, as with ParallelForChunkIds. */
  template <typename TBody>
  void
  SweepChunks(size_t nChunks, TBody && body)
  {
    m_Runner.Run(m_Threader, nChunks, body);
  }

  /** Active lists from scratch: every boundary pixel in its colour's scan list and its cell's gather list, every
   * cell stamped inside the first window of every colour (so the first sweep evaluates every boundary pixel). */
  void
  BuildActiveLists()
  {
    const size_t n = m_Grid.numberOfPixels;
    const size_t nCells = m_Mass.size();
    m_PixelState.assign(n, 0);
    m_CellLists.resize(nCells * NumberOfColours);
    for (auto & list : m_CellLists)
    {
      list.clear();
    }
    m_CellListCompactedSize.assign(nCells * NumberOfColours, 0);
    for (unsigned int colour = 0; colour < NumberOfColours; ++colour)
    {
      m_ScanList[colour].clear();
      m_PendingList[colour].clear();
      m_Queue[colour].clear();
    }
    m_SubSweep = NumberOfColours + 1;
    m_CellStamp.assign(nCells, NumberOfColours); // >= the window start (1 + colour) of the first sweep
    // the boundary pixels of every colour, found per chunk on the threader and joined in chunk order: pixel order
    const size_t nChunks = std::max<size_t>(1, std::min<size_t>(64, n / 16384));
    const size_t chunk = (n + nChunks - 1) / nChunks;
    std::vector<std::array<std::vector<uint32_t>, NumberOfColours>> found(nChunks);
    ParallelForChunkIds(m_Threader, nChunks, [&](size_t c) {
      const size_t begin = std::min(n, c * chunk);
      const size_t end = std::min(n, (c + 1) * chunk);
      if (begin == end)
      {
        return;
      }
      IndexType idx = PixelIndex(begin);
      for (size_t p = begin; p < end; ++p, Increment(idx))
      {
        if (IsBoundary(p, idx))
        {
          m_PixelState[p] = InColourList | InCellList;
          found[c][Colour(idx)].push_back(static_cast<uint32_t>(p));
        }
      }
    });
    for (unsigned int colour = 0; colour < NumberOfColours; ++colour)
    {
      auto & list = m_ScanList[colour];
      for (const auto & f : found)
      {
        list.insert(list.end(), f[colour].begin(), f[colour].end());
      }
      for (const uint32_t p : list) // every cell's list in pixel order
      {
        m_CellLists[static_cast<size_t>(m_Labels[p]) * NumberOfColours + colour].push_back(p);
      }
    }
    for (size_t l = 0; l < m_CellLists.size(); ++l)
    {
      m_CellListCompactedSize[l] = m_CellLists[l].size();
    }
  }

  /** Next grid index in linear order. */
  void
  Increment(IndexType & idx) const
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      if (++idx[k] < static_cast<int64_t>(m_Grid.size[k]) || k + 1 == D)
      {
        return;
      }
      idx[k] = 0;
    }
  }

  /** Removes from gather list l (cell's list of one colour) the pixels that left the cell, duplicates (a pixel that
   * left and came back) and interior pixels (no longer InCellList). */
  void
  CompactCellList(size_t l, LabelType cell)
  {
    auto & list = m_CellLists[l];
    size_t kept = 0;
    for (size_t i = 0; i < list.size(); ++i)
    {
      const size_t p = list[i];
      if (m_Labels[p] != cell || (m_PixelState[p] & Seen))
      {
        continue;
      }
      if (!IsBoundary(p, PixelIndex(p)))
      {
        m_PixelState[p] &= static_cast<uint8_t>(~InCellList); // listed again when it becomes a boundary pixel
        continue;
      }
      m_PixelState[p] |= Seen;
      list[kept++] = static_cast<uint32_t>(p);
    }
    list.resize(kept);
    m_CellListCompactedSize[l] = kept;
    for (const uint32_t p : list)
    {
      m_PixelState[p] &= static_cast<uint8_t>(~Seen);
    }
  }

  /** Queues pixel p (of the colour of queue) for evaluation in its colour's next sub-sweep, flagged changed. */
  void
  Enqueue(size_t p, std::vector<uint32_t> & queue, uint8_t flags)
  {
    uint8_t & state = m_PixelState[p];
    if (!(state & Queued))
    {
      queue.push_back(static_cast<uint32_t>(p));
    }
    state |= Queued | flags;
  }

  /** BestSwap for the active paths: skips p while its removal is known to disconnect its cell (the local test
   * depends on the labels of its 3^D neighbourhood only), and records the outcome of that test. Writes only p's
   * state. */
  bool
  ActiveSwap(size_t            p,
             const IndexType & idx,
             LabelType         own,
             const LabelType * candidates,
             unsigned int      nc,
             Proposal &        out)
  {
    uint8_t & state = m_PixelState[p];
    if ((state & (Blocked | Changed)) == Blocked)
    {
      return false;
    }
    bool       blocked = false;
    const bool proposed = BestSwap(p, idx, own, candidates, nc, out, &blocked);
    state = blocked ? (state | Blocked) : (state & static_cast<uint8_t>(~Blocked));
    return proposed;
  }

  /** Phase 1 on the active lists of one colour (see class comment): the proposals of the pixels whose inputs may
   * have changed since the colour's previous sub-sweep, sorted by pixel like the full scan's. */
  void
  CollectActiveProposals(unsigned int colour)
  {
    // the colour's previous sub-sweep proposed before its commit, which is stamped windowStart
    const uint64_t windowStart = m_SubSweep - NumberOfColours;
    const size_t   nCells = m_Mass.size();
    size_t         listWork = 0; // the gather lists' entries of the changed cells
    m_ChangedCells.clear();
    for (size_t a = 0; a < nCells; ++a)
    {
      if (m_CellStamp[a] >= windowStart)
      {
        m_ChangedCells.push_back(static_cast<LabelType>(a));
        listWork += GatherWork(static_cast<LabelType>(a), colour);
      }
    }
    const size_t gatherWork = m_Queue[colour].size() + listWork;
    const size_t scanWork = m_ScanList[colour].size() + m_PendingList[colour].size();
    m_Proposals.clear();
    if (m_SweepMode == SweepMode::ActiveScan || (m_SweepMode == SweepMode::Auto && gatherWork >= scanWork))
    {
      ScanColourList(colour, windowStart);
    }
    else
    {
      GatherChangedCells(colour, listWork);
      EvaluateQueue(colour);
      std::sort(m_Proposals.begin(), m_Proposals.end(), [](const Proposal & x, const Proposal & y) {
        return x.pixel < y.pixel;
      });
    }
    // the evaluated pixels are clean now, except the proposers, evaluated again next time (committed or not)
    auto & queue = m_Queue[colour];
    for (const uint32_t p : queue)
    {
      m_PixelState[p] &= static_cast<uint8_t>(~(Queued | Changed));
    }
    queue.clear();
    for (const Proposal & prop : m_Proposals)
    {
      Enqueue(prop.pixel, queue, Changed);
    }
  }

  /** Scan mode: merges the pending pixels into the colour's scan list (sorted), then evaluates the listed pixels
   * that are dirty or whose own or face neighbours' cell changed in the window, in parallel and in pixel order,
   * dropping the pixels found interior from the list. */
  void
  ScanColourList(unsigned int colour, uint64_t windowStart)
  {
    auto & list = m_ScanList[colour];
    auto & pending = m_PendingList[colour];
    if (!pending.empty())
    {
      std::sort(pending.begin(), pending.end());
      m_MergeBuffer.resize(list.size() + pending.size());
      std::merge(list.begin(), list.end(), pending.begin(), pending.end(), m_MergeBuffer.begin());
      list.swap(m_MergeBuffer);
      pending.clear();
    }
    const size_t n = list.size();
    const size_t nChunks = n >= 2048 ? std::max<size_t>(2, std::min<size_t>(64, n / 8192)) : 1;
    const size_t chunk = (n + nChunks - 1) / nChunks;
    if (m_ChunkProposals.size() < nChunks)
    {
      m_ChunkProposals.resize(nChunks);
    }
    m_ChunkKept.resize(nChunks);
    SweepChunks(nChunks, [&](size_t c) {
      auto &       proposals = m_ChunkProposals[c];
      const size_t begin = std::min(n, c * chunk), end = std::min(n, begin + chunk);
      size_t       kept = begin;
      proposals.clear();
      for (size_t i = begin; i < end; ++i)
      {
        const size_t p = list[i];
        if ((m_PixelState[p] & (Blocked | Changed)) == Blocked)
        {
          list[kept++] = static_cast<uint32_t>(p); // a boundary pixel still, and still no proposal (ActiveSwap)
          continue;
        }
        const auto      idx = PixelIndex(p);
        const LabelType own = m_Labels[p];
        LabelType       candidates[2 * D];
        const unsigned  nc = NeighbourCells(p, idx, own, candidates);
        if (nc == 0)
        {
          // interior now: listed again when it becomes a boundary pixel
          m_PixelState[p] &= static_cast<uint8_t>(~InColourList);
          continue;
        }
        list[kept++] = static_cast<uint32_t>(p);
        bool changed = (m_PixelState[p] & Changed) != 0; // without branches: their outcome is data
        changed |= m_CellStamp[own] >= windowStart;
        for (unsigned int j = 0; j < nc; ++j)
        {
          changed |= m_CellStamp[candidates[j]] >= windowStart;
        }
        Proposal prop;
        if (changed && ActiveSwap(p, idx, own, candidates, nc, prop))
        {
          proposals.push_back(prop);
        }
      }
      m_ChunkKept[c] = kept;
    });
    // close the gaps left by the dropped pixels; concatenate the proposals in chunk (= pixel) order
    size_t size = 0;
    for (size_t c = 0; c < nChunks; ++c)
    {
      const size_t begin = std::min(n, c * chunk);
      if (size < begin)
      {
        std::copy(list.begin() + begin, list.begin() + m_ChunkKept[c], list.begin() + size);
      }
      size += m_ChunkKept[c] - begin;
      m_Proposals.insert(m_Proposals.end(), m_ChunkProposals[c].begin(), m_ChunkProposals[c].end());
    }
    list.resize(size);
  }

  /** Gather mode, step 1: queue the pixels of the colour that a cell change of the window may affect: the cell's
   * own boundary pixels, and the pixels of other cells face-adjacent to its boundary pixels (found from the
   * cell's gather lists of the colours that differ in one axis). With enough list entries to read, the changed cells
   * are split into chunks of about equal work (SetGatherChunkWork entries or more each), gathered in parallel; a
   * pixel's Queued bit is then set atomically, so each pixel is queued once, by the chunk that sets it. The queue holds
   * the same pixels either way, in another order, which nothing depends on: EvaluateQueue's proposals are sorted by
   * pixel, and each evaluation writes only its own pixel's state. work: the changed cells' GatherWork, summed. */
  void
  GatherChangedCells(unsigned int colour, size_t work)
  {
    auto &       queue = m_Queue[colour];
    const size_t nChanged = m_ChangedCells.size();
#if defined(__GNUC__) || defined(__clang__)
    const size_t nChunks = std::min<size_t>({ 64, nChanged, work / m_GatherChunkWork });
#else
    const size_t nChunks = 1;
#endif
    if (nChunks < 2)
    {
      GatherCells(colour, 0, nChanged, [&](size_t p) { Enqueue(p, queue, 0); });
      return;
    }
    // chunk c takes the changed cells [m_GatherChunkStart[c], m_GatherChunkStart[c + 1]), split by their work
    m_GatherChunkStart.assign(nChunks + 1, nChanged);
    m_GatherChunkStart[0] = 0;
    size_t done = 0, chunk = 1;
    for (size_t i = 0; i < nChanged && chunk < nChunks; ++i)
    {
      done += GatherWork(m_ChangedCells[i], colour);
      if (done * nChunks >= chunk * work)
      {
        m_GatherChunkStart[chunk++] = i + 1;
      }
    }
    if (m_ChunkQueue.size() < nChunks)
    {
      m_ChunkQueue.resize(nChunks);
    }
    SweepChunks(nChunks, [&](size_t c) {
      auto & local = m_ChunkQueue[c];
      local.clear();
      GatherCells(colour, m_GatherChunkStart[c], m_GatherChunkStart[c + 1], [&](size_t p) {
#if defined(__GNUC__) || defined(__clang__)
        if (!(__atomic_fetch_or(&m_PixelState[p], Queued, __ATOMIC_RELAXED) & Queued))
        {
          local.push_back(static_cast<uint32_t>(p));
        }
#endif
      });
    });
    for (size_t c = 0; c < nChunks; ++c)
    {
      queue.insert(queue.end(), m_ChunkQueue[c].begin(), m_ChunkQueue[c].end());
    }
  }

  /** The list entries that gathering changed cell a for the colour reads. */
  size_t
  GatherWork(LabelType a, unsigned int colour) const
  {
    const size_t l = static_cast<size_t>(a) * NumberOfColours;
    size_t       work = m_CellLists[l + colour].size();
    for (unsigned int k = 0; k < D; ++k)
    {
      work += m_CellLists[l + (colour ^ (1u << k))].size();
    }
    return work;
  }

  /** GatherChangedCells on the changed cells [begin, end): enqueue(p) for every pixel to queue (maybe more than once;
   * stale and interior entries too, which the evaluation skips: lists are compacted when they double). */
  template <typename TEnqueue>
  void
  GatherCells(unsigned int colour, size_t begin, size_t end, TEnqueue && enqueue) const
  {
    for (size_t i = begin; i < end; ++i)
    {
      const LabelType cell = m_ChangedCells[i];
      const size_t    a = static_cast<size_t>(cell);
      for (const uint32_t p : m_CellLists[a * NumberOfColours + colour])
      {
        if (m_Labels[p] == cell)
        {
          enqueue(p);
        }
      }
      for (unsigned int k = 0; k < D; ++k)
      {
        const int64_t last = static_cast<int64_t>(m_Grid.size[k]) - 1;
        const size_t  stride = m_Grid.stride[k];
        for (const uint32_t q : m_CellLists[a * NumberOfColours + (colour ^ (1u << k))])
        {
          if (m_Labels[q] != cell)
          {
            continue; // stale entry (dropped when its list is compacted)
          }
          const int64_t j = static_cast<int64_t>((q / stride) % m_Grid.size[k]);
          if (j > 0 && m_Labels[q - stride] != cell)
          {
            enqueue(q - stride);
          }
          if (j < last && m_Labels[q + stride] != cell)
          {
            enqueue(q + stride);
          }
        }
      }
    }
  }

  /** Gather mode, step 2: the proposals of the queued pixels (parallel; each pixel is queued once). */
  void
  EvaluateQueue(unsigned int colour)
  {
    const auto & queue = m_Queue[colour];
    const size_t n = queue.size();
    const size_t nChunks = std::max<size_t>(1, std::min<size_t>(64, n / 4096));
    const size_t chunk = (n + nChunks - 1) / nChunks;
    if (m_ChunkProposals.size() < nChunks)
    {
      m_ChunkProposals.resize(nChunks);
    }
    SweepChunks(nChunks, [&](size_t c) {
      auto & proposals = m_ChunkProposals[c];
      proposals.clear();
      const size_t end = std::min(n, (c + 1) * chunk);
      for (size_t i = c * chunk; i < end; ++i)
      {
        const size_t    p = queue[i];
        const auto      idx = PixelIndex(p);
        const LabelType own = m_Labels[p];
        LabelType       candidates[2 * D];
        const unsigned  nc = NeighbourCells(p, idx, own, candidates);
        Proposal        prop;
        if (nc > 0 && ActiveSwap(p, idx, own, candidates, nc, prop))
        {
          proposals.push_back(prop);
        }
      }
    });
    for (size_t c = 0; c < nChunks; ++c)
    {
      m_Proposals.insert(m_Proposals.end(), m_ChunkProposals[c].begin(), m_ChunkProposals[c].end());
    }
  }

  /** After committing proposals [0, count): stamp the changed cells, queue the 3^D neighbourhoods of the moved
   * pixels, and list the moved pixels and their face neighbours that are boundary pixels where they are not
   * listed. No two committed pixels lie in each other's neighbourhood (they have one colour), so each is handled
   * on its own. */
  void
  UpdateActiveLists(size_t count)
  {
    for (LabelType c : m_TouchedList)
    {
      m_CellStamp[c] = m_SubSweep;
    }
    for (size_t i = 0; i < count; ++i)
    {
      const size_t p = m_Proposals[i].pixel;
      const auto   idx = PixelIndex(p);
      m_PixelState[p] &= static_cast<uint8_t>(~InCellList); // its entry is in its former cell's gather list
      for (unsigned int q = 0; q < NeighbourhoodSize; ++q)
      {
        IndexType nidx;
        bool      inside = true;
        for (unsigned int k = 0; k < D; ++k)
        {
          nidx[k] = idx[k] + m_Offsets[q][k];
          inside = inside && nidx[k] >= 0 && nidx[k] < static_cast<int64_t>(m_Grid.size[k]);
        }
        if (!inside)
        {
          continue;
        }
        const size_t       r = static_cast<size_t>(static_cast<int64_t>(p) + m_LinearOffsets[q]);
        const unsigned int colour = Colour(nidx);
        Enqueue(r, m_Queue[colour], Changed);
        const uint8_t state = m_PixelState[r];
        if (!m_FaceOrCentre[q] || (state & (InColourList | InCellList)) == (InColourList | InCellList) ||
            !IsBoundary(r, nidx))
        {
          continue;
        }
        if (!(state & InColourList))
        {
          m_PixelState[r] |= InColourList;
          m_PendingList[colour].push_back(static_cast<uint32_t>(r));
        }
        if (!(state & InCellList))
        {
          m_PixelState[r] |= InCellList;
          const LabelType cell = m_Labels[r];
          const size_t    l = static_cast<size_t>(cell) * NumberOfColours + colour;
          m_CellLists[l].push_back(static_cast<uint32_t>(r));
          if (m_CellLists[l].size() > 2 * m_CellListCompactedSize[l] + 64)
          {
            CompactCellList(l, cell); // bounds the stale entries
          }
        }
      }
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

  GridType                           m_Grid;
  const float *                      m_Density{ nullptr };
  MultiThreaderBase *                m_Threader{ nullptr };
  TeamRunner                         m_Runner; // the sub-sweeps' threads, during Optimize only
  std::vector<LabelType>             m_Labels;
  std::vector<double>                m_Mass;
  std::vector<double>                m_Centroid;
  double                             m_Energy{ 0.0 };
  double                             m_SwapTolerance{ 0.0 };
  int                                m_Offsets[NeighbourhoodSize][D];
  std::vector<std::vector<Proposal>> m_ChunkProposals;
  std::vector<Proposal>              m_Proposals;
  std::vector<double>                m_DeltaMass;
  std::vector<double>                m_DeltaMoment;
  std::vector<double>                m_DeltaSecond;
  std::vector<uint8_t>               m_Touched;
  std::vector<LabelType>             m_TouchedList;
  SweepMode                          m_SweepMode{ SweepMode::Auto };
  std::function<void(double)>        m_Checkpoint;
  int64_t                            m_LinearOffsets[NeighbourhoodSize];
  bool                               m_FaceOrCentre[NeighbourhoodSize];
  GridIndexer<D>                     m_Indexer;
  // active lists (see class comment)
  std::vector<uint8_t>                               m_PixelState;
  std::array<std::vector<uint32_t>, NumberOfColours> m_ScanList;    // sorted
  std::array<std::vector<uint32_t>, NumberOfColours> m_PendingList; // to merge into the scan list
  std::vector<uint32_t>                              m_MergeBuffer;
  std::vector<size_t>                                m_ChunkKept;
  std::vector<std::vector<uint32_t>>                 m_CellLists; // gather lists, [cell * NumberOfColours + colour]
  std::vector<size_t>                                m_CellListCompactedSize;
  std::array<std::vector<uint32_t>, NumberOfColours> m_Queue;
  std::vector<std::vector<uint32_t>>                 m_ChunkQueue;       // GatherChangedCells' chunks
  std::vector<size_t>                                m_GatherChunkStart; // and their changed cells
  size_t                                             m_GatherChunkWork{ GatherChunkWork };
  std::vector<LabelType>                             m_ChangedCells;
  std::vector<uint64_t>                              m_CellStamp;
  uint64_t                                           m_SubSweep{ 0 };
};
} // namespace dmr
} // namespace itk

#endif
