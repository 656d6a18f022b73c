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
// The tool's --initial-transform reader (dmrtools::InitialFieldOnGrid): every format gives u_0(x) = T(x) - x on the
// fixed grid, through physical space (rotated, anisotropic, shifted grids), and bad files are refused with a reason.
#include "dmrExampleTestDirectory.h"
#include "dmrInitialTransform.h"
#include "itkAffineTransform.h"
#include "itkBSplineTransform.h"
#include "itkCompositeTransform.h"
#include "itkEuler3DTransform.h"
#include "itkImageFileWriter.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "itkTransformFileWriter.h"
#include "itkTranslationTransform.h"
#include "gtest/gtest.h"
#include "itksys/SystemTools.hxx"
#include <fstream>
#include <limits>

namespace
{
using ImageType = itk::Image<float, 3>;
using FieldType = itk::Image<itk::Vector<float, 3>, 3>;

std::string
Path(const std::string & name)
{
  // one folder for the whole run, removed when the test program ends
  static const struct Folder
  {
    std::string path = dmrtools::test::TemporaryDirectory("dmrInitialTransformGTest");
    ~Folder() { itksys::SystemTools::RemoveADirectory(path); }
  } folder;
  return folder.path + "/" + name;
}

/** The fixed grid: 20 x 16 x 12, spacing 0.9 x 1.1 x 2.0, an origin and a rotated direction. */
ImageType::Pointer
Reference()
{
  auto image = ImageType::New();
  image->SetRegions(ImageType::SizeType{ { 20, 16, 12 } });
  ImageType::SpacingType spacing;
  spacing[0] = 0.9;
  spacing[1] = 1.1;
  spacing[2] = 2.0;
  image->SetSpacing(spacing);
  ImageType::PointType origin;
  origin[0] = -30.0;
  origin[1] = 12.5;
  origin[2] = 100.0;
  image->SetOrigin(origin);
  auto euler = itk::Euler3DTransform<double>::New();
  euler->SetRotation(0.2, -0.3, 0.5);
  ImageType::DirectionType direction;
  for (unsigned int r = 0; r < 3; ++r)
  {
    for (unsigned int c = 0; c < 3; ++c)
    {
      direction[r][c] = euler->GetMatrix()[r][c];
    }
  }
  image->SetDirection(direction);
  image->Allocate();
  image->FillBuffer(0.0f);
  return image;
}

/** Largest |u(x) - (T(x) - x)| over the grid, mm. */
double
LargestErrorAgainst(const FieldType * field, const itk::Transform<double, 3, 3> * transform)
{
  double                                            largest = 0.0;
  itk::ImageRegionConstIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    FieldType::PointType x;
    field->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const auto y = transform->TransformPoint(x);
    for (unsigned int k = 0; k < 3; ++k)
    {
      largest = std::max(largest, std::abs(static_cast<double>(it.Get()[k]) - (y[k] - x[k])));
    }
  }
  return largest;
}

/** Fills the allocated `field` with u(x) = T(x) - x and writes it to path. */
void
WriteDisplacementOf(const itk::Transform<double, 3, 3> * transform, FieldType * field, const std::string & path)
{
  itk::ImageRegionIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    FieldType::PointType x;
    field->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const auto           y = transform->TransformPoint(x);
    FieldType::PixelType u;
    for (unsigned int k = 0; k < 3; ++k)
    {
      u[k] = static_cast<float>(y[k] - x[k]);
    }
    it.Set(u);
  }
  auto writer = itk::ImageFileWriter<FieldType>::New();
  writer->SetInput(field);
  writer->SetFileName(path);
  writer->Update();
}

itk::AffineTransform<double, 3>::Pointer
SomeAffine()
{
  auto         affine = itk::AffineTransform<double, 3>::New();
  auto         parameters = affine->GetParameters();
  const double values[12] = { 1.05, 0.02, -0.01, 0.03, 0.96, 0.02, -0.02, 0.01, 1.02, 4.0, -3.0, 7.5 };
  for (unsigned int i = 0; i < 12; ++i)
  {
    parameters[i] = values[i];
  }
  affine->SetParameters(parameters);
  itk::Point<double, 3> centre;
  centre[0] = -20.0;
  centre[1] = 20.0;
  centre[2] = 110.0;
  affine->SetCenter(centre);
  return affine;
}

