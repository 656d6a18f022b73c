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
#include "itkDensityFieldFilter.h"
#include "dmrBackEndRounding.h"
#include "dmrImageMetrics.h"
#include "dmrGaussianShrink.h"
#include "itkCastImageFilter.h"
#include "itkDiscreteGaussianImageFilter.h"
#include "itkShrinkImageFilter.h"
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <tuple>
#include <vector>
#include "dmrObjectChecks.h"
#include "dmrTestHelpers.h"
#include "itkRegionOfInterestImageFilter.h"
#include "itkImageRegionConstIteratorWithIndex.h"
#include "gtest/gtest.h"

namespace
{
using ImageType = itk::Image<float, 2>;
using FilterType = itk::DensityFieldFilter<ImageType>;
using FieldType = FilterType::DisplacementFieldType;

ImageType::SpacingType
Spacing(double sx, double sy)
{
  ImageType::SpacingType s;
  s[0] = sx;
  s[1] = sy;
  return s;
}

ImageType::PointType
Origin(double x, double y)
{
  ImageType::PointType p;
  p[0] = x;
  p[1] = y;
  return p;
}

/** Smooth blob of intensity 100 (Gaussian, sigma 4 mm) centred at c, in physical space. */
auto
Blob(const ImageType::PointType & c)
{
  return [c](const ImageType::PointType & p) {
    const double r2 = (p[0] - c[0]) * (p[0] - c[0]) + (p[1] - c[1]) * (p[1] - c[1]);
    return static_cast<float>(100.0 * std::exp(-r2 / (2.0 * 4.0 * 4.0)));
  };
}

/** 40 x 32 pixels, spacing 1 x 1.5 mm: a blob and the same blob 3 mm to the right and 2 mm down. */
constexpr ImageType::SizeType BlobPairSize{ { 40, 32 } };
std::pair<ImageType::Pointer, ImageType::Pointer>
BlobPair()
{
  const auto identity = itk::dmr::test::RotationDirection2D<ImageType>(0.0);
  return {
    itk::dmr::test::MakeImage<ImageType>(BlobPairSize, Spacing(1, 1.5), Origin(0, 0), identity, Blob(Origin(18, 20))),
    itk::dmr::test::MakeImage<ImageType>(BlobPairSize, Spacing(1, 1.5), Origin(0, 0), identity, Blob(Origin(21, 18)))
  };
}

itk::Vector<double, 2>
Vec(double x, double y)
{
  itk::Vector<double, 2> v;
  v[0] = x;
  v[1] = y;
  return v;
}

FieldType::Pointer
ConstantField(const ImageType * like, const FieldType::PixelType & value)
{
  auto field = FieldType::New();
  field->CopyInformation(like);
  field->SetRegions(like->GetLargestPossibleRegion());
  field->Allocate();
  field->FillBuffer(value);
  return field;
}

/** IntensityRange and FirstNonFinitePixel on the threader's work units give the serial scan's answers: on random
 * images with a planted extreme or non-finite value at the start, in the middle of a chunk, at a chunk's edge and at
 * the end, with several non-finite values (the first one counts) and with NaNs that the range passes over. */
TEST(ImageMetrics, ThreadedRangeAndFirstNonFinitePixelEqualTheSerialScan)
{
  auto threader = itk::MultiThreaderBase::New();
  threader->SetNumberOfWorkUnits(8);
  using Image3 = itk::Image<float, 3>;
  auto image = Image3::New();
  image->SetRegions(Image3::SizeType{ { 97, 61, 23 } }); // 136 091 pixels: 33 chunks, the last one cut
  image->Allocate();
  const size_t                          n = image->GetBufferedRegion().GetNumberOfPixels();
  float *                               buffer = image->GetBufferPointer();
  std::mt19937                          random(7);
  std::uniform_real_distribution<float> value(-1000.0f, 3000.0f);
  for (const size_t at : { size_t{ 0 }, size_t{ 4123 }, size_t{ 4124 }, n / 3, n - 1 })
  {
    SCOPED_TRACE("planted at " + std::to_string(at));
    for (size_t p = 0; p < n; ++p)
    {
      buffer[p] = value(random);
    }
    EXPECT_EQ(itk::dmr::FirstNonFinitePixel(image.GetPointer(), threader), -1);
    buffer[at] = -5000.0f;
    buffer[n - 1 - at] = 7000.0f;
    const auto serial = itk::dmr::IntensityRange(image.GetPointer());
    EXPECT_EQ(serial, std::make_pair(-5000.0, 7000.0));
    EXPECT_EQ(itk::dmr::IntensityRange(image.GetPointer(), threader), serial);
    // a NaN is passed over by both
    buffer[(at + n / 5) % n] = std::numeric_limits<float>::quiet_NaN();
    EXPECT_EQ(itk::dmr::IntensityRange(image.GetPointer(), threader), itk::dmr::IntensityRange(image.GetPointer()));
    // non-finite values: the first one, wherever the chunks fall
    buffer[n - 1] = std::numeric_limits<float>::infinity();
    buffer[at] = -std::numeric_limits<float>::infinity();
    const int64_t first = static_cast<int64_t>(std::min(at, (at + n / 5) % n));
    EXPECT_EQ(itk::dmr::FirstNonFinitePixel(image.GetPointer()), first);
    EXPECT_EQ(itk::dmr::FirstNonFinitePixel(image.GetPointer(), threader), first);
  }
  // a displacement field: a non-finite component of a vector pixel
  auto field = FieldType::New();
  field->SetRegions(FieldType::SizeType{ { 300, 200 } });
  field->Allocate();
  field->FillBuffer(FieldType::PixelType(1.5f));
  EXPECT_EQ(itk::dmr::FirstNonFinitePixel(field.GetPointer(), threader), -1);
  field->GetBufferPointer()[45678][1] = std::numeric_limits<float>::quiet_NaN();
  field->GetBufferPointer()[59000][0] = std::numeric_limits<float>::infinity();
  EXPECT_EQ(itk::dmr::FirstNonFinitePixel(field.GetPointer(), threader), 45678);
  EXPECT_EQ(itk::dmr::FirstNonFinitePixel(field.GetPointer()), 45678);
}

TEST(BackEndRounding, RoundsToSinglePrecisionsSignificandInDoublesRange)
{
  using itk::dmr::RoundToSingleSignificand;
  // in float's normal range it is the cast to float, ties to even included
  std::mt19937_64 rng(33);
  for (int i = 0; i < 100000; ++i)
  {
    const double x =
      std::ldexp(std::uniform_real_distribution<double>(-1.0, 1.0)(rng), static_cast<int>(rng() % 200) - 100);
    ASSERT_EQ(RoundToSingleSignificand(x), static_cast<double>(static_cast<float>(x))) << x;
  }
  EXPECT_EQ(RoundToSingleSignificand(1.0 + 0x1p-24), 1.0);
  EXPECT_EQ(RoundToSingleSignificand(1.0 + 3 * 0x1p-24), 1.0 + 0x1p-22);
  EXPECT_EQ(RoundToSingleSignificand(-(1.0 + 3 * 0x1p-24)), -(1.0 + 0x1p-22));
  // beyond float's range it keeps double's exponent (a cast would give infinity or 0)
  for (const double x : { 1e300, 3.3e-300, -7e200 })
  {
    const double r = RoundToSingleSignificand(x);
    EXPECT_NE(r, 0.0) << x;
    EXPECT_TRUE(std::isfinite(r)) << x;
    EXPECT_LE(std::abs(r - x), 0x1p-24 * std::abs(x)) << x;
    int e = 0;
    EXPECT_EQ(std::ldexp(std::frexp(r, &e), 24), std::round(std::ldexp(std::frexp(r, &e), 24))) << "24 bits: " << x;
  }
  EXPECT_EQ(RoundToSingleSignificand(0.0), 0.0);
  EXPECT_TRUE(std::isnan(RoundToSingleSignificand(std::nan(""))));
  EXPECT_EQ(RoundToSingleSignificand(HUGE_VAL), HUGE_VAL);
  // what it is for: sums that differ in their last bits give the same value
  EXPECT_EQ(RoundToSingleSignificand(0.1), RoundToSingleSignificand(std::nextafter(0.1, 1.0) + 4e-17));
}

TEST(DensityFieldFilter, BasicObjectMethodsPrintAndSetGet)
{
  auto filter = FilterType::New();
  EXPECT_TRUE(itk::dmr::test::BasicObjectMethods(filter.GetPointer(), "DensityFieldFilter", "ImageToImageFilter"));
  EXPECT_TRUE(itk::dmr::test::PrintMentions(
    filter.GetPointer(),
    { "NumberOfLevels", "AlphaFactor", "UseFixedAlpha", "Alpha", "MSSD", "SSD", "MeanSquaredForce", "ForceGradient" }));
  DMR_EXPECT_SET_GET(filter, NumberOfLevels, 2u);
  EXPECT_EQ(filter->GetForceGradient(), FilterType::ForceGradientEnum::WarpedMoving);
  DMR_EXPECT_SET_GET(filter, ForceGradient, FilterType::ForceGradientEnum::MappedMoving);
  DMR_EXPECT_SET_GET(filter, AlphaFactor, 0.25);
  DMR_EXPECT_SET_GET(filter, UseFixedAlpha, true);
  DMR_EXPECT_SET_GET(filter, Alpha, 3.5);
  filter->UseFixedAlphaOff();
  EXPECT_FALSE(filter->GetUseFixedAlpha());
  filter->SetNumberOfLevels(0);
  EXPECT_EQ(filter->GetNumberOfLevels(), 1u);
  filter->SetNumberOfLevels(9);
  EXPECT_EQ(filter->GetNumberOfLevels(), 8u);
  filter->SetAlphaFactor(-1.0);
  EXPECT_EQ(filter->GetAlphaFactor(), 0.0);
  auto image = ImageType::New();
  filter->SetFixedImage(image);
  filter->SetMovingImage(image);
  EXPECT_EQ(filter->GetFixedImage(), image.GetPointer());
  EXPECT_EQ(filter->GetMovingImage(), image.GetPointer());
  auto field = FieldType::New();
  filter->SetDisplacementField(field);
  EXPECT_EQ(filter->GetDisplacementField(), field.GetPointer());
}

TEST(DensityFieldFilter, BadInputThrows)
{
  auto image = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 16 } },
                                                    Spacing(1, 1),
                                                    Origin(0, 0),
                                                    itk::dmr::test::RotationDirection2D<ImageType>(0.0),
                                                    Blob(Origin(10, 8)));
  {
    auto filter = FilterType::New();
    filter->SetFixedImage(image);
    filter->SetMovingImage(image);
    auto field = FieldType::New();
    field->SetRegions(FieldType::SizeType{ { 10, 16 } });
    field->Allocate(true);
    filter->SetDisplacementField(field);
    EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  }
  {
    auto thin = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 1 } },
                                                     Spacing(1, 1),
                                                     Origin(0, 0),
                                                     itk::dmr::test::RotationDirection2D<ImageType>(0.0),
                                                     Blob(Origin(10, 0)));
    auto filter = FilterType::New();
    filter->SetFixedImage(thin);
    filter->SetMovingImage(thin);
    EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  }
  {
    auto filter = FilterType::New();
    filter->SetFixedImage(image); // no moving image
    EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  }
  // a direction that is not a rotation (sheared): the force is turned with the direction's transpose, which is its
  // inverse only for a rotation or reflection, so it was wrong without a word
  for (const bool inFixed : { true, false })
  {
    ImageType::DirectionType sheared;
    sheared.SetIdentity();
    sheared[0][1] = 0.4;
    auto shearedImage = itk::dmr::test::MakeImage<ImageType>(
      ImageType::SizeType{ { 20, 16 } }, Spacing(1, 1), Origin(0, 0), sheared, Blob(Origin(10, 8)));
    auto filter = FilterType::New();
    filter->SetFixedImage(inFixed ? shearedImage : image);
    filter->SetMovingImage(inFixed ? image : shearedImage);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      filter,
      { std::string("the ") + (inFixed ? "fixed" : "moving") + " image's direction matrix is not orthonormal" }));
  }
  // geometry that the force cannot be computed in: coordinates that double precision cannot tell apart, a spacing
  // below what a float resolves (1e-45 mm gave a zero force and density alpha without a word), not a number
  for (const bool inFixed : { true, false })
  {
    for (const auto & [spacing, origin, what] :
         { std::make_tuple(1.0, 1e16, "physical coordinates reach 1e+16 mm"),
           std::make_tuple(1e-45, 0.0, "spacing"),
           std::make_tuple(1.0, std::nan(""), "physical coordinates are not finite") })
    {
      auto odd = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 16 } },
                                                      Spacing(spacing, spacing),
                                                      Origin(origin, 0),
                                                      itk::dmr::test::RotationDirection2D<ImageType>(0.0),
                                                      Blob(Origin(10 * spacing, 8 * spacing)));
      auto filter = FilterType::New();
      filter->SetFixedImage(inFixed ? odd : image);
      filter->SetMovingImage(inFixed ? image : odd);
      EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
        filter, { std::string("the ") + (inFixed ? "fixed" : "moving") + " image's " + what }))
        << spacing << " " << origin;
    }
  }
  // an alpha beyond single precision (the density's type) or NaN (which passes the clamping setters): every density
  // was infinite or NaN, and only the CVT's refusal of it said something, without the reason
  for (const int which : { 0, 1, 2 })
  {
    auto filter = FilterType::New();
    filter->SetFixedImage(image);
    filter->SetMovingImage(itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 16 } },
                                                                Spacing(1, 1),
                                                                Origin(0, 0),
                                                                itk::dmr::test::RotationDirection2D<ImageType>(0.0),
                                                                Blob(Origin(11, 8))));
    if (which == 0)
    {
      filter->SetAlphaFactor(std::nan(""));
    }
    else
    {
      filter->SetUseFixedAlpha(true);
      filter->SetAlpha(which == 1 ? 1e39 : std::nan(""));
    }
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      filter,
      { "alpha is", which == 0 ? "AlphaFactor nan" : "the fixed Alpha", "finite number within single precision" }))
      << which;
  }
}

