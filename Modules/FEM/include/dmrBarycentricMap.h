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
#ifndef dmrBarycentricMap_h
#define dmrBarycentricMap_h

#include "dmrFixedPointGather.h"
#include "dmrSimplexMesh.h"
#include <algorithm>
#include <cmath>
#include <limits>

namespace itk
{
namespace dmr
{
/** \brief Per-pixel element and barycentric coordinates of a simplex mesh over an image grid (paper 4.7).
 *
 * Built by rasterising every element: along each row of its bounding box the barycentric coordinates are affine in
 * the first index, so only the span where all of them can be >= 0 (widened by a pixel on each side) is tested, with
 * the same per-pixel test as a full scan of the box. A pixel centre on a shared edge/face is inside several elements;
 * the element with the lowest id wins (the rule the CUDA kernel uses too, there by an atomic minimum), so every pixel
 * lies in exactly one element. The threads take bands of planes along the slowest axis and rasterise the elements
 * reaching into their band in increasing id, so the first element to claim a pixel is its owner: no atomics, and the
 * weights are written in the same pass. Weights are in [0,1] and sum to 1.
 * Gather() forms the consistent load vector f_a = sum_x phi_a(x) f(x) dV; Interpolate() gives u(x) = sum_a phi_a(x)
 * u_a.
 * \ingroup DynamicMeshRegistration */
template <unsigned int D>
class BarycentricMap
{
public:
  static constexpr unsigned int NumberOfVertices = D + 1;

