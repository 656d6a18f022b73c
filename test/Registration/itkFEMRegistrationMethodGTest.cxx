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
#include "itkFEMRegistrationMethod.h"
#include "itkCastImageFilter.h"
#include "itkCommand.h"
#include "itkResampleImageFilter.h"
#include "itkTriangleCell.h"
#include "itkVectorLinearInterpolateImageFunction.h"
#include "dmrFieldImage.h"
#include "dmrObjectChecks.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>
#include <thread>
#include <vector>

namespace
{
using ImageType = itk::Image<float, 2>;
using MethodType = itk::FEMRegistrationMethod<ImageType, ImageType>;
using MeshMode = itk::DynamicMeshRegistrationEnums::MeshMode;

/** Smooth blob (Gaussian-edged ellipse) on a w x h grid; geometry set by the caller. */
ImageType::Pointer
Blob(unsigned int w, unsigned int h, double cx, double cy, double rx, double ry)
{
  auto image = ImageType::New();
  image->SetRegions(ImageType::SizeType{ { w, h } });
  image->Allocate();
  for (unsigned int y = 0; y < h; ++y)
  {
    for (unsigned int x = 0; x < w; ++x)
    {
      const double r = std::sqrt(std::pow((x - cx) / rx, 2) + std::pow((y - cy) / ry, 2));
      image->SetPixel({ { x, y } }, static_cast<float>(1.0 / (1.0 + std::exp((r - 1.0) * 8.0))));
    }
  }
  return image;
}

MethodType::Pointer
SmallRegistration(MeshMode mode, unsigned int iterations = 40)
{
  auto method = MethodType::New();
  method->SetFixedImage(Blob(64, 56, 30, 28, 16, 12));
  method->SetMovingImage(Blob(64, 56, 34, 27, 12, 12));
  method->SetNumberOfNodes(30);
  method->SetNumberOfIterations(iterations);
  method->SetMeshMode(mode);
  return method;
}
} // namespace

TEST(FEMRegistrationMethod, BasicObjectMethodsPrintAndSetGet)
{
  auto method = MethodType::New();
  EXPECT_TRUE(itk::dmr::test::BasicObjectMethods(method.GetPointer(), "FEMRegistrationMethod", "ProcessObject"));
  EXPECT_TRUE(itk::dmr::test::PrintMentions(method.GetPointer(),
                                            { "NumberOfIterations",
                                              "NumberOfNodes",
                                              "NumberOfLevels",
                                              "Lambda",
                                              "Mu",
                                              "EnergyRatio",
                                              "AlphaFactor",
                                              "CVTEpsilon",
                                              "SolverTolerance",
                                              "MaximumNumberOfSweeps",
                                              "ReinitializationInterval",
                                              "MeshMode",
                                              "RegularGridSize",
                                              "Backend",
                                              "Beta",
                                              "FinalSSD",
                                              "ForceGradient",
                                              "MaximumStepHalvings",
                                              "ComputeInverse",
                                              "GPUOrderSolve",
                                              "AlwaysContractOnHost",
                                              "ContractedOnHost" }));
  DMR_EXPECT_SET_GET(method, MaximumStepHalvings, 2u);
  DMR_EXPECT_SET_GET(method, ForceGradient, itk::DynamicMeshRegistrationEnums::ForceGradient::MappedMoving);
  DMR_EXPECT_SET_GET(method, NumberOfIterations, 7u);
  DMR_EXPECT_SET_GET(method, NumberOfNodes, 55u);
  DMR_EXPECT_SET_GET(method, Lambda, 0.5);
  DMR_EXPECT_SET_GET(method, Mu, 2.0);
  DMR_EXPECT_SET_GET(method, EnergyRatio, 0.05);
  DMR_EXPECT_SET_GET(method, AlphaFactor, 0.2);
  DMR_EXPECT_SET_GET(method, RegularGridSize, 6u);
  DMR_EXPECT_SET_GET(method, ReinitializationInterval, 3u);
  DMR_EXPECT_SET_GET(method, SolverTolerance, 1e-8);
  EXPECT_EQ(method->GetDirectSolverMaximumDegreesOfFreedom(), 300u); // the default
  // at the defaults no system is both factorised by the CPU back-end and solved by CG on the device: the CUDA back-end
  // solves on the device only systems that the CPU back-end solves by CG too
  EXPECT_GT(method->GetDeviceSolverMinimumDegreesOfFreedom(), method->GetDirectSolverMaximumDegreesOfFreedom());
  DMR_EXPECT_SET_GET(method, DeviceSolverMinimumDegreesOfFreedom, 0u);
  DMR_EXPECT_SET_GET(method, DirectSolverMaximumDegreesOfFreedom, 40u);
  DMR_EXPECT_SET_GET(method, ComputeInverse, true);
  EXPECT_TRUE(method->GetGPUOrderSolve()); // the default
  DMR_EXPECT_SET_GET(method, GPUOrderSolve, false);
  EXPECT_FALSE(method->GetAlwaysContractOnHost()); // the default
  DMR_EXPECT_SET_GET(method, AlwaysContractOnHost, true);
  EXPECT_FALSE(method->GetContractedOnHost()); // no run yet
  method->SetSolverTolerance(1.0);             // clamped to the loosest tolerance allowed
  EXPECT_EQ(method->GetSolverTolerance(), 1e-2);
  method->SetNumberOfNodes(1); // clamped to the 4 nodes a mesh needs at least
  EXPECT_EQ(method->GetNumberOfNodes(), 4u);
}

// the solver's stopping rule is the registration's setting: a looser one takes fewer conjugate-gradient products and
// gives nearly the same registration
TEST(FEMRegistrationMethod, SolverToleranceSetsWhereTheSolveStops)
{
  auto tight = SmallRegistration(MeshMode::Regular, 15);
  auto loose = SmallRegistration(MeshMode::Regular, 15);
  EXPECT_EQ(loose->GetSolverTolerance(), 1e-6); // the default
  // the tolerance is the conjugate gradients' (this small system would otherwise be factorised)
  tight->SetDirectSolverMaximumDegreesOfFreedom(0);
  loose->SetDirectSolverMaximumDegreesOfFreedom(0);
  tight->SetSolverTolerance(1e-12);
  tight->Update();
  loose->Update();
  size_t tightProducts = 0, looseProducts = 0;
  for (const auto & r : tight->GetHistory())
  {
    tightProducts += r.solverIterations;
  }
  for (const auto & r : loose->GetHistory())
  {
    looseProducts += r.solverIterations;
  }
  std::cout << "CG products: " << tightProducts << " at 1e-12, " << looseProducts << " at 1e-6; SSD "
            << tight->GetFinalSSD() << " vs " << loose->GetFinalSSD() << std::endl;
  EXPECT_GT(looseProducts, 0u);
  EXPECT_LT(static_cast<double>(looseProducts), 0.8 * static_cast<double>(tightProducts));
  EXPECT_LT(tight->GetFinalSSD(), 0.8 * tight->GetHistory().front().ssd); // it registered
  EXPECT_NEAR(loose->GetFinalSSD(), tight->GetFinalSSD(), 1e-3 * tight->GetFinalSSD());
}

// GPUOrderSolve: every system by the GPU-order CG (its equality with the device is a GPU test); the run registers as
// the assembled CG's does, to the tolerance's reach, and is repeatable bit for bit
TEST(FEMRegistrationMethod, GPUOrderSolveRegistersLikeTheAssembledCG)
{
  auto ordered = SmallRegistration(MeshMode::Dynamic, 15);
  auto assembled = SmallRegistration(MeshMode::Dynamic, 15);
  auto again = SmallRegistration(MeshMode::Dynamic, 15);
  for (auto * m : { ordered.GetPointer(), assembled.GetPointer(), again.GetPointer() })
  {
    m->SetDirectSolverMaximumDegreesOfFreedom(0);
    m->SetSolverTolerance(1e-10);
  }
  ordered->SetGPUOrderSolve(true);
  assembled->SetGPUOrderSolve(false);
  again->SetGPUOrderSolve(true);
  ordered->Update();
  assembled->Update();
  again->Update();
  size_t orderedProducts = 0, assembledProducts = 0;
  for (const auto & r : ordered->GetHistory())
  {
    EXPECT_FALSE(r.directSolve);
    EXPECT_GT(r.solverIterations, 0u);
    orderedProducts += r.solverIterations;
  }
  for (const auto & r : assembled->GetHistory())
  {
    assembledProducts += r.solverIterations;
  }
  // a different CG ran: from u = 0 and counting products, where the assembled one starts from the last solution
  std::cout << "CG products: GPU order " << orderedProducts << ", assembled " << assembledProducts << std::endl;
  EXPECT_NE(orderedProducts, assembledProducts);
  EXPECT_LT(ordered->GetFinalSSD(), 0.8 * ordered->GetHistory().front().ssd); // it registered
  EXPECT_NEAR(ordered->GetFinalSSD(), assembled->GetFinalSSD(), 1e-4 * assembled->GetFinalSSD());
  const auto * a = ordered->GetDisplacementField();
  const auto * b = assembled->GetDisplacementField();
  const auto * c = again->GetDisplacementField();
  const size_t n = a->GetLargestPossibleRegion().GetNumberOfPixels();
  double       largest = 0.0;
  for (size_t p = 0; p < n; ++p)
  {
    for (unsigned int k = 0; k < 2; ++k)
    {
      largest =
        std::max(largest, std::abs(static_cast<double>(a->GetBufferPointer()[p][k]) - b->GetBufferPointer()[p][k]));
      EXPECT_EQ(a->GetBufferPointer()[p][k], c->GetBufferPointer()[p][k]);
    }
  }
  std::cout << "GPU-order CG against the assembled CG: fields up to " << largest << " mm apart" << std::endl;
  EXPECT_LT(largest, 0.01);
}

