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
#include "dmrBreathingDeformation.h"
#include "dmrLungMask.h"
#include "dmrErrorStatistics.h"
#include "dmrFieldImage.h"
#include "dmrImageMetrics.h"
#include "dmrDataTestHelpers.h"
#include "itkDisplacementFieldTransform.h"
#include "itkLinearInterpolateImageFunction.h"
#include "itkResampleImageFilter.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "gtest/gtest.h"
#include <random>

namespace
{
using FieldType = itk::Image<itk::Vector<float, 3>, 3>;
using DoubleFieldType = itk::Image<itk::Vector<double, 3>, 3>;
using ImageType = itk::Image<float, 3>;

/** A thorax-sized grid: 315 x 295 x 330 mm at 5 x 5 x 6 mm (anisotropic), oblique direction. */
ImageType::Pointer
ThoraxGrid(const itk::Vector<double, 3> & spacing = dmrtest::Vec(5.0, 5.0, 6.0),
           const itk::Size<3> &           size = { { 64, 60, 56 } })
{
  return dmrtest::MakeImage<ImageType>(size, spacing, dmrtest::ObliqueDirection(), dmrtest::Pt(0.0, 0.0, -30.0));
}

dmrtools::BreathingDeformation
MakeDeformation(const ImageType * grid, double amplitude = 15.0)
{
  dmrtools::BreathingParameters p;
  p.amplitudeMM = amplitude;
  return dmrtools::BreathingDeformation(grid, dmrtools::DefaultLungBox(grid), p);
}

/** Smooth test image in physical space: a few broad Gaussians (sigma 25-40 mm) plus a gentle ramp. */
double
SmoothIntensity(const itk::Point<double, 3> & x)
{
  const double centres[4][3] = { { -40, 10, -50 }, { 50, -20, -10 }, { 0, 30, 40 }, { 10, -40, -90 } };
  const double sigma[4] = { 30, 25, 40, 28 };
  const double weight[4] = { 400, -300, 250, 350 };
  double       v = 0.2 * x[2];
  for (int g = 0; g < 4; ++g)
  {
    double r2 = 0;
    for (unsigned int k = 0; k < 3; ++k)
    {
      r2 += (x[k] - centres[g][k]) * (x[k] - centres[g][k]);
    }
    v += weight[g] * std::exp(-0.5 * r2 / (sigma[g] * sigma[g]));
  }
  return v;
}

template <typename TImage>
void
FillWith(TImage * image, double (*f)(const itk::Point<double, 3> &))
{
  itk::ImageRegionIteratorWithIndex<TImage> it(image, image->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    itk::Point<double, 3> x;
    image->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    it.Set(static_cast<typename TImage::PixelType>(f(x)));
  }
}

/** Random voxel indices at least margin voxels inside the image. */
std::vector<itk::Index<3>>
RandomInteriorIndices(const itk::ImageBase<3> * image, size_t count, unsigned int margin, uint32_t seed)
{
  std::mt19937               engine(seed);
  std::vector<itk::Index<3>> out;
  const auto                 size = image->GetLargestPossibleRegion().GetSize();
  for (size_t i = 0; i < count; ++i)
  {
    itk::Index<3> idx;
    for (unsigned int k = 0; k < 3; ++k)
    {
      std::uniform_int_distribution<long> d(margin, static_cast<long>(size[k]) - 1 - margin);
      idx[k] = d(engine);
    }
    out.push_back(idx);
  }
  return out;
}
} // namespace

