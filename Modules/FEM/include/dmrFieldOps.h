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
#ifndef dmrFieldOps_h
#define dmrFieldOps_h

#include "dmrDoublePair.h"
#include "dmrGrid.h"
#include <vector>
#include <cmath>

namespace itk
{
namespace dmr
{
/** Displacement-field algebra on flat grid-frame fields (D interleaved floats, mm along the image axes), written
 * for data-parallel execution (one independent output pixel per work item, no allocation inside the loops).
 * \ingroup DynamicMeshRegistration */

/** out(x) = v(x) + w(x + v(x)): the displacement of W o V where W(x) = x + w(x), V(x) = x + v(x).
 * w is sampled multilinearly (clamped at the border). out may not alias w; it may alias v. */
template <unsigned int D>
void
ComposeFields(const Grid<D> & grid, const float * w, const float * v, float * out, MultiThreaderBase * threader)
{
  auto pixel = [&](size_t p, const std::array<int64_t, D> & idx) {
    double c[D], s[D] = {};
    for (unsigned int k = 0; k < D; ++k)
    {
      c[k] = static_cast<double>(idx[k]) + static_cast<double>(v[p * D + k]) / grid.spacing[k];
    }
    InterpolateAdd<D, D>(grid, w, c, 1.0, s);
    for (unsigned int k = 0; k < D; ++k)
    {
      out[p * D + k] = static_cast<float>(static_cast<double>(v[p * D + k]) + s[k]);
    }
  };
#if DMR_HAVE_DOUBLE_PAIR
  // Two neighbouring pixels of a row at once: `pixel`'s operations in the two lanes of SSE2 registers, the same doubles
  // bit for bit (as in DensityFieldFilter's force loop). The pair also adds the corners of weight 0, which changes a
  // sum only where such a corner holds a non-finite value; a pixel whose pair sum is not finite is computed again
  // alone. Both lanes are read before either is written (out may alias v).
  bool pairs = true;
  for (unsigned int k = 0; k < D; ++k)
  {
    pairs = pairs && grid.size[k] < (size_t(1) << 31);
  }
  if (pairs)
  {
    auto pixelPair = [&](size_t p, const std::array<int64_t, D> & idx) {
      DoublePair c[D], s[D];
      for (unsigned int k = 0; k < D; ++k)
      {
        const DoublePair i = DoublePair::Of(static_cast<double>(idx[k]), static_cast<double>(idx[k] + (k == 0)));
        c[k] = i + DoublePair::OfFloats(v[p * D + k], v[(p + 1) * D + k]) / DoublePair::Both(grid.spacing[k]);
        s[k] = DoublePair::Both(0.0);
      }
      ForEachInterpolationCornerPair<D>(grid, c, [&](size_t o0, size_t o1, DoublePair weight) {
        for (unsigned int k = 0; k < D; ++k)
        {
          s[k] += weight * DoublePair::OfFloats(w[o0 * D + k], w[o1 * D + k]);
        }
      });
      DoublePair sum[D];
      bool       finite[2] = { true, true };
      for (unsigned int k = 0; k < D; ++k)
      {
        sum[k] = DoublePair::OfFloats(v[p * D + k], v[(p + 1) * D + k]) + s[k];
        finite[0] = finite[0] && std::isfinite(s[k].Lane0());
        finite[1] = finite[1] && std::isfinite(s[k].Lane1());
      }
      for (unsigned int lane = 0; lane < 2; ++lane)
      {
        if (!finite[lane])
        {
          std::array<int64_t, D> laneIdx = idx;
          laneIdx[0] += lane;
          pixel(p + lane, laneIdx);
          continue;
        }
        for (unsigned int k = 0; k < D; ++k)
        {
          out[(p + lane) * D + k] = static_cast<float>(lane == 0 ? sum[k].Lane0() : sum[k].Lane1());
        }
      }
    };
    ParallelForChunks(threader, grid.numberOfPixels, [&](size_t b, size_t e) {
      ForEachPixelOrRowPair(
        grid, b, e, [](size_t) { return true; }, pixelPair, pixel);
    });
    return;
  }
#endif
  ParallelForChunks(threader, grid.numberOfPixels, [&](size_t b, size_t e) { ForEachPixel(grid, b, e, pixel); });
}

/** The two bounds of ExponentialField, in pixel units: the largest displacement (max over pixels and axes of
 * |v_k| / spacing_k) and the largest difference of v between neighbouring pixels (max over pixels, axes k and
 * components r of |v_r(p + e_k) - v_r(p)| / spacing_r), a discrete bound on the displacement gradient. */
struct FieldBounds
{
  double displacement{ 0.0 };
  double neighbourDifference{ 0.0 };
};

/** FieldBounds of v in one pass, on the threader's work units when one is given (64 chunks; a maximum does not
 * depend on the order); 0 for no pixel. The pass keeps the largest |v_k| and |v_r(p + e_k) - v_r(p)| per component
 * and divides by the spacing once at the end: a correctly rounded division by a positive number never reverses an
 * order, so max_p fl(x_p / s) = fl(max_p x_p / s), the same value as dividing at every pixel. */
template <unsigned int D>
FieldBounds
FieldBoundsInPixels(const Grid<D> & grid, const float * v, MultiThreaderBase * threader = nullptr)
{
  struct Maxima
  {
    double displacement[D]{};        // max |v_k| per component k
    double neighbourDifference[D]{}; // max |v_r(p + e_k) - v_r(p)| over the axes k, per component r
  };
  const size_t        nChunks = 64;
  const size_t        chunk = (grid.numberOfPixels + nChunks - 1) / nChunks;
  std::vector<Maxima> partial(nChunks);
  ParallelForChunkIds(threader, nChunks, [&](size_t c) {
    const size_t end = std::min(grid.numberOfPixels, (c + 1) * chunk);
    Maxima       m;
    ForEachPixel(grid, std::min(end, c * chunk), end, [&](size_t p, const std::array<int64_t, D> & idx) {
      for (unsigned int k = 0; k < D; ++k)
      {
        m.displacement[k] = std::max(m.displacement[k], std::abs(static_cast<double>(v[p * D + k])));
        if (idx[k] + 1 >= static_cast<int64_t>(grid.size[k]))
        {
          continue;
        }
        const size_t q = p + grid.stride[k];
        for (unsigned int r = 0; r < D; ++r)
        {
          m.neighbourDifference[r] =
            std::max(m.neighbourDifference[r], std::abs(static_cast<double>(v[q * D + r]) - v[p * D + r]));
        }
      }
    });
    partial[c] = m;
  });
  FieldBounds bounds;
  for (const auto & m : partial)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      bounds.displacement = std::max(bounds.displacement, m.displacement[k] / grid.spacing[k]);
      bounds.neighbourDifference = std::max(bounds.neighbourDifference, m.neighbourDifference[k] / grid.spacing[k]);
    }
  }
  return bounds;
}