TEST(FEMRegistrationMethod, DynamicMeshLowersSSDWithPositiveJacobian)
{
  // beta R / D = 0.02 at iteration 1 makes each iteration lower the SSD by a few percent: 100 iterations
  auto method = SmallRegistration(MeshMode::Dynamic, 100);
  method->Update();
  const auto & history = method->GetHistory();
  ASSERT_EQ(history.size(), 100u);
  EXPECT_LT(method->GetFinalSSD(), 0.25 * history.front().ssd);
  EXPECT_GT(method->GetBeta(), 0.0);
  // rounded to a 24-bit significand, so that both back-ends take the same beta (dmrBackEndRounding.h)
  EXPECT_EQ(method->GetBeta(), static_cast<double>(static_cast<float>(method->GetBeta())));
  std::pair<double, double> range;
  itk::dmr::JacobianDeterminantImage(method->GetDisplacementField(), range, nullptr);
  EXPECT_GT(range.first, 0.0);
  for (const auto & r : history)
  {
    EXPECT_EQ(r.nodes, method->GetCurrentSimplexMesh().NumberOfNodes() > 0 ? r.nodes : 0u);
    EXPECT_GE(r.nodes, 4u);
  }
  // the stage times: every part of the registration stage was timed and the parts fit inside it
  const auto & t = method->GetTiming();
  EXPECT_GT(t.force, 0.0);
  EXPECT_GT(t.gather, 0.0);
  EXPECT_GT(t.update, 0.0);
  EXPECT_GT(t.femSolve, 0.0);
  EXPECT_LE(t.force + t.gather + t.update + t.femSolve, t.registration);
  EXPECT_LE(t.initialTessellation + t.tessellationOptimization + t.meshConstruction + t.barycentric + t.registration,
            t.total);
}

// Fixed and moving images that are outputs of filters not yet run (reader -> ... -> registration, one Update() at the
// end) have no size until the pipeline's information pass reaches them.
TEST(FEMRegistrationMethod, RunsDownstreamOfFiltersThatHaveNotRun)
{
  using CastType = itk::CastImageFilter<ImageType, ImageType>;
  auto direct = SmallRegistration(MeshMode::Dynamic, 10);
  direct->Update();

  auto fixedStage = CastType::New();
  fixedStage->SetInput(Blob(64, 56, 30, 28, 16, 12));
  auto movingStage = CastType::New();
  movingStage->SetInput(Blob(64, 56, 34, 27, 12, 12));
  auto method = MethodType::New();
  method->SetFixedImage(fixedStage->GetOutput());
  method->SetMovingImage(movingStage->GetOutput());
  method->SetNumberOfNodes(30);
  method->SetNumberOfIterations(10);
  ASSERT_NO_THROW(method->Update());
  const auto * field = method->GetDisplacementField();
  EXPECT_EQ(field->GetLargestPossibleRegion().GetSize(), (ImageType::SizeType{ { 64, 56 } }));
  EXPECT_EQ(method->GetFinalSSD(), direct->GetFinalSSD());
  for (size_t p = 0; p < 64 * 56; ++p)
  {
    ASSERT_EQ(field->GetBufferPointer()[p], direct->GetDisplacementField()->GetBufferPointer()[p]) << "pixel " << p;
  }

  // the checks on the sizes still hold once the pipeline has run: more nodes than pixels
  auto bad = MethodType::New();
  auto badStage = CastType::New();
  badStage->SetInput(Blob(8, 6, 4, 3, 2, 2));
  bad->SetFixedImage(badStage->GetOutput());
  bad->SetMovingImage(badStage->GetOutput());
  bad->SetNumberOfNodes(49);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(bad, { "exceeds the number of pixels (48)" }));
}

TEST(FEMRegistrationMethod, DoubleImagesGiveTheFieldOfFloatImages)
{
  // the ITK Python packages wrap double images too (wrapping/): the same pair as doubles, 20 iterations on the CPU
  using DoubleImageType = itk::Image<double, 2>;
  using DoubleMethodType = itk::FEMRegistrationMethod<DoubleImageType, DoubleImageType>;
  auto toDouble = [](const ImageType * image) {
    auto out = DoubleImageType::New();
    out->SetRegions(image->GetLargestPossibleRegion());
    out->CopyInformation(image);
    out->Allocate();
    const size_t n = image->GetLargestPossibleRegion().GetNumberOfPixels();
    std::copy(image->GetBufferPointer(), image->GetBufferPointer() + n, out->GetBufferPointer());
    return out;
  };
  auto single = SmallRegistration(MeshMode::Dynamic, 20);
  single->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
  single->Update();
  auto twice = DoubleMethodType::New();
  twice->SetFixedImage(toDouble(single->GetFixedImage()));
  twice->SetMovingImage(toDouble(single->GetMovingImage()));
  twice->SetNumberOfNodes(30);
  twice->SetNumberOfIterations(20);
  twice->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
  twice->Update();
  EXPECT_LT(twice->GetFinalSSD(), 0.8 * twice->GetHistory().front().ssd);
  EXPECT_NEAR(twice->GetFinalSSD(), single->GetFinalSSD(), 1e-6 * single->GetFinalSSD());
  const auto * a = single->GetDisplacementField();
  const auto * b = twice->GetDisplacementField();
  ASSERT_EQ(a->GetLargestPossibleRegion(), b->GetLargestPossibleRegion());
  const size_t n = a->GetLargestPossibleRegion().GetNumberOfPixels();
  double       largest = 0.0, difference = 0.0;
  for (size_t i = 0; i < n; ++i)
  {
    for (unsigned int k = 0; k < 2; ++k)
    {
      largest = std::max(largest, std::abs(static_cast<double>(a->GetBufferPointer()[i][k])));
      difference =
        std::max(difference, std::abs(static_cast<double>(a->GetBufferPointer()[i][k] - b->GetBufferPointer()[i][k])));
    }
  }
  EXPECT_GT(largest, 1.0); // the blobs are 4 px apart
  EXPECT_LT(difference, 1e-4);
}

TEST(FEMRegistrationMethod, TheIntensityUnitDoesNotChangeTheRegistration)
{
  // Beta and alpha follow the force, so the method does not depend on the intensities' unit. Images of height 2^70
  // (about 1e21) overflowed the float density ("the density must be positive and finite") and images of height
  // 2^-70 left only alpha in it (a uniform mesh, another result). Scaled by a power of two, the pair must give the
  // same field, bit for bit, with energies and beta in the images' units.
  auto reference = SmallRegistration(MeshMode::Dynamic, 20);
  reference->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
  reference->Update();
  const size_t n = reference->GetFixedImage()->GetLargestPossibleRegion().GetNumberOfPixels();
  for (const int exponent : { 70, -70 })
  {
    auto method = SmallRegistration(MeshMode::Dynamic, 20);
    method->SetFixedImage(itk::dmr::test::ScaledByPowerOfTwo(reference->GetFixedImage(), exponent));
    method->SetMovingImage(itk::dmr::test::ScaledByPowerOfTwo(reference->GetMovingImage(), exponent));
    method->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
    ASSERT_NO_THROW(method->Update()) << exponent;
    const auto * a = reference->GetDisplacementField()->GetBufferPointer();
    const auto * b = method->GetDisplacementField()->GetBufferPointer();
    for (size_t p = 0; p < n; ++p)
    {
      ASSERT_EQ(a[p], b[p]) << exponent << " pixel " << p;
    }
    const double energyUnit = std::ldexp(1.0, 2 * exponent);
    ASSERT_EQ(method->GetHistory().size(), reference->GetHistory().size());
    for (size_t i = 0; i < reference->GetHistory().size(); ++i)
    {
      EXPECT_EQ(method->GetHistory()[i].ssd, reference->GetHistory()[i].ssd * energyUnit) << exponent << " " << i;
      EXPECT_EQ(method->GetHistory()[i].mssd, reference->GetHistory()[i].mssd * energyUnit) << exponent << " " << i;
      EXPECT_EQ(method->GetHistory()[i].total, reference->GetHistory()[i].total * energyUnit) << exponent << " " << i;
    }
    EXPECT_EQ(method->GetFinalSSD(), reference->GetFinalSSD() * energyUnit) << exponent;
    EXPECT_EQ(method->GetBeta(), reference->GetBeta() * energyUnit) << exponent;
  }
  EXPECT_LT(reference->GetFinalSSD(), 0.8 * reference->GetHistory().front().ssd); // it registered
}

TEST(FEMRegistrationMethod, MSSDDecreasesOverTheRun)
{
  auto method = SmallRegistration(MeshMode::Dynamic, 30);
  method->Update();
  const auto & h = method->GetHistory();
  // not necessarily monotone step by step (the mesh changes), but clearly decreasing over windows of 10 iterations
  for (size_t i = 10; i < h.size(); i += 10)
  {
    EXPECT_LT(h[i].mssd, h[i - 10].mssd) << "iteration " << i;
  }
  EXPECT_LT(method->GetFinalMSSD(), h.back().mssd);
}

// Far too large steps (energy ratio 2 instead of 0.02): the paper's plain iteration overshoots and the MSSD rises;
// the safeguarded step halves such updates, so the MSSD never increases and the run ends lower.
TEST(FEMRegistrationMethod, SafeguardedStepNeverRaisesTheMSSD)
{
  auto plain = SmallRegistration(MeshMode::Dynamic, 30);
  plain->SetEnergyRatio(2.0);
  plain->SetMaximumStepHalvings(0);
  plain->Update();
  const auto & p = plain->GetHistory();
  size_t       rises = 0;
  for (size_t i = 1; i < p.size(); ++i)
  {
    rises += p[i].mssd > p[i - 1].mssd ? 1 : 0;
    EXPECT_EQ(p[i].stepScale, 1.0);
  }
  EXPECT_GT(rises, 0u) << "the plain iteration should overshoot at this step size";

  auto safe = SmallRegistration(MeshMode::Dynamic, 30);
  safe->SetEnergyRatio(2.0);
  EXPECT_EQ(safe->GetMaximumStepHalvings(), 5u);
  safe->Update();
  const auto & h = safe->GetHistory();
  ASSERT_EQ(h.size(), 30u);
  size_t halved = 0;
  for (size_t i = 1; i < h.size(); ++i)
  {
    EXPECT_LE(h[i].mssd, h[i - 1].mssd) << "iteration " << h[i].iteration;
    halved += h[i].stepScale < 1.0 ? 1 : 0;
  }
  EXPECT_GT(halved, 0u);
  EXPECT_LE(safe->GetFinalMSSD(), h.back().mssd);
  EXPECT_LT(safe->GetFinalMSSD(), plain->GetFinalMSSD());
  std::pair<double, double> range;
  itk::dmr::JacobianDeterminantImage(safe->GetDisplacementField(), range, nullptr);
  EXPECT_GT(range.first, 0.0);
}

