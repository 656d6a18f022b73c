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
#ifndef dmrContractionSums_h
#define dmrContractionSums_h

#include "dmrFixedPointGather.h" // DMR_HOST_DEVICE

namespace itk
{
namespace dmr
{
/** The contraction's block sums, one definition for the CPU (DiscreteCVT::ContractionInitialize) and the GPU
 * (BlockSumsKernel), so that both back-ends start the merges from the same bits: adds the pixels row[first, end) of
 * one block's row, pixel i at x[0] = i spacing0 (x[1..D-1] are the row's), to the block's mass and first moments, in
 * pixel order. */
template <unsigned int D, typename TIndex>
DMR_HOST_DEVICE inline void
AddRowToBlockSums(const float * row,
                  TIndex        first,
                  TIndex        end,
                  double        spacing0,
                  double (&x)[D],
                  double & mass,
                  double (&moment)[D])
{
  for (TIndex i = first; i < end; ++i)
  {
    x[0] = static_cast<double>(i) * spacing0;
    const double w = row[i];
    mass += w;
    for (unsigned int k = 0; k < D; ++k)
    {
      moment[k] += w * x[k];
    }
  }
}
} // namespace dmr
} // namespace itk

#endif
