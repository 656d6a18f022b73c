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
// 3D end to end on a synthetic pair with a known smooth deformation (issue 3): a textured ellipsoid, a moving image
// S(y) and a fixed image F(x) = S(x + u(x)), so the true displacement on the fixed grid is u (ITK convention:
// moving point = fixed point + u). The registered field must match u to < 0.5 voxel on average inside the object,
// with det J > 0 everywhere. The image has a rotated direction and a non-zero origin so that physical space is
// exercised in 3D.
#include "itkFEMRegistrationMethod.h"
#include "dmrFieldImage.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"
#include <array>
#include <cmath>
#include <iostream>

namespace
{
using ImageType = itk::Image<float, 3>;
using MethodType = itk::FEMRegistrationMethod<ImageType, ImageType>;
using MeshMode = itk::DynamicMeshRegistrationEnums::MeshMode;
using PointType = ImageType::PointType;

constexpr unsigned int N = 64;

/** The geometry shared by both images: 1 mm voxels, rotated about an oblique axis, origin away from 0. */
void
SetGeometry(ImageType * image)
{
  image->SetRegions(ImageType::SizeType{ { N, N, N } });
  ImageType::PointType origin;
  origin[0] = -20.0;
  origin[1] = 15.0;
  origin[2] = 7.5;
  image->SetOrigin(origin);
  // rotation by 0.3 rad about z then 0.2 rad about x
  const double             a = 0.3, b = 0.2;
  ImageType::DirectionType rz, rx;
  rz.SetIdentity();
  rx.SetIdentity();
  rz(0, 0) = std::cos(a);
  rz(0, 1) = -std::sin(a);
  rz(1, 0) = std::sin(a);
  rz(1, 1) = std::cos(a);
  rx(1, 1) = std::cos(b);
  rx(1, 2) = -std::sin(b);
  rx(2, 1) = std::sin(b);
  rx(2, 2) = std::cos(b);
  image->SetDirection(rx * rz);
}

PointType
Centre(const ImageType * image)
{
  itk::ContinuousIndex<double, 3> c;
  c.Fill((N - 1) / 2.0);
  PointType p;
  image->TransformContinuousIndexToPhysicalPoint(c, p);
  return p;
}

/** The known deformation: two smooth Gaussian bumps (max about 3 mm), negligible at the border. */
itk::Vector<double, 3>
TrueDisplacement(const PointType & x, const PointType & centre)
{
  const double sigma = 10.0;
  const double c1[3] = { -6.0, 4.0, 0.0 }, a1[3] = { 2.5, -1.5, 1.0 };
  const double c2[3] = { 6.0, -4.0, 3.0 }, a2[3] = { -1.5, 2.0, 2.0 };
  double       r1 = 0.0, r2 = 0.0;
  for (unsigned int k = 0; k < 3; ++k)
  {
    const double q = x[k] - centre[k];
    r1 += (q - c1[k]) * (q - c1[k]);
    r2 += (q - c2[k]) * (q - c2[k]);
  }
  const double           g1 = std::exp(-r1 / (2 * sigma * sigma)), g2 = std::exp(-r2 / (2 * sigma * sigma));
  itk::Vector<double, 3> u;
  for (unsigned int k = 0; k < 3; ++k)
  {
    u[k] = a1[k] * g1 + a2[k] * g2;
  }
  return u;
}

/** Smooth inside indicator of the ellipsoid (radii 22, 18, 15 mm about the centre, in the image axes). */
double
Inside(const PointType & y, const PointType & centre, const ImageType * image)
{
  const auto & dir = image->GetDirection();
  const double radii[3] = { 22.0, 18.0, 15.0 };
  double       r2 = 0.0;
  for (unsigned int k = 0; k < 3; ++k)
  {
    double q = 0.0; // coordinate along image axis k
    for (unsigned int j = 0; j < 3; ++j)
    {
      q += dir[j][k] * (y[j] - centre[j]);
    }
    r2 += (q / radii[k]) * (q / radii[k]);
  }
  return 1.0 / (1.0 + std::exp((std::sqrt(r2) - 1.0) * 12.0));
}

/** Texture: blobs at fixed pseudo-random places (like vessels and nodules in a lung), so that motion inside the
 * object is observable in every direction, not only at its surface. Positions relative to the centre, in mm. */
struct Blobs
{
  std::vector<std::array<double, 4>> blobs; // x, y, z, amplitude
  Blobs()
  {
    uint32_t state = 12345u;
    auto     next = [&state]() {
      state = state * 1664525u + 1013904223u;
      return static_cast<double>(state >> 8) / static_cast<double>(1u << 24);
    };
    while (blobs.size() < 60)
    {
      const double x = (next() * 2 - 1) * 20, y = (next() * 2 - 1) * 16, z = (next() * 2 - 1) * 13;
      if ((x / 20) * (x / 20) + (y / 16) * (y / 16) + (z / 13) * (z / 13) < 1.0)
      {
        blobs.push_back({ x, y, z, (next() < 0.5 ? -0.3 : 0.3) });
      }
    }
  }
};

/** The object: a textured ellipsoid. */
double
Shape(const PointType & y, const PointType & centre, const ImageType * image)
{
  static const Blobs texture;
  double             t = 0.0;
  for (const auto & b : texture.blobs)
  {
    const double r2 = (y[0] - centre[0] - b[0]) * (y[0] - centre[0] - b[0]) +
                      (y[1] - centre[1] - b[1]) * (y[1] - centre[1] - b[1]) +
                      (y[2] - centre[2] - b[2]) * (y[2] - centre[2] - b[2]);
    t += b[3] * std::exp(-r2 / (2.0 * 2.5 * 2.5));
  }
  return Inside(y, centre, image) * (0.6 + t);
}

struct Pair
{
  ImageType::Pointer fixed, moving;
};

Pair
MakePair()
{
  Pair pair;
  pair.fixed = ImageType::New();
  pair.moving = ImageType::New();
  SetGeometry(pair.fixed);
  SetGeometry(pair.moving);
  pair.fixed->Allocate();
  pair.moving->Allocate();
  const PointType                              centre = Centre(pair.fixed);
  itk::ImageRegionIteratorWithIndex<ImageType> it(pair.fixed, pair.fixed->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    PointType x;
    pair.fixed->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const auto u = TrueDisplacement(x, centre);
    it.Set(static_cast<float>(Shape(x + u, centre, pair.fixed))); // F(x) = S(x + u(x))
    pair.moving->SetPixel(it.GetIndex(), static_cast<float>(Shape(x, centre, pair.fixed)));
  }
  return pair;
}

struct Errors
{
  double initialMean{ 0 }, mean{ 0 }, p95{ 0 }, max{ 0 };
  size_t voxels{ 0 };
};

Errors
DenseError(const MethodType::DisplacementFieldType * field, const ImageType * fixed)
{
  const PointType                                                           centre = Centre(fixed);
  Errors                                                                    e;
  std::vector<double>                                                       errors;
  itk::ImageRegionConstIteratorWithIndex<MethodType::DisplacementFieldType> it(field,
                                                                               field->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    PointType x;
    fixed->TransformIndexToPhysicalPoint(it.GetIndex(), x);
    const auto u = TrueDisplacement(x, centre);
    if (Inside(x + u, centre, fixed) < 0.5)
    {
      continue;
    }
    double d2 = 0.0;
    for (unsigned int k = 0; k < 3; ++k)
    {
      d2 += std::pow(it.Get()[k] - u[k], 2);
    }
    errors.push_back(std::sqrt(d2));
    e.initialMean += u.GetNorm();
  }
  e.voxels = errors.size();
  e.initialMean /= static_cast<double>(e.voxels);
  double sum = 0.0;
  for (double d : errors)
  {
    sum += d;
    e.max = std::max(e.max, d);
  }
  e.mean = sum / static_cast<double>(e.voxels);
  std::sort(errors.begin(), errors.end());
  e.p95 = errors[static_cast<size_t>(0.95 * static_cast<double>(errors.size() - 1))];
  return e;
}

class Synthetic3D : public ::testing::TestWithParam<MeshMode>
{
};

TEST_P(Synthetic3D, RecoversTheKnownFieldWithPositiveJacobian)
{
  const Pair pair = MakePair();
  auto       method = MethodType::New();
  method->SetFixedImage(pair.fixed);
  method->SetMovingImage(pair.moving);
  method->SetMeshMode(GetParam());
  method->SetNumberOfNodes(2000);
  // The paper's energy ratio 0.02 makes every step lower D by about 4 % to first order; it reaches the bar only after
  // about 400 iterations on this pair (measured with the regular mesh: mean error 0.89 mm at 60 iterations, 0.54 at
  // 200, 0.43 at 400). 0.2 takes ten times larger steps and keeps the test short; det J > 0 must still hold.
  method->SetEnergyRatio(0.2);
  method->SetNumberOfIterations(60);
  method->Update();

  const Errors              e = DenseError(method->GetDisplacementField(), pair.fixed);
  std::pair<double, double> jacobianRange;
  itk::dmr::JacobianDeterminantImage(method->GetDisplacementField(), jacobianRange, method->GetMultiThreader());
  const auto & t = method->GetTiming();
  std::cout << "[figure] 3D synthetic 64^3 (" << GetParam()
            << " mesh, 2000 nodes, 60 iterations, energy ratio 0.2): dense error mean " << e.mean << " mm (initial "
            << e.initialMean << "), p95 " << e.p95 << ", max " << e.max << " over " << e.voxels << " voxels; det J in ["
            << jacobianRange.first << ", " << jacobianRange.second << "]; SSD " << method->GetHistory().front().ssd
            << " -> " << method->GetFinalSSD() << "; total " << t.total << " s (tess. opt. "
            << t.tessellationOptimization << ", mesh " << t.meshConstruction << ", bary " << t.barycentric
            << ", registration " << t.registration << ")" << std::endl;
  EXPECT_GT(e.initialMean, 1.0); // the test pair is not trivial
  EXPECT_LT(e.mean, 0.5);        // voxels are 1 mm
  EXPECT_GT(jacobianRange.first, 0.0);
}

INSTANTIATE_TEST_SUITE_P(Meshes, Synthetic3D, ::testing::Values(MeshMode::Dynamic, MeshMode::Regular));
} // namespace
