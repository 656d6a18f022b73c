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
#ifndef dmrDualMeshPhantom_h
#define dmrDualMeshPhantom_h

#include "dmrTestHelpers.h"
#include "itkDiscreteCVTFilter.h"
#include "itkDualMeshFilter.h"

namespace itk
{
namespace dmr
{
namespace test
{
/** A smooth positive 2D density (two Gaussian bumps on a floor) with the given geometry. */
inline Image<float, 2>::Pointer
SmoothDensity2D(const Image<float, 2>::SizeType &      size,
                const Image<float, 2>::SpacingType &   spacing,
                const Image<float, 2>::PointType &     origin,
                const Image<float, 2>::DirectionType & direction)
{
  using ImageType = Image<float, 2>;
  auto image =
    MakeImage<ImageType>(size, spacing, origin, direction, [](const ImageType::PointType &) { return 0.0f; });
  // defined on the index grid so the pattern does not depend on the physical placement
  ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    const double x = it.GetIndex()[0] / static_cast<double>(size[0]);
    const double y = it.GetIndex()[1] / static_cast<double>(size[1]);
    const double b1 = std::exp(-((x - 0.3) * (x - 0.3) + (y - 0.6) * (y - 0.6)) / 0.02);
    const double b2 = std::exp(-((x - 0.7) * (x - 0.7) + (y - 0.3) * (y - 0.3)) / 0.05);
    it.Set(static_cast<float>(0.2 + 3.0 * b1 + 1.5 * b2));
  }
  return image;
}

/** CVT labels and sites of a density image, then its dual mesh (triangles in 2D, tetrahedra in 3D). Keeps every
 * pipeline object alive. */
template <unsigned int D>
struct DualMeshPhantomOf
{
  using ImageType = Image<float, D>;
  using CVTFilterType = DiscreteCVTFilter<ImageType>;
  using DualMeshFilterType = DualMeshFilter<typename CVTFilterType::LabelImageType>;

  typename ImageType::Pointer          density;
  typename CVTFilterType::Pointer      cvt;
  typename DualMeshFilterType::Pointer dual;

  DualMeshPhantomOf(typename ImageType::Pointer densityImage, SizeValueType numberOfCells)
    : density(densityImage)
  {
    cvt = CVTFilterType::New();
    cvt->SetInput(density);
    cvt->SetNumberOfCells(numberOfCells);
    cvt->Update();
    dual = DualMeshFilterType::New();
    dual->SetInput(cvt->GetOutput());
    dual->SetSites(cvt->GetSites());
    dual->Update();
  }

  Grid<D>
  GetGrid() const
  {
    return Grid<D>::FromImage(density);
  }
  const SimplexMesh<D> &
  GetMesh() const
  {
    return dual->GetSimplexMesh();
  }
};
using DualMeshPhantom = DualMeshPhantomOf<2>;
using DualMeshPhantom3D = DualMeshPhantomOf<3>;

/** 64x48 density, spacing 0.8 x 1.3, rotated by -40 degrees, origin (-20, 35): non-trivial geometry everywhere. */
inline DualMeshPhantom
MakeDualMeshPhantom(SizeValueType numberOfCells = 20)
{
  using ImageType = Image<float, 2>;
  ImageType::SizeType    size{ { 64, 48 } };
  ImageType::SpacingType spacing;
  spacing[0] = 0.8;
  spacing[1] = 1.3;
  ImageType::PointType origin;
  origin[0] = -20.0;
  origin[1] = 35.0;
  return DualMeshPhantom(SmoothDensity2D(size, spacing, origin, RotationDirection2D<ImageType>(-0.6981317007977318)),
                         numberOfCells);
}
/** The same density on a unit-spacing grid (rotated, shifted): border-pixel averages are exact there. */
inline DualMeshPhantom
MakeUnitSpacingDualMeshPhantom(SizeValueType numberOfCells = 20)
{
  using ImageType = Image<float, 2>;
  ImageType::SizeType    size{ { 64, 48 } };
  ImageType::SpacingType spacing;
  spacing.Fill(1.0);
  ImageType::PointType origin;
  origin[0] = 7.0;
  origin[1] = -3.0;
  return DualMeshPhantom(SmoothDensity2D(size, spacing, origin, RotationDirection2D<ImageType>(0.3)), numberOfCells);
}

/** Rotation by angle (radians) about an axis (normalised here; Rodrigues) as a 3D image direction. */
template <typename TImage>
typename TImage::DirectionType
RotationDirection3D(const std::array<double, 3> & axis, double angle)
{
  const double                   norm = std::sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
  const double                   u[3] = { axis[0] / norm, axis[1] / norm, axis[2] / norm };
  const double                   c = std::cos(angle), s = std::sin(angle);
  typename TImage::DirectionType direction;
  for (unsigned int r = 0; r < 3; ++r)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      direction(r, k) = (r == k ? c : 0.0) + (1.0 - c) * u[r] * u[k];
    }
  }
  direction(0, 1) -= s * u[2];
  direction(0, 2) += s * u[1];
  direction(1, 0) += s * u[2];
  direction(1, 2) -= s * u[0];
  direction(2, 0) -= s * u[1];
  direction(2, 1) += s * u[0];
  return direction;
}

/** A positive 3D density with a ridge (a Gaussian slab along a tilted plane) and a bump on a floor, defined on the
 * index grid so the pattern does not depend on the physical placement. */
inline Image<float, 3>::Pointer
RidgeDensity3D(const Image<float, 3>::SizeType &      size,
               const Image<float, 3>::SpacingType &   spacing,
               const Image<float, 3>::PointType &     origin,
               const Image<float, 3>::DirectionType & direction)
{
  using ImageType = Image<float, 3>;
  auto image =
    MakeImage<ImageType>(size, spacing, origin, direction, [](const ImageType::PointType &) { return 0.0f; });
  ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    const double x = it.GetIndex()[0] / static_cast<double>(size[0]);
    const double y = it.GetIndex()[1] / static_cast<double>(size[1]);
    const double z = it.GetIndex()[2] / static_cast<double>(size[2]);
    const double ridge = std::exp(-std::pow(0.8 * x + 0.5 * y - 0.3 * z - 0.55, 2) / 0.01);
    const double bump = std::exp(-((x - 0.25) * (x - 0.25) + (y - 0.7) * (y - 0.7) + (z - 0.6) * (z - 0.6)) / 0.03);
    it.Set(static_cast<float>(0.2 + 3.0 * ridge + 1.5 * bump));
  }
  return image;
}

/** 40 x 36 x 30 ridge density, spacing 1.0 x 1.2 x 2.5, rotated by 0.7 rad about (1, 2, 2), origin (-12, 30, 7.5). */
inline DualMeshPhantom3D
MakeDualMeshPhantom3D(SizeValueType numberOfCells = 200)
{
  using ImageType = Image<float, 3>;
  ImageType::SizeType    size{ { 40, 36, 30 } };
  ImageType::SpacingType spacing;
  spacing[0] = 1.0;
  spacing[1] = 1.2;
  spacing[2] = 2.5;
  ImageType::PointType origin;
  origin[0] = -12.0;
  origin[1] = 30.0;
  origin[2] = 7.5;
  return DualMeshPhantom3D(
    RidgeDensity3D(size, spacing, origin, RotationDirection3D<ImageType>({ 1.0, 2.0, 2.0 }, 0.7)), numberOfCells);
}
} // namespace test
} // namespace dmr
} // namespace itk

#endif
