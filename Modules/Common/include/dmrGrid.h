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
#ifndef dmrGrid_h
#define dmrGrid_h

#include "dmrSimplexGeometry.h" // FloorByTruncation, CeilByTruncation
#include "itkImageBase.h"
#include "itkImageToImageFilterCommon.h"
#include "itkMultiThreaderBase.h"
#include <array>
#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <limits>
#include <algorithm>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

namespace itk
{
namespace dmr
{
/** \brief Flat-array view of an image grid in the "grid frame".
 *
 * The grid frame has its axes along the image axes and is measured in mm: a pixel with index i sits at
 * p = spacing (.) (i - start). It differs from ITK's physical space only by the image origin and the rotation
 * (or reflection) in Direction, which preserve distances, so densities, centroids, Delaunay triangulations and
 * linear-elastic stiffness computed in the grid frame are the physical ones. Vectors convert to physical space
 * by v_phys = Direction v_grid.
 * \ingroup DynamicMeshRegistration */
template <unsigned int VDimension>
struct Grid
{
  static constexpr unsigned int  Dimension = VDimension;
  std::array<size_t, VDimension> size{};
  std::array<size_t, VDimension> stride{};
  std::array<double, VDimension> spacing{};
  size_t                         numberOfPixels{ 0 };

  Grid() = default;

  template <typename TSize, typename TSpacing>
  Grid(const TSize & sz, const TSpacing & sp)
  {
    size_t s = 1;
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      size[k] = static_cast<size_t>(sz[k]);
      spacing[k] = static_cast<double>(sp[k]);
      stride[k] = s;
      s *= size[k];
    }
    numberOfPixels = s;
  }

  /** Grid of an image's largest possible region (the whole image). */
  static Grid
  FromImage(const ImageBase<VDimension> * image)
  {
    return Grid(image->GetLargestPossibleRegion().GetSize(), image->GetSpacing());
  }

  std::array<int64_t, VDimension>
  Index(size_t linear) const
  {
    std::array<int64_t, VDimension> idx;
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      idx[k] = static_cast<int64_t>(linear % size[k]);
      linear /= size[k];
    }
    return idx;
  }

  double
  PixelVolume() const
  {
    double v = 1.0;
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      v *= spacing[k];
    }
    return v;
  }

  /** True when the pixel lies on the border of the image box. */
  bool
  OnBorder(const std::array<int64_t, VDimension> & idx) const
  {
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      if (idx[k] == 0 || idx[k] == static_cast<int64_t>(size[k]) - 1)
      {
        return true;
      }
    }
    return false;
  }
};

/** The two pixels of the finite difference along axis k at pixel p (index idx): its neighbours, one-sided at the
 * border (p itself for a single-pixel axis), and their distance in mm (2 or 1 spacings; 0 when lo == hi). */
struct DifferenceStencil
{
  size_t lo;
  size_t hi;
  double h;
};
template <unsigned int VDimension>
inline DifferenceStencil
DifferenceAlong(const Grid<VDimension> &                                     grid,
                const std::array<int64_t, static_cast<size_t>(VDimension)> & idx, // VDimension deduced from grid
                size_t                                                       p,
                unsigned int                                                 k)
{
  const size_t lo = idx[k] > 0 ? p - grid.stride[k] : p;
  const size_t hi = idx[k] + 1 < static_cast<int64_t>(grid.size[k]) ? p + grid.stride[k] : p;
  return { lo, hi, (hi == lo ? 0.0 : (hi - lo == 2 * grid.stride[k] ? 2.0 : 1.0)) * grid.spacing[k] };
}

/** Grid::Index without a division per axis: for grids of at most 2^32 - 1 pixels with no axis of size 1, floor(n / d)
 * is the high 64 bits of M n with M = floor((2^64 - 1) / d) + 1, exact for all n, d below 2^32 (Lemire, Kaser and
 * Kurz, "Faster remainder by direct computation", 2019); other grids take Grid::Index. For the per-pixel loops that
 * visit pixels out of order (the CVT's active lists), where three 64-bit divisions per pixel are a measurable cost.
 * \ingroup DynamicMeshRegistration */