TEST(BreathingDeformation, JacobianPositiveOnEveryVoxel)
{
  auto grid = ThoraxGrid();
  for (const double amplitude : { 5.0, 15.0, 25.0 })
  {
    const auto deformation = MakeDeformation(grid, amplitude);
    auto       field = dmrtools::SampleDisplacementField<FieldType>(deformation, grid);
    const auto r = dmrtools::AnalyzeDisplacementField(field.GetPointer());
    EXPECT_GT(r.minimumJacobian, 0.0) << "amplitude " << amplitude;
    EXPECT_LT(r.maximumGradientNorm, 1.0) << "amplitude " << amplitude << ": not a contraction";
    std::cout << "amplitude " << amplitude << ": det J [" << r.minimumJacobian << ", " << r.maximumJacobian
              << "], max |grad u| " << r.maximumGradientNorm << ", max |u| " << r.maximumMagnitude << std::endl;
    // the library's Jacobian (grid frame) agrees with this one (physical frame): the direction is handled right
    std::pair<double, double> range;
    itk::dmr::JacobianDeterminantImage(field.GetPointer(), range, itk::MultiThreaderBase::New());
    EXPECT_NEAR(range.first, r.minimumJacobian, 1e-4);
    EXPECT_NEAR(range.second, r.maximumJacobian, 1e-4);
  }
}

TEST(BreathingDeformation, MaximumDisplacementNearAmplitude)
{
  auto       grid = ThoraxGrid();
  auto       field = dmrtools::SampleDisplacementField<FieldType>(MakeDeformation(grid, 15.0), grid);
  const auto r = dmrtools::AnalyzeDisplacementField(field.GetPointer());
  EXPECT_GE(r.maximumMagnitude, 10.0);
  EXPECT_LE(r.maximumMagnitude, 16.0);
  // linear in the amplitude, zero for zero amplitude
  // with a fixed border ramp (the default one grows with large amplitudes) u is linear in the amplitude
  dmrtools::BreathingParameters p;
  p.borderRampMM = 80.0;
  p.amplitudeMM = 15.0;
  auto full = dmrtools::SampleDisplacementField<FieldType>(
    dmrtools::BreathingDeformation(grid, dmrtools::DefaultLungBox(grid), p), grid);
  p.amplitudeMM = 7.5;
  auto half = dmrtools::SampleDisplacementField<FieldType>(
    dmrtools::BreathingDeformation(grid, dmrtools::DefaultLungBox(grid), p), grid);
  EXPECT_NEAR(dmrtools::AnalyzeDisplacementField(half.GetPointer()).maximumMagnitude,
              0.5 * dmrtools::AnalyzeDisplacementField(full.GetPointer()).maximumMagnitude,
              1e-4);
  auto zero = dmrtools::SampleDisplacementField<FieldType>(MakeDeformation(grid, 0.0), grid);
  EXPECT_EQ(dmrtools::AnalyzeDisplacementField(zero.GetPointer()).maximumMagnitude, 0.0);
}

TEST(BreathingDeformation, ZeroNearTheImageBorder)
{
  auto       grid = ThoraxGrid();
  const auto deformation = MakeDeformation(grid);
  auto       field = dmrtools::SampleDisplacementField<FieldType>(deformation, grid);
  const auto r = dmrtools::AnalyzeDisplacementField(field.GetPointer());
  EXPECT_EQ(r.maximumBorderMagnitude, 0.0);
  const double                                      zone = deformation.GetParameters().borderZeroMM;
  const auto                                        size = grid->GetLargestPossibleRegion().GetSize();
  size_t                                            checked = 0;
  itk::ImageRegionConstIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    double d = 1e9; // mm to the outer voxel layer
    for (unsigned int k = 0; k < 3; ++k)
    {
      const auto i = it.GetIndex()[k];
      d =
        std::min(d, static_cast<double>(std::min<long>(i, static_cast<long>(size[k]) - 1 - i)) * grid->GetSpacing()[k]);
    }
    if (d < zone - 1e-6)
    {
      ++checked;
      ASSERT_EQ(it.Get().GetNorm(), 0.0f) << "at " << it.GetIndex();
    }
  }
  EXPECT_GT(checked, 0u);
}

