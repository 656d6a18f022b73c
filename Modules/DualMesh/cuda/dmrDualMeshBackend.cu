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
// Label summary of the dual mesh stage on the device (see dmrDualMeshBackend.h and dmrLabelSummary.h).
//
// One call: zero the statistics, then
// 1. BulkKernel: every thread walks a run of kRun voxels along x, accumulating the voxel count and index sums of the
//    current cell until the label changes; the partial sums go into a block-local hash table in shared memory, which
//    is flushed to the global per-cell statistics with 64-bit integer atomics (exact and order independent). The
//    same walk compares every voxel with its +x, +y (+z) neighbours and inserts the pairs of different cells, as keys
//    lo * numberOfCells + hi, into a block-local hash set; the set's keys are appended to a global key list.
//    Anything that does not fit a block's table goes to global memory directly, so any labelling is handled.
// 2. BorderKernel: the same run accumulation over the border parts (faces, 3D edge lines); CornerKernel: the corners.
// 3. One download of the statistics and counters (pinned), then CUB radix sort (only the bits of numberOfCells^2)
//    and unique of the keys, and the download of the unique keys.
#include "dmrCudaUtils.cuh"
#include "dmrDualMeshBackend.h"

#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_select.cuh>

#include <algorithm>
#include <cstring>
#include <limits>
#include <mutex>
#include <vector>