template <unsigned int VDimension>
class GridIndexer
{
public:
  GridIndexer() = default;
  explicit GridIndexer(const Grid<VDimension> & grid)
    : m_Grid(grid)
  {
    m_ByMultiplication = grid.numberOfPixels <= std::numeric_limits<uint32_t>::max();
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      m_ByMultiplication = m_ByMultiplication && grid.size[k] > 1;
      m_Reciprocal[k] = grid.size[k] > 1 ? std::numeric_limits<uint64_t>::max() / grid.size[k] + 1 : 0;
    }
  }

  /** The same as Grid::Index(linear) for every pixel of the grid. */
  std::array<int64_t, VDimension>
  Index(size_t linear) const
  {
    if (!m_ByMultiplication)
    {
      return m_Grid.Index(linear);
    }
    std::array<int64_t, VDimension> idx;
    uint64_t                        rest = linear;
    for (unsigned int k = 0; k + 1 < VDimension; ++k)
    {
      const uint64_t q = static_cast<uint64_t>((static_cast<unsigned __int128>(m_Reciprocal[k]) * rest) >> 64);
      idx[k] = static_cast<int64_t>(rest - q * m_Grid.size[k]);
      rest = q;
    }
    idx[VDimension - 1] = static_cast<int64_t>(rest);
    return idx;
  }

  /** True when Index divides by multiplication. */
  bool
  GetByMultiplication() const
  {
    return m_ByMultiplication;
  }

private:
  Grid<VDimension>                 m_Grid;
  bool                             m_ByMultiplication{ false };
  std::array<uint64_t, VDimension> m_Reciprocal{};
};

/** body(p, idx) for the pixels p in [begin, end) in order, idx = grid.Index(p) advanced pixel by pixel (no division
 * per pixel). */
template <unsigned int VDimension, typename TBody>
inline void
ForEachPixel(const Grid<VDimension> & grid, size_t begin, size_t end, TBody && body)
{
  if (begin >= end)
  {
    return;
  }
  std::array<int64_t, VDimension> idx = grid.Index(begin);
  for (size_t p = begin; p < end; ++p)
  {
    body(p, static_cast<const std::array<int64_t, VDimension> &>(idx));
    for (unsigned int k = 0; k < VDimension && ++idx[k] == static_cast<int64_t>(grid.size[k]); ++k)
    {
      idx[k] = 0;
    }
  }
}

/** ForEachPixel for loops that take two neighbouring pixels of a row at once (dmr::DoublePair): in pixel order over
 * [begin, end), pair(p, idx) for p and p + 1 where both lie in the row and in the range and pairable(p) holds (the
 * caller's condition on both pixels), one(p, idx) for a pixel taken alone. */
template <unsigned int VDimension, typename TPairable, typename TPair, typename TOne>
inline void
ForEachPixelOrRowPair(const Grid<VDimension> & grid,
                      size_t                   begin,
                      size_t                   end,
                      TPairable &&             pairable,
                      TPair &&                 pair,
                      TOne &&                  one)
{
  if (begin >= end)
  {
    return;
  }
  std::array<int64_t, VDimension> idx = grid.Index(begin);
  const int64_t                   rowSize = static_cast<int64_t>(grid.size[0]);
  for (size_t p = begin; p < end;)
  {
    if (idx[0] + 1 < rowSize && p + 1 < end && pairable(p))
    {
      pair(p, static_cast<const std::array<int64_t, VDimension> &>(idx));
      p += 2;
      idx[0] += 2;
    }
    else
    {
      one(p, static_cast<const std::array<int64_t, VDimension> &>(idx));
      ++p;
      ++idx[0];
    }
    for (unsigned int k = 0; k + 1 < VDimension && idx[k] == static_cast<int64_t>(grid.size[k]); ++k)
    {
      idx[k] = 0;
      ++idx[k + 1];
    }
  }
}

/** The corners of the multilinear interpolation at a continuous index, clamped to the border (zero-flux extension):
 * body(offset, weight) for every corner whose weight w x prod(frac or 1 - frac) is not zero, in a fixed corner order
 * (offset: the corner's pixel in the grid). */