  void
  Build(const Grid<D> & grid, const SimplexMesh<D> & mesh, MultiThreaderBase * threader)
  {
    m_Grid = grid;
    const size_t n = grid.numberOfPixels;
    m_Element.resize(n);
    m_Weights.resize(n * NumberOfVertices);
    const size_t nElements = mesh.elements.size();
    // per-element inverse edge matrix, first vertex and pixel bounding box, computed once
    constexpr size_t                        affineSize = D * D + D;
    std::vector<double>                     affine(nElements * affineSize);
    std::vector<std::array<int64_t, 2 * D>> box(nElements);
    {
      const size_t nChunks = std::max<size_t>(1, std::min<size_t>(256, nElements / 64));
      const size_t chunk = (nElements + nChunks - 1) / nChunks;
      ParallelForChunkIds(threader, nChunks, [&](size_t c) {
        const size_t end = std::min(nElements, (c + 1) * chunk);
        for (size_t e = c * chunk; e < end; ++e)
        {
          ElementAffine(grid, mesh, e, affine.data() + e * affineSize, box[e].data(), box[e].data() + D);
        }
      });
    }
    // Bands of planes along the slowest axis, one task each. Every band lists the elements whose box reaches into it,
    // in increasing id, and rasterises their rows inside the band: the first element that claims a pixel has the
    // lowest id of those containing it, so no pixel is written twice and no atomic is needed.
    constexpr unsigned int S = D - 1;
    const size_t           planes = grid.size[S];
    const size_t           workUnits = threader ? std::max<size_t>(1, threader->GetNumberOfWorkUnits()) : 1;
    const size_t           nBands = std::max<size_t>(1, std::min<size_t>(planes, 4 * workUnits));
    std::vector<size_t>    bandOfPlane(planes);
    for (size_t b = 0; b < nBands; ++b)
    {
      for (size_t z = b * planes / nBands; z < (b + 1) * planes / nBands; ++z)
      {
        bandOfPlane[z] = b;
      }
    }
    std::vector<size_t> listStart(nBands + 1, 0);
    for (size_t e = 0; e < nElements; ++e)
    {
      if (box[e][0] <= box[e][D])
      {
        for (size_t b = bandOfPlane[box[e][S]]; b <= bandOfPlane[box[e][D + S]]; ++b)
        {
          ++listStart[b + 1];
        }
      }
    }
    for (size_t b = 0; b < nBands; ++b)
    {
      listStart[b + 1] += listStart[b];
    }
    std::vector<int32_t> list(listStart[nBands]);
    {
      std::vector<size_t> cursor(listStart.begin(), listStart.end() - 1);
      for (size_t e = 0; e < nElements; ++e)
      {
        if (box[e][0] <= box[e][D])
        {
          for (size_t b = bandOfPlane[box[e][S]]; b <= bandOfPlane[box[e][D + S]]; ++b)
          {
            list[cursor[b]++] = static_cast<int32_t>(e);
          }
        }
      }
    }
    constexpr int32_t   none = std::numeric_limits<int32_t>::max();
    std::vector<size_t> firstUncovered(nBands, n);
    ParallelForChunkIds(threader, nBands, [&](size_t band) {
      const int64_t zBegin = static_cast<int64_t>(band * planes / nBands);
      const int64_t zEnd = static_cast<int64_t>((band + 1) * planes / nBands);
      const size_t  pBegin = static_cast<size_t>(zBegin) * grid.stride[S];
      const size_t  pEnd = static_cast<size_t>(zEnd) * grid.stride[S];
      std::fill(m_Element.begin() + pBegin, m_Element.begin() + pEnd, none);
      for (size_t i = listStart[band]; i < listStart[band + 1]; ++i)
      {
        const int32_t e = list[i];
        double        inv[D][D], x0[D];
        std::copy(affine.data() + e * affineSize, affine.data() + e * affineSize + D * D, &inv[0][0]);
        std::copy(affine.data() + e * affineSize + D * D, affine.data() + (e + 1) * affineSize, x0);
        int64_t lo[D], hi[D];
        std::copy(box[e].data(), box[e].data() + D, lo);
        std::copy(box[e].data() + D, box[e].data() + 2 * D, hi);
        lo[S] = std::max(lo[S], zBegin);
        hi[S] = std::min(hi[S], zEnd - 1);
        // slope of every barycentric coordinate along axis 0 (per pixel) and its scale, for the row spans
        double slope[NumberOfVertices], scale[NumberOfVertices];
        slope[0] = 0.0;
        scale[0] = 0.0;
        for (unsigned int r = 0; r < D; ++r)
        {
          slope[r + 1] = inv[r][0] * grid.spacing[0];
          slope[0] -= slope[r + 1];
          scale[r + 1] = 0.0;
          for (unsigned int c = 0; c < D; ++c)
          {
            scale[r + 1] += std::abs(inv[r][c]) * grid.spacing[c];
          }
          scale[0] += scale[r + 1];
        }
        // one row (fixed indices 1..D-1) at a time
        int64_t idx[D];
        for (unsigned int k = 0; k < D; ++k)
        {
          idx[k] = lo[k];
        }
        while (true)
        {
          // the span of this row where lambda_v(i) = lambda_v(lo) + slope_v (i - lo) >= -1e-9 for all v, widened by
          // one pixel on each side against rounding; a flat coordinate only empties the row when clearly < 0
          idx[0] = lo[0];
          double lambda[NumberOfVertices];
          Barycentric(inv, x0, idx, lambda);
          double first = static_cast<double>(lo[0]), last = static_cast<double>(hi[0]);
          bool   empty = false;
          for (unsigned int v = 0; v < NumberOfVertices; ++v)
          {
            if (std::abs(slope[v]) <= 1e-9 * scale[v])
            {
              empty = empty || lambda[v] < -1e-6;
              continue;
            }
            const double at = static_cast<double>(lo[0]) + (-1e-9 - lambda[v]) / slope[v];
            if (slope[v] > 0.0)
            {
              first = std::max(first, FloorByTruncation(at) - 1.0);
            }
            else
            {
              last = std::min(last, CeilByTruncation(at) + 1.0);
            }
          }
          const int64_t rowEnd = empty ? lo[0] - 1 : static_cast<int64_t>(last);
          size_t        rowStart = 0;
          for (unsigned int k = 1; k < D; ++k)
          {
            rowStart += static_cast<size_t>(idx[k]) * grid.stride[k];
          }
          for (idx[0] = static_cast<int64_t>(first); idx[0] <= rowEnd; ++idx[0])
          {
            const size_t p = rowStart + static_cast<size_t>(idx[0]);
            if (m_Element[p] != none)
            {
              continue; // an element of lower id holds it
            }
            // the same test as a scan of the whole bounding box
            Barycentric(inv, x0, idx, lambda);
            bool inside = true;
            for (unsigned int v = 0; v < NumberOfVertices; ++v)
            {
              inside = inside && lambda[v] >= -1e-9;
            }
            if (inside)
            {
              // weights of the owner, clamped to [0,1] and renormalised
              m_Element[p] = e;
              double sum = 0.0;
              for (unsigned int v = 0; v < NumberOfVertices; ++v)
              {
                lambda[v] = std::min(1.0, std::max(0.0, lambda[v]));
                sum += lambda[v];
              }
              for (unsigned int v = 0; v < NumberOfVertices; ++v)
              {
                m_Weights[p * NumberOfVertices + v] = static_cast<float>(lambda[v] / sum);
              }
            }
          }
          unsigned int k = 1;
          for (; k < D; ++k)
          {
            if (++idx[k] <= hi[k])
            {
              break;
            }
            idx[k] = lo[k];
          }
          if (k == D)
          {
            break;
          }
        }
      }
      for (size_t p = pBegin; p < pEnd; ++p)
      {
        if (m_Element[p] == none)
        {
          m_Element[p] = -1;
          firstUncovered[band] = std::min(firstUncovered[band], p);
        }
      }
    });
    const size_t uncovered = *std::min_element(firstUncovered.begin(), firstUncovered.end());
    if (uncovered < n)
    {
      itkGenericExceptionMacro("BarycentricMap: pixel " << uncovered
                                                        << " is not covered by any element: the mesh does not cover "
                                                           "the image domain");
    }
    m_Mesh = &mesh;
  }

