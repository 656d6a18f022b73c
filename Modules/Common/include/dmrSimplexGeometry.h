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
#ifndef dmrSimplexGeometry_h
#define dmrSimplexGeometry_h

#include "dmrFixedPointGather.h" // DMR_HOST_DEVICE
#include <cmath>
#include <cstdint>

namespace itk
{
namespace dmr
{
/** std::floor and std::ceil by truncation, for the per-row and per-pixel loops: baseline x86-64 code (no SSE4.1
 * roundsd) evaluates the std versions by a slow sequence or a call. Within |x| < 2^52 the truncation is exact and the
 * value is adjusted by one where it went the wrong way; beyond it (every double is whole there), for NaN and
 * infinities, the std versions. The same values, except that a zero result carries no sign. */
DMR_HOST_DEVICE inline double
FloorByTruncation(double x)
{
  if (!(fabs(x) < 4503599627370496.0))
  {
    return floor(x);
  }
  const double t = static_cast<double>(static_cast<int64_t>(x));
  return t > x ? t - 1.0 : t;
}
DMR_HOST_DEVICE inline double
CeilByTruncation(double x)
{
  if (!(fabs(x) < 4503599627370496.0))
  {
    return ceil(x);
  }
  const double t = static_cast<double>(static_cast<int64_t>(x));
  return t < x ? t + 1.0 : t;
}

/** The geometry of one simplex (triangle or tetrahedron) from its D + 1 vertices v[0..D] (grid frame, mm), one
 * definition for the CPU (SimplexMesh::EdgeMatrix, BarycentricMap::ElementAffine) and the GPU's element set-up, so
 * that both rasterise and assemble from the same bits.
 *
 * SimplexEdgeInverse: x0 = v[0]; returns det M of the edge matrix M (column c: v[c + 1] - v[0]) and, when inv is
 * given and det != 0, writes M^-1 (row-major) as the transposed cofactors over det. */
template <unsigned int D>
DMR_HOST_DEVICE inline double
SimplexEdgeInverse(const double (&v)[D + 1][D], double (&x0)[D], double (*inv)[D][D])
{
  double m[D][D];
  for (unsigned int r = 0; r < D; ++r)
  {
    x0[r] = v[0][r];
    for (unsigned int c = 0; c < D; ++c)
    {
      m[r][c] = v[c + 1][r] - x0[r];
    }
  }
  double det;
  if constexpr (D == 2)
  {
    det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    if (inv && det != 0.0)
    {
      (*inv)[0][0] = m[1][1] / det;
      (*inv)[0][1] = -m[0][1] / det;
      (*inv)[1][0] = -m[1][0] / det;
      (*inv)[1][1] = m[0][0] / det;
    }
  }
  else
  {
    det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
          m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    if (inv && det != 0.0)
    {
      for (unsigned int r = 0; r < D; ++r)
      {
        for (unsigned int c = 0; c < D; ++c)
        {
          // transposed cofactor over det
          const unsigned int r1 = (c + 1) % 3, r2 = (c + 2) % 3, c1 = (r + 1) % 3, c2 = (r + 2) % 3;
          (*inv)[r][c] = (m[r1][c1] * m[r2][c2] - m[r1][c2] * m[r2][c1]) / det;
        }
      }
    }
  }
  return det;
}

/** The pixel bounding box [lo, hi] of a simplex on a grid of size[k] pixels of spacing[k] mm: the pixels whose
 * index lies within a millionth of a pixel of the vertices' range, clipped to the grid. Returns false for an empty
 * box (along some axis no pixel index lies in that range: the simplex lies outside the grid, or is a sliver between
 * two pixel rows), which is then written as lo[0] = 1 > hi[0] = 0; the axes after that one are left as they were. */
template <unsigned int D>
DMR_HOST_DEVICE inline bool
SimplexPixelBox(const double (&v)[D + 1][D], const double * spacing, const int64_t * size, int64_t * lo, int64_t * hi)
{
  for (unsigned int k = 0; k < D; ++k)
  {
    double mn = 1.7976931348623157e308, mx = -mn; // as std::min and std::max from the largest double
    for (unsigned int i = 0; i <= D; ++i)
    {
      const double q = v[i][k] / spacing[k];
      mn = q < mn ? q : mn;
      mx = mx < q ? q : mx;
    }
    const int64_t first = static_cast<int64_t>(CeilByTruncation(mn - 1e-6));
    const int64_t last = static_cast<int64_t>(FloorByTruncation(mx + 1e-6));
    lo[k] = first > 0 ? first : 0;
    hi[k] = last < size[k] - 1 ? last : size[k] - 1;
    if (lo[k] > hi[k])
    {
      lo[0] = 1;
      hi[0] = 0;
      return false;
    }
  }
  return true;
}
} // namespace dmr
} // namespace itk

#endif