TEST(BreathingDeformation, SmoothField)
{
  auto       grid = ThoraxGrid();
  const auto deformation = MakeDeformation(grid);
  auto       field = dmrtools::SampleDisplacementField<FieldType>(deformation, grid);
  const auto r = dmrtools::AnalyzeDisplacementField(field.GetPointer());
  EXPECT_LT(r.maximumGradientNorm, 0.5);
  // |d2u/dx2| < 0.03/mm: the gradient changes by less than 0.03 per mm (largest in the border ramp, where the
  // smoothstep's second derivative is 5.77 A / ramp^2 = 0.018/mm for A = 15 mm, ramp 70 mm)
  EXPECT_LT(r.maximumSecondDifference, 0.03);
  // the sampled field interpolates the closed form closely between voxels (no high frequencies)
  auto interpolator = itk::VectorLinearInterpolateImageFunction<FieldType, double>::New();
  interpolator->SetInputImage(field);
  std::mt19937                           engine(11);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  double                                 worst = 0.0;
  for (int i = 0; i < 2000; ++i)
  {
    itk::ContinuousIndex<double, 3> c;
    for (unsigned int k = 0; k < 3; ++k)
    {
      c[k] = unit(engine) * static_cast<double>(grid->GetLargestPossibleRegion().GetSize(k) - 1);
    }
    itk::Point<double, 3> x;
    grid->TransformContinuousIndexToPhysicalPoint(c, x);
    const auto a = deformation.Displacement(x);
    const auto b = interpolator->EvaluateAtContinuousIndex(c);
    for (unsigned int k = 0; k < 3; ++k)
    {
      worst = std::max(worst, std::abs(a[k] - b[k]));
    }
  }
  EXPECT_LT(worst, 0.1) << "mm";
}

TEST(BreathingDeformation, BreathingLikeDirections)
{
  // identity direction: the lung box is then the image box's central part along the patient axes
  auto grid = dmrtest::MakeImage<ImageType>(
    { { 64, 60, 56 } }, dmrtest::Vec(5.0, 5.0, 6.0), dmrtest::ObliqueDirection(0.0, 0.0), dmrtest::Pt(0.0, 0.0, -30.0));
  const auto                  box = dmrtools::DefaultLungBox(grid);
  const auto                  deformation = MakeDeformation(grid);
  const itk::Point<double, 3> c = dmrtest::Pt(
    0.5 * (box.lower[0] + box.upper[0]), 0.5 * (box.lower[1] + box.upper[1]), 0.5 * (box.lower[2] + box.upper[2]));
  auto       at = [&](double x, double y, double z) { return deformation.Displacement(dmrtest::Pt(x, y, z)); };
  const auto base = at(c[0], c[1], box.lower[2]);
  const auto apex = at(c[0], c[1], box.upper[2]);
  EXPECT_LT(base[2], -10.0); // LPS: z is superior, the diaphragm moves down
  EXPECT_LT(std::abs(apex[2]), 0.15 * std::abs(base[2]));
  EXPECT_NEAR(base[0], 0.0, 1e-9); // no sideways motion on the axis
  const double zMid = box.lower[2] + 0.3 * (box.upper[2] - box.lower[2]);
  EXPECT_GT(at(box.upper[0], c[1], zMid)[0], 1.0);  // left wall (+x in LPS) moves left
  EXPECT_LT(at(box.lower[0], c[1], zMid)[0], -1.0); // right wall moves right
  EXPECT_LT(at(c[0], box.lower[1], zMid)[1], -2.0); // anterior wall (-y in LPS) moves anteriorly
}

TEST(BreathingDeformation, InverseIsExact)
{
  auto                                   grid = ThoraxGrid();
  const auto                             deformation = MakeDeformation(grid, 20.0);
  std::mt19937                           engine(3);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int i = 0; i < 1000; ++i)
  {
    itk::ContinuousIndex<double, 3> c;
    for (unsigned int k = 0; k < 3; ++k)
    {
      c[k] = unit(engine) * static_cast<double>(grid->GetLargestPossibleRegion().GetSize(k) - 1);
    }
    itk::Point<double, 3> x;
    grid->TransformContinuousIndexToPhysicalPoint(c, x);
    const itk::Point<double, 3> y = x + deformation.Displacement(x);
    const itk::Point<double, 3> back = y + deformation.InverseDisplacement(y);
    ASSERT_LT(back.EuclideanDistanceTo(x), 1e-4) << "at " << x;
  }
}