// Inputs that are outputs of filters not yet run (an ITK pipeline: reader -> ... -> DensityFieldFilter) have no size
// until the pipeline's information pass reaches them; the checks on their sizes must wait for it.
TEST(DensityFieldFilter, RunsDownstreamOfFiltersThatHaveNotRun)
{
  using CastType = itk::CastImageFilter<ImageType, ImageType>;
  const auto size = ImageType::SizeType{ { 24, 20 } };
  auto       fixed = itk::dmr::test::MakeImage<ImageType>(
    size, Spacing(1, 1.5), Origin(2, -1), itk::dmr::test::RotationDirection2D<ImageType>(0.3), Blob(Origin(12, 12)));
  auto moving = itk::dmr::test::MakeImage<ImageType>(
    size, Spacing(1, 1.5), Origin(2, -1), itk::dmr::test::RotationDirection2D<ImageType>(0.3), Blob(Origin(14, 11)));
  auto direct = FilterType::New();
  direct->SetFixedImage(fixed);
  direct->SetMovingImage(moving);
  direct->Update();

  auto fixedStage = CastType::New();
  fixedStage->SetInput(fixed);
  auto movingStage = CastType::New();
  movingStage->SetInput(moving);
  auto filter = FilterType::New();
  filter->SetFixedImage(fixedStage->GetOutput());
  filter->SetMovingImage(movingStage->GetOutput());
  ASSERT_NO_THROW(filter->Update());
  EXPECT_EQ(filter->GetOutput()->GetLargestPossibleRegion(), fixed->GetLargestPossibleRegion());
  EXPECT_EQ(filter->GetMSSD(), direct->GetMSSD());
  for (size_t p = 0; p < 24 * 20; ++p)
  {
    ASSERT_EQ(filter->GetOutput()->GetBufferPointer()[p], direct->GetOutput()->GetBufferPointer()[p]) << "pixel " << p;
  }

  // the size checks still hold once the pipeline has run: a fixed image 1 pixel high
  auto thin = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 1 } },
                                                   Spacing(1, 1),
                                                   Origin(0, 0),
                                                   itk::dmr::test::RotationDirection2D<ImageType>(0.0),
                                                   Blob(Origin(10, 0)));
  auto thinStage = CastType::New();
  thinStage->SetInput(thin);
  auto bad = FilterType::New();
  bad->SetFixedImage(thinStage->GetOutput());
  bad->SetMovingImage(thinStage->GetOutput());
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(bad, { "at least 2 pixels along every axis, axis 1 has 1" }));
}

void
CheckIdenticalImages(double angle, double relativeTolerance)
{
  auto   image = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 40, 32 } },
                                                    Spacing(1.0, 1.2),
                                                    Origin(-5, 3),
                                                    itk::dmr::test::RotationDirection2D<ImageType>(angle),
                                                    Blob(Origin(8, 20)));
  double energy = 0.0; // sum T^2: the scale of the SSD
  for (size_t p = 0; p < 40 * 32; ++p)
  {
    energy += double(image->GetBufferPointer()[p]) * image->GetBufferPointer()[p];
  }
  auto filter = FilterType::New();
  filter->SetFixedImage(image);
  filter->SetMovingImage(image);
  filter->Update();
  EXPECT_LE(filter->GetMSSD(), relativeTolerance * energy);
  EXPECT_LE(filter->GetSSD(), relativeTolerance * energy);
  EXPECT_LE(filter->GetMeanSquaredForce(), relativeTolerance * energy);
  EXPECT_GT(filter->GetAlpha(), 0.0);
  const auto * density = filter->GetOutput();
  EXPECT_EQ(density->GetLargestPossibleRegion(), image->GetLargestPossibleRegion());
  EXPECT_EQ(density->GetDirection(), image->GetDirection());
  const size_t n = image->GetLargestPossibleRegion().GetNumberOfPixels();
  for (size_t p = 0; p < n; ++p)
  {
    ASSERT_EQ(density->GetBufferPointer()[p], static_cast<float>(filter->GetAlpha())) << "pixel " << p;
    ASSERT_LE(filter->GetForceField()->GetBufferPointer()[p].GetSquaredNorm(), relativeTolerance * energy)
      << "pixel " << p;
  }
}