template <unsigned int VDimension, typename TBody>
inline void
ForEachInterpolationCorner(const Grid<VDimension> & grid, const double * cidx, double w, TBody && body)
{
  size_t base[VDimension];
  size_t step[VDimension];
  double frac[VDimension];
  for (unsigned int k = 0; k < VDimension; ++k)
  {
    const double hi = static_cast<double>(grid.size[k] - 1);
    double       c = cidx[k] < 0.0 ? 0.0 : (cidx[k] > hi ? hi : cidx[k]);
    // c lies in [0, size - 1] (or is NaN, which takes the clamp below), where truncation is floor: the same i and f
    // as std::floor, which baseline x86-64 code (no SSE4.1 roundsd) evaluates by a much slower sequence
    size_t i = c >= 0.0 ? static_cast<size_t>(static_cast<int64_t>(c)) : std::numeric_limits<size_t>::max();
    double f = static_cast<double>(i);
    if (i >= grid.size[k] - 1)
    {
      i = grid.size[k] > 1 ? grid.size[k] - 2 : 0;
      f = static_cast<double>(i);
    }
    base[k] = i * grid.stride[k];
    step[k] = grid.size[k] > 1 ? grid.stride[k] : 0;
    frac[k] = c - f;
  }
  size_t offset0 = 0;
  for (unsigned int k = 0; k < VDimension; ++k)
  {
    offset0 += base[k];
  }
  for (unsigned int corner = 0; corner < (1u << VDimension); ++corner)
  {
    double weight = w;
    size_t offset = offset0;
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      if (corner & (1u << k))
      {
        weight *= frac[k];
        offset += step[k];
      }
      else
      {
        weight *= 1.0 - frac[k];
      }
    }
    if (weight != 0.0)
    {
      body(offset, weight);
    }
  }
}

/** Multilinear interpolation of NComp interleaved float components at a continuous index; positions outside the
 * image are clamped to the border (zero-flux extension). Adds w * value into out[]. */
template <unsigned int VDimension, unsigned int NComp>
inline void
InterpolateAdd(const Grid<VDimension> & grid, const float * data, const double * cidx, double w, double * out)
{
  ForEachInterpolationCorner<VDimension>(grid, cidx, w, [&](size_t offset, double weight) {
    const float * v = data + offset * NComp;
    for (unsigned int c = 0; c < NComp; ++c)
    {
      out[c] += weight * static_cast<double>(v[c]);
    }
  });
}

/** InterpolateAdd of two images on the same grid at the same continuous index (NA and NB interleaved components):
 * the corner weights are computed once; every output gets the very operations of its own InterpolateAdd call, so the
 * sums are the same bit for bit. */
template <unsigned int VDimension, unsigned int NA, unsigned int NB>
inline void
InterpolateAddPair(const Grid<VDimension> & grid,
                   const float *            a,
                   const float *            b,
                   const double *           cidx,
                   double                   w,
                   double *                 outA,
                   double *                 outB)
{
  ForEachInterpolationCorner<VDimension>(grid, cidx, w, [&](size_t offset, double weight) {
    const float * va = a + offset * NA;
    const float * vb = b + offset * NB;
    for (unsigned int c = 0; c < NA; ++c)
    {
      outA[c] += weight * static_cast<double>(va[c]);
    }
    for (unsigned int c = 0; c < NB; ++c)
    {
      outB[c] += weight * static_cast<double>(vb[c]);
    }
  });
}

/** Runs body(begin, end) over [0, n) in contiguous chunks through ITK's threader, so that
 * ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS and the filter's work-unit settings keep control. */
template <typename TBody>
void
ParallelForChunks(MultiThreaderBase * threader, size_t n, TBody && body, size_t minChunk = 1024)
{
  if (n == 0)
  {
    return;
  }
  const size_t workUnits = threader ? std::max<size_t>(1, threader->GetNumberOfWorkUnits()) : 1;
  size_t       chunks = std::min<size_t>(workUnits * 4, (n + minChunk - 1) / minChunk);
  chunks = std::max<size_t>(chunks, 1);
  if (chunks == 1 || threader == nullptr)
  {
    body(size_t{ 0 }, n);
    return;
  }
  const size_t chunkSize = (n + chunks - 1) / chunks;
  threader->ParallelizeArray(
    0,
    chunks,
    [&](SizeValueType c) {
      const size_t b = c * chunkSize;
      const size_t e = std::min(n, b + chunkSize);
      if (b < e)
      {
        body(b, e);
      }
    },
    nullptr);
}
/** Runs body(chunkId) for chunkId in [0, numberOfChunks) through ITK's threader. Callers that need deterministic
 * results combine per-chunk outputs in chunk order. */
