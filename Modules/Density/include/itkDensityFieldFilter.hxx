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
#ifndef itkDensityFieldFilter_hxx
#define itkDensityFieldFilter_hxx

#include "itkDensityFieldFilter.h"
#include "itkCastImageFilter.h"
#include "dmrGaussianShrink.h"
#include "itkImageRegionConstIterator.h"
#include "itkImageAlgorithm.h"
#include "itkProgressReporter.h"
#include "dmrImageMetrics.h"
#include "dmrDoublePair.h"
#include "dmrBackEndRounding.h"
#include <cmath>
#include <numeric>

namespace itk
{
template <typename TF, typename TM, typename TD, typename TO>
DensityFieldFilter<TF, TM, TD, TO>::DensityFieldFilter()
{
  this->SetPrimaryInputName("FixedImage");
  this->AddRequiredInputName("MovingImage");
  this->AddOptionalInputName("DisplacementField");
  this->AddOptionalInputName("FixedMask");
  this->SetNumberOfRequiredOutputs(2);
  this->SetNthOutput(0, this->MakeOutput(0));
  this->SetNthOutput(1, this->MakeOutput(1));
}

template <typename TF, typename TM, typename TD, typename TO>
DataObject::Pointer
DensityFieldFilter<TF, TM, TD, TO>::MakeOutput(DataObjectPointerArraySizeType idx)
{
  if (idx == 1)
  {
    return ForceFieldType::New().GetPointer();
  }
  return Superclass::MakeOutput(idx);
}

template <typename TF, typename TM, typename TD, typename TO>
auto
DensityFieldFilter<TF, TM, TD, TO>::GetForceField() -> ForceFieldType *
{
  return dynamic_cast<ForceFieldType *>(this->ProcessObject::GetOutput(1));
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::VerifyInputInformation() ITKv5_CONST
{
  ProcessObject::VerifyInputInformation(); // not ImageToImageFilter's: the moving image may lie on any grid
  const FixedImageType * fixed = this->GetFixedImage();
  const auto             fixedSize = fixed->GetLargestPossibleRegion().GetSize();
  for (unsigned int k = 0; k < ImageDimension; ++k)
  {
    if (fixedSize[k] < 2)
    {
      itkExceptionMacro("the fixed image must have at least 2 pixels along every axis, axis " << k << " has "
                                                                                              << fixedSize[k]);
    }
  }
  auto checkOnFixedGrid = [&](const ImageBase<ImageDimension> * image, const char * what) {
    if (image == nullptr)
    {
      return;
    }
    const std::string why =
      dmr::GridMismatch<ImageDimension>(fixed, image, this->GetCoordinateTolerance(), this->GetDirectionTolerance());
    if (!why.empty())
    {
      itkExceptionMacro("the " << what << " must lie on the fixed image grid: " << why);
    }
  };
  checkOnFixedGrid(this->GetDisplacementField(), "displacement field");
  checkOnFixedGrid(this->GetFixedMask(), "fixed mask");
  // the force is sampled through physical space and kept in floats per mm
  const std::string geometry = dmr::FixedAndMovingGeometryProblem<ImageDimension>(fixed, this->GetMovingImage());
  if (!geometry.empty())
  {
    itkExceptionMacro(<< geometry);
  }
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::GenerateInputRequestedRegion()
{
  // Global computation (pyramids, mean |f|^2): every input is needed whole.
  for (auto & input : this->GetInputs())
  {
    if (auto * image = dynamic_cast<ImageBase<ImageDimension> *>(input.GetPointer()))
    {
      image->SetRequestedRegionToLargestPossibleRegion();
    }
  }
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::EnlargeOutputRequestedRegion(DataObject * output)
{
  // Every output is computed whole (alpha is a mean over the image): a downstream filter that asks for a part (a
  // region of interest, streaming) gets the whole. Without this the density was allocated for the requested part and
  // written for every pixel, past the end of its buffer.
  Superclass::EnlargeOutputRequestedRegion(output);
  for (auto & out : this->GetOutputs())
  {
    if (auto * image = dynamic_cast<ImageBase<ImageDimension> *>(out.GetPointer()))
    {
      image->SetRequestedRegionToLargestPossibleRegion();
    }
  }
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::GenerateOutputInformation()
{
  Superclass::GenerateOutputInformation();
  ForceFieldType * force = this->GetForceField();
  force->CopyInformation(this->GetFixedImage());
  force->SetRegions(this->GetFixedImage()->GetLargestPossibleRegion());
}

namespace dmr
{
/** Float copy of an image's buffer (whole image) into a flat array (on the threader's work units when one is given
 * and the image is buffered whole). */
template <typename TImage>
void
CopyToFloat(const TImage * image, std::vector<float> & out, MultiThreaderBase * threader = nullptr)
{
  out.resize(image->GetLargestPossibleRegion().GetNumberOfPixels());
  if (image->GetBufferedRegion() == image->GetLargestPossibleRegion())
  {
    // scalar images: the buffer in index order, each value converted as the iterator's Get() would
    const auto * buffer = image->GetBufferPointer();
    float *      to = out.data();
    ParallelForChunks(threader, out.size(), [buffer, to](size_t b, size_t e) {
      std::transform(buffer + b, buffer + e, to + b, [](const auto & v) { return static_cast<float>(v); });
    });
    return;
  }
  ImageRegionConstIterator<TImage> it(image, image->GetLargestPossibleRegion());
  size_t                           i = 0;
  for (it.GoToBegin(); !it.IsAtEnd(); ++it, ++i)
  {
    out[i] = static_cast<float>(it.Get());
  }
}

/** Central-difference gradient (per mm, one-sided at the border) of a flat image, rotated by R into another frame:
 * out = R * grad. */
template <unsigned int D>
void
GradientInto(MultiThreaderBase *        threader,
             const Grid<D> &            grid,
             const std::vector<float> & image,
             const double (&R)[D][D],
             std::vector<float> & out)
{
  out.assign(grid.numberOfPixels * D, 0.0f);
  ParallelForChunks(threader, grid.numberOfPixels, [&](size_t begin, size_t end) {
    for (size_t p = begin; p < end; ++p)
    {
      const auto idx = grid.Index(p);
      double     g[D];
      for (unsigned int k = 0; k < D; ++k)
      {
        const auto d = DifferenceAlong(grid, idx, p, k);
        g[k] = d.hi > d.lo ? (static_cast<double>(image[d.hi]) - static_cast<double>(image[d.lo])) / d.h : 0.0;
      }
      for (unsigned int r = 0; r < D; ++r)
      {
        double v = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          v += R[r][k] * g[k];
        }
        out[p * D + r] = static_cast<float>(v);
      }
    }
  });
}

/** A moving level's continuous index of a pixel (T = double) or of two (T = DoublePair), the same operations:
 * cm_r = Mc_r + sum_k (MA_rk index_k + MB_rk u_k), index the fine pixel's index, u its displacement (physical). */
template <unsigned int D, typename T, typename TLevel>
inline void
MovingLevelIndex(const TLevel & L, const T (&index)[D], const T (&u)[D], T (&cm)[D])
{
  for (unsigned int r = 0; r < D; ++r)
  {
    cm[r] = Broadcast<T>(L.Mc[r]);
    for (unsigned int k = 0; k < D; ++k)
    {
      cm[r] += Broadcast<T>(L.MA[r][k]) * index[k] + Broadcast<T>(L.MB[r][k]) * u[k];
    }
  }
}

/** One level's term of paper Eq. 5 added to the force of a pixel (T = double) or of two (T = DoublePair), the same
 * operations: f_j += 2 residual (Jt g)_j, g the moving level's gradient at the warped position. */
template <unsigned int D, typename T>
inline void
AddLevelForce(const T & residual, const T (&Jt)[D][D], const T (&g)[D], T (&f)[D])
{
  for (unsigned int j = 0; j < D; ++j)
  {
    T gj = Broadcast<T>(0.0);
    for (unsigned int k = 0; k < D; ++k)
    {
      gj += Jt[j][k] * g[k];
    }
    f[j] += Broadcast<T>(2.0) * residual * gj;
  }
}

/** Jt[j][k] = delta_jk + d u_k / d x_j at pixel p (index idx), the transpose of the Jacobian of W(x) = x + u(x) in
 * the grid frame of `grid` (per mm; central differences, one-sided at the border). u is a physical-frame vector field
 * on the grid (nullptr: identity), rotated into the grid frame by the direction matrix. */
template <unsigned int D, typename TVector, typename TDirection>
inline void
WarpJacobianTranspose(const Grid<D> &                grid,
                      const std::array<int64_t, D> & idx,
                      size_t                         p,
                      const TVector *                u,
                      const TDirection &             direction,
                      double (&Jt)[D][D])
{
  for (unsigned int j = 0; j < D; ++j)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      Jt[j][k] = (j == k) ? 1.0 : 0.0;
    }
  }
  if (!u)
  {
    return;
  }
  for (unsigned int j = 0; j < D; ++j)
  {
    const auto d = DifferenceAlong(grid, idx, p, j);
    if (d.hi == d.lo)
    {
      continue; // a single pixel along this axis
    }
    for (unsigned int k = 0; k < D; ++k)
    {
      double du = 0.0;
      for (unsigned int m = 0; m < D; ++m)
      {
        du += direction[m][k] * (static_cast<double>(u[d.hi][m]) - static_cast<double>(u[d.lo][m]));
      }
      Jt[j][k] += du / d.h;
    }
  }
}

/** Affine map from a reference image's buffer positions (index minus the start of its largest region) to another
 * image's buffer positions through physical space: c = A * position + c0. Both images' buffers are read from 0, so
 * the other image's start index is taken off (a region need not start at 0, e.g. after CropImageFilter). */
template <unsigned int D, typename TRef, typename TOther>
void
IndexToContinuousIndexMap(const TRef * ref, const TOther * other, double (&A)[D][D], double (&c0)[D])
{
  using IndexType = typename TRef::IndexType;
  IndexType                start = ref->GetLargestPossibleRegion().GetIndex();
  typename TRef::PointType p0;
  ref->TransformIndexToPhysicalPoint(start, p0);
  const auto ci0 = other->template TransformPhysicalPointToContinuousIndex<double, double>(p0);
  const auto otherStart = other->GetLargestPossibleRegion().GetIndex();
  for (unsigned int r = 0; r < D; ++r)
  {
    c0[r] = ci0[r] - static_cast<double>(otherStart[r]);
  }
  for (unsigned int k = 0; k < D; ++k)
  {
    IndexType idx = start;
    idx[k] += 1;
    typename TRef::PointType p1;
    ref->TransformIndexToPhysicalPoint(idx, p1);
    const auto ci1 = other->template TransformPhysicalPointToContinuousIndex<double, double>(p1);
    for (unsigned int r = 0; r < D; ++r)
    {
      A[r][k] = ci1[r] - ci0[r];
    }
  }
}
} // namespace dmr

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::BuildPyramids(bool complete)
{
  const FixedImageType *  fixed = this->GetFixedImage();
  const MovingImageType * moving = this->GetMovingImage();
  const ModifiedTimeType  inputTime = std::max(fixed->GetMTime(), moving->GetMTime());
  if (!m_Levels.empty() && m_PyramidTime >= inputTime && m_PyramidLevels == m_NumberOfLevels &&
      m_PyramidFixed == fixed && m_PyramidMoving == moving && (m_PyramidComplete || !complete))
  {
    return; // the pyramids depend only on the images, not on the displacement field: keep them across iterations
  }
  using FloatImageType = Image<float, ImageDimension>;
  m_Levels.clear();
  m_Levels.resize(m_NumberOfLevels);

  // The intensity scale (class description): a power of two that brings the force scale 2 R^2 / h to about 1 when it
  // is outside [2^-40, 2^40], so that |f|^2 (up to ~1e4 force scales squared) and alpha (down to 1e-12 of it) stay
  // normal floats. Exact, so results do not change otherwise.
  const auto   fixedRange = dmr::IntensityRange(fixed, this->GetMultiThreader());
  const auto   movingRange = dmr::IntensityRange(moving, this->GetMultiThreader());
  const double range = std::max(fixedRange.second - fixedRange.first, movingRange.second - movingRange.first);
  double       minSpacing = fixed->GetSpacing()[0];
  for (unsigned int k = 1; k < ImageDimension; ++k)
  {
    minSpacing = std::min(minSpacing, static_cast<double>(fixed->GetSpacing()[k]));
  }
  const double forceScale = 2.0 * range * range / minSpacing;
  m_IntensityScale = 1.0;
  if (forceScale > 0.0 && std::isfinite(forceScale) && std::abs(std::ilogb(forceScale)) > 40)
  {
    m_IntensityScale = std::ldexp(1.0, -(std::ilogb(forceScale) / 2));
  }
  const float scale = static_cast<float>(m_IntensityScale);
  auto        applyScale = [this, scale](float * values, size_t count) {
    if (scale != 1.0f)
    {
      dmr::ParallelForChunks(this->GetMultiThreader(), count, [&](size_t b, size_t e) {
        for (size_t p = b; p < e; ++p)
        {
          values[p] *= scale;
        }
      });
    }
  };

  const auto & dirF = fixed->GetDirection();
  const auto & dirM = moving->GetDirection();
  double       R[ImageDimension][ImageDimension]; // moving grid frame -> fixed grid frame
  for (unsigned int r = 0; r < ImageDimension; ++r)
  {
    for (unsigned int c = 0; c < ImageDimension; ++c)
    {
      double v = 0.0;
      for (unsigned int k = 0; k < ImageDimension; ++k)
      {
        v += dirF[k][r] * dirM[k][c];
      }
      R[r][c] = v;
    }
  }

  auto toFloat = [this, &applyScale](const auto * image) {
    using InImageType = std::remove_cv_t<std::remove_pointer_t<decltype(image)>>;
    auto cast = CastImageFilter<InImageType, FloatImageType>::New();
    cast->SetInput(image);
    cast->SetNumberOfWorkUnits(this->GetNumberOfWorkUnits());
    cast->Update();
    typename FloatImageType::Pointer out = cast->GetOutput();
    out->DisconnectPipeline();
    applyScale(out->GetBufferPointer(), out->GetBufferedRegion().GetNumberOfPixels());
    return out;
  };
  // level l: ShrinkImageFilter(DiscreteGaussianImageFilter(image)) with sigma = 0.5 x shrink factor pixels, as ITK's
  // pyramids, computed only where the shrink keeps it (dmr::GaussianShrink: the same floats). Incomplete: the plan
  // only (geometry, kept positions, coefficients), for the GPU back-end to run.
  auto shrinkOf = [](const auto * image, unsigned int level, unsigned int * factors) {
    const unsigned int factor = 1u << level;
    for (unsigned int k = 0; k < ImageDimension; ++k)
    {
      const auto n = image->GetLargestPossibleRegion().GetSize()[k];
      factors[k] = std::max<unsigned int>(1, std::min<unsigned int>(factor, n / 2));
    }
    return 0.25 * factor * factor; // the variance
  };
  typename FloatImageType::Pointer fixedFloat, movingFloat;
  if (complete)
  {
    fixedFloat = toFloat(fixed);
    movingFloat = toFloat(moving);
  }

  for (unsigned int l = 0; l < m_NumberOfLevels; ++l)
  {
    PyramidLevel &                   L = m_Levels[l];
    typename FloatImageType::Pointer f, m; // the level's images (incomplete: their geometry only above level 0)
    if (l == 0)
    {
      if (complete)
      {
        f = fixedFloat;
        m = movingFloat;
        dmr::CopyToFloat(f.GetPointer(), L.fixed, this->GetMultiThreader());
        dmr::CopyToFloat(m.GetPointer(), L.moving, this->GetMultiThreader());
      }
      else
      {
        f = FloatImageType::New();
        m = FloatImageType::New();
        f->CopyInformation(fixed);
        f->SetRegions(fixed->GetLargestPossibleRegion());
        m->CopyInformation(moving);
        m->SetRegions(moving->GetLargestPossibleRegion());
        // the cast's floats (static_cast), no cast image; a float input buffered whole and not scaled is its own
        // level 0 (no copy)
        auto level0 = [&](const auto * image, std::vector<float> & copy, const float *& input) {
          using PixelType = typename std::decay_t<decltype(*image)>::PixelType;
          if constexpr (std::is_same_v<PixelType, float>)
          {
            if (scale == 1.0f && image->GetBufferedRegion() == image->GetLargestPossibleRegion())
            {
              input = image->GetBufferPointer();
              return;
            }
          }
          dmr::CopyToFloat(image, copy, this->GetMultiThreader());
          applyScale(copy.data(), copy.size());
        };
        level0(fixed, L.fixed, L.fixedInput);
        level0(moving, L.moving, L.movingInput);
      }
    }
    else
    {
      unsigned int fixedFactors[ImageDimension], movingFactors[ImageDimension];
      const double fixedVariance = shrinkOf(fixed, l, fixedFactors);
      const double movingVariance = shrinkOf(moving, l, movingFactors);
      if (complete)
      {
        f = dmr::GaussianShrink<ImageDimension>(
          fixedFloat.GetPointer(), fixedVariance, 64, fixedFactors, this->GetMultiThreader());
        m = dmr::GaussianShrink<ImageDimension>(
          movingFloat.GetPointer(), movingVariance, 64, movingFactors, this->GetMultiThreader());
        dmr::CopyToFloat(f.GetPointer(), L.fixed, this->GetMultiThreader());
        dmr::CopyToFloat(m.GetPointer(), L.moving, this->GetMultiThreader());
      }
      else
      {
        L.fixedPlan = dmr::PlanGaussianShrink<ImageDimension>(fixed, fixedVariance, 64, fixedFactors);
        L.movingPlan = dmr::PlanGaussianShrink<ImageDimension>(moving, movingVariance, 64, movingFactors);
        f = L.fixedPlan.output;
        m = L.movingPlan.output;
      }
    }
    L.fixedGrid = GridType::FromImage(f);
    L.movingGrid = GridType::FromImage(m);
    std::copy(&R[0][0], &R[0][0] + ImageDimension * ImageDimension, &L.R[0][0]);
    if (complete)
    {
      dmr::GradientInto<ImageDimension>(this->GetMultiThreader(), L.movingGrid, L.moving, R, L.movingGradient);
    }
    dmr::IndexToContinuousIndexMap<ImageDimension>(fixed, f.GetPointer(), L.FA, L.Fc);
    dmr::IndexToContinuousIndexMap<ImageDimension>(fixed, m.GetPointer(), L.MA, L.Mc);
    // physical vector -> moving-level index vector: diag(1/spacing) Direction^-1
    const auto & inverseDirection = m->GetInverseDirection();
    for (unsigned int r = 0; r < ImageDimension; ++r)
    {
      for (unsigned int c = 0; c < ImageDimension; ++c)
      {
        L.MB[r][c] = inverseDirection[r][c] / m->GetSpacing()[r];
      }
    }
  }
  // the floor of alpha (ComputeAlpha): the force scale of the moving image's working range
  const double workingMovingRange = m_IntensityScale * (movingRange.second - movingRange.first);
  m_MovingForceScale = 2.0 * workingMovingRange * workingMovingRange / minSpacing;
  m_PyramidTime = inputTime;
  m_PyramidFixed = fixed;
  m_PyramidMoving = moving;
  m_PyramidLevels = m_NumberOfLevels;
  m_PyramidComplete = complete;
  m_FixedAtFinePixels.clear();
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::GenerateData()
{
  constexpr unsigned int D = ImageDimension;
  ProgressReporter       progress(this, 0, 3);
  this->BuildPyramids(true);
  progress.CompletedPixel();

  const FixedImageType *        fixed = this->GetFixedImage();
  const DisplacementFieldType * field = this->GetDisplacementField();
  const GridType                grid = GridType::FromImage(fixed);
  const size_t                  n = grid.numberOfPixels;
  const auto &                  dirF = fixed->GetDirection();

  DensityImageType * density = this->GetOutput();
  density->SetBufferedRegion(density->GetLargestPossibleRegion()); // EnlargeOutputRequestedRegion: all of it
  density->Allocate();
  ForceFieldType * force = this->GetForceField();
  if (m_ComputeForceField)
  {
    force->SetBufferedRegion(force->GetLargestPossibleRegion());
    force->Allocate();
  }
  else
  {
    force->Initialize(); // no buffer
    force->CopyInformation(fixed);
    force->SetLargestPossibleRegion(fixed->GetLargestPossibleRegion());
  }
  m_GridForce.resize(n * D);

  const auto *          fieldBuffer = field ? field->GetBufferPointer() : nullptr;
  const MaskImageType * maskImage = this->GetFixedMask();
  const auto *          maskBuffer = maskImage ? maskImage->GetBufferPointer() : nullptr;
  auto *                densityBuffer = density->GetBufferPointer();
  auto *                forceBuffer = m_ComputeForceField ? force->GetBufferPointer() : nullptr;
  float *               gridForce = m_GridForce.data();
  const auto *          levels = m_Levels.data();
  const unsigned int    nLevels = m_NumberOfLevels;
  // a coarser fixed level (l > 0) at a fine pixel, interpolated at FA idx + Fc
  auto fixedLevelAt = [](const PyramidLevel & L, const std::array<int64_t, D> & idx) {
    double cf[D];
    for (unsigned int r = 0; r < D; ++r)
    {
      cf[r] = L.Fc[r];
      for (unsigned int k = 0; k < D; ++k)
      {
        cf[r] += L.FA[r][k] * static_cast<double>(idx[k]);
      }
    }
    double t = 0.0;
    dmr::InterpolateAdd<D, 1>(L.fixedGrid, L.fixed.data(), cf, 1.0, &t);
    return t;
  };
  // The coarser fixed levels at the fine pixels do not change between updates: interpolated once and kept while the
  // pyramids are, where they take at most 256 MiB; otherwise the force loop interpolates them (the same doubles).
  if (m_FixedAtFinePixels.empty() && nLevels > 1 && n * (nLevels - 1) * sizeof(double) <= (size_t(256) << 20))
  {
    m_FixedAtFinePixels.resize(nLevels - 1);
    for (unsigned int l = 1; l < nLevels; ++l)
    {
      const PyramidLevel &  L = levels[l];
      std::vector<double> & cache = m_FixedAtFinePixels[l - 1];
      cache.resize(n);
      dmr::ParallelForChunks(this->GetMultiThreader(), n, [&](size_t b, size_t e) {
        for (size_t p = b; p < e; ++p)
        {
          cache[p] = fixedLevelAt(L, grid.Index(p));
        }
      });
    }
  }
  const std::vector<std::vector<double>> & fixedAtFine = m_FixedAtFinePixels;
  const bool                               warpedGradient = m_ForceGradient == ForceGradientEnum::WarpedMoving;
  // Eq. 3 sums level i over the pixels of level i. Evaluated at the fine pixels, each fine pixel stands for
  // (pixels of level i) / (fine pixels) of them.
  std::vector<double> levelWeight(nLevels);
  for (unsigned int l = 0; l < nLevels; ++l)
  {
    levelWeight[l] = static_cast<double>(m_Levels[l].fixedGrid.numberOfPixels) / static_cast<double>(n);
  }

  // Per-chunk partial sums, combined in chunk order so the result does not depend on thread timing.
  struct Partial
  {
    double mssd{ 0 }, ssd{ 0 }, f2{ 0 };
    size_t inside{ 0 };
  };
  const size_t         chunk = std::max<size_t>(4096, n / 64 + 1);
  const size_t         nChunks = (n + chunk - 1) / chunk;
  std::vector<Partial> partial(nChunks);
  // the end of a pixel: |f|^2, the outputs, and the sums in pixel order
  auto finishPixel = [&](size_t p, const double(&f)[D], Partial & acc) {
    double f2 = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      f2 += f[k] * f[k];
      gridForce[p * D + k] = static_cast<float>(f[k]);
      double phys = 0.0;
      for (unsigned int j = 0; j < D; ++j)
      {
        phys += dirF[k][j] * f[j];
      }
      if (forceBuffer)
      {
        forceBuffer[p][k] = static_cast<typename ForceFieldType::PixelType::ValueType>(phys);
      }
    }
    densityBuffer[p] = static_cast<typename DensityImageType::PixelType>(f2);
    acc.f2 += f2;
  };
  auto maskedPixel = [&](size_t p) {
    for (unsigned int k = 0; k < D; ++k)
    {
      gridForce[p * D + k] = 0.0f;
      if (forceBuffer)
      {
        forceBuffer[p][k] = 0;
      }
    }
    densityBuffer[p] = 0;
  };
  auto pixel = [&](size_t p, const std::array<int64_t, D> & idx, Partial & acc) {
    if (maskBuffer && maskBuffer[p] == 0)
    {
      maskedPixel(p);
      return;
    }
    ++acc.inside;
    double u[D] = {};
    if (fieldBuffer)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        u[k] = fieldBuffer[p][k];
      }
    }
    // WarpedMoving: grad_x S(W(x)) = (I + grad u)^T (grad S)(W(x)); Jt[j][k] = delta_jk + d u_k / d x_j in the
    // fixed grid frame (u_k = sum_m Direction[m][k] u_m), per mm.
    double Jt[D][D];
    dmr::WarpJacobianTranspose<D>(grid, idx, p, warpedGradient ? fieldBuffer : nullptr, dirF, Jt);
    double f[D] = {}, index[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      index[k] = static_cast<double>(idx[k]);
    }
    for (unsigned int l = 0; l < nLevels; ++l)
    {
      const PyramidLevel & L = levels[l];
      double               cm[D];
      dmr::MovingLevelIndex<D>(L, index, u, cm);
      // level 0 is the fixed image itself
      const double t =
        l == 0 ? static_cast<double>(L.fixed[p]) : (fixedAtFine.empty() ? fixedLevelAt(L, idx) : fixedAtFine[l - 1][p]);
      double s = 0.0, g[D] = {};
      dmr::InterpolateAddPair<D, 1, D>(L.movingGrid, L.moving.data(), L.movingGradient.data(), cm, 1.0, &s, g);
      const double residual = t - s;
      acc.mssd += levelWeight[l] * residual * residual;
      if (l == 0)
      {
        acc.ssd += residual * residual;
      }
      dmr::AddLevelForce<D>(residual, Jt, g, f); // paper Eq. 5
    }
    finishPixel(p, f, acc);
  };
#if DMR_HAVE_DOUBLE_PAIR
  // Two neighbouring pixels of a row at once: the operations of `pixel` in the two lanes of SSE2 registers, so the
  // same doubles bit for bit. The pair also adds the corners of weight 0 (ForEachInterpolationCornerPair), which
  // changes a sum only where such a corner holds a non-finite value; then the pixel's result is not finite, and
  // `pixel` computes that pixel again (as it does any pixel whose pair result is not finite).
  bool pairs = true;
  for (unsigned int l = 0; l < nLevels; ++l)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      pairs = pairs && levels[l].movingGrid.size[k] < (size_t(1) << 31);
    }
  }
  auto pixelPair = [&](size_t p, const std::array<int64_t, D> & idx, Partial & acc) {
    using dmr::DoublePair;
    DoublePair u[D], index[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      u[k] = fieldBuffer ? DoublePair::OfFloats(fieldBuffer[p][k], fieldBuffer[p + 1][k]) : DoublePair::Both(0.0);
      index[k] = DoublePair::Of(static_cast<double>(idx[k]), static_cast<double>(idx[k] + (k == 0 ? 1 : 0)));
    }
    DoublePair Jt[D][D], f[D];
    bool       interior = idx[0] > 0 && idx[0] + 2 < static_cast<int64_t>(grid.size[0]);
    for (unsigned int k = 1; k < D; ++k)
    {
      interior = interior && idx[k] > 0 && idx[k] + 1 < static_cast<int64_t>(grid.size[k]);
    }
    if (warpedGradient && fieldBuffer && interior)
    {
      // WarpJacobianTranspose's operations with central differences on every axis (both pixels are interior)
      for (unsigned int j = 0; j < D; ++j)
      {
        const size_t     stride = grid.stride[j];
        const DoublePair h = DoublePair::Both(2.0 * grid.spacing[j]);
        for (unsigned int k = 0; k < D; ++k)
        {
          DoublePair du = DoublePair::Both(0.0);
          for (unsigned int m = 0; m < D; ++m)
          {
            du += DoublePair::Both(dirF[m][k]) *
                  (DoublePair::OfFloats(fieldBuffer[p + stride][m], fieldBuffer[p + 1 + stride][m]) -
                   DoublePair::OfFloats(fieldBuffer[p - stride][m], fieldBuffer[p + 1 - stride][m]));
          }
          Jt[j][k] = DoublePair::Both(j == k ? 1.0 : 0.0) + du / h;
        }
      }
    }
    else
    {
      double                 Jt0[D][D], Jt1[D][D];
      std::array<int64_t, D> idx1 = idx;
      ++idx1[0];
      dmr::WarpJacobianTranspose<D>(grid, idx, p, warpedGradient ? fieldBuffer : nullptr, dirF, Jt0);
      dmr::WarpJacobianTranspose<D>(grid, idx1, p + 1, warpedGradient ? fieldBuffer : nullptr, dirF, Jt1);
      for (unsigned int j = 0; j < D; ++j)
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          Jt[j][k] = DoublePair::Of(Jt0[j][k], Jt1[j][k]);
        }
      }
    }
    for (unsigned int j = 0; j < D; ++j)
    {
      f[j] = DoublePair::Both(0.0);
    }
    double mssdTerms[2][MaximumNumberOfLevels], ssdTerms[2] = { 0.0, 0.0 };
    for (unsigned int l = 0; l < nLevels; ++l)
    {
      const PyramidLevel & L = levels[l];
      DoublePair           cm[D];
      dmr::MovingLevelIndex<D>(L, index, u, cm);
      DoublePair t;
      if (l == 0)
      {
        t = DoublePair::OfFloats(L.fixed[p], L.fixed[p + 1]);
      }
      else if (!fixedAtFine.empty())
      {
        t = DoublePair::Load(fixedAtFine[l - 1].data() + p);
      }
      else
      {
        std::array<int64_t, D> idx1 = idx;
        ++idx1[0];
        t = DoublePair::Of(fixedLevelAt(L, idx), fixedLevelAt(L, idx1));
      }
      DoublePair s = DoublePair::Both(0.0), g[D];
      for (unsigned int k = 0; k < D; ++k)
      {
        g[k] = DoublePair::Both(0.0);
      }
      const float * moving = L.moving.data();
      const float * gradient = L.movingGradient.data();
      dmr::ForEachInterpolationCornerPair<D>(L.movingGrid, cm, [&](size_t o0, size_t o1, DoublePair w) {
        s += w * DoublePair::OfFloats(moving[o0], moving[o1]);
        for (unsigned int k = 0; k < D; ++k)
        {
          g[k] += w * DoublePair::OfFloats(gradient[o0 * D + k], gradient[o1 * D + k]);
        }
      });
      const DoublePair residual = t - s;
      // the sums take lane 0's terms before lane 1's, as the pixel loop would: kept per level
      const DoublePair term = DoublePair::Both(levelWeight[l]) * residual * residual;
      mssdTerms[0][l] = term.Lane0();
      mssdTerms[1][l] = term.Lane1();
      if (l == 0)
      {
        const DoublePair square = residual * residual;
        ssdTerms[0] = square.Lane0();
        ssdTerms[1] = square.Lane1();
      }
      dmr::AddLevelForce<D>(residual, Jt, g, f);
    }
    for (unsigned int lane = 0; lane < 2; ++lane)
    {
      double fl[D];
      bool   finite = std::isfinite(ssdTerms[lane]);
      for (unsigned int k = 0; k < D; ++k)
      {
        fl[k] = lane == 0 ? f[k].Lane0() : f[k].Lane1();
        finite = finite && std::isfinite(fl[k]);
      }
      for (unsigned int l = 0; l < nLevels; ++l)
      {
        finite = finite && std::isfinite(mssdTerms[lane][l]);
      }
      if (!finite)
      {
        std::array<int64_t, D> laneIdx = idx;
        laneIdx[0] += lane;
        pixel(p + lane, laneIdx, acc);
        continue;
      }
      ++acc.inside;
      for (unsigned int l = 0; l < nLevels; ++l)
      {
        acc.mssd += mssdTerms[lane][l];
      }
      acc.ssd += ssdTerms[lane];
      finishPixel(p + lane, fl, acc);
    }
  };