TEST(FEMRegistrationMethod, StepsThatDoNotLowerTheMSSDEnoughAreNotTaken)
{
  // Regression test (a fixed bug): a moving image with next to no contrast (a blob at 1e-17) against a fixed blob at
  // 1. The automatic beta makes the first step u = K^-1 f D / (f K^-1 f), which grows like D / |f|: 1.4e16 pixels
  // here. Such a step leaves the MSSD as it was (the moving image adds nothing at double precision), and the
  // safeguard's former test "not larger" took it: the field went to 1e16 pixels, det J to -1e18, with no error. The
  // sufficient-decrease test (1e-4 of the first-order decrease) rejects it and every halving of it, so W stays.
  // At 1e-44 the step is not even finite in single precision: its field is not evaluated (that
  // evaluation threw "alpha is nan").
  for (const auto & [mode, contrast] : { std::make_pair(MeshMode::Regular, 1e-17f),
                                         std::make_pair(MeshMode::Dynamic, 1e-17f),
                                         std::make_pair(MeshMode::Regular, 1e-44f) })
  {
    SCOPED_TRACE(::testing::Message() << (mode == MeshMode::Regular ? "regular, " : "dynamic, ") << contrast);
    auto method = MethodType::New();
    method->SetFixedImage(Blob(64, 56, 30, 28, 16, 12));
    auto moving = Blob(64, 56, 34, 27, 12, 12);
    for (float * v = moving->GetBufferPointer(); v != moving->GetBufferPointer() + 64 * 56; ++v)
    {
      *v *= contrast;
    }
    method->SetMovingImage(moving);
    method->SetNumberOfNodes(30);
    method->SetNumberOfIterations(3);
    method->SetMeshMode(mode);
    method->Update();
    for (const auto & record : method->GetHistory())
    {
      EXPECT_EQ(record.stepScale, 0.0) << "iteration " << record.iteration;
    }
    const auto * field = method->GetDisplacementField();
    double       largest = 0.0;
    for (auto v = field->GetBufferPointer(); v != field->GetBufferPointer() + 64 * 56; ++v)
    {
      largest = std::max(largest, static_cast<double>(v->GetNorm()));
    }
    EXPECT_EQ(largest, 0.0);
    std::pair<double, double> range;
    itk::dmr::JacobianDeterminantImage(field, range, nullptr);
    EXPECT_EQ(range.first, 1.0);
    EXPECT_EQ(range.second, 1.0);
  }
  // the same pair with contrast registers as before: the safeguard takes its full steps
  auto method = SmallRegistration(MeshMode::Regular, 5);
  method->Update();
  for (const auto & record : method->GetHistory())
  {
    EXPECT_EQ(record.stepScale, 1.0) << "iteration " << record.iteration;
  }
}

TEST(FEMRegistrationMethod, RegularAndStaticMeshesLowerSSD)
{
  auto regular = SmallRegistration(MeshMode::Regular, 60);
  regular->SetRegularGridSize(6);
  regular->Update();
  EXPECT_EQ(regular->GetCurrentSimplexMesh().NumberOfNodes(), 36u);
  EXPECT_LT(regular->GetFinalSSD(), 0.5 * regular->GetHistory().front().ssd);

  // the regular mesh, handed back as a user-given static mesh, gives the same registration
  auto staticMethod = SmallRegistration(MeshMode::Static, 60);
  using MeshType = MethodType::MeshType;
  MeshType::ConstPointer mesh = regular->GetCurrentMesh();
  staticMethod->SetStaticMesh(mesh);
  staticMethod->Update();
  EXPECT_NEAR(staticMethod->GetFinalSSD(), regular->GetFinalSSD(), 1e-3 * regular->GetFinalSSD());
}

TEST(FEMRegistrationMethod, TransformOutputWarpsLikeTheField)
{
  auto method = SmallRegistration(MeshMode::Dynamic, 20);
  method->Update();
  auto resample = itk::ResampleImageFilter<ImageType, ImageType, double>::New();
  resample->SetInput(method->GetMovingImage());
  resample->SetTransform(method->GetTransform());
  resample->SetOutputParametersFromImage(method->GetFixedImage());
  resample->Update();
  double       ssd = 0.0;
  const auto * w = resample->GetOutput()->GetBufferPointer();
  const auto * f = method->GetFixedImage()->GetBufferPointer();
  for (size_t p = 0; p < 64 * 56; ++p)
  {
    ssd += (w[p] - f[p]) * (w[p] - f[p]);
  }
  EXPECT_NEAR(ssd, method->GetFinalSSD(), 0.02 * method->GetFinalSSD() + 1e-3);
}

TEST(FEMRegistrationMethod, PhysicalSpaceIsRespected)
{
  // the same pixel data with spacing 0.5 x 2, a rotated direction and an origin: the registration in pixel terms is
  // the same, and the field is the reference field scaled by the spacing and rotated by the direction
  auto reference = SmallRegistration(MeshMode::Regular, 30);
  reference->SetRegularGridSize(6);
  reference->Update();

  auto                   fixed = Blob(64, 56, 30, 28, 16, 12);
  auto                   moving = Blob(64, 56, 34, 27, 12, 12);
  ImageType::SpacingType spacing;
  spacing[0] = 0.5;
  spacing[1] = 2.0;
  ImageType::DirectionType direction;
  const double             a = 0.3;
  direction[0][0] = std::cos(a);
  direction[0][1] = -std::sin(a);
  direction[1][0] = std::sin(a);
  direction[1][1] = std::cos(a);
  ImageType::PointType origin;
  origin[0] = 12.5;
  origin[1] = -40.0;
  for (auto * image : { fixed.GetPointer(), moving.GetPointer() })
  {
    image->SetSpacing(spacing);
    image->SetDirection(direction);
    image->SetOrigin(origin);
  }
  auto method = MethodType::New();
  method->SetFixedImage(fixed);
  method->SetMovingImage(moving);
  method->SetNumberOfIterations(30);
  method->SetMeshMode(MeshMode::Regular);
  method->SetRegularGridSize(6);
  method->Update();
  // intensities are identical per pixel, so the SSD (x pixel volume 1) matches
  EXPECT_NEAR(method->GetFinalSSD(), reference->GetFinalSSD(), 0.05 * reference->GetFinalSSD());
  EXPECT_LT(method->GetFinalSSD(), 0.7 * method->GetHistory().front().ssd);
  // the field points the same way in pixel terms
  const auto *           u = method->GetDisplacementField()->GetBufferPointer();
  const auto *           r = reference->GetDisplacementField()->GetBufferPointer();
  const size_t           p = 28 * 64 + 42; // right edge of the moving blob
  itk::Vector<double, 2> phys;
  phys[0] = u[p][0];
  phys[1] = u[p][1];
  const auto grid = ImageType::DirectionType(direction.GetTranspose()) * phys; // back to the image axes, mm
  EXPECT_GT(std::abs(r[p][0]), 0.2);
  EXPECT_NEAR(grid[0] / spacing[0], r[p][0], 0.35 * std::abs(r[p][0]) + 0.05);
}

TEST(FEMRegistrationMethod, EventsAndAbort)
{
  auto         method = SmallRegistration(MeshMode::Dynamic, 10);
  unsigned int iterations = 0;
  float        lastProgress = -1.0f;
  bool         monotone = true;
  auto         iterationCommand = itk::CStyleCommand::New();
  struct Ctx
  {
    unsigned int * count;
    MethodType *   method;
  } ctx{ &iterations, method.GetPointer() };
  iterationCommand->SetClientData(&ctx);
  iterationCommand->SetCallback([](itk::Object *, const itk::EventObject &, void * d) {
    auto * c = static_cast<Ctx *>(d);
    ++*c->count;
    EXPECT_NE(c->method->GetCurrentMesh(), nullptr);
    if (c->method->GetCurrentIteration() == 4)
    {
      c->method->AbortGenerateDataOn();
    }
  });
  method->AddObserver(itk::IterationEvent(), iterationCommand);
  auto progressCommand = itk::CStyleCommand::New();
  struct PCtx
  {
    float *      last;
    bool *       monotone;
    MethodType * method;
  } pctx{ &lastProgress, &monotone, method.GetPointer() };
  progressCommand->SetClientData(&pctx);
  progressCommand->SetCallback([](itk::Object *, const itk::EventObject &, void * d) {
    auto *      c = static_cast<PCtx *>(d);
    const float p = c->method->GetProgress();
    if (p < *c->last)
    {
      *c->monotone = false;
    }
    *c->last = p;
  });
  method->AddObserver(itk::ProgressEvent(), progressCommand);
  try
  {
    method->Update();
  }
  catch (const itk::ProcessAborted &)
  {
  }
  EXPECT_EQ(iterations, 4u);
  EXPECT_EQ(method->GetHistory().size(), 4u);
  EXPECT_TRUE(monotone);
  EXPECT_EQ(method->GetStopConditionDescription(), "aborted (AbortGenerateData) before iteration 5");
}

