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
#ifndef dmrSyntheticShapes_h
#define dmrSyntheticShapes_h

#include "itkImage.h"
#include "itkImageRegionIteratorWithIndex.h"
#include <cmath>
#include <functional>

namespace itk
{
namespace dmr
{
/** The paper's 2D test pairs (section 5.2), rendered with 4 x 4 supersampling so edges are anti-aliased.
 * Intensity 1 inside the shape, 0 outside; unit spacing, origin 0, identity direction. */
using ShapeImageType = Image<float, 2>;
using InsideFunction = std::function<bool(double x, double y)>;

inline ShapeImageType::Pointer
RenderShape(unsigned int width, unsigned int height, const InsideFunction & inside)
{
  auto                     image = ShapeImageType::New();
  ShapeImageType::SizeType size = { { width, height } };
  image->SetRegions(size);
  image->Allocate();
  constexpr int sub = 4;
  for (ImageRegionIteratorWithIndex<ShapeImageType> it(image, image->GetLargestPossibleRegion()); !it.IsAtEnd(); ++it)
  {
    const auto idx = it.GetIndex();
    int        count = 0;
    for (int a = 0; a < sub; ++a)
    {
      for (int b = 0; b < sub; ++b)
      {
        const double x = idx[0] + (a + 0.5) / sub - 0.5;
        const double y = idx[1] + (b + 0.5) / sub - 0.5;
        count += inside(x, y) ? 1 : 0;
      }
    }
    it.Set(static_cast<float>(count) / (sub * sub));
  }
  return image;
}

/** The source of every pair: (x, y) in the closed disk of radius TPair::Radius around (TPair::CentreX,
 * TPair::CentreY). */
template <typename TPair>
struct DiskSource
{
  static bool
  Source(double x, double y)
  {
    const double dx = x - TPair::CentreX, dy = y - TPair::CentreY;
    return dx * dx + dy * dy <= TPair::Radius * TPair::Radius;
  }
};

/** Circle-to-leaf (paper Fig. 3): 1024 x 256, source a disk of radius 60; target: the right half is the same
 * semicircle, the left half a semi-ellipse with semi-major axis 600 (and semi-minor axis 60). */
struct CircleToLeaf : DiskSource<CircleToLeaf>
{
  static constexpr unsigned int Width = 1024, Height = 256;
  static constexpr double       CentreX = 700.0, CentreY = 127.5, Radius = 60.0, SemiMajor = 600.0;
  static bool
  Target(double x, double y)
  {
    if (x >= CentreX)
    {
      return Source(x, y);
    }
    const double a = (x - CentreX) / SemiMajor, b = (y - CentreY) / Radius;
    return a * a + b * b <= 1.0;
  }
};

/** Circle-to-epsilon (paper Figs. 4, 5): 512 x 512, source a disk of radius 120; target an epsilon-like shape: a disk
 * of radius 130 with two elliptical bays on its right side, each joined to the outside by an entrance 5 pixels wide
 * (the narrow passages that trap static meshes). */
struct CircleToEpsilon : DiskSource<CircleToEpsilon>
{
  static constexpr unsigned int Width = 512, Height = 512;
  static constexpr double       CentreX = 255.5, CentreY = 255.5, Radius = 120.0;
  static constexpr double       OuterRadius = 150.0, BayOffsetX = 55.0, BayOffsetY = 62.0, BayA = 80.0, BayB = 40.0;
  static constexpr double       Entrance = 5.0;
  static bool
  Target(double x, double y)
  {
    const double dx = x - CentreX, dy = y - CentreY;
    if (dx * dx + dy * dy > OuterRadius * OuterRadius)
    {
      return false;
    }
    for (double s : { -1.0, 1.0 })
    {
      const double by = s * BayOffsetY;
      const double a = (dx - BayOffsetX) / BayA, b = (dy - by) / BayB;
      if (a * a + b * b <= 1.0)
      {
        return false; // inside a bay
      }
      if (dx >= BayOffsetX && std::abs(dy - by) <= Entrance / 2.0)
      {
        return false; // the entrance channel from the bay to the outside
      }
    }
    return true;
  }
};

/** Two pairs beyond the paper's, for checking the method on shapes it was not shown on (not tuned to: the registration
 * runs with the paper's settings). 256 x 256; the source is a disk of radius 60 in both. */
struct CircleToC : DiskSource<CircleToC>
{
  static constexpr unsigned int Width = 256, Height = 256;
  static constexpr double       CentreX = 127.5, CentreY = 127.5, Radius = 60.0;
  static constexpr double       OuterRadius = 90.0, InnerRadius = 45.0, Gap = 20.0;
  /** A "C": the ring between radii 45 and 90, cut open on its right by a gap 20 pixels wide. */
  static bool
  Target(double x, double y)
  {
    const double dx = x - CentreX, dy = y - CentreY, r2 = dx * dx + dy * dy;
    if (r2 > OuterRadius * OuterRadius || r2 < InnerRadius * InnerRadius)
    {
      return false;
    }
    return !(dx > 0.0 && std::abs(dy) < Gap / 2.0);
  }
};

struct CircleToStar : DiskSource<CircleToStar>
{
  static constexpr unsigned int Width = 256, Height = 256;
  static constexpr double       CentreX = 127.5, CentreY = 127.5, Radius = 60.0;
  static constexpr double       InnerRadius = 40.0, OuterRadius = 90.0;
  static constexpr int          Arms = 5;
  /** A smooth five-armed star: r(theta) = 40 + 50 (1 + cos 5 theta) / 2. */
  static bool
  Target(double x, double y)
  {
    const double dx = x - CentreX, dy = y - CentreY;
    const double r = InnerRadius + (OuterRadius - InnerRadius) * 0.5 * (1.0 + std::cos(Arms * std::atan2(dy, dx)));
    return dx * dx + dy * dy <= r * r;
  }
};
} // namespace dmr
} // namespace itk

#endif
