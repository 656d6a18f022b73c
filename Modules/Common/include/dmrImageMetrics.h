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
#ifndef dmrImageMetrics_h
#define dmrImageMetrics_h

#include "dmrGrid.h" // ParallelForChunks, FirstIndexWhere
#include "itkImage.h"
#include "itkImageRegionConstIterator.h"
#include "itkMacro.h"
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <utility>
#include <vector>

namespace itk
{
namespace dmr
{
/** Smallest and largest intensity of an image (whole buffer); on the threader's work units when one is given (the
 * same result: NaNs are passed over either way). */
template <typename TImage>
std::pair<double, double>
IntensityRange(const TImage * image, MultiThreaderBase * threader = nullptr)
{
  double lo = NumericTraits<double>::max(), hi = NumericTraits<double>::NonpositiveMin();
  if (image->GetBufferedRegion() == image->GetLargestPossibleRegion())
  {
    // the whole buffer in memory order: the same values as the iterator's, without its per-pixel index bookkeeping;
    // 64 chunks, each with its own range
    const auto *                           buffer = image->GetBufferPointer();
    const size_t                           n = image->GetLargestPossibleRegion().GetNumberOfPixels();
    const size_t                           nChunks = std::max<size_t>(1, std::min<size_t>(64, n / 4096));
    const size_t                           chunk = (n + nChunks - 1) / nChunks;
    std::vector<std::pair<double, double>> ranges(nChunks, { lo, hi });
    ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      double     l = ranges[c].first, h = ranges[c].second;
      const auto end = buffer + std::min(n, (c + 1) * chunk);
      for (auto p = buffer + std::min(n, c * chunk); p < end; ++p)
      {
        const double v = static_cast<double>(*p);
        l = std::min(l, v);
        h = std::max(h, v);
      }
      ranges[c] = { l, h };
    });
    for (const auto & r : ranges)
    {
      lo = std::min(lo, r.first);
      hi = std::max(hi, r.second);
    }
    return { lo, hi };
  }
  ImageRegionConstIterator<TImage> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    const double v = static_cast<double>(it.Get());
    lo = std::min(lo, v);
    hi = std::max(hi, v);
  }
  return { lo, hi };
}

/** Buffer offset of the first pixel whose value (or, for a vector pixel such as a displacement, one of whose
 * components) is not a finite number (NaN or infinite), -1 when there is none. Integer images have none. On the
 * threader's work units when one is given (the same answer). */
template <typename TImage>
int64_t
FirstNonFinitePixel(const TImage * image, MultiThreaderBase * threader = nullptr)
{
  using PixelType = typename TImage::PixelType;
  if constexpr (std::is_floating_point_v<typename NumericTraits<PixelType>::ValueType>)
  {
    const auto * buffer = image->GetBufferPointer();
    const size_t n = image->GetBufferedRegion().GetNumberOfPixels();
    const size_t first = FirstIndexWhere(threader, n, [buffer](size_t p) {
      if constexpr (std::is_floating_point_v<PixelType>)
      {
        return !std::isfinite(buffer[p]);
      }
      else
      {
        bool bad = false;
        for (unsigned int k = 0; k < NumericTraits<PixelType>::GetLength(buffer[p]); ++k)
        {
          bad |= !std::isfinite(buffer[p][k]);
        }
        return bad;
      }
    });
    return first < n ? static_cast<int64_t>(first) : -1;
  }
  return -1;
}

/** Dice overlap of the regions {a > threshold} and {b > threshold} of two images of the same size. */
template <typename TImageA, typename TImageB>
double
DiceCoefficient(const TImageA * a, const TImageB * b, double threshold = 0.5)
{
  if (a->GetLargestPossibleRegion().GetSize() != b->GetLargestPossibleRegion().GetSize())
  {
    itkGenericExceptionMacro("DiceCoefficient: the images differ in size");
  }
  ImageRegionConstIterator<TImageA> ia(a, a->GetLargestPossibleRegion());
  ImageRegionConstIterator<TImageB> ib(b, b->GetLargestPossibleRegion());
  double                            na = 0, nb = 0, both = 0;
  for (; !ia.IsAtEnd(); ++ia, ++ib)
  {
    const bool ina = static_cast<double>(ia.Get()) > threshold;
    const bool inb = static_cast<double>(ib.Get()) > threshold;
    na += ina;
    nb += inb;
    both += ina && inb;
  }
  return na + nb > 0 ? 2.0 * both / (na + nb) : 1.0;
}
} // namespace dmr
} // namespace itk

#endif