void
Write(const itk::TransformBaseTemplate<double> * transform, const std::string & path)
{
  auto writer = itk::TransformFileWriterTemplate<double>::New();
  writer->SetInput(transform);
  writer->SetFileName(path);
  writer->Update();
}

::testing::AssertionResult
RefusedMentioning(const std::string & path, const std::string & text)
{
  std::string kind;
  try
  {
    dmrtools::InitialFieldOnGrid<3>(path, Reference().GetPointer(), kind);
  }
  catch (const itk::ExceptionObject & e)
  {
    const std::string description = e.GetDescription();
    return description.find(text) != std::string::npos
             ? ::testing::AssertionSuccess()
             : ::testing::AssertionFailure() << "the message does not mention '" << text << "': " << description;
  }
  catch (const std::exception & e)
  {
    const std::string description = e.what();
    return description.find(text) != std::string::npos
             ? ::testing::AssertionSuccess()
             : ::testing::AssertionFailure() << "the message does not mention '" << text << "': " << description;
  }
  return ::testing::AssertionFailure() << path << " was not refused";
}
} // namespace

// ITK's text format, MATLAB (ANTs' affine files) and HDF5 (ANTs' composite files): the field is T(x) - x at every
// voxel of the rotated, anisotropic fixed grid
TEST(InitialTransform, TransformFilesOfEveryFormatGiveTheirDisplacementOnTheFixedGrid)
{
  const auto affine = SomeAffine();
  for (const std::string name : { "affine.tfm", "affine.txt", "affine.mat", "affine.h5" })
  {
    Write(affine, Path(name));
    std::string kind;
    const auto  field = dmrtools::InitialFieldOnGrid<3>(Path(name), Reference().GetPointer(), kind);
    EXPECT_NE(kind.find("AffineTransform"), std::string::npos) << kind;
    EXPECT_EQ(field->GetLargestPossibleRegion(), Reference()->GetLargestPossibleRegion());
    EXPECT_EQ(field->GetDirection(), Reference()->GetDirection());
    EXPECT_LT(LargestErrorAgainst(field, affine), 1e-4) << name;
  }
}

// the check that runs before ITK's text reader (CheckTextTransformFile) takes what ITK writes: a B-spline (whose
// number of parameters its fixed parameters set), a rigid transform, and a float transform read as double
TEST(InitialTransform, TextFilesOfOtherTransformKindsPassTheCheck)
{
  using BSplineType = itk::BSplineTransform<double, 3, 3>;
  auto                                bspline = BSplineType::New();
  BSplineType::PhysicalDimensionsType extent;
  BSplineType::MeshSizeType           mesh;
  BSplineType::OriginType             origin;
  extent.Fill(60.0);
  mesh.Fill(3);
  origin[0] = -50.0;
  origin[1] = -10.0;
  origin[2] = 80.0;
  bspline->SetTransformDomainOrigin(origin);
  bspline->SetTransformDomainPhysicalDimensions(extent);
  bspline->SetTransformDomainMeshSize(mesh);
  auto parameters = bspline->GetParameters();
  for (unsigned int i = 0; i < parameters.size(); ++i)
  {
    parameters[i] = 0.5 * std::sin(0.37 * i);
  }
  bspline->SetParameters(parameters);
  auto euler = itk::Euler3DTransform<double>::New();
  euler->SetRotation(0.05, -0.02, 0.1);
  auto offset = euler->GetTranslation();
  offset[2] = 3.0;
  euler->SetTranslation(offset);
  for (const auto & [name, transform] :
       { std::make_pair("bspline.tfm", static_cast<itk::Transform<double, 3, 3> *>(bspline)),
         std::make_pair("euler.tfm", static_cast<itk::Transform<double, 3, 3> *>(euler)) })
  {
    Write(transform, Path(name));
    std::string kind;
    const auto  field = dmrtools::InitialFieldOnGrid<3>(Path(name), Reference().GetPointer(), kind);
    EXPECT_LT(LargestErrorAgainst(field, transform), 1e-4) << name;
  }
  auto single = itk::AffineTransform<float, 3>::New();
  auto singleParameters = single->GetParameters();
  singleParameters[9] = 2.5f;
  single->SetParameters(singleParameters);
  auto writer = itk::TransformFileWriterTemplate<float>::New();
  writer->SetInput(single);
  writer->SetFileName(Path("float.tfm"));
  writer->Update();
  std::string kind;
  const auto  field = dmrtools::InitialFieldOnGrid<3>(Path("float.tfm"), Reference().GetPointer(), kind);
  EXPECT_NEAR(field->GetPixel({ { 2, 3, 4 } })[0], 2.5f, 1e-5);
}