TEST(DensityFieldFilter, IdenticalImagesGiveZeroMSSDAndConstantPositiveDensity)
{
  // the moving image is sampled through physical space (index -> point -> index), a round trip that is exact only to
  // rounding: measured MSSD 2e-25 (identity direction) and 3e-25 (rotated) for an image energy of 1e6
  CheckIdenticalImages(0.0, 1e-20);
  CheckIdenticalImages(0.4, 1e-20);
}

// Regression test (a fixed bug): for identical constant images the
// intensity range is 0, the alpha floor is DBL_MIN, and density = 0 + alpha is cast to float -> 0: the density is
// zero everywhere although the class promises it is never all zero (DiscreteCVTFilter then throws).
TEST(DensityFieldFilter, IdenticalConstantImagesGiveAPositiveDensity)
{
  auto image = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 16 } },
                                                    Spacing(1, 1),
                                                    Origin(0, 0),
                                                    itk::dmr::test::RotationDirection2D<ImageType>(0.0),
                                                    [](const ImageType::PointType &) { return 5.0f; });
  auto filter = FilterType::New();
  filter->SetFixedImage(image);
  filter->SetMovingImage(image);
  filter->Update();
  EXPECT_GT(filter->GetOutput()->GetBufferPointer()[0], 0.0f);
}

/** Sigmoid edge of height 100 and width 2 mm across the physical direction e, at e.p = position. */
auto
Edge(double position, double ex, double ey)
{
  return [=](const ImageType::PointType & p) {
    return static_cast<float>(100.0 / (1.0 + std::exp(-((p[0] * ex + p[1] * ey) - position) / 2.0)));
  };
}

TEST(DensityFieldFilter, ForcePointsTheWayTheDisplacementMustGo)
{
  // Moving S has its edge at x = 30, fixed T at x = 34. W(x) = x + u(x) maps fixed points to moving points and
  // registration wants S(x + u) = T(x) = S(x - 4), i.e. u = -4 along x. The force f = 2 (T - S(W)) grad S(W) is
  // minus the gradient of the SSD with respect to u: at x = 32, T < S and grad S > 0, so f_x < 0 (towards u = -4).
  const ImageType::SizeType size{ { 64, 8 } };
  const auto                identity = itk::dmr::test::RotationDirection2D<ImageType>(0.0);
  auto fixed = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Edge(34, 1, 0));
  auto moving = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Edge(30, 1, 0));
  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->Update();
  const auto * force = filter->GetForceField();
  for (int y = 0; y < 8; ++y)
  {
    const auto f = force->GetPixel({ { 32, y } });
    EXPECT_LT(f[0], -1.0) << "row " << y;
    EXPECT_NEAR(f[1], 0.0, 1e-3 * std::abs(f[0])) << "row " << y;
  }
  const double ssdBefore = filter->GetSSD();
  ASSERT_GT(ssdBefore, 0.0);
  // following the force lowers the SSD; going against it raises it
  FieldType::PixelType step;
  step[0] = -1.0f;
  step[1] = 0.0f;
  filter->SetDisplacementField(ConstantField(fixed, step));
  filter->Update();
  EXPECT_LT(filter->GetSSD(), ssdBefore);
  step[0] = 1.0f;
  filter->SetDisplacementField(ConstantField(fixed, step));
  filter->Update();
  EXPECT_GT(filter->GetSSD(), ssdBefore);
  // and u = -4 registers the images (the edge is ~0 where the clamped border is sampled)
  step[0] = -4.0f;
  filter->SetDisplacementField(ConstantField(fixed, step));
  filter->Update();
  EXPECT_LT(filter->GetSSD(), 1e-6 * ssdBefore);
}

TEST(DensityFieldFilter, PhysicalForceFollowsARotatedImage)
{
  // the same edge pair along a physical direction e on rotated images: the physical force is along -e
  const double              angle = 0.5;
  const double              ex = std::cos(angle), ey = std::sin(angle);
  const ImageType::SizeType size{ { 48, 40 } };
  const auto                direction = itk::dmr::test::RotationDirection2D<ImageType>(angle + 0.2);
  auto                      fixed =
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(1.0, 1.1), Origin(-10, -15), direction, Edge(12, ex, ey));
  auto moving =
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(1.0, 1.1), Origin(-10, -15), direction, Edge(9, ex, ey));
  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->Update();
  const auto *                                      force = filter->GetForceField();
  size_t                                            checked = 0;
  itk::ImageRegionConstIteratorWithIndex<FieldType> it(force, force->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    ImageType::PointType p;
    force->TransformIndexToPhysicalPoint(it.GetIndex(), p);
    const double s = p[0] * ex + p[1] * ey;
    const auto   idx = it.GetIndex();
    if (s < 9.5 || s > 11.5 || idx[0] < 3 || idx[1] < 3 || idx[0] > 44 || idx[1] > 36)
    {
      continue; // between the edges, away from the image border
    }
    const auto   f = it.Get();
    const double along = f[0] * ex + f[1] * ey;
    const double across = -f[0] * ey + f[1] * ex;
    EXPECT_LT(along, 0.0) << it.GetIndex();
    EXPECT_LT(std::abs(across), 0.05 * std::abs(along)) << it.GetIndex();
    ++checked;
  }
  EXPECT_GT(checked, 20u);
}

TEST(DensityFieldFilter, DisplacementThatUndoesATranslationGivesZeroSSD)
{
  // fixed T(p) = B(p), moving S(p) = B(p - t): S(p + t) = T(p), so the field u = t registers them. t is a whole
  // number of pixels along the rotated image axes, so linear interpolation is exact.
  const ImageType::SizeType size{ { 48, 40 } };
  const auto                spacing = Spacing(0.9, 1.2);
  const auto                direction = itk::dmr::test::RotationDirection2D<ImageType>(0.6);
  const auto                origin = Origin(4, -9);
  auto                      fixed = itk::dmr::test::MakeImage<ImageType>(
    size, spacing, origin, direction, [&](const ImageType::PointType &) { return 0.0f; });
  ImageType::PointType centre;
  fixed->TransformIndexToPhysicalPoint({ { 22, 20 } }, centre);
  fixed = itk::dmr::test::MakeImage<ImageType>(size, spacing, origin, direction, Blob(centre));
  itk::Vector<double, 2> indexShift;
  indexShift[0] = 3 * spacing[0];
  indexShift[1] = -2 * spacing[1];
  const itk::Vector<double, 2> t = direction * indexShift;
  ImageType::PointType         movedCentre = centre + t;
  auto moving = itk::dmr::test::MakeImage<ImageType>(size, spacing, origin, direction, Blob(movedCentre));

  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->Update();
  const double ssdIdentity = filter->GetSSD();
  ASSERT_GT(ssdIdentity, 1.0);
  FieldType::PixelType u;
  u[0] = static_cast<float>(t[0]);
  u[1] = static_cast<float>(t[1]);
  auto field = ConstantField(fixed, u);
  filter->SetDisplacementField(field);
  filter->Update();
  EXPECT_LT(filter->GetSSD(), 1e-6 * ssdIdentity);
  std::vector<float> warped;
  filter->WarpMovingImage(field, warped);
  const auto grid = itk::dmr::Grid<2>::FromImage(fixed.GetPointer());
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    if (idx[0] < 4 || idx[1] < 4 || idx[0] > 43 || idx[1] > 35)
    {
      continue;
    }
    ASSERT_NEAR(warped[p], fixed->GetBufferPointer()[p], 1e-3) << "pixel " << p;
  }
  // the wrong sign doubles the shift instead
  filter->SetDisplacementField(ConstantField(fixed, -u));
  filter->Update();
  EXPECT_GT(filter->GetSSD(), ssdIdentity);
}

