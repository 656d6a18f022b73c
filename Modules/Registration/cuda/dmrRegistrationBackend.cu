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
/** GPU registration iteration: force over the pyramid + density, element rasterisation (barycentric owner), force
 * gathering, nodal sampling, interpolation, exponential map by scaling and squaring and composition. Every kernel
 * mirrors the CPU reference (DensityFieldFilter, BarycentricMap, dmrFieldOps) in double arithmetic; the library
 * compiles these files with --fmad=false so products are rounded as on the CPU. Every reduction is deterministic:
 * per-block partials summed in a fixed order, maxima, or (the force gather) 64-bit fixed-point sums. */
#include "dmrRegistrationBackend.h"
#include "dmrCudaUtils.cuh"
#include "dmrElasticOperator.h"
#include "dmrFixedPointGather.h"
#include "dmrSimplexGeometry.h"

#include <cooperative_groups.h>
#include <cub/block/block_scan.cuh>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstring>
#include <limits>
#include <vector>

namespace itk
{
namespace dmr
{
namespace cuda
{
namespace
{
constexpr int MaxLevels = 8;
constexpr int Threads = 256;

struct DeviceGrid
{
  int       size[3];
  long long stride[3];
  double    spacing[3];
  long long n;
};

struct DeviceLevel
{
  int           fixedSize[3];
  long long     fixedStride[3];
  int           movingSize[3];
  long long     movingStride[3];
  const float * fixed;
  const float * moving;
  const float * gradient;
  double        FA[3][3], Fc[3], MA[3][3], Mc[3], MB[3][3];
  double        weight;
};

struct DeviceLevels
{
  DeviceLevel level[MaxLevels];
  int         count;
  double      direction[3][3]; // the fixed image's: u = float(Direction w), the CPU path's field image
};

template <int D>
__device__ inline void
IndexOf(const DeviceGrid & g, long long p, int * idx)
{
  for (int k = 0; k < D; ++k)
  {
    idx[k] = static_cast<int>(p % g.size[k]);
    p /= g.size[k];
  }
}

/** dmr::InterpolateAdd on the device: multilinear, clamped to the border. */
template <int D, int NC>
__device__ inline void
InterpolateAdd(const int *       size,
               const long long * stride,
               const float *     data,
               const double *    cidx,
               double            w,
               double *          out)
{
  long long offset0 = 0;
  long long step[D];
  double    frac[D];
  for (int k = 0; k < D; ++k)
  {
    const double hi = static_cast<double>(size[k] - 1);
    const double c = cidx[k] < 0.0 ? 0.0 : (cidx[k] > hi ? hi : cidx[k]);
    double       f = floor(c);
    long long    i = static_cast<long long>(f);
    if (i >= size[k] - 1)
    {
      i = size[k] > 1 ? size[k] - 2 : 0;
      f = static_cast<double>(i);
    }
    offset0 += i * stride[k];
    step[k] = size[k] > 1 ? stride[k] : 0;
    frac[k] = c - f;
  }
  for (unsigned int corner = 0; corner < (1u << D); ++corner)
  {
    double    weight = w;
    long long offset = offset0;
    for (int k = 0; k < D; ++k)
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
      const float * v = data + offset * NC;
      for (int c = 0; c < NC; ++c)
      {
        out[c] += weight * static_cast<double>(v[c]);
      }
    }
  }
}

/** combine(v over the block) with a fixed tree (every thread must call); valid in thread 0. The shuffle tree within
 * each warp, then the warps in order from `identity`: the same operations, hence the same result, on every call. */
template <typename TCombine>
__device__ inline double
BlockCombine(double v, double * shared, double identity, TCombine combine)
{
  for (int o = 16; o > 0; o >>= 1)
  {
    v = combine(v, __shfl_down_sync(0xffffffffu, v, o));
  }
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  __syncthreads(); // shared may still be read from an earlier call
  if (lane == 0)
  {
    shared[warp] = v;
  }
  __syncthreads();
  double s = identity;
  if (threadIdx.x == 0)
  {
    for (int w = 0; w < static_cast<int>(blockDim.x >> 5); ++w)
    {
      s = combine(s, shared[w]);
    }
  }
  return s;
}

/** Sum of v over the block (every thread must call); valid in thread 0. */
__device__ inline double
BlockSum(double v, double * shared)
{
  return BlockCombine(v, shared, 0.0, [](double a, double b) { return a + b; });
}

/** Largest v over the block (every thread must call; v >= 0); valid in thread 0. */
__device__ inline double
BlockMax(double v, double * shared)
{
  return BlockCombine(v, shared, 0.0, [](double a, double b) { return fmax(a, b); });
}

/** atomic max of a non-negative double (its bit pattern orders like the value). */
__device__ inline void
AtomicMaxNonNegative(unsigned long long * address, double v)
{
  atomicMax(address, static_cast<unsigned long long>(__double_as_longlong(v)));
}

/** out = float(Direction w) per component, as double: the floats of the CPU path's field image (double sums in
 * column order, rounded once; FEMRegistrationMethod::WriteGridFieldToImage). */
template <int D>
__device__ inline void
PhysicalFloats(const double (&direction)[3][3], const float * w, double * out)
{
  for (int r = 0; r < D; ++r)
  {
    double v = 0.0;
    for (int k = 0; k < D; ++k)
    {
      v += direction[r][k] * static_cast<double>(w[k]);
    }
    out[r] = static_cast<double>(static_cast<float>(v));
  }
}

template <int D>
__global__ void
ForceKernel(DeviceGrid      g,
            DeviceLevels    levels,
            const float *   w,
            bool            warpedGradient,
            const uint8_t * mask,
            float *         force,
            float *         f2out,
            double *        sums)
{
  __shared__ double shared[Threads / 32];
  double            mssd = 0.0, ssd = 0.0, f2sum = 0.0, inside = 0.0;
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < g.n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    if (mask && mask[p] == 0)
    {
      for (int k = 0; k < D; ++k)
      {
        force[p * D + k] = 0.0f;
      }
      f2out[p] = 0.0f;
      continue;
    }
    inside += 1.0;
    int idx[D];
    IndexOf<D>(g, p, idx);
    // The CPU path reads W from its field image, u = Direction w rounded to float per component
    // (FEMRegistrationMethod::WriteGridFieldToImage): the same floats here, and the CPU's formulas below, so that both
    // back-ends compute the same force for the same w, bit for bit (a difference in the last bits can flip a near-tie
    // of the greedy contraction and lead the two runs apart).
    double u[D];
    PhysicalFloats<D>(levels.direction, w + p * D, u);
    // warped moving gradient: Jt[j][k] = delta_jk + d u_k / d x_j in the grid frame (per mm; central differences,
    // one-sided at the border), as dmr::WarpJacobianTranspose on the CPU
    double Jt[D][D];
    for (int j = 0; j < D; ++j)
    {
      for (int k = 0; k < D; ++k)
      {
        Jt[j][k] = (j == k) ? 1.0 : 0.0;
      }
    }
    if (warpedGradient)
    {
      for (int j = 0; j < D; ++j)
      {
        const long long lo = idx[j] > 0 ? p - g.stride[j] : p;
        const long long hi = idx[j] + 1 < g.size[j] ? p + g.stride[j] : p;
        if (hi == lo)
        {
          continue;
        }
        const double h = static_cast<double>((hi - lo) / g.stride[j]) * g.spacing[j];
        double       uhi[D], ulo[D];
        PhysicalFloats<D>(levels.direction, w + hi * D, uhi);
        PhysicalFloats<D>(levels.direction, w + lo * D, ulo);
        for (int k = 0; k < D; ++k)
        {
          double du = 0.0;
          for (int m = 0; m < D; ++m)
          {
            du += levels.direction[m][k] * (uhi[m] - ulo[m]);
          }
          Jt[j][k] += du / h;
        }
      }
    }
    double f[D] = {};
    for (int l = 0; l < levels.count; ++l)
    {
      const DeviceLevel & L = levels.level[l];
      double              cf[D], cm[D];
      for (int r = 0; r < D; ++r)
      {
        cf[r] = L.Fc[r];
        cm[r] = L.Mc[r];
        for (int k = 0; k < D; ++k)
        {
          cf[r] += L.FA[r][k] * static_cast<double>(idx[k]);
          cm[r] += L.MA[r][k] * static_cast<double>(idx[k]) + L.MB[r][k] * u[k];
        }
      }
      double t = 0.0, s = 0.0, gr[D] = {};
      if (l == 0)
      {
        t = L.fixed[p];
      }
      else
      {
        InterpolateAdd<D, 1>(L.fixedSize, L.fixedStride, L.fixed, cf, 1.0, &t);
      }
      InterpolateAdd<D, 1>(L.movingSize, L.movingStride, L.moving, cm, 1.0, &s);
      InterpolateAdd<D, D>(L.movingSize, L.movingStride, L.gradient, cm, 1.0, gr);
      const double residual = t - s;
      mssd += L.weight * residual * residual;
      if (l == 0)
      {
        ssd += residual * residual;
      }
      for (int j = 0; j < D; ++j)
      {
        double gj = 0.0;
        for (int k = 0; k < D; ++k)
        {
          gj += Jt[j][k] * gr[k];
        }
        f[j] += 2.0 * residual * gj;
      }
    }
    double f2 = 0.0;
    for (int k = 0; k < D; ++k)
    {
      f2 += f[k] * f[k];
      force[p * D + k] = static_cast<float>(f[k]);
    }
    f2out[p] = static_cast<float>(f2);
    f2sum += f2;
  }
  const double a = BlockSum(mssd, shared);
  const double b = BlockSum(ssd, shared);
  const double c = BlockSum(f2sum, shared);
  const double d = BlockSum(inside, shared);
  if (threadIdx.x == 0)
  {
    // per-block partials, summed in block order on the host: deterministic, unlike atomics
    sums[4 * blockIdx.x + 0] = a;
    sums[4 * blockIdx.x + 1] = b;
    sums[4 * blockIdx.x + 2] = c;
    sums[4 * blockIdx.x + 3] = d;
  }
}

__global__ void
AddKernel(float * data, long long n, double alpha)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    data[p] = static_cast<float>(data[p] + alpha);
  }
}

/** The moving level's gradient image as dmr::GradientInto computes it on the CPU: per axis the central difference (one-
 * sided at the border, 0 on an axis of one pixel) over the distance in mm, then rotated by R into the fixed grid frame,
 * D interleaved floats. Every operation is explicitly rounded (no fused multiply-add) in the CPU's order, so the floats
 * are the CPU's, bit for bit. */
struct GradientParams
{
  int       size[3];
  long long stride[3];
  long long n;
  double    spacing[3];
  double    R[3][3];
};

