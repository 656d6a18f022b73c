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
/** CUDA kernels and launchers of the CVT swap optimisation (see dmrCVTBackend.h and dmr::DiscreteCVT<D>).
 *
 * One sub-sweep (one parity colour) is a fixed chain of three launches without a host round trip (five without
 * the cells' slots, SetCellSlots(0)):
 *  1. Propose: one thread per pixel of the colour (two on large colours), against the frozen labels (the rule of
 *     DiscreteCVT::BestSwap); appends its proposal (one atomic per warp) and counts it for its two cells, listing the
 *     touched cells and placing the two entries in the cells' slots (CellSlots). Two counter sets alternate between
 *     batches: Propose also clears the previous batch's set.
 *     A pixel is evaluated only when one of its cells (its own, its face neighbours') changed since the colour's
 *     previous batch: every proposal stamps its two cells with the batch number (SweepState::phase), which covers
 *     every commit and every proposal a halving dropped. A pixel with no stamped cell has the inputs of its previous
 *     evaluation (labels of its cells' pixels, masses, centroids, density), which proposed nothing, so skipping it
 *     gives the full scan's proposals (a read of a stamp written in the same batch only adds a needless evaluation).
 *     The pixels to evaluate are queued per block in shared memory and evaluated by consecutive threads (full warps).
 *     With at most 65536 cells the sweeps read a 16-bit copy of the labels, kept by the commits (half the traffic;
 *     for 256 x 256 x 132 it stays in L2).
 *  2. Without slots, Allocate/Scatter: for each touched cell, its segment of (proposal, side) entries, keyed by pixel.
 *  3. Cell: one warp per touched cell orders its entries by key (by rank; pixel order is the CPU's proposal order)
 *     and sums the deltas of mass, first moment about the old centroid and second moment in that order
 *     (DiscreteCVT::JointEnergyChange's order). A cell with more entries than slots finds the rest in the batch's
 *     overflow list.
 *  4. DecideCommit: every block reduces the cells' terms to the joint change dE in one fixed order (so all blocks
 *     agree) and, if dE < 0, commits its share: labels, masses, centroids; block 0 records energy and swap count.
 * The sweeps of an Optimize call are one CUDA graph, captured once and replayed: a conditional while node around a
 * sweep (all colours) and EndSweepKernel, which applies the stopping rule on the device, then the copy of SweepState
 * to pinned host memory. Where conditional nodes are unavailable (or SetDeviceLoop(false)), one sweep with its
 * EndSweepKernel is the graph and the host synchronises once per sweep to read the rule's verdict.
 * A rejected batch halts the rest of the sweep on the device (every later kernel of the sweep returns at once);
 * the host sees it at the end of the sweep, halves the batch like the CPU (sorted by gain, ties by pixel) and
 * resumes with the next colour (Count, Allocate, Scatter, Cell, Decide, Commit on its sorted halves, entries keyed by
 * proposal index; no slots). Counts stay on the device: grid-stride kernels read them from SweepState.
 *
 * Statistics (SetLabels/KeepLabels): a stable radix sort of the pixels by label gives each cell's pixels in pixel
 * order, summed in that order by one warp per cell (DiscreteCVT::RecomputeStatistics's order). The energy is a
 * fixed-shape (deterministic) reduction. */
#include "dmrCVTBackend.h"
#include "dmrContractionSums.h"
#include "dmrCudaUtils.cuh"
#include "dmrNeighbourhood.h"

#include <cub/block/block_reduce.cuh>
#include <cub/device/device_radix_sort.cuh>