/** exp(v) by scaling and squaring (Vercauteren et al. 2009, paper ref. [39]): v is halved until both its largest
 * displacement and its largest change between neighbouring pixels are below half a pixel, then the field is
 * composed with itself as many times. The second bound keeps each small step invertible where v varies sharply
 * (thin elements of a static mesh), so det J stays positive. scratch is resized as needed; it may be the storage
 * of v itself (v is read completely before scratch is written), which saves one field of memory. The squarings
 * alternate between out and scratch (no copies), starting where the last one lands in out. Returns the number of
 * squarings; bounds, when given, receives v's FieldBoundsInPixels. */
template <unsigned int D>
unsigned int
ExponentialField(const Grid<D> &      grid,
                 const float *        v,
                 float *              out,
                 std::vector<float> & scratch,
                 MultiThreaderBase *  threader,
                 FieldBounds *        bounds = nullptr)
{
  const size_t      n = grid.numberOfPixels * D;
  const FieldBounds b = FieldBoundsInPixels<D>(grid, v, threader);
  if (bounds)
  {
    *bounds = b;
  }
  const double maxNorm = std::max(b.displacement, b.neighbourDifference);
  unsigned int squarings = 0;
  while (maxNorm / std::ldexp(1.0, static_cast<int>(squarings)) > 0.5 && squarings < 30)
  {
    ++squarings;
  }
  const float scale = static_cast<float>(std::ldexp(1.0, -static_cast<int>(squarings)));
  scratch.resize(n); // when v lives in scratch, scratch already has n values and nothing moves
  float * buffers[2] = { out, scratch.data() };
  float * from = buffers[squarings % 2];
  ParallelForChunks(threader, n, [&](size_t b0, size_t e0) {
    for (size_t i = b0; i < e0; ++i)
    {
      from[i] = v[i] * scale;
    }
  });
  for (unsigned int s = 0; s < squarings; ++s)
  {
    float * to = from == out ? scratch.data() : out;
    ComposeFields<D>(grid, from, from, to, threader); // to = e o e
    from = to;
  }
  return squarings;
}

/** Outcome of InvertField. */
struct FieldInversion
{
  double       residual{ 0.0 }; // largest |v(y) + w(y + v(y))| / spacing over pixels and axes, in pixels
  unsigned int iterations{ 0 };
};

/** The inverse of the transformation x -> x + w(x) as a field v on the same grid: y -> y + v(y), with
 * v(y) = -w(y + v(y)), w interpolated as ComposeFields does (multilinear, clamped to the border). Fixed-point
 * iteration from v = -w, all pixels at once from the previous iterate (the result does not depend on the threads): v
 * <- v - s r with the residual r(y) = v(y) + w(y + v(y)) and the step s = 1, halved (down to 1/64) whenever the largest
 * residual grew. Stops when the largest residual is at most `tolerance` pixels or after `maximumIterations`; the
 * caller decides from the returned residual whether the inverse is good enough. A small residual does not show that
 * w is invertible: each pixel's iteration looks for one point that maps onto it, and may find one where w is folded
 * (det(I + grad w) <= 0 somewhere), which has no inverse; InverseDisplacementField checks that first. v must not
 * alias w. */
