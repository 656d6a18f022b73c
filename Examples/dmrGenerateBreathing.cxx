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

// Makes a 3D registration pair with a known answer from one CT: the CT (fixed), the CT deformed by a smooth,
// breathing-like motion (moving), the true displacement and a lung mask. See dmrBreathingDeformation.h for the motion
// and its direction convention (moving point = fixed point + u, so moving(x + u(x)) = fixed(x)).
#include "dmrBreathingDeformation.h"
#include "dmrErrorStatistics.h"
#include "dmrLungMask.h"
#include "dmrReadImage.h"
#include "dmrToolErrors.h"
#include "dmrToolOutput.h"
#include "itkResampleImageFilter.h"
#include <array>
#include "itkImageFileWriter.h"
#include "itkImageIOFactory.h"
#include "itksys/SystemTools.hxx"
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <iomanip>
#include <iostream>
#include <limits>
#include <stdexcept>
#include <string>
#include <unistd.h>
#include <vector>

namespace
{
const char * const kUsage =
  "Usage: dmrGenerateBreathing --input CT --output-dir D [--amplitude-mm A] [--size NX,NY,NZ] [--float]\n"
  "  CT: a 3D CT in HU, as an image file (NIfTI .nii/.nii.gz, .mha, ...) or a directory holding one DICOM series\n"
  "      (slices ordered by position).\n"
  "  Writes into D (created if missing; files appear only when everything succeeded):\n"
  "    fixed.nii.gz                 the CT as read\n"
  "    moving.nii.gz                the CT deformed by a breathing-like motion: moving(x + u(x)) = fixed(x)\n"
  "    truth-displacement.nii.gz    u on the fixed grid, mm, physical (LPS) frame, 3-vector per voxel (float);\n"
  "                                 ITK convention: the moving point of fixed point x is x + u(x)\n"
  "    lung-mask.nii.gz             lung mask of the fixed CT (uint8 0/1; HU < -400 inside the body)\n"
  "  --amplitude-mm A  peak inferior displacement of the diaphragm in mm (default 15; lateral and anterior-posterior\n"
  "                    expansion are 0.2 A and 0.33 A)\n"
  "  --size NX,NY,NZ   first resample the CT (linear) onto a grid of this size covering the same physical box\n"
  "                    (e.g. 256,256,132 for the paper's 3D benchmark size)\n"
  "  --float           write fixed/moving as float (default: short when the CT holds integers in the int16 range)\n"
  "  Prints the field's max |u|, det(I + grad u) range, the lung volume and |u| inside the lungs.\n";

using dmrtools::UsageError;

struct Options
{
  std::string                  input, outputDir;
  double                       amplitude{ 15.0 };
  bool                         forceFloat{ false };
  std::array<unsigned long, 3> size{ { 0, 0, 0 } }; // 0: keep the input grid
};

Options
ParseArguments(int argc, char * argv[])
{
  Options opt;
  for (int i = 1; i < argc; ++i)
  {
    const std::string a = argv[i];
    auto              value = [&]() -> std::string {
      if (i + 1 >= argc)
      {
        throw UsageError(a + " needs a value");
      }
      return argv[++i];
    };
    if (a == "--help" || a == "-h")
    {
      std::cout << kUsage;
      std::exit(0);
    }
    else if (a == "--input")
    {
      opt.input = value();
    }
    else if (a == "--output-dir")
    {
      opt.outputDir = value();
    }
    else if (a == "--amplitude-mm")
    {
      const std::string v = value();
      char *            end = nullptr;
      opt.amplitude = std::strtod(v.c_str(), &end);
      if (v.empty() || *end != '\0' || !std::isfinite(opt.amplitude) || opt.amplitude < 0.0 || opt.amplitude > 100.0)
      {
        throw UsageError("--amplitude-mm needs a number in [0, 100], got \"" + v + "\"");
      }
    }
    else if (a == "--size")
    {
      const std::string v = value();
      unsigned long     n[3];
      char              tail = 0;
      if (std::sscanf(v.c_str(), "%lu,%lu,%lu%c", &n[0], &n[1], &n[2], &tail) != 3 || n[0] < 8 || n[1] < 8 ||
          n[2] < 8 || n[0] > 4096 || n[1] > 4096 || n[2] > 4096)
      {
        throw UsageError("--size needs NX,NY,NZ with 8 <= N <= 4096, got \"" + v + "\"");
      }
      opt.size = { { n[0], n[1], n[2] } };
    }
    else if (a == "--float")
    {
      opt.forceFloat = true;
    }
    else
    {
      throw UsageError("unknown argument \"" + a + "\" (see --help)");
    }
  }
  if (opt.input.empty())
  {
    throw UsageError("--input is required (see --help)");
  }
  if (opt.outputDir.empty())
  {
    throw UsageError("--output-dir is required (see --help)");
  }
  dmrtools::RefuseOutputOverInput(opt.outputDir,
                                  { "fixed.nii.gz", "moving.nii.gz", "truth-displacement.nii.gz", "lung-mask.nii.gz" },
                                  "--input",
                                  opt.input);
  return opt;
}

using dmrtools::Staging;
using dmrtools::WriteImage;

template <typename TOut, typename TIn>
typename TOut::Pointer
CastImage(const TIn * in)
{
  auto out = TOut::New();
  out->CopyInformation(in);
  out->SetRegions(in->GetLargestPossibleRegion());
  out->Allocate();
  const size_t n = in->GetLargestPossibleRegion().GetNumberOfPixels();
  const auto * a = in->GetBufferPointer();
  auto *       b = out->GetBufferPointer();
  for (size_t p = 0; p < n; ++p)
  {
    b[p] = static_cast<typename TOut::PixelType>(a[p]);
  }
  return out;
}

/** Checks that path holds one 3D scalar image or a DICOM series directory. */
void
CheckInput(const std::string & path)
{
  unsigned int       components = 1;
  const unsigned int d = dmrtools::ImageDimensionOf(path, &components);
  if (d != 3)
  {
    throw UsageError("the input must be a 3D image, " + path + " is " + std::to_string(d) + "D");
  }
  if (components != 1)
  {
    throw UsageError("the input must be a scalar (CT) image, " + path + " has " + std::to_string(components) +
                     " components per voxel");
  }
}

int
Run(const Options & opt)
{
  using ImageType = itk::Image<float, 3>;
  using ShortImageType = itk::Image<short, 3>;
  using FieldType = itk::Image<itk::Vector<float, 3>, 3>;
  const auto start = std::chrono::steady_clock::now();

  CheckInput(opt.input);
  ImageType::Pointer fixed;
  try
  {
    fixed = dmrtools::ReadImageOrDicomSeries<ImageType>(opt.input);
  }
  catch (const itk::ExceptionObject & e)
  {
    throw UsageError("cannot read " + opt.input + ": " + e.GetDescription());
  }
  if (opt.size[0] > 0)
  {
    // same physical box (outer voxel centres kept): spacing' = spacing (n - 1) / (n' - 1)
    const auto             in = fixed->GetLargestPossibleRegion().GetSize();
    ImageType::SizeType    outSize;
    ImageType::SpacingType spacing;
    for (unsigned int k = 0; k < 3; ++k)
    {
      outSize[k] = opt.size[k];
      spacing[k] = fixed->GetSpacing()[k] * static_cast<double>(in[k] - 1) / static_cast<double>(opt.size[k] - 1);
    }
    auto resample = itk::ResampleImageFilter<ImageType, ImageType, double>::New();
    resample->SetInput(fixed);
    resample->SetSize(outSize);
    resample->SetOutputSpacing(spacing);
    resample->SetOutputOrigin(fixed->GetOrigin());
    resample->SetOutputDirection(fixed->GetDirection());
    resample->SetDefaultPixelValue(-1000.0f);
    resample->Update();
    fixed = resample->GetOutput();
    fixed->DisconnectPipeline();
    // keep integral HU so that the output stays short
    float *      v = fixed->GetBufferPointer();
    const size_t count = fixed->GetBufferedRegion().GetNumberOfPixels();
    for (size_t p = 0; p < count; ++p)
    {
      v[p] = std::round(v[p]);
    }
  }
  const auto size = fixed->GetLargestPossibleRegion().GetSize();
  for (unsigned int k = 0; k < 3; ++k)
  {
    if (size[k] < 8)
    {
      throw UsageError("the input is too small for a 3D CT (size " + std::to_string(size[0]) + " x " +
                       std::to_string(size[1]) + " x " + std::to_string(size[2]) + ", at least 8 per axis)");
    }
  }
  bool integral = true;
  {
    const size_t  n = fixed->GetLargestPossibleRegion().GetNumberOfPixels();
    const float * v = fixed->GetBufferPointer();
    for (size_t p = 0; p < n && integral; ++p)
    {
      integral = std::isfinite(v[p]) && v[p] == std::round(v[p]) && v[p] >= std::numeric_limits<short>::lowest() &&
                 v[p] <= std::numeric_limits<short>::max();
    }
  }
  const bool writeShort = integral && !opt.forceFloat;

  // lung mask, then the motion placed on the lungs
  dmrtools::LungMaskReport lungReport;
  auto                     mask = dmrtools::LungMask(fixed.GetPointer(), {}, &lungReport);
  if (lungReport.voxels == 0)
  {
    throw UsageError("no lung region found (no air below -400 HU inside the body): is " + opt.input + " a CT in HU?");
  }
  dmrtools::BreathingParameters parameters;
  parameters.amplitudeMM = opt.amplitude;
  const dmrtools::PhysicalBox          lungBox = dmrtools::LungBoxFromMask(mask.GetPointer());
  const dmrtools::BreathingDeformation deformation(fixed, lungBox, parameters);
  auto                                 truth = dmrtools::SampleDisplacementField<FieldType>(deformation, fixed);
  const auto                           check = dmrtools::AnalyzeDisplacementField(truth.GetPointer());
  if (!(check.maximumGradientNorm < 1.0) || !(check.minimumJacobian > 0.0))
  {
    throw std::runtime_error("the deformation is not safely invertible for this image (max |grad u| " +
                             std::to_string(check.maximumGradientNorm) + ", min det J " +
                             std::to_string(check.minimumJacobian) + "): use a smaller --amplitude-mm");
  }
  const auto inside = dmrtools::DisplacementMagnitudeInMask(truth.GetPointer(), mask.GetPointer());

  Staging staging(opt.outputDir);
  if (writeShort)
  {
    auto fixedShort = CastImage<ShortImageType>(fixed.GetPointer());
    auto moving = dmrtools::WarpWithBreathing(fixedShort.GetPointer(), deformation);
    WriteImage(fixedShort.GetPointer(), staging.Path("fixed.nii.gz"));
    WriteImage(moving.GetPointer(), staging.Path("moving.nii.gz"));
  }
  else
  {
    auto moving = dmrtools::WarpWithBreathing(fixed.GetPointer(), deformation);
    WriteImage(fixed.GetPointer(), staging.Path("fixed.nii.gz"));
    WriteImage(moving.GetPointer(), staging.Path("moving.nii.gz"));
  }
  WriteImage(truth.GetPointer(), staging.Path("truth-displacement.nii.gz"));
  WriteImage(mask.GetPointer(), staging.Path("lung-mask.nii.gz"));
  staging.Commit();

  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const auto & h = fixed->GetSpacing();
  std::cout << std::fixed << std::setprecision(3);
  std::cout << "input: " << opt.input << " (" << size[0] << " x " << size[1] << " x " << size[2] << ", spacing " << h[0]
            << " x " << h[1] << " x " << h[2] << " mm)\n";
  std::cout << "amplitude: " << opt.amplitude << " mm (border ramp " << deformation.GetRampMM() << " mm)\n";
  std::cout << "max |u|: " << check.maximumMagnitude << " mm (on the image border: " << check.maximumBorderMagnitude
            << " mm)\n";
  std::cout << "det(I + grad u): [" << check.minimumJacobian << ", " << check.maximumJacobian << "] (min at index "
            << check.minimumJacobianIndex << ")\n";
  std::cout << "max |grad u| (Frobenius): " << check.maximumGradientNorm << "\n";
  const auto imageBox = dmrtools::ImageBoundingBox(fixed);
  std::cout << "image box (LPS mm): " << imageBox.lower << " - " << imageBox.upper << "\n";
  std::cout << "lung box (LPS mm): " << lungBox.lower << " - " << lungBox.upper << "\n";
  std::cout << "lung mask: " << lungReport.voxels << " voxels, " << lungReport.volumeLitres << " l, "
            << lungReport.components << " component(s)\n";
  std::cout << "|u| inside the lung mask (initial dense error): mean " << inside.mean << " mm, p95 " << inside.p95
            << " mm, max " << inside.max << " mm\n";
  std::cout << "images written as: " << (writeShort ? "short" : "float") << "\n";
  std::cout << "output: " << opt.outputDir << "\n";
  std::cout << "time: " << std::setprecision(1) << seconds << " s\n";
  return 0;
}
} // namespace

int
main(int argc, char * argv[])
{
  return dmrtools::RunReportingErrors("dmrGenerateBreathing", [&]() {
    dmrtools::CatchInterruptSignals(); // an interrupted run commits nothing (Staging::Commit)
    const Options opt = ParseArguments(argc, argv);
    dmrtools::StartItkThreadPool();
    return Run(opt);
  });
}