#endif
  dmr::ParallelForChunks(
    this->GetMultiThreader(),
    nChunks,
    [&](size_t cBegin, size_t cEnd) {
      for (size_t c = cBegin; c < cEnd; ++c)
      {
        Partial      acc;
        const size_t pBegin = c * chunk;
        const size_t pEnd = std::min(n, (c + 1) * chunk);
#if DMR_HAVE_DOUBLE_PAIR
        if (pairs)
        {
          // rows of the chunk in pixel order; two pixels at once where both are in the row, the chunk and the mask
          // (`pixel` handles a masked pixel alone)
          dmr::ForEachPixelOrRowPair(
            grid,
            pBegin,
            pEnd,
            [&](size_t p) { return !(maskBuffer && (maskBuffer[p] == 0 || maskBuffer[p + 1] == 0)); },
            [&](size_t p, const std::array<int64_t, D> & idx) { pixelPair(p, idx, acc); },
            [&](size_t p, const std::array<int64_t, D> & idx) { pixel(p, idx, acc); });
          partial[c] = acc;
          continue;
        }
#endif
        dmr::ForEachPixel(
          grid, pBegin, pEnd, [&](size_t p, const std::array<int64_t, D> & idx) { pixel(p, idx, acc); });
        partial[c] = acc;
      }
    },
    1);
  progress.CompletedPixel();

  Partial total;
  for (const auto & p : partial)
  {
    total.mssd += p.mssd;
    total.ssd += p.ssd;
    total.f2 += p.f2;
    total.inside += p.inside;
  }
  if (total.inside == 0)
  {
    itkExceptionMacro("the fixed mask is empty: no pixel to register");
  }
  m_MSSD = total.mssd;
  m_SSD = total.ssd;
  m_MeanSquaredForce = total.f2 / static_cast<double>(total.inside);
  m_Alpha = this->ComputeAlpha(m_MeanSquaredForce);
  const double alpha = m_Alpha;
  dmr::ParallelForChunks(this->GetMultiThreader(), n, [&](size_t b, size_t e) {
    for (size_t p = b; p < e; ++p)
    {
      densityBuffer[p] = static_cast<typename DensityImageType::PixelType>(densityBuffer[p] + alpha); // Eq. 9
    }
  });
  progress.CompletedPixel();
}