// The registration updates W <- W o exp(u), so the force must be the negative derivative of the SSD with respect to
// that update: d/de SSD(W o (id + e v)) at e = 0 equals -sum_x f(x) . v(x). Checked by central differences under a
// strongly non-uniform W (grad u up to ~0.5), on a rotated, anisotropic grid, for one level (where the SSD is the
// whole objective). The warped moving gradient passes; the mapped gradient (grad S)(W(x)) does not.
TEST(DensityFieldFilter, WarpedGradientForceIsTheDerivativeOfTheSSDForTheCompositionalUpdate)
{
  const ImageType::SizeType size{ { 96, 88 } };
  const auto                spacing = Spacing(0.9, 1.2);
  const auto                direction = itk::dmr::test::RotationDirection2D<ImageType>(0.4);
  const auto                origin = Origin(-7, 5);
  auto                      shape = [](const ImageType::PointType & c, double sigma) {
    return [c, sigma](const ImageType::PointType & p) {
      const double r2 = (p[0] - c[0]) * (p[0] - c[0]) + 0.6 * (p[1] - c[1]) * (p[1] - c[1]);
      return static_cast<float>(100.0 * std::exp(-r2 / (2.0 * sigma * sigma)));
    };
  };
  auto probe = itk::dmr::test::MakeImage<ImageType>(
    size, spacing, origin, direction, [](const ImageType::PointType &) { return 0.0f; });
  ImageType::PointType centre;
  probe->TransformIndexToPhysicalPoint({ { 48, 44 } }, centre);
  auto fixed = itk::dmr::test::MakeImage<ImageType>(size, spacing, origin, direction, shape(centre, 11.0));
  auto moving = itk::dmr::test::MakeImage<ImageType>(
    size, spacing, origin, direction, shape(centre + itk::Vector<double, 2>(4.0), 9.0));

  // W(x) = x + u(x), u a smooth swirl; the perturbation direction v(x) another smooth field (both physical, mm)
  auto u = [&](const ImageType::PointType & p) {
    const double dx = p[0] - centre[0], dy = p[1] - centre[1];
    const double a = 9.0 * std::exp(-(dx * dx + dy * dy) / (2.0 * 18.0 * 18.0));
    return Vec(-a * dy / 18.0, a * dx / 18.0);
  };
  auto v = [&](const ImageType::PointType & p) {
    return Vec(1.0 + 0.3 * std::sin(0.05 * p[1]), -0.5 + 0.4 * std::cos(0.07 * p[0]));
  };
  const auto grid = itk::dmr::Grid<2>::FromImage(fixed.GetPointer());
  // u_e(x) = e v(x) + u(x + e v(x)): the displacement of W o (id + e v)
  auto fieldFor = [&](double e) {
    auto field = ConstantField(fixed, FieldType::PixelType(0.0f));
    for (size_t p = 0; p < grid.numberOfPixels; ++p)
    {
      const auto           idx = grid.Index(p);
      ImageType::PointType x;
      fixed->TransformIndexToPhysicalPoint({ { idx[0], idx[1] } }, x);
      const auto step = e * v(x);
      const auto w = step + u(x + step);
      field->GetBufferPointer()[p][0] = static_cast<float>(w[0]);
      field->GetBufferPointer()[p][1] = static_cast<float>(w[1]);
    }
    return field;
  };
  // the largest |grad u| over the image: the test must be far from W = identity
  double largestGrad = 0.0;
  for (double x = -40; x <= 40; x += 2)
  {
    for (double y = -40; y <= 40; y += 2)
    {
      const auto p = centre + Vec(x, y);
      const auto dudx = (u(p + Vec(1e-3, 0)) - u(p)) / 1e-3;
      largestGrad = std::max(largestGrad, std::max(std::abs(dudx[0]), std::abs(dudx[1])));
    }
  }
  ASSERT_GT(largestGrad, 0.4);

  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->SetNumberOfLevels(1);
  const double e = 1e-2;
  filter->SetDisplacementField(fieldFor(e));
  filter->Update();
  const double plus = filter->GetSSD();
  filter->SetDisplacementField(fieldFor(-e));
  filter->Update();
  const double minus = filter->GetSSD();
  const double derivative = (plus - minus) / (2.0 * e);
  ASSERT_GT(std::abs(derivative), 100.0);

  auto predicted = [&](FilterType::ForceGradientEnum rule) {
    filter->SetForceGradient(rule);
    filter->SetDisplacementField(fieldFor(0.0));
    filter->Update();
    const auto * f = filter->GetForceField()->GetBufferPointer();
    double       sum = 0.0;
    for (size_t p = 0; p < grid.numberOfPixels; ++p)
    {
      const auto           idx = grid.Index(p);
      ImageType::PointType x;
      fixed->TransformIndexToPhysicalPoint({ { idx[0], idx[1] } }, x);
      const auto vx = v(x);
      sum -= f[p][0] * vx[0] + f[p][1] * vx[1];
    }
    return sum;
  };
  const double warped = predicted(FilterType::ForceGradientEnum::WarpedMoving);
  const double mapped = predicted(FilterType::ForceGradientEnum::MappedMoving);
  std::cout << "dSSD/de " << derivative << ", warped-gradient prediction " << warped << ", mapped " << mapped
            << std::endl;
  EXPECT_NEAR(warped, derivative, 0.02 * std::abs(derivative));
  EXPECT_GT(std::abs(mapped - derivative), 0.1 * std::abs(derivative));
  // at W = identity both rules are the same
  filter->SetDisplacementField(nullptr);
  filter->SetForceGradient(FilterType::ForceGradientEnum::WarpedMoving);
  filter->Update();
  const auto atIdentity = filter->GetGridForce();
  filter->SetForceGradient(FilterType::ForceGradientEnum::MappedMoving);
  filter->Update();
  EXPECT_EQ(filter->GetGridForce(), atIdentity);
}

/** Force of the blob pair on a grid with the given spacing; the pixel data do not depend on the spacing. */
std::vector<float>
ForceWithSpacing(double sx, double sy, unsigned int levels)
{
  const ImageType::SizeType size{ { 40, 32 } };
  const auto                identity = itk::dmr::test::RotationDirection2D<ImageType>(0.0);
  auto fixed = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(18, 15)));
  auto moving = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(21, 13)));
  fixed->SetSpacing(Spacing(sx, sy));
  moving->SetSpacing(Spacing(sx, sy));
  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->SetNumberOfLevels(levels);
  filter->Update();
  const auto *       f = filter->GetForceField()->GetBufferPointer();
  std::vector<float> out;
  for (size_t p = 0; p < size[0] * size[1]; ++p)
  {
    out.push_back(f[p][0]);
    out.push_back(f[p][1]);
  }
  EXPECT_EQ(filter->GetGridForce(), out); // identity direction: grid frame = physical frame
  return out;
}

TEST(DensityFieldFilter, ForceIsPerMillimetre)
{
  for (unsigned int levels : { 1u, 3u })
  {
    const auto unit = ForceWithSpacing(1.0, 1.0, levels);
    const auto twice = ForceWithSpacing(2.0, 2.0, levels);
    const auto anisotropic = ForceWithSpacing(1.0, 2.0, levels);
    float      maxForce = 0.0f;
    for (float v : unit)
    {
      maxForce = std::max(maxForce, std::abs(v));
    }
    ASSERT_GT(maxForce, 1.0f);
    for (size_t i = 0; i < unit.size(); i += 2)
    {
      // doubling the spacing halves the gradient (per mm), and the residual is unchanged
      EXPECT_NEAR(twice[i], 0.5f * unit[i], 1e-5f * maxForce) << "levels " << levels << " component " << i;
      EXPECT_NEAR(twice[i + 1], 0.5f * unit[i + 1], 1e-5f * maxForce) << "levels " << levels << " component " << i;
      // per axis: only the y component halves when only the y spacing doubles
      EXPECT_NEAR(anisotropic[i], unit[i], 1e-5f * maxForce) << "levels " << levels << " component " << i;
      EXPECT_NEAR(anisotropic[i + 1], 0.5f * unit[i + 1], 1e-5f * maxForce)
        << "levels " << levels << " component " << i;
    }
  }
}

TEST(DensityFieldFilter, DensityIsSquaredForcePlusAlpha)
{
  const ImageType::SizeType size = BlobPairSize;
  const auto [fixed, moving] = BlobPair();
  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->Update();
  const size_t n = size[0] * size[1];
  const auto * density = filter->GetOutput()->GetBufferPointer();
  const auto * force = filter->GetForceField()->GetBufferPointer();
  double       meanF2 = 0.0;
  for (size_t p = 0; p < n; ++p)
  {
    const double f2 = force[p].GetSquaredNorm();
    meanF2 += f2 / n;
    ASSERT_NEAR(density[p], f2 + filter->GetAlpha(), 1e-5 * (f2 + filter->GetAlpha())) << "pixel " << p;
  }
  EXPECT_NEAR(filter->GetMeanSquaredForce(), meanF2, 1e-5 * meanF2);
  // paper 5.1, rounded to a 24-bit significand so that both back-ends take the same alpha (dmrBackEndRounding.h)
  EXPECT_EQ(filter->GetAlpha(), itk::dmr::RoundToSingleSignificand(0.1 * filter->GetMeanSquaredForce()));
  EXPECT_NEAR(filter->GetAlpha(), 0.1 * filter->GetMeanSquaredForce(), 0x1p-24 * 0.1 * filter->GetMeanSquaredForce());
  // the multi-resolution sum includes the full-resolution term
  EXPECT_GT(filter->GetMSSD(), filter->GetSSD());
  filter->SetNumberOfLevels(1);
  filter->Update();
  EXPECT_DOUBLE_EQ(filter->GetMSSD(), filter->GetSSD());
  // a fixed alpha is used as given
  filter->SetUseFixedAlpha(true);
  filter->SetAlpha(7.0);
  filter->Update();
  EXPECT_EQ(filter->GetAlpha(), 7.0);
  for (size_t p = 0; p < n; ++p)
  {
    const double f2 = filter->GetForceField()->GetBufferPointer()[p].GetSquaredNorm();
    ASSERT_NEAR(filter->GetOutput()->GetBufferPointer()[p], f2 + 7.0, 1e-5 * (f2 + 7.0));
  }
}