TEST(InitialTransform, ACompositeTransformIsTheCompositionOfItsParts)
{
  auto translation = itk::TranslationTransform<double, 3>::New();
  auto offset = translation->GetParameters();
  offset[0] = -6.0;
  offset[1] = 2.5;
  offset[2] = 1.0;
  translation->SetParameters(offset);
  auto composite = itk::CompositeTransform<double, 3>::New();
  composite->AddTransform(SomeAffine());
  composite->AddTransform(translation);
  for (const std::string name : { "composite.tfm", "composite.h5" })
  {
    Write(composite, Path(name));
    std::string kind;
    const auto  field = dmrtools::InitialFieldOnGrid<3>(Path(name), Reference().GetPointer(), kind);
    EXPECT_NE(kind.find("CompositeTransform"), std::string::npos) << kind;
    EXPECT_LT(LargestErrorAgainst(field, composite), 1e-4) << name;
  }
}

// a field image on another grid is interpolated linearly through physical space: a field that is affine in x comes
// back exactly; beyond its border it keeps the nearest value
TEST(InitialTransform, AFieldImageOnAnotherGridIsResampledThroughPhysicalSpace)
{
  const auto affine = SomeAffine();
  auto       coarse = FieldType::New();
  coarse->SetRegions(FieldType::SizeType{ { 30, 30, 30 } });
  FieldType::SpacingType spacing;
  spacing.Fill(3.0);
  coarse->SetSpacing(spacing);
  FieldType::PointType origin;
  origin[0] = -70.0;
  origin[1] = -30.0;
  origin[2] = 60.0;
  coarse->SetOrigin(origin);
  coarse->Allocate();
  WriteDisplacementOf(affine, coarse, Path("field.nii.gz"));
  auto writer = itk::ImageFileWriter<FieldType>::New();
  // the fixed grid must lie inside the coarse one for the exact comparison
  auto reference = Reference();
  for (unsigned int corner = 0; corner < 8; ++corner)
  {
    ImageType::IndexType index;
    for (unsigned int k = 0; k < 3; ++k)
    {
      index[k] = (corner >> k) & 1u ? reference->GetLargestPossibleRegion().GetUpperIndex()[k] : 0;
    }
    FieldType::PointType x;
    reference->TransformIndexToPhysicalPoint(index, x);
    ASSERT_TRUE(coarse->GetLargestPossibleRegion().IsInside(coarse->TransformPhysicalPointToIndex(x))) << x;
  }
  std::string kind;
  const auto  field = dmrtools::InitialFieldOnGrid<3>(Path("field.nii.gz"), reference.GetPointer(), kind);
  EXPECT_NE(kind.find("resampled"), std::string::npos) << kind;
  EXPECT_LT(LargestErrorAgainst(field, affine), 1e-3);

  // on the fixed grid already: taken as it is
  auto onGrid = FieldType::New();
  onGrid->CopyInformation(reference);
  onGrid->SetRegions(reference->GetLargestPossibleRegion());
  onGrid->Allocate();
  FieldType::PixelType u;
  u[0] = 1.25f;
  u[1] = -2.5f;
  u[2] = 0.125f;
  onGrid->FillBuffer(u);
  writer->SetInput(onGrid);
  writer->SetFileName(Path("on-grid.nii.gz"));
  writer->Update();
  const auto same = dmrtools::InitialFieldOnGrid<3>(Path("on-grid.nii.gz"), reference.GetPointer(), kind);
  EXPECT_EQ(kind, "displacement field");
  EXPECT_EQ(same->GetPixel({ { 3, 4, 5 } }), u);
}