#include <algorithm>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace itk
{
namespace dmr
{
namespace cuda
{
namespace
{
constexpr unsigned int Threads = 256;
constexpr unsigned int EnergyBlocks = 512; // fixed: the energy reduction has one shape for a given grid

struct GridParams
{
  int32_t size[3];
  int32_t stride[3];
  double  spacing[3];
  int32_t numberOfPixels;
};

/** One pixel's proposed swap. */
struct Proposal
{
  uint32_t pixel;
  int32_t  from;
  int32_t  to;
  int32_t  unused;
  double   gain; // -(single-swap energy change) > 0
};

/** The scalars of one batch (its counter set). */
struct BatchCounts
{
  int32_t numberOfProposals;
  int32_t numberOfTouched;
  int32_t cursor;     // next free entry of the cells' segments
  int32_t overflowed; // entries beyond their cells' slots (CellSlots::overflow)
};

/** Device-side state of the optimisation (the energy) and of the current sweep; read by the host once per sweep.
 * Consecutive batches alternate between two counter sets, so that a batch's Propose can clear the set of the batch
 * before it (whose kernels have finished) while filling its own: no separate reset launch. */
struct SweepState
{
  double             energy;
  double             dE;
  unsigned long long swaps;  // committed in this sweep
  int32_t            halted; // a batch of this sweep was rejected: later kernels of the sweep do nothing
  int32_t            rejectedColour;
  int32_t            commit;       // the current batch is committed
  int32_t            parity;       // the counter set of the current batch
  int32_t            nextParity;   // the counter set of the next batch
  int32_t            phase;        // number of the current batch in this Optimize call (from 1)
  int32_t            lastPhase[8]; // per colour: the number of its previous batch (0: none yet)
  BatchCounts        batch[2];
  // the stopping rule of Optimize, applied on the device by EndSweepKernel
  double             sweepStartEnergy;
  double             epsilon;
  unsigned long long totalSwaps;
  int32_t            sweeps;
  int32_t            maximumSweeps;
  int32_t            stop;
  unsigned long long slotOverflows; // cells whose entries of a batch outnumbered their slots (see CellSlots)
};

/** The sweep path's per-cell slots: entry k of a batch for cell c (k: the cell's count when the entry was counted)
 * at c x capacity + k, with its sort key, written by ProposeKernel, so that no allocation pass (AllocateKernel,
 * ScatterKernel) is needed. The entries beyond a cell's slots go to the batch's overflow list, which CellKernel scans
 * for the cells that have more entries than slots. capacity 0: every batch goes through the allocation pass. */
struct CellSlots
{
  int32_t *  entries;
  uint32_t * keys;
  int32_t *  sorted;
  int32_t *  overflow; // the batch's entries that found their cells' slots full (BatchCounts::overflowed of them)
  int32_t    capacity;
};

/** Outcome of the statistics recomputation. */
struct StatisticsReport
{
  unsigned long long badPixel; // smallest pixel with a label outside [0, n), or ~0
  unsigned long long badCell;  // smallest cell with no positive mass, or ~0
};

template <unsigned int D>
__device__ inline void
IndexOf(const GridParams & g, int32_t p, int32_t * idx)
{
  for (unsigned int k = 0; k < D; ++k)
  {
    idx[k] = p % g.size[k];
    p /= g.size[k];
  }
}

template <unsigned int D>
__device__ inline void
PositionOf(const GridParams & g, const int32_t * idx, double * x)
{
  for (unsigned int k = 0; k < D; ++k)
  {
    x[k] = static_cast<double>(idx[k]) * g.spacing[k];
  }
}

/** Paper Eq. 23, the arithmetic of dmr::SwapEnergyChange. */
template <unsigned int D>
__device__ inline double
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

/** DiscreteCVT::RemovalKeepsCellConnected: the cell's pixels of the 3^D neighbourhood that touch p by a face stay
 * face-connected (inside the neighbourhood, without p). Bit-set flood fill. */
template <unsigned int D, typename TLabel>
__device__ inline bool
RemovalKeepsCellConnected(const GridParams & g, const TLabel * labels, int32_t p, const int32_t * idx, int32_t own)
{
  using N = Neighbourhood<D>;
  uint32_t member = 0;
#pragma unroll
  for (unsigned int q = 0; q < N::Size; ++q)
  {
    if (q == N::Centre)
    {
      continue;
    }
    bool    inside = true;
    int32_t offset = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const int32_t c = idx[k] + N::Offset(q, k);
      inside = inside && c >= 0 && c < g.size[k];
      offset += N::Offset(q, k) * g.stride[k];
    }
    if (inside && static_cast<int32_t>(labels[p + offset]) == own)
    {
      member |= 1u << q;
    }
  }
  return N::RemovalKeepsConnected(member);
}

struct ColourParams
{
  int32_t  origin[3];
  int32_t  sub[3];
  int32_t  count;
  int32_t  colour;
  uint64_t reciprocal[3]; // ceil(2^32 / sub[k]): rest / sub[k] as a product (0: divide; see ColourIndex)
};

/** The index of pixel number q of colour cp and its offset p. Dividing by sub[k] is a multiplication by
 * ceil(2^32 / sub[k]) and a shift, exact for every rest < 2^32 / sub[k] (the host sets the reciprocals only when
 * count x sub[k] < 2^32); otherwise an integer division. */
template <unsigned int D>
__device__ inline int32_t
ColourIndex(const GridParams & g, const ColourParams & cp, int32_t q, int32_t * idx)
{
  int32_t  p = 0;
  uint32_t rest = static_cast<uint32_t>(q);
  for (unsigned int k = 0; k < D; ++k)
  {
    const uint32_t sub = static_cast<uint32_t>(cp.sub[k]);
    const uint32_t next = cp.reciprocal[k] != 0
                            ? static_cast<uint32_t>((static_cast<uint64_t>(rest) * cp.reciprocal[k]) >> 32)
                            : rest / sub;
    idx[k] = cp.origin[k] + 2 * static_cast<int32_t>(rest - next * sub);
    rest = next;
    p += idx[k] * g.stride[k];
  }
  return p;
}

/** The sweep's kernels are launched as programmatic dependent launches (LaunchAfter): a kernel may be scheduled
 * while its predecessor still runs, and waits here, before touching memory, until the predecessor has finished and
 * its writes are visible. The order of the work is unchanged; the gap between the many small kernels shrinks.
 * (Allowing the next kernel's launch right after the wait, cudaTriggerProgrammaticLaunchCompletion, made the 3D sweeps
 * 1-2 % slower on the H100.) */
__device__ inline void
WaitForPrevious()
{
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  cudaGridDependencySynchronize();
#endif
}

/** kernel<<<blocks, threads, 0, stream>>>(args...) as a programmatic dependent launch (see WaitForPrevious). */
template <typename... TParams, typename... TArgs>
void
LaunchAfter(void (*kernel)(TParams...),
            unsigned int blocks,
            unsigned int threads,
            cudaStream_t stream,
            TArgs &&... args)
{
  cudaLaunchConfig_t  config{};
  cudaLaunchAttribute attribute[1];
  attribute[0].id = cudaLaunchAttributeProgrammaticStreamSerialization;
  attribute[0].val.programmaticStreamSerializationAllowed = 1;
  config.gridDim = dim3(blocks);
  config.blockDim = dim3(threads);
  config.dynamicSmemBytes = 0;
  config.stream = stream;
  config.attrs = attribute;
  config.numAttrs = 1;
  Check(cudaLaunchKernelEx(&config, kernel, std::forward<TArgs>(args)...), "cudaLaunchKernelEx");
}

/** Reset of a counter set: the counts and fill cursors of every cell and the scalars of the batch. */
__device__ inline void
ResetSet(size_t thread, size_t threads, BatchCounts & batch, int32_t * set, int32_t nCells, bool keepProposals)
{
  if (thread == 0)
  {
    if (!keepProposals)
    {
      batch.numberOfProposals = 0;
    }
    batch.numberOfTouched = 0;
    batch.cursor = 0;
    batch.overflowed = 0;
  }
  for (size_t c = thread; c < 2 * static_cast<size_t>(nCells); c += threads)
  {
    set[c] = 0;
  }
}

/** The counter set of the current batch: per cell its number of entries (count) and, after it, the fill cursors. */
__device__ inline int32_t *
CurrentSet(const SweepState * state, int32_t * counters, int32_t nCells)
{
  return counters + static_cast<size_t>(state->parity) * 2 * static_cast<size_t>(nCells);
}

/** Halving path: the current set is cleared for a batch of state->batch[parity].numberOfProposals proposals that the
 * host has placed in `proposals`. */
__global__ void
ResetBatchKernel(SweepState * state, int32_t * counters, int32_t nCells)
{
  WaitForPrevious();
  const size_t thread = blockIdx.x * static_cast<size_t>(blockDim.x) + threadIdx.x;
  if (thread == 0)
  {
    state->commit = 0;
  }
  ResetSet(thread,
           static_cast<size_t>(gridDim.x) * blockDim.x,
           state->batch[state->parity],
           CurrentSet(state, counters, nCells),
           nCells,
           true);
}

/** Touches the cells of proposal number `index`, `prop`: counts its two entries, lists cells touched for the first
 * time and places the entries in their cells' slots while there is room. */
__device__ inline void
CountProposal(const Proposal &  prop,
              int32_t           index,
              BatchCounts &     batch,
              int32_t *         count,
              int32_t *         touched,
              const CellSlots & slots)
{
  for (int side = 0; side < 2; ++side)
  {
    const int32_t c = side == 0 ? prop.from : prop.to;
    const int32_t k = atomicAdd(&count[c], 1);
    if (k == 0)
    {
      touched[atomicAdd(&batch.numberOfTouched, 1)] = c;
    }
    if (k < slots.capacity)
    {
      const size_t at = static_cast<size_t>(c) * static_cast<size_t>(slots.capacity) + static_cast<size_t>(k);
      slots.entries[at] = 2 * index + side;
      slots.keys[at] = prop.pixel;
    }
    else if (slots.capacity > 0)
    {
      slots.overflow[atomicAdd(&batch.overflowed, 1)] = 2 * index + side;
    }
  }
}

/** Phase 1 for one colour (DiscreteCVT::ProposeSwap on every pixel of the colour), appending the proposals (in no
 * particular order: the cell sums sort their entries by pixel) and counting them per cell.
 * The batch uses the counter set state->nextParity (it becomes state->parity); the set of the previous batch, whose
 * kernels have all finished, is cleared here for the next one.
 * Every thread takes K pixels of the colour (K x Threads per block), whose loads it issues together: the kernel is
 * bound by the latency of its chain of dependent loads (labels, stamps, cell sums, connectivity), so K pixels per
 * thread keep K times the loads in flight (3D warm-start sweep 0.345 -> 0.316 ms on the H100, against one pixel per
 * thread on 5 blocks per SM). K = 1 when the colour has too few pixels to fill the device twice. At most 64 registers
 * (4 resident blocks per SM): K = 2 needs them without spilling. */
template <unsigned int D, typename TLabel, int K>
__global__ void
__launch_bounds__(Threads, 4) ProposeKernel(GridParams     g,
                                            ColourParams   cp,
                                            const TLabel * labels,
                                            const float *  density,
                                            const double * mass,
                                            const double * centroid,
                                            double         tolerance,
                                            SweepState *   state,
                                            Proposal *     proposals,
                                            int32_t *      counters,
                                            int32_t *      touched,
                                            int32_t *      cellStamp,
                                            CellSlots      slots,
                                            int32_t        nCells)
{
  WaitForPrevious();
  if (state->halted)
  {
    return;
  }
  const size_t  thread = blockIdx.x * static_cast<size_t>(blockDim.x) + threadIdx.x;
  const int32_t set = state->nextParity; // not written by this kernel
  const int32_t phase = state->phase;    // nor these two (DecideCommitKernel advances them)
  const int32_t since = state->lastPhase[cp.colour];
  if (thread == 0)
  {
    state->parity = set; // read by the later kernels of the batch only
    state->commit = 0;
  }
  ResetSet(thread,
           static_cast<size_t>(gridDim.x) * blockDim.x,
           state->batch[1 - set],
           counters + static_cast<size_t>(1 - set) * 2 * static_cast<size_t>(nCells),
           nCells,
           false);
  // Two passes over the block's pixels. The first, one thread per K pixels, finds the pixels to evaluate (boundary
  // pixels with a changed cell) and queues them in shared memory; the second evaluates the queue with consecutive
  // threads, so the warps that compute the energies and the connectivity are full (most pixels are skipped).
  struct Queued
  {
    int32_t p;
    int32_t own;
    int32_t nc;
    int32_t idx[D];
    int32_t candidates[2 * D];
  };
  __shared__ Queued  queue[K * Threads];
  __shared__ int32_t queued;
  if (threadIdx.x == 0)
  {
    queued = 0;
  }
  __syncthreads();
  {
    // pixel j of this thread: number blockIdx.x x K x Threads + j x Threads + threadIdx.x of the colour
    const size_t first = blockIdx.x * static_cast<size_t>(K * Threads) + threadIdx.x;
    bool         inside[K];
    int32_t      idx[K][D], p[K], own[K], nb[K][2 * D];
#pragma unroll
    for (int j = 0; j < K; ++j)
    {
      const size_t q = first + static_cast<size_t>(j) * Threads;
      inside[j] = q < static_cast<size_t>(cp.count);
      p[j] = inside[j] ? ColourIndex<D>(g, cp, static_cast<int32_t>(q), idx[j]) : 0;
      if (!inside[j])
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          idx[j][k] = 0;
        }
      }
    }
    // the labels of the pixels and of their face neighbours (the pixel's own where a neighbour is outside), all
    // loads issued before any is used
#pragma unroll
    for (int j = 0; j < K; ++j)
    {
      own[j] = static_cast<int32_t>(labels[p[j]]);
      for (unsigned int k = 0; k < D; ++k)
      {
        nb[j][2 * k] = static_cast<int32_t>(labels[idx[j][k] > 0 ? p[j] - g.stride[k] : p[j]]);
        nb[j][2 * k + 1] = static_cast<int32_t>(labels[idx[j][k] + 1 < g.size[k] ? p[j] + g.stride[k] : p[j]]);
      }
    }
    // DiscreteCVT::NeighbourCells: distinct other labels of the face neighbours, axis by axis, lower then upper,
    // compacted in place (constant indices only, so that the arrays stay in registers)
    unsigned int nc[K];
#pragma unroll
    for (int j = 0; j < K; ++j)
    {
      nc[j] = 0;
#pragma unroll
      for (unsigned int s = 0; s < 2 * D; ++s)
      {
        const int32_t l = nb[j][s];
        bool          known = l == own[j];
#pragma unroll
        for (unsigned int c = 0; c < s; ++c)
        {
          known |= c < nc[j] && nb[j][c] == l;
        }
#pragma unroll
        for (unsigned int t = 0; t <= s; ++t)
        {
          nb[j][t] = t == nc[j] ? l : nb[j][t];
        }
        nc[j] += known ? 0u : 1u;
      }
      nc[j] = inside[j] ? nc[j] : 0u;
    }
    // Skip a pixel none of whose cells (its own, the candidates) changed or took part in a proposal since the
    // colour's previous batch: its inputs are those of its previous evaluation, which found no swap.
    bool changed[K];
#pragma unroll
    for (int j = 0; j < K; ++j)
    {
      changed[j] = false;
      if (nc[j] > 0)
      {
        changed[j] = cellStamp[own[j]] >= since;
#pragma unroll
        for (unsigned int c = 0; c < 2 * D; ++c)
        {
          changed[j] |= c < nc[j] && cellStamp[nb[j][c]] >= since;
        }
      }
    }
#pragma unroll
    for (int j = 0; j < K; ++j)
    {
      if (changed[j])
      {
        Queued & e = queue[atomicAdd(&queued, 1)];
        e.p = p[j];
        e.own = own[j];
        e.nc = static_cast<int32_t>(nc[j]);
        for (unsigned int k = 0; k < D; ++k)
        {
          e.idx[k] = idx[j][k];
        }
        for (unsigned int c = 0; c < 2 * D; ++c)
        {
          e.candidates[c] = nb[j][c];
        }
      }
    }
  }
  __syncthreads();
  const int32_t total = queued; // the same for the whole block: every lane takes part in each round's ballot
  for (int32_t round = 0; round < total; round += static_cast<int32_t>(Threads))
  {
    bool          flag = false;
    Proposal      prop{};
    const int32_t at = round + static_cast<int32_t>(threadIdx.x);
    if (at < total)
    {
      const Queued & e = queue[at];
      const int32_t  p = e.p, own = e.own;
      const double   w = static_cast<double>(density[p]);
      const double   mi = mass[own];
      if (mi - w > 0.0)
      {
        double x[D];
        PositionOf<D>(g, e.idx, x);
        double  best = -tolerance * w;
        int32_t bestLabel = own;
        for (int32_t c = 0; c < e.nc; ++c)
        {
          const int32_t j = e.candidates[c];
          const double  dE = SwapEnergyChange<D>(w, x, mi, &centroid[own * D], mass[j], &centroid[j * D]);
          if (dE < best || (dE == best && bestLabel != own && j < bestLabel))
          {
            best = dE;
            bestLabel = j;
          }
        }
        if (bestLabel != own && RemovalKeepsCellConnected<D>(g, labels, p, e.idx, own))
        {
          flag = true;
          prop = Proposal{ static_cast<uint32_t>(p), own, bestLabel, 0, -best };
          // both cells change if the swap is committed; if it is not (halving), this pixel must propose again
          cellStamp[own] = phase;
          cellStamp[bestLabel] = phase;
        }
      }
    }
    // one atomic per warp for the slots (every lane of the block is here)
    const unsigned int want = __ballot_sync(0xffffffffu, flag);
    if (flag)
    {
      BatchCounts &      batch = state->batch[set];
      const unsigned int lane = threadIdx.x % 32;
      const int          leader = __ffs(want) - 1;
      int32_t            base = 0;
      if (static_cast<int>(lane) == leader)
      {
        base = atomicAdd(&batch.numberOfProposals, __popc(want));
      }
      base = __shfl_sync(want, base, leader);
      const int32_t index = base + __popc(want & ((1u << lane) - 1u));
      proposals[index] = prop;
      CountProposal(
        prop, index, batch, counters + static_cast<size_t>(set) * 2 * static_cast<size_t>(nCells), touched, slots);
    }
  }
}

/** Halving path: counts, per cell, the proposals of the batch placed by the host, and lists the touched cells. */
__global__ void
CountKernel(SweepState * state, const Proposal * proposals, int32_t * counters, int32_t * touched, int32_t nCells)
{
  WaitForPrevious();
  if (state->halted)
  {
    return;
  }
  BatchCounts & batch = state->batch[state->parity];
  int32_t *     count = CurrentSet(state, counters, nCells);
  const int32_t n = batch.numberOfProposals;
  for (int32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x)
  {
    CountProposal(proposals[i], i, batch, count, touched, CellSlots{});
  }
}

/** Places every touched cell's segment of entries (where does not matter: each is sorted later). */
__global__ void
AllocateKernel(SweepState * state, int32_t * counters, const int32_t * touched, int32_t * segment, int32_t nCells)
{
  WaitForPrevious();
  if (state->halted)
  {
    return;
  }
  BatchCounts &   batch = state->batch[state->parity];
  const int32_t * count = CurrentSet(state, counters, nCells);
  const int32_t   n = batch.numberOfTouched;
  for (int32_t j = blockIdx.x * blockDim.x + threadIdx.x; j < n; j += gridDim.x * blockDim.x)
  {
    const int32_t c = touched[j];
    segment[c] = atomicAdd(&batch.cursor, count[c]);
  }
}

/** Entry 2 i + side of proposal i (side 0: its former cell, 1: its new cell) into the cell's segment, with its sort
 * key: the proposal's pixel (byPixel: the sweep's batches, appended in no particular order) or the entry itself (the
 * host's halved batches, in the order of the CPU's sorted proposals). */
__global__ void
ScatterKernel(SweepState *     state,
              const Proposal * proposals,
              const int32_t *  segment,
              int32_t *        counters,
              int32_t *        entries,
              uint32_t *       keys,
              int32_t          nCells,
              int32_t          byPixel)
{
  WaitForPrevious();
  if (state->halted)
  {
    return;
  }
  const int32_t n = state->batch[state->parity].numberOfProposals;
  int32_t *     fill = CurrentSet(state, counters, nCells) + nCells;
  for (int32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x)
  {
    const Proposal prop = proposals[i];
    for (int side = 0; side < 2; ++side)
    {
      const int32_t c = side == 0 ? prop.from : prop.to;
      const int32_t at = segment[c] + atomicAdd(&fill[c], 1);
      entries[at] = 2 * i + side;
      keys[at] = byPixel ? prop.pixel : static_cast<uint32_t>(2 * i + side);
    }
  }
}

/** Per touched cell, one warp: the deltas of DiscreteCVT::JointEnergyChange summed in proposal order, and the
 * cell's term dQ - |dS|^2 / (m + dm) of the joint change. The cell's entries are in its segment (slots.capacity 0:
 * placed by Allocate/Scatter) or in its slots (see CellSlots).
 * The cell's entries (a proposal touches a cell once, so their keys differ) are placed by the rank of their key into
 * `sorted`: the order of the CPU's proposals. The lanes then compute the terms w, w (x - r)_k and w |x - r|^2 of 32
 * entries at a time, and every lane adds them up in entry order from shuffles: the same products added in the same
 * order as the CPU, so the sums are bit-identical, while the loads of an entry's proposal and density overlap across
 * the lanes. */
template <unsigned int D>
__global__ void
CellKernel(GridParams       g,
           SweepState *     state,
           const Proposal * proposals,
           const float *    density,
           const double *   mass,
           const double *   centroid,
           int32_t *        counters,
           const int32_t *  touched,
           const int32_t *  segment,
           int32_t *        entries, // written here for a cell with more entries than slots
           uint32_t *       keys,
           int32_t *        sorted,
           double *         deltaMass,
           double *         deltaMoment,
           double *         term,
           CellSlots        slots,
           int32_t          nCells)
{
  WaitForPrevious();
  if (state->halted)
  {
    return;
  }
  const int32_t *    count = CurrentSet(state, counters, nCells);
  BatchCounts &      batch = state->batch[state->parity];
  const int32_t      n = batch.numberOfTouched;
  const unsigned int lane = threadIdx.x % 32;
  const int32_t      warps = static_cast<int32_t>(gridDim.x * blockDim.x / 32);
  for (int32_t j = static_cast<int32_t>((blockIdx.x * blockDim.x + threadIdx.x) / 32); j < n; j += warps)
  {
    const int32_t    c = touched[j];
    const int32_t    len = count[c];
    const int32_t *  e = nullptr;
    const uint32_t * key = nullptr;
    int32_t *        out = nullptr;
    if (slots.capacity == 0)
    {
      e = entries + segment[c];
      key = keys + segment[c];
      out = sorted + segment[c];
    }
    else if (len <= slots.capacity)
    {
      const size_t at = static_cast<size_t>(c) * static_cast<size_t>(slots.capacity);
      e = slots.entries + at;
      key = slots.keys + at;
      out = slots.sorted + at;
    }
    else
    {
      // more entries than slots: a segment of the batch's entry arrays, filled with the cell's slots and then its
      // entries from the overflow list (in list order; the ranks below order them by pixel)
      const int32_t cap = slots.capacity;
      int32_t       at = 0;
      if (lane == 0)
      {
        at = atomicAdd(&batch.cursor, len);
        atomicAdd(&state->slotOverflows, 1ull);
      }
      at = __shfl_sync(0xffffffffu, at, 0);
      const size_t own = static_cast<size_t>(c) * static_cast<size_t>(cap);
      for (int32_t k = static_cast<int32_t>(lane); k < cap; k += 32)
      {
        entries[at + k] = slots.entries[own + k];
        keys[at + k] = slots.keys[own + k];
      }
      const int32_t listed = batch.overflowed;
      int32_t       found = cap;
      for (int32_t base = 0; base < listed; base += 32)
      {
        const int32_t i = base + static_cast<int32_t>(lane);
        int32_t       entry = -1;
        uint32_t      pixel = 0;
        if (i < listed)
        {
          entry = slots.overflow[i];
          const Proposal & prop = proposals[entry >> 1];
          entry = ((entry & 1) ? prop.to : prop.from) == c ? entry : -1;
          pixel = prop.pixel;
        }
        const unsigned int mine = __ballot_sync(0xffffffffu, entry >= 0);
        if (entry >= 0)
        {
          const int32_t k = at + found + __popc(mine & ((1u << lane) - 1u));
          entries[k] = entry;
          keys[k] = pixel;
        }
        found += __popc(mine);
      }
      __syncwarp();
      e = entries + at;
      key = keys + at;
      out = sorted + at;
    }
    for (int32_t a = static_cast<int32_t>(lane); a < len; a += 32)
    {
      const uint32_t v = key[a];
      int32_t        rank = 0;
      for (int32_t b = 0; b < len; ++b)
      {
        rank += key[b] < v ? 1 : 0;
      }
      out[rank] = e[a];
    }
    __syncwarp();
    double r[D], dS[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      r[k] = centroid[c * D + k];
      dS[k] = 0.0;
    }
    double dm = 0.0, dQ = 0.0;
    for (int32_t base = 0; base < len; base += 32)
    {
      const int32_t a = base + static_cast<int32_t>(lane);
      double        w = 0.0, wd[D], wd2 = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        wd[k] = 0.0;
      }
      if (a < len)
      {
        const int32_t    entry = out[a];
        const Proposal & prop = proposals[entry >> 1];
        const double     wp = static_cast<double>(density[prop.pixel]);
        w = (entry & 1) ? wp : -wp;
        int32_t idx[D];
        double  x[D];
        IndexOf<D>(g, static_cast<int32_t>(prop.pixel), idx);
        PositionOf<D>(g, idx, x);
        double d2 = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          const double d = x[k] - r[k];
          wd[k] = w * d;
          d2 += d * d;
        }
        wd2 = w * d2;
      }
      const int32_t valid = min(32, len - base);
      for (int32_t t = 0; t < valid; ++t)
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          dS[k] += __shfl_sync(0xffffffffu, wd[k], t);
        }
        dm += __shfl_sync(0xffffffffu, w, t);
        dQ += __shfl_sync(0xffffffffu, wd2, t);
      }
    }
    if (lane == 0)
    {
      double s2 = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        s2 += dS[k] * dS[k];
        deltaMoment[c * D + k] = dS[k];
      }
      deltaMass[c] = dm;
      term[c] = dQ - s2 / (mass[c] + dm);
    }
  }
}