TEST(DensityFieldFilter, IntensitiesBeyondSinglePrecisionAreScaledExactly)
{
  // |f|^2 grows with the fourth power of the intensities: blobs of height 2^70 (about 1e21) overflowed the float
  // density, blobs of height 2^-70 left only alpha in it. The filter scales such images by a power of two: the
  // density, force, SSD and MSSD are then those of the ordinary images times exact powers of two.
  const ImageType::SizeType size = BlobPairSize;
  const auto [fixed, moving] = BlobPair();
  auto reference = FilterType::New();
  reference->SetFixedImage(fixed);
  reference->SetMovingImage(moving);
  reference->Update();
  EXPECT_EQ(reference->GetIntensityScale(), 1.0); // ordinary intensities are not scaled
  const size_t n = size[0] * size[1];
  for (const int exponent : { 70, -70, 10 })
  {
    auto filter = FilterType::New();
    filter->SetFixedImage(itk::dmr::test::ScaledByPowerOfTwo(fixed.GetPointer(), exponent));
    filter->SetMovingImage(itk::dmr::test::ScaledByPowerOfTwo(moving.GetPointer(), exponent));
    filter->Update();
    // the reference's force scale 2 R^2 / h is about 2^14, the scaled images' 2^(14 + 2 exponent): only beyond 2^40
    // are they scaled
    const double s = filter->GetIntensityScale();
    EXPECT_EQ(s == 1.0, exponent == 10) << exponent;
    const double c = std::ldexp(s, exponent); // the working images are the reference's times c
    EXPECT_EQ(c, std::exp2(std::round(std::log2(c)))) << "a power of two";
    EXPECT_EQ(filter->GetSSD(), reference->GetSSD() * c * c) << exponent;
    EXPECT_EQ(filter->GetMSSD(), reference->GetMSSD() * c * c) << exponent;
    EXPECT_EQ(filter->GetAlpha(), reference->GetAlpha() * c * c * c * c) << exponent;
    const auto * density = filter->GetOutput()->GetBufferPointer();
    const auto * expected = reference->GetOutput()->GetBufferPointer();
    for (size_t p = 0; p < n; ++p)
    {
      ASSERT_TRUE(std::isfinite(density[p]) && density[p] > 0.0f) << exponent << " pixel " << p;
      ASSERT_EQ(density[p], static_cast<float>(expected[p] * c * c * c * c)) << exponent << " pixel " << p;
      for (unsigned int k = 0; k < 2; ++k)
      {
        ASSERT_EQ(filter->GetForceField()->GetBufferPointer()[p][k],
                  static_cast<float>(reference->GetForceField()->GetBufferPointer()[p][k] * c * c))
          << exponent << " pixel " << p;
      }
    }
    // the warped moving image keeps the image's own intensities
    std::vector<float> warped, warpedReference;
    filter->WarpMovingImage(nullptr, warped);
    reference->WarpMovingImage(nullptr, warpedReference);
    for (size_t p = 0; p < n; ++p)
    {
      ASSERT_EQ(warped[p], std::ldexp(warpedReference[p], exponent)) << exponent << " pixel " << p;
    }
  }
}

TEST(DensityFieldFilter, ADownstreamRegionOfInterestGetsTheWholeOutputs)
{
  // A filter downstream that asks for a part of the density or of the force field (a region of interest, streaming):
  // the density was allocated for that part and written for every pixel, past the end of its buffer.
  const ImageType::SizeType size = BlobPairSize;
  const auto [fixed, moving] = BlobPair();
  auto whole = FilterType::New();
  whole->SetFixedImage(fixed);
  whole->SetMovingImage(moving);
  whole->Update();
  ImageType::RegionType part({ { 10, 12 } }, { { 20, 15 } });
  for (const bool viaForce : { false, true })
  {
    auto filter = FilterType::New();
    filter->SetFixedImage(fixed);
    filter->SetMovingImage(moving);
    using ForceFieldType = FilterType::ForceFieldType;
    auto densityPart = itk::RegionOfInterestImageFilter<ImageType, ImageType>::New();
    auto forcePart = itk::RegionOfInterestImageFilter<ForceFieldType, ForceFieldType>::New();
    densityPart->SetInput(filter->GetOutput());
    densityPart->SetRegionOfInterest(part);
    forcePart->SetInput(filter->GetForceField());
    forcePart->SetRegionOfInterest(part);
    if (viaForce)
    {
      forcePart->Update();
    }
    else
    {
      densityPart->Update();
    }
    EXPECT_EQ(filter->GetOutput()->GetBufferedRegion(), fixed->GetLargestPossibleRegion()) << viaForce;
    EXPECT_EQ(filter->GetForceField()->GetBufferedRegion(), fixed->GetLargestPossibleRegion()) << viaForce;
    EXPECT_EQ(filter->GetAlpha(), whole->GetAlpha()) << "alpha is the whole image's";
    densityPart->Update();
    forcePart->Update();
    const auto * out = densityPart->GetOutput();
    ASSERT_EQ(out->GetLargestPossibleRegion().GetSize(), part.GetSize());
    for (itk::ImageRegionConstIteratorWithIndex<ImageType> it(out, out->GetLargestPossibleRegion()); !it.IsAtEnd();
         ++it)
    {
      // the region of interest's output starts at index 0
      const auto index = part.GetIndex() + (it.GetIndex() - out->GetLargestPossibleRegion().GetIndex());
      ASSERT_EQ(it.Get(), whole->GetOutput()->GetPixel(index)) << index;
      ASSERT_EQ(forcePart->GetOutput()->GetPixel(it.GetIndex()), whole->GetForceField()->GetPixel(index)) << index;
    }
  }
}

// Regression test (a fixed bug): BuildPyramids() reuses its cached
// pyramids when m_PyramidTime >= max(fixed MTime, moving MTime) and the pixel count matches, so a different input
// image that is older than the cached ones (here: created first) is ignored; SSD is 184760 instead of 0.
TEST(DensityFieldFilter, SwappingInAnotherImageOfTheSameSizeIsSeen)
{
  // the pyramids are cached between updates; a different moving image must not reuse the old ones
  const ImageType::SizeType size{ { 32, 24 } };
  const auto                identity = itk::dmr::test::RotationDirection2D<ImageType>(0.0);
  // created first: the oldest modification time of the three
  auto same = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(15, 12)));
  auto fixed = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(15, 12)));
  auto other = itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(18, 10)));
  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(other);
  filter->Update();
  EXPECT_GT(filter->GetSSD(), 0.0);
  filter->SetMovingImage(same);
  filter->Update();
  EXPECT_EQ(filter->GetSSD(), 0.0);
}
} // namespace

// A fixed mask (issue 3, e.g. the lungs) restricts the force, the density's |f|^2 and the similarity to its inside;
// alpha is 0.1 x the mean |f|^2 over the inside; an empty mask or one on another grid is refused.
TEST(DensityFieldFilter, FixedMaskRestrictsForceDensityAndSimilarity)
{
  const ImageType::SizeType size = BlobPairSize;
  const auto [fixed, moving] = BlobPair();
  using MaskType = FilterType::MaskImageType;
  auto mask = MaskType::New();
  mask->CopyInformation(fixed);
  mask->SetRegions(fixed->GetLargestPossibleRegion());
  mask->Allocate();
  const size_t n = size[0] * size[1];
  size_t       inside = 0;
  for (size_t p = 0; p < n; ++p)
  {
    const bool in = (p % size[0]) < 20; // left half (holds most of the blobs' overlap)
    mask->GetBufferPointer()[p] = in ? 1 : 0;
    inside += in;
  }
  auto unmasked = FilterType::New();
  unmasked->SetFixedImage(fixed);
  unmasked->SetMovingImage(moving);
  unmasked->SetNumberOfLevels(1);
  unmasked->Update();
  auto filter = FilterType::New();
  filter->SetFixedImage(fixed);
  filter->SetMovingImage(moving);
  filter->SetNumberOfLevels(1);
  filter->SetFixedMask(mask);
  filter->Update();
  const auto * density = filter->GetOutput()->GetBufferPointer();
  const auto * force = filter->GetForceField()->GetBufferPointer();
  const auto * freeForce = unmasked->GetForceField()->GetBufferPointer();
  double       meanF2 = 0.0, ssd = 0.0;
  for (size_t p = 0; p < n; ++p)
  {
    if (mask->GetBufferPointer()[p])
    {
      ASSERT_NEAR((force[p] - freeForce[p]).GetNorm(), 0.0, 1e-5 * (1.0 + freeForce[p].GetNorm())) << p;
      const double f2 = force[p].GetSquaredNorm();
      meanF2 += f2 / static_cast<double>(inside);
      ASSERT_NEAR(density[p], f2 + filter->GetAlpha(), 1e-5 * (f2 + filter->GetAlpha())) << p;
      const double r = fixed->GetBufferPointer()[p] - moving->GetBufferPointer()[p];
      ssd += r * r;
    }
    else
    {
      ASSERT_EQ(force[p].GetNorm(), 0.0) << p;
      ASSERT_FLOAT_EQ(density[p], static_cast<float>(filter->GetAlpha())) << p;
    }
  }
  EXPECT_GT(meanF2, 0.0);
  EXPECT_NEAR(filter->GetMeanSquaredForce(), meanF2, 1e-5 * meanF2);
  EXPECT_NEAR(filter->GetAlpha(), 0.1 * meanF2, 1e-5 * meanF2);
  EXPECT_NEAR(filter->GetSSD(), ssd, 1e-5 * ssd);
  EXPECT_LT(filter->GetSSD(), unmasked->GetSSD());

  mask->FillBuffer(0);
  mask->Modified();
  EXPECT_THROW(filter->Update(), itk::ExceptionObject);
  auto small = MaskType::New();
  small->SetRegions(MaskType::SizeType{ { 10, 10 } });
  small->Allocate();
  small->FillBuffer(1);
  filter->SetFixedMask(small);
  EXPECT_THROW(filter->Update(), itk::ExceptionObject);
}