template <int D>
__global__ void
MovingGradientKernel(GradientParams g, const float * image, float * out)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < g.n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    double    d[D];
    long long rest = p;
    for (int k = 0; k < D; ++k)
    {
      const int       i = static_cast<int>(rest % g.size[k]);
      const long long lo = i > 0 ? p - g.stride[k] : p;
      const long long hi = i + 1 < g.size[k] ? p + g.stride[k] : p;
      rest /= g.size[k];
      const double h = __dmul_rn(static_cast<double>(hi > lo ? (hi - lo) / g.stride[k] : 1), g.spacing[k]);
      d[k] = hi > lo ? __ddiv_rn(__dsub_rn(static_cast<double>(image[hi]), static_cast<double>(image[lo])), h) : 0.0;
    }
    for (int r = 0; r < D; ++r)
    {
      double v = 0.0;
      for (int k = 0; k < D; ++k)
      {
        v = __dadd_rn(v, __dmul_rn(g.R[r][k], d[k]));
      }
      out[p * D + r] = __double2float_rn(v);
    }
  }
}

/** One pass of dmr::GaussianShrink along `axis`: target(i) = float(sum_k c_k double(source(i with axis index clamp(
 * kept[i_axis] + k - r)))) summed in kernel order, every operation explicitly rounded (no fused multiply-add) as on the
 * CPU. source has `shape`, the target the same shape but kept-count pixels along the axis. */
__global__ void
ShrinkPassKernel(const float *     source,
                 long long         s0,
                 long long         s1,
                 long long         s2,
                 int               axis,
                 long long         outLength,
                 const long long * kept,
                 const double *    c,
                 int               width,
                 float *           target,
                 long long         total)
{
  const long long shape[3] = { s0, s1, s2 };
  long long       tshape[3] = { s0, s1, s2 };
  tshape[axis] = outLength;
  const long long stride = axis == 0 ? 1 : (axis == 1 ? s0 : s0 * s1); // of the axis in the source
  const long long length = shape[axis];
  const int       r = width / 2;
  for (long long t = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; t < total;
       t += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    long long i[3];
    long long rest = t;
    for (int k = 0; k < 3; ++k)
    {
      i[k] = rest % tshape[k];
      rest /= tshape[k];
    }
    const long long centre = kept[i[axis]];
    i[axis] = 0;
    const float * line = source + i[0] + shape[0] * (i[1] + shape[1] * i[2]);
    double        sum = 0.0;
    for (int k = 0; k < width; ++k)
    {
      const long long j = min(max(centre + k - r, 0LL), length - 1);
      sum = __dadd_rn(sum, __dmul_rn(c[k], static_cast<double>(line[j * stride])));
    }
    target[t] = __double2float_rn(sum);
  }
}

/** out = M v at every pixel (D floats each), the sum taken in double from 0 in column order with every operation
 * rounded on its own, as the CPU's WriteGridFieldToImage does, then rounded to float. */
struct RotationParams
{
  double M[3][3];
};

template <int D>
__global__ void
RotateKernel(RotationParams r, const float * v, long long n, float * out)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    double x[D];
    for (int k = 0; k < D; ++k)
    {
      x[k] = static_cast<double>(v[p * D + k]);
    }
    for (int i = 0; i < D; ++i)
    {
      double s = 0.0;
      for (int k = 0; k < D; ++k)
      {
        s = __dadd_rn(s, __dmul_rn(r.M[i][k], x[k]));
      }
      out[p * D + i] = __double2float_rn(s);
    }
  }
}

/** Barycentric coordinates of the pixel at idx in an element (BarycentricMap::Barycentric). */
template <int D>
__device__ inline void
Barycentric(const double * affine, const double * spacing, const int * idx, double * lambda)
{
  double d[D];
  for (int k = 0; k < D; ++k)
  {
    d[k] = static_cast<double>(idx[k]) * spacing[k] - affine[D * D + k];
  }
  double rest = 1.0;
  for (int r = 0; r < D; ++r)
  {
    double v = 0.0;
    for (int c = 0; c < D; ++c)
    {
      v += affine[r * D + c] * d[c];
    }
    lambda[r + 1] = v;
    rest -= v;
  }
  lambda[0] = rest;
}

/** The stored weights of BarycentricMap: clamped to [0,1], renormalised, rounded to float. */
template <int D>
__device__ inline void
Weights(const double * affine, const double * spacing, const int * idx, float * weight)
{
  double lambda[D + 1];
  Barycentric<D>(affine, spacing, idx, lambda);
  double sum = 0.0;
  for (int v = 0; v <= D; ++v)
  {
    lambda[v] = fmin(1.0, fmax(0.0, lambda[v]));
    sum += lambda[v];
  }
  for (int v = 0; v <= D; ++v)
  {
    weight[v] = static_cast<float>(lambda[v] / sum);
  }
}

/** The pixels of one row of an element's bounding box that lie in the element (BarycentricMap::Build's spans and
 * inside test): body(p) for each. row numbers the box's rows along axes 1..D-1. */
template <int D, typename TBody>
__device__ inline void
ForEachPixelInElementRow(const DeviceGrid & g,
                         const double *     affine,
                         const long long *  bounds,
                         long long          row,
                         TBody &&           body)
{
  long long lo[D], hi[D];
  for (int k = 0; k < D; ++k)
  {
    lo[k] = bounds[k];
    hi[k] = bounds[D + k];
  }
  double slope[D + 1], scale[D + 1];
  slope[0] = 0.0;
  scale[0] = 0.0;
  for (int r = 0; r < D; ++r)
  {
    slope[r + 1] = affine[r * D + 0] * g.spacing[0];
    slope[0] -= slope[r + 1];
    scale[r + 1] = 0.0;
    for (int c = 0; c < D; ++c)
    {
      scale[r + 1] += fabs(affine[r * D + c]) * g.spacing[c];
    }
    scale[0] += scale[r + 1];
  }
  int       idx[D];
  long long rest = row;
  for (int k = 1; k < D; ++k)
  {
    const long long extent = hi[k] - lo[k] + 1;
    idx[k] = static_cast<int>(lo[k] + rest % extent);
    rest /= extent;
  }
  idx[0] = static_cast<int>(lo[0]);
  double lambda[D + 1];
  Barycentric<D>(affine, g.spacing, idx, lambda);
  double first = static_cast<double>(lo[0]), last = static_cast<double>(hi[0]);
  for (int v = 0; v <= D; ++v)
  {
    if (fabs(slope[v]) <= 1e-9 * scale[v])
    {
      if (lambda[v] < -1e-6)
      {
        return; // this coordinate does not change along the row and is negative: the row misses the element
      }
      continue;
    }
    const double at = static_cast<double>(lo[0]) + (-1e-9 - lambda[v]) / slope[v];
    if (slope[v] > 0.0)
    {
      first = fmax(first, floor(at) - 1.0);
    }
    else
    {
      last = fmin(last, ceil(at) + 1.0);
    }
  }
  long long base = 0;
  for (int k = 1; k < D; ++k)
  {
    base += static_cast<long long>(idx[k]) * g.stride[k];
  }
  for (long long x = static_cast<long long>(first); x <= static_cast<long long>(last); ++x)
  {
    idx[0] = static_cast<int>(x);
    Barycentric<D>(affine, g.spacing, idx, lambda);
    bool inside = true;
    for (int v = 0; v <= D; ++v)
    {
      inside = inside && lambda[v] >= -1e-9;
    }
    if (inside)
    {
      body(base + x);
    }
  }
}

/** Per element e: the inverse edge matrix and first vertex (affine), the pixel bounding box (bounds) and its number of
 * rows along axes 1..D-1 (rowStart[e + 1]; RowStartKernel sums them), with BarycentricMap::ElementAffine's arithmetic
 * (dmrSimplexGeometry.h), so the CPU and the GPU rasterise and assemble from the same bits. */
template <int D>
__global__ void
ElementSetupKernel(DeviceGrid     g,
                   const double * nodes,
                   const int *    elements,
                   long long      nElements,
                   double *       affine,
                   long long *    bounds,
                   long long *    rowStart)
{
  for (long long e = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; e < nElements;
       e += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    double v[D + 1][D], inv[D][D] = {}, x0[D];
    for (int i = 0; i <= D; ++i)
    {
      const long long a = elements[e * (D + 1) + i];
      for (int k = 0; k < D; ++k)
      {
        v[i][k] = nodes[a * D + k];
      }
    }
    SimplexEdgeInverse<D>(v, x0, &inv);
    double * out = affine + e * (D * D + D);
    for (int r = 0; r < D; ++r)
    {
      for (int c = 0; c < D; ++c)
      {
        out[r * D + c] = inv[r][c];
      }
      out[D * D + r] = x0[r];
    }
    int64_t size[D], lo[D] = {}, hi[D] = {};
    for (int k = 0; k < D; ++k)
    {
      size[k] = g.size[k];
    }
    SimplexPixelBox<D>(v, g.spacing, size, lo, hi);
    long long rows = lo[0] <= hi[0] ? 1 : 0;
    for (int k = 0; k < D; ++k)
    {
      bounds[e * 2 * D + k] = lo[k];
      bounds[e * 2 * D + D + k] = hi[k];
      rows *= k > 0 ? (hi[k] >= lo[k] ? hi[k] - lo[k] + 1 : 0) : 1;
    }
    rowStart[e + 1] = rows;
    if (e == 0)
    {
      rowStart[0] = 0;
    }
  }
}

/** rowStart[1..n] <- its inclusive prefix sums (rowStart[0] is 0): the elements' first rows in one numbering. One
 * block; integer sums, so the order of the additions does not matter. */
__global__ void
RowStartKernel(long long * rowStart, long long n)
{
  using BlockScan = cub::BlockScan<long long, Threads>;
  __shared__ typename BlockScan::TempStorage scan;
  const long long                            chunk = (n + blockDim.x - 1) / blockDim.x;
  const long long                            begin = 1 + threadIdx.x * chunk, end = min(n + 1, begin + chunk);
  long long                                  sum = 0;
  for (long long i = begin; i < end; ++i)
  {
    sum += rowStart[i];
  }
  long long before = 0;
  BlockScan(scan).ExclusiveSum(sum, before);
  for (long long i = begin; i < end; ++i)
  {
    before += rowStart[i];
    rowStart[i] = before;
  }
}

/** owner[p] = the lowest element containing pixel p. One thread per row of an element's bounding box (rowStart: the
 * elements' first rows, a prefix sum over the elements): the work is spread evenly whatever the element sizes. */
template <int D>
__global__ void
RasteriseKernel(DeviceGrid        g,
                long long         nElements,
                const long long * rowStart,
                const double *    affine,
                const long long * bounds,
                int *             owner)
{
  const long long rows = rowStart[nElements];
  for (long long r = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; r < rows;
       r += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    // the element of row r: the last e with rowStart[e] <= r
    long long lo = 0, hi = nElements - 1;
    while (lo < hi)
    {
      const long long mid = (lo + hi + 1) / 2;
      if (rowStart[mid] <= r)
      {
        lo = mid;
      }
      else
      {
        hi = mid - 1;
      }
    }
    const int mine = static_cast<int>(lo);
    ForEachPixelInElementRow<D>(g, affine + lo * (D * D + D), bounds + lo * 2 * D, r - rowStart[lo], [&](long long p) {
      atomicMin(owner + p, mine);
    });
  }
}

