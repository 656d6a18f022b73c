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
#include "dmrLandmarks.h"
#include "dmrDataTestHelpers.h"
#include "itkImageFileReader.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "gtest/gtest.h"
#include <fstream>
#include <random>
#include <sstream>

namespace
{
using FieldType = itk::Image<itk::Vector<float, 3>, 3>;
using GeometryType = itk::Image<unsigned char, 3>;

/** The message of the itk::ExceptionObject thrown by f, or "" when nothing was thrown. */
template <typename F>
std::string
ErrorOf(F && f)
{
  try
  {
    f();
  }
  catch (const itk::ExceptionObject & e)
  {
    return e.GetDescription();
  }
  return "";
}

std::vector<std::array<double, 3>>
Parse(const std::string & text)
{
  std::istringstream in(text);
  return dmrtools::ParseLandmarks<3>(in, "test.txt");
}

void
WriteText(const std::string & path, const std::string & text)
{
  std::ofstream out(path);
  out << text;
}

/** Anisotropic, oblique test grid (STYLE.md: 0.6 x 0.6 x 2.5 and a non-identity direction). */
GeometryType::Pointer
ObliqueGrid(const itk::Size<3> & size = { { 40, 36, 20 } })
{
  itk::Vector<double, 3> spacing;
  spacing[0] = 0.6;
  spacing[1] = 0.6;
  spacing[2] = 2.5;
  itk::Point<double, 3> centre;
  centre[0] = 12.0;
  centre[1] = -7.0;
  centre[2] = 30.0;
  return dmrtest::MakeImage<GeometryType>(size, spacing, dmrtest::ObliqueDirection(0.4, -0.3), centre);
}
} // namespace

TEST(Landmarks, ParsesDirLabFormat)
{
  // DIR-Lab files: leading blanks, tabs, trailing tab; plus CRLF, blank and comment lines and exponents
  const auto v = Parse(" 322.000000\t 337.000000\t 10.000000\t\n"
                       "\n"
                       "# a comment\n"
                       "1 2 3\r\n"
                       "  -1.5e1   2E0 +0.25   \n");
  ASSERT_EQ(v.size(), 3u);
  EXPECT_DOUBLE_EQ(v[0][0], 322.0);
  EXPECT_DOUBLE_EQ(v[0][1], 337.0);
  EXPECT_DOUBLE_EQ(v[0][2], 10.0);
  EXPECT_DOUBLE_EQ(v[1][2], 3.0);
  EXPECT_DOUBLE_EQ(v[2][0], -15.0);
  EXPECT_DOUBLE_EQ(v[2][1], 2.0);
  EXPECT_DOUBLE_EQ(v[2][2], 0.25);
  // 2D files hold two numbers per line
  std::istringstream in2("4 5\n6 7\n");
  EXPECT_EQ(dmrtools::ParseLandmarks<2>(in2, "2d").size(), 2u);
  // a UTF-8 byte order mark at the start (Windows editors write one) was read as part of the first number, and the
  // message quoted it invisibly: "\"64\" is not a finite number"
  const auto bom = Parse("\xEF\xBB\xBF"
                         "64 65 3\r\n1 2 3\r\n");
  ASSERT_EQ(bom.size(), 2u);
  EXPECT_DOUBLE_EQ(bom[0][0], 64.0);
  // only at the start of the file
  EXPECT_NE(ErrorOf([] {
              Parse("1 2 3\n\xEF\xBB\xBF"
                    "4 5 6\n");
            }).find("test.txt:2:"),
            std::string::npos);
}

TEST(Landmarks, MalformedInputThrowsWithLineNumber)
{
  std::string e = ErrorOf([] { Parse("1 2 3\n4 5\n"); });
  EXPECT_NE(e.find("test.txt:2:"), std::string::npos) << e;
  EXPECT_NE(e.find("expected 3 numbers"), std::string::npos) << e;
  e = ErrorOf([] { Parse("1 2 3 4\n"); });
  EXPECT_NE(e.find("test.txt:1:"), std::string::npos) << e;
  e = ErrorOf([] { Parse("1 2 3\n\n# c\n1 2 x\n"); });
  EXPECT_NE(e.find("test.txt:4:"), std::string::npos) << e;
  EXPECT_NE(e.find("\"x\" is not a finite number"), std::string::npos) << e;
  e = ErrorOf([] { Parse("1 2 3abc\n"); });
  EXPECT_NE(e.find("\"3abc\""), std::string::npos) << e;
  e = ErrorOf([] { Parse("nan 2 3\n"); });
  EXPECT_NE(e.find("not a finite number"), std::string::npos) << e;
  e = ErrorOf([] { Parse("1,2,3\n"); });
  EXPECT_NE(e.find("expected 3 numbers"), std::string::npos) << e;
  e = ErrorOf([] { Parse(""); });
  EXPECT_NE(e.find("no landmarks"), std::string::npos) << e;
  e = ErrorOf([] { Parse("\n  \n# only comments\n"); });
  EXPECT_NE(e.find("no landmarks"), std::string::npos) << e;
  e = ErrorOf([] { dmrtools::ReadLandmarkValues<3>("/nonexistent/landmarks.txt"); });
  EXPECT_NE(e.find("cannot open landmark file /nonexistent/landmarks.txt"), std::string::npos) << e;
}