namespace
{
/** dmr::GaussianShrink against ShrinkImageFilter(DiscreteGaussianImageFilter) on a random image: the same geometry
 * and the same floats, bit for bit, for the pyramid's factors (and an axis too thin for the factor, which then
 * shrinks by less). The same image indexed from other starts (3, 4, 5 and -7, -6, -5 along the axes) gets
 * ShrinkImageFilter's geometry for that start and the same floats as from 0: ShrinkImageFilter itself keeps other
 * pixels there (it clamps a negative offset to 0, see dmr::PlanGaussianShrink). Rotated (a non-trivial geometry):
 * sizes whose offsets are whole pixels; otherwise (identity direction, unit spacing, where ShrinkImageFilter's
 * physical round trip is exact) also sizes whose first kept pixel is half a pixel off, which both round up. */
template <unsigned int D>
void
GaussianShrinkMatchesItk(const std::array<unsigned int, D> & size, bool rotated)
{
  using Img = itk::Image<float, D>;
  auto                     image = Img::New();
  typename Img::RegionType region;
  for (unsigned int k = 0; k < D; ++k)
  {
    region.SetSize(k, size[k]);
  }
  image->SetRegions(region);
  typename Img::SpacingType   spacing;
  typename Img::PointType     origin;
  typename Img::DirectionType direction;
  direction.SetIdentity();
  for (unsigned int k = 0; k < D; ++k)
  {
    spacing[k] = rotated ? 0.7 + 0.35 * k : 1.0;
    origin[k] = rotated ? -12.5 + 4.0 * k : 0.0;
  }
  const double angle = rotated ? 0.3 : 0.0;
  direction[0][0] = std::cos(angle);
  direction[0][1] = -std::sin(angle);
  direction[1][0] = std::sin(angle);
  direction[1][1] = std::cos(angle);
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  image->SetDirection(direction);
  image->Allocate();
  uint64_t h = 12345;
  for (size_t p = 0; p < region.GetNumberOfPixels(); ++p)
  {
    h = h * 6364136223846793005ULL + 1442695040888963407ULL;
    image->GetBufferPointer()[p] = static_cast<float>(static_cast<double>(h >> 40) * 1e-3 - 5000.0);
  }
  auto itkLevel = [](const Img * input, unsigned int factor, unsigned int * factors, bool informationOnly) {
    auto smooth = itk::DiscreteGaussianImageFilter<Img, Img>::New();
    smooth->SetInput(input);
    smooth->SetUseImageSpacing(false);
    smooth->SetVariance(0.25 * factor * factor);
    smooth->SetMaximumKernelWidth(64);
    auto shrink = itk::ShrinkImageFilter<Img, Img>::New();
    shrink->SetInput(smooth->GetOutput());
    for (unsigned int k = 0; k < D; ++k)
    {
      factors[k] =
        std::max<unsigned int>(1, std::min<unsigned int>(factor, input->GetLargestPossibleRegion().GetSize()[k] / 2));
      shrink->SetShrinkFactor(k, factors[k]);
    }
    if (informationOnly)
    {
      shrink->UpdateOutputInformation();
    }
    else
    {
      shrink->Update();
    }
    typename Img::Pointer out = shrink->GetOutput();
    out->DisconnectPipeline();
    return out;
  };
  for (int shift : { 0, 3, -7 })
  {
    auto indexed = Img::New();
    indexed->Graft(image);
    typename Img::IndexType start;
    for (unsigned int k = 0; k < D; ++k)
    {
      start[k] = static_cast<typename Img::IndexValueType>(shift == 0 ? 0 : shift + static_cast<int>(k));
    }
    itk::dmr::test::ShiftRegionStart(indexed.GetPointer(), start);
    for (unsigned int level = 1; level <= 3; ++level)
    {
      const unsigned int factor = 1u << level;
      unsigned int       factors[D];
      const auto         values = itkLevel(image.GetPointer(), factor, factors, false);
      const auto         geometry = itkLevel(indexed.GetPointer(), factor, factors, true);
      const auto         actual =
        itk::dmr::GaussianShrink<D>(indexed.GetPointer(), 0.25 * factor * factor, 64, factors, nullptr);
      ASSERT_EQ(actual->GetLargestPossibleRegion(), geometry->GetLargestPossibleRegion()) << "level " << level;
      EXPECT_EQ(actual->GetOrigin(), geometry->GetOrigin());
      EXPECT_EQ(actual->GetSpacing(), geometry->GetSpacing());
      EXPECT_EQ(actual->GetDirection(), geometry->GetDirection());
      size_t different = 0;
      for (size_t p = 0; p < values->GetLargestPossibleRegion().GetNumberOfPixels(); ++p)
      {
        different += actual->GetBufferPointer()[p] == values->GetBufferPointer()[p] ? 0 : 1;
      }
      EXPECT_EQ(different, 0u) << D << "D level " << level << ", start " << shift << ", of "
                               << values->GetLargestPossibleRegion().GetNumberOfPixels() << " pixels";
    }
  }
}
} // namespace

TEST(DensityFieldFilter, GaussianShrinkGivesItksSmoothedAndShrunkPyramidLevels)
{
  GaussianShrinkMatchesItk<2>({ 37, 29 }, true);
  GaussianShrinkMatchesItk<2>({ 65, 5 }, true); // thin: shrinks by 2 at most along y
  GaussianShrinkMatchesItk<3>({ 33, 25, 19 }, true);
  GaussianShrinkMatchesItk<3>({ 41, 35, 3 }, true); // one slice too few for factor 2 along z: no shrink there
  GaussianShrinkMatchesItk<2>({ 64, 26 }, false);   // first kept pixels half a pixel off: rounded up
  GaussianShrinkMatchesItk<3>({ 40, 26, 18 }, false);
}

// Regression test (a fixed bug): the moving image was sampled at its continuous index without taking off the start
// of its region, so images whose region does not start at 0 (CropImageFilter, ExtractImageFilter) were sampled
// shifted by that start. Sizes 41 x 33 (1 more than a multiple of 4): the shrunk pyramid levels keep the same pixels
// whatever the start (ShrinkImageFilter rounds a half-pixel offset otherwise, which depends on the start).
TEST(DensityFieldFilter, RegionsThatDoNotStartAtZeroGiveTheSameResult)
{
  const auto direction = itk::dmr::test::RotationDirection2D<ImageType>(0.3);
  auto       makeImage = [&](const ImageType::PointType & centre) {
    return itk::dmr::test::MakeImage<ImageType>(
      ImageType::SizeType{ { 41, 33 } }, Spacing(1.0, 1.2), Origin(-5, 3), direction, Blob(centre));
  };
  auto run = [](ImageType * fixed, ImageType * moving) {
    auto filter = FilterType::New();
    filter->SetFixedImage(fixed);
    filter->SetMovingImage(moving);
    filter->SetDisplacementField(ConstantField(fixed, FieldType::PixelType(0.7f)));
    filter->SetNumberOfLevels(3);
    filter->Update();
    return filter;
  };
  const auto   reference = run(makeImage(Origin(8, 20)), makeImage(Origin(10, 18)));
  const size_t n = 41 * 33;
  auto         maxForceDifference = [&](FilterType * filter) {
    double maxDiff = 0.0;
    for (size_t p = 0; p < n; ++p)
    {
      const auto f = reference->GetForceField()->GetBufferPointer()[p];
      maxDiff = std::max(maxDiff, static_cast<double>((f - filter->GetForceField()->GetBufferPointer()[p]).GetNorm()));
    }
    return maxDiff;
  };
  double maxForce = 0.0;
  for (size_t p = 0; p < n; ++p)
  {
    maxForce = std::max(maxForce, static_cast<double>(reference->GetForceField()->GetBufferPointer()[p].GetNorm()));
  }
  ASSERT_GT(maxForce, 1.0);
  for (const auto & start : { std::array<int, 2>{ 8, -4 }, std::array<int, 2>{ 7, -3 }, std::array<int, 2>{ 1, 2 } })
  {
    ImageType::IndexType index;
    index[0] = start[0];
    index[1] = start[1];
    auto fixed = makeImage(Origin(8, 20));
    auto moving = makeImage(Origin(10, 18));
    itk::dmr::test::ShiftRegionStart(fixed.GetPointer(), index);
    itk::dmr::test::ShiftRegionStart(moving.GetPointer(), index);
    const auto filter = run(fixed, moving);
    EXPECT_EQ(filter->GetOutput()->GetLargestPossibleRegion(), fixed->GetLargestPossibleRegion());
    EXPECT_NEAR(filter->GetMSSD(), reference->GetMSSD(), 1e-9 * reference->GetMSSD()) << start[0] << "," << start[1];
    EXPECT_LE(maxForceDifference(filter), 1e-5 * maxForce) << start[0] << "," << start[1];
  }
  // only the moving image on its own start: another grid, the same image
  auto                 moving = makeImage(Origin(10, 18));
  ImageType::IndexType movingStart;
  movingStart[0] = -11;
  movingStart[1] = 5;
  itk::dmr::test::ShiftRegionStart(moving.GetPointer(), movingStart);
  const auto filter = run(makeImage(Origin(8, 20)), moving);
  EXPECT_NEAR(filter->GetMSSD(), reference->GetMSSD(), 1e-9 * reference->GetMSSD());
  EXPECT_LE(maxForceDifference(filter), 1e-5 * maxForce);
}

