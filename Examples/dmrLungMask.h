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
#ifndef dmrLungMask_h
#define dmrLungMask_h

// A simple lung mask of a 3D CT in HU, for evaluation (dense error inside the lungs) and for placing the synthetic
// breathing motion; not a segmentation method. Steps:
//  1. air = HU < threshold (-400 by default);
//  2. outside air is removed slice by slice: in every axial slice, air 4-connected to the slice's border is the
//     surroundings of the body (the scan may cut through the lungs at its first/last slice, so a 3D border fill would
//     remove them);
//  3. the remaining air is split into 6-connected components; the largest is kept, and the second largest too when
//     it has at least secondComponentFraction of the largest's voxels (two lungs not joined through the airways);
//     smaller pockets (bowel gas, table foam) are dropped;
//  4. holes are filled slice by slice (vessels and nodules inside the lung are above the threshold).
// "Axial" is the image axis closest to the patient's superior-inferior axis (physical z in ITK's LPS frame), taken
// from the direction matrix.
#include "itkImage.h"
#include "itkMacro.h"
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

namespace dmrtools
{
struct LungMaskParameters
{
  double threshold{ -400.0 };            ///< HU: lung parenchyma and air are below
  double secondComponentFraction{ 0.1 }; ///< keep the 2nd component when >= this fraction of the largest
};

struct LungMaskReport
{
  unsigned int components{ 0 }; ///< components kept (0, 1 or 2)
  size_t       voxels{ 0 };
  double       volumeLitres{ 0.0 };
  unsigned int axialAxis{ 2 }; ///< image axis used as the slice normal
};

using LungMaskImageType = itk::Image<uint8_t, 3>;

/** Image axis (0..2) whose direction is closest to the patient's superior-inferior axis (physical z). */
inline unsigned int
SuperiorInferiorAxis(const itk::ImageBase<3> * image)
{
  const auto & dir = image->GetDirection();
  unsigned int best = 2;
  double       bestValue = -1.0;
  for (unsigned int a = 0; a < 3; ++a)
  {
    if (std::abs(dir[2][a]) > bestValue)
    {
      bestValue = std::abs(dir[2][a]);
      best = a;
    }
  }
  return best;
}

namespace detail
{
/** Flood fill over pixels with in[p] == value, 4-connected within each slice normal to axis, seeded at the slice
 * borders; marks reached pixels with reached[p] = 1. */
inline void
FillFromSliceBorders(const std::array<size_t, 3> & size,
                     unsigned int                  axis,
                     const std::vector<uint8_t> &  in,
                     uint8_t                       value,
                     std::vector<uint8_t> &        reached)
{
  const std::array<size_t, 3> stride{ 1, size[0], size[0] * size[1] };
  const unsigned int          a0 = axis == 0 ? 1 : 0;
  const unsigned int          a1 = axis == 2 ? 1 : 2;
  std::vector<size_t>         stack;
  for (size_t s = 0; s < size[axis]; ++s)
  {
    const size_t base = s * stride[axis];
    auto         seed = [&](size_t i, size_t j) {
      const size_t p = base + i * stride[a0] + j * stride[a1];
      if (in[p] == value && !reached[p])
      {
        reached[p] = 1;
        stack.push_back(p);
      }
    };
    for (size_t i = 0; i < size[a0]; ++i)
    {
      seed(i, 0);
      seed(i, size[a1] - 1);
    }
    for (size_t j = 0; j < size[a1]; ++j)
    {
      seed(0, j);
      seed(size[a0] - 1, j);
    }
    while (!stack.empty())
    {
      const size_t p = stack.back();
      stack.pop_back();
      const size_t i = (p / stride[a0]) % size[a0];
      const size_t j = (p / stride[a1]) % size[a1];
      auto         visit = [&](size_t q) {
        if (in[q] == value && !reached[q])
        {
          reached[q] = 1;
          stack.push_back(q);
        }
      };
      if (i > 0)
      {
        visit(p - stride[a0]);
      }
      if (i + 1 < size[a0])
      {
        visit(p + stride[a0]);
      }
      if (j > 0)
      {
        visit(p - stride[a1]);
      }
      if (j + 1 < size[a1])
      {
        visit(p + stride[a1]);
      }
    }
  }
}
} // namespace detail

/** Lung mask (1 inside, 0 outside) of a 3D CT in HU on the CT's grid; report (optional) receives what was kept. */
template <typename TImage>
LungMaskImageType::Pointer
LungMask(const TImage * ct, const LungMaskParameters & parameters = {}, LungMaskReport * report = nullptr)
{
  static_assert(TImage::ImageDimension == 3, "LungMask needs a 3D CT");
  const auto                  region = ct->GetLargestPossibleRegion();
  const std::array<size_t, 3> size{ region.GetSize(0), region.GetSize(1), region.GetSize(2) };
  const std::array<size_t, 3> stride{ 1, size[0], size[0] * size[1] };
  const size_t                n = size[0] * size[1] * size[2];
  const auto *                buffer = ct->GetBufferPointer();
  const unsigned int          axis = SuperiorInferiorAxis(ct);

  // 1-2: air, then air not connected to a slice border
  std::vector<uint8_t> air(n), outside(n, 0);
  for (size_t p = 0; p < n; ++p)
  {
    air[p] = static_cast<double>(buffer[p]) < parameters.threshold ? 1 : 0;
  }
  detail::FillFromSliceBorders(size, axis, air, 1, outside);

  // 3: 6-connected components of the inner air
  std::vector<int32_t> label(n, -1);
  std::vector<size_t>  componentSize;
  std::vector<size_t>  stack;
  for (size_t p0 = 0; p0 < n; ++p0)
  {
    if (!air[p0] || outside[p0] || label[p0] >= 0)
    {
      continue;
    }
    const auto id = static_cast<int32_t>(componentSize.size());
    size_t     count = 0;
    label[p0] = id;
    stack.push_back(p0);
    while (!stack.empty())
    {
      const size_t p = stack.back();
      stack.pop_back();
      ++count;
      for (unsigned int k = 0; k < 3; ++k)
      {
        const size_t i = (p / stride[k]) % size[k];
        if (i > 0 && air[p - stride[k]] && !outside[p - stride[k]] && label[p - stride[k]] < 0)
        {
          label[p - stride[k]] = id;
          stack.push_back(p - stride[k]);
        }
        if (i + 1 < size[k] && air[p + stride[k]] && !outside[p + stride[k]] && label[p + stride[k]] < 0)
        {
          label[p + stride[k]] = id;
          stack.push_back(p + stride[k]);
        }
      }
    }
    componentSize.push_back(count);
  }
  std::vector<int32_t> order(componentSize.size());
  for (size_t c = 0; c < order.size(); ++c)
  {
    order[c] = static_cast<int32_t>(c);
  }
  std::sort(order.begin(), order.end(), [&](int32_t a, int32_t b) { return componentSize[a] > componentSize[b]; });
  std::vector<uint8_t> keep(componentSize.size(), 0);
  unsigned int         kept = 0;
  if (!order.empty())
  {
    keep[order[0]] = 1;
    kept = 1;
    if (order.size() > 1 && static_cast<double>(componentSize[order[1]]) >=
                              parameters.secondComponentFraction * static_cast<double>(componentSize[order[0]]))
    {
      keep[order[1]] = 1;
      kept = 2;
    }
  }

  // 4: fill holes slice by slice (non-lung pixels not reachable from the slice border)
  std::vector<uint8_t> lung(n, 0);
  for (size_t p = 0; p < n; ++p)
  {
    lung[p] = label[p] >= 0 && keep[label[p]] ? 1 : 0;
  }
  std::fill(outside.begin(), outside.end(), 0);
  detail::FillFromSliceBorders(size, axis, lung, 0, outside);

  auto mask = LungMaskImageType::New();
  mask->CopyInformation(ct);
  mask->SetRegions(region);
  mask->Allocate();
  auto * m = mask->GetBufferPointer();
  size_t voxels = 0;
  for (size_t p = 0; p < n; ++p)
  {
    m[p] = (lung[p] || !outside[p]) && kept > 0 ? 1 : 0;
    voxels += m[p];
  }
  if (report)
  {
    const auto & h = ct->GetSpacing();
    report->components = kept;
    report->voxels = voxels;
    report->volumeLitres = static_cast<double>(voxels) * h[0] * h[1] * h[2] * 1e-6;
    report->axialAxis = axis;
  }
  return mask;
}
} // namespace dmrtools

#endif