__global__ void
CoverageKernel(const int * owner, long long n, unsigned long long * firstUncovered)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    if (owner[p] == INT_MAX)
    {
      atomicMin(firstUncovered, static_cast<unsigned long long>(p));
    }
  }
}

/** The largest |f_i| of the force field, as the bit pattern of a non-negative double in *maximum (which must start
 * at 0). The gather's fixed-point quantum is derived from it. */
__global__ void
MaxAbsKernel(const float * f, long long n, unsigned long long * maximum)
{
  float m = 0.0f;
  for (long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; i < n;
       i += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    m = isfinite(f[i]) ? fmaxf(m, fabsf(f[i])) : INFINITY; // a NaN or infinite force makes the maximum infinite
  }
  __shared__ double shared[Threads / 32];
  const double      b = BlockMax(m, shared);
  if (threadIdx.x == 0)
  {
    AtomicMaxNonNegative(maximum, b); // one atomic per block: per warp they serialise on one address
  }
}

/** The consistent load vector sum_x phi_a(x) f(x) in fixed point (dmrFixedPointGather.h, the CPU's rule): every term
 * phi_v(x) f_k(x) is rounded to a multiple of the quantum and added as a 64-bit integer, so the sums do not depend on
 * the order of the additions and the result is deterministic although the pixels run in parallel. One warp takes 32
 * consecutive pixels; the lanes of a run with the same owner element sum their terms (segmented scan), and the run's
 * last lane adds them to the element's nodes: a few atomics per warp instead of one per pixel. sums (nNodes x D) must
 * start at 0. */
template <int D>
__global__ void
GatherPixelsKernel(DeviceGrid                 g,
                   const int *                owner,
                   const double *             affine,
                   const int *                elements,
                   const float *              force,
                   const unsigned long long * maxAbsBits,
                   unsigned long long *       sums)
{
  const double quantum = GatherQuantum(__longlong_as_double(static_cast<long long>(*maxAbsBits)), g.n);
  if (quantum == 0.0 || !isfinite(quantum))
  {
    return;
  }
  const double   inverse = 1.0 / quantum; // a power of two: scaling by it is exact
  const int      lane = threadIdx.x & 31;
  const unsigned below = (1u << lane) - 1u;
  for (long long base = blockIdx.x * static_cast<long long>(blockDim.x) + (threadIdx.x & ~31); base < g.n;
       base += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    const long long p = base + lane;
    const int       e = p < g.n ? owner[p] : -1;
    long long       term[(D + 1) * D];
    if (e >= 0 && e != INT_MAX)
    {
      int idx[D];
      IndexOf<D>(g, p, idx);
      float wt[D + 1];
      Weights<D>(affine + static_cast<long long>(e) * (D * D + D), g.spacing, idx, wt);
      for (int v = 0; v <= D; ++v)
      {
        for (int k = 0; k < D; ++k)
        {
          term[v * D + k] = GatherTerm(wt[v], force[p * D + k], inverse);
        }
      }
    }
    else
    {
      for (int i = 0; i < (D + 1) * D; ++i)
      {
        term[i] = 0;
      }
    }
    // runs of lanes with the same owner: the first lane of each run is a head
    const int      previous = __shfl_up_sync(0xffffffffu, e, 1);
    const bool     head = lane == 0 || previous != e;
    const unsigned heads = __ballot_sync(0xffffffffu, head);
    const int      runStart = 31 - __clz(heads & (below | (1u << lane)));
    for (int o = 1; o < 32; o <<= 1)
    {
      for (int i = 0; i < (D + 1) * D; ++i)
      {
        const long long t = __shfl_up_sync(0xffffffffu, term[i], o);
        term[i] += lane - o >= runStart ? t : 0;
      }
    }
    const bool tail = lane == 31 || ((heads >> (lane + 1)) & 1u);
    if (tail && e >= 0 && e != INT_MAX)
    {
      for (int v = 0; v <= D; ++v)
      {
        const long long node = elements[static_cast<long long>(e) * (D + 1) + v];
        for (int k = 0; k < D; ++k)
        {
          if (term[v * D + k] != 0)
          {
            atomicAdd(sums + node * D + k, static_cast<unsigned long long>(term[v * D + k])); // two's complement
          }
        }
      }
    }
  }
}

/** nodal = scale x quantum x sums (NaN everywhere when the force is not finite). */
__global__ void
GatherFinishKernel(long long                  n,
                   const unsigned long long * sums,
                   const unsigned long long * maxAbsBits,
                   long long                  pixels,
                   double                     scale,
                   double *                   nodal)
{
  const double maxAbs = __longlong_as_double(static_cast<long long>(*maxAbsBits));
  const double quantum = GatherQuantum(maxAbs, pixels);
  for (long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; i < n;
       i += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    nodal[i] = isfinite(maxAbs) ? GatherValue(static_cast<long long>(sums[i]), quantum, scale) : NAN;
  }
}

template <int D>
__global__ void
SampleNodesKernel(DeviceGrid g, long long nNodes, const double * nodes, const float * w, double * nodal)
{
  for (long long a = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; a < nNodes;
       a += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    double c[D], s[D] = {};
    for (int k = 0; k < D; ++k)
    {
      c[k] = nodes[a * D + k] / g.spacing[k];
    }
    InterpolateAdd<D, D>(g.size, g.stride, w, c, 1.0, s);
    for (int k = 0; k < D; ++k)
    {
      nodal[a * D + k] = s[k];
    }
  }
}

/** u(x) = scale x sum_v phi_v(x) u_v, and the largest |u_k| / spacing_k (BarycentricMap::Interpolate). */
template <int D>
__global__ void
InterpolateKernel(DeviceGrid     g,
                  const int *    owner,
                  const double * affine,
                  const int *    elements,
                  const double * nodalU,
                  double         scale,
                  float *        out)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < g.n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    const int e = owner[p];
    int       idx[D];
    IndexOf<D>(g, p, idx);
    float wt[D + 1];
    Weights<D>(affine + static_cast<long long>(e) * (D * D + D), g.spacing, idx, wt);
    double u[D] = {};
    for (int v = 0; v <= D; ++v)
    {
      const double    w = wt[v];
      const long long node = elements[static_cast<long long>(e) * (D + 1) + v];
      for (int k = 0; k < D; ++k)
      {
        u[k] += w * nodalU[node * D + k];
      }
    }
    for (int k = 0; k < D; ++k)
    {
      out[p * D + k] = static_cast<float>(scale * u[k]);
    }
  }
}

/** The two bounds of ExponentialField: largest |v_k| / spacing_k and largest neighbour difference |dv_r| / spacing_r
 * (both in pixels). */
template <int D>
__global__ void
NormsKernel(DeviceGrid g, const float * v, unsigned long long * maxima)
{
  double m0 = 0.0, m1 = 0.0;
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < g.n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    int idx[D];
    IndexOf<D>(g, p, idx);
    for (int k = 0; k < D; ++k)
    {
      m0 = fmax(m0, fabs(static_cast<double>(v[p * D + k])) / g.spacing[k]);
      if (idx[k] + 1 < g.size[k])
      {
        const long long q = p + g.stride[k];
        for (int r = 0; r < D; ++r)
        {
          m1 = fmax(m1, fabs(static_cast<double>(v[q * D + r]) - v[p * D + r]) / g.spacing[r]);
        }
      }
    }
  }
  __shared__ double shared[Threads / 32];
  const double      b0 = BlockMax(m0, shared);
  const double      b1 = BlockMax(m1, shared);
  if (threadIdx.x == 0)
  {
    AtomicMaxNonNegative(maxima, b0);
    AtomicMaxNonNegative(maxima + 1, b1);
  }
}

__global__ void
ScaleKernel(const float * in, float * out, long long n, float scale)
{
  for (long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; i < n;
       i += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    out[i] = in[i] * scale;
  }
}

/** out(x) = v(x) + w(x + v(x)) (ComposeFields); out may not alias w or v. */
template <int D>
__global__ void
ComposeKernel(DeviceGrid g, const float * w, const float * v, float * out)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < g.n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    int idx[D];
    IndexOf<D>(g, p, idx);
    double c[D], s[D] = {};
    for (int k = 0; k < D; ++k)
    {
      c[k] = static_cast<double>(idx[k]) + static_cast<double>(v[p * D + k]) / g.spacing[k];
    }
    InterpolateAdd<D, D>(g.size, g.stride, w, c, 1.0, s);
    for (int k = 0; k < D; ++k)
    {
      out[p * D + k] = static_cast<float>(static_cast<double>(v[p * D + k]) + s[k]);
    }
  }
}

__global__ void
FillKernel(int * data, long long n, int value)
{
  for (long long p = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; p < n;
       p += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    data[p] = value;
  }
}

// ---- linear elasticity, matrix-free (LinearElasticFEMSolver's system) --------------------------------------------
// Per element e: the gradients g_a (a = 0..D) of the barycentric shape functions and the volume V_e. For a nodal
// vector p, K p at node a is sum_e V_e sigma_e g_a with G = sum_b p_b (x) g_b and sigma = lambda tr(G) I + mu (G +
// G^T), which is the element matrix V (lambda g_a,i g_b,j + mu g_a,j g_b,i + mu delta_ij g_a.g_b) applied to p.
constexpr int CGThreads = 256;

template <int D>
__device__ constexpr int
GeometryStride()
{
  return static_cast<int>(ElasticGeometryStride<D>());
}

template <int D>
__global__ void
ElementGeometryKernel(long long      ne,
                      const double * nodes,
                      const int *    elements,
                      const double * affine,
                      double *       geometry)
{
  for (long long e = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; e < ne;
       e += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    // affine: the inverse edge matrix (row r = grad phi_{r+1}) then the first vertex
    ElasticElementGeometry<D>(
      affine + e * (D * D + D), nodes, elements + e * (D + 1), geometry + e * GeometryStride<D>());
  }
}

/** Inverse diagonal of K (Eigen's DiagonalPreconditioner: 1 where the diagonal is 0), 0 on fixed nodes. */
template <int D>
__global__ void
ElasticDiagonalKernel(long long       nn,
                      const int *     start,
                      const int *     incidence,
                      const double *  geometry,
                      const uint8_t * fixed,
                      double          lambda,
                      double          mu,
                      double *        inverseDiagonal)
{
  for (long long a = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; a < nn;
       a += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    double d[D] = {};
    for (int i = start[a]; i < start[a + 1]; ++i)
    {
      const int e = incidence[i] / (D + 1), slot = incidence[i] % (D + 1);
      AddElasticDiagonal<D>(geometry + static_cast<long long>(e) * GeometryStride<D>(), slot, lambda, mu, d);
    }
    for (int k = 0; k < D; ++k)
    {
      inverseDiagonal[a * D + k] = fixed[a] ? 0.0 : (d[k] != 0.0 ? 1.0 / d[k] : 1.0);
    }
  }
}