template <typename TBody>
void
ParallelForChunkIds(MultiThreaderBase * threader, size_t numberOfChunks, TBody && body)
{
  if (threader == nullptr || numberOfChunks <= 1 || threader->GetNumberOfWorkUnits() <= 1)
  {
    for (size_t c = 0; c < numberOfChunks; ++c)
    {
      body(c);
    }
    return;
  }
  threader->ParallelizeArray(
    0, numberOfChunks, [&](SizeValueType c) { body(static_cast<size_t>(c)); }, nullptr);
}

/** The smallest i in [0, n) with bad(i), or n when there is none; on the threader's work units (64 chunks), with the
 * same answer as a serial scan. */
template <typename TPredicate>
size_t
FirstIndexWhere(MultiThreaderBase * threader, size_t n, TPredicate && bad)
{
  const size_t        nChunks = std::max<size_t>(1, std::min<size_t>(64, n / 4096));
  const size_t        chunk = (n + nChunks - 1) / nChunks;
  std::vector<size_t> first(nChunks, n);
  ParallelForChunkIds(threader, nChunks, [&](size_t c) {
    const size_t end = std::min(n, (c + 1) * chunk);
    // blocks of 256 tested without a branch per element (vectorisable), searched only when one of them is bad
    for (size_t b = std::min(n, c * chunk); b < end; b += 256)
    {
      const size_t blockEnd = std::min(end, b + 256);
      bool         any = false;
      for (size_t i = b; i < blockEnd; ++i)
      {
        any |= bad(i);
      }
      if (any)
      {
        for (size_t i = b; i < blockEnd; ++i)
        {
          if (bad(i))
          {
            first[c] = i;
            return;
          }
        }
      }
    }
  });
  return *std::min_element(first.begin(), first.end());
}

/** Why `image` does not lie on the grid of `reference` (the same largest region, start and size, and the same origin,
 * spacing and direction), or an empty string when it does. Origin and spacing are compared to coordinateTolerance x
 * the reference's first spacing, the direction to directionTolerance: ImageToImageFilter's rule. For inputs that are
 * read pixel for pixel with the reference (a mask, a displacement field, initial labels); referenceName names the
 * reference in the reason. */
template <unsigned int VDimension>
std::string
GridMismatch(const ImageBase<VDimension> * reference,
             const ImageBase<VDimension> * image,
             double                        coordinateTolerance,
             double                        directionTolerance,
             const char *                  referenceName = "the fixed image")
{
  std::ostringstream why;
  const auto &       region = image->GetLargestPossibleRegion();
  const auto &       referenceRegion = reference->GetLargestPossibleRegion();
  const double       tolerance = std::abs(coordinateTolerance * reference->GetSpacing()[0]);
  if (region.GetSize() != referenceRegion.GetSize())
  {
    why << "its size " << region.GetSize() << " differs from " << referenceName << " size "
        << referenceRegion.GetSize();
  }
  else if (region.GetIndex() != referenceRegion.GetIndex())
  {
    why << "its region starts at " << region.GetIndex() << ", " << referenceName << "'s at "
        << referenceRegion.GetIndex();
  }
  else if (!image->GetOrigin().GetVnlVector().is_equal(reference->GetOrigin().GetVnlVector(), tolerance))
  {
    why << "its origin " << image->GetOrigin() << " differs from " << referenceName << "'s " << reference->GetOrigin();
  }
  else if (!image->GetSpacing().GetVnlVector().is_equal(reference->GetSpacing().GetVnlVector(), tolerance))
  {
    why << "its spacing " << image->GetSpacing() << " differs from " << referenceName << "'s "
        << reference->GetSpacing();
  }
  else if (!image->GetDirection().GetVnlMatrix().as_ref().is_equal(reference->GetDirection().GetVnlMatrix().as_ref(),
                                                                   directionTolerance))
  {
    why << "its direction differs from " << referenceName << "'s";
  }
  return why.str();
}

/** GridMismatch at ITK's global default tolerances (ImageToImageFilterCommon): the rule by which
 * FEMRegistrationMethod takes its fixed mask and initial displacement field, so that a caller that prepares them (the
 * tool resamples what is off the grid) decides by the very same rule. */
