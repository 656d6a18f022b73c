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
#ifndef dmrErrorStatistics_h
#define dmrErrorStatistics_h

// Error summaries for the command-line tools and their tests: {mean, std, p95, max} of a list of distances in mm
// (landmark TRE, dense displacement error), the dense error |u_est - u_truth| of two displacement fields inside
// a mask, and how far a field's inverse is from undoing it.
#include "dmrFieldImage.h"
#include "itkImage.h"
#include "itkImageRegionConstIterator.h"
#include "itkMacro.h"
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <ostream>
#include <utility>
#include <vector>

namespace dmrtools
{
/** Summary of non-negative errors in mm. std is the population standard deviation (divides by n); p95 is the 95th
 * percentile with linear interpolation between order statistics (numpy's default: rank 0.95 (n - 1)). All zero when
 * count == 0. */
struct ErrorStatistics
{
  std::size_t count{ 0 };
  double      mean{ 0.0 };
  double      std{ 0.0 };
  double      p95{ 0.0 };
  double      max{ 0.0 };
};

inline std::ostream &
operator<<(std::ostream & os, const ErrorStatistics & s)
{
  return os << "mean " << s.mean << " mm, std " << s.std << " mm, p95 " << s.p95 << " mm, max " << s.max << " mm (n "
            << s.count << ")";
}

/** Percentile q in [0, 1] of values (linear interpolation between order statistics); reorders values. */
inline double
Percentile(std::vector<double> & values, double q)
{
  if (values.empty())
  {
    return 0.0;
  }
  const double      rank = std::clamp(q, 0.0, 1.0) * static_cast<double>(values.size() - 1);
  const std::size_t lo = static_cast<std::size_t>(std::floor(rank));
  const std::size_t hi = std::min(lo + 1, values.size() - 1);
  std::nth_element(values.begin(), values.begin() + lo, values.end());
  const double vlo = values[lo];
  if (hi == lo)
  {
    return vlo;
  }
  // after nth_element every element past lo is >= values[lo]: the next order statistic is their minimum
  const double vhi = *std::min_element(values.begin() + lo + 1, values.end());
  return vlo + (rank - static_cast<double>(lo)) * (vhi - vlo);
}

/** mean, std (population), p95 and max of errors. */
inline ErrorStatistics
SummarizeErrors(std::vector<double> errors)
{
  ErrorStatistics s;
  s.count = errors.size();
  if (errors.empty())
  {
    return s;
  }
  double sum = 0.0;
  for (const double e : errors)
  {
    sum += e;
    s.max = std::max(s.max, e);
  }
  s.mean = sum / static_cast<double>(s.count);
  double squares = 0.0;
  for (const double e : errors)
  {
    squares += (e - s.mean) * (e - s.mean);
  }
  s.std = std::sqrt(squares / static_cast<double>(s.count));
  s.p95 = Percentile(errors, 0.95);
  return s;
}

/** True when a and b have the same size, and spacing, origin and direction agree to 1e-4 (relative to the spacing;
 * origins also to 1e-3 mm): the float precision of NIfTI headers. */
template <unsigned int D>
bool
SameGrid(const itk::ImageBase<D> * a, const itk::ImageBase<D> * b)
{
  if (a->GetLargestPossibleRegion().GetSize() != b->GetLargestPossibleRegion().GetSize())
  {
    return false;
  }
  const double tol = 1e-4;
  for (unsigned int i = 0; i < D; ++i)
  {
    const double h = a->GetSpacing()[i];
    bool         same =
      std::abs(h - b->GetSpacing()[i]) <= tol * h && std::abs(a->GetOrigin()[i] - b->GetOrigin()[i]) <= tol * h + 1e-3;
    for (unsigned int j = 0; j < D; ++j)
    {
      same = same && std::abs(a->GetDirection()[i][j] - b->GetDirection()[i][j]) <= tol;
    }
    if (!same)
    {
      return false;
    }
  }
  return true;
}

namespace detail
{
/** Throws unless SameGrid(a, b). */
template <unsigned int D>
void
RequireSameGrid(const itk::ImageBase<D> * a, const itk::ImageBase<D> * b, const char * what)
{
  if (a->GetLargestPossibleRegion().GetSize() != b->GetLargestPossibleRegion().GetSize())
  {
    itkGenericExceptionMacro(<< what << ": the images differ in size (" << a->GetLargestPossibleRegion().GetSize()
                             << " vs " << b->GetLargestPossibleRegion().GetSize() << ")");
  }
  if (!SameGrid<D>(a, b))
  {
    itkGenericExceptionMacro(<< what << ": the images differ in spacing, origin or direction");
  }
}
} // namespace detail

namespace detail
{
/** errors[i] = |a(x) - b(x)| (b == nullptr: |a(x)|) over the voxels with mask(x) != 0 (all voxels without mask). */
template <typename TFieldA, typename TFieldB, typename TMask>
ErrorStatistics
FieldDifferenceStatistics(const TFieldA * a, const TFieldB * b, const TMask * mask, const char * what)
{
  constexpr unsigned int D = TFieldA::ImageDimension;
  static_assert(TFieldB::ImageDimension == D && TMask::ImageDimension == D, "dimensions differ");
  if (a == nullptr)
  {
    itkGenericExceptionMacro(<< what << ": missing displacement field");
  }
  if (b)
  {
    RequireSameGrid<D>(a, b, what);
  }
  if (mask)
  {
    RequireSameGrid<D>(mask, a, what);
  }
  const auto                             region = a->GetLargestPossibleRegion();
  itk::ImageRegionConstIterator<TFieldA> ia(a, region);
  itk::ImageRegionConstIterator<TFieldB> ib;
  itk::ImageRegionConstIterator<TMask>   im;
  if (b)
  {
    ib = itk::ImageRegionConstIterator<TFieldB>(b, region);
  }
  if (mask)
  {
    im = itk::ImageRegionConstIterator<TMask>(mask, region);
  }
  std::vector<double> errors;
  errors.reserve(mask ? region.GetNumberOfPixels() / 8 : region.GetNumberOfPixels());
  for (; !ia.IsAtEnd(); ++ia)
  {
    const bool inside = mask == nullptr || im.Get() != 0;
    if (inside)
    {
      double sq = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        const double d = static_cast<double>(ia.Get()[k]) - (b ? static_cast<double>(ib.Get()[k]) : 0.0);
        sq += d * d;
      }
      errors.push_back(std::sqrt(sq));
    }
    if (b)
    {
      ++ib;
    }
    if (mask)
    {
      ++im;
    }
  }
  return SummarizeErrors(std::move(errors));
}
} // namespace detail