/** Every block sums the same partials in the same order: the same total everywhere. */
__device__ double
SumPartials(const double * partials, int count, double * shared)
{
  double v = 0.0;
  for (int i = threadIdx.x; i < count; i += blockDim.x)
  {
    v += partials[i];
  }
  const double total = BlockSum(v, shared);
  __syncthreads();
  if (threadIdx.x == 0)
  {
    shared[0] = total;
  }
  __syncthreads();
  return shared[0]; // the next BlockSum synchronises before it writes shared again
}

/** S_e = V_e sigma_e(G) with G = sum_b p_b (x) g_b (D x D, row-major), for the elements of a grid-stride loop. */
template <int D>
__device__ void
ElementStresses(long long      ne,
                const int *    elements,
                const double * geometry,
                const double * p,
                double         lambda,
                double         mu,
                double *       stress)
{
  for (long long e = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; e < ne;
       e += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    ElasticElementStress<D>(
      geometry + e * GeometryStride<D>(), elements + e * (D + 1), p, lambda, mu, stress + e * D * D);
  }
}

template <int D>
__global__ void
ElementStressKernel(long long      ne,
                    const int *    elements,
                    const double * geometry,
                    const double * p,
                    double         lambda,
                    double         mu,
                    const int *    done,
                    double *       stress)
{
  if (done && *done)
  {
    return;
  }
  ElementStresses<D>(ne, elements, geometry, p, lambda, mu, stress);
}

/** q = K p at the nodes of block `block` (CGThreads threads, 8 nodes; 0 on fixed nodes when fixed is given), and the
 * block's partial sum of p . q. One warp per node: lane l takes the node's incidences l, l + 32, ... (element order)
 * and the warp sums them by a fixed shuffle tree, so the result is deterministic. */
template <int D>
__device__ void
NodeApplyBlock(long long       block,
               long long       nn,
               const int *     start,
               const int *     incidence,
               const double *  geometry,
               const double *  stress,
               const uint8_t * fixed,
               const double *  p,
               double *        q,
               double *        partials,
               double *        shared)
{
  const int       lane = threadIdx.x & 31;
  const long long a = (block * blockDim.x + threadIdx.x) >> 5;
  double          y[D] = {};
  if (a < nn && !(fixed && fixed[a]))
  {
    for (int i = start[a] + lane; i < start[a + 1]; i += 32)
    {
      const int      e = incidence[i] / (D + 1), slot = incidence[i] % (D + 1);
      const double * g = geometry + static_cast<long long>(e) * GeometryStride<D>() + slot * D;
      AddElasticNodeTerm<D>(stress + static_cast<long long>(e) * D * D, g, y);
    }
  }
  for (int o = 16; o > 0; o >>= 1)
  {
    for (int k = 0; k < D; ++k)
    {
      y[k] += __shfl_down_sync(0xffffffffu, y[k], o);
    }
  }
  double pq = 0.0;
  if (lane == 0 && a < nn)
  {
    for (int k = 0; k < D; ++k)
    {
      q[a * D + k] = y[k];
      pq += p[a * D + k] * y[k];
    }
  }
  const double total = BlockSum(pq, shared);
  if (threadIdx.x == 0)
  {
    partials[block] = total;
  }
}

template <int D>
__global__ void
NodeApplyKernel(long long       nn,
                const int *     start,
                const int *     incidence,
                const double *  geometry,
                const double *  stress,
                const uint8_t * fixed,
                const double *  p,
                const int *     done,
                double *        q,
                double *        partials)
{
  __shared__ double shared[CGThreads];
  if (done && *done)
  {
    return;
  }
  NodeApplyBlock<D>(blockIdx.x, nn, start, incidence, geometry, stress, fixed, p, q, partials, shared);
}

/** r_i = ri and z_i = M^-1 ri (for i < ndof), then per block the partial sums of r.r and r.z; returns z_i. Every thread
 * of the block calls it. */
__device__ double
StoreResidual(long long      block,
              long long      i,
              long long      ndof,
              double         ri,
              const double * inverseDiagonal,
              double *       r,
              double *       z,
              double *       shared,
              double *       rrPartials,
              double *       rzPartials)
{
  double rr = 0.0, rz = 0.0, zi = 0.0;
  if (i < ndof)
  {
    zi = inverseDiagonal[i] * ri;
    r[i] = ri;
    z[i] = zi;
    rr = ri * ri;
    rz = ri * zi;
  }
  const double rrBlock = BlockSum(rr, shared);
  const double rzBlock = BlockSum(rz, shared);
  if (threadIdx.x == 0)
  {
    rrPartials[block] = rrBlock;
    rzPartials[block] = rzBlock;
  }
  return zi;
}

// CG state: scalars[0..1] = r.z by iteration parity, scalars[2] = |r|^2 of the last step; state[0] = converged flag,
// state[1] = products taken.
/** x += alpha p, r -= alpha q, z = M^-1 r with alpha = (r.z) / (p.q) for the degrees of freedom of block `block`
 * (CGThreads each), and its partial sums of r.r and r.z. */
__device__ void
CGStepBlock(long long      block,
            long long      ndof,
            int            parity,
            const double * pqPartials,
            int            pqCount,
            const double * p,
            const double * q,
            const double * inverseDiagonal,
            const double * scalars,
            double *       x,
            double *       r,
            double *       z,
            double *       rrPartials,
            double *       rzPartials,
            double *       shared)
{
  const double    alpha = scalars[parity] / SumPartials(pqPartials, pqCount, shared);
  const long long i = block * blockDim.x + threadIdx.x;
  double          ri = 0.0;
  if (i < ndof)
  {
    x[i] += alpha * p[i];
    ri = r[i] - alpha * q[i];
  }
  StoreResidual(block, i, ndof, ri, inverseDiagonal, r, z, shared, rrPartials, rzPartials);
}

__global__ void
CGStepKernel(long long      ndof,
             int            parity,
             const double * pqPartials,
             int            pqCount,
             const double * p,
             const double * q,
             const double * inverseDiagonal,
             const double * scalars,
             const int *    state,
             double *       x,
             double *       r,
             double *       z,
             double *       rrPartials,
             double *       rzPartials)
{
  __shared__ double shared[CGThreads];
  if (state[0])
  {
    return;
  }
  CGStepBlock(blockIdx.x,
              ndof,
              parity,
              pqPartials,
              pqCount,
              p,
              q,
              inverseDiagonal,
              scalars,
              x,
              r,
              z,
              rrPartials,
              rzPartials,
              shared);
}

/** Counts the product; true (and the converged flag set) when |r|^2 < threshold, otherwise p = z + beta p with
 * beta = (r.z)_new / (r.z)_old for the degrees of freedom of a grid-stride loop. Every block computes the same sums. */
__device__ bool
CGDirection(long long      ndof,
            int            parity,
            const double * rrPartials,
            const double * rzPartials,
            int            count,
            double         threshold,
            const double * z,
            double *       p,
            double *       scalars,
            int *          state,
            double *       shared)
{
  const double rr = SumPartials(rrPartials, count, shared);
  const double rzNew = SumPartials(rzPartials, count, shared);
  if (blockIdx.x == 0 && threadIdx.x == 0)
  {
    state[1] += 1;
    scalars[2] = rr;
    scalars[1 - parity] = rzNew;
  }
  if (rr < threshold)
  {
    if (blockIdx.x == 0 && threadIdx.x == 0)
    {
      state[0] = 1;
    }
    return true;
  }
  const double beta = rzNew / scalars[parity];
  for (long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x; i < ndof;
       i += static_cast<long long>(gridDim.x) * blockDim.x)
  {
    p[i] = z[i] + beta * p[i];
  }
  return false;
}

__global__ void
CGDirectionKernel(long long      ndof,
                  int            parity,
                  const double * rrPartials,
                  const double * rzPartials,
                  int            count,
                  double         threshold,
                  const double * z,
                  double *       p,
                  double *       scalars,
                  int *          state)
{
  __shared__ double shared[CGThreads];
  if (state[0])
  {
    return;
  }
  CGDirection(ndof, parity, rrPartials, rzPartials, count, threshold, z, p, scalars, state, shared);
}

/** r = f (0 on fixed), x = 0, z = p = M^-1 r; partial sums of r.r and r.z. */
__global__ void
CGStartKernel(long long       ndof,
              const double *  f,
              const double *  inverseDiagonal,
              const uint8_t * fixed,
              int             dimension,
              double *        x,
              double *        r,
              double *        z,
              double *        p,
              double *        rrPartials,
              double *        rzPartials)
{
  __shared__ double shared[CGThreads];
  const long long   i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x;
  double            ri = 0.0;
  if (i < ndof)
  {
    ri = fixed[i / dimension] ? 0.0 : f[i];
    x[i] = 0.0;
  }
  const double zi = StoreResidual(blockIdx.x, i, ndof, ri, inverseDiagonal, r, z, shared, rrPartials, rzPartials);
  if (i < ndof)
  {
    p[i] = zi;
  }
}

unsigned int
GridBlocks(long long n)
{
  // grid-stride loops: enough blocks to fill the device several times over, never more than the work
  const long long blocks = (n + Threads - 1) / Threads;
  return static_cast<unsigned int>(std::max<long long>(1, std::min<long long>(blocks, 65535LL * 8)));
}

/** Blocks of a grid-stride reduction into one address (one atomic per block): about as many threads as the device
 * keeps resident, not one block per 256 items, so that the atomics do not queue up. */
unsigned int
ReductionBlocks(long long n)
{
  return std::min(GridBlocks(n), 1024u);
}

/** The device mesh and element data the elastic operator reads. */
struct ElasticOperator
{
  unsigned int   dimension;
  long long      nodes, elements;
  const int *    vertices;
  const int *    start;
  const int *    incidence;
  const double * geometry;
  double *       stress;
  double         lambda, mu;

  /** q = K p (fixed rows zero when fixed is given) and per node block the partial sums of p . q. */
  void
  Apply(const double * p, const uint8_t * fixed, const int * done, double * q, double * partials) const
  {
    const unsigned nodeBlocks = Blocks(static_cast<size_t>(nodes) * 32, CGThreads);
    if (dimension == 2)
    {
      ElementStressKernel<2>
        <<<GridBlocks(elements), Threads>>>(elements, vertices, geometry, p, lambda, mu, done, stress);
      NodeApplyKernel<2>
        <<<nodeBlocks, CGThreads>>>(nodes, start, incidence, geometry, stress, fixed, p, done, q, partials);
    }
    else
    {
      ElementStressKernel<3>
        <<<GridBlocks(elements), Threads>>>(elements, vertices, geometry, p, lambda, mu, done, stress);
      NodeApplyKernel<3>
        <<<nodeBlocks, CGThreads>>>(nodes, start, incidence, geometry, stress, fixed, p, done, q, partials);
    }
    CheckLaunch("NodeApplyKernel");
  }
};