template <unsigned int VDimension>
std::string
GridMismatchAtDefaultTolerances(const ImageBase<VDimension> * reference, const ImageBase<VDimension> * image)
{
  return GridMismatch<VDimension>(reference,
                                  image,
                                  ImageToImageFilterCommon::GetGlobalDefaultCoordinateTolerance(),
                                  ImageToImageFilterCommon::GetGlobalDefaultDirectionTolerance());
}

/** The largest |(D^T D - I)_ij| of the image's direction D: 0 for a rotation or reflection. */
template <unsigned int VDimension>
double
DirectionOrthonormalityError(const ImageBase<VDimension> * image)
{
  const auto & d = image->GetDirection();
  double       error = 0.0;
  for (unsigned int i = 0; i < VDimension; ++i)
  {
    for (unsigned int j = 0; j < VDimension; ++j)
    {
      double dot = 0.0;
      for (unsigned int k = 0; k < VDimension; ++k)
      {
        dot += d[k][i] * d[k][j];
      }
      error = std::max(error, std::abs(dot - (i == j ? 1.0 : 0.0)));
    }
  }
  return error;
}

/** Entries of D^T D - I up to this are taken as rounding (direction cosines stored with 4 to 6 decimals, as DICOM
 * headers and NIfTI's single-precision sform hold them); beyond it a direction is sheared or scaled. */
constexpr double DirectionOrthonormalityTolerance = 1e-3;

/** Why the image's direction is not a rotation or reflection (empty if it is): the method turns physical vectors into
 * the grid frame with D^T, which is D's inverse only then, so a sheared or scaled direction (ITK and MetaImage headers
 * allow any matrix) gave wrong forces and fields without a word. name names the image in the reason. */
template <unsigned int VDimension>
std::string
DirectionNotOrthonormal(const ImageBase<VDimension> * image, const char * name)
{
  const double error = DirectionOrthonormalityError<VDimension>(image);
  if (!(error <= DirectionOrthonormalityTolerance))
  {
    std::ostringstream why;
    why << "the " << name << "'s direction matrix is not orthonormal (D^T D differs from the identity by up to "
        << error << "): the registration needs direction cosines that form a rotation; resample the image onto a grid "
        << "with orthogonal unit axes";
    return why.str();
  }
  return "";
}

/** DirectionNotOrthonormal of the first of the named images that fails it, "" if none does (null images are skipped).
 */
template <unsigned int VDimension>
std::string
FirstDirectionNotOrthonormal(std::initializer_list<std::pair<const ImageBase<VDimension> *, const char *>> namedImages)
{
  for (const auto & [image, name] : namedImages)
  {
    const std::string why = image ? DirectionNotOrthonormal<VDimension>(image, name) : std::string();
    if (!why.empty())
    {
      return why;
    }
  }
  return "";
}

/** The physical coordinates of an image must tell its pixels apart to this fraction of its smallest spacing. */
constexpr double CoordinateResolutionTolerance = 1e-5;

/** Why the image's physical coordinates cannot tell its pixels apart (empty if they can): in double precision the
 * largest coordinate of its box's corners must be exact to CoordinateResolutionTolerance of its smallest spacing. An
 * origin far from 0 (a header in other units, a corrupt header) otherwise made the registration compute with
 * coordinates that no longer separate neighbouring pixels: with an origin of 1e16 mm and 1 mm pixels it reported a
 * "registration" whose field folded (det J down to -5.8), further out a mesh that did not cover the image or "no free
 * node". name names the image in the reason. */
template <unsigned int VDimension>
std::string
CoordinatesDoNotResolvePixels(const ImageBase<VDimension> * image, const char * name)
{
  const auto & region = image->GetLargestPossibleRegion();
  double       largest = 0.0;
  bool         finite = true;
  for (unsigned int corner = 0; corner < (1u << VDimension); ++corner)
  {
    typename ImageBase<VDimension>::IndexType index = region.GetIndex();
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      if ((corner >> k) & 1u)
      {
        index[k] += static_cast<IndexValueType>(region.GetSize()[k]) - 1;
      }
    }
    typename ImageBase<VDimension>::PointType point;
    image->TransformIndexToPhysicalPoint(index, point);
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      finite = finite && std::isfinite(point[k]);
      largest = std::max(largest, std::abs(point[k]));
    }
  }
  double smallest = std::numeric_limits<double>::infinity();
  for (unsigned int k = 0; k < VDimension; ++k)
  {
    finite = finite && std::isfinite(image->GetSpacing()[k]);
    smallest = std::min(smallest, std::abs(image->GetSpacing()[k]));
  }
  if (!finite) // std::max and std::min pass over a NaN, so it is looked for on its own
  {
    std::ostringstream why;
    why << "the " << name << "'s physical coordinates are not finite numbers (origin " << image->GetOrigin()
        << ", spacing " << image->GetSpacing() << "): the header is corrupt";
    return why.str();
  }
  const double resolution = std::nextafter(largest, std::numeric_limits<double>::infinity()) - largest;
  if (resolution <= CoordinateResolutionTolerance * smallest)
  {
    return "";
  }
  std::ostringstream why;
  why << "the " << name << "'s physical coordinates reach " << largest << " mm, where double precision resolves only "
      << resolution << " mm, more than " << CoordinateResolutionTolerance << " of its smallest spacing (" << smallest
      << " mm): the registration's geometry needs finer coordinates; the header's origin (or spacing) is likely "
      << "wrong, e.g. in other units";
  return why.str();
}