/** The joint change dE of the batch: the touched cells' terms summed by one block in a fixed order (every block that
 * calls it gets the same value). */
__device__ inline double
BatchEnergyChange(const int32_t * count, const double * term, int32_t nCells)
{
  double sum = 0.0;
  // the thread's cells in groups of 16: all the group's loads are issued before its additions (term is zeroed at
  // allocation, so an untouched cell's load is harmless), then added in cell order as one at a time would be
  constexpr int32_t G = 16;
  const int32_t     step = static_cast<int32_t>(blockDim.x);
  for (int32_t first = threadIdx.x; first < nCells; first += G * step)
  {
    int32_t n[G];
    double  t[G];
#pragma unroll
    for (int32_t g = 0; g < G; ++g)
    {
      const int32_t c = first + g * step;
      n[g] = c < nCells ? count[c] : 0;
      t[g] = c < nCells ? term[c] : 0.0;
    }
#pragma unroll
    for (int32_t g = 0; g < G; ++g)
    {
      sum += n[g] > 0 ? t[g] : 0.0;
    }
  }
  using Reduce = cub::BlockReduce<double, Threads>;
  __shared__ typename Reduce::TempStorage storage;
  __shared__ double                       total;
  const double                            dE = Reduce(storage).Sum(sum);
  if (threadIdx.x == 0)
  {
    total = dE;
  }
  __syncthreads();
  return total;
}

/** The decision on the batch (thread 0 of one block): energy and swap count on commit; on a rejection with
 * haltOnReject, the sweep halts and the host halves the batch. */
__device__ inline void
RecordDecision(SweepState * state, double dE, int32_t n, int32_t colour, bool haltOnReject)
{
  state->dE = dE;
  state->commit = 0;
  if (n > 0)
  {
    if (dE < 0.0)
    {
      state->commit = 1;
      state->energy += dE;
      state->swaps += static_cast<unsigned long long>(n);
    }
    else if (haltOnReject)
    {
      state->halted = 1;
      state->rejectedColour = colour;
    }
  }
}

/** Commits the batch from grid-stride thread `thread`: new labels, and per touched cell m += dm, r += dS / m
 * (DiscreteCVT::CommitProposals). */