template <unsigned int D>
FieldInversion
InvertField(const Grid<D> &     grid,
            const float *       w,
            float *             v,
            MultiThreaderBase * threader,
            unsigned int        maximumIterations = 200,
            double              tolerance = 1e-3)
{
  const size_t n = grid.numberOfPixels * D;
  for (size_t i = 0; i < n; ++i)
  {
    v[i] = -w[i];
  }
  std::vector<float>  residual(n);
  const size_t        nChunks = 64;
  const size_t        chunk = (grid.numberOfPixels + nChunks - 1) / nChunks;
  std::vector<double> chunkMax(nChunks);
  // r = v + w(y + v) at every pixel; returns the largest |r_k| / spacing_k (infinite where r is not finite)
  auto residuals = [&]() {
    ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      const size_t end = std::min(grid.numberOfPixels, (c + 1) * chunk);
      double       m = 0.0;
      ForEachPixel(grid, std::min(end, c * chunk), end, [&](size_t p, const std::array<int64_t, D> & idx) {
        double at[D], r[D];
        for (unsigned int k = 0; k < D; ++k)
        {
          at[k] = static_cast<double>(idx[k]) + static_cast<double>(v[p * D + k]) / grid.spacing[k];
          r[k] = static_cast<double>(v[p * D + k]);
        }
        InterpolateAdd<D, D>(grid, w, at, 1.0, r);
        for (unsigned int k = 0; k < D; ++k)
        {
          residual[p * D + k] = static_cast<float>(r[k]);
          const double e = std::abs(r[k]) / grid.spacing[k];
          m = std::isfinite(e) ? std::max(m, e) : std::numeric_limits<double>::infinity();
        }
      });
      chunkMax[c] = m;
    });
    return *std::max_element(chunkMax.begin(), chunkMax.end());
  };
  FieldInversion result;
  result.residual = residuals();
  double step = 1.0;
  while (result.iterations < maximumIterations && result.residual > tolerance && std::isfinite(result.residual))
  {
    ++result.iterations;
    ParallelForChunks(threader, n, [&](size_t b, size_t e) {
      for (size_t i = b; i < e; ++i)
      {
        v[i] = static_cast<float>(static_cast<double>(v[i]) - step * static_cast<double>(residual[i]));
      }
    });
    const double previous = result.residual;
    result.residual = residuals();
    if (result.residual > previous)
    {
      step = std::max(step / 2.0, 1.0 / 64.0);
    }
  }
  return result;
}

/** det(I + grad u) at every pixel (central differences, one-sided at the border; grid frame, so the value is the
 * physical Jacobian determinant). Writes into jac and returns {min, max}. */
template <unsigned int D>
std::pair<double, double>
JacobianDeterminant(const Grid<D> & grid, const float * u, float * jac, MultiThreaderBase * threader)
{
  const size_t                           nChunks = 64;
  std::vector<std::pair<double, double>> partial(
    nChunks, { std::numeric_limits<double>::max(), -std::numeric_limits<double>::max() });
  const size_t chunk = (grid.numberOfPixels + nChunks - 1) / nChunks;
  ParallelForChunkIds(threader, nChunks, [&](size_t c) {
    const size_t end = std::min(grid.numberOfPixels, (c + 1) * chunk);
    auto &       mm = partial[c];
    ForEachPixel(grid, c * chunk, end, [&](size_t p, const std::array<int64_t, D> & idx) {
      double J[D][D];
      for (unsigned int k = 0; k < D; ++k) // derivative along axis k
      {
        const auto d = DifferenceAlong(grid, idx, p, k);
        for (unsigned int r = 0; r < D; ++r)
        {
          J[r][k] =
            (r == k ? 1.0 : 0.0) + (d.h > 0 ? (static_cast<double>(u[d.hi * D + r]) - u[d.lo * D + r]) / d.h : 0.0);
        }
      }
      double det;
      if (D == 2)
      {
        det = J[0][0] * J[1][1] - J[0][1] * J[1][0];
      }
      else
      {
        det = J[0][0] * (J[1][1] * J[2][2] - J[1][2] * J[2][1]) - J[0][1] * (J[1][0] * J[2][2] - J[1][2] * J[2][0]) +
              J[0][2] * (J[1][0] * J[2][1] - J[1][1] * J[2][0]);
      }
      if (jac)
      {
        jac[p] = static_cast<float>(det);
      }
      mm.first = std::min(mm.first, det);
      mm.second = std::max(mm.second, det);
    });
  });
  std::pair<double, double> r = partial[0];
  for (const auto & mm : partial)
  {
    r.first = std::min(r.first, mm.first);
    r.second = std::max(r.second, mm.second);
  }
  return r;
}
} // namespace dmr
} // namespace itk

#endif