namespace itk
{
namespace dmr
{
namespace cuda
{
namespace
{
using ull = unsigned long long;

constexpr int      kThreads = 256;
constexpr int      kRun = 8;            // voxels per work item along x
constexpr int      kItemsPerThread = 4; // work items per thread: a block covers kThreads * kItemsPerThread runs
constexpr int      kCellSlotBits = 9;   // shared per-cell table: 512 slots
constexpr int      kCellSlots = 1 << kCellSlotBits;
constexpr int      kPairSlotBits = 11; // shared pair set: 2048 slots
constexpr int      kPairSlots = 1 << kPairSlotBits;
constexpr int      kProbes = 16;
constexpr int32_t  kNoCell = -1;
constexpr ull      kNoPair = ~0ull;
constexpr unsigned kCounterPairs = 0;   // keys appended to the key list (may exceed its capacity: then retried)
constexpr unsigned kCounterInvalid = 1; // voxels with a label outside [0, numberOfCells)
constexpr unsigned kNumberOfCounters = 2;

struct BulkParams
{
  const int32_t * labels;
  long long       size[3];
  long long       stride[3];
  long long       rowsPerSlab; // size[1]
  long long       segmentsPerRow;
  long long       items;
  long long       numberOfCells;
  int             dimension;
  ull *           cellStats; // (dimension + 1) per cell
  ull *           keys;
  ull             keyCapacity;
  ull *           counters;
  int             findPairs; // 0: no adjacency keys (LabelSummarizer::SetFindAdjacentPairs)
};

__device__ inline bool
ValidLabel(int32_t c, long long numberOfCells)
{
  return c >= 0 && static_cast<long long>(c) < numberOfCells;
}

/** Adds a run of n voxels of cell c (sums sx along x, n * y, n * z) to the shared table, or to global memory when the
 * table has no room for c. */
__device__ inline void
AddRun(const BulkParams & p, int32_t * sCellKey, ull (*sCellVal)[4], int32_t c, ull n, ull sx, ull y, ull z)
{
  if (n == 0)
  {
    return;
  }
  unsigned slot = (static_cast<unsigned>(c) * 2654435761u) >> (32 - kCellSlotBits);
  for (int probe = 0; probe < kProbes; ++probe)
  {
    const int32_t prev = atomicCAS(&sCellKey[slot], kNoCell, c);
    if (prev == kNoCell || prev == c)
    {
      atomicAdd(&sCellVal[slot][0], n);
      atomicAdd(&sCellVal[slot][1], sx);
      atomicAdd(&sCellVal[slot][2], n * y);
      atomicAdd(&sCellVal[slot][3], n * z);
      return;
    }
    slot = (slot + 1) & (kCellSlots - 1);
  }
  ull * st = p.cellStats + static_cast<size_t>(p.dimension + 1) * static_cast<size_t>(c);
  atomicAdd(&st[0], n);
  atomicAdd(&st[1], sx);
  atomicAdd(&st[2], n * y);
  if (p.dimension == 3)
  {
    atomicAdd(&st[3], n * z);
  }
}

__device__ inline void
AppendKey(const BulkParams & p, ull key)
{
  const ull i = atomicAdd(&p.counters[kCounterPairs], 1ull);
  if (i < p.keyCapacity)
  {
    p.keys[i] = key;
  }
}

__device__ inline void
AddPair(const BulkParams & p, ull * sPairKey, ull & last, int32_t a, int32_t b)
{
  const ull lo = static_cast<ull>(a < b ? a : b), hi = static_cast<ull>(a < b ? b : a);
  const ull key = lo * static_cast<ull>(p.numberOfCells) + hi;
  if (key == last)
  {
    return;
  }
  last = key;
  unsigned slot = static_cast<unsigned>((key * 0x9e3779b97f4a7c15ull) >> (64 - kPairSlotBits));
  for (int probe = 0; probe < kProbes; ++probe)
  {
    const ull prev = atomicCAS(&sPairKey[slot], kNoPair, key);
    if (prev == kNoPair || prev == key)
    {
      return;
    }
    slot = (slot + 1) & (kPairSlots - 1);
  }
  AppendKey(p, key);
}

__global__ void
BulkKernel(BulkParams p)
{
  __shared__ int32_t sCellKey[kCellSlots];
  __shared__ ull     sCellVal[kCellSlots][4];
  __shared__ ull     sPairKey[kPairSlots];
  __shared__ ull     sCount;
  __shared__ ull     sBase;
  __shared__ ull     sCursor;
  for (int i = threadIdx.x; i < kCellSlots; i += blockDim.x)
  {
    sCellKey[i] = kNoCell;
    sCellVal[i][0] = sCellVal[i][1] = sCellVal[i][2] = sCellVal[i][3] = 0;
  }
  for (int i = threadIdx.x; i < kPairSlots; i += blockDim.x)
  {
    sPairKey[i] = kNoPair;
  }
  if (threadIdx.x == 0)
  {
    sCount = 0;
    sCursor = 0;
  }
  __syncthreads();

  const long long sx = p.size[0];
  unsigned        invalid = 0;
  for (int it = 0; it < kItemsPerThread; ++it)
  {
    const long long item =
      (static_cast<long long>(blockIdx.x) * kItemsPerThread + it) * kThreads + static_cast<long long>(threadIdx.x);
    if (item >= p.items)
    {
      break;
    }
    const long long row = item / p.segmentsPerRow;
    const long long x0 = (item - row * p.segmentsPerRow) * kRun;
    const long long x1 = x0 + kRun < sx ? x0 + kRun : sx;
    const long long y = row % p.rowsPerSlab, z = row / p.rowsPerSlab;
    const bool      hasY = y + 1 < p.size[1], hasZ = p.dimension == 3 && z + 1 < p.size[2];
    const int32_t * L = p.labels + row * sx;
    int32_t         current = kNoCell;
    ull             n = 0, sumX = 0;
    ull             last[3] = { kNoPair, kNoPair, kNoPair };
    for (long long x = x0; x < x1; ++x)
    {
      const int32_t c = L[x];
      if (!ValidLabel(c, p.numberOfCells))
      {
        ++invalid;
        continue;
      }
      if (c != current)
      {
        if (current != kNoCell)
        {
          AddRun(p, sCellKey, sCellVal, current, n, sumX, static_cast<ull>(y), static_cast<ull>(z));
        }
        current = c;
        n = 0;
        sumX = 0;
      }
      ++n;
      sumX += static_cast<ull>(x);
      if (!p.findPairs)
      {
        continue;
      }
      if (x + 1 < sx)
      {
        const int32_t o = L[x + 1];
        if (o != c && ValidLabel(o, p.numberOfCells))
        {
          AddPair(p, sPairKey, last[0], c, o);
        }
      }
      if (hasY)
      {
        const int32_t o = L[x + p.stride[1]];
        if (o != c && ValidLabel(o, p.numberOfCells))
        {
          AddPair(p, sPairKey, last[1], c, o);
        }
      }
      if (hasZ)
      {
        const int32_t o = L[x + p.stride[2]];
        if (o != c && ValidLabel(o, p.numberOfCells))
        {
          AddPair(p, sPairKey, last[2], c, o);
        }
      }
    }
    if (current != kNoCell)
    {
      AddRun(p, sCellKey, sCellVal, current, n, sumX, static_cast<ull>(y), static_cast<ull>(z));
    }
  }
  if (invalid)
  {
    atomicAdd(&p.counters[kCounterInvalid], static_cast<ull>(invalid));
  }
  __syncthreads();

  // flush the per-cell table
  for (int i = threadIdx.x; i < kCellSlots; i += blockDim.x)
  {
    const int32_t c = sCellKey[i];
    if (c != kNoCell)
    {
      ull * st = p.cellStats + static_cast<size_t>(p.dimension + 1) * static_cast<size_t>(c);
      for (int j = 0; j <= p.dimension; ++j)
      {
        if (sCellVal[i][j])
        {
          atomicAdd(&st[j], sCellVal[i][j]);
        }
      }
    }
  }
  // append the pair set to the global key list: one global atomic per block for the block's range
  ull mine = 0;
  for (int i = threadIdx.x; i < kPairSlots; i += blockDim.x)
  {
    mine += sPairKey[i] != kNoPair ? 1 : 0;
  }
  if (mine)
  {
    atomicAdd(&sCount, mine);
  }
  __syncthreads();
  if (threadIdx.x == 0)
  {
    sBase = sCount ? atomicAdd(&p.counters[kCounterPairs], sCount) : 0;
  }
  __syncthreads();
  for (int i = threadIdx.x; i < kPairSlots; i += blockDim.x)
  {
    if (sPairKey[i] != kNoPair)
    {
      const ull at = sBase + atomicAdd(&sCursor, 1ull);
      if (at < p.keyCapacity)
      {
        p.keys[at] = sPairKey[i];
      }
    }
  }
}

/** One border part: voxels base + ia strideA + ib strideB for ia in [startA, startA + countA), ib likewise; per cell c
 * its statistics are at out + values (partsPerCell c + part): count, sum ia, (sum ib). */
struct BorderPart
{
  long long base;
  long long strideA;
  long long strideB;
  long long startA;
  long long countA;
  long long startB;
  long long countB;
  long long segmentsPerLine;
  int       part;
  int       partsPerCell;
  int       values; // 2 (count, sum ia) or 3 (count, sum ia, sum ib)
  int       isEdge; // 0: faceStats, 1: edgeStats
};

constexpr int kMaxBorderParts = 18; // 6 faces + 12 edge lines

struct BorderParams
{
  const int32_t * labels;
  long long       numberOfCells;
  ull *           faceStats;
  ull *           edgeStats;
  int             numberOfParts;
  BorderPart      parts[kMaxBorderParts];
};

__device__ inline void
FlushBorderRun(const BorderParams & p, const BorderPart & b, int32_t c, ull n, ull sumA, ull ib)
{
  ull * st = (b.isEdge ? p.edgeStats : p.faceStats) +
             static_cast<size_t>(b.values) * (static_cast<size_t>(b.partsPerCell) * static_cast<size_t>(c) + b.part);
  atomicAdd(&st[0], n);
  if (sumA)
  {
    atomicAdd(&st[1], sumA);
  }
  if (b.values == 3 && ib)
  {
    atomicAdd(&st[2], n * ib);
  }
}

__global__ void
BorderKernel(BorderParams p)
{
  const BorderPart & b = p.parts[blockIdx.y];
  const long long    item = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (item >= b.countB * b.segmentsPerLine)
  {
    return;
  }
  const long long line = item / b.segmentsPerLine;
  const long long a0 = b.startA + (item - line * b.segmentsPerLine) * kRun;
  const long long aEnd = b.startA + b.countA;
  const long long a1 = a0 + kRun < aEnd ? a0 + kRun : aEnd;
  const long long ib = b.startB + line;
  int32_t         current = kNoCell;
  ull             n = 0, sumA = 0;
  for (long long ia = a0; ia < a1; ++ia)
  {
    const int32_t c = p.labels[b.base + ia * b.strideA + ib * b.strideB];
    if (!ValidLabel(c, p.numberOfCells))
    {
      continue; // counted by the bulk kernel
    }
    if (c != current)
    {
      if (current != kNoCell)
      {
        FlushBorderRun(p, b, current, n, sumA, static_cast<ull>(ib));
      }
      current = c;
      n = 0;
      sumA = 0;
    }
    ++n;
    sumA += static_cast<ull>(ia);
  }
  if (current != kNoCell)
  {
    FlushBorderRun(p, b, current, n, sumA, static_cast<ull>(ib));
  }
}

struct CornerParams
{
  const int32_t * labels;
  long long       offsets[8];
  int             numberOfCorners;
  ull *           out;
};

__global__ void
CornerKernel(CornerParams p)
{
  const int q = threadIdx.x;
  if (q < p.numberOfCorners)
  {
    p.out[q] = static_cast<ull>(static_cast<long long>(p.labels[p.offsets[q]]));
  }
}

/** Owning pinned host allocation (cudaMallocHost), grown on demand; contents discarded when it grows. */
class PinnedBuffer
{
public:
  PinnedBuffer() = default;
  PinnedBuffer(const PinnedBuffer &) = delete;
  PinnedBuffer &
  operator=(const PinnedBuffer &) = delete;
  ~PinnedBuffer()
  {
    if (m_Data)
    {
      cudaFreeHost(m_Data);
    }
  }
  ull *
  Reserve(size_t n)
  {
    if (n > m_Size)
    {
      if (m_Data)
      {
        cudaFreeHost(m_Data);
        m_Data = nullptr;
        m_Size = 0;
      }
      void * q = nullptr;
      Check(cudaMallocHost(&q, n * sizeof(ull)), "cudaMallocHost");
      m_Data = static_cast<ull *>(q);
      m_Size = n;
    }
    return m_Data;
  }

private:
  ull *  m_Data{ nullptr };
  size_t m_Size{ 0 };
};

unsigned
BitsFor(ull maximum)
{
  unsigned bits = 0;
  while (bits < 64 && (maximum >> bits) != 0)
  {
    ++bits;
  }
  return std::max(bits, 1u);
}
} // namespace

struct LabelSummarizer::Impl
{
  DeviceBuffer<int32_t>       uploaded;
  DeviceBuffer<ull>           stats; // cell | face | edge statistics, corners, counters
  DeviceBuffer<ull>           keys;
  DeviceBuffer<ull>           sortedKeys;
  DeviceBuffer<ull>           numberSelected;
  DeviceBuffer<unsigned char> cubTemp;
  PinnedBuffer                hostStats;
  PinnedBuffer                hostKeys;

