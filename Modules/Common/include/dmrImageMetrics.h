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

#include "itkImage.h"
#include "itkImageRegionConstIterator.h"
#include "itkMacro.h"
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <utility>

namespace itk
{
namespace dmr
{
/** Smallest and largest intensity of an image (whole buffer). */
template <typename TImage>
std::pair<double, double>
IntensityRange(const TImage * image)
{
  double lo = NumericTraits<double>::max(), hi = NumericTraits<double>::NonpositiveMin();
  if (image->GetBufferedRegion() == image->GetLargestPossibleRegion())
  {
    // the whole buffer in memory order: the same values as the iterator's, without its per-pixel index bookkeeping
    const auto * p = image->GetBufferPointer();
    const auto * end = p + image->GetLargestPossibleRegion().GetNumberOfPixels();
    for (; p != end; ++p)
    {
      const double v = static_cast<double>(*p);
      lo = std::min(lo, v);
      hi = std::max(hi, v);
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
 * components) is not a finite number (NaN or infinite), -1 when there is none. Integer images have none. */
template <typename TImage>
int64_t
FirstNonFinitePixel(const TImage * image)
{
  using PixelType = typename TImage::PixelType;
  if constexpr (std::is_floating_point_v<typename NumericTraits<PixelType>::ValueType>)
  {
    const auto * buffer = image->GetBufferPointer();
    const auto   n = static_cast<int64_t>(image->GetBufferedRegion().GetNumberOfPixels());
    for (int64_t p = 0; p < n; ++p)
    {
      if constexpr (std::is_floating_point_v<PixelType>)
      {
        if (!std::isfinite(buffer[p]))
        {
          return p;
        }
      }
      else
      {
        for (unsigned int k = 0; k < NumericTraits<PixelType>::GetLength(buffer[p]); ++k)
        {
          if (!std::isfinite(buffer[p][k]))
          {
            return p;
          }
        }
      }
    }
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