// An abort set while an iteration runs (e.g. on Ctrl-C) waited for the end of the iteration: minutes for the first
// iteration of a CT on the CPU. The registration now passes on the CVT's progress reports from inside its loops, and an
// abort set there stops the CVT with ProcessAborted. The method can run again afterwards, to the same result.
TEST(FEMRegistrationMethod, AnAbortDuringTheFirstIterationStopsItFromWithinTheTessellation)
{
  auto method = SmallRegistration(MeshMode::Dynamic, 5);
  struct Context
  {
    MethodType * method;
    unsigned int events;
  } context{ method.GetPointer(), 0 };
  auto observer = itk::CStyleCommand::New();
  observer->SetClientData(&context);
  observer->SetCallback([](itk::Object *, const itk::EventObject &, void * data) {
    auto * c = static_cast<Context *>(data);
    ++c->events;
    c->method->AbortGenerateDataOn(); // at the first report
  });
  method->AddObserver(itk::ProgressEvent(), observer);
  EXPECT_THROW(method->Update(), itk::ProcessAborted);
  EXPECT_EQ(method->GetCurrentIteration(), 1u);
  EXPECT_TRUE(method->GetHistory().empty()); // stopped inside iteration 1
  method->RemoveAllObservers();
  method->Modified();
  ASSERT_NO_THROW(method->Update());
  auto fresh = SmallRegistration(MeshMode::Dynamic, 5);
  fresh->Update();
  EXPECT_EQ(method->GetHistory().size(), 5u);
  EXPECT_EQ(method->GetFinalSSD(), fresh->GetFinalSSD());
}

TEST(FEMRegistrationMethod, BadInputThrows)
{
  auto flat = ImageType::New();
  flat->SetRegions(ImageType::SizeType{ { 32, 32 } });
  flat->Allocate();
  flat->FillBuffer(3.0f);
  auto method = MethodType::New();
  method->SetFixedImage(Blob(32, 32, 16, 16, 8, 8));
  method->SetMovingImage(flat);
  method->SetNumberOfIterations(2);
  EXPECT_THROW(method->Update(), itk::ExceptionObject); // constant image: no force

  auto tooMany = MethodType::New();
  tooMany->SetFixedImage(Blob(8, 8, 4, 4, 2, 2));
  tooMany->SetMovingImage(Blob(8, 8, 4, 4, 3, 3));
  tooMany->SetNumberOfNodes(65);
  EXPECT_THROW(tooMany->Update(), itk::ExceptionObject);

  auto noMesh = SmallRegistration(MeshMode::Static);
  EXPECT_THROW(noMesh->Update(), itk::ExceptionObject);

  auto missingMoving = MethodType::New();
  missingMoving->SetFixedImage(Blob(32, 32, 16, 16, 8, 8));
  EXPECT_THROW(missingMoving->Update(), itk::ExceptionObject);

  // border nodes are fixed: a mesh whose nodes all lie on the border cannot move anything, so it is refused
  auto twoPerAxis = SmallRegistration(MeshMode::Regular, 5);
  twoPerAxis->SetRegularGridSize(2);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(twoPerAxis, { "RegularGridSize (2) must be 0" }));
  auto fiveNodes = SmallRegistration(MeshMode::Regular, 5);
  fiveNodes->SetNumberOfNodes(5); // round(sqrt(5)) = 2 per axis
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
    fiveNodes, { "NumberOfNodes (5) gives a Regular mesh of 2 nodes along axis 0", "at least 3 per axis" }));
  auto threePerAxis = SmallRegistration(MeshMode::Regular, 5);
  threePerAxis->SetRegularGridSize(3); // one free node
  EXPECT_NO_THROW(threePerAxis->Update());
  {
    using MeshType = MethodType::MeshType;
    auto corners = MeshType::New();
    for (unsigned int i = 0; i < 4; ++i)
    {
      MeshType::PointType p;
      p[0] = (i == 1 || i == 2) ? 63.0 : 0.0; // the corners of the 64 x 56 image
      p[1] = i >= 2 ? 55.0 : 0.0;
      corners->SetPoint(i, p);
    }
    for (unsigned int t = 0; t < 2; ++t)
    {
      MeshType::CellAutoPointer cell;
      cell.TakeOwnership(new itk::TriangleCell<MeshType::CellType>);
      cell->SetPointId(0, 0);
      cell->SetPointId(1, t == 0 ? 1 : 2);
      cell->SetPointId(2, t == 0 ? 2 : 3);
      corners->SetCell(t, cell);
    }
    auto cornerMesh = SmallRegistration(MeshMode::Static, 5);
    cornerMesh->SetStaticMesh(corners);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      cornerMesh, { "the static mesh has no free node: all its 4 nodes lie on the border" }));
  }
  // a static mesh must tile the image box (pixel centres first to last): not leave it, not overlap itself
  {
    using MeshType = MethodType::MeshType;
    auto makeMesh = [](const std::vector<std::array<double, 2>> &       points,
                       const std::vector<std::array<unsigned int, 3>> & triangles) {
      auto mesh = MeshType::New();
      for (unsigned int i = 0; i < points.size(); ++i)
      {
        MeshType::PointType p;
        p[0] = points[i][0];
        p[1] = points[i][1];
        mesh->SetPoint(i, p);
      }
      for (unsigned int t = 0; t < triangles.size(); ++t)
      {
        MeshType::CellAutoPointer cell;
        cell.TakeOwnership(new itk::TriangleCell<MeshType::CellType>);
        for (unsigned int k = 0; k < 3; ++k)
        {
          cell->SetPointId(k, triangles[t][k]);
        }
        mesh->SetCell(t, cell);
      }
      return mesh;
    };
    const std::vector<std::array<unsigned int, 3>> fan{ { 0, 1, 4 }, { 1, 2, 4 }, { 2, 3, 4 }, { 3, 0, 4 } };
    auto                                           withMesh = [&](const std::vector<std::array<double, 2>> &       points,
                        const std::vector<std::array<unsigned int, 3>> & triangles) {
      auto method = SmallRegistration(MeshMode::Static, 3);
      method->SetStaticMesh(makeMesh(points, triangles));
      return method;
    };
    // the pixel edges instead of the centres: half a pixel out, so no node would be fixed (a singular system)
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      withMesh({ { -0.5, -0.5 }, { 63.5, -0.5 }, { 63.5, 55.5 }, { -0.5, 55.5 }, { 30, 28 } }, fan),
      { "mesh node 0 lies outside the image box", "by 0.5 pixel" }));
    auto overlapping = fan;
    overlapping.push_back({ 0, 1, 2 });
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      withMesh({ { 0, 0 }, { 63, 0 }, { 63, 55 }, { 0, 55 }, { 30, 28 } }, overlapping),
      { "the mesh's elements overlap", "1.5 times the image box" }));
    // a mesh stored in float: corners a few 1e-5 pixel off the box are put on it and fixed, the centre moves
    auto rounded = withMesh({ { -2e-5, 3e-5 }, { 63.00004, 0 }, { 63, 55.00002 }, { 1e-5, 55 }, { 30, 28 } }, fan);
    EXPECT_NO_THROW(rounded->Update());
    EXPECT_LT(rounded->GetFinalSSD(), rounded->GetHistory().front().ssd);
    const auto & corner = rounded->GetDisplacementField()->GetPixel({ { 63, 55 } });
    EXPECT_EQ(corner.GetNorm(), 0.0);
  }
  // a dynamic mesh of few nodes: every cell touches the border, so every node is fixed; found at the first mesh
  for (const unsigned int nodes : { 4u, 5u })
  {
    auto fewNodes = SmallRegistration(MeshMode::Dynamic, 5);
    fewNodes->SetNumberOfNodes(nodes);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      fewNodes, { "the dynamic mesh has no free node", "all " + std::to_string(nodes) + " cells", "use more nodes" }));
  }
  // a strip: 40 cells along it, and the dual mesh has a node at image corners that no cell holds (the message counted
  // the mesh's 42 nodes as cells)
  {
    auto strip = MethodType::New();
    strip->SetFixedImage(Blob(300, 8, 150, 4, 3, 3));
    strip->SetMovingImage(Blob(300, 8, 152, 4, 3, 3));
    strip->SetNumberOfNodes(40);
    strip->SetNumberOfIterations(2);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(strip, { "has no free node: all 40 cells" }));
  }

  // a mask is read pixel for pixel with the fixed image: one that is not on its grid is refused, with the reason
  for (const int what : { 0, 1 })
  {
    auto mask = MethodType::MaskImageType::New();
    mask->SetRegions(MethodType::MaskImageType::SizeType{ { 32, 32 } });
    if (what == 0)
    {
      MethodType::MaskImageType::PointType origin;
      origin[0] = 1.5;
      origin[1] = 0.0;
      mask->SetOrigin(origin);
    }
    else
    {
      auto region = mask->GetLargestPossibleRegion();
      region.SetIndex(1, 2);
      mask->SetRegions(region);
    }
    mask->Allocate();
    mask->FillBuffer(1);
    auto masked = MethodType::New();
    masked->SetFixedImage(Blob(32, 32, 16, 16, 8, 8));
    masked->SetMovingImage(Blob(32, 32, 17, 16, 8, 8));
    masked->SetNumberOfNodes(10);
    masked->SetFixedMask(mask);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(masked,
                                                       { "FEMRegistrationMethod",
                                                         "the fixed mask must lie on the fixed image grid",
                                                         what == 0 ? "its origin" : "starts at" }));
  }

  // a NaN or an infinite intensity: an error naming the image and the pixel, on either back-end, before any work
  for (const float bad : { std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity() })
  {
    for (const bool inFixed : { true, false })
    {
      auto image = Blob(32, 32, 16, 16, 8, 8);
      image->SetPixel({ { 7, 5 } }, bad);
      auto nonFinite = MethodType::New();
      nonFinite->SetFixedImage(inFixed ? image : Blob(32, 32, 16, 16, 8, 8));
      nonFinite->SetMovingImage(inFixed ? Blob(32, 32, 17, 16, 8, 8) : image);
      nonFinite->SetNumberOfNodes(10);
      nonFinite->SetNumberOfIterations(2);
      EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
        nonFinite, { std::string("the ") + (inFixed ? "fixed" : "moving") + " image has a non-finite", "[7, 5]" }));
    }
  }
}