  void
  Run(unsigned int    dimension,
      const size_t *  size,
      const int32_t * labels,
      size_t          numberOfCells,
      bool            findPairs,
      LabelSummary &  out);
};

void
LabelSummarizer::Impl::Run(unsigned int    dimension,
                           const size_t *  size,
                           const int32_t * labels,
                           size_t          numberOfCells,
                           bool            findPairs,
                           LabelSummary &  out)
{
  const unsigned int D = dimension;
  size_t             numberOfPixels = 1;
  long long          stride[3] = { 1, 1, 1 };
  long long          sz[3] = { 1, 1, 1 };
  for (unsigned int k = 0; k < D; ++k)
  {
    stride[k] = static_cast<long long>(numberOfPixels);
    sz[k] = static_cast<long long>(size[k]);
    numberOfPixels *= size[k];
  }
  const size_t nFaces = 2 * D, nEdges = D == 3 ? LabelSummary::NumberOfEdges3D : 0;
  const size_t cellValues = (D + 1) * numberOfCells, faceValues = nFaces * D * numberOfCells,
               edgeValues = 2 * nEdges * numberOfCells;
  const size_t cornerAt = cellValues + faceValues + edgeValues, counterAt = cornerAt + 8;
  const size_t statValues = counterAt + kNumberOfCounters;
  stats.Reserve(statValues);
  ull * hostStatsData = hostStats.Reserve(statValues);

  BulkParams bulk{};
  bulk.labels = labels;
  for (unsigned int k = 0; k < 3; ++k)
  {
    bulk.size[k] = sz[k];
    bulk.stride[k] = stride[k];
  }
  bulk.rowsPerSlab = sz[1];
  bulk.segmentsPerRow = (sz[0] + kRun - 1) / kRun;
  bulk.items = static_cast<long long>(numberOfPixels / size[0]) * bulk.segmentsPerRow;
  bulk.numberOfCells = static_cast<long long>(numberOfCells);
  bulk.dimension = static_cast<int>(D);
  bulk.cellStats = stats.Data();
  bulk.counters = stats.Data() + counterAt;
  bulk.findPairs = findPairs ? 1 : 0;
  const unsigned bulkBlocks = Blocks(static_cast<size_t>(bulk.items), kThreads * kItemsPerThread);

  BorderParams border{};
  border.labels = labels;
  border.numberOfCells = bulk.numberOfCells;
  border.faceStats = stats.Data() + cellValues;
  border.edgeStats = stats.Data() + cellValues + faceValues;
  long long maxBorderItems = 0;
  auto      addPart = [&](BorderPart b) {
    if (b.countA <= 0 || b.countB <= 0)
    {
      return;
    }
    b.segmentsPerLine = (b.countA + kRun - 1) / kRun;
    maxBorderItems = std::max(maxBorderItems, b.countB * b.segmentsPerLine);
    border.parts[border.numberOfParts++] = b;
  };
  for (unsigned int f = 0; f < nFaces; ++f)
  {
    const unsigned int k = f / 2, a = (k + 1) % D, bAxis = (k + 2) % D;
    BorderPart         b{};
    b.base = (f % 2 ? sz[k] - 1 : 0) * stride[k];
    b.strideA = stride[a];
    b.part = static_cast<int>(f);
    b.partsPerCell = static_cast<int>(nFaces);
    b.isEdge = 0;
    if (D == 2)
    {
      b.startA = 0; // a 2D face is the whole border line, corners included
      b.countA = sz[a];
      b.strideB = 0;
      b.startB = 0;
      b.countB = 1;
      b.values = 2;
    }
    else
    {
      b.startA = 1; // a 3D face is its inner voxels
      b.countA = sz[a] - 2;
      b.strideB = stride[bAxis];
      b.startB = 1;
      b.countB = sz[bAxis] - 2;
      b.values = 3;
    }
    addPart(b);
  }
  for (unsigned int e = 0; e < nEdges; ++e)
  {
    const unsigned int a = e / 4, bAxis = (a + 1) % 3, cAxis = (a + 2) % 3;
    BorderPart         b{};
    b.base = ((e >> 1) & 1u ? sz[bAxis] - 1 : 0) * stride[bAxis] + (e & 1u ? sz[cAxis] - 1 : 0) * stride[cAxis];
    b.strideA = stride[a];
    b.startA = 1;
    b.countA = sz[a] - 2;
    b.strideB = 0;
    b.startB = 0;
    b.countB = 1;
    b.part = static_cast<int>(e);
    b.partsPerCell = static_cast<int>(nEdges);
    b.values = 2;
    b.isEdge = 1;
    addPart(b);
  }

  CornerParams corners{};
  corners.labels = labels;
  corners.numberOfCorners = 1 << D;
  corners.out = stats.Data() + cornerAt;
  for (int q = 0; q < corners.numberOfCorners; ++q)
  {
    long long o = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      o += ((q >> k) & 1 ? sz[k] - 1 : 0) * stride[k];
    }
    corners.offsets[q] = o;
  }