TEST(BreathingDeformation, WarpSatisfiesMovingOfXPlusUEqualsFixed)
{
  auto fixed = ThoraxGrid(dmrtest::Vec(4.0, 4.0, 5.0), { { 80, 74, 66 } });
  FillWith(fixed.GetPointer(), SmoothIntensity);
  const auto deformation = MakeDeformation(fixed);
  auto       moving = dmrtools::WarpWithBreathing(fixed.GetPointer(), deformation);
  auto       interpolator = itk::LinearInterpolateImageFunction<ImageType, double>::New();
  interpolator->SetInputImage(moving);
  double     worst = 0.0, sumError = 0.0, sumChange = 0.0;
  const auto points = RandomInteriorIndices(fixed, 2000, 4, 5);
  for (const auto & idx : points)
  {
    itk::Point<double, 3> x;
    fixed->TransformIndexToPhysicalPoint(idx, x);
    const double f = fixed->GetPixel(idx);
    const double m = interpolator->Evaluate(x + deformation.Displacement(x)); // moving(x + u(x))
    worst = std::max(worst, std::abs(m - f));
    sumError += std::abs(m - f);
    sumChange += std::abs(moving->GetPixel(idx) - f);
  }
  std::cout << "mean |moving(x+u)-fixed(x)| " << sumError / points.size() << ", mean |moving(x)-fixed(x)| "
            << sumChange / points.size() << ", worst " << worst << std::endl;
  const auto range = itk::dmr::IntensityRange(fixed.GetPointer());
  EXPECT_LT(worst, 0.01 * (range.second - range.first));
  EXPECT_LT(sumError, 0.05 * sumChange); // the warp is real, and undone by x + u(x)
  // the wrong direction (x - u(x)) does not undo it
  double wrong = 0.0;
  for (const auto & idx : points)
  {
    itk::Point<double, 3> x;
    fixed->TransformIndexToPhysicalPoint(idx, x);
    wrong += std::abs(interpolator->Evaluate(x - deformation.Displacement(x)) - fixed->GetPixel(idx));
  }
  EXPECT_GT(wrong, 10.0 * sumError);
}

TEST(BreathingDeformation, ItkResampleWithTruthFieldReproducesFixed)
{
  // ITK's convention: ResampleImageFilter(moving, DisplacementFieldTransform(u)) gives moving(x + u(x)) = fixed(x)
  auto fixed = ThoraxGrid(dmrtest::Vec(4.0, 4.0, 5.0), { { 80, 74, 66 } });
  FillWith(fixed.GetPointer(), SmoothIntensity);
  const auto deformation = MakeDeformation(fixed);
  auto       moving = dmrtools::WarpWithBreathing(fixed.GetPointer(), deformation);
  auto       truth = dmrtools::SampleDisplacementField<DoubleFieldType>(deformation, fixed);
  auto       transform = itk::DisplacementFieldTransform<double, 3>::New();
  transform->SetDisplacementField(truth);
  auto resample = itk::ResampleImageFilter<ImageType, ImageType>::New();
  resample->SetInput(moving);
  resample->SetTransform(transform);
  resample->SetOutputParametersFromImage(fixed);
  resample->Update();
  double     error = 0.0, change = 0.0;
  const auto points = RandomInteriorIndices(fixed, 2000, 4, 9);
  for (const auto & idx : points)
  {
    error += std::abs(resample->GetOutput()->GetPixel(idx) - fixed->GetPixel(idx));
    change += std::abs(moving->GetPixel(idx) - fixed->GetPixel(idx));
  }
  EXPECT_LT(error, 0.05 * change);
}