// The method turns physical vectors into the grid frame with the direction's transpose, its inverse only for a rotation
// or reflection; ITK and MetaImage headers allow any matrix, and a sheared or scaled direction gave another field
// without a word. It is refused; rounding in the direction cosines (as headers store them) is not.
// NaN passes itkSetClampMacro and infinity is clamped to the largest double: a NaN EnergyRatio gave beta NaN and a run
// that moved nothing, an infinite Lambda the stop condition "the images already match", an infinite EnergyRatio a NaN
// density. Such values, and values beyond LargestParameterValue, are refused with the parameter's name.
TEST(FEMRegistrationMethod, ParametersThatAreNotFiniteOrFarTooLargeAreRefused)
{
  const double nan = std::numeric_limits<double>::quiet_NaN(), inf = std::numeric_limits<double>::infinity();
  using Setter = void (MethodType::*)(double);
  for (const auto & [name, set] : { std::make_pair("Lambda", static_cast<Setter>(&MethodType::SetLambda)),
                                    std::make_pair("Mu", static_cast<Setter>(&MethodType::SetMu)),
                                    std::make_pair("EnergyRatio", static_cast<Setter>(&MethodType::SetEnergyRatio)),
                                    std::make_pair("AlphaFactor", static_cast<Setter>(&MethodType::SetAlphaFactor)) })
  {
    for (const double value : { nan, inf, 1e31 })
    {
      auto method = SmallRegistration(MeshMode::Dynamic, 2);
      ((*method).*set)(value);
      EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
        method, { std::string(name) + " must be a finite number of at most 1e+30" }))
        << name << " = " << value;
    }
  }
  auto method = SmallRegistration(MeshMode::Dynamic, 2);
  method->SetCVTEpsilon(nan);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "CVTEpsilon must be a number in [0, 1]" }));
  method = SmallRegistration(MeshMode::Dynamic, 2);
  method->SetSolverTolerance(nan);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "SolverTolerance must be a number in [1e-16, 1e-2]" }));
  // at the bound, the elastic constants scaled together give the run of the default ones: beta absorbs the scale
  auto reference = SmallRegistration(MeshMode::Dynamic, 10);
  reference->Update();
  auto scaled = SmallRegistration(MeshMode::Dynamic, 10);
  scaled->SetLambda(MethodType::LargestParameterValue);
  scaled->SetMu(MethodType::LargestParameterValue);
  scaled->Update();
  EXPECT_NEAR(scaled->GetFinalSSD(), reference->GetFinalSSD(), 1e-6 * reference->GetFinalSSD());
}

TEST(FEMRegistrationMethod, CoordinatesThatCannotTellThePixelsApartAreRefused)
{
  // the same pair moved far from the origin: 1e9 mm registers as at the origin; at 1e16 mm, where double precision
  // resolves only 2 mm, the run reported a folded field (det J -5.8) with 1 mm pixels, and is refused now
  auto reference = SmallRegistration(MeshMode::Dynamic, 10);
  reference->Update();
  auto movedTo = [](ImageType::Pointer image, double far) {
    ImageType::PointType origin;
    origin[0] = far;
    origin[1] = -far;
    image->SetOrigin(origin);
    return image;
  };
  auto method = SmallRegistration(MeshMode::Dynamic, 10);
  method->SetFixedImage(movedTo(Blob(64, 56, 30, 28, 16, 12), 1e9));
  method->SetMovingImage(movedTo(Blob(64, 56, 34, 27, 12, 12), 1e9));
  method->Update();
  EXPECT_NEAR(method->GetFinalSSD(), reference->GetFinalSSD(), 1e-6 * reference->GetFinalSSD());
  for (const bool inFixed : { true, false })
  {
    auto far = SmallRegistration(MeshMode::Dynamic, 10);
    (inFixed ? far->SetFixedImage(movedTo(Blob(64, 56, 30, 28, 16, 12), 1e16))
             : far->SetMovingImage(movedTo(Blob(64, 56, 34, 27, 12, 12), 1e16)));
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      far,
      { "FEMRegistrationMethod",
        std::string("the ") + (inFixed ? "fixed" : "moving") + " image's physical coordinates reach 1e+16 mm",
        "resolves only 2 mm" }));
  }
}

TEST(FEMRegistrationMethod, SpacingsThatSinglePrecisionCannotHoldAreRefused)
{
  // The fields are floats in mm. Spacings of 2^-100 and 2^100 mm (about 8e-31 and 1.3e30) register like 1 mm; a
  // spacing of 1e-45 mm gave a "registration" that moved nothing (det J 1, SSD unchanged) and 3e38 mm a NaN density.
  auto reference = SmallRegistration(MeshMode::Dynamic, 20);
  reference->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
  reference->Update();
  const auto spaced = [](ImageType::Pointer image, double spacing) {
    ImageType::SpacingType s;
    s.Fill(spacing);
    image->SetSpacing(s);
    return image;
  };
  const size_t n = reference->GetFixedImage()->GetLargestPossibleRegion().GetNumberOfPixels();
  for (const int exponent : { -100, 100 })
  {
    const double spacing = std::ldexp(1.0, exponent);
    auto         method = SmallRegistration(MeshMode::Dynamic, 20);
    method->SetFixedImage(spaced(Blob(64, 56, 30, 28, 16, 12), spacing));
    method->SetMovingImage(spaced(Blob(64, 56, 34, 27, 12, 12), spacing));
    method->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
    ASSERT_NO_THROW(method->Update()) << exponent;
    // the same registration in pixel units (a power of two only moves exponents): the field in pixels and the SSD in
    // the images' area unit agree to rounding
    const auto * a = reference->GetDisplacementField()->GetBufferPointer();
    const auto * b = method->GetDisplacementField()->GetBufferPointer();
    double       largest = 0.0;
    for (size_t p = 0; p < n; ++p)
    {
      for (unsigned int k = 0; k < 2; ++k)
      {
        largest = std::max(largest, std::abs(b[p][k] / spacing - a[p][k]));
      }
    }
    EXPECT_LT(largest, 1e-6) << exponent;
    EXPECT_NEAR(method->GetFinalSSD() / (spacing * spacing), reference->GetFinalSSD(), 1e-6 * reference->GetFinalSSD())
      << exponent;
  }
  EXPECT_LT(reference->GetFinalSSD(), 0.8 * reference->GetHistory().front().ssd); // it registered
  for (const bool inFixed : { true, false })
  {
    for (const double spacing : { 1e-34, 1e-45, 1e33, 3e38 })
    {
      auto method = SmallRegistration(MeshMode::Dynamic, 20);
      (inFixed ? method->SetFixedImage(spaced(Blob(64, 56, 30, 28, 16, 12), spacing))
               : method->SetMovingImage(spaced(Blob(64, 56, 34, 27, 12, 12), spacing)));
      EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
        method,
        { "FEMRegistrationMethod",
          std::string("the ") + (inFixed ? "fixed" : "moving") + " image's spacing",
          spacing < 1 ? "is below 1.17" : "makes an extent of",
          "single-precision fields" }))
        << spacing;
    }
  }
}

TEST(FEMRegistrationMethod, CoordinatesThatAreNotFiniteAreRefused)
{
  // std::max passes over a NaN, so a NaN origin slipped through the check of the coordinates' resolution
  for (const double bad : { std::nan(""), std::numeric_limits<double>::infinity() })
  {
    auto                 method = SmallRegistration(MeshMode::Dynamic, 2);
    auto                 image = Blob(64, 56, 30, 28, 16, 12);
    ImageType::PointType origin;
    origin[0] = 0.0;
    origin[1] = bad;
    image->SetOrigin(origin);
    method->SetMovingImage(image);
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
      method, { "FEMRegistrationMethod", "the moving image's physical coordinates are not finite numbers" }))
      << bad;
  }
}

TEST(FEMRegistrationMethod, ADirectionThatIsNotARotationIsRefused)
{
  for (const bool inFixed : { true, false })
  {
    for (const double shear : { 0.4, 2e-3 })
    {
      ImageType::DirectionType sheared;
      sheared.SetIdentity();
      sheared[0][1] = shear;
      auto image = Blob(64, 56, 30, 28, 16, 12);
      image->SetDirection(sheared);
      auto method = SmallRegistration(MeshMode::Dynamic, 2);
      (inFixed ? method->SetFixedImage(image) : method->SetMovingImage(image));
      EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(
        method,
        { "FEMRegistrationMethod",
          std::string("the ") + (inFixed ? "fixed" : "moving") + " image's direction matrix",
          "not orthonormal" }))
        << "shear " << shear;
    }
    ImageType::DirectionType scaled;
    scaled.SetIdentity();
    scaled[1][1] = 2.0;
    auto image = Blob(64, 56, 30, 28, 16, 12);
    image->SetDirection(scaled);
    auto method = SmallRegistration(MeshMode::Dynamic, 2);
    (inFixed ? method->SetFixedImage(image) : method->SetMovingImage(image));
    EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "not orthonormal", "up to 3" }));
  }
  // a rotation whose cosines are rounded to 5 decimals (as a DICOM header may store them) is accepted and registers
  const double             angle = 0.3;
  ImageType::DirectionType rounded;
  rounded[0][0] = rounded[1][1] = std::round(std::cos(angle) * 1e5) / 1e5;
  rounded[0][1] = -std::round(std::sin(angle) * 1e5) / 1e5;
  rounded[1][0] = -rounded[0][1];
  auto fixed = Blob(64, 56, 30, 28, 16, 12), moving = Blob(64, 56, 34, 27, 12, 12);
  fixed->SetDirection(rounded);
  moving->SetDirection(rounded);
  const double error = itk::dmr::DirectionOrthonormalityError<2>(fixed.GetPointer());
  EXPECT_GT(error, 0.0);
  EXPECT_LT(error, 1e-5);
  auto method = SmallRegistration(MeshMode::Dynamic, 5);
  method->SetFixedImage(fixed);
  method->SetMovingImage(moving);
  ASSERT_NO_THROW(method->Update());
  EXPECT_LT(method->GetFinalSSD(), method->GetHistory().front().ssd);
}