  // Pass 1 (statistics and candidate keys); repeated once with an exact key capacity when the keys did not fit.
  if (keys.Size() == 0)
  {
    keys.Reserve(std::max<size_t>(size_t{ 1 } << 16, numberOfPixels / 8));
  }
  for (int attempt = 0;; ++attempt)
  {
    bulk.keys = keys.Data();
    bulk.keyCapacity = keys.Size();
    stats.Zero();
    BulkKernel<<<bulkBlocks, kThreads>>>(bulk);
    CheckLaunch("BulkKernel");
    if (border.numberOfParts > 0)
    {
      BorderKernel<<<dim3(Blocks(static_cast<size_t>(maxBorderItems), kThreads), border.numberOfParts), kThreads>>>(
        border);
      CheckLaunch("BorderKernel");
    }
    CornerKernel<<<1, 8>>>(corners);
    CheckLaunch("CornerKernel");
    Check(cudaMemcpyAsync(hostStatsData, stats.Data(), statValues * sizeof(ull), cudaMemcpyDeviceToHost, nullptr),
          "download of the label summary");
    Check(cudaStreamSynchronize(nullptr), "label summary kernels");
    if (hostStatsData[counterAt + kCounterInvalid] != 0)
    {
      throw CudaError(std::to_string(hostStatsData[counterAt + kCounterInvalid]) + " voxels have a label outside [0, " +
                      std::to_string(numberOfCells) + ")");
    }
    const ull emitted = hostStatsData[counterAt + kCounterPairs];
    if (emitted <= keys.Size())
    {
      break;
    }
    if (attempt > 0)
    {
      throw CudaError("label summary: the adjacency key count changed between two passes");
    }
    keys.Reserve(static_cast<size_t>(emitted + emitted / 4));
  }
  const size_t emitted = static_cast<size_t>(hostStatsData[counterAt + kCounterPairs]);

