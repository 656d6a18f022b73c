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
#ifndef dmrNeighbourhood_h
#define dmrNeighbourhood_h

#include "dmrFixedPointGather.h" // DMR_HOST_DEVICE
#include <cstdint>

namespace itk
{
namespace dmr
{
/** The 3^D neighbourhood of a pixel as bit sets, one definition for the CPU CVT (DiscreteCVT) and its CUDA kernels:
 * position q = sum_k (offset_k + 1) 3^k is bit q (the centre is bit 3^D / 2). Everything but Dilate is a compile-time
 * constant, so the connectivity test below needs no table in memory.
 * \ingroup DynamicMeshRegistration */
template <unsigned int D>
struct Neighbourhood
{
  static_assert(D == 2 || D == 3, "2D or 3D");
  static constexpr unsigned int Size = D == 2 ? 9 : 27;
  static constexpr unsigned int Centre = Size / 2;

  DMR_HOST_DEVICE static constexpr uint32_t
  Power(unsigned int k)
  {
    return k == 0 ? 1u : 3u * Power(k - 1);
  }
  /** Offset (-1, 0 or 1) of position q along axis k. */
  DMR_HOST_DEVICE static constexpr int
  Offset(unsigned int q, unsigned int k)
  {
    return static_cast<int>((q / Power(k)) % 3u) - 1;
  }
  /** The positions whose digit along axis k is not `digit`. */
  DMR_HOST_DEVICE static constexpr uint32_t
  NotDigit(unsigned int k, unsigned int digit)
  {
    uint32_t mask = 0;
    for (unsigned int q = 0; q < Size; ++q)
    {
      mask |= (q / Power(k)) % 3u != digit ? 1u << q : 0u;
    }
    return mask;
  }
  /** The centre's face neighbours. */
  DMR_HOST_DEVICE static constexpr uint32_t
  FaceMask()
  {
    uint32_t mask = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      mask |= (1u << (Centre - Power(k))) | (1u << (Centre + Power(k)));
    }
    return mask;
  }
  /** The positions that differ by one along one axis from a position of `set`. */
  DMR_HOST_DEVICE static constexpr uint32_t
  Dilate(uint32_t set)
  {
    uint32_t out = ((set & NotDigit(0, 2)) << 1) | ((set & NotDigit(0, 0)) >> 1) | ((set & NotDigit(1, 2)) << 3) |
                   ((set & NotDigit(1, 0)) >> 3);
    if (D == 3)
    {
      out |= ((set & NotDigit(2, 2)) << 9) | ((set & NotDigit(2, 0)) >> 9);
    }
    return out;
  }
  /** The local topology test of the swap step: given the positions of the neighbourhood that hold the pixel's cell
   * (the centre excluded), true when those that touch the centre by a face are face-connected to one another inside
   * the neighbourhood without the centre, i.e. removing the pixel keeps its cell locally connected. False when no face
   * neighbour is in the cell (the pixel is its cell's last link, or its only pixel). Bit-set flood fill from the
   * lowest face neighbour in the cell. */
  DMR_HOST_DEVICE static inline bool
  RemovalKeepsConnected(uint32_t member)
  {
    member &= ~(1u << Centre);
    const uint32_t faces = member & FaceMask();
    if (faces == 0)
    {
      return false;
    }
    uint32_t reach = faces & (~faces + 1u);
    for (;;)
    {
      const uint32_t next = reach | (Dilate(reach) & member);
      if (next == reach)
      {
        break;
      }
      reach = next;
    }
    return (faces & ~reach) == 0;
  }
};
} // namespace dmr
} // namespace itk

#endif