  /** Rasterisation set-up of element e: its inverse edge matrix (D x D, row-major) then its first vertex into
   * affine[0 .. D*D+D), and the pixel bounding box [lo, hi] (empty: lo[0] > hi[0]); a degenerate element gets a zero
   * matrix. The CUDA back-end computes the same numbers on the device through the same functions
   * (dmrSimplexGeometry.h), so both rasterise from the same bits. */
  static void
  ElementAffine(const Grid<D> &        grid,
                const SimplexMesh<D> & mesh,
                size_t                 e,
                double *               affine,
                int64_t *              lo,
                int64_t *              hi)
  {
    double v[D + 1][D], inv[D][D] = {}, x0[D];
    for (unsigned int i = 0; i <= D; ++i)
    {
      std::copy_n(&mesh.nodes[static_cast<size_t>(mesh.elements[e][i]) * D], D, v[i]);
    }
    SimplexEdgeInverse<D>(v, x0, &inv);
    std::copy(&inv[0][0], &inv[0][0] + D * D, affine);
    std::copy(x0, x0 + D, affine + D * D);
    int64_t size[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      size[k] = static_cast<int64_t>(grid.size[k]);
    }
    SimplexPixelBox<D>(v, grid.spacing.data(), size, lo, hi);
  }

  const std::vector<int32_t> &
  GetElements() const
  {
    return m_Element;
  }
  const std::vector<float> &
  GetWeights() const
  {
    return m_Weights;
  }