TEST(FEMRegistrationMethod, IdenticalImagesStopWithZeroField)
{
  auto method = MethodType::New();
  method->SetFixedImage(Blob(40, 40, 20, 20, 9, 9));
  method->SetMovingImage(Blob(40, 40, 20, 20, 9, 9));
  method->SetNumberOfIterations(5);
  method->Update();
  EXPECT_LE(method->GetHistory().size(), 1u);
  EXPECT_NE(method->GetStopConditionDescription().find("the images already match"), std::string::npos)
    << method->GetStopConditionDescription();
  const auto * u = method->GetDisplacementField()->GetBufferPointer();
  double       maxU = 0.0;
  for (size_t p = 0; p < 40 * 40; ++p)
  {
    maxU = std::max({ maxU, std::abs(double(u[p][0])), std::abs(double(u[p][1])) });
  }
  EXPECT_LT(maxU, 1e-3);
}

TEST(FEMRegistrationMethod, ALaterDynamicMeshWithoutAFreeNodeEndsTheRunWithTheTransformationReached)
{
  // On a strip 4 pixels high every cell touches the border sooner or later: at iteration 1 there is a free node (the
  // run starts), a later tessellation has none, and the run ends there with the transformation of the iteration
  // before (nothing can move on that mesh), saying so.
  auto strip = [](double cx) {
    auto image = ImageType::New();
    image->SetRegions(ImageType::SizeType{ { 400, 4 } });
    image->Allocate();
    for (unsigned int y = 0; y < 4; ++y)
    {
      for (unsigned int x = 0; x < 400; ++x)
      {
        const double r = std::sqrt(std::pow((x - cx) / 100.0, 2) + std::pow((y - 1.5) / 3.0, 2));
        image->SetPixel({ { x, y } }, static_cast<float>(255.0 / (1.0 + std::exp((r - 1.0) * 20.0))));
      }
    }
    return image;
  };
  auto method = MethodType::New();
  method->SetFixedImage(strip(200));
  method->SetMovingImage(strip(210));
  method->SetNumberOfNodes(100);
  method->SetNumberOfIterations(20);
  method->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CPU);
  ASSERT_NO_THROW(method->Update());
  const auto & history = method->GetHistory();
  ASSERT_GE(history.size(), 2u);
  ASSERT_LT(history.size(), 20u) << "the strip's tessellations all had a free node: the case no longer tests this";
  const std::string why = method->GetStopConditionDescription();
  EXPECT_NE(why.find("the dynamic mesh of iteration " + std::to_string(history.size()) + " has no free node"),
            std::string::npos)
    << why;
  EXPECT_EQ(history.back().stepScale, 0.0);              // no step on the last mesh
  EXPECT_LT(method->GetFinalSSD(), history.front().ssd); // the iterations before it registered
  EXPECT_EQ(method->GetFinalSSD(), history.back().ssd);  // and the last one kept their transformation
}

TEST(FEMRegistrationMethod, BackendWithoutDevice)
{
  if (itk::dmr::cuda::DeviceAvailable())
  {
    GTEST_SKIP() << "a CUDA device is present (test/Cuda compares the back-ends)";
  }
  // CUDA requested: a clear exception naming the reason, no output
  auto cuda = SmallRegistration(MeshMode::Dynamic, 3);
  cuda->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::CUDA);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(cuda, { "CUDA back-end was requested but" }));
  // Auto: the CPU path, and it says so
  auto autoBackend = SmallRegistration(MeshMode::Dynamic, 3);
  autoBackend->SetBackend(itk::DynamicMeshRegistrationEnums::Backend::Auto);
  autoBackend->Update();
  EXPECT_EQ(autoBackend->GetBackendUsed(), itk::DynamicMeshRegistrationEnums::Backend::CPU);
  EXPECT_EQ(autoBackend->GetDeviceBytes(), 0u);
  EXPECT_EQ(autoBackend->GetDevicePeakBytes(), 0u);
  EXPECT_EQ(autoBackend->GetDeviceUsedAtPeakBytes(), 0u);
  EXPECT_LT(autoBackend->GetFinalSSD(), autoBackend->GetHistory().front().ssd);
}

// Regression test (a fixed bug): the moving image was sampled at its continuous index without taking off the start
// of its region, so images whose region does not start at 0 (as CropImageFilter and ExtractImageFilter leave them)
// were registered as if shifted by that start. Sizes 65 x 57 (1 more than a multiple of 4): the pyramid's shrunk
// grids then keep the same pixels whatever the start (ShrinkImageFilter rounds a half-pixel offset otherwise).
TEST(FEMRegistrationMethod, RegionsThatDoNotStartAtZeroGiveTheSameRegistration)
{
  auto run = [](ImageType * fixed, ImageType * moving) {
    auto method = MethodType::New();
    method->SetFixedImage(fixed);
    method->SetMovingImage(moving);
    method->SetNumberOfNodes(30);
    method->SetNumberOfIterations(20);
    method->SetMeshMode(MeshMode::Dynamic);
    method->Update();
    return method;
  };
  auto       fixed = Blob(65, 57, 30, 28, 16, 12);
  auto       moving = Blob(65, 57, 34, 27, 12, 12);
  const auto reference = run(fixed, moving);
  const auto referenceField = reference->GetDisplacementField();
  EXPECT_LT(reference->GetFinalSSD(), 0.7 * reference->GetHistory().front().ssd);
  for (const auto & start : { std::array<int, 2>{ 7, -3 }, std::array<int, 2>{ -12, 5 } })
  {
    ImageType::IndexType index;
    index[0] = start[0];
    index[1] = start[1];
    auto shiftedFixed = Blob(65, 57, 30, 28, 16, 12);
    auto shiftedMoving = Blob(65, 57, 34, 27, 12, 12);
    itk::dmr::test::ShiftRegionStart(shiftedFixed.GetPointer(), index);
    itk::dmr::test::ShiftRegionStart(shiftedMoving.GetPointer(), index);
    const auto method = run(shiftedFixed, shiftedMoving);
    const auto field = method->GetDisplacementField();
    EXPECT_EQ(field->GetLargestPossibleRegion(), shiftedFixed->GetLargestPossibleRegion());
    EXPECT_EQ(field->GetBufferedRegion(), shiftedFixed->GetLargestPossibleRegion());
    EXPECT_EQ(field->GetOrigin(), shiftedFixed->GetOrigin());
    EXPECT_NEAR(method->GetFinalSSD(), reference->GetFinalSSD(), 1e-9 * reference->GetFinalSSD());
    // the same field pixel for pixel (the mesh nodes go through physical space and back: rounding only)
    double maxDiff = 0.0;
    for (size_t p = 0; p < 65 * 57; ++p)
    {
      maxDiff = std::max(maxDiff, (field->GetBufferPointer()[p] - referenceField->GetBufferPointer()[p]).GetNorm());
    }
    EXPECT_LE(maxDiff, 1e-6);
    // and the transforms map the same physical points
    ImageType::PointType x;
    x[0] = 40.3;
    x[1] = 27.7;
    const auto a = method->GetTransform()->TransformPoint(x);
    const auto b = reference->GetTransform()->TransformPoint(x);
    EXPECT_GT(b.EuclideanDistanceTo(x), 0.1);
    EXPECT_NEAR(a.EuclideanDistanceTo(b), 0.0, 1e-6);
  }
}

// Regression test (a fixed bug): the method promises a moving image on any grid (sampled through physical space), but
// its density filter inherited ImageToImageFilter's rule that all inputs share the fixed image's physical space and
// threw "Inputs do not occupy the same physical space". Here the moving image is the same function of the physical
// point on a larger grid with another origin, whose pixels fall on the fixed image's pixels (one level: no pyramid, so
// the samples are the same; only the moving gradient at the old border and samples beyond it may differ, where the
// blob is about 0).
TEST(FEMRegistrationMethod, MovingImageOnAnotherGrid)
{
  auto run = [](ImageType * moving, unsigned int levels) {
    auto method = MethodType::New();
    method->SetFixedImage(Blob(64, 56, 30, 28, 16, 12));
    method->SetMovingImage(moving);
    method->SetNumberOfNodes(30);
    method->SetNumberOfIterations(20);
    method->SetNumberOfLevels(levels);
    method->Update();
    return method;
  };
  const auto           reference = run(Blob(64, 56, 34, 27, 12, 12), 1);
  auto                 padded = Blob(64 + 8, 56 + 6, 34 + 3, 27 + 2, 12, 12); // 3 pixels more on the left, 2 below
  ImageType::PointType origin;
  origin[0] = -3.0;
  origin[1] = -2.0;
  padded->SetOrigin(origin);
  const auto method = run(padded, 1);
  EXPECT_LT(reference->GetFinalSSD(), 0.7 * reference->GetHistory().front().ssd);
  EXPECT_NEAR(
    method->GetHistory().front().ssd, reference->GetHistory().front().ssd, 1e-6 * reference->GetHistory().front().ssd);
  EXPECT_NEAR(method->GetFinalSSD(), reference->GetFinalSSD(), 1e-3 * reference->GetFinalSSD());
  double maxDiff = 0.0, maxU = 0.0;
  for (size_t p = 0; p < 64 * 56; ++p)
  {
    const auto & u = reference->GetDisplacementField()->GetBufferPointer()[p];
    maxU = std::max(maxU, static_cast<double>(u.GetNorm()));
    maxDiff = std::max(maxDiff, (method->GetDisplacementField()->GetBufferPointer()[p] - u).GetNorm());
  }
  EXPECT_GT(maxU, 0.5);
  EXPECT_LE(maxDiff, 1e-3 * maxU);

  // a rotated, finer moving grid with the pyramid: the same shapes, registered as well
  auto       fine = ImageType::New();
  const auto direction = itk::dmr::test::RotationDirection2D<ImageType>(0.4);
  fine->SetRegions(ImageType::SizeType{ { 150, 140 } });
  ImageType::SpacingType spacing;
  spacing[0] = 0.6;
  spacing[1] = 0.7;
  fine->SetSpacing(spacing);
  fine->SetDirection(direction);
  ImageType::PointType fineOrigin;
  fineOrigin[0] = 20.0;
  fineOrigin[1] = -25.0;
  fine->SetOrigin(fineOrigin);
  fine->Allocate();
  itk::ImageRegionIteratorWithIndex<ImageType> it(fine, fine->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    ImageType::PointType x;
    fine->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const double r = std::sqrt(std::pow((x[0] - 34) / 12, 2) + std::pow((x[1] - 27) / 12, 2));
    it.Set(static_cast<float>(1.0 / (1.0 + std::exp((r - 1.0) * 8.0))));
  }
  const auto onThreeLevels = run(Blob(64, 56, 34, 27, 12, 12), 3);
  const auto fineMethod = run(fine, 3);
  EXPECT_NEAR(fineMethod->GetHistory().front().ssd,
              onThreeLevels->GetHistory().front().ssd,
              0.02 * onThreeLevels->GetHistory().front().ssd);
  EXPECT_LT(fineMethod->GetFinalSSD(), 0.7 * fineMethod->GetHistory().front().ssd);
  EXPECT_NEAR(fineMethod->GetFinalSSD(), onThreeLevels->GetFinalSSD(), 0.25 * onThreeLevels->GetFinalSSD());
}