TEST(BreathingDeformation, BadParametersThrow)
{
  auto                          grid = ThoraxGrid();
  dmrtools::BreathingParameters p;
  p.amplitudeMM = -1.0;
  EXPECT_THROW(dmrtools::BreathingDeformation(grid, dmrtools::DefaultLungBox(grid), p), itk::ExceptionObject);
  p.amplitudeMM = 15.0;
  dmrtools::PhysicalBox flat = dmrtools::DefaultLungBox(grid);
  flat.upper[2] = flat.lower[2];
  EXPECT_THROW(dmrtools::BreathingDeformation(grid, flat, p), itk::ExceptionObject);
  auto empty = dmrtools::LungMaskImageType::New();
  empty->SetRegions(itk::Size<3>{ { 4, 4, 4 } });
  empty->Allocate();
  empty->FillBuffer(0);
  EXPECT_THROW(dmrtools::MaskBoundingBox(empty.GetPointer()), itk::ExceptionObject);
}

TEST(DenseError, MeanAndP95InsideMask)
{
  auto truth = dmrtest::MakeImage<FieldType>(
    { { 10, 8, 6 } }, dmrtest::Vec(0.6, 0.6, 2.5), dmrtest::ObliqueDirection(), dmrtest::Pt(0, 0, 0));
  auto estimate = dmrtest::MakeImage<FieldType>(
    { { 10, 8, 6 } }, dmrtest::Vec(0.6, 0.6, 2.5), dmrtest::ObliqueDirection(), dmrtest::Pt(0, 0, 0));
  auto mask = dmrtest::MakeImage<dmrtools::LungMaskImageType>(
    { { 10, 8, 6 } }, dmrtest::Vec(0.6, 0.6, 2.5), dmrtest::ObliqueDirection(), dmrtest::Pt(0, 0, 0));
  truth->FillBuffer(dmrtest::Vec(1.0f, 2.0f, 3.0f));
  // estimate = truth + (0.3, 0.4, 0) in the x < 5 half (the mask), truth + (3, 4, 0) elsewhere
  itk::ImageRegionIteratorWithIndex<FieldType> it(estimate, estimate->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    const bool in = it.GetIndex()[0] < 5;
    it.Set(in ? dmrtest::Vec(1.3f, 2.4f, 3.0f) : dmrtest::Vec(4.0f, 6.0f, 3.0f));
    mask->SetPixel(it.GetIndex(), in ? 1 : 0);
  }
  const auto inside = dmrtools::DisplacementErrorInMask(estimate.GetPointer(), truth.GetPointer(), mask.GetPointer());
  EXPECT_EQ(inside.count, 5u * 8u * 6u);
  EXPECT_NEAR(inside.mean, 0.5, 1e-6);
  EXPECT_NEAR(inside.p95, 0.5, 1e-6);
  const auto all = dmrtools::DisplacementErrorInMask(
    estimate.GetPointer(), truth.GetPointer(), static_cast<dmrtools::LungMaskImageType *>(nullptr));
  EXPECT_EQ(all.count, 10u * 8u * 6u);
  EXPECT_NEAR(all.mean, 2.75, 1e-6);
  EXPECT_NEAR(all.max, 5.0, 1e-6);
  const auto magnitude = dmrtools::DisplacementMagnitudeInMask(truth.GetPointer(), mask.GetPointer());
  EXPECT_NEAR(magnitude.mean, std::sqrt(14.0), 1e-6);
  // fields on different grids are refused
  auto other = dmrtest::MakeImage<FieldType>(
    { { 10, 8, 6 } }, dmrtest::Vec(0.6, 0.6, 2.0), dmrtest::ObliqueDirection(), dmrtest::Pt(0, 0, 0));
  EXPECT_THROW(dmrtools::DisplacementErrorInMask(other.GetPointer(), truth.GetPointer(), mask.GetPointer()),
               itk::ExceptionObject);
}