/** Why single precision cannot hold the image's geometry (empty if it can). The registration keeps its fields, forces
 * and densities in floats measured in mm: a float must resolve CoordinateResolutionTolerance of the smallest spacing
 * as a normal number, and the image's extent divided by that tolerance must stay finite, which leaves the squares and
 * differences of the field's values room. Beyond these bounds a spacing of 1e-45 mm gave a "registration" that moved
 * nothing with exit 0, and one of 3e38 mm a NaN density. name names the image in the reason. */
template <unsigned int VDimension>
std::string
SpacingOutsideSinglePrecision(const ImageBase<VDimension> * image, const char * name)
{
  double smallest = std::numeric_limits<double>::infinity();
  double extent = 0.0;
  for (unsigned int k = 0; k < VDimension; ++k)
  {
    const double spacing = std::abs(image->GetSpacing()[k]);
    smallest = std::min(smallest, spacing);
    extent = std::max(extent, spacing * static_cast<double>(image->GetLargestPossibleRegion().GetSize()[k]));
  }
  const double lowest = static_cast<double>(std::numeric_limits<float>::min()) / CoordinateResolutionTolerance;
  const double highest = static_cast<double>(std::numeric_limits<float>::max()) * CoordinateResolutionTolerance;
  if (smallest >= lowest && extent <= highest)
  {
    return "";
  }
  std::ostringstream why;
  why << "the " << name << "'s spacing " << image->GetSpacing() << " mm ";
  if (smallest < lowest)
  {
    why << "is below " << lowest;
  }
  else
  {
    why << "makes an extent of " << extent << " mm, above " << highest;
  }
  why << " mm, outside what the registration's single-precision fields can hold; the header's spacing is likely "
      << "wrong, e.g. in other units";
  return why.str();
}

/** Why the image's geometry is one the registration cannot compute in (empty if it is not): its physical
 * coordinates do not tell its pixels apart (CoordinatesDoNotResolvePixels) or single precision cannot hold its
 * spacing (SpacingOutsideSinglePrecision). name names the image in the reason. */
template <unsigned int VDimension>
std::string
GeometryOutsidePrecision(const ImageBase<VDimension> * image, const char * name)
{
  const std::string far = CoordinatesDoNotResolvePixels<VDimension>(image, name);
  return far.empty() ? SpacingOutsideSinglePrecision<VDimension>(image, name) : far;
}

/** Why a registration's fixed and moving images (either may be null, and is then skipped) have a geometry it cannot
 * compute in (empty if they have none): a direction that is not a rotation (FirstDirectionNotOrthonormal), then
 * GeometryOutsidePrecision, the fixed image first. */
template <unsigned int VDimension>
std::string
FixedAndMovingGeometryProblem(const ImageBase<VDimension> * fixed, const ImageBase<VDimension> * moving)
{
  const std::string skew =
    FirstDirectionNotOrthonormal<VDimension>({ { fixed, "fixed image" }, { moving, "moving image" } });
  if (!skew.empty())
  {
    return skew;
  }
  const std::string fixedWhy = fixed ? GeometryOutsidePrecision<VDimension>(fixed, "fixed image") : std::string();
  return !fixedWhy.empty() || !moving ? fixedWhy : GeometryOutsidePrecision<VDimension>(moving, "moving image");
}

} // namespace dmr
} // namespace itk

#endif