TEST(Landmarks, CountMismatchBetweenFixedAndMovingThrows)
{
  dmrtest::ScratchDirectory dir("landmarks");
  const std::string         fixedPath = dir.Path() + "/fixed.txt", movingPath = dir.Path() + "/moving.txt";
  WriteText(fixedPath, "1 1 1\n2 2 2\n3 3 3\n");
  WriteText(movingPath, "1 1 1\n2 2 2\n");
  auto              grid = ObliqueGrid();
  const std::string e = ErrorOf([&] { dmrtools::ReadLandmarkPairs<3>(fixedPath, movingPath, grid, grid); });
  EXPECT_NE(e.find("the fixed set has 3 landmarks and the moving set 2"), std::string::npos) << e;
  WriteText(movingPath, "1 1 1\n2 2 2\n4 4 4\n");
  const auto pairs = dmrtools::ReadLandmarkPairs<3>(fixedPath, movingPath, grid, grid);
  EXPECT_EQ(pairs.fixed.size(), 3u);
  EXPECT_EQ(pairs.moving.size(), 3u);
  // empty moving file
  WriteText(movingPath, "");
  const std::string e2 = ErrorOf([&] { dmrtools::ReadLandmarkPairs<3>(fixedPath, movingPath, grid, grid); });
  EXPECT_NE(e2.find(movingPath + ": no landmarks"), std::string::npos) << e2;
}

TEST(Landmarks, PhysicalConversionWithObliqueDirection)
{
  auto         grid = ObliqueGrid();
  const auto & D = grid->GetDirection();
  const auto & h = grid->GetSpacing();
  const auto & o = grid->GetOrigin();
  ASSERT_GT(std::abs(D[0][1]), 0.1); // really oblique
  const std::vector<std::array<double, 3>> values{
    { 1, 1, 1 }, { 2, 3, 4 }, { 39.5, 35.5, 19.5 }, { 10.5, 7.25, 3.5 }
  };
  const auto one = dmrtools::LandmarksToPhysical<3>(values, grid, dmrtools::LandmarkUnits::OneBasedIndex);
  const auto zero = dmrtools::LandmarksToPhysical<3>(values, grid, dmrtools::LandmarkUnits::ZeroBasedIndex);
  const auto mm = dmrtools::LandmarksToPhysical<3>(values, grid, dmrtools::LandmarkUnits::PhysicalMM);
  for (size_t i = 0; i < values.size(); ++i)
  {
    for (unsigned int r = 0; r < 3; ++r)
    {
      // p = origin + Direction diag(spacing) (value - 1), written out by hand
      double p1 = o[r], p0 = o[r];
      for (unsigned int k = 0; k < 3; ++k)
      {
        p1 += D[r][k] * h[k] * (values[i][k] - 1.0);
        p0 += D[r][k] * h[k] * values[i][k];
      }
      EXPECT_NEAR(one[i][r], p1, 1e-9) << "landmark " << i << " axis " << r;
      EXPECT_NEAR(zero[i][r], p0, 1e-9) << "landmark " << i << " axis " << r;
      EXPECT_DOUBLE_EQ(mm[i][r], values[i][r]);
    }
  }
  // landmark (1,1,1) is the first voxel centre, i.e. the origin
  EXPECT_NEAR(one[0].EuclideanDistanceTo(o), 0.0, 1e-12);
  // distances are preserved by the direction: |p(2,3,4) - p(1,1,1)| = |(1,2,3) * spacing|
  EXPECT_NEAR(one[1].EuclideanDistanceTo(one[0]), std::sqrt(0.36 + 4 * 0.36 + 9 * 6.25), 1e-9);
  // an index past the grid means the file belongs to another image
  const std::string e = ErrorOf([&] {
    dmrtools::LandmarksToPhysical<3>({ { 1, 1, 22 } }, grid, dmrtools::LandmarkUnits::OneBasedIndex);
  });
  EXPECT_NE(e.find("landmark 1 lies outside the image grid"), std::string::npos) << e;
}

