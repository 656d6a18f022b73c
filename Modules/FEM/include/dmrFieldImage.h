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
#ifndef dmrFieldImage_h
#define dmrFieldImage_h

#include "dmrFieldOps.h"
#include "itkImage.h"
#include <algorithm>
#include <cmath>
#include <vector>

namespace itk
{
namespace dmr
{
/** Physical-frame displacement image -> grid-frame flat field (u_grid = Direction^T u_phys). */
template <typename TField>
std::vector<float>
ToGridFrame(const TField * field)
{
  constexpr unsigned int D = TField::ImageDimension;
  const auto &           dir = field->GetDirection();
  const size_t           n = field->GetLargestPossibleRegion().GetNumberOfPixels();
  std::vector<float>     out(n * D);
  const auto *           in = field->GetBufferPointer();
  for (size_t p = 0; p < n; ++p)
  {
    for (unsigned int r = 0; r < D; ++r)
    {
      double v = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        v += dir[k][r] * in[p][k];
      }
      out[p * D + r] = static_cast<float>(v);
    }
  }
  return out;
}

/** det(I + grad u) of a physical displacement field as an image on the field's grid (equal to the determinant in
 * the grid frame, since the direction is a rotation/reflection). minMax receives the extreme values. */
template <typename TField>
typename Image<float, TField::ImageDimension>::Pointer
JacobianDeterminantImage(const TField * field, std::pair<double, double> & minMax, MultiThreaderBase * threader)
{
  constexpr unsigned int D = TField::ImageDimension;
  auto                   jac = Image<float, D>::New();
  jac->CopyInformation(field);
  jac->SetRegions(field->GetLargestPossibleRegion());
  jac->Allocate();
  const auto grid = Grid<D>::FromImage(field);
  const auto u = ToGridFrame(field);
  minMax = JacobianDeterminant<D>(grid, u.data(), jac->GetBufferPointer(), threader);
  return jac;
}
/** Statistics of an inverse consistency error (mm) over the pixels where it is defined. */
struct InverseConsistencyStatistics
{
  double mean{ 0.0 };
  double p95{ 0.0 };
  double max{ 0.0 };
  size_t count{ 0 };
};

/** |a(x) + b(x + a(x))| (mm) at every pixel x of a whose image x + a(x) lies inside the grid, b sampled multilinearly:
 * 0 everywhere when b is the inverse of a. a and b are physical displacement fields on one grid (the forward field and
 * the inverse of FEMRegistrationMethod). */
template <typename TField>
InverseConsistencyStatistics
InverseConsistency(const TField * a, const TField * b, MultiThreaderBase * threader)
{
  constexpr unsigned int D = TField::ImageDimension;
  if (a->GetLargestPossibleRegion().GetSize() != b->GetLargestPossibleRegion().GetSize())
  {
    itkGenericExceptionMacro("InverseConsistency: the two fields must lie on one grid");
  }
  const auto         grid = Grid<D>::FromImage(a);
  const auto         ag = ToGridFrame(a);
  const auto         bg = ToGridFrame(b);
  std::vector<float> error(grid.numberOfPixels, -1.0f); // -1: the point leaves the grid
  ParallelForChunks(threader, grid.numberOfPixels, [&](size_t begin, size_t end) {
    ForEachPixel(grid, begin, end, [&](size_t p, const std::array<int64_t, D> & idx) {
      double c[D], s[D] = {};
      for (unsigned int k = 0; k < D; ++k)
      {
        c[k] = static_cast<double>(idx[k]) + static_cast<double>(ag[p * D + k]) / grid.spacing[k];
        if (!(c[k] >= 0.0 && c[k] <= static_cast<double>(grid.size[k] - 1)))
        {
          return;
        }
      }
      InterpolateAdd<D, D>(grid, bg.data(), c, 1.0, s);
      double e2 = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        const double e = static_cast<double>(ag[p * D + k]) + s[k];
        e2 += e * e;
      }
      error[p] = static_cast<float>(std::sqrt(e2));
    });
  });
  InverseConsistencyStatistics statistics;
  std::vector<float>           inside;
  inside.reserve(error.size());
  double sum = 0.0;
  for (const float e : error)
  {
    if (e >= 0.0f)
    {
      inside.push_back(e);
      sum += e;
      statistics.max = std::max(statistics.max, static_cast<double>(e));
    }
  }
  statistics.count = inside.size();
  if (!inside.empty())
  {
    statistics.mean = sum / static_cast<double>(inside.size());
    const size_t k = std::min(inside.size() - 1, static_cast<size_t>(0.95 * static_cast<double>(inside.size())));
    std::nth_element(inside.begin(), inside.begin() + static_cast<std::ptrdiff_t>(k), inside.end());
    statistics.p95 = inside[k];
  }
  return statistics;
}
} // namespace dmr
} // namespace itk

#endif