template <unsigned int D>
__device__ inline void
CommitBatch(size_t           thread,
            size_t           threads,
            int32_t          n,
            int32_t          nt,
            const Proposal * proposals,
            const int32_t *  touched,
            const double *   deltaMass,
            const double *   deltaMoment,
            int32_t *        labels,
            uint16_t *       shortLabels,
            double *         mass,
            double *         centroid)
{
  for (size_t i = thread; i < static_cast<size_t>(max(n, nt)); i += threads)
  {
    if (i < static_cast<size_t>(n))
    {
      labels[proposals[i].pixel] = proposals[i].to;
      if (shortLabels)
      {
        shortLabels[proposals[i].pixel] = static_cast<uint16_t>(proposals[i].to);
      }
    }
    if (i < static_cast<size_t>(nt))
    {
      const int32_t c = touched[i];
      const double  m = mass[c] + deltaMass[c];
      for (unsigned int k = 0; k < D; ++k)
      {
        centroid[c * D + k] += deltaMoment[c * D + k] / m;
      }
      mass[c] = m;
    }
  }
}

/** Halving path, one block: dE of the batch and the decision (the host reads it). */
__global__ void
DecideKernel(SweepState * state, int32_t * counters, const double * term, int32_t nCells, int32_t colour)
{
  WaitForPrevious();
  if (state->halted)
  {
    return;
  }
  const double dE = BatchEnergyChange(CurrentSet(state, counters, nCells), term, nCells);
  if (threadIdx.x == 0)
  {
    RecordDecision(state, dE, state->batch[state->parity].numberOfProposals, colour, false);
  }
}

/** Halving path: commits the batch when the host's decision says so. */
template <unsigned int D>
__global__ void
CommitKernel(SweepState *     state,
             const Proposal * proposals,
             const int32_t *  touched,
             const double *   deltaMass,
             const double *   deltaMoment,
             int32_t *        labels,
             uint16_t *       shortLabels,
             double *         mass,
             double *         centroid)
{
  WaitForPrevious();
  if (state->halted || !state->commit)
  {
    return;
  }
  const BatchCounts & batch = state->batch[state->parity];
  CommitBatch<D>(blockIdx.x * static_cast<size_t>(blockDim.x) + threadIdx.x,
                 static_cast<size_t>(gridDim.x) * blockDim.x,
                 batch.numberOfProposals,
                 batch.numberOfTouched,
                 proposals,
                 touched,
                 deltaMass,
                 deltaMoment,
                 labels,
                 shortLabels,
                 mass,
                 centroid);
}

/** Sweep path: every block computes the same dE (BatchEnergyChange) and commits its share of the batch when dE < 0;
 * block 0 records the decision (a rejection halts the sweep) and hands the counter set over to the next batch. */
template <unsigned int D>
__global__ void
DecideCommitKernel(SweepState *     state,
                   int32_t *        counters,
                   const double *   term,
                   int32_t          nCells,
                   int32_t          colour,
                   const Proposal * proposals,
                   const int32_t *  touched,
                   const double *   deltaMass,
                   const double *   deltaMoment,
                   int32_t *        labels,
                   uint16_t *       shortLabels,
                   double *         mass,
                   double *         centroid)
{
  WaitForPrevious();
  if (state->halted) // set by an earlier batch of the sweep (block 0 of this kernel sets it only on a rejection)
  {
    return;
  }
  const int32_t       set = state->parity;
  const BatchCounts & batch = state->batch[set];
  const int32_t       n = batch.numberOfProposals, nt = batch.numberOfTouched;
  const double        dE = BatchEnergyChange(counters + static_cast<size_t>(set) * 2 * nCells, term, nCells);
  if (blockIdx.x == 0 && threadIdx.x == 0)
  {
    RecordDecision(state, dE, n, colour, true);
    state->nextParity = 1 - set;
    state->lastPhase[colour] = state->phase;
    state->phase += 1;
  }
  if (n > 0 && dE < 0.0)
  {
    CommitBatch<D>(blockIdx.x * static_cast<size_t>(blockDim.x) + threadIdx.x,
                   static_cast<size_t>(gridDim.x) * blockDim.x,
                   n,
                   nt,
                   proposals,
                   touched,
                   deltaMass,
                   deltaMoment,
                   labels,
                   shortLabels,
                   mass,
                   centroid);
  }
}

/** Start of a sweep: no swap yet, not halted (the energy carries over). */
__global__ void
BeginSweepKernel(SweepState * state)
{
  WaitForPrevious();
  state->swaps = 0;
  state->halted = 0;
  state->rejectedColour = -1;
  state->sweepStartEnergy = state->energy;
}

/** End of a sweep that was not halted: the sweep and its swaps are counted and Optimize's stopping rule decides
 * (no swap, an energy decrease of at most epsilon x energy, or the sweep limit). In the loop graph it also sets the
 * loop's condition (0 after a halted sweep too: the host halves the batch and finishes the sweep). */
__global__ void
EndSweepKernel(SweepState * state, cudaGraphConditionalHandle loop, int32_t inGraph)
{
  WaitForPrevious();
  int32_t stop = 1;
  if (!state->halted)
  {
    state->sweeps += 1;
    state->totalSwaps += state->swaps;
    const double before = state->sweepStartEnergy;
    stop =
      state->swaps == 0 || before - state->energy <= state->epsilon * before || state->sweeps >= state->maximumSweeps;
    state->stop = stop;
  }
  if (inGraph)
  {
    cudaGraphSetConditional(loop, stop ? 0u : 1u);
  }
}

/** The 16-bit copy of labels below 65536. */
__global__ void
ShortLabelsKernel(const int32_t * labels, int32_t n, uint16_t * shortLabels)
{
  for (int32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x)
  {
    shortLabels[i] = static_cast<uint16_t>(labels[i]);
  }
}

__global__ void
IotaKernel(uint32_t * values, int32_t n)
{
  for (int32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x)
  {
    values[i] = static_cast<uint32_t>(i);
  }
}

/** Smallest pixel whose label is outside [0, nCells). */
__global__ void
ValidateKernel(const int32_t * labels, int32_t n, int32_t nCells, StatisticsReport * report)
{
  for (int32_t p = blockIdx.x * blockDim.x + threadIdx.x; p < n; p += gridDim.x * blockDim.x)
  {
    const int32_t l = labels[p];
    if (l < 0 || l >= nCells)
    {
      atomicMin(&report->badPixel, static_cast<unsigned long long>(p));
    }
  }
}

/** Each cell's range [start, end) in the pixels sorted by label (an empty cell keeps [0, 0)). */
__global__ void
CellRangeKernel(const uint32_t * sortedLabels, int32_t n, int32_t * start, int32_t * end)
{
  for (int32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x)
  {
    const uint32_t l = sortedLabels[i];
    if (i == 0 || sortedLabels[i - 1] != l)
    {
      start[l] = i;
    }
    if (i + 1 == n || sortedLabels[i + 1] != l)
    {
      end[l] = i + 1;
    }
  }
}

/** One warp per cell: mass and centroid summed over the cell's pixels in pixel order, the order of
 * DiscreteCVT::RecomputeStatistics. The lanes load the pixels of StatisticsChunks x 32 at once (all their loads in
 * flight together, the next group's pixel ids while this group is summed) and store their terms (w, w x) in shared
 * memory; lane k (k <= D) then adds component k of the terms in order, so the sums are the sequential ones. The time
 * is that of the largest cell, a chain of dependent loads and additions: one group per 32 pixels kept each warp
 * waiting on every load (a 20 000-pixel cell, 625 round trips). (Broadcasting every term to all lanes by shuffles gave
 * the same sums with D + 1 shuffles per term, which bounded the kernel.) */
constexpr int StatisticsChunks = 4;

template <unsigned int D>
__global__ void
CellStatisticsKernel(GridParams         g,
                     const uint32_t *   pixels,
                     const int32_t *    start,
                     const int32_t *    stop,
                     const float *      density,
                     int32_t            nCells,
                     double *           mass,
                     double *           centroid,
                     StatisticsReport * report)
{
  constexpr unsigned int all = 0xffffffffu;
  constexpr int32_t      G = StatisticsChunks, span = 32 * G;
  // a row of span + 1: the D + 1 summing lanes read distinct banks
  __shared__ double terms[Threads / 32][D + 1][span + 1];
  const int32_t     lane = static_cast<int32_t>(threadIdx.x & 31u);
  double(*const term)[span + 1] = terms[threadIdx.x / 32];
  const int32_t warps = static_cast<int32_t>(gridDim.x * blockDim.x / 32);
  for (int32_t c = static_cast<int32_t>((blockIdx.x * blockDim.x + threadIdx.x) / 32); c < nCells; c += warps)
  {
    double        sum = 0.0; // lane 0: the mass; lane 1 + k: the first moment along axis k
    const int32_t end = stop[c];
    int32_t       base = start[c];
    uint32_t      p[G];
    for (int32_t q = 0; q < G; ++q)
    {
      const int32_t i = base + q * 32 + lane;
      p[q] = i < end ? pixels[i] : 0u;
    }
    for (; base < end; base += span)
    {
      float wf[G];
      for (int32_t q = 0; q < G; ++q)
      {
        wf[q] = base + q * 32 + lane < end ? density[p[q]] : 0.0f;
      }
      for (int32_t q = 0; q < G; ++q)
      {
        int32_t idx[D];
        double  x[D];
        IndexOf<D>(g, static_cast<int32_t>(p[q]), idx);
        PositionOf<D>(g, idx, x);
        const bool inside = base + q * 32 + lane < end;
        term[0][q * 32 + lane] = inside ? static_cast<double>(wf[q]) : 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          term[1 + k][q * 32 + lane] = inside ? wf[q] * x[k] : 0.0;
        }
      }
      // the next group's pixel ids, loaded while this group is summed
      for (int32_t q = 0; q < G; ++q)
      {
        const int32_t i = base + span + q * 32 + lane;
        p[q] = i < end ? pixels[i] : 0u;
      }
      __syncwarp();
      if (lane <= static_cast<int32_t>(D))
      {
        const int32_t n = min(span, end - base);
        for (int32_t j = 0; j < n; ++j)
        {
          sum += term[lane][j];
        }
      }
      __syncwarp();
    }
    const double m = __shfl_sync(all, sum, 0);
    double       s[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      s[k] = __shfl_sync(all, sum, 1 + k);
    }
    if (lane == 0)
    {
      if (!(m > 0.0))
      {
        atomicMin(&report->badCell, static_cast<unsigned long long>(c));
      }
      mass[c] = m;
      for (unsigned int k = 0; k < D; ++k)
      {
        centroid[c * D + k] = s[k] / m;
      }
    }
  }
}

/** The blocks of the contraction's start (DiscreteCVT::ContractionInitialize): blockSize pixels per axis, nb per axis
 * (axis 0 fastest), the last ones cut at the grid's end. */
