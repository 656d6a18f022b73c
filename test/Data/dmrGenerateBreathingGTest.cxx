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
// The dmrGenerateBreathing tool on a small thorax phantom: outputs, their geometry and direction convention, and
// bad input (one error line, non-zero exit, nothing written).
#include "dmrDataTestHelpers.h"
#include "dmrErrorStatistics.h"
#include "itkDisplacementFieldTransform.h"
#include "itkImageFileReader.h"
#include "itkImageFileWriter.h"
#include "itkImageRegionConstIterator.h"
#include "itkResampleImageFilter.h"
#include "itkSmoothingRecursiveGaussianImageFilter.h"
#include "itksys/Directory.hxx"
#include "gtest/gtest.h"
#include <fstream>
#include <sstream>
#include <sys/wait.h>

namespace
{
using ShortImageType = itk::Image<short, 3>;
using FloatImageType = itk::Image<float, 3>;
using FieldType = itk::Image<itk::Vector<double, 3>, 3>;
using MaskType = itk::Image<unsigned char, 3>;

#ifdef DMR_GENERATE_BREATHING_EXE
const char * const kTool = DMR_GENERATE_BREATHING_EXE;
#else
const char * const kTool = nullptr;
#endif

struct RunResult
{
  int         exitCode{ -1 };
  std::string out, err;
};

std::string
ReadText(const std::string & path)
{
  std::ifstream      in(path);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

RunResult
RunTool(const std::string & arguments, const std::string & scratch)
{
  const std::string out = scratch + "/stdout.txt", err = scratch + "/stderr.txt";
  const std::string command = std::string("'") + kTool + "' " + arguments + " > '" + out + "' 2> '" + err + "'";
  const int         status = std::system(command.c_str());
  RunResult         r;
  r.exitCode = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.out = ReadText(out);
  r.err = ReadText(err);
  std::remove(out.c_str());
  std::remove(err.c_str());
  return r;
}

template <typename TImage>
typename TImage::Pointer
Read(const std::string & path)
{
  auto reader = itk::ImageFileReader<TImage>::New();
  reader->SetFileName(path);
  reader->Update();
  return reader->GetOutput();
}

template <typename TImage>
void
Write(const TImage * image, const std::string & path)
{
  auto writer = itk::ImageFileWriter<TImage>::New();
  writer->SetInput(image);
  writer->SetFileName(path);
  writer->Update();
}

::testing::AssertionResult
SameGeometry(const itk::ImageBase<3> * a, const itk::ImageBase<3> * b)
{
  if (a->GetLargestPossibleRegion().GetSize() != b->GetLargestPossibleRegion().GetSize())
  {
    return ::testing::AssertionFailure() << "size " << a->GetLargestPossibleRegion().GetSize() << " vs "
                                         << b->GetLargestPossibleRegion().GetSize();
  }
  for (unsigned int i = 0; i < 3; ++i)
  {
    if (std::abs(a->GetSpacing()[i] - b->GetSpacing()[i]) > 1e-5 ||
        std::abs(a->GetOrigin()[i] - b->GetOrigin()[i]) > 1e-3)
    {
      return ::testing::AssertionFailure()
             << "spacing/origin " << a->GetSpacing() << a->GetOrigin() << " vs " << b->GetSpacing() << b->GetOrigin();
    }
    for (unsigned int j = 0; j < 3; ++j)
    {
      if (std::abs(a->GetDirection()[i][j] - b->GetDirection()[i][j]) > 1e-5)
      {
        return ::testing::AssertionFailure() << "direction differs";
      }
    }
  }
  return ::testing::AssertionSuccess();
}

/** Names in dir other than . and .. */
std::vector<std::string>
Listing(const std::string & dir)
{
  std::vector<std::string> names;
  itksys::Directory        d;
  if (d.Load(dir))
  {
    for (unsigned long i = 0; i < d.GetNumberOfFiles(); ++i)
    {
      const std::string n = d.GetFile(i);
      if (n != "." && n != "..")
      {
        names.push_back(n);
      }
    }
  }
  std::sort(names.begin(), names.end());
  return names;
}

/** One line on stderr naming the tool, non-zero exit, nothing on stdout. */
::testing::AssertionResult
OneLineError(const RunResult & r, const std::string & expected)
{
  if (r.exitCode == 0)
  {
    return ::testing::AssertionFailure() << "exit code 0";
  }
  if (r.err.rfind("dmrGenerateBreathing: error: ", 0) != 0 || std::count(r.err.begin(), r.err.end(), '\n') != 1)
  {
    return ::testing::AssertionFailure() << "stderr is not one error line: \"" << r.err << "\"";
  }
  if (r.err.find(expected) == std::string::npos)
  {
    return ::testing::AssertionFailure() << "stderr \"" << r.err << "\" lacks \"" << expected << "\"";
  }
  return ::testing::AssertionSuccess();
}
} // namespace

TEST(GenerateBreathingTool, WritesAConsistentPair)
{
  if (!kTool)
  {
    GTEST_SKIP() << "dmrGenerateBreathing is not built (DMR_BUILD_EXAMPLES=OFF)";
  }
  dmrtest::ScratchDirectory scratch("tool");
  double                    lungVolume = 0.0;
  auto                      sharp = dmrtest::MakeThoraxPhantom(
    { { 80, 70, 56 } }, dmrtest::Vec(4.0, 4.0, 6.0), dmrtest::ObliqueDirection(), false, &lungVolume);
  // smoothed (sigma 8 mm), so that two linear interpolations (warp, then resample) stay close to the original
  auto blur = itk::SmoothingRecursiveGaussianImageFilter<ShortImageType, ShortImageType>::New();
  blur->SetInput(sharp);
  blur->SetSigma(8.0);
  blur->Update();
  ShortImageType::Pointer ct = blur->GetOutput();
  Write(ct.GetPointer(), scratch.Path() + "/ct.nii.gz");
  const std::string out = scratch.Path() + "/out";
  const RunResult   r =
    RunTool("--input " + scratch.Path() + "/ct.nii.gz --output-dir " + out + " --amplitude-mm 12", scratch.Path());
  ASSERT_EQ(r.exitCode, 0) << r.err;
  EXPECT_EQ(r.err, "");
  EXPECT_NE(r.out.find("det(I + grad u): ["), std::string::npos) << r.out;
  EXPECT_EQ(
    Listing(out),
    (std::vector<std::string>{ "fixed.nii.gz", "lung-mask.nii.gz", "moving.nii.gz", "truth-displacement.nii.gz" }));
  // fixed is the input, unchanged (short)
  auto fixed = Read<ShortImageType>(out + "/fixed.nii.gz");
  auto input = Read<ShortImageType>(scratch.Path() + "/ct.nii.gz");
  ASSERT_TRUE(SameGeometry(fixed, input));
  EXPECT_TRUE(std::equal(fixed->GetBufferPointer(),
                         fixed->GetBufferPointer() + fixed->GetLargestPossibleRegion().GetNumberOfPixels(),
                         input->GetBufferPointer()));
  auto moving = Read<FloatImageType>(out + "/moving.nii.gz");
  auto truth = Read<FieldType>(out + "/truth-displacement.nii.gz");
  auto mask = Read<MaskType>(out + "/lung-mask.nii.gz");
  EXPECT_TRUE(SameGeometry(moving, fixed));
  EXPECT_TRUE(SameGeometry(truth, fixed));
  EXPECT_TRUE(SameGeometry(mask, fixed));
  const auto inside = dmrtools::DisplacementMagnitudeInMask(truth.GetPointer(), mask.GetPointer());
  EXPECT_GT(inside.mean, 1.0);
  EXPECT_LE(inside.max, 12.0 + 1e-3);
  EXPECT_NEAR(static_cast<double>(inside.count) * 4.0 * 4.0 * 6.0, lungVolume, 0.15 * lungVolume); // blurred
  // direction: resampling moving through x -> x + u(x) gives back fixed (up to two linear interpolations), through
  // x -> x - u(x) it does not
  auto resampled = [&](double sign) {
    auto negated = FieldType::New();
    negated->CopyInformation(truth);
    negated->SetRegions(truth->GetLargestPossibleRegion());
    negated->Allocate();
    const size_t n = truth->GetLargestPossibleRegion().GetNumberOfPixels();
    for (size_t p = 0; p < n; ++p)
    {
      negated->GetBufferPointer()[p] = truth->GetBufferPointer()[p] * sign;
    }
    auto transform = itk::DisplacementFieldTransform<double, 3>::New();
    transform->SetDisplacementField(negated);
    auto resample = itk::ResampleImageFilter<FloatImageType, FloatImageType>::New();
    resample->SetInput(moving);
    resample->SetTransform(transform);
    resample->SetOutputParametersFromImage(moving);
    resample->Update();
    FloatImageType::Pointer out = resample->GetOutput();
    return out;
  };
  auto                                          forward = resampled(1.0), backward = resampled(-1.0);
  double                                        error = 0.0, wrong = 0.0, change = 0.0;
  itk::ImageRegionConstIterator<ShortImageType> f(fixed, fixed->GetLargestPossibleRegion());
  itk::ImageRegionConstIterator<FloatImageType> m(moving, moving->GetLargestPossibleRegion());
  itk::ImageRegionConstIterator<FloatImageType> w(forward, moving->GetLargestPossibleRegion());
  itk::ImageRegionConstIterator<FloatImageType> b(backward, moving->GetLargestPossibleRegion());
  for (; !f.IsAtEnd(); ++f, ++m, ++w, ++b)
  {
    error += std::abs(w.Get() - f.Get());
    wrong += std::abs(b.Get() - f.Get());
    change += std::abs(m.Get() - f.Get());
  }
  std::cout << "sum |moving(x + u) - fixed| / sum |moving - fixed| = " << error / change
            << ", with x - u: " << wrong / change << std::endl;
  EXPECT_GT(change, 0.0);
  EXPECT_LT(error, 0.25 * change); // rest: interpolation blur and the rounding of moving to short
  EXPECT_GT(wrong, change);
}

TEST(GenerateBreathingTool, BadInputGivesOneLineAndWritesNothing)
{
  if (!kTool)
  {
    GTEST_SKIP() << "dmrGenerateBreathing is not built (DMR_BUILD_EXAMPLES=OFF)";
  }
  dmrtest::ScratchDirectory scratch("toolbad");
  const std::string         out = scratch.Path() + "/out";
  EXPECT_TRUE(OneLineError(RunTool("--input /nonexistent.nii.gz --output-dir " + out, scratch.Path()),
                           "no such file or directory"));
  EXPECT_TRUE(OneLineError(RunTool("--output-dir " + out, scratch.Path()), "--input is required"));
  EXPECT_TRUE(OneLineError(RunTool("--input x --output-dir " + out + " --bogus", scratch.Path()), "unknown argument"));
  EXPECT_TRUE(OneLineError(RunTool("--input x --output-dir " + out + " --amplitude-mm abc", scratch.Path()),
                           "--amplitude-mm needs a number"));
  // a 3D image without air below -400: not a CT in HU
  auto bright = dmrtest::MakeImage<ShortImageType>(
    { { 16, 16, 12 } }, dmrtest::Vec(2.0, 2.0, 2.0), dmrtest::ObliqueDirection(), dmrtest::Pt(0, 0, 0));
  bright->FillBuffer(100);
  Write(bright.GetPointer(), scratch.Path() + "/bright.nii.gz");
  EXPECT_TRUE(OneLineError(RunTool("--input " + scratch.Path() + "/bright.nii.gz --output-dir " + out, scratch.Path()),
                           "no lung region found"));
  // a 2D image
  auto flat = itk::Image<short, 2>::New();
  flat->SetRegions(itk::Size<2>{ { 16, 16 } });
  flat->Allocate();
  flat->FillBuffer(0);
  Write(flat.GetPointer(), scratch.Path() + "/flat.nii.gz");
  EXPECT_TRUE(OneLineError(RunTool("--input " + scratch.Path() + "/flat.nii.gz --output-dir " + out, scratch.Path()),
                           "must be a 3D image"));
  // not an image
  std::ofstream(scratch.Path() + "/text.nii.gz") << "hello";
  EXPECT_TRUE(OneLineError(RunTool("--input " + scratch.Path() + "/text.nii.gz --output-dir " + out, scratch.Path()),
                           "text.nii.gz"));
  // an empty directory is no DICOM series
  itksys::SystemTools::MakeDirectory(scratch.Path() + "/empty");
  EXPECT_TRUE(OneLineError(RunTool("--input " + scratch.Path() + "/empty --output-dir " + out, scratch.Path()),
                           "no DICOM series"));
  // nothing was created for any of them
  EXPECT_FALSE(itksys::SystemTools::FileExists(out));
  // the output directory exists and is a file
  std::ofstream(scratch.Path() + "/afile") << "x";
  auto ct = dmrtest::MakeThoraxPhantom({ { 48, 40, 32 } }, dmrtest::Vec(6.0, 6.0, 9.0), dmrtest::ObliqueDirection());
  Write(ct.GetPointer(), scratch.Path() + "/ct.nii.gz");
  EXPECT_TRUE(OneLineError(
    RunTool("--input " + scratch.Path() + "/ct.nii.gz --output-dir " + scratch.Path() + "/afile", scratch.Path()),
    "not a directory"));
  // an existing output directory keeps only what was there when the run fails
  itksys::SystemTools::MakeDirectory(out);
  std::ofstream(out + "/keep.txt") << "x";
  EXPECT_TRUE(OneLineError(RunTool("--input " + scratch.Path() + "/bright.nii.gz --output-dir " + out, scratch.Path()),
                           "no lung region found"));
  EXPECT_EQ(Listing(out), std::vector<std::string>{ "keep.txt" });
  // an input that an output would replace (the tool read it first and went through: --size replaced the CT by its
  // resampled copy)
  itksys::SystemTools::CopyAFile(scratch.Path() + "/ct.nii.gz", out + "/fixed.nii.gz");
  const std::string copy = out + "/fixed.nii.gz";
  EXPECT_TRUE(OneLineError(
    RunTool("--input " + copy + " --output-dir " + scratch.Path() + "/./out --size 24,20,16", scratch.Path()),
    "the output fixed.nii.gz in --output-dir would replace the input --input"));
  EXPECT_EQ(Listing(out), (std::vector<std::string>{ "fixed.nii.gz", "keep.txt" }));
  EXPECT_FALSE(itksys::SystemTools::FilesDiffer(copy, scratch.Path() + "/ct.nii.gz"));
}
