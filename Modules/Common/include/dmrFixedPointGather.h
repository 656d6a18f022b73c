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
#ifndef dmrFixedPointGather_h
#define dmrFixedPointGather_h

#include <cmath>
#include <limits>
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
#include <emmintrin.h>
#endif

#ifdef __CUDACC__
#define DMR_HOST_DEVICE __host__ __device__
#else
#define DMR_HOST_DEVICE
#endif

namespace itk
{
namespace dmr
{
/** The gather's fixed-point rule, one definition for the CPU (BarycentricMap::Gather) and the GPU
 * (GatherPixelsKernel): every term phi_v(x) f_k(x) of the consistent load vector is rounded to a multiple of a power of
 * two q and summed as a 64-bit integer. Integer sums do not depend on the order of the additions, so the nodal forces
 * are the same bit for bit however the pixels are split among threads, blocks or back-ends. q is chosen so that every
 * partial sum, at most n terms of magnitude at most maxAbs (weights are in [0, 1]), stays below 2^62 q.
 * \ingroup DynamicMeshRegistration */

/** q for a force whose largest |f_k| is maxAbs, over n pixels: 0 when there is no force, NaN when it is not finite. */
DMR_HOST_DEVICE inline double
GatherQuantum(double maxAbs, long long n)
{
  if (!(maxAbs <= std::numeric_limits<double>::max()))
  {
    return std::numeric_limits<double>::quiet_NaN();
  }
  if (!(maxAbs > 0.0))
  {
    return 0.0;
  }
  int exponent = 0;
  frexp(maxAbs * static_cast<double>(n), &exponent); // maxAbs n < 2^exponent
  return ldexp(1.0, exponent - 62);
}

/** One term, float weight times float force in double, in units of q (inverse = 1 / q, exact for a power of two). */
DMR_HOST_DEVICE inline long long
GatherTerm(float weight, float force, double inverse)
{
  const double term = static_cast<double>(weight) * static_cast<double>(force) * inverse;
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
  // llrint is this instruction (cvtsd2si: the current rounding mode, to nearest even by default) behind a call into
  // libm, six calls per pixel of a 2D gather
  return _mm_cvtsd_si64(_mm_set_sd(term));
#else
  return llrint(term);
#endif
}

/** The nodal value of an integer sum: scale x q x sum. */
DMR_HOST_DEVICE inline double
GatherValue(long long sum, double quantum, double scale)
{
  return scale * (quantum * static_cast<double>(sum));
}
} // namespace dmr
} // namespace itk

#endif