/** The arguments of CGSolveKernel: the elastic operator and the CG vectors, partial sums and state. */
struct CGSolveParams
{
  ElasticOperator op;
  const uint8_t * fixed;
  const double *  inverseDiagonal;
  long long       ndof;
  double *        x, *r, *z, *p, *q;
  double *        pqPartials, *rrPartials, *rzPartials;
  int             nodeBlocks, dofBlocks;
  double *        scalars;
  int *           state;
  double          threshold;
  long long       maximumProducts;
};

/** The whole CG loop in one cooperative launch: the phases of ElementStressKernel, NodeApplyKernel, CGStepKernel and
 * CGDirectionKernel separated by grid barriers, each block taking the blocks of those launches in turn, so the sums
 * and the iterates are those of the separate launches, without a launch or a host round trip per product. */
template <int D>
__global__ void
CGSolveKernel(CGSolveParams a)
{
  __shared__ double              shared[CGThreads];
  cooperative_groups::grid_group grid = cooperative_groups::this_grid();
  for (long long k = 0; k < a.maximumProducts; ++k)
  {
    const int parity = static_cast<int>(k & 1);
    ElementStresses<D>(a.op.elements, a.op.vertices, a.op.geometry, a.p, a.op.lambda, a.op.mu, a.op.stress);
    grid.sync();
    for (long long b = blockIdx.x; b < a.nodeBlocks; b += gridDim.x)
    {
      NodeApplyBlock<D>(
        b, a.op.nodes, a.op.start, a.op.incidence, a.op.geometry, a.op.stress, a.fixed, a.p, a.q, a.pqPartials, shared);
    }
    grid.sync();
    for (long long b = blockIdx.x; b < a.dofBlocks; b += gridDim.x)
    {
      CGStepBlock(b,
                  a.ndof,
                  parity,
                  a.pqPartials,
                  a.nodeBlocks,
                  a.p,
                  a.q,
                  a.inverseDiagonal,
                  a.scalars,
                  a.x,
                  a.r,
                  a.z,
                  a.rrPartials,
                  a.rzPartials,
                  shared);
    }
    grid.sync();
    const bool converged = CGDirection(
      a.ndof, parity, a.rrPartials, a.rzPartials, a.dofBlocks, a.threshold, a.z, a.p, a.scalars, a.state, shared);
    grid.sync(); // scalars and p are read by the next product
    if (converged)
    {
      return;
    }
  }
}
} // namespace

/** dmr::GaussianShrink on the device: `out` (outSize pixels) from `source` (inSize pixels) by the passes of `plan`,
 * the last axis first; the intermediate images live in scratch buffers for the call. */
static void
ShrinkOnDevice(unsigned int          dimension,
               const float *         source,
               const int *           inSize,
               const int *           outSize,
               const ShrinkView &    plan,
               DeviceBuffer<float> & out)
{
  long long shape[3] = { 1, 1, 1 };
  for (unsigned int k = 0; k < dimension; ++k)
  {
    shape[k] = inSize[k];
    if (!plan.kept[k] || !plan.coefficients[k] || plan.width[k] % 2 != 1)
    {
      throw CudaError("a pyramid level without its image or a complete shrink plan");
    }
  }
  DeviceBuffer<float>     buffers[2];
  DeviceBuffer<long long> kept;
  DeviceBuffer<double>    coefficients;
  const float *           from = source;
  for (int d = static_cast<int>(dimension) - 1; d >= 0; --d)
  {
    const long long       outLength = outSize[d];
    const long long       total = shape[0] * shape[1] * shape[2] / shape[d] * outLength;
    DeviceBuffer<float> & to = d > 0 ? buffers[d % 2] : out;
    to.Resize(static_cast<size_t>(total));
    static_assert(sizeof(long long) == sizeof(int64_t), "kept positions are 64-bit");
    kept.Upload(reinterpret_cast<const long long *>(plan.kept[d]), static_cast<size_t>(outLength));
    coefficients.Upload(plan.coefficients[d], plan.width[d]);
    ShrinkPassKernel<<<GridBlocks(total), Threads>>>(from,
                                                     shape[0],
                                                     shape[1],
                                                     shape[2],
                                                     d,
                                                     outLength,
                                                     kept.Data(),
                                                     coefficients.Data(),
                                                     static_cast<int>(plan.width[d]),
                                                     to.Data(),
                                                     total);
    CheckLaunch("ShrinkPassKernel");
    // the scratch buffers are freed (cudaFree synchronises) only after the last pass has read them
    from = to.Data();
    shape[d] = outLength;
  }
  Check(cudaDeviceSynchronize(), "pyramid level");
}

struct RegistrationContext::Impl
{
  unsigned int dimension{ 0 };
  DeviceGrid   grid{};
  DeviceLevels levels{};
  size_t       numberOfPixels{ 0 };
  // pyramid storage (level 0 fixed is the fixed image on the registration grid)
  std::vector<DeviceBuffer<float>> levelFixed, levelMoving, levelGradient;
  DeviceBuffer<uint8_t>            mask;
  bool                             hasMask{ false };
  DeviceBuffer<float>              w, bufferA, bufferB, force, density;
  DeviceBuffer<float>              inverse;             // v of W^-1 (EnableInverse), else empty
  DeviceBuffer<float> *            previous{ nullptr }; // the buffer holding w before the last ApplyUpdate
  DeviceBuffer<int>                owner;
  DeviceBuffer<double>             sums;
  DeviceBuffer<unsigned long long> scratch64;
  // mesh
  size_t                           numberOfNodes{ 0 }, numberOfElements{ 0 };
  DeviceBuffer<double>             nodes, affine, nodal;
  DeviceBuffer<unsigned long long> nodalSums; // the gather's fixed-point accumulators
  DeviceBuffer<long long>          bounds, rowStart;
  DeviceBuffer<int>                elements, incidenceStart, incidence;
  std::vector<int>                 hostStart, hostIncidence;
  // linear elasticity (SetElasticity / SolveElasticity): element gradients and volumes, stresses, CG vectors
  double                lambda{ 0 }, mu{ 0 };
  bool                  elasticityReady{ false };
  DeviceBuffer<uint8_t> fixedNodes;
  DeviceBuffer<double>  geometry, stress, inverseDiagonal, cgX, cgR, cgZ, cgP, cgQ, cgPartials, cgScalars;
  DeviceBuffer<int>     cgState;
  bool                  cooperativeSolve{ true };
  int                   cgResidentBlocks[2]{ -1, -1 }; // CGSolveKernel<2, 3>: 0 where unavailable, -1 unknown
  size_t                allocated{ 0 };                // the largest Bytes() seen

  /** How many blocks of CGSolveKernel<D> the device keeps resident at once (0: no cooperative launch). */
  template <int D>
  int
  ResidentCGBlocks()
  {
    int & n = cgResidentBlocks[D - 2];
    if (n < 0)
    {
      int        device = 0, cooperative = 0, sms = 0, perSM = 0;
      const bool ok =
        cudaGetDevice(&device) == cudaSuccess &&
        cudaDeviceGetAttribute(&cooperative, cudaDevAttrCooperativeLaunch, device) == cudaSuccess &&
        cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device) == cudaSuccess &&
        cudaOccupancyMaxActiveBlocksPerMultiprocessor(&perSM, CGSolveKernel<D>, CGThreads, 0) == cudaSuccess;
      n = ok && cooperative ? sms * perSM : 0;
      if (!ok)
      {
        cudaGetLastError(); // the failed query's error only: a launch error pending from before was already checked
      }
    }
    return n;
  }

  /** The CG loop as one cooperative launch; false (nothing launched) where the device cannot have it. */
  template <int D>
  bool
  LaunchCGSolve(CGSolveParams params)
  {
    const long long needed = std::max<long long>(
      { params.nodeBlocks, params.dofBlocks, (params.op.elements + CGThreads - 1) / CGThreads, 1LL });
    const int blocks = static_cast<int>(std::min<long long>(needed, ResidentCGBlocks<D>()));
    if (blocks <= 0)
    {
      return false;
    }
    void * args[] = { &params };
    if (cudaLaunchCooperativeKernel(
          reinterpret_cast<const void *>(CGSolveKernel<D>), blocks, CGThreads, args, 0, nullptr) != cudaSuccess)
    {
      cudaGetLastError();
      cgResidentBlocks[D - 2] = 0; // not again
      return false;
    }
    return true;
  }

  ElasticOperator
  Operator()
  {
    return ElasticOperator{ dimension,
                            static_cast<long long>(numberOfNodes),
                            static_cast<long long>(numberOfElements),
                            elements.Data(),
                            incidenceStart.Data(),
                            incidence.Data(),
                            geometry.Data(),
                            stress.Data(),
                            lambda,
                            mu };
  }

  /** u = scale x sum_a phi_a(x) nodalU_a into a, then exp(u) by scaling and squaring (the CPU's rule for the number
   * of squarings), ping-ponging between a and b (two of the update buffers): on return b holds exp(u), a is free. */
  void
  ExponentialOfUpdate(const double * nodalU,
                      double         scale,
                      float *&       a,
                      float *&       b,
                      double &       maxUpdatePixels,
                      unsigned int & squarings);
  size_t
  Bytes() const
  {
    size_t s = 0;
    for (const auto * v : { &levelFixed, &levelMoving, &levelGradient })
    {
      for (const auto & b : *v)
      {
        s += b.Bytes();
      }
    }
    return s + BytesOf(mask,
                       w,
                       inverse,
                       bufferA,
                       bufferB,
                       force,
                       density,
                       owner,
                       sums,
                       scratch64,
                       nodes,
                       affine,
                       nodal,
                       nodalSums,
                       bounds,
                       rowStart,
                       elements,
                       incidenceStart,
                       incidence,
                       fixedNodes,
                       geometry,
                       stress,
                       inverseDiagonal,
                       cgX,
                       cgR,
                       cgZ,
                       cgP,
                       cgQ,
                       cgPartials,
                       cgScalars,
                       cgState);
  }
};

RegistrationContext::RegistrationContext()
  : m_Impl(new Impl)
{
}

RegistrationContext::~RegistrationContext() = default;

