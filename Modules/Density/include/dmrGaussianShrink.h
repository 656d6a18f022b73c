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
#ifndef dmrGaussianShrink_h
#define dmrGaussianShrink_h

#include "dmrGrid.h"
#include "itkGaussianOperator.h"
#include "itkImage.h"
#include "itkShrinkImageFilter.h"
#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

namespace itk
{
namespace dmr
{
/** ShrinkImageFilter(DiscreteGaussianImageFilter(image)) without the full-resolution smoothed image: the same values,
 * bit for bit, at a fraction of the cost.
 *
 * DiscreteGaussianImageFilter (ITK 5.2, float in and out, UseImageSpacing off, zero-flux Neumann boundary) convolves
 * one axis after the other, the last axis first, each pass storing floats: out(v) = float(sum_k c_k double(in(v + (k -
 * r) e))) summed in double in kernel order, the index clamped to the image, c the coefficients of GaussianOperator
 * <double> (variance, MaximumKernelWidth, MaximumError 0.01). ShrinkImageFilter then keeps input index o f + offset of
 * every output index o (see PlanGaussianShrink for the offset). Only the kept indices matter, so each pass is computed
 * only where a later pass or the output reads it: the pass along axis d at the kept indices of axes d..D-1 and at every
 * index of the axes below d. The same operations in the same order give the same floats; the geometry is
 * ShrinkImageFilter's own (its output information). */
/** What GaussianShrink computes, without computing it: the output's geometry (ShrinkImageFilter's output information
 * and region, no buffer) and, per axis, the kept input positions and the Gaussian coefficients. The GPU back-end runs
 * the same passes from it (dmr::cuda::RegistrationContext::Initialize). */
template <unsigned int D>
struct GaussianShrinkPlan
{
  typename Image<float, D>::Pointer   output;      // information and largest region only
  std::array<int64_t, D>              inputSize{}; // the input's buffered region
  std::array<int64_t, D>              outputSize{};
  std::array<std::vector<int64_t>, D> kept;         // per axis: the kept input positions (buffer-relative)
  std::array<std::vector<double>, D>  coefficients; // per axis: GaussianOperator<double>, 2 r + 1 of them
};

/** GaussianOperator<double>'s coefficients (ITK 5.2) for a variance t at which ITK's own evaluation fails. ITK takes
 * c_n = e^-t I_n(t) for n = 0, 1, ... until their two-sided sum reaches 1 - maximumError or there are more than
 * maximumKernelWidth of them, divides by that sum and mirrors them; above t of about 700 e^-t underflows to 0 and
 * I_n(t) overflows, so every coefficient is NaN (the pyramid's level 7 has t = 1024). The same rule, evaluated
 * stably: e^-t I_0(t) from its asymptotic series (relative error below 2e-9 for t >= 100, 1e-12 where it is used),
 * the ratios I_n / I_(n-1) from the backward recurrence of their continued fraction, started far enough (t + width +
 * 64 terms) to converge. Used only where ITK's coefficients are not finite, so every other level keeps ITK's values
 * bit for bit (which, for variances of some tens and more, are themselves approximate: ITK's I_n(t) starts its
 * downward recurrence at an order that does not grow with t). */
inline std::vector<double>
LargeVarianceGaussianCoefficients(double t, double maximumError, unsigned int maximumKernelWidth)
{
  const unsigned int  width = std::max(2u, maximumKernelWidth);
  std::vector<double> ratio(width + 2, 0.0); // ratio[k] = I_k(t) / I_(k-1)(t)
  double              r = 0.0;
  for (size_t k = width + 1 + static_cast<size_t>(t) + 64; k >= 1; --k)
  {
    r = 1.0 / (2.0 * static_cast<double>(k) / t + r);
    if (k < ratio.size())
    {
      ratio[k] = r;
    }
  }
  const double        pi = 3.14159265358979323846;
  std::vector<double> half{ (1.0 + 1.0 / (8.0 * t) + 9.0 / (128.0 * t * t) + 225.0 / (3072.0 * t * t * t)) /
                            std::sqrt(2.0 * pi * t) };
  half.push_back(half[0] * ratio[1]);
  double sum = half[0] + 2.0 * half[1];
  for (size_t i = 2; sum < 1.0 - maximumError; ++i) // ITK's loop, its failsafe and its width limit
  {
    half.push_back(half[i - 1] * ratio[i]);
    sum += 2.0 * half[i];
    if (half[i] <= 0.0 || half.size() > maximumKernelWidth)
    {
      break;
    }
  }
  std::vector<double> coefficients(2 * half.size() - 1);
  for (size_t i = 0; i < half.size(); ++i)
  {
    coefficients[half.size() - 1 + i] = coefficients[half.size() - 1 - i] = half[i] / sum;
  }
  return coefficients;
}

template <unsigned int D, typename TImage>
GaussianShrinkPlan<D>
PlanGaussianShrink(const TImage * image, double variance, unsigned int maximumKernelWidth, const unsigned int * factors)
{
  static_assert(TImage::ImageDimension == D, "PlanGaussianShrink: the image must have dimension D");
  using ImageType = Image<float, D>;
  GaussianShrinkPlan<D> plan;
  auto                  shrink = ShrinkImageFilter<TImage, ImageType>::New();
  shrink->SetInput(image);
  for (unsigned int k = 0; k < D; ++k)
  {
    shrink->SetShrinkFactor(k, factors[k]);
  }
  shrink->UpdateOutputInformation();
  plan.output = ImageType::New();
  plan.output->CopyInformation(shrink->GetOutput());
  plan.output->SetRegions(shrink->GetOutput()->GetLargestPossibleRegion());

  // The kept input pixels. ShrinkImageFilter places the output so that its centre and the input's coincide, then keeps
  // input pixel f o + offset of output pixel o, the offset found by rounding (half up) the input continuous index of
  // the first output pixel, (n - 1)/2 - (m - 1) f/2 after the input's first pixel. It computes that index through
  // physical points, where floating-point noise rounds a half-pixel offset either way, and it clamps a negative offset
  // to 0, which shifts the kept pixels of images whose region starts at some indices (e.g. 5 or -7 with f = 4): the
  // same image then gives another level depending on how its region is indexed. Here the offset is computed exactly
  // in index arithmetic, so the level depends on the pixels only (the same pixels as ShrinkImageFilter wherever its
  // rounding is exact and its offset not clamped, as for every region starting at 0).
  const auto & inRegion = image->GetBufferedRegion();
  const auto & outRegion = plan.output->GetLargestPossibleRegion();
  for (unsigned int k = 0; k < D; ++k)
  {
    plan.inputSize[k] = static_cast<int64_t>(inRegion.GetSize()[k]);
    plan.outputSize[k] = static_cast<int64_t>(outRegion.GetSize()[k]);
    const int64_t f = static_cast<int64_t>(factors[k]);
    const int64_t twice = (plan.inputSize[k] - 1) - (plan.outputSize[k] - 1) * f; // twice the first kept position
    const int64_t first = (twice + 1) / 2;                                        // half up (twice >= 0)
    plan.kept[k].resize(static_cast<size_t>(plan.outputSize[k]));
    for (int64_t o = 0; o < plan.outputSize[k]; ++o)
    {
      const int64_t i = first + o * f;
      if (twice < 0 || i >= plan.inputSize[k])
      {
        itkGenericExceptionMacro("GaussianShrink: output index " << o << " maps outside the input along axis " << k);
      }
      plan.kept[k][static_cast<size_t>(o)] = i;
    }
    GaussianOperator<double, D> op;
    op.SetDirection(k);
    op.SetVariance(variance);
    op.SetMaximumKernelWidth(maximumKernelWidth);
    op.SetMaximumError(0.01);
    op.CreateDirectional();
    plan.coefficients[k].resize(op.Size());
    for (size_t j = 0; j < plan.coefficients[k].size(); ++j)
    {
      plan.coefficients[k][j] = op[static_cast<unsigned int>(j)];
    }
    if (!std::all_of(
          plan.coefficients[k].begin(), plan.coefficients[k].end(), [](double c) { return std::isfinite(c); }))
    {
      plan.coefficients[k] = // ITK overflowed: the same operator's coefficients, evaluated stably
        LargeVarianceGaussianCoefficients(variance, op.GetMaximumError(), op.GetMaximumKernelWidth());
    }
  }
  return plan;
}

template <unsigned int D>
typename Image<float, D>::Pointer
GaussianShrink(const Image<float, D> * image,
               double                  variance,
               unsigned int            maximumKernelWidth,
               const unsigned int *    factors,
               MultiThreaderBase *     threader)
{
  const GaussianShrinkPlan<D> plan = PlanGaussianShrink<D>(image, variance, maximumKernelWidth, factors);
  const auto                  out = plan.output;
  out->Allocate();
  const std::array<int64_t, D> & n = plan.inputSize;
  const std::array<int64_t, D> & m = plan.outputSize;

  // passes along axes D-1, ..., 0 (DiscreteGaussianImageFilter's order); shape before the pass along d: n[0..d],
  // m[d+1..D-1]. The first pass reads the image, the last writes the output, the others alternate between two buffers.
  const float *      source = image->GetBufferPointer();
  std::vector<float> buffers[2];
  for (int d = static_cast<int>(D) - 1; d >= 0; --d)
  {
    const std::vector<double> & c = plan.coefficients[d];
    const int64_t               r = static_cast<int64_t>(c.size() / 2);

    std::array<int64_t, D> shape{}; // of the source
    for (unsigned int k = 0; k < D; ++k)
    {
      shape[k] = static_cast<int>(k) <= d ? n[k] : m[k];
    }
    int64_t stride = 1; // of axis d in the source (and the target: the axes below d keep their extent)
    for (int k = 0; k < d; ++k)
    {
      stride *= shape[k];
    }
    int64_t above = 1; // number of index combinations of the axes above d
    for (unsigned int k = static_cast<unsigned int>(d) + 1; k < D; ++k)
    {
      above *= shape[k];
    }
    const int64_t                length = shape[d], outLength = m[d];
    const std::vector<int64_t> & at = plan.kept[d];
    std::vector<float> &         buffer = buffers[d % 2];
    if (d > 0)
    {
      buffer.resize(static_cast<size_t>(stride * outLength * above));
    }
    float * const target = d > 0 ? buffer.data() : out->GetBufferPointer();
    if (stride == 1)
    {
      // along the contiguous axis: one line at a time
      ParallelForChunks(
        threader,
        static_cast<size_t>(above),
        [&](size_t begin, size_t end) {
          for (size_t a = begin; a < end; ++a)
          {
            const float * in = source + static_cast<int64_t>(a) * length;
            float *       o = target + static_cast<int64_t>(a) * outLength;
            for (int64_t j = 0; j < outLength; ++j)
            {
              const int64_t centre = at[static_cast<size_t>(j)];
              double        sum = 0.0;
              for (int64_t k = 0; k <= 2 * r; ++k)
              {
                sum += c[static_cast<size_t>(k)] *
                       static_cast<double>(in[std::min(std::max<int64_t>(centre + k - r, 0), length - 1)]);
              }
              o[j] = static_cast<float>(sum);
            }
          }
        },
        16);
    }
    else
    {
      // along a strided axis: a whole row of the axes below d at a time, so the reads are contiguous; every element
      // still sums its terms in kernel order
      ParallelForChunks(
        threader,
        static_cast<size_t>(above * outLength),
        [&](size_t begin, size_t end) {
          std::vector<double> sum(static_cast<size_t>(stride));
          for (size_t task = begin; task < end; ++task)
          {
            const int64_t a = static_cast<int64_t>(task) / outLength, j = static_cast<int64_t>(task) % outLength;
            const int64_t centre = at[static_cast<size_t>(j)];
            std::fill(sum.begin(), sum.end(), 0.0);
            for (int64_t k = 0; k <= 2 * r; ++k)
            {
              const int64_t i = std::min(std::max<int64_t>(centre + k - r, 0), length - 1);
              const float * in = source + (a * length + i) * stride;
              const double  ck = c[static_cast<size_t>(k)];
              for (int64_t b = 0; b < stride; ++b)
              {
                sum[static_cast<size_t>(b)] += ck * static_cast<double>(in[b]);
              }
            }
            float * o = target + (a * outLength + j) * stride;
            for (int64_t b = 0; b < stride; ++b)
            {
              o[b] = static_cast<float>(sum[static_cast<size_t>(b)]);
            }
          }
        },
        1);
    }
    source = target;
  }
  return out;
}
} // namespace dmr
} // namespace itk

#endif