// The field and the mask are read pixel for pixel with the fixed image: on another grid they are refused, with the
// reason; the moving image may lie on any grid.
TEST(DensityFieldFilter, FieldAndMaskMustLieOnTheFixedGrid)
{
  auto image = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 20, 16 } },
                                                    Spacing(1, 1.5),
                                                    Origin(2, -1),
                                                    itk::dmr::test::RotationDirection2D<ImageType>(0.2),
                                                    Blob(Origin(10, 8)));
  using MaskType = FilterType::MaskImageType;
  auto maskLike = [&](auto && change) {
    auto mask = MaskType::New();
    mask->CopyInformation(image);
    mask->SetRegions(image->GetLargestPossibleRegion());
    change(mask.GetPointer());
    mask->Allocate(true);
    mask->FillBuffer(1);
    return mask;
  };
  auto filterWithMask = [&](MaskType * mask) {
    auto filter = FilterType::New();
    filter->SetFixedImage(image);
    filter->SetMovingImage(image);
    filter->SetFixedMask(mask);
    return filter;
  };
  EXPECT_NO_THROW(filterWithMask(maskLike([](MaskType *) {}))->Update());
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
    filterWithMask(maskLike([](MaskType * m) {
      auto r = m->GetLargestPossibleRegion();
      r.SetIndex(0, 3);
      m->SetRegions(r);
    })),
    { "fixed mask must lie on the fixed image grid", "its region starts at [3, 0], the fixed image's at [0, 0]" }));
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
    filterWithMask(maskLike([](MaskType * m) { m->SetOrigin(Origin(2.5, -1)); })), { "fixed mask", "its origin" }));
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
    filterWithMask(maskLike([](MaskType * m) { m->SetSpacing(Spacing(1, 1)); })), { "fixed mask", "its spacing" }));
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
    filterWithMask(
      maskLike([](MaskType * m) { m->SetDirection(itk::dmr::test::RotationDirection2D<ImageType>(0.0)); })),
    { "fixed mask", "its direction" }));
  auto field = ConstantField(image, FieldType::PixelType(0.0f));
  field->SetOrigin(Origin(0, 0));
  auto filter = FilterType::New();
  filter->SetFixedImage(image);
  filter->SetMovingImage(image);
  filter->SetDisplacementField(field);
  EXPECT_TRUE(
    itk::dmr::test::UpdateThrowsMentioning(filter, { "displacement field must lie on the fixed image grid" }));
  // a moving image elsewhere (another origin, spacing, direction and size) is sampled through physical space
  auto moving = itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 42, 42 } }, // covers the fixed image
                                                     Spacing(0.8, 0.9),
                                                     Origin(-4, -5),
                                                     itk::dmr::test::RotationDirection2D<ImageType>(-0.1),
                                                     Blob(Origin(10, 8)));
  auto elsewhere = FilterType::New();
  elsewhere->SetFixedImage(image);
  elsewhere->SetMovingImage(moving);
  EXPECT_NO_THROW(elsewhere->Update());
  // the same blob, sampled on two grids: the SSD is small beside the image energy
  double energy = 0.0;
  for (size_t p = 0; p < 20 * 16; ++p)
  {
    energy += double(image->GetBufferPointer()[p]) * image->GetBufferPointer()[p];
  }
  EXPECT_LT(elsewhere->GetSSD(), 0.01 * energy);
}

// Regression test (a fixed bug): ITK's GaussianOperator evaluates e^-t I_n(t) directly, which gives NaN above a
// variance of about 700 (e^-t underflows, I_n(t) overflows). The pyramid's level l smooths with variance 4^l / 4, so
// levels 7 and 8 (variance 1024 and 4096, both allowed by SetNumberOfLevels) made every density NaN. There the
// coefficients now come from LargeVarianceGaussianCoefficients, checked here against e^-t I_n(t) = (1/pi) int_0^pi e^(t
// (cos u - 1)) cos(n u) du (trapezoid rule, exact to rounding for this periodic integrand) under ITK's truncation rule.
TEST(DensityFieldFilter, GaussianCoefficientsOfLargeVariancesAreFinite)
{
  auto itkCoefficients = [](double variance) {
    itk::GaussianOperator<double, 2> op;
    op.SetDirection(0);
    op.SetVariance(variance);
    op.SetMaximumKernelWidth(64);
    op.SetMaximumError(0.01);
    op.CreateDirectional();
    std::vector<double> c(op.Size());
    for (size_t j = 0; j < c.size(); ++j)
    {
      c[j] = op[static_cast<unsigned int>(j)];
    }
    return c;
  };
  auto reference = [](double t) {
    const int           steps = 20000;
    const double        pi = 3.14159265358979323846, h = pi / steps;
    std::vector<double> half;
    double              sum = 0.0;
    for (int n = 0; n == 0 || n == 1 || (sum < 0.99 && half.size() <= 64); ++n)
    {
      double integral = 0.0;
      for (int k = 0; k <= steps; ++k)
      {
        const double u = k * h;
        integral += (k == 0 || k == steps ? 0.5 : 1.0) * std::exp(t * (std::cos(u) - 1.0)) * std::cos(n * u);
      }
      half.push_back(integral * h / pi);
      sum += (n == 0 ? 1.0 : 2.0) * half.back();
    }
    std::vector<double> c(2 * half.size() - 1);
    for (size_t i = 0; i < half.size(); ++i)
    {
      c[half.size() - 1 + i] = c[half.size() - 1 - i] = half[i] / sum;
    }
    return c;
  };
  for (const double t : { 100.0, 1024.0, 4096.0 })
  {
    const auto ours = itk::dmr::LargeVarianceGaussianCoefficients(t, 0.01, 64);
    const auto expected = reference(t);
    ASSERT_EQ(ours.size(), expected.size()) << "variance " << t;
    double sum = 0.0;
    for (size_t j = 0; j < ours.size(); ++j)
    {
      EXPECT_NEAR(ours[j], expected[j], 1e-9 * expected[j]) << "variance " << t << ", coefficient " << j;
      EXPECT_EQ(ours[j], ours[ours.size() - 1 - j]);
      sum += ours[j];
    }
    EXPECT_NEAR(sum, 1.0, 1e-12);
    if (t > 1000.0)
    {
      const auto itkOwn = itkCoefficients(t);
      EXPECT_FALSE(std::isfinite(itkOwn[itkOwn.size() / 2])) << "ITK's coefficients are finite at variance " << t;
      EXPECT_EQ(ours.size(), 129u); // ITK's width limit: 65 on each side, the centre shared
    }
  }
  // all eight levels of a 64 x 48 pair: finite force and density everywhere
  const ImageType::SizeType size{ { 64, 48 } };
  const auto                identity = itk::dmr::test::RotationDirection2D<ImageType>(0.0);
  auto                      filter = FilterType::New();
  filter->SetFixedImage(
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(30, 22))));
  filter->SetMovingImage(
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(33, 24))));
  filter->SetNumberOfLevels(8);
  filter->Update();
  EXPECT_TRUE(std::isfinite(filter->GetMSSD()));
  EXPECT_GT(filter->GetMSSD(), filter->GetSSD());
  for (size_t p = 0; p < 64 * 48; ++p)
  {
    ASSERT_TRUE(std::isfinite(filter->GetOutput()->GetBufferPointer()[p])) << "pixel " << p;
    ASSERT_GT(filter->GetOutput()->GetBufferPointer()[p], 0.0f) << "pixel " << p;
  }
}

namespace
{
/** Runs the filter on (fixed, moving, field) three times: without a mask, where it takes two neighbouring pixels of a
 * row at once wherever it can, and with the two checkerboard masks, where every unmasked pixel's row neighbours are
 * masked, so it takes every pixel alone. Every pixel's grid-frame force and physical force must be the same floats
 * (bit patterns, NaN included) whichever way it was computed. Returns the unmasked run. */
template <unsigned int D>
typename itk::DensityFieldFilter<itk::Image<float, D>>::Pointer
ExpectPairsGiveTheSinglePixelsForce(
  itk::Image<float, D> *                                                          fixed,
  itk::Image<float, D> *                                                          moving,
  typename itk::DensityFieldFilter<itk::Image<float, D>>::DisplacementFieldType * field,
  unsigned int                                                                    levels,
  itk::DynamicMeshRegistrationEnums::ForceGradient                                gradient =
    itk::DynamicMeshRegistrationEnums::ForceGradient::WarpedMoving)
{
  using Image = itk::Image<float, D>;
  using Filter = itk::DensityFieldFilter<Image>;
  const auto   size = fixed->GetLargestPossibleRegion().GetSize();
  const size_t n = fixed->GetLargestPossibleRegion().GetNumberOfPixels();
  auto         parityOf = [&](size_t p) {
    size_t sum = 0;
    for (unsigned int k = 0; k < D; ++k)
    {
      sum += p % size[k];
      p /= size[k];
    }
    return sum % 2;
  };
  auto run = [&](int parity) {
    auto filter = Filter::New();
    filter->SetFixedImage(fixed);
    filter->SetMovingImage(moving);
    if (field)
    {
      filter->SetDisplacementField(field);
    }
    filter->SetNumberOfLevels(levels);
    filter->SetForceGradient(gradient);
    filter->SetUseFixedAlpha(true); // the force does not depend on alpha; a non-finite force would make it NaN
    filter->SetAlpha(1.0);
    if (parity >= 0)
    {
      auto mask = Filter::MaskImageType::New();
      mask->CopyInformation(fixed);
      mask->SetRegions(fixed->GetLargestPossibleRegion());
      mask->Allocate();
      for (size_t p = 0; p < n; ++p)
      {
        mask->GetBufferPointer()[p] = parityOf(p) == static_cast<size_t>(parity) ? 1 : 0;
      }
      filter->SetFixedMask(mask);
    }
    filter->Update();
    return filter;
  };
  const auto whole = run(-1);
  const auto singles = std::array<typename Filter::Pointer, 2>{ run(0), run(1) };
  size_t     different = 0;
  for (size_t p = 0; p < n; ++p)
  {
    Filter *   single = singles[parityOf(p)];
    const bool gridSame =
      std::memcmp(&whole->GetGridForce()[p * D], &single->GetGridForce()[p * D], D * sizeof(float)) == 0;
    const bool physicalSame = std::memcmp(whole->GetForceField()->GetBufferPointer() + p,
                                          single->GetForceField()->GetBufferPointer() + p,
                                          sizeof(typename Filter::ForceFieldType::PixelType)) == 0;
    if (!gridSame || !physicalSame)
    {
      ADD_FAILURE() << "pixel " << p << ": force " << whole->GetForceField()->GetBufferPointer()[p]
                    << " with its neighbour, " << single->GetForceField()->GetBufferPointer()[p] << " alone";
      if (++different == 5)
      {
        break;
      }
    }
  }
  return whole;
}
} // namespace