struct BlockGrid
{
  int32_t blockSize;
  int32_t nb[3];
  int32_t numberOfBlocks;
};

/** One thread per block: its mass and first moments summed over its pixels in pixel order, as the CPU sums them (the
 * same products and additions in the same order), then its centroid. */
template <unsigned int D>
__global__ void
BlockSumsKernel(GridParams g, BlockGrid bg, const float * density, double * mass, double * centroid)
{
  for (int32_t b = blockIdx.x * blockDim.x + threadIdx.x; b < bg.numberOfBlocks; b += gridDim.x * blockDim.x)
  {
    int32_t lo[3] = { 0, 0, 0 }, hi[3] = { 1, 1, 1 };
    int32_t rest = b;
    for (unsigned int k = 0; k < D; ++k)
    {
      lo[k] = (rest % bg.nb[k]) * bg.blockSize;
      rest /= bg.nb[k];
      hi[k] = min(g.size[k], lo[k] + bg.blockSize);
    }
    double m = 0.0, moment[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      moment[k] = 0.0;
    }
    for (int32_t z = lo[2]; z < hi[2]; ++z)
    {
      for (int32_t y = lo[1]; y < hi[1]; ++y)
      {
        const int32_t row = y * g.stride[1] + (D == 3 ? z * g.stride[2] : 0);
        double        x[D];
        x[1] = static_cast<double>(y) * g.spacing[1];
        if (D == 3)
        {
          x[D - 1] = static_cast<double>(z) * g.spacing[D - 1];
        }
        AddRowToBlockSums<D>(density + row, lo[0], hi[0], g.spacing[0], x, m, moment);
      }
    }
    mass[b] = m;
    for (unsigned int k = 0; k < D; ++k)
    {
      centroid[b * D + k] = moment[k] / m;
    }
  }
}

/** Every pixel takes its block's label. */
template <unsigned int D>
__global__ void
BlockLabelsKernel(GridParams g, BlockGrid bg, const int32_t * blockLabel, int32_t * labels)
{
  for (int32_t p = blockIdx.x * blockDim.x + threadIdx.x; p < g.numberOfPixels; p += gridDim.x * blockDim.x)
  {
    int32_t idx[D];
    IndexOf<D>(g, p, idx);
    int32_t b = 0, stride = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      b += (idx[k] / bg.blockSize) * stride;
      stride *= bg.nb[k];
    }
    labels[p] = blockLabel[b];
  }
}

/** Energy, paper Eq. 10: fixed grid of EnergyBlocks blocks, each a partial sum (deterministic shape). */
template <unsigned int D>
__global__ void
EnergyPartialKernel(GridParams      g,
                    const int32_t * labels,
                    const float *   density,
                    const double *  centroid,
                    double *        partial)
{
  double sum = 0.0;
  for (int32_t p = blockIdx.x * blockDim.x + threadIdx.x; p < g.numberOfPixels; p += gridDim.x * blockDim.x)
  {
    int32_t idx[D];
    double  x[D];
    IndexOf<D>(g, p, idx);
    PositionOf<D>(g, idx, x);
    const double * r = &centroid[labels[p] * D];
    double         d2 = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      d2 += (x[k] - r[k]) * (x[k] - r[k]);
    }
    sum += density[p] * d2;
  }
  using Reduce = cub::BlockReduce<double, Threads>;
  __shared__ typename Reduce::TempStorage storage;
  const double                            total = Reduce(storage).Sum(sum);
  if (threadIdx.x == 0)
  {
    partial[blockIdx.x] = total;
  }
}

__global__ void
EnergyFinalKernel(const double * partial, int32_t n, double * energy)
{
  double sum = 0.0;
  for (int32_t i = threadIdx.x; i < n; i += blockDim.x)
  {
    sum += partial[i];
  }
  using Reduce = cub::BlockReduce<double, Threads>;
  __shared__ typename Reduce::TempStorage storage;
  const double                            total = Reduce(storage).Sum(sum);
  if (threadIdx.x == 0)
  {
    *energy = total;
  }
}

} // namespace

struct CVTSwapOptimizer::Impl
{
  unsigned int dimension{ 0 };
  GridParams   grid{};
  size_t       numberOfPixels{ 0 };
  ColourParams colours[8]{};
  unsigned int numberOfColours{ 0 };
  int32_t      maxColourCount{ 0 };
  int          strideBlocks{ 1 };
  int          multiProcessors{ 1 };
  double       tolerance{ 0.0 };
  // one non-blocking stream; a borrowed device input must be complete when it is passed
  cudaStream_t stream{ nullptr };
  SweepState * hostState{ nullptr }; // pinned: the per-sweep read-back

  DeviceBuffer<float>    ownDensity;
  const float *          density{ nullptr };
  DeviceBuffer<int32_t>  labels;
  DeviceBuffer<uint16_t> shortLabels; // 16-bit copy read by Propose when every label fits (useShortLabels)
  bool                   useShortLabels{ false };
  bool                   shortLabelsAllowed{ true };
  bool                   hasLabels{ false };
  DeviceBuffer<uint32_t> iota, sortedKeys, sortedPixels;
  size_t                 nCells{ 0 };
  DeviceBuffer<double>   mass, centroid, deltaMass, deltaMoment, term, partial;
  DeviceBuffer<int32_t>  counters, segment, touched, entries, sortedEntries, cellStart, cellEnd;
  DeviceBuffer<int32_t>  cellStamp; // per cell: the last batch (SweepState::phase) it took part in
  DeviceBuffer<Proposal> proposals;
  DeviceBuffer<uint32_t> entryKeys;
  // the sweeps' per-cell slots (CellSlots): slotCapacity entries per cell, fewer where the cells are many
  DeviceBuffer<int32_t>          slotEntries, slotSorted, slotOverflow;
  DeviceBuffer<uint32_t>         slotKeys;
  unsigned int                   requestedSlots{ std::numeric_limits<unsigned int>::max() };
  int32_t                        slotCapacity{ 0 };
  unsigned int                   pixelsPerThread{ 0 }; // ProposeKernel's K; 0: chosen by the colour's size
  DeviceBuffer<SweepState>       state;
  DeviceBuffer<StatisticsReport> report;
  DeviceBuffer<uint8_t>          temp;
  double                         energy{ 0.0 };

  // one whole sweep (all colours) as a CUDA graph, replayed every sweep; rebuilt when what it captured changes
  cudaGraphExec_t sweepGraph{ nullptr };
  const void *    graphKey[8]{};
  bool            graphUnavailable{ false };
  // all the sweeps of an Optimize call as one graph: a conditional while node around a sweep and EndSweepKernel,
  // so the host does not wait for every sweep (falls back to sweepGraph where conditional nodes are unavailable)
  cudaGraphExec_t loopGraph{ nullptr };
  bool            loopUnavailable{ false };
  bool            deviceLoop{ true };

  Impl() = default;
  Impl(const Impl &) = delete;
  Impl &
  operator=(const Impl &) = delete;
  ~Impl()
  {
    DropGraph();
    if (hostState)
    {
      cudaFreeHost(hostState);
    }
    if (stream)
    {
      cudaStreamDestroy(stream);
    }
  }

  void
  DropGraph() noexcept
  {
    if (sweepGraph)
    {
      cudaGraphExecDestroy(sweepGraph);
      sweepGraph = nullptr;
    }
    if (loopGraph)
    {
      cudaGraphExecDestroy(loopGraph);
      loopGraph = nullptr;
    }
  }

  void
  RequireGrid() const
  {
    if (dimension != 2 && dimension != 3)
    {
      throw CudaError("CVTSwapOptimizer: SetGrid must be called first (dimension 2 or 3)");
    }
  }

  /** New labels for the whole grid, written on the stream by fill; then the statistics (Recompute). The labels count
   * as absent from the start until Recompute has accepted them. */
  template <typename TFill>
  void
  ReplaceLabels(size_t numberOfCells, TFill && fill)
  {
    hasLabels = false;
    fill();
    Check(cudaStreamSynchronize(stream), "labels (synchronise)");
    hasLabels = true;
    try
    {
      Recompute(numberOfCells);
    }
    catch (...)
    {
      hasLabels = false; // the new labels are invalid
      throw;
    }
  }

  BlockGrid
  BlockGridOf(unsigned int blockSize) const
  {
    RequireGrid();
    if (blockSize < 1)
    {
      throw CudaError("CVTSwapOptimizer: the block size must be at least 1");
    }
    BlockGrid bg{};
    bg.blockSize = static_cast<int32_t>(blockSize);
    size_t n = 1;
    for (unsigned int k = 0; k < 3; ++k)
    {
      bg.nb[k] = k < dimension ? (grid.size[k] + bg.blockSize - 1) / bg.blockSize : 1;
      n *= static_cast<size_t>(bg.nb[k]);
    }
    bg.numberOfBlocks = static_cast<int32_t>(n);
    return bg;
  }

  void
  RequireCells() const
  {
    RequireGrid();
    if (!density)
    {
      throw CudaError("CVTSwapOptimizer: no density (SetDensity)");
    }
    if (!hasLabels || nCells == 0)
    {
      throw CudaError("CVTSwapOptimizer: no labels (SetLabels)");
    }
  }

  void
  ReserveTemp(size_t bytes)
  {
    temp.Reserve(std::max<size_t>(bytes, 1));
  }

  void
  Recompute(size_t numberOfCells)
  {
    if (dimension == 2)
    {
      RecomputeStatistics<2>(numberOfCells);
    }
    else
    {
      RecomputeStatistics<3>(numberOfCells);
    }
  }