Status
RegistrationContext::Initialize(unsigned int                          dimension,
                                const size_t *                        size,
                                const double *                        spacing,
                                const std::vector<PyramidLevelView> & levels,
                                const uint8_t *                       mask)
{
  return Guard([&] {
    if (dimension != 2 && dimension != 3)
    {
      throw CudaError("the GPU registration supports 2D and 3D images only");
    }
    if (levels.empty() || levels.size() > static_cast<size_t>(MaxLevels))
    {
      throw CudaError("the GPU registration needs 1 to 8 pyramid levels");
    }
    Impl & m = *m_Impl;
    m.dimension = dimension;
    long long s = 1;
    for (int k = 0; k < 3; ++k)
    {
      const bool used = k < static_cast<int>(dimension);
      m.grid.size[k] = used ? static_cast<int>(size[k]) : 1;
      m.grid.spacing[k] = used ? spacing[k] : 1.0;
      m.grid.stride[k] = s;
      s *= m.grid.size[k];
    }
    m.grid.n = s;
    m.numberOfPixels = static_cast<size_t>(s);
    const size_t n = m.numberOfPixels;
    const size_t D = dimension;
    m.levelFixed.resize(levels.size());
    m.levelMoving.resize(levels.size());
    m.levelGradient.resize(levels.size());
    m.levels = DeviceLevels{};
    m.levels.count = static_cast<int>(levels.size());
    for (int r = 0; r < 3; ++r)
    {
      for (int k = 0; k < 3; ++k)
      {
        m.levels.direction[r][k] = levels.empty() ? (r == k ? 1.0 : 0.0) : levels[0].direction[r][k];
      }
    }
    for (size_t l = 0; l < levels.size(); ++l)
    {
      const PyramidLevelView & v = levels[l];
      DeviceLevel &            L = m.levels.level[l];
      size_t                   nf = 1, nm = 1;
      long long                sf = 1, sm = 1;
      for (int k = 0; k < 3; ++k)
      {
        const bool used = k < static_cast<int>(dimension);
        L.fixedSize[k] = used ? static_cast<int>(v.fixedSize[k]) : 1;
        L.movingSize[k] = used ? static_cast<int>(v.movingSize[k]) : 1;
        L.fixedStride[k] = sf;
        L.movingStride[k] = sm;
        sf *= L.fixedSize[k];
        sm *= L.movingSize[k];
        nf *= L.fixedSize[k];
        nm *= L.movingSize[k];
        L.Fc[k] = v.Fc[k];
        L.Mc[k] = v.Mc[k];
        for (int j = 0; j < 3; ++j)
        {
          L.FA[k][j] = v.FA[k][j];
          L.MA[k][j] = v.MA[k][j];
          L.MB[k][j] = v.MB[k][j];
        }
      }
      L.weight = v.weight;
      if (l == 0 && nf != n)
      {
        throw CudaError("pyramid level 0 of the fixed image must be the registration grid");
      }
      if (l == 0 && (!v.fixed || !v.moving))
      {
        throw CudaError("pyramid level 0 must hold the fixed and the moving image");
      }
      if (v.fixed)
      {
        m.levelFixed[l].Upload(v.fixed, nf);
      }
      else if (l > 0)
      {
        ShrinkOnDevice(
          dimension, m.levelFixed[0].Data(), m.levels.level[0].fixedSize, L.fixedSize, v.fixedShrink, m.levelFixed[l]);
      }
      if (v.moving)
      {
        m.levelMoving[l].Upload(v.moving, nm);
      }
      else if (l > 0)
      {
        ShrinkOnDevice(dimension,
                       m.levelMoving[0].Data(),
                       m.levels.level[0].movingSize,
                       L.movingSize,
                       v.movingShrink,
                       m.levelMoving[l]);
      }
      if (v.movingGradient)
      {
        m.levelGradient[l].Upload(v.movingGradient, nm * D);
      }
      else
      {
        GradientParams g{};
        for (int k = 0; k < 3; ++k)
        {
          g.size[k] = L.movingSize[k];
          g.stride[k] = L.movingStride[k];
          g.spacing[k] = k < static_cast<int>(dimension) ? v.movingSpacing[k] : 1.0;
          for (int j = 0; j < 3; ++j)
          {
            g.R[k][j] = v.R[k][j];
          }
        }
        g.n = static_cast<long long>(nm);
        m.levelGradient[l].Resize(nm * D);
        if (dimension == 2)
        {
          MovingGradientKernel<2><<<GridBlocks(g.n), Threads>>>(g, m.levelMoving[l].Data(), m.levelGradient[l].Data());
        }
        else
        {
          MovingGradientKernel<3><<<GridBlocks(g.n), Threads>>>(g, m.levelMoving[l].Data(), m.levelGradient[l].Data());
        }
        CheckLaunch("MovingGradientKernel");
      }
      L.fixed = m.levelFixed[l].Data();
      L.moving = m.levelMoving[l].Data();
      L.gradient = m.levelGradient[l].Data();
    }
    m.hasMask = mask != nullptr;
    if (m.hasMask)
    {
      m.mask.Upload(mask, n);
    }
    else
    {
      m.mask.Free();
    }
    m.w.Resize(n * D);
    m.w.Zero();
    m.bufferA.Resize(n * D);
    m.bufferB.Resize(n * D);
    m.force.Resize(n * D);
    m.density.Resize(n);
    m.owner.Resize(n);
    m.sums.Resize(4 * 1024); // ForceKernel's per-block partials (ReductionBlocks)
    m.scratch64.Resize(2);
    Check(cudaDeviceSynchronize(), "Initialize");
    m.allocated = std::max(m.allocated, m.Bytes());
  });
}

Status
RegistrationContext::ComputeForce(ForceStatistics & statistics, bool warpedGradient)
{
  return Guard([&] {
    Impl &          m = *m_Impl;
    const uint8_t * mask = m.hasMask ? m.mask.Data() : nullptr;
    const unsigned  blocks = ReductionBlocks(m.grid.n);
    if (m.dimension == 2)
    {
      ForceKernel<2><<<blocks, Threads>>>(
        m.grid, m.levels, m.w.Data(), warpedGradient, mask, m.force.Data(), m.density.Data(), m.sums.Data());
    }
    else
    {
      ForceKernel<3><<<blocks, Threads>>>(
        m.grid, m.levels, m.w.Data(), warpedGradient, mask, m.force.Data(), m.density.Data(), m.sums.Data());
    }
    CheckLaunch("ForceKernel");
    std::vector<double> partial(4 * blocks);
    m.sums.Download(partial.data(), partial.size());
    double host[4] = { 0.0, 0.0, 0.0, 0.0 };
    for (unsigned int b = 0; b < blocks; ++b)
    {
      for (unsigned int i = 0; i < 4; ++i)
      {
        host[i] += partial[4 * b + i];
      }
    }
    statistics.mssd = host[0];
    statistics.ssd = host[1];
    statistics.sumSquaredForce = host[2];
    statistics.inside = static_cast<size_t>(host[3] + 0.5);
  });
}

Status
RegistrationContext::AddToDensity(double alpha)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    AddKernel<<<GridBlocks(m.grid.n), Threads>>>(m.density.Data(), m.grid.n, alpha);
    CheckLaunch("AddKernel");
  });
}

const float *
RegistrationContext::DeviceDensity() const
{
  return m_Impl->density.Data();
}

Status
RegistrationContext::DownloadDensity(float * host) const
{
  return Guard([&] { m_Impl->density.Download(host, m_Impl->numberOfPixels); });
}

Status
RegistrationContext::DownloadForce(float * host) const
{
  return Guard([&] { m_Impl->force.Download(host, m_Impl->numberOfPixels * m_Impl->dimension); });
}

Status
RegistrationContext::DownloadLevel(unsigned int level, float * fixed, float * moving, float * movingGradient) const
{
  return Guard([&] {
    const Impl & m = *m_Impl;
    if (level >= static_cast<unsigned int>(m.levels.count))
    {
      throw CudaError("no pyramid level " + std::to_string(level));
    }
    const DeviceLevel & L = m.levels.level[level];
    const size_t        nf = static_cast<size_t>(L.fixedSize[0]) * L.fixedSize[1] * L.fixedSize[2];
    const size_t        nm = static_cast<size_t>(L.movingSize[0]) * L.movingSize[1] * L.movingSize[2];
    if (fixed)
    {
      m.levelFixed[level].Download(fixed, nf);
    }
    if (moving)
    {
      m.levelMoving[level].Download(moving, nm);
    }
    if (movingGradient)
    {
      m.levelGradient[level].Download(movingGradient, nm * m.dimension);
    }
  });
}

Status
RegistrationContext::SetMesh(const double *  nodes,
                             size_t          numberOfNodes,
                             const int32_t * elements,
                             size_t          numberOfElements)
{
  return Guard([&] {
    Impl &       m = *m_Impl;
    const size_t D = m.dimension;
    if (numberOfElements == 0 || numberOfElements > static_cast<size_t>(INT_MAX) - 1)
    {
      throw CudaError("the mesh has no element or too many elements");
    }
    // node -> (element, vertex) incidence in element order, for a deterministic nodal sum (and the check of the ids)
    m.hostStart.assign(numberOfNodes + 1, 0);
    for (size_t i = 0; i < numberOfElements * (D + 1); ++i)
    {
      const int a = elements[i];
      if (a < 0 || static_cast<size_t>(a) >= numberOfNodes)
      {
        throw CudaError("a mesh element refers to a node that does not exist");
      }
      ++m.hostStart[a + 1];
    }
    for (size_t a = 0; a < numberOfNodes; ++a)
    {
      m.hostStart[a + 1] += m.hostStart[a];
    }
    m.hostIncidence.resize(numberOfElements * (D + 1));
    std::vector<int> fill(m.hostStart.begin(), m.hostStart.end() - 1);
    for (size_t i = 0; i < numberOfElements * (D + 1); ++i)
    {
      m.hostIncidence[fill[elements[i]]++] = static_cast<int>(i);
    }
    m.numberOfNodes = numberOfNodes;
    m.numberOfElements = numberOfElements;
    m.elasticityReady = false;
    m.nodes.Upload(nodes, numberOfNodes * D);
    m.elements.Upload(elements, numberOfElements * (D + 1));
    m.incidenceStart.Upload(m.hostStart.data(), m.hostStart.size());
    m.incidence.Upload(m.hostIncidence.data(), m.hostIncidence.size());
    m.nodalSums.Reserve(numberOfNodes * D);
    m.nodal.Reserve(numberOfNodes * D);

    // the elements' rasterisation set-up and their first rows, on the device
    m.affine.Reserve(numberOfElements * (D * D + D));
    m.bounds.Reserve(numberOfElements * 2 * D);
    m.rowStart.Reserve(numberOfElements + 1);
    const long long nElements = static_cast<long long>(numberOfElements);
    if (D == 2)
    {
      ElementSetupKernel<2><<<GridBlocks(nElements), Threads>>>(
        m.grid, m.nodes.Data(), m.elements.Data(), nElements, m.affine.Data(), m.bounds.Data(), m.rowStart.Data());
    }
    else
    {
      ElementSetupKernel<3><<<GridBlocks(nElements), Threads>>>(
        m.grid, m.nodes.Data(), m.elements.Data(), nElements, m.affine.Data(), m.bounds.Data(), m.rowStart.Data());
    }
    CheckLaunch("ElementSetupKernel");
    RowStartKernel<<<1, Threads>>>(m.rowStart.Data(), nElements);
    CheckLaunch("RowStartKernel");
    FillKernel<<<GridBlocks(m.grid.n), Threads>>>(m.owner.Data(), m.grid.n, INT_MAX);
    CheckLaunch("FillKernel");
    long long rows = 0;
    Check(cudaMemcpy(&rows, m.rowStart.Data() + nElements, sizeof(rows), cudaMemcpyDeviceToHost), "element rows");
    const unsigned rowBlocks = GridBlocks(rows);
    if (D == 2)
    {
      RasteriseKernel<2><<<rowBlocks, Threads>>>(
        m.grid, nElements, m.rowStart.Data(), m.affine.Data(), m.bounds.Data(), m.owner.Data());
    }
    else
    {
      RasteriseKernel<3><<<rowBlocks, Threads>>>(
        m.grid, nElements, m.rowStart.Data(), m.affine.Data(), m.bounds.Data(), m.owner.Data());
    }
    CheckLaunch("RasteriseKernel");
    const unsigned long long none = ~0ULL;
    Check(cudaMemcpy(m.scratch64.Data(), &none, sizeof(none), cudaMemcpyHostToDevice), "coverage reset");
    CoverageKernel<<<GridBlocks(m.grid.n), Threads>>>(m.owner.Data(), m.grid.n, m.scratch64.Data());
    CheckLaunch("CoverageKernel");
    unsigned long long first = 0;
    m.scratch64.Download(&first, 1);
    if (first != none)
    {
      throw CudaError("pixel " + std::to_string(first) +
                      " is not covered by any element: the mesh does not cover the image domain");
    }
    m.allocated = std::max(m.allocated, m.Bytes());
  });
}