// Registrations of a batch pipeline may run side by side on threads of one process: they share no state (the TetGen
// runs of 3D meshes are serialised inside the library), so each gives, bit for bit, what it gives alone. ITK's own
// globals are created on first use without a lock (see the tools' dmrtools::InitializeItkGlobals), so the sequential
// runs come first, on this thread.
TEST(FEMRegistrationMethod, ConcurrentRegistrationsGiveTheirSequentialResults)
{
  using Image3DType = itk::Image<float, 3>;
  using Method3DType = itk::FEMRegistrationMethod<Image3DType, Image3DType>;
  auto blob3D = [](double cx, double rx) {
    auto image = Image3DType::New();
    image->SetRegions(Image3DType::SizeType{ { 24, 22, 20 } });
    image->Allocate();
    for (unsigned int z = 0; z < 20; ++z)
    {
      for (unsigned int y = 0; y < 22; ++y)
      {
        for (unsigned int x = 0; x < 24; ++x)
        {
          const double r =
            std::sqrt(std::pow((x - cx) / rx, 2) + std::pow((y - 11.0) / 6.0, 2) + std::pow((z - 10.0) / 5.0, 2));
          image->SetPixel({ { x, y, z } }, static_cast<float>(1.0 / (1.0 + std::exp((r - 1.0) * 6.0))));
        }
      }
    }
    return image;
  };
  auto run2D = [](int which) {
    auto method = SmallRegistration(which == 1 ? MeshMode::Regular : MeshMode::Dynamic, 15);
    if (which == 2)
    {
      method->SetMovingImage(Blob(64, 56, 28, 30, 14, 10));
      method->SetNumberOfNodes(45);
    }
    method->Update();
    return std::vector<float>(method->GetDisplacementField()->GetBufferPointer()->GetDataPointer(),
                              method->GetDisplacementField()->GetBufferPointer()->GetDataPointer() + 64 * 56 * 2);
  };
  auto run3D = [&blob3D](int which) {
    auto method = Method3DType::New();
    method->SetFixedImage(blob3D(11.0, 6.0));
    method->SetMovingImage(which == 0 ? blob3D(12.5, 5.0) : blob3D(10.0, 7.0));
    method->SetNumberOfNodes(150);
    method->SetNumberOfIterations(8);
    method->Update();
    const auto * u = method->GetDisplacementField()->GetBufferPointer()->GetDataPointer();
    return std::vector<float>(u, u + 24 * 22 * 20 * 3);
  };
  constexpr int                   runs = 5; // three 2D runs and two 3D runs
  std::vector<std::vector<float>> alone(runs), together(runs);
  auto                            runOne = [&](int i) { return i < 3 ? run2D(i) : run3D(i - 3); };
  for (int i = 0; i < runs; ++i)
  {
    alone[i] = runOne(i);
  }
  std::vector<std::thread> threads;
  std::vector<std::string> errors(runs);
  for (int i = 0; i < runs; ++i)
  {
    threads.emplace_back([&, i] {
      try
      {
        together[i] = runOne(i);
      }
      catch (const std::exception & e)
      {
        errors[i] = e.what();
      }
    });
  }
  for (auto & t : threads)
  {
    t.join();
  }
  for (int i = 0; i < runs; ++i)
  {
    EXPECT_EQ(errors[i], "") << "run " << i;
    const float maxU = std::abs(
      *std::max_element(alone[i].begin(), alone[i].end(), [](float a, float b) { return std::abs(a) < std::abs(b); }));
    EXPECT_GT(maxU, 0.05f) << "run " << i << " did not register";
    EXPECT_TRUE(alone[i] == together[i]) << "run " << i << " differs when run beside the others";
  }
}

namespace
{
/** fixed: an elliptic blob at x = 30; moving: a round blob at x = movingCentre (index axis 0); both on a rotated,
 * anisotropic grid (the initial field is physical, so a frame mix-up shows). */
std::array<ImageType::Pointer, 2>
ShiftedPair(unsigned int movingCentre)
{
  std::array<ImageType::Pointer, 2> pair{ Blob(112, 72, 30, 36, 14, 10), Blob(112, 72, movingCentre, 36, 12, 12) };
  for (auto & image : pair)
  {
    ImageType::SpacingType spacing;
    spacing[0] = 0.8;
    spacing[1] = 1.1;
    image->SetSpacing(spacing);
    image->SetDirection(itk::dmr::test::RotationDirection2D<ImageType>(0.5));
    ImageType::PointType origin;
    origin[0] = -12.0;
    origin[1] = 7.5;
    image->SetOrigin(origin);
  }
  return pair;
}

/** The physical displacement of `pixels` pixels along index axis 0 of `image`, on its grid. */
MethodType::DisplacementFieldType::Pointer
IndexShiftField(const ImageType * image, double pixels)
{
  auto field = MethodType::DisplacementFieldType::New();
  field->CopyInformation(image);
  field->SetRegions(image->GetLargestPossibleRegion());
  field->Allocate();
  MethodType::DisplacementFieldType::PixelType u;
  for (unsigned int r = 0; r < 2; ++r)
  {
    u[r] = static_cast<float>(image->GetDirection()[r][0] * image->GetSpacing()[0] * pixels);
  }
  field->FillBuffer(u);
  return field;
}
} // namespace

// A pre-alignment (here a translation of 32 pixels, far beyond the capture range: the blobs do not overlap) given as
// the initial field: the run is the registration of the pre-shifted moving image, composed onto the shift. A regular
// mesh makes the two runs comparable pixel for pixel (no tessellation to amplify rounding); the dynamic mesh shows
// the use: without the initial field the blobs stay apart.
TEST(FEMRegistrationMethod, AnInitialFieldIsWhereTheRegistrationStarts)
{
  constexpr unsigned int shift = 32;
  const auto             shifted = ShiftedPair(30 + shift);
  const auto             aligned = ShiftedPair(30);
  const auto             initial = IndexShiftField(shifted[0], shift);
  auto                   run = [](const std::array<ImageType::Pointer, 2> & pair,
                const MethodType::DisplacementFieldType * initialField,
                MeshMode                                  mode) {
    auto method = MethodType::New();
    method->SetFixedImage(pair[0]);
    method->SetMovingImage(pair[1]);
    method->SetInitialDisplacementField(initialField);
    method->SetNumberOfNodes(36);
    method->SetNumberOfIterations(30);
    method->SetEnergyRatio(0.1);
    method->SetMeshMode(mode);
    method->Update();
    return method;
  };
  const auto withInitial = run(shifted, initial, MeshMode::Regular);
  const auto preShifted = run(aligned, nullptr, MeshMode::Regular);
  EXPECT_NEAR(withInitial->GetHistory().front().ssd,
              preShifted->GetHistory().front().ssd,
              1e-4 * preShifted->GetHistory().front().ssd);
  EXPECT_LT(preShifted->GetFinalSSD(), 0.5 * preShifted->GetHistory().front().ssd); // it registered
  const size_t n = shifted[0]->GetLargestPossibleRegion().GetNumberOfPixels();
  const auto * u = withInitial->GetDisplacementField()->GetBufferPointer();
  const auto * v = preShifted->GetDisplacementField()->GetBufferPointer();
  const auto   u0 = initial->GetBufferPointer()[0];
  double       maxDifference = 0.0, maxV = 0.0, maxBorder = 0.0;
  for (size_t p = 0; p < n; ++p)
  {
    maxDifference = std::max(maxDifference, static_cast<double>((u[p] - u0 - v[p]).GetNorm()));
    maxV = std::max(maxV, static_cast<double>(v[p].GetNorm()));
    const size_t x = p % 112, y = p / 112;
    if (x == 0 || y == 0 || x == 111 || y == 71)
    {
      // the border nodes are fixed: the border keeps W_0
      maxBorder = std::max(maxBorder, static_cast<double>((u[p] - u0).GetNorm()));
    }
  }
  std::cout << "initial 32 px shift: SSD " << withInitial->GetHistory().front().ssd << " -> "
            << withInitial->GetFinalSSD() << "; field - u0 against the pre-shifted run's field (max " << maxV
            << " mm): " << maxDifference << " mm; border " << maxBorder << " mm" << std::endl;
  EXPECT_GT(maxV, 1.0);
  EXPECT_LT(maxDifference, 1e-3 * maxV);
  EXPECT_LT(maxBorder, 1e-4);

  const auto dynamicWith = run(shifted, initial, MeshMode::Dynamic);
  const auto dynamicWithout = run(shifted, nullptr, MeshMode::Dynamic);
  std::cout << "dynamic mesh: final SSD " << dynamicWith->GetFinalSSD() << " with the initial field, "
            << dynamicWithout->GetFinalSSD() << " without (start " << dynamicWithout->GetHistory().front().ssd << ")"
            << std::endl;
  EXPECT_LT(dynamicWith->GetFinalSSD(), 0.5 * dynamicWith->GetHistory().front().ssd);
  EXPECT_LT(dynamicWith->GetFinalSSD(), 0.2 * dynamicWithout->GetFinalSSD());
}