// --inverse with a displacement field image: its inverse on the fixed grid by fixed-point iteration. For an affine
// field the iteration of a voxel y only samples the field at y + v(y), so wherever T^-1(y) lies inside the grid the
// result is the exact inverse T^-1(y) - y to the tolerance (0.001 voxel). A folded field is refused, although every
// voxel's iteration converges there (to one of the points that map onto it).
TEST(InitialTransform, TheInverseOfAFieldImageIsItsFixedPointInverse)
{
  auto         reference = Reference();
  auto         affine = itk::AffineTransform<double, 3>::New();
  auto         parameters = affine->GetParameters();
  const double values[12] = { 1.04, 0.03, -0.02, -0.02, 0.97, 0.01, 0.02, -0.01, 1.03, 0.6, -0.4, 0.9 };
  for (unsigned int i = 0; i < 12; ++i)
  {
    parameters[i] = values[i];
  }
  affine->SetParameters(parameters);
  FieldType::PointType centre;
  reference->TransformContinuousIndexToPhysicalPoint(
    itk::ContinuousIndex<double, 3>(std::array<double, 3>{ 9.5, 7.5, 5.5 }.data()), centre);
  affine->SetCenter(centre);
  auto field = FieldType::New();
  field->CopyInformation(reference);
  field->SetRegions(reference->GetLargestPossibleRegion());
  field->Allocate();
  WriteDisplacementOf(affine, field, Path("affine-field.nii.gz"));
  std::string kind;
  const auto  forward = dmrtools::InitialFieldOnGrid<3>(Path("affine-field.nii.gz"), reference.GetPointer(), kind);
  const auto  inverse =
    dmrtools::InitialInverseFieldOnGrid<3>(Path("affine-field.nii.gz"), reference.GetPointer(), forward.GetPointer());
  // on the forward field's grid, the fixed grid as read back from the file
  EXPECT_EQ(inverse->GetDirection(), forward->GetDirection());
  EXPECT_EQ(inverse->GetOrigin(), forward->GetOrigin());
  EXPECT_EQ(inverse->GetSpacing(), forward->GetSpacing());
  EXPECT_EQ(inverse->GetLargestPossibleRegion(), reference->GetLargestPossibleRegion());
  const auto exact = affine->GetInverseTransform();
  ASSERT_TRUE(exact);
  size_t                                            compared = 0;
  double                                            largest = 0.0;
  itk::ImageRegionConstIteratorWithIndex<FieldType> iv(inverse, inverse->GetLargestPossibleRegion());
  for (iv.GoToBegin(); !iv.IsAtEnd(); ++iv)
  {
    FieldType::PointType y;
    inverse->TransformIndexToPhysicalPoint(iv.GetIndex(), y);
    const auto                      x = exact->TransformPoint(y);
    itk::ContinuousIndex<double, 3> c;
    inverse->TransformPhysicalPointToContinuousIndex(x, c);
    bool inside = true;
    for (unsigned int k = 0; k < 3; ++k)
    {
      inside =
        inside && c[k] >= 0.0 && c[k] <= static_cast<double>(inverse->GetLargestPossibleRegion().GetSize()[k] - 1);
    }
    if (!inside)
    {
      continue;
    }
    ++compared;
    for (unsigned int k = 0; k < 3; ++k)
    {
      largest = std::max(largest, std::abs(static_cast<double>(iv.Get()[k]) - (x[k] - y[k])));
    }
  }
  std::cout << "inverse of the field image: " << compared << " voxels compared, largest error " << largest << " mm"
            << std::endl;
  EXPECT_GT(compared, inverse->GetLargestPossibleRegion().GetNumberOfPixels() / 2);
  EXPECT_LT(largest, 3e-3); // 0.001 voxel of at most 2 mm, plus float rounding

  // folded: u = 6 sin(2 pi i_2 / 6) mm along the direction's third column, on a 2 mm axis (|du/dz| up to 3)
  itk::ImageRegionIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    const double         a = 6.0 * std::sin(2.0 * M_PI * static_cast<double>(it.GetIndex()[2]) / 6.0);
    FieldType::PixelType u;
    for (unsigned int k = 0; k < 3; ++k)
    {
      u[k] = static_cast<float>(a * reference->GetDirection()[k][2]);
    }
    it.Set(u);
  }
  auto writer = itk::ImageFileWriter<FieldType>::New();
  writer->SetInput(field);
  writer->SetFileName(Path("folded-field.nii.gz"));
  writer->Update();
  const auto folded = dmrtools::InitialFieldOnGrid<3>(Path("folded-field.nii.gz"), reference.GetPointer(), kind);
  try
  {
    dmrtools::InitialInverseFieldOnGrid<3>(Path("folded-field.nii.gz"), reference.GetPointer(), folded.GetPointer());
    ADD_FAILURE() << "a folded field was inverted";
  }
  catch (const itk::ExceptionObject & e)
  {
    EXPECT_NE(std::string(e.GetDescription()).find("is folded"), std::string::npos) << e.GetDescription();
  }
}