Status
RegistrationContext::DownloadElementRaster(double * affine, int64_t * bounds) const
{
  return Guard([&] {
    const Impl & m = *m_Impl;
    if (m.numberOfElements == 0)
    {
      throw CudaError("DownloadElementRaster() needs SetMesh() first");
    }
    const size_t D = m.dimension;
    m.affine.Download(affine, m.numberOfElements * (D * D + D));
    static_assert(sizeof(long long) == sizeof(int64_t), "64-bit bounds");
    m.bounds.Download(reinterpret_cast<long long *>(bounds), m.numberOfElements * 2 * D);
  });
}

Status
RegistrationContext::SetElasticity(double lambda, double mu, const uint8_t * fixed)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    if (m.numberOfElements == 0)
    {
      throw CudaError("SetElasticity() needs SetMesh() first");
    }
    if (!(lambda >= 0.0) || !(mu > 0.0))
    {
      throw CudaError("the elastic system needs lambda >= 0 and mu > 0");
    }
    const size_t    D = m.dimension;
    const long long nn = static_cast<long long>(m.numberOfNodes);
    const long long ne = static_cast<long long>(m.numberOfElements);
    m.lambda = lambda;
    m.mu = mu;
    std::vector<uint8_t> flags(m.numberOfNodes, 0);
    if (fixed)
    {
      std::copy(fixed, fixed + m.numberOfNodes, flags.begin());
    }
    m.fixedNodes.Upload(flags.data(), flags.size());
    m.geometry.Reserve(m.numberOfElements * ((D + 1) * D + 1));
    m.stress.Reserve(m.numberOfElements * D * D);
    for (auto * b : { &m.inverseDiagonal, &m.cgX, &m.cgR, &m.cgZ, &m.cgP, &m.cgQ })
    {
      b->Reserve(m.numberOfNodes * D);
    }
    m.cgPartials.Reserve(static_cast<size_t>(Blocks(m.numberOfNodes * 32, CGThreads)) +
                         2 * static_cast<size_t>(Blocks(m.numberOfNodes * D, CGThreads)));
    m.cgScalars.Reserve(3);
    m.cgState.Reserve(2);
    const unsigned elementBlocks = GridBlocks(ne), nodeBlocks = GridBlocks(nn);
    if (D == 2)
    {
      ElementGeometryKernel<2>
        <<<elementBlocks, Threads>>>(ne, m.nodes.Data(), m.elements.Data(), m.affine.Data(), m.geometry.Data());
      CheckLaunch("ElementGeometryKernel");
      ElasticDiagonalKernel<2><<<nodeBlocks, Threads>>>(nn,
                                                        m.incidenceStart.Data(),
                                                        m.incidence.Data(),
                                                        m.geometry.Data(),
                                                        m.fixedNodes.Data(),
                                                        lambda,
                                                        mu,
                                                        m.inverseDiagonal.Data());
    }
    else
    {
      ElementGeometryKernel<3>
        <<<elementBlocks, Threads>>>(ne, m.nodes.Data(), m.elements.Data(), m.affine.Data(), m.geometry.Data());
      CheckLaunch("ElementGeometryKernel");
      ElasticDiagonalKernel<3><<<nodeBlocks, Threads>>>(nn,
                                                        m.incidenceStart.Data(),
                                                        m.incidence.Data(),
                                                        m.geometry.Data(),
                                                        m.fixedNodes.Data(),
                                                        lambda,
                                                        mu,
                                                        m.inverseDiagonal.Data());
    }
    CheckLaunch("ElasticDiagonalKernel");
    m.elasticityReady = true;
    m.allocated = std::max(m.allocated, m.Bytes());
  });
}

Status
RegistrationContext::SolveElasticity(const double * f,
                                     double *       u,
                                     double         tolerance,
                                     size_t         maxIterations,
                                     size_t &       iterations,
                                     bool &         converged)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    if (!m.elasticityReady)
    {
      throw CudaError("SolveElasticity() needs SetElasticity() after the last SetMesh()");
    }
    const size_t    D = m.dimension;
    const size_t    ndof = m.numberOfNodes * D;
    const long long nd = static_cast<long long>(ndof);
    const unsigned  dofBlocks = Blocks(ndof, CGThreads);
    const unsigned  nodeBlocks = Blocks(m.numberOfNodes * 32, CGThreads);
    double *        pqPartials = m.cgPartials.Data();
    double *        rrPartials = pqPartials + nodeBlocks;
    double *        rzPartials = rrPartials + dofBlocks;
    m.cgQ.Upload(f, ndof); // f in q's buffer until the start kernel has read it
    CGStartKernel<<<dofBlocks, CGThreads>>>(nd,
                                            m.cgQ.Data(),
                                            m.inverseDiagonal.Data(),
                                            m.fixedNodes.Data(),
                                            static_cast<int>(D),
                                            m.cgX.Data(),
                                            m.cgR.Data(),
                                            m.cgZ.Data(),
                                            m.cgP.Data(),
                                            rrPartials,
                                            rzPartials);
    CheckLaunch("CGStartKernel");
    std::vector<double> start(2 * dofBlocks);
    Check(cudaMemcpy(start.data(), rrPartials, start.size() * sizeof(double), cudaMemcpyDeviceToHost), "CG start");
    double rhsNorm2 = 0.0, rz = 0.0;
    for (unsigned b = 0; b < dofBlocks; ++b)
    {
      rhsNorm2 += start[b];
      rz += start[dofBlocks + b];
    }
    iterations = 0;
    converged = true;
    if (rhsNorm2 == 0.0)
    {
      std::fill(u, u + ndof, 0.0);
      return;
    }
    const double threshold = std::max(tolerance * tolerance * rhsNorm2, std::numeric_limits<double>::min());
    const double scalars[3] = { rz, 0.0, rhsNorm2 };
    const int    state[2] = { 0, 0 };
    Check(cudaMemcpy(m.cgScalars.Data(), scalars, sizeof(scalars), cudaMemcpyHostToDevice), "CG scalars");
    Check(cudaMemcpy(m.cgState.Data(), state, sizeof(state), cudaMemcpyHostToDevice), "CG state");
    const ElasticOperator op = m.Operator();
    int                   hostState[2] = { 0, 0 };
    const CGSolveParams   params{ op,
                                m.fixedNodes.Data(),
                                m.inverseDiagonal.Data(),
                                nd,
                                m.cgX.Data(),
                                m.cgR.Data(),
                                m.cgZ.Data(),
                                m.cgP.Data(),
                                m.cgQ.Data(),
                                pqPartials,
                                rrPartials,
                                rzPartials,
                                static_cast<int>(nodeBlocks),
                                static_cast<int>(dofBlocks),
                                m.cgScalars.Data(),
                                m.cgState.Data(),
                                threshold,
                                static_cast<long long>(maxIterations) };
    const bool fused = m.cooperativeSolve && (D == 2 ? m.LaunchCGSolve<2>(params) : m.LaunchCGSolve<3>(params));
    if (fused)
    {
      CheckLaunch("CGSolveKernel");
      Check(cudaMemcpy(hostState, m.cgState.Data(), sizeof(hostState), cudaMemcpyDeviceToHost), "CG state");
    }
    // otherwise batches of separate launches without a host round trip; the kernels of a converged solve return at
    // once
    constexpr size_t Batch = 16;
    for (size_t k = fused ? maxIterations : 0; k < maxIterations && !hostState[0];)
    {
      const size_t end = std::min(maxIterations, k + Batch);
      for (; k < end; ++k)
      {
        const int parity = static_cast<int>(k & 1);
        op.Apply(m.cgP.Data(), m.fixedNodes.Data(), m.cgState.Data(), m.cgQ.Data(), pqPartials);
        CGStepKernel<<<dofBlocks, CGThreads>>>(nd,
                                               parity,
                                               pqPartials,
                                               static_cast<int>(nodeBlocks),
                                               m.cgP.Data(),
                                               m.cgQ.Data(),
                                               m.inverseDiagonal.Data(),
                                               m.cgScalars.Data(),
                                               m.cgState.Data(),
                                               m.cgX.Data(),
                                               m.cgR.Data(),
                                               m.cgZ.Data(),
                                               rrPartials,
                                               rzPartials);
        CGDirectionKernel<<<dofBlocks, CGThreads>>>(nd,
                                                    parity,
                                                    rrPartials,
                                                    rzPartials,
                                                    static_cast<int>(dofBlocks),
                                                    threshold,
                                                    m.cgZ.Data(),
                                                    m.cgP.Data(),
                                                    m.cgScalars.Data(),
                                                    m.cgState.Data());
      }
      CheckLaunch("CG kernels");
      Check(cudaMemcpy(hostState, m.cgState.Data(), sizeof(hostState), cudaMemcpyDeviceToHost), "CG state");
    }
    iterations = static_cast<size_t>(hostState[1]);
    converged = hostState[0] != 0;
    m.cgX.Download(u, ndof);
  });
}

Status
RegistrationContext::ElasticEnergy(const double * u, double & energy)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    if (!m.elasticityReady)
    {
      throw CudaError("ElasticEnergy() needs SetElasticity() after the last SetMesh()");
    }
    const size_t   ndof = m.numberOfNodes * m.dimension;
    const unsigned nodeBlocks = Blocks(m.numberOfNodes * 32, CGThreads);
    m.cgP.Upload(u, ndof);
    m.Operator().Apply(m.cgP.Data(), nullptr, nullptr, m.cgQ.Data(), m.cgPartials.Data());
    std::vector<double> partials(nodeBlocks);
    Check(cudaMemcpy(partials.data(), m.cgPartials.Data(), partials.size() * sizeof(double), cudaMemcpyDeviceToHost),
          "elastic energy");
    double sum = 0.0;
    for (const double v : partials)
    {
      sum += v;
    }
    energy = 0.5 * sum;
  });
}