  // the summary's statistics (unsigned atomics on non-negative values: the same bits as the int64 sums)
  out.dimension = D;
  out.numberOfCells = numberOfCells;
  out.size = { { 1, 1, 1 } };
  for (unsigned int k = 0; k < D; ++k)
  {
    out.size[k] = size[k];
  }
  out.cellStats.resize(cellValues);
  out.faceStats.resize(faceValues);
  out.edgeStats.resize(edgeValues);
  std::memcpy(out.cellStats.data(), hostStatsData, cellValues * sizeof(int64_t));
  std::memcpy(out.faceStats.data(), hostStatsData + cellValues, faceValues * sizeof(int64_t));
  std::memcpy(out.edgeStats.data(), hostStatsData + cellValues + faceValues, edgeValues * sizeof(int64_t));
  out.cornerLabels.fill(0);
  for (int q = 0; q < corners.numberOfCorners; ++q)
  {
    out.cornerLabels[q] = static_cast<int32_t>(static_cast<long long>(hostStatsData[cornerAt + q]));
  }
  out.adjacentPairs.clear();
  if (emitted == 0 || !findPairs)
  {
    return;
  }

  // Pass 2: sort and deduplicate the keys (lo * numberOfCells + hi: only the low bits of numberOfCells^2 vary).
  if (emitted > static_cast<size_t>(std::numeric_limits<int>::max()))
  {
    throw CudaError("label summary: " + std::to_string(emitted) + " adjacency keys exceed the sort's int range");
  }
  const int numItems = static_cast<int>(emitted);
  const int endBit = static_cast<int>(BitsFor(static_cast<ull>(numberOfCells) * numberOfCells - 1));
  sortedKeys.Reserve(emitted);
  numberSelected.Reserve(1);
  size_t sortBytes = 0, uniqueBytes = 0;
  Check(
    cub::DeviceRadixSort::SortKeys(nullptr, sortBytes, keys.Data(), sortedKeys.Data(), numItems, 0, endBit, nullptr),
    "DeviceRadixSort (size query)");
  Check(cub::DeviceSelect::Unique(
          nullptr, uniqueBytes, sortedKeys.Data(), keys.Data(), numberSelected.Data(), numItems, nullptr),
        "DeviceSelect::Unique (size query)");
  cubTemp.Reserve(std::max<size_t>(std::max(sortBytes, uniqueBytes), 1));
  sortBytes = cubTemp.Size();
  Check(cub::DeviceRadixSort::SortKeys(
          cubTemp.Data(), sortBytes, keys.Data(), sortedKeys.Data(), numItems, 0, endBit, nullptr),
        "DeviceRadixSort");
  uniqueBytes = cubTemp.Size();
  Check(cub::DeviceSelect::Unique(
          cubTemp.Data(), uniqueBytes, sortedKeys.Data(), keys.Data(), numberSelected.Data(), numItems, nullptr),
        "DeviceSelect::Unique");
  ull unique = 0;
  numberSelected.Download(&unique, 1);
  if (unique > emitted)
  {
    throw CudaError("label summary: more unique adjacency keys than keys");
  }
  ull * hostKeysData = hostKeys.Reserve(static_cast<size_t>(std::max<ull>(unique, 1)));
  keys.Download(hostKeysData, static_cast<size_t>(unique));
  out.adjacentPairs.resize(static_cast<size_t>(unique));
  const ull n = static_cast<ull>(numberOfCells);
  for (size_t i = 0; i < out.adjacentPairs.size(); ++i)
  {
    const ull lo = hostKeysData[i] / n, hi = hostKeysData[i] % n;
    out.adjacentPairs[i] = (static_cast<uint64_t>(lo) << 32) | static_cast<uint64_t>(hi);
  }
}

LabelSummarizer::LabelSummarizer()
  : m_Impl(new Impl)
{
}

LabelSummarizer::~LabelSummarizer()
{
  delete m_Impl;
}

Status
LabelSummarizer::Summarize(unsigned int    dimension,
                           const size_t *  size,
                           const int32_t * deviceLabels,
                           size_t          numberOfCells,
                           LabelSummary &  out)
{
  if (!DeviceAvailable())
  {
    return Status::Error(UnavailableReason());
  }
  if (dimension != 2 && dimension != 3)
  {
    return Status::Error("label summary: dimension " + std::to_string(dimension) + " is not 2 or 3");
  }
  if (size == nullptr || deviceLabels == nullptr)
  {
    return Status::Error("label summary: no size or no labels");
  }
  for (unsigned int k = 0; k < dimension; ++k)
  {
    if (size[k] == 0 || size[k] > (size_t{ 1 } << 30))
    {
      return Status::Error("label summary: size " + std::to_string(size[k]) + " along axis " + std::to_string(k));
    }
  }
  if (numberOfCells == 0 || numberOfCells >= (size_t{ 1 } << 31))
  {
    return Status::Error("label summary: " + std::to_string(numberOfCells) + " cells (1 to 2^31 - 1 supported)");
  }
  return Guard([&] { m_Impl->Run(dimension, size, deviceLabels, numberOfCells, m_FindAdjacentPairs, out); });
}

Status
LabelSummarizer::UploadLabels(const int32_t * hostLabels, size_t numberOfPixels)
{
  if (!DeviceAvailable())
  {
    return Status::Error(UnavailableReason());
  }
  if (hostLabels == nullptr && numberOfPixels > 0)
  {
    return Status::Error("label upload: no labels");
  }
  return Guard([&] {
    m_Impl->uploaded.Reserve(std::max<size_t>(numberOfPixels, 1));
    m_Impl->uploaded.Upload(hostLabels, numberOfPixels);
    Check(cudaStreamSynchronize(nullptr), "label upload");
  });
}

const int32_t *
LabelSummarizer::UploadedLabels() const
{
  return m_Impl->uploaded.Data();
}

size_t
LabelSummarizer::AllocatedBytes() const
{
  const Impl & m = *m_Impl;
  return BytesOf(m.uploaded, m.stats, m.keys, m.sortedKeys, m.numberSelected, m.cubTemp);
}

Status
LabelSummarizer::SummarizeHostLabels(unsigned int    dimension,
                                     const size_t *  size,
                                     const int32_t * hostLabels,
                                     size_t          numberOfCells,
                                     LabelSummary &  out)
{
  if (size == nullptr || (dimension != 2 && dimension != 3))
  {
    return Status::Error("label summary: bad dimension or no size");
  }
  size_t numberOfPixels = 1;
  for (unsigned int k = 0; k < dimension; ++k)
  {
    numberOfPixels *= size[k];
  }
  const Status uploaded = UploadLabels(hostLabels, numberOfPixels);
  if (!uploaded.Ok())
  {
    return uploaded;
  }
  return Summarize(dimension, size, UploadedLabels(), numberOfCells, out);
}

namespace
{
std::mutex &
SharedMutex()
{
  static std::mutex mutex;
  return mutex;
}
LabelSummarizer &
SharedSummarizer()
{
  static LabelSummarizer summarizer;
  return summarizer;
}
} // namespace

Status
SummarizeLabels(unsigned int    dimension,
                const size_t *  size,
                const int32_t * deviceLabels,
                size_t          numberOfCells,
                LabelSummary &  out)
{
  std::lock_guard<std::mutex> lock(SharedMutex());
  return SharedSummarizer().Summarize(dimension, size, deviceLabels, numberOfCells, out);
}

Status
SummarizeHostLabels(unsigned int    dimension,
                    const size_t *  size,
                    const int32_t * hostLabels,
                    size_t          numberOfCells,
                    LabelSummary &  out)
{
  std::lock_guard<std::mutex> lock(SharedMutex());
  return SharedSummarizer().SummarizeHostLabels(dimension, size, hostLabels, numberOfCells, out);
}
} // namespace cuda
} // namespace dmr
} // namespace itk