TEST(Landmarks, SummaryStatistics)
{
  const auto s = dmrtools::SummarizeErrors({ 4.0, 1.0, 3.0, 2.0 });
  EXPECT_EQ(s.count, 4u);
  EXPECT_DOUBLE_EQ(s.mean, 2.5);
  EXPECT_DOUBLE_EQ(s.std, std::sqrt(1.25)); // population
  EXPECT_DOUBLE_EQ(s.max, 4.0);
  EXPECT_NEAR(s.p95, 3.85, 1e-12); // rank 0.95 * 3 = 2.85 -> 3 + 0.85 * (4 - 3)
  std::vector<double> ramp(101);
  for (size_t i = 0; i < ramp.size(); ++i)
  {
    ramp[i] = static_cast<double>(100 - i);
  }
  EXPECT_DOUBLE_EQ(dmrtools::SummarizeErrors(ramp).p95, 95.0);
  const auto empty = dmrtools::SummarizeErrors({});
  EXPECT_EQ(empty.count, 0u);
  EXPECT_EQ(empty.mean, 0.0);
}

TEST(Landmarks, SyntheticFieldGivesKnownTRE)
{
  // u(x) = A (x - c) + b is affine, so linear interpolation reproduces it exactly at any point inside the grid.
  auto field = dmrtest::MakeImage<FieldType>(
    { { 30, 28, 16 } }, dmrtest::Vec(0.6, 0.6, 2.5), dmrtest::ObliqueDirection(0.4, -0.3), dmrtest::Pt(5.0, 5.0, 5.0));
  const double A[3][3] = { { 0.02, -0.01, 0.0 }, { 0.005, 0.03, -0.01 }, { 0.0, 0.01, -0.02 } };
  const double b[3] = { 3.0, -4.0, 1.5 };
  auto         u = [&](const itk::Point<double, 3> & x) {
    itk::Vector<double, 3> v;
    for (unsigned int r = 0; r < 3; ++r)
    {
      v[r] = b[r];
      for (unsigned int k = 0; k < 3; ++k)
      {
        v[r] += A[r][k] * (x[k] - 5.0);
      }
    }
    return v;
  };
  itk::ImageRegionIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    itk::Point<double, 3> x;
    field->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const auto v = u(x);
    it.Set(dmrtest::Vec(static_cast<float>(v[0]), static_cast<float>(v[1]), static_cast<float>(v[2])));
  }
  // fixed landmarks at random continuous indices; moving = fixed + u(fixed) + e_i with |e_i| = 0.1 i mm
  std::mt19937                           engine(7);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  dmrtools::LandmarkPointList<3>         fixed, moving;
  std::vector<double>                    expected, initial;
  itk::Vector<double, 3>                 meanOffset, meanInitial; // of moving - (fixed + u(fixed)), moving - fixed
  meanOffset.Fill(0.0);
  meanInitial.Fill(0.0);
  for (int i = 0; i < 50; ++i)
  {
    itk::ContinuousIndex<double, 3> c;
    for (unsigned int k = 0; k < 3; ++k)
    {
      c[k] = unit(engine) * static_cast<double>(field->GetLargestPossibleRegion().GetSize(k) - 1);
    }
    itk::Point<double, 3> p;
    field->TransformContinuousIndexToPhysicalPoint(c, p);
    // one draw per statement: the order of a call's arguments is unspecified, so the input would depend on the compiler
    const double           dx = unit(engine) - 0.5;
    const double           dy = unit(engine) - 0.5;
    const double           dz = unit(engine) - 0.5;
    itk::Vector<double, 3> dir = dmrtest::Vec(dx, dy, dz);
    dir.Normalize();
    const itk::Point<double, 3> q = p + u(p) + dir * (0.1 * i);
    fixed.push_back(p);
    moving.push_back(q);
    expected.push_back(0.1 * i);
    initial.push_back(p.EuclideanDistanceTo(q));
    meanOffset += dir * (0.1 * i / 50.0);
    meanInitial += (q - p) / 50.0;
  }
  const auto errors = dmrtools::LandmarkErrors(fixed, moving, field.GetPointer());
  for (size_t i = 0; i < errors.size(); ++i)
  {
    EXPECT_NEAR(errors[i], expected[i], 2e-5) << "landmark " << i;
  }
  const auto tre = dmrtools::TargetRegistrationError(fixed, moving, field.GetPointer());
  const auto want = dmrtools::SummarizeErrors(expected);
  EXPECT_NEAR(tre.mean, 2.45, 1e-4); // 0.1 * mean(0..49)
  EXPECT_NEAR(tre.std, want.std, 1e-4);
  EXPECT_NEAR(tre.p95, want.p95, 1e-4);
  EXPECT_NEAR(tre.max, 4.9, 1e-4);
  // the mean residual is the landmarks' shared offset: minus the mean of the offsets added to the moving landmarks
  const auto residual = dmrtools::MeanLandmarkResidual(fixed, moving, field.GetPointer());
  const auto residual0 = dmrtools::MeanLandmarkResidual<FieldType>(fixed, moving, nullptr);
  for (unsigned int k = 0; k < 3; ++k)
  {
    EXPECT_NEAR(residual[k], -meanOffset[k], 2e-5) << "axis " << k;
    EXPECT_NEAR(residual0[k], -meanInitial[k], 1e-12) << "axis " << k;
  }
  EXPECT_LE(residual.GetNorm(), tre.mean);
  EXPECT_GT(meanOffset.GetNorm(), 0.05); // the test can tell a wrong sign or a missing field
  // the initial TRE ignores the field: plain distances
  const auto before = dmrtools::InitialTargetRegistrationError<3>(fixed, moving);
  EXPECT_NEAR(before.mean, dmrtools::SummarizeErrors(initial).mean, 1e-12);
  EXPECT_GT(before.mean, tre.mean);
  // and equals the TRE of a zero field
  field->FillBuffer(dmrtest::Vec(0.0f, 0.0f, 0.0f));
  EXPECT_NEAR(dmrtools::TargetRegistrationError(fixed, moving, field.GetPointer()).mean, before.mean, 1e-9);
  // a landmark outside the field's grid is an error, not an extrapolation
  fixed.push_back(dmrtest::Pt(500.0, 0.0, 0.0));
  moving.push_back(dmrtest::Pt(500.0, 0.0, 0.0));
  const std::string e = ErrorOf([&] { dmrtools::TargetRegistrationError(fixed, moving, field.GetPointer()); });
  EXPECT_NE(e.find("landmark 51"), std::string::npos) << e;
  EXPECT_NE(e.find("outside the displacement field"), std::string::npos) << e;
  // lists of different length
  moving.pop_back();
  EXPECT_NE(ErrorOf([&] { dmrtools::TargetRegistrationError(fixed, moving, field.GetPointer()); }), "");
}