Status
RegistrationContext::DownloadElementOfPixels(int32_t * host) const
{
  return Guard([&] { m_Impl->owner.Download(host, m_Impl->numberOfPixels); });
}

Status
RegistrationContext::GatherForce(double scale, double * nodal)
{
  return Guard([&] {
    Impl &          m = *m_Impl;
    const long long nd = static_cast<long long>(m.numberOfNodes * m.dimension);
    Check(cudaMemsetAsync(m.scratch64.Data(), 0, sizeof(unsigned long long)), "gather reset");
    Check(cudaMemsetAsync(m.nodalSums.Data(), 0, static_cast<size_t>(nd) * sizeof(unsigned long long)), "gather reset");
    MaxAbsKernel<<<ReductionBlocks(m.grid.n * m.dimension), Threads>>>(
      m.force.Data(), m.grid.n * m.dimension, m.scratch64.Data());
    CheckLaunch("MaxAbsKernel");
    const unsigned blocks = GridBlocks(m.grid.n);
    if (m.dimension == 2)
    {
      GatherPixelsKernel<2><<<blocks, Threads>>>(m.grid,
                                                 m.owner.Data(),
                                                 m.affine.Data(),
                                                 m.elements.Data(),
                                                 m.force.Data(),
                                                 m.scratch64.Data(),
                                                 m.nodalSums.Data());
    }
    else
    {
      GatherPixelsKernel<3><<<blocks, Threads>>>(m.grid,
                                                 m.owner.Data(),
                                                 m.affine.Data(),
                                                 m.elements.Data(),
                                                 m.force.Data(),
                                                 m.scratch64.Data(),
                                                 m.nodalSums.Data());
    }
    CheckLaunch("GatherPixelsKernel");
    GatherFinishKernel<<<GridBlocks(nd), Threads>>>(
      nd, m.nodalSums.Data(), m.scratch64.Data(), m.grid.n, scale, m.nodal.Data());
    CheckLaunch("GatherFinishKernel");
    m.nodal.Download(nodal, m.numberOfNodes * m.dimension);
  });
}

Status
RegistrationContext::SampleFieldAtNodes(double * nodal)
{
  return Guard([&] {
    Impl &         m = *m_Impl;
    const unsigned blocks = GridBlocks(static_cast<long long>(m.numberOfNodes));
    if (m.dimension == 2)
    {
      SampleNodesKernel<2><<<blocks, Threads>>>(
        m.grid, static_cast<long long>(m.numberOfNodes), m.nodes.Data(), m.w.Data(), m.nodal.Data());
    }
    else
    {
      SampleNodesKernel<3><<<blocks, Threads>>>(
        m.grid, static_cast<long long>(m.numberOfNodes), m.nodes.Data(), m.w.Data(), m.nodal.Data());
    }
    CheckLaunch("SampleNodesKernel");
    m.nodal.Download(nodal, m.numberOfNodes * m.dimension);
  });
}

void
RegistrationContext::Impl::ExponentialOfUpdate(const double * nodalU,
                                               double         scale,
                                               float *&       a,
                                               float *&       b,
                                               double &       maxUpdatePixels,
                                               unsigned int & squarings)
{
  Impl &          m = *this;
  const long long n = m.grid.n;
  const long long values = n * m.dimension;
  const unsigned  blocks = GridBlocks(n);
  m.nodal.Upload(nodalU, m.numberOfNodes * m.dimension);
  m.scratch64.Zero();
  if (m.dimension == 2)
  {
    InterpolateKernel<2>
      <<<blocks, Threads>>>(m.grid, m.owner.Data(), m.affine.Data(), m.elements.Data(), m.nodal.Data(), scale, a);
    CheckLaunch("InterpolateKernel");
    NormsKernel<2><<<ReductionBlocks(n), Threads>>>(m.grid, a, m.scratch64.Data());
  }
  else
  {
    InterpolateKernel<3>
      <<<blocks, Threads>>>(m.grid, m.owner.Data(), m.affine.Data(), m.elements.Data(), m.nodal.Data(), scale, a);
    CheckLaunch("InterpolateKernel");
    NormsKernel<3><<<ReductionBlocks(n), Threads>>>(m.grid, a, m.scratch64.Data());
  }
  CheckLaunch("NormsKernel");
  unsigned long long bits[2];
  m.scratch64.Download(bits, 2);
  double maxima[2];
  std::memcpy(maxima, bits, sizeof(maxima));
  maxUpdatePixels = maxima[0];
  const double maxNorm = std::max(maxima[0], maxima[1]);
  squarings = 0;
  while (maxNorm / std::ldexp(1.0, static_cast<int>(squarings)) > 0.5 && squarings < 30)
  {
    ++squarings;
  }
  const float factor = static_cast<float>(std::ldexp(1.0, -static_cast<int>(squarings)));
  ScaleKernel<<<GridBlocks(values), Threads>>>(a, b, values, factor);
  CheckLaunch("ScaleKernel");
  for (unsigned int s = 0; s < squarings; ++s)
  {
    if (m.dimension == 2)
    {
      ComposeKernel<2><<<blocks, Threads>>>(m.grid, b, b, a);
    }
    else
    {
      ComposeKernel<3><<<blocks, Threads>>>(m.grid, b, b, a);
    }
    CheckLaunch("ComposeKernel (squaring)");
    std::swap(a, b);
  }
}

Status
RegistrationContext::ApplyUpdate(const double * nodalU,
                                 double         scale,
                                 double &       maxUpdatePixels,
                                 unsigned int & squarings)
{
  return Guard([&] {
    Impl &          m = *m_Impl;
    const long long n = m.grid.n;
    const unsigned  blocks = GridBlocks(n);
    float *         a = m.bufferA.Data();
    float *         b = m.bufferB.Data();
    m.ExponentialOfUpdate(nodalU, scale, a, b, maxUpdatePixels, squarings);
    // b = exp(u); W <- W o exp(u): a = b + w(x + b)
    if (m.dimension == 2)
    {
      ComposeKernel<2><<<blocks, Threads>>>(m.grid, m.w.Data(), b, a);
    }
    else
    {
      ComposeKernel<3><<<blocks, Threads>>>(m.grid, m.w.Data(), b, a);
    }
    CheckLaunch("ComposeKernel");
    // a now holds the new w: swap the buffers' roles (the previous w stays in that buffer for RevertUpdate)
    if (a == m.bufferA.Data())
    {
      std::swap(m.w, m.bufferA);
      m.previous = &m.bufferA;
    }
    else
    {
      std::swap(m.w, m.bufferB);
      m.previous = &m.bufferB;
    }
  });
}

Status
RegistrationContext::RevertUpdate()
{
  return Guard([&] {
    Impl & m = *m_Impl;
    if (!m.previous)
    {
      throw std::runtime_error("RevertUpdate without a preceding ApplyUpdate");
    }
    std::swap(m.w, *m.previous);
    m.previous = nullptr;
  });
}

Status
RegistrationContext::DownloadField(float * host) const
{
  return Guard([&] { m_Impl->w.Download(host, m_Impl->numberOfPixels * m_Impl->dimension); });
}

Status
RegistrationContext::DownloadPhysicalField(const double * direction, float * host) const
{
  return Guard([&] {
    Impl &             m = *m_Impl;
    RotationParams     r{};
    const unsigned int D = m.dimension;
    for (unsigned int i = 0; i < D; ++i)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        r.M[i][k] = direction[i * D + k];
      }
    }
    // the update buffer that does not hold the previous w (RevertUpdate stays valid): no allocation
    DeviceBuffer<float> & rotated = m.previous == &m.bufferA ? m.bufferB : m.bufferA;
    if (D == 2)
    {
      RotateKernel<2><<<GridBlocks(m.grid.n), Threads>>>(r, m.w.Data(), m.grid.n, rotated.Data());
    }
    else
    {
      RotateKernel<3><<<GridBlocks(m.grid.n), Threads>>>(r, m.w.Data(), m.grid.n, rotated.Data());
    }
    CheckLaunch("RotateKernel");
    rotated.Download(host, m.numberOfPixels * D);
  });
}

Status
RegistrationContext::EnableInverse(const float * host)
{
  return Guard([&] {
    Impl &       m = *m_Impl;
    const size_t values = m.numberOfPixels * m.dimension;
    m.inverse.Resize(values);
    if (host)
    {
      m.inverse.Upload(host, values);
    }
    else
    {
      m.inverse.Zero();
    }
    Check(cudaStreamSynchronize(nullptr), "EnableInverse");
    m.allocated = std::max(m.allocated, m.Bytes());
  });
}

Status
RegistrationContext::ApplyInverseUpdate(const double * nodalU, double scale)
{
  return Guard([&] {
    Impl & m = *m_Impl;
    if (m.inverse.Size() == 0)
    {
      throw std::runtime_error("ApplyInverseUpdate without EnableInverse");
    }
    // both update buffers are free once the step is accepted (the previous w is no longer needed)
    m.previous = nullptr;
    float *      a = m.bufferA.Data();
    float *      b = m.bufferB.Data();
    double       maxUpdate = 0.0;
    unsigned int squarings = 0;
    m.ExponentialOfUpdate(nodalU, scale, a, b, maxUpdate, squarings);
    // v <- exp(u) o v: a = v + b(x + v)
    const unsigned blocks = GridBlocks(m.grid.n);
    if (m.dimension == 2)
    {
      ComposeKernel<2><<<blocks, Threads>>>(m.grid, b, m.inverse.Data(), a);
    }
    else
    {
      ComposeKernel<3><<<blocks, Threads>>>(m.grid, b, m.inverse.Data(), a);
    }
    CheckLaunch("ComposeKernel (inverse)");
    std::swap(m.inverse, a == m.bufferA.Data() ? m.bufferA : m.bufferB);
  });
}

Status
RegistrationContext::DownloadInverse(float * host) const
{
  return Guard([&] { m_Impl->inverse.Download(host, m_Impl->numberOfPixels * m_Impl->dimension); });
}

Status
RegistrationContext::UploadField(const float * host)
{
  return Guard([&] {
    m_Impl->w.Upload(host, m_Impl->numberOfPixels * m_Impl->dimension);
    m_Impl->previous = nullptr;
    Check(cudaStreamSynchronize(nullptr), "UploadField");
  });
}

void
RegistrationContext::SetCooperativeSolve(bool on)
{
  m_Impl->cooperativeSolve = on;
}

size_t
RegistrationContext::AllocatedBytes() const
{
  return m_Impl->allocated;
}
} // namespace cuda
} // namespace dmr
} // namespace itk