TEST(DensityFieldFilter, PixelsTakenInPairsGetTheForceTheyGetAlone2D)
{
  // odd row length (a single pixel at the end of every row), anisotropic spacing, rotated directions, a moving image
  // on another grid (and one on the fixed grid), and a field that is exactly 0 in a band (with the moving image on the
  // fixed grid, positions on the grid: corners of weight 0)
  const ImageType::SizeType size{ { 41, 33 } };
  const auto                direction = itk::dmr::test::RotationDirection2D<ImageType>(0.3);
  const auto                fixed =
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(0.9, 1.3), Origin(2, -1), direction, Blob(Origin(14, 18)));
  const auto moving =
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(0.9, 1.3), Origin(2, -1), direction, Blob(Origin(17, 16)));
  const auto movingElsewhere =
    itk::dmr::test::MakeImage<ImageType>(ImageType::SizeType{ { 37, 35 } },
                                         Spacing(0.7, 1.1),
                                         Origin(1.3, -0.4),
                                         itk::dmr::test::RotationDirection2D<ImageType>(0.25),
                                         Blob(Origin(17, 16)));
  auto field = ConstantField(fixed, FieldType::PixelType(0.0f));
  for (size_t p = 0; p < size[0] * size[1]; ++p)
  {
    const double x = static_cast<double>(p % size[0]), y = static_cast<double>(p / size[0]);
    if (y > 10 && y < 20)
    {
      continue; // u = 0 in this band
    }
    field->GetBufferPointer()[p][0] = static_cast<float>(1.7 * std::sin(0.21 * x + 0.1 * y));
    field->GetBufferPointer()[p][1] = static_cast<float>(-1.1 * std::cos(0.13 * x - 0.17 * y));
  }
  using Gradient = itk::DynamicMeshRegistrationEnums::ForceGradient;
  for (const Gradient gradient : { Gradient::WarpedMoving, Gradient::MappedMoving })
  {
    for (const unsigned int levels : { 1u, 3u })
    {
      SCOPED_TRACE(std::to_string(levels) + " levels");
      ExpectPairsGiveTheSinglePixelsForce<2>(fixed, moving, field, levels, gradient);
      ExpectPairsGiveTheSinglePixelsForce<2>(fixed, moving, nullptr, levels, gradient);
      ExpectPairsGiveTheSinglePixelsForce<2>(fixed, movingElsewhere, field, levels, gradient);
    }
  }
}

TEST(DensityFieldFilter, PixelsTakenInPairsGetTheForceTheyGetAlone3D)
{
  using Image3 = itk::Image<float, 3>;
  using Field3 = itk::DensityFieldFilter<Image3>::DisplacementFieldType;
  const Image3::SizeType size{ { 17, 12, 9 } };
  Image3::SpacingType    spacing;
  spacing[0] = 1.0;
  spacing[1] = 1.2;
  spacing[2] = 2.0;
  Image3::PointType origin;
  origin.Fill(0.0);
  Image3::DirectionType direction;
  direction.SetIdentity();
  direction(0, 0) = direction(1, 1) = std::cos(0.2);
  direction(0, 1) = -std::sin(0.2);
  direction(1, 0) = std::sin(0.2);
  auto blob3 = [](double cx, double cy, double cz) {
    return [=](const Image3::PointType & p) {
      const double r2 = (p[0] - cx) * (p[0] - cx) + (p[1] - cy) * (p[1] - cy) + (p[2] - cz) * (p[2] - cz);
      return static_cast<float>(100.0 * std::exp(-r2 / (2.0 * 4.0 * 4.0)));
    };
  };
  const auto          fixed = itk::dmr::test::MakeImage<Image3>(size, spacing, origin, direction, blob3(7, 8, 8));
  const auto          moving = itk::dmr::test::MakeImage<Image3>(size, spacing, origin, direction, blob3(9, 7, 9));
  Image3::SpacingType movingSpacing = spacing;
  movingSpacing[2] = 1.7;
  Image3::PointType movingOrigin = origin;
  movingOrigin[0] = 0.35;
  const auto movingElsewhere = itk::dmr::test::MakeImage<Image3>(
    Image3::SizeType{ { 15, 13, 11 } }, movingSpacing, movingOrigin, direction, blob3(9, 7, 9));
  auto field = Field3::New();
  field->CopyInformation(fixed);
  field->SetRegions(fixed->GetLargestPossibleRegion());
  field->Allocate();
  for (size_t p = 0; p < size[0] * size[1] * size[2]; ++p)
  {
    const double x = static_cast<double>(p % size[0]), y = static_cast<double>((p / size[0]) % size[1]),
                 z = static_cast<double>(p / (size[0] * size[1]));
    const bool zero = z > 3 && z < 6; // u = 0 in a slab
    field->GetBufferPointer()[p][0] = zero ? 0.0f : static_cast<float>(1.3 * std::sin(0.3 * x + 0.2 * z));
    field->GetBufferPointer()[p][1] = zero ? 0.0f : static_cast<float>(0.8 * std::cos(0.25 * y - 0.1 * x));
    field->GetBufferPointer()[p][2] = zero ? 0.0f : static_cast<float>(-0.9 * std::sin(0.2 * z + 0.15 * y));
  }
  for (const unsigned int levels : { 1u, 3u })
  {
    ExpectPairsGiveTheSinglePixelsForce<3>(fixed, moving, field, levels);
    ExpectPairsGiveTheSinglePixelsForce<3>(fixed, moving, nullptr, levels);
    ExpectPairsGiveTheSinglePixelsForce<3>(fixed, movingElsewhere, field, levels);
  }
}

TEST(DensityFieldFilter, PixelsTakenInPairsGetTheForceTheyGetAloneNextToAnInfiniteMovingPixel)
{
  // Without a field every position lies on the grid, so the corners of the next pixel have weight 0. The pixel two
  // to the left of an infinite moving pixel reads, at weight 0, the infinite gradient of its right neighbour: alone
  // it skips that corner, and a pair must give it the same finite force.
  const ImageType::SizeType size{ { 24, 10 } };
  const auto                identity = itk::dmr::test::RotationDirection2D<ImageType>(0.0);
  const auto                fixed =
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(11, 5)));
  const auto moving =
    itk::dmr::test::MakeImage<ImageType>(size, Spacing(1, 1), Origin(0, 0), identity, Blob(Origin(12, 4)));
  for (const size_t column : { size_t{ 12 }, size_t{ 13 } }) // the pixel two to the left is a pair's first or second
  {
    SCOPED_TRACE("infinite pixel at column " + std::to_string(column));
    const size_t       q = 5 * size[0] + column;
    std::vector<float> copy(moving->GetBufferPointer(), moving->GetBufferPointer() + size[0] * size[1]);
    copy[q] = std::numeric_limits<float>::infinity();
    const auto infinite = itk::dmr::test::MakeImage<ImageType>(
      size, Spacing(1, 1), Origin(0, 0), identity, [&](const ImageType::PointType & point) {
        ImageType::IndexType index;
        moving->TransformPhysicalPointToIndex(point, index);
        return copy[static_cast<size_t>(index[1]) * size[0] + static_cast<size_t>(index[0])];
      });
    const auto whole = ExpectPairsGiveTheSinglePixelsForce<2>(fixed, infinite, nullptr, 1);
    for (unsigned int k = 0; k < 2; ++k)
    {
      EXPECT_TRUE(std::isfinite(whole->GetGridForce()[(q - 2) * 2 + k])) << "the pixel two to the left of it";
      EXPECT_FALSE(std::isfinite(whole->GetGridForce()[(q - 1) * 2 + k]) &&
                   std::isfinite(whole->GetGridForce()[(q - 1) * 2 + 1 - k]))
        << "its left neighbour reads its infinite gradient";
    }
  }
}