TEST(FEMRegistrationMethod, AnInitialFieldOffTheFixedGridOrNotFiniteIsRefused)
{
  auto method = SmallRegistration(MeshMode::Regular, 2);
  auto other = Blob(64, 50, 30, 28, 16, 12);
  method->SetInitialDisplacementField(IndexShiftField(other, 1.0));
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "initial displacement field", "size" }));
  auto field = IndexShiftField(method->GetFixedImage(), 1.0);
  auto origin = field->GetOrigin();
  origin[1] += 0.5;
  field->SetOrigin(origin);
  method->SetInitialDisplacementField(field);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "initial displacement field", "origin" }));
  field = IndexShiftField(method->GetFixedImage(), 1.0);
  field->GetBufferPointer()[100][1] = std::numeric_limits<float>::quiet_NaN();
  method->SetInitialDisplacementField(field);
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "initial displacement field", "non-finite" }));
  method->SetInitialDisplacementField(nullptr);
  EXPECT_NO_THROW(method->Update());
}

namespace
{
/** |a(x) + b(x + a(x))| in pixels (of the larger spacing) at every pixel x whose image x + a(x) lies inside b's grid:
 * {mean, max}. Zero when b is the inverse of a. */
std::pair<double, double>
InverseConsistency(const MethodType::DisplacementFieldType * a, const MethodType::DisplacementFieldType * b)
{
  using FieldType = MethodType::DisplacementFieldType;
  auto interpolator = itk::VectorLinearInterpolateImageFunction<FieldType>::New();
  interpolator->SetInputImage(b);
  const double spacing = std::max(a->GetSpacing()[0], a->GetSpacing()[1]);
  double       sum = 0.0, largest = 0.0;
  size_t       count = 0;
  for (itk::ImageRegionConstIteratorWithIndex<FieldType> it(a, a->GetLargestPossibleRegion()); !it.IsAtEnd(); ++it)
  {
    FieldType::PointType x;
    a->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const auto u = it.Get();
    for (unsigned int k = 0; k < 2; ++k)
    {
      x[k] += u[k];
    }
    if (!interpolator->IsInsideBuffer(x))
    {
      continue;
    }
    const auto   v = interpolator->Evaluate(x);
    const double e = std::hypot(u[0] + v[0], u[1] + v[1]) / spacing;
    sum += e;
    largest = std::max(largest, e);
    ++count;
  }
  return { count ? sum / static_cast<double>(count) : 0.0, largest };
}
} // namespace

// ComputeInverse carries W^-1 along the iterations (W^-1 <- exp(-s u) o W^-1). On a pair that needs a large
// deformation (an ellipse lying across x to one lying along y, up to 16 px), the inverse undoes the transformation
// both ways to about a tenth of a pixel on average (the forward field is resampled at every composition, the inverse
// is not, and where the field compresses a small offset is magnified: the largest errors are about a pixel), five and
// more times better than taking -u as the inverse; the transform output's GetInverseTransform() maps points back, and
// the option leaves the registration itself as it was, bit for bit.
TEST(FEMRegistrationMethod, TheInverseUndoesTheTransformation)
{
  auto run = [](bool inverse, MeshMode mode) {
    auto method = MethodType::New();
    method->SetFixedImage(Blob(96, 80, 48, 40, 28, 14));
    method->SetMovingImage(Blob(96, 80, 46, 40, 15, 24));
    method->SetNumberOfNodes(40);
    method->SetNumberOfIterations(80);
    method->SetEnergyRatio(0.1);
    method->SetMeshMode(mode);
    method->SetComputeInverse(inverse);
    method->Update();
    return method;
  };
  for (const MeshMode mode : { MeshMode::Dynamic, MeshMode::Regular })
  {
    const auto   plain = run(false, mode);
    const auto   both = run(true, mode);
    const auto * u = both->GetDisplacementField();
    const auto * v = both->GetInverseDisplacementField();
    EXPECT_EQ(plain->GetInverseDisplacementField(), nullptr);
    ASSERT_NE(v, nullptr);
    EXPECT_EQ(v->GetLargestPossibleRegion(), u->GetLargestPossibleRegion());
    EXPECT_EQ(v->GetSpacing(), u->GetSpacing());
    EXPECT_EQ(v->GetOrigin(), u->GetOrigin());
    const size_t n = u->GetLargestPossibleRegion().GetNumberOfPixels();
    auto         negated = MethodType::DisplacementFieldType::New(); // -u: the inverse of a small deformation only
    negated->CopyInformation(u);
    negated->SetRegions(u->GetLargestPossibleRegion());
    negated->Allocate();
    double maxU = 0.0, maxDifference = 0.0;
    for (size_t p = 0; p < n; ++p)
    {
      const auto up = u->GetBufferPointer()[p];
      negated->GetBufferPointer()[p] = -up;
      maxU = std::max(maxU, static_cast<double>(up.GetNorm()));
      maxDifference = std::max(
        maxDifference, static_cast<double>((up - plain->GetDisplacementField()->GetBufferPointer()[p]).GetNorm()));
    }
    const auto forward = InverseConsistency(u, v);
    const auto backward = InverseConsistency(v, u);
    const auto naive = InverseConsistency(u, negated);
    std::cout << (mode == MeshMode::Dynamic ? "dynamic" : "regular") << ": SSD " << both->GetHistory().front().ssd
              << " -> " << both->GetFinalSSD() << ", max |u| " << maxU << " px; |u(x) + v(x + u(x))| mean "
              << forward.first << " max " << forward.second << " px; |v(y) + u(y + v(y))| mean " << backward.first
              << " max " << backward.second << " px; with v = -u: mean " << naive.first << " max " << naive.second
              << " px" << std::endl;
    EXPECT_EQ(maxDifference, 0.0); // the option does not change the registration
    EXPECT_LT(both->GetFinalSSD(), 0.3 * both->GetHistory().front().ssd);
    EXPECT_GT(maxU, 10.0); // a large deformation
    EXPECT_LT(forward.first, 0.15);
    EXPECT_LT(forward.second, 1.5);
    EXPECT_LT(backward.first, 0.15);
    EXPECT_LT(backward.second, 1.5);
    EXPECT_LT(5.0 * forward.first, naive.first);
    // the transform output carries the inverse
    const auto * transform = both->GetTransform();
    auto         inverseTransform = MethodType::TransformType::New();
    ASSERT_TRUE(transform->GetInverse(inverseTransform));
    double largest = 0.0;
    for (const auto & index : { itk::Index<2>{ { 30, 40 } }, itk::Index<2>{ { 48, 30 } }, itk::Index<2>{ { 70, 44 } } })
    {
      MethodType::TransformType::InputPointType x;
      u->TransformIndexToPhysicalPoint(index, x);
      const auto back = inverseTransform->TransformPoint(transform->TransformPoint(x));
      largest = std::max(largest, back.EuclideanDistanceTo(x));
    }
    EXPECT_LT(largest, 1.5);
  }
}

// With an initial transformation W_0 the inverse starts from W_0^-1, which the caller gives (here a 32-pixel shift and
// its negation); without it the run is refused with a message, as is an inverse off the fixed grid.
TEST(FEMRegistrationMethod, TheInverseStartsFromTheInitialInverse)
{
  constexpr unsigned int shift = 32;
  const auto             pair = ShiftedPair(30 + shift);
  auto                   method = MethodType::New();
  method->SetFixedImage(pair[0]);
  method->SetMovingImage(pair[1]);
  method->SetInitialDisplacementField(IndexShiftField(pair[0], shift));
  method->SetNumberOfNodes(36);
  method->SetNumberOfIterations(30);
  method->SetEnergyRatio(0.1);
  method->ComputeInverseOn();
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "ComputeInverse", "inverse" }));
  method->SetInitialInverseDisplacementField(IndexShiftField(Blob(64, 50, 30, 28, 16, 12), -1.0));
  EXPECT_TRUE(itk::dmr::test::UpdateThrowsMentioning(method, { "initial inverse displacement field" }));
  method->SetInitialInverseDisplacementField(IndexShiftField(pair[0], -static_cast<double>(shift)));
  method->Update();
  EXPECT_LT(method->GetFinalSSD(), 0.5 * method->GetHistory().front().ssd);
  const auto forward = InverseConsistency(method->GetDisplacementField(), method->GetInverseDisplacementField());
  const auto backward = InverseConsistency(method->GetInverseDisplacementField(), method->GetDisplacementField());
  std::cout << "with a 32 px initial shift: |u(x) + v(x + u(x))| mean " << forward.first << " max " << forward.second
            << " px; backward mean " << backward.first << " max " << backward.second << " px" << std::endl;
  EXPECT_LT(forward.first, 0.01);
  EXPECT_LT(forward.second, 0.1);
  EXPECT_LT(backward.first, 0.01);
  EXPECT_LT(backward.second, 0.1);
}