  /** Masses and centroids summed in pixel order (stable sort by label, one warp per cell), then the energy. */
  template <unsigned int D>
  void
  RecomputeStatistics(size_t numberOfCells)
  {
    if (numberOfCells < 1 || numberOfCells > numberOfPixels)
    {
      std::ostringstream os;
      os << "CVTSwapOptimizer: cannot have " << numberOfCells << " cells on " << numberOfPixels << " pixels";
      throw CudaError(os.str());
    }
    const int32_t n = static_cast<int32_t>(numberOfPixels);
    const int32_t cells = static_cast<int32_t>(numberOfCells);
    if (numberOfCells != nCells)
    {
      nCells = numberOfCells;
      mass.Resize(nCells);
      centroid.Resize(nCells * D);
      deltaMass.Resize(nCells);
      deltaMoment.Resize(nCells * D);
      term.Resize(nCells);
      term.Zero(stream);           // BatchEnergyChange reads every cell's term
      counters.Resize(4 * nCells); // two counter sets of (count, fill) per cell
      segment.Resize(nCells);
      touched.Resize(nCells);
      cellStart.Resize(nCells);
      cellEnd.Resize(nCells);
      cellStamp.Resize(nCells);
    }
    // the slots: requestedSlots per cell, at most as many in all as a batch can have entries (the size of the
    // allocation pass's entry arrays; for 3000 cells on 256 x 256 x 132, 720 per cell)
    const size_t capacity = std::min<size_t>(requestedSlots, std::max<size_t>(1, entries.Size() / nCells));
    slotCapacity = static_cast<int32_t>(capacity);
    slotEntries.Resize(capacity * nCells);
    slotKeys.Resize(capacity * nCells);
    slotSorted.Resize(capacity * nCells);
    slotOverflow.Resize(capacity > 0 ? entries.Size() : 0); // at most every entry of a batch
    report.Resize(1);
    Check(cudaMemsetAsync(report.Data(), 0xFF, sizeof(StatisticsReport), stream), "cudaMemset");
    ValidateKernel<<<strideBlocks, Threads, 0, stream>>>(labels.Data(), n, cells, report.Data());
    CheckLaunch("ValidateKernel");
    StatisticsReport r{};
    report.Download(&r, 1, stream);
    if (r.badPixel != std::numeric_limits<unsigned long long>::max())
    {
      int32_t l = 0;
      Check(cudaMemcpyAsync(&l, labels.Data() + r.badPixel, sizeof(l), cudaMemcpyDeviceToHost, stream), "download");
      Check(cudaStreamSynchronize(stream), "download (synchronise)");
      std::ostringstream os;
      os << "CVTSwapOptimizer: label " << l << " at pixel " << r.badPixel << " is outside [0, " << numberOfCells << ")";
      throw CudaError(os.str());
    }
    // the 16-bit copy that Propose reads (half the bytes of the labels: an L2-resident working set for larger
    // images), kept by the commits
    useShortLabels = shortLabelsAllowed && numberOfCells <= size_t{ 65536 };
    if (useShortLabels)
    {
      shortLabels.Resize(numberOfPixels);
      ShortLabelsKernel<<<strideBlocks, Threads, 0, stream>>>(labels.Data(), n, shortLabels.Data());
      CheckLaunch("ShortLabelsKernel");
    }
    int endBit = 1;
    while (endBit < 31 && (size_t{ 1 } << endBit) < numberOfCells)
    {
      ++endBit;
    }
    const auto * keys = reinterpret_cast<const uint32_t *>(labels.Data());
    size_t       sortBytes = 0;
    Check(cub::DeviceRadixSort::SortPairs(
            nullptr, sortBytes, keys, sortedKeys.Data(), iota.Data(), sortedPixels.Data(), n, 0, endBit, stream),
          "cub::DeviceRadixSort::SortPairs");
    ReserveTemp(sortBytes);
    sortBytes = temp.Size();
    Check(cub::DeviceRadixSort::SortPairs(
            temp.Data(), sortBytes, keys, sortedKeys.Data(), iota.Data(), sortedPixels.Data(), n, 0, endBit, stream),
          "cub::DeviceRadixSort::SortPairs");
    cellStart.Zero(stream);
    cellEnd.Zero(stream);
    CellRangeKernel<<<strideBlocks, Threads, 0, stream>>>(sortedKeys.Data(), n, cellStart.Data(), cellEnd.Data());
    CheckLaunch("CellRangeKernel");
    CellStatisticsKernel<D><<<Blocks(nCells * 32, Threads), Threads, 0, stream>>>(grid,
                                                                                  sortedPixels.Data(),
                                                                                  cellStart.Data(),
                                                                                  cellEnd.Data(),
                                                                                  density,
                                                                                  cells,
                                                                                  mass.Data(),
                                                                                  centroid.Data(),
                                                                                  report.Data());
    CheckLaunch("CellStatisticsKernel");
    report.Download(&r, 1, stream);
    if (r.badCell != std::numeric_limits<unsigned long long>::max())
    {
      std::ostringstream os;
      os << "CVTSwapOptimizer: cell " << r.badCell << " is empty or has zero mass";
      throw CudaError(os.str());
    }
    energy = ComputeEnergy<D>();
  }

  template <unsigned int D>
  double
  ComputeEnergy()
  {
    partial.Resize(EnergyBlocks + 1);
    EnergyPartialKernel<D>
      <<<EnergyBlocks, Threads, 0, stream>>>(grid, labels.Data(), density, centroid.Data(), partial.Data());
    CheckLaunch("EnergyPartialKernel");
    EnergyFinalKernel<<<1, Threads, 0, stream>>>(partial.Data(), EnergyBlocks, partial.Data() + EnergyBlocks);
    CheckLaunch("EnergyFinalKernel");
    double e = 0.0;
    Check(cudaMemcpyAsync(&e, partial.Data() + EnergyBlocks, sizeof(e), cudaMemcpyDeviceToHost, stream), "download");
    Check(cudaStreamSynchronize(stream), "download (synchronise)");
    return e;
  }

  /** Propose for one colour: the proposals, their count and the per-cell counts of the batch. */
  template <unsigned int D>
  void
  EnqueuePropose(const ColourParams & cp)
  {
    if (uint16_t * shortCopy = ShortLabels())
    {
      EnqueuePropose<D>(cp, static_cast<const uint16_t *>(shortCopy));
    }
    else
    {
      EnqueuePropose<D>(cp, static_cast<const int32_t *>(labels.Data()));
    }
  }

  /** Propose reading the labels from `labelsToRead` (the labels or their 16-bit copy). */
  template <unsigned int D, typename TLabel>
  void
  EnqueuePropose(const ColourParams & cp, const TLabel * labelsToRead)
  {
    // two pixels per thread when that still gives the device two full rounds of blocks (4 per SM)
    const size_t pixels = static_cast<size_t>(std::max(cp.count, 1));
    const bool two = pixelsPerThread == 0 ? Blocks(pixels, 2 * Threads) >= static_cast<size_t>(2 * 4 * multiProcessors)
                                          : pixelsPerThread == 2;
    LaunchAfter(two ? ProposeKernel<D, TLabel, 2> : ProposeKernel<D, TLabel, 1>,
                Blocks(pixels, two ? 2 * Threads : Threads),
                Threads,
                stream,
                grid,
                cp,
                labelsToRead,
                density,
                mass.Data(),
                centroid.Data(),
                tolerance,
                state.Data(),
                proposals.Data(),
                counters.Data(),
                touched.Data(),
                cellStamp.Data(),
                Slots(),
                static_cast<int32_t>(nCells));
    CheckLaunch("ProposeKernel");
  }

  /** The sweep's slots (CellSlots), or none (capacity 0). */
  CellSlots
  Slots()
  {
    return CellSlots{ slotEntries.Data(), slotKeys.Data(), slotSorted.Data(), slotOverflow.Data(), slotCapacity };
  }

  /** The cells' entries of the counted batch and their sums (Cell; before it Allocate and Scatter unless the entries
   * are in the slots). byPixel: the batch is in no particular order (the sweep's), so the entries are ordered by
   * pixel; otherwise by proposal index (halving, which never uses the slots). */
  template <unsigned int D>
  void
  EnqueueCellSums(bool byPixel, bool inSlots)
  {
    const auto cells = static_cast<int32_t>(nCells);
    if (!inSlots)
    {
      EnqueueAllocation(byPixel);
    }
    LaunchAfter(CellKernel<D>,
                strideBlocks,
                128,
                stream,
                grid,
                state.Data(),
                proposals.Data(),
                density,
                mass.Data(),
                centroid.Data(),
                counters.Data(),
                touched.Data(),
                segment.Data(),
                entries.Data(),
                entryKeys.Data(),
                sortedEntries.Data(),
                deltaMass.Data(),
                deltaMoment.Data(),
                term.Data(),
                inSlots ? Slots() : CellSlots{},
                cells);
    CheckLaunch("CellKernel");
  }

  /** Every touched cell's segment of the batch's entries, and the entries in them (Allocate, Scatter). */
  void
  EnqueueAllocation(bool byPixel)
  {
    const auto cells = static_cast<int32_t>(nCells);
    LaunchAfter(AllocateKernel,
                strideBlocks,
                Threads,
                stream,
                state.Data(),
                counters.Data(),
                touched.Data(),
                segment.Data(),
                cells);
    CheckLaunch("AllocateKernel");
    LaunchAfter(ScatterKernel,
                strideBlocks,
                Threads,
                stream,
                state.Data(),
                proposals.Data(),
                segment.Data(),
                counters.Data(),
                entries.Data(),
                entryKeys.Data(),
                cells,
                byPixel ? 1 : 0);
    CheckLaunch("ScatterKernel");
  }

  /** Halving path: joint change of the batch the host placed in `proposals`, and the decision (not committed). */
  template <unsigned int D>
  void
  EnqueueJointChange(int32_t colour)
  {
    LaunchAfter(CountKernel,
                strideBlocks,
                Threads,
                stream,
                state.Data(),
                proposals.Data(),
                counters.Data(),
                touched.Data(),
                static_cast<int32_t>(nCells));
    CheckLaunch("CountKernel");
    EnqueueCellSums<D>(false, false);
    LaunchAfter(DecideKernel,
                1,
                Threads,
                stream,
                state.Data(),
                counters.Data(),
                term.Data(),
                static_cast<int32_t>(nCells),
                colour);
    CheckLaunch("DecideKernel");
  }

  template <unsigned int D>
  void
  EnqueueCommit()
  {
    LaunchAfter(CommitKernel<D>,
                strideBlocks,
                Threads,
                stream,
                state.Data(),
                proposals.Data(),
                touched.Data(),
                deltaMass.Data(),
                deltaMoment.Data(),
                labels.Data(),
                ShortLabels(),
                mass.Data(),
                centroid.Data());
    CheckLaunch("CommitKernel");
  }

  /** Sweep path: one colour's batch, proposed, summed, decided and committed (or halting the sweep). */
  template <unsigned int D>
  void
  EnqueueBatch(const ColourParams & cp)
  {
    EnqueuePropose<D>(cp);
    EnqueueCellSums<D>(true, slotCapacity > 0);
    LaunchAfter(DecideCommitKernel<D>,
                strideBlocks,
                Threads,
                stream,
                state.Data(),
                counters.Data(),
                term.Data(),
                static_cast<int32_t>(nCells),
                cp.colour,
                proposals.Data(),
                touched.Data(),
                deltaMass.Data(),
                deltaMoment.Data(),
                labels.Data(),
                ShortLabels(),
                mass.Data(),
                centroid.Data());
    CheckLaunch("DecideCommitKernel");
  }

  /** The sub-sweeps of colours first..last of a sweep (from its start when first is 0), then the state's copy to
   * the pinned host copy. */
  template <unsigned int D>
  void
  EnqueueSweep(unsigned int first)
  {
    if (first == 0)
    {
      LaunchAfter(BeginSweepKernel, 1, 1, stream, state.Data());
      CheckLaunch("BeginSweepKernel");
    }
    for (unsigned int c = first; c < numberOfColours; ++c)
    {
      if (colours[c].count == 0)
      {
        continue;
      }
      EnqueueBatch<D>(colours[c]);
    }
  }