TEST(LungMask, PhantomLungsFoundVesselsFilledGasExcluded)
{
  double volume = 0.0;
  auto   ct = dmrtest::MakeThoraxPhantom(
    { { 96, 80, 60 } }, dmrtest::Vec(3.5, 3.5, 5.0), dmrtest::ObliqueDirection(), false, &volume);
  dmrtools::LungMaskReport report;
  auto                     mask = dmrtools::LungMask(ct.GetPointer(), {}, &report);
  EXPECT_EQ(report.axialAxis, 2u);
  EXPECT_EQ(report.components, 2u);
  EXPECT_NEAR(report.volumeLitres, volume * 1e-6, 0.08 * volume * 1e-6);
  // every voxel in the mask is lung or vessel; every lung voxel is in the mask; no air outside, no gas pocket
  size_t                                                       wrong = 0, vessels = 0;
  itk::ImageRegionConstIteratorWithIndex<itk::Image<short, 3>> it(ct, ct->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    const bool  in = mask->GetPixel(it.GetIndex()) != 0;
    const short v = it.Get();
    wrong += (v == -850 && !in) || (v == -1000 && in) || (v == -900 && in) || (v == 40 && in);
    vessels += v == 60 && in;
  }
  EXPECT_EQ(wrong, 0u);
  EXPECT_GT(vessels, 0u);
  EXPECT_EQ(mask->GetSpacing(), ct->GetSpacing());
  EXPECT_EQ(mask->GetDirection(), ct->GetDirection());
}

TEST(LungMask, LungsCutByTheLastSliceAreKept)
{
  double volume = 0.0;
  auto   ct = dmrtest::MakeThoraxPhantom(
    { { 96, 80, 60 } }, dmrtest::Vec(3.5, 3.5, 5.0), dmrtest::ObliqueDirection(), true, &volume);
  dmrtools::LungMaskReport report;
  dmrtools::LungMask(ct.GetPointer(), {}, &report);
  EXPECT_EQ(report.components, 2u);
  EXPECT_NEAR(report.volumeLitres, volume * 1e-6, 0.08 * volume * 1e-6);
}

TEST(LungMask, NoAirMeansEmptyMask)
{
  auto ct = dmrtest::MakeImage<itk::Image<short, 3>>(
    { { 20, 20, 10 } }, dmrtest::Vec(1.0, 1.0, 1.0), dmrtest::ObliqueDirection(0, 0), dmrtest::Pt(0, 0, 0));
  ct->FillBuffer(100);
  dmrtools::LungMaskReport report;
  auto                     mask = dmrtools::LungMask(ct.GetPointer(), {}, &report);
  EXPECT_EQ(report.voxels, 0u);
  EXPECT_EQ(report.components, 0u);
}

TEST(LungMask, LungBoxFromMaskSkipsTracheaAndRecesses)
{
  auto ct =
    dmrtest::MakeThoraxPhantom({ { 96, 80, 60 } }, dmrtest::Vec(3.5, 3.5, 5.0), dmrtest::ObliqueDirection(0, 0));
  auto       mask = dmrtools::LungMask(ct.GetPointer());
  const auto bbox = dmrtools::MaskBoundingBox(mask.GetPointer());
  const auto box = dmrtools::LungBoxFromMask(mask.GetPointer());
  // x, y as the bounding box; z starts above the ellipsoids' thin bottom caps and ends below their tips
  EXPECT_EQ(box.lower[0], bbox.lower[0]);
  EXPECT_EQ(box.upper[1], bbox.upper[1]);
  EXPECT_GT(box.lower[2], bbox.lower[2]);
  EXPECT_LT(box.upper[2], bbox.upper[2] + 1e-9);
  // an ellipsoid's section area reaches half its largest at (1 - 1/sqrt(2)) of the half height above the bottom
  const double halfHeight = 0.5 * (bbox.upper[2] - bbox.lower[2]);
  EXPECT_NEAR(box.lower[2] - bbox.lower[2], (1.0 - std::sqrt(0.5)) * halfHeight, 6.0);
}