  /** Consistent nodal load f_a = scale x sum_x phi_a(x) f(x) for a D-component pixel field (grid frame), summed in
   * fixed point (dmrFixedPointGather.h) as the GPU's gather does: the result does not depend on how the pixels are
   * split among threads, and equals the GPU's bit for bit for the same weights and field. A field with a NaN or
   * infinite value gives NaN everywhere. */
  void
  Gather(const float * field, double scale, std::vector<double> & nodal, MultiThreaderBase * threader) const
  {
    const size_t nNodes = m_Mesh->NumberOfNodes();
    const size_t n = m_Grid.numberOfPixels;
    const size_t nChunks = std::max<size_t>(1, std::min<size_t>(32, n / 8192));
    const size_t chunk = (n + nChunks - 1) / nChunks;
    // the largest |f_k| (infinite when a value is not finite) gives the quantum
    std::vector<float> chunkMax(nChunks, 0.0f);
    ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      float        m = 0.0f;
      const size_t end = std::min(n, (c + 1) * chunk) * D;
      for (size_t i = c * chunk * D; i < end; ++i)
      {
        m = std::isfinite(field[i]) ? std::max(m, std::abs(field[i])) : std::numeric_limits<float>::infinity();
      }
      chunkMax[c] = m;
    });
    const double quantum =
      GatherQuantum(*std::max_element(chunkMax.begin(), chunkMax.end()), static_cast<long long>(n));
    nodal.assign(nNodes * D, 0.0);
    if (!(quantum > 0.0)) // no force (0), or one that is not finite (NaN)
    {
      std::fill(nodal.begin(), nodal.end(), quantum == 0.0 ? 0.0 : std::numeric_limits<double>::quiet_NaN());
      return;
    }
    const double                        inverse = 1.0 / quantum;
    std::vector<std::vector<long long>> partial(nChunks);
    ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      auto & acc = partial[c];
      acc.assign(nNodes * D, 0);
      const size_t end = std::min(n, (c + 1) * chunk);
      for (size_t p = c * chunk; p < end; ++p)
      {
        const auto & el = m_Mesh->elements[m_Element[p]];
        for (unsigned int v = 0; v < NumberOfVertices; ++v)
        {
          const float w = m_Weights[p * NumberOfVertices + v];
          for (unsigned int k = 0; k < D; ++k)
          {
            acc[el[v] * D + k] += GatherTerm(w, field[p * D + k], inverse);
          }
        }
      }
    });
    for (size_t i = 0; i < nodal.size(); ++i)
    {
      long long sum = 0;
      for (const auto & acc : partial)
      {
        sum += acc[i];
      }
      nodal[i] = GatherValue(sum, quantum, scale);
    }
  }

  /** u(x) = scale x sum_a phi_a(x) u_a into a D-component pixel field. */
  void
  Interpolate(const std::vector<double> & nodal, double scale, float * field, MultiThreaderBase * threader) const
  {
    ParallelForChunks(threader, m_Grid.numberOfPixels, [&](size_t b, size_t end) {
      for (size_t p = b; p < end; ++p)
      {
        const auto & el = m_Mesh->elements[m_Element[p]];
        double       u[D] = {};
        for (unsigned int v = 0; v < NumberOfVertices; ++v)
        {
          const double w = m_Weights[p * NumberOfVertices + v];
          for (unsigned int k = 0; k < D; ++k)
          {
            u[k] += w * nodal[el[v] * D + k];
          }
        }
        for (unsigned int k = 0; k < D; ++k)
        {
          field[p * D + k] = static_cast<float>(scale * u[k]);
        }
      }
    });
  }

private:
  void
  Barycentric(const double (&inv)[D][D], const double (&x0)[D], const int64_t * idx, double * lambda) const
  {
    double d[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      d[k] = static_cast<double>(idx[k]) * m_Grid.spacing[k] - x0[k];
    }
    double rest = 1.0;
    for (unsigned int r = 0; r < D; ++r)
    {
      double v = 0.0;
      for (unsigned int c = 0; c < D; ++c)
      {
        v += inv[r][c] * d[c];
      }
      lambda[r + 1] = v;
      rest -= v;
    }
    lambda[0] = rest;
  }

  Grid<D>                m_Grid;
  const SimplexMesh<D> * m_Mesh{ nullptr };
  std::vector<int32_t>   m_Element;
  std::vector<float>     m_Weights;
};
} // namespace dmr
} // namespace itk

#endif
