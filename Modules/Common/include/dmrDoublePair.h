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
#ifndef dmrDoublePair_h
#define dmrDoublePair_h

#include "dmrGrid.h"

#include <cstdint>

// Two doubles in one SSE2 register, for the CPU loops that treat two neighbouring pixels at once. Every operation is
// the IEEE operation of the scalar code in each lane (addpd, subpd, mulpd, divpd, the compares), so a loop written on
// DoublePair gives every pixel the doubles of its scalar version, bit for bit (as long as the compiler does not fuse
// a * b + c into one rounding, which baseline x86-64 code cannot; the tests comparing pairs with single pixels would
// show it). Only where SSE2 is there (every x86-64 host); elsewhere DMR_HAVE_DOUBLE_PAIR is 0 and the callers keep
// their scalar loops (a build may also set it to 0).
#ifndef DMR_HAVE_DOUBLE_PAIR
#if (defined(__SSE2__) || defined(_M_X64)) && !defined(__CUDACC__)
#define DMR_HAVE_DOUBLE_PAIR 1
#else
#define DMR_HAVE_DOUBLE_PAIR 0
#endif
#endif
#if DMR_HAVE_DOUBLE_PAIR
#include <emmintrin.h>
#endif

namespace itk
{
namespace dmr
{
/** x as a T: the double itself, or (DoublePair) x in both lanes; for the formulas written once for one pixel and for
 * a pair. */
template <typename T>
inline T
Broadcast(double x)
{
  return x;
}
} // namespace dmr
} // namespace itk

#if DMR_HAVE_DOUBLE_PAIR
namespace itk
{
namespace dmr
{
/** Lane 0 and lane 1: the first and the second pixel of a pair. */
struct DoublePair
{
  __m128d v;

  static DoublePair
  Both(double a)
  {
    return { _mm_set1_pd(a) };
  }
  static DoublePair
  Of(double lane0, double lane1)
  {
    return { _mm_set_pd(lane1, lane0) };
  }
  /** Two consecutive doubles, p[0] in lane 0. */
  static DoublePair
  Load(const double * p)
  {
    return { _mm_loadu_pd(p) };
  }
  /** Two floats converted exactly to doubles (the scalar code's static_cast<double>). */
  static DoublePair
  OfFloats(float lane0, float lane1)
  {
    return Of(static_cast<double>(lane0), static_cast<double>(lane1));
  }
  double
  Lane0() const
  {
    return _mm_cvtsd_f64(v);
  }
  double
  Lane1() const
  {
    return _mm_cvtsd_f64(_mm_unpackhi_pd(v, v));
  }
  DoublePair &
  operator+=(DoublePair o)
  {
    v = _mm_add_pd(v, o.v);
    return *this;
  }
};

template <>
inline DoublePair
Broadcast<DoublePair>(double x)
{
  return DoublePair::Both(x);
}

inline DoublePair
operator+(DoublePair a, DoublePair b)
{
  return { _mm_add_pd(a.v, b.v) };
}
inline DoublePair
operator-(DoublePair a, DoublePair b)
{
  return { _mm_sub_pd(a.v, b.v) };
}
inline DoublePair
operator*(DoublePair a, DoublePair b)
{
  return { _mm_mul_pd(a.v, b.v) };
}
inline DoublePair
operator/(DoublePair a, DoublePair b)
{
  return { _mm_div_pd(a.v, b.v) };
}

/** ForEachInterpolationCorner for two positions at once: body(offset0, offset1, weight) for every corner, in the same
 * corner order, offsetN and lane N of weight those of position N. Unlike the scalar version it also visits corners of
 * weight 0, so a caller's sums equal the scalar ones only where the values read are finite (a finite value times 0 is
 * a zero, and a sum that starts at +0 is never -0, so adding it changes nothing). Every axis must have fewer than 2^31
 * pixels (the truncation is to 32-bit integers). */
template <unsigned int VDimension, typename TBody>
inline void
ForEachInterpolationCornerPair(const Grid<VDimension> & grid, const DoublePair * cidx, TBody && body)
{
  size_t     base0 = 0, base1 = 0;
  size_t     step[VDimension];
  DoublePair frac[VDimension];
  for (unsigned int k = 0; k < VDimension; ++k)
  {
    const __m128d hi = _mm_set1_pd(static_cast<double>(grid.size[k] - 1));
    const __m128d x = cidx[k].v;
    // c = x < 0 ? 0 : (x > hi ? hi : x), NaN kept, as in the scalar version
    const __m128d below = _mm_cmplt_pd(x, _mm_setzero_pd());
    const __m128d above = _mm_cmpgt_pd(x, hi);
    __m128d       c = _mm_or_pd(_mm_and_pd(above, hi), _mm_andnot_pd(above, x));
    c = _mm_andnot_pd(below, c); // +0 where x < 0
    // truncation toward zero; a NaN gives INT32_MIN, which the clamp below treats as the scalar version's SIZE_MAX
    const __m128i t = _mm_cvttpd_epi32(c);
    int64_t       i[2] = { _mm_cvtsi128_si32(t), _mm_cvtsi128_si32(_mm_shuffle_epi32(t, 1)) };
    const int64_t last = static_cast<int64_t>(grid.size[k]) - 1;
    for (int64_t & ii : i)
    {
      if (ii < 0 || ii >= last)
      {
        ii = grid.size[k] > 1 ? last - 1 : 0;
      }
    }
    base0 += static_cast<size_t>(i[0]) * grid.stride[k];
    base1 += static_cast<size_t>(i[1]) * grid.stride[k];
    step[k] = grid.size[k] > 1 ? grid.stride[k] : 0;
    frac[k] = { _mm_sub_pd(c, _mm_set_pd(static_cast<double>(i[1]), static_cast<double>(i[0]))) };
  }
  const DoublePair one = DoublePair::Both(1.0);
  for (unsigned int corner = 0; corner < (1u << VDimension); ++corner)
  {
    DoublePair weight = one;
    size_t     offset = 0;
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      if (corner & (1u << k))
      {
        weight = weight * frac[k];
        offset += step[k];
      }
      else
      {
        weight = weight * (one - frac[k]);
      }
    }
    body(base0 + offset, base1 + offset, weight);
  }
}
} // namespace dmr
} // namespace itk
#endif

#endif