  /** End of a sweep: EndSweepKernel (setting the loop graph's condition when `loop` is given), then, outside the
   * loop graph, the state's copy to the pinned host copy. */
  void
  EnqueueEndSweep(const cudaGraphConditionalHandle * loop)
  {
    LaunchAfter(EndSweepKernel, 1, 1, stream, state.Data(), loop ? *loop : cudaGraphConditionalHandle{}, loop ? 1 : 0);
    CheckLaunch("EndSweepKernel");
    if (!loop)
    {
      Check(cudaMemcpyAsync(hostState, state.Data(), sizeof(SweepState), cudaMemcpyDeviceToHost, stream),
            "download state");
    }
  }

  SweepState
  ReadState()
  {
    Check(cudaMemcpyAsync(hostState, state.Data(), sizeof(SweepState), cudaMemcpyDeviceToHost, stream),
          "download state");
    Check(cudaStreamSynchronize(stream), "download state (synchronise)");
    return *hostState;
  }

  void
  WriteInt(int32_t * device, int32_t value)
  {
    Check(cudaMemcpyAsync(device, &value, sizeof(value), cudaMemcpyHostToDevice, stream), "upload");
    Check(cudaStreamSynchronize(stream), "upload (synchronise)"); // value lives on this stack frame
  }

  /** The 16-bit copy of the labels that the sweeps read and keep, or null when the labels do not fit. */
  uint16_t *
  ShortLabels()
  {
    return useShortLabels ? shortLabels.Data() : nullptr;
  }

  /** Drops both graphs when the buffers they captured have changed, and records the current ones. */
  void
  ForgetStaleGraphs()
  {
    const void * key[8] = { density,
                            mass.Data(),
                            temp.Data(),
                            labels.Data(),
                            reinterpret_cast<const void *>(static_cast<uintptr_t>(nCells)),
                            ShortLabels(),
                            slotEntries.Data(),
                            reinterpret_cast<const void *>(static_cast<uintptr_t>(slotCapacity) |
                                                           static_cast<uintptr_t>(pixelsPerThread) << 32) };
    if ((sweepGraph || loopGraph) && !std::equal(key, key + 8, graphKey))
    {
      DropGraph();
    }
    std::copy(key, key + 8, graphKey);
  }

  /** Captures the launches of `enqueue` into `graph` (after `dependency` when not null); false on any failure. */
  template <typename TEnqueue>
  bool
  CaptureInto(cudaGraph_t graph, const cudaGraphNode_t * dependency, TEnqueue && enqueue)
  {
    if (cudaStreamBeginCaptureToGraph(
          stream, graph, dependency, nullptr, dependency ? 1 : 0, cudaStreamCaptureModeRelaxed) != cudaSuccess)
    {
      return false;
    }
    bool ok = true;
    try
    {
      enqueue();
    }
    catch (const CudaError &)
    {
      ok = false;
    }
    cudaGraph_t captured = nullptr;
    return cudaStreamEndCapture(stream, &captured) == cudaSuccess && ok && captured == graph;
  }

  /** Instantiates `graph` into `exec` and destroys it; on failure `unavailable` is set (and the error cleared). */
  static void
  Instantiate(cudaGraph_t graph, bool ok, cudaGraphExec_t & exec, bool & unavailable)
  {
    ok = ok && cudaGraphInstantiate(&exec, graph, 0) == cudaSuccess;
    if (!ok)
    {
      exec = nullptr;
      unavailable = true;
      cudaGetLastError();
    }
    if (graph)
    {
      cudaGraphDestroy(graph);
    }
  }

  /** A whole sweep from its start and its end: the graph when it can be had (captured once, replayed), else direct
   * launches. */
  template <unsigned int D>
  void
  LaunchSweep()
  {
    ForgetStaleGraphs();
    if (!sweepGraph && !graphUnavailable)
    {
      Check(cudaStreamSynchronize(stream), "cudaStreamSynchronize");
      cudaGraph_t graph = nullptr;
      const bool  created = cudaGraphCreate(&graph, 0) == cudaSuccess;
      Instantiate(graph,
                  created && CaptureInto(graph,
                                         nullptr,
                                         [&] {
                                           EnqueueSweep<D>(0);
                                           EnqueueEndSweep(nullptr);
                                         }),
                  sweepGraph,
                  graphUnavailable);
    }
    if (sweepGraph)
    {
      Check(cudaGraphLaunch(sweepGraph, stream), "cudaGraphLaunch");
    }
    else
    {
      EnqueueSweep<D>(0);
      EnqueueEndSweep(nullptr);
    }
  }

  /** The rejected batch of colour cp, halved on the host like DiscreteCVT::CommitProposals (the first rejection
   * is already counted). */
  template <unsigned int D>
  void
  HalveBatch(const ColourParams & cp, CVTSwapResult & result)
  {
    WriteInt(&state.Data()->halted, 0);
    // the rejected batch is still in place: its proposals (in no particular order) and its counter set
    const int32_t set = ReadState().parity;
    size_t        count = static_cast<size_t>(hostState->batch[set].numberOfProposals);
    if (count <= 1)
    {
      return;
    }
    std::vector<Proposal> host(count);
    proposals.Download(host.data(), count, stream);
    std::sort(host.begin(), host.end(), [](const Proposal & a, const Proposal & b) {
      return a.gain != b.gain ? a.gain > b.gain : a.pixel < b.pixel;
    });
    Check(cudaMemcpyAsync(proposals.Data(), host.data(), count * sizeof(Proposal), cudaMemcpyHostToDevice, stream),
          "upload");
    for (;;)
    {
      count /= 2;
      WriteInt(&state.Data()->batch[set].numberOfProposals, static_cast<int32_t>(count));
      ResetBatchKernel<<<strideBlocks, Threads, 0, stream>>>(
        state.Data(), counters.Data(), static_cast<int32_t>(nCells));
      CheckLaunch("ResetBatchKernel");
      EnqueueJointChange<D>(cp.colour);
      if (ReadState().commit)
      {
        EnqueueCommit<D>();
        return;
      }
      ++result.rejectedBatches;
      if (count == 1)
      {
        return;
      }
    }
  }

  /** The loop graph for the current buffers, captured on first use: while (condition) { sweep; EndSweepKernel },
   * then the state's download. False where it cannot be had. */
  template <unsigned int D>
  bool
  PrepareLoopGraph()
  {
    ForgetStaleGraphs();
    if (loopGraph || loopUnavailable)
    {
      return loopGraph != nullptr;
    }
    Check(cudaStreamSynchronize(stream), "cudaStreamSynchronize");
    cudaGraph_t                graph = nullptr;
    bool                       ok = cudaGraphCreate(&graph, 0) == cudaSuccess;
    cudaGraphConditionalHandle handle{};
    cudaGraphNode_t            loopNode = nullptr;
    cudaGraphNodeParams        params{};
    ok = ok && cudaGraphConditionalHandleCreate(&handle, graph, 1, cudaGraphCondAssignDefault) == cudaSuccess;
    if (ok)
    {
      params.type = cudaGraphNodeTypeConditional;
      params.conditional.handle = handle;
      params.conditional.type = cudaGraphCondTypeWhile;
      params.conditional.size = 1;
      ok = cudaGraphAddNode(&loopNode, graph, nullptr, nullptr, 0, &params) == cudaSuccess;
    }
    ok = ok && CaptureInto(params.conditional.phGraph_out[0], nullptr, [&] {
           EnqueueSweep<D>(0);
           EnqueueEndSweep(&handle);
         });
    ok = ok && CaptureInto(graph, &loopNode, [&] {
           Check(cudaMemcpyAsync(hostState, state.Data(), sizeof(SweepState), cudaMemcpyDeviceToHost, stream),
                 "download state");
         });
    Instantiate(graph, ok, loopGraph, loopUnavailable);
    return loopGraph != nullptr;
  }

  template <unsigned int D>
  void
  Optimize(double epsilon, size_t maximumNumberOfSweeps, CVTSwapResult & result)
  {
    RequireCells();
    result = CVTSwapResult{};
    result.energyBefore = energy;
    result.energyAfter = energy;
    if (maximumNumberOfSweeps == 0)
    {
      return;
    }
    *hostState = SweepState{};
    hostState->energy = energy;
    hostState->rejectedColour = -1;
    hostState->phase = 1; // every cell stamped 0 >= every colour's lastPhase 0: the first sweep evaluates all
    hostState->epsilon = epsilon;
    hostState->maximumSweeps =
      static_cast<int32_t>(std::min<size_t>(maximumNumberOfSweeps, std::numeric_limits<int32_t>::max()));
    Check(cudaMemcpyAsync(state.Data(), hostState, sizeof(SweepState), cudaMemcpyHostToDevice, stream), "upload state");
    counters.Zero(stream); // both counter sets start empty
    cellStamp.Zero(stream);
    const bool loop = deviceLoop && PrepareLoopGraph<D>();
    for (;;)
    {
      // the sweeps until the stopping rule holds (EndSweepKernel) or one is halted: on the device in the loop graph,
      // otherwise one sweep per launch
      if (loop)
      {
        Check(cudaGraphLaunch(loopGraph, stream), "cudaGraphLaunch");
      }
      else
      {
        LaunchSweep<D>();
      }
      Check(cudaStreamSynchronize(stream), "sweeps (synchronise)");
      while (hostState->halted)
      {
        const SweepState s = *hostState;
        ++result.rejectedBatches;
        HalveBatch<D>(colours[s.rejectedColour], result);
        EnqueueSweep<D>(static_cast<unsigned int>(s.rejectedColour) + 1); // the rest of the sweep
        EnqueueEndSweep(nullptr);
        Check(cudaStreamSynchronize(stream), "sweep (synchronise)");
      }
      if (hostState->stop)
      {
        break;
      }
    }
    energy = hostState->energy;
    result.sweeps = static_cast<size_t>(hostState->sweeps);
    result.swaps = static_cast<size_t>(hostState->totalSwaps);
    result.slotOverflows = static_cast<size_t>(hostState->slotOverflows);
    result.energyAfter = energy;
  }
};

CVTSwapOptimizer::CVTSwapOptimizer()
  : m_Impl(new Impl)
{
}

CVTSwapOptimizer::~CVTSwapOptimizer() = default;