TEST(Landmarks, Copd2IdentityTREIs21_79mm)
{
  const std::string dir = dmrtest::SharedDataFolder("copd2-lung-masks");
  if (dir.empty())
  {
    GTEST_SKIP() << "no shared data (set DMR_SHARED_DATA_DIR): " << dmrtest::SharedDataDir();
  }
  // expiration = fixed, inspiration = moving (data README); geometry from the masks' headers
  auto reader = itk::ImageFileReader<GeometryType>::New();
  reader->SetFileName(dir + "/copd2_eBHCT_lungmask.nii.gz");
  reader->UpdateOutputInformation();
  GeometryType::Pointer grid = GeometryType::New();
  grid->CopyInformation(reader->GetOutput());
  ASSERT_EQ(grid->GetLargestPossibleRegion().GetSize(), (itk::Size<3>{ { 512, 512, 102 } }));
  EXPECT_NEAR(grid->GetSpacing()[0], 0.645, 1e-3);
  EXPECT_NEAR(grid->GetSpacing()[2], 2.5, 1e-3);
  const auto pairs = dmrtools::ReadLandmarkPairs<3>(
    dir + "/copd2_300_eBH_xyz_r1.txt", dir + "/copd2_300_iBH_xyz_r1.txt", grid.GetPointer(), grid.GetPointer());
  ASSERT_EQ(pairs.fixed.size(), 300u);
  const auto initial = dmrtools::InitialTargetRegistrationError<3>(pairs.fixed, pairs.moving);
  std::cout << "copd2 initial TRE: " << initial << std::endl;
  EXPECT_NEAR(initial.mean, 21.79, 0.005);
  EXPECT_NEAR(initial.std, 6.46, 0.02); // README: sd 6.46 (6.47 with the n - 1 divisor)
  EXPECT_NEAR(initial.max, 40.39, 0.005);
  // the same through an identity (zero) displacement field on a coarse grid over the same physical box
  auto field = FieldType::New();
  field->SetOrigin(grid->GetOrigin());
  field->SetDirection(grid->GetDirection());
  field->SetSpacing(dmrtest::Vec(4 * 0.645, 4 * 0.645, 2 * 2.5));
  field->SetRegions(itk::Size<3>{ { 129, 129, 52 } });
  field->Allocate();
  field->FillBuffer(dmrtest::Vec(0.0f, 0.0f, 0.0f));
  const auto identity = dmrtools::TargetRegistrationError(pairs.fixed, pairs.moving, field.GetPointer());
  EXPECT_NEAR(identity.mean, initial.mean, 1e-9);
  EXPECT_NEAR(identity.p95, initial.p95, 1e-9);
}