TEST(InitialTransform, BadFilesAreRefusedWithTheReason)
{
  auto translation2D = itk::TranslationTransform<double, 2>::New();
  Write(translation2D, Path("two-d.tfm"));
  EXPECT_TRUE(RefusedMentioning(Path("two-d.tfm"), "the images are 3D"));

  {
    std::ofstream two(Path("two.tfm"));
    two << "#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_3_3\nParameters: 1 2 3\n"
           "FixedParameters:\n#Transform 1\nTransform: TranslationTransform_double_3_3\nParameters: 1 2 3\n"
           "FixedParameters:\n";
  }
  EXPECT_TRUE(RefusedMentioning(Path("two.tfm"), "holds 2 transforms"));

  {
    std::ofstream garbage(Path("garbage.tfm"));
    garbage << "not a transform\n";
  }
  EXPECT_TRUE(RefusedMentioning(Path("garbage.tfm"), "garbage.tfm"));
  std::ofstream(Path("TransformParameters.0.txt"))
    << "(Transform \"AffineTransform\")\n(NumberOfParameters 6)\n(TransformParameters 1 0 0 1 2 3)\n";
  EXPECT_TRUE(RefusedMentioning(Path("TransformParameters.0.txt"), "elastix transform parameter file"));
  EXPECT_TRUE(RefusedMentioning(Path("missing.tfm"), "no such file"));

  // ITK's text reader alone took these without a word (another translation than the file says)
  const std::string header = "#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_3_3\n";
  std::ofstream(Path("unknown.tfm")) << header.substr(0, header.find("Transform: "))
                                     << "Transform: NoSuchTransform_double_3_3\n"
                                     << "Parameters: 1\nFixedParameters:\n";
  EXPECT_TRUE(RefusedMentioning(Path("unknown.tfm"), "which this ITK does not know"));
  std::ofstream(Path("no-parameters.tfm")) << header << "FixedParameters:\n";
  EXPECT_TRUE(RefusedMentioning(Path("no-parameters.tfm"), "has no \"Parameters:\" line"));
  std::ofstream(Path("fixed-short.tfm"))
    << "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
       "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 1 2\n";
  EXPECT_TRUE(RefusedMentioning(Path("fixed-short.tfm"), "has 2 fixed parameters, it takes 3"));
  for (const auto & [name, parameters, text] :
       { std::make_tuple("nan.tfm", "1 NaN 3", "\"NaN\" in the parameters of transform 0 is not a finite number"),
         std::make_tuple("typo.txt", "1 2 x3", "\"x3\" in the parameters"),
         std::make_tuple("short.tfm", "1 2", "has 2 parameters, it takes 3"),
         std::make_tuple("long.tfm", "1 2 3 4", "has 4 parameters, it takes 3") })
  {
    std::ofstream(Path(name)) << header << "Parameters: " << parameters << "\nFixedParameters:\n";
    EXPECT_TRUE(RefusedMentioning(Path(name), text)) << name;
  }
  // binary formats keep a NaN: the field is checked
  auto translation = itk::TranslationTransform<double, 3>::New();
  auto offset = translation->GetParameters();
  offset[1] = std::numeric_limits<double>::quiet_NaN();
  translation->SetParameters(offset);
  Write(translation, Path("nan.h5"));
  EXPECT_TRUE(RefusedMentioning(Path("nan.h5"), "not finite"));

  // a scalar image is not a displacement field
  auto writer = itk::ImageFileWriter<ImageType>::New();
  writer->SetInput(Reference());
  writer->SetFileName(Path("scalar.nii.gz"));
  writer->Update();
  EXPECT_TRUE(RefusedMentioning(Path("scalar.nii.gz"), "displacement field of 3 components"));
}