Status
CVTSwapOptimizer::SetGrid(unsigned int dimension, const size_t * size, const double * spacing)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    m.dimension = 0;
    m.hasLabels = false;
    m.density = nullptr;
    m.nCells = 0;
    m.DropGraph();
    if (dimension != 2 && dimension != 3)
    {
      throw CudaError("CVTSwapOptimizer: the dimension must be 2 or 3");
    }
    size_t n = 1;
    for (unsigned int k = 0; k < dimension; ++k)
    {
      if (size[k] < 1 || !(spacing[k] > 0.0))
      {
        throw CudaError("CVTSwapOptimizer: every size must be >= 1 and every spacing > 0");
      }
      n *= size[k];
      if (n >= (size_t{ 1 } << 31))
      {
        throw CudaError("CVTSwapOptimizer: the grid must have fewer than 2^31 pixels");
      }
    }
    GridParams g{};
    int32_t    stride = 1;
    for (unsigned int k = 0; k < 3; ++k)
    {
      g.size[k] = k < dimension ? static_cast<int32_t>(size[k]) : 1;
      g.spacing[k] = k < dimension ? spacing[k] : 1.0;
      g.stride[k] = stride;
      stride *= g.size[k];
    }
    g.numberOfPixels = static_cast<int32_t>(n);
    m.grid = g;
    m.numberOfPixels = n;
    m.numberOfColours = 1u << dimension;
    m.maxColourCount = 0;
    for (unsigned int c = 0; c < m.numberOfColours; ++c)
    {
      ColourParams cp{};
      cp.colour = static_cast<int32_t>(c);
      cp.count = 1;
      for (unsigned int k = 0; k < 3; ++k)
      {
        cp.origin[k] = k < dimension ? static_cast<int32_t>((c >> k) & 1u) : 0;
        cp.sub[k] = g.size[k] > cp.origin[k] ? (g.size[k] - cp.origin[k] + 1) / 2 : 0;
        cp.count *= k < dimension ? cp.sub[k] : 1;
      }
      for (unsigned int k = 0; k < dimension; ++k)
      {
        // exact for every quotient the kernels take (rest < count) when count x sub < 2^32
        const uint64_t sub = static_cast<uint64_t>(std::max(cp.sub[k], 1));
        cp.reciprocal[k] =
          static_cast<uint64_t>(cp.count) * sub < (uint64_t{ 1 } << 32) ? ((uint64_t{ 1 } << 32) + sub - 1) / sub : 0;
      }
      m.colours[c] = cp;
      m.maxColourCount = std::max(m.maxColourCount, cp.count);
    }
    int device = 0, sms = 1;
    Check(cudaGetDevice(&device), "cudaGetDevice");
    Check(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device), "cudaDeviceGetAttribute");
    m.strideBlocks = 2 * sms; // grid-stride kernels: their work is known on the device only
    m.multiProcessors = sms;
    if (!m.stream)
    {
      Check(cudaStreamCreateWithFlags(&m.stream, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
    }
    if (!m.hostState)
    {
      void * pinned = nullptr;
      Check(cudaMallocHost(&pinned, sizeof(SweepState)), "cudaMallocHost");
      m.hostState = static_cast<SweepState *>(pinned);
    }
    // DiscreteCVT's rounding guard: 1e-9 x the smallest squared pixel size
    double h2 = g.spacing[0] * g.spacing[0];
    for (unsigned int k = 1; k < dimension; ++k)
    {
      h2 = std::min(h2, g.spacing[k] * g.spacing[k]);
    }
    m.tolerance = 1e-9 * h2;
    m.labels.Resize(n);
    m.iota.Resize(n);
    m.sortedKeys.Resize(n);
    m.sortedPixels.Resize(n);
    const size_t slotsNeeded = static_cast<size_t>(std::max(m.maxColourCount, 1));
    m.proposals.Resize(slotsNeeded);
    m.entries.Resize(2 * slotsNeeded);
    m.entryKeys.Resize(2 * slotsNeeded);
    m.sortedEntries.Resize(2 * slotsNeeded);
    m.state.Resize(1);
    IotaKernel<<<m.strideBlocks, Threads, 0, m.stream>>>(m.iota.Data(), static_cast<int32_t>(n));
    CheckLaunch("IotaKernel");
    Check(cudaStreamSynchronize(m.stream), "SetGrid (synchronise)");
    m.dimension = dimension;
  });
}

Status
CVTSwapOptimizer::SetDensity(const float * density, bool devicePointer)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    m.RequireGrid();
    if (!density)
    {
      throw CudaError("CVTSwapOptimizer: null density");
    }
    if (devicePointer)
    {
      m.ownDensity.Free();
      m.density = density;
    }
    else
    {
      m.ownDensity.Upload(density, m.numberOfPixels, m.stream);
      Check(cudaStreamSynchronize(m.stream), "upload (synchronise)");
      m.density = m.ownDensity.Data();
    }
  });
}

Status
CVTSwapOptimizer::SetLabels(const int32_t * labels, size_t numberOfCells, bool devicePointer)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    m.RequireGrid();
    if (!labels)
    {
      throw CudaError("CVTSwapOptimizer: null labels");
    }
    m.ReplaceLabels(numberOfCells, [&] {
      Check(cudaMemcpyAsync(m.labels.Data(),
                            labels,
                            m.numberOfPixels * sizeof(int32_t),
                            devicePointer ? cudaMemcpyDeviceToDevice : cudaMemcpyHostToDevice,
                            m.stream),
            "upload labels");
    });
  });
}

Status
CVTSwapOptimizer::KeepLabels(size_t numberOfCells)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    m.RequireGrid();
    if (!m.hasLabels)
    {
      throw CudaError("CVTSwapOptimizer: no labels on the device (SetLabels)");
    }
    if (!m.density)
    {
      throw CudaError("CVTSwapOptimizer: no density (SetDensity)");
    }
    m.Recompute(numberOfCells);
  });
}

Status
CVTSwapOptimizer::ContractionBlockSums(unsigned int          blockSize,
                                       std::vector<double> & masses,
                                       std::vector<double> & centroids)
{
  return Guard([&] {
    Impl &          m = *m_Impl;
    const BlockGrid bg = m.BlockGridOf(blockSize);
    if (!m.density)
    {
      throw CudaError("CVTSwapOptimizer: no density (SetDensity)");
    }
    const size_t         n = static_cast<size_t>(bg.numberOfBlocks);
    DeviceBuffer<double> mass(n), centroid(n * m.dimension);
    const unsigned int   blocks = Blocks(n, Threads);
    if (m.dimension == 2)
    {
      BlockSumsKernel<2><<<blocks, Threads, 0, m.stream>>>(m.grid, bg, m.density, mass.Data(), centroid.Data());
    }
    else
    {
      BlockSumsKernel<3><<<blocks, Threads, 0, m.stream>>>(m.grid, bg, m.density, mass.Data(), centroid.Data());
    }
    CheckLaunch("BlockSumsKernel");
    masses.resize(n);
    centroids.resize(n * m.dimension);
    mass.Download(masses.data(), n, m.stream);
    centroid.Download(centroids.data(), n * m.dimension, m.stream);
    Check(cudaStreamSynchronize(m.stream), "block sums (synchronise)");
  });
}

Status
CVTSwapOptimizer::SetBlockLabels(unsigned int blockSize, const int32_t * blockLabels, size_t numberOfCells)
{
  return Guard([&] {
    Impl &          m = *m_Impl;
    const BlockGrid bg = m.BlockGridOf(blockSize);
    if (!blockLabels)
    {
      throw CudaError("CVTSwapOptimizer: null block labels");
    }
    DeviceBuffer<int32_t> blockLabel(static_cast<size_t>(bg.numberOfBlocks));
    blockLabel.Upload(blockLabels, static_cast<size_t>(bg.numberOfBlocks), m.stream);
    m.ReplaceLabels(numberOfCells, [&] {
      if (m.dimension == 2)
      {
        BlockLabelsKernel<2><<<m.strideBlocks, Threads, 0, m.stream>>>(m.grid, bg, blockLabel.Data(), m.labels.Data());
      }
      else
      {
        BlockLabelsKernel<3><<<m.strideBlocks, Threads, 0, m.stream>>>(m.grid, bg, blockLabel.Data(), m.labels.Data());
      }
      CheckLaunch("BlockLabelsKernel");
    });
  });
}

Status
CVTSwapOptimizer::Optimize(double epsilon, size_t maximumNumberOfSweeps, CVTSwapResult & result)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    m.RequireCells();
    if (m.dimension == 2)
    {
      m.Optimize<2>(epsilon, maximumNumberOfSweeps, result);
    }
    else
    {
      m.Optimize<3>(epsilon, maximumNumberOfSweeps, result);
    }
  });
}

Status
CVTSwapOptimizer::DownloadLabels(int32_t * host) const
{
  return Guard([&] {
    const Impl & m = *m_Impl;
    m.RequireGrid();
    if (!m.hasLabels)
    {
      throw CudaError("CVTSwapOptimizer: no labels on the device (SetLabels)");
    }
    m.labels.Download(host, m.numberOfPixels, m.stream);
  });
}

const int32_t *
CVTSwapOptimizer::DeviceLabels() const
{
  return m_Impl->dimension ? m_Impl->labels.Data() : nullptr;
}

Status
CVTSwapOptimizer::GetCells(std::vector<double> & masses, std::vector<double> & centroids) const
{
  return Guard([&] {
    const Impl & m = *m_Impl;
    m.RequireCells();
    masses.resize(m.nCells);
    centroids.resize(m.nCells * m.dimension);
    m.mass.Download(masses.data(), m.nCells, m.stream);
    m.centroid.Download(centroids.data(), m.nCells * m.dimension, m.stream);
  });
}

void
CVTSwapOptimizer::SetDeviceLoop(bool enabled)
{
  m_Impl->deviceLoop = enabled;
}

void
CVTSwapOptimizer::SetShortLabels(bool enabled)
{
  m_Impl->shortLabelsAllowed = enabled;
}

void
CVTSwapOptimizer::SetCellSlots(unsigned int capacity)
{
  m_Impl->requestedSlots = capacity;
}

void
CVTSwapOptimizer::SetPixelsPerProposalThread(unsigned int pixels)
{
  if (pixels > 2)
  {
    throw std::invalid_argument("CVTSwapOptimizer::SetPixelsPerProposalThread: 0 (automatic), 1 or 2");
  }
  m_Impl->pixelsPerThread = pixels;
}

size_t
CVTSwapOptimizer::AllocatedBytes() const
{
  const Impl & m = *m_Impl;
  return BytesOf(m.ownDensity,
                 m.labels,
                 m.shortLabels,
                 m.iota,
                 m.sortedKeys,
                 m.sortedPixels,
                 m.mass,
                 m.centroid,
                 m.deltaMass,
                 m.deltaMoment,
                 m.term,
                 m.partial,
                 m.counters,
                 m.segment,
                 m.touched,
                 m.entries,
                 m.sortedEntries,
                 m.slotEntries,
                 m.slotKeys,
                 m.slotSorted,
                 m.slotOverflow,
                 m.cellStart,
                 m.cellEnd,
                 m.cellStamp,
                 m.proposals,
                 m.entryKeys,
                 m.state,
                 m.report,
                 m.temp);
}

double
CVTSwapOptimizer::Energy() const
{
  return m_Impl->energy;
}

size_t
CVTSwapOptimizer::NumberOfCells() const
{
  return m_Impl->hasLabels ? m_Impl->nCells : 0;
}
} // namespace cuda
} // namespace dmr
} // namespace itk