/** Dense displacement error: statistics of |u_est(x) - u_truth(x)| in mm over the voxels x where mask(x) != 0 (all
 * voxels when mask is nullptr). The fields (any itk::Vector pixel types, displacements in mm, physical frame) and
 * the mask must share one grid, the fixed image's; throws itk::ExceptionObject otherwise. */
template <typename TEstimateField, typename TTruthField, typename TMask>
ErrorStatistics
DisplacementErrorInMask(const TEstimateField * estimate, const TTruthField * truth, const TMask * mask)
{
  if (truth == nullptr)
  {
    itkGenericExceptionMacro("DisplacementErrorInMask: missing displacement field");
  }
  return detail::FieldDifferenceStatistics(estimate, truth, mask, "DisplacementErrorInMask");
}

/** Statistics of |u(x)| in mm inside the mask (nullptr: everywhere): the dense error of the zero (identity)
 * estimate, i.e. the initial error before registration. */
template <typename TField, typename TMask>
ErrorStatistics
DisplacementMagnitudeInMask(const TField * field, const TMask * mask)
{
  return detail::FieldDifferenceStatistics(
    field, static_cast<const TField *>(nullptr), mask, "DisplacementMagnitudeInMask");
}
/** How far v is from the inverse of u (two physical displacement fields on one grid, e.g. FEMRegistrationMethod's
 * field and its inverse): first the errors |u(x) + v(x + u(x))| (mm) at the pixels x whose image x + u(x) lies inside
 * the grid, then |v(y) + u(y + v(y))|, v and u sampled multilinearly. All zero for an exact inverse. Each field is
 * brought to the grid frame once. */
template <typename TField>
std::pair<ErrorStatistics, ErrorStatistics>
InverseConsistency(const TField * u, const TField * v, itk::MultiThreaderBase * threader)
{
  constexpr unsigned int D = TField::ImageDimension;
  if (u->GetLargestPossibleRegion().GetSize() != v->GetLargestPossibleRegion().GetSize())
  {
    itkGenericExceptionMacro("InverseConsistency: the two fields must lie on one grid");
  }
  const auto grid = itk::dmr::Grid<D>::FromImage(u);
  const auto ug = itk::dmr::ToGridFrame(u);
  const auto vg = itk::dmr::ToGridFrame(v);
  // |a(x) + b(x + a(x))| where defined, in pixel order (NaN marks a point that leaves the grid)
  auto errors = [&](const std::vector<float> & a, const std::vector<float> & b) {
    std::vector<double> error(grid.numberOfPixels, std::numeric_limits<double>::quiet_NaN());
    itk::dmr::ParallelForChunks(threader, grid.numberOfPixels, [&](size_t begin, size_t end) {
      itk::dmr::ForEachPixel(grid, begin, end, [&](size_t p, const std::array<int64_t, D> & idx) {
        double c[D], s[D] = {};
        for (unsigned int k = 0; k < D; ++k)
        {
          c[k] = static_cast<double>(idx[k]) + static_cast<double>(a[p * D + k]) / grid.spacing[k];
          if (!(c[k] >= 0.0 && c[k] <= static_cast<double>(grid.size[k] - 1)))
          {
            return;
          }
        }
        itk::dmr::InterpolateAdd<D, D>(grid, b.data(), c, 1.0, s);
        double e2 = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          const double e = static_cast<double>(a[p * D + k]) + s[k];
          e2 += e * e;
        }
        error[p] = std::sqrt(e2);
      });
    });
    error.erase(std::remove_if(error.begin(), error.end(), [](double e) { return std::isnan(e); }), error.end());
    return SummarizeErrors(std::move(error));
  };
  const ErrorStatistics forward = errors(ug, vg);
  return { forward, errors(vg, ug) };
}
} // namespace dmrtools

#endif