template <typename TF, typename TM, typename TD, typename TO>
double
DensityFieldFilter<TF, TM, TD, TO>::ComputeAlpha(double meanSquaredForce) const
{
  // the density is stored in single precision: an alpha beyond it (or NaN, which passes itkSetClampMacro) made every
  // pixel's density infinite, and the CVT's refusal of it did not say why
  auto checked = [this, meanSquaredForce](double alpha) {
    if (!(alpha <= static_cast<double>(NumericTraits<float>::max())))
    {
      std::ostringstream source;
      if (m_UseFixedAlpha)
      {
        source << "the fixed Alpha";
      }
      else
      {
        source << "AlphaFactor " << m_AlphaFactor << " x the mean |f|^2 " << meanSquaredForce;
      }
      itkExceptionMacro("alpha is " << alpha << " (" << source.str()
                                    << "): it must be a finite number within single precision");
    }
    return alpha;
  };
  if (m_UseFixedAlpha)
  {
    return checked(m_Alpha);
  }
  // Paper 5.1: alpha = 0.1 x the mean importance |f|^2. When the images already match the mean is 0 and the
  // density would vanish: fall back to a floor relative to the squared force scale of the intensity range.
  const double forceScale = m_MovingForceScale;
  // (constant images: any positive value gives the same uniform density; keep it representable as float)
  const double floor = forceScale > 0.0 ? std::max(1e-12 * forceScale * forceScale, 1e-30) : 1.0;
  // (a NaN product stays NaN: max keeps its first.) Rounded to single precision's 24 bits, the density's precision:
  // the mean |f|^2 is a sum over the image whose last bits depend on the order of summation, which differs between the
  // CPU and the GPU; rounded, both back-ends take the same alpha (see dmr::RoundToSingleSignificand)
  return dmr::RoundToSingleSignificand(checked(std::max(m_AlphaFactor * meanSquaredForce, floor)));
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::WarpMovingImage(const DisplacementFieldType * field, std::vector<float> & out) const
{
  constexpr unsigned int D = ImageDimension;
  if (m_Levels.empty())
  {
    itkExceptionMacro("WarpMovingImage needs the pyramids: call Update() first");
  }
  const PyramidLevel & L = m_Levels[0];
  const GridType       grid = m_Levels[0].fixedGrid;
  out.resize(grid.numberOfPixels);
  const auto * fieldBuffer = field ? field->GetBufferPointer() : nullptr;
  dmr::ParallelForChunks(this->GetMultiThreader(), grid.numberOfPixels, [&](size_t b, size_t e) {
    for (size_t p = b; p < e; ++p)
    {
      const auto idx = grid.Index(p);
      double     cm[D];
      for (unsigned int r = 0; r < D; ++r)
      {
        cm[r] = L.Mc[r];
        for (unsigned int k = 0; k < D; ++k)
        {
          cm[r] += L.MA[r][k] * static_cast<double>(idx[k]) + (fieldBuffer ? L.MB[r][k] * fieldBuffer[p][k] : 0.0);
        }
      }
      double s = 0.0;
      dmr::InterpolateAdd<D, 1>(L.movingGrid, L.moving.data(), cm, 1.0 / m_IntensityScale, &s);
      out[p] = static_cast<float>(s);
    }
  });
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::ReleaseInternalBuffers()
{
  std::vector<PyramidLevel>().swap(m_Levels);
  std::vector<float>().swap(m_GridForce);
  std::vector<std::vector<double>>().swap(m_FixedAtFinePixels);
  m_PyramidTime = 0;
  m_PyramidFixed = nullptr;
  m_PyramidMoving = nullptr;
  m_PyramidLevels = 0;
  this->GetOutput()->ReleaseData();
  this->GetForceField()->ReleaseData();
  this->Modified();
}

template <typename TF, typename TM, typename TD, typename TO>
void
DensityFieldFilter<TF, TM, TD, TO>::PrintSelf(std::ostream & os, Indent indent) const
{
  Superclass::PrintSelf(os, indent);
  os << indent << "NumberOfLevels: " << m_NumberOfLevels << std::endl;
  os << indent << "AlphaFactor: " << m_AlphaFactor << std::endl;
  os << indent << "UseFixedAlpha: " << (m_UseFixedAlpha ? "On" : "Off") << std::endl;
  os << indent << "ForceGradient: " << m_ForceGradient << std::endl;
  os << indent << "ComputeForceField: " << (m_ComputeForceField ? "On" : "Off") << std::endl;
  os << indent << "Alpha: " << m_Alpha << std::endl;
  os << indent << "MSSD: " << m_MSSD << std::endl;
  os << indent << "SSD: " << m_SSD << std::endl;
  os << indent << "MeanSquaredForce: " << m_MeanSquaredForce << std::endl;
  os << indent << "IntensityScale: " << m_IntensityScale << std::endl;
}
} // namespace itk

#endif
