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
#ifndef dmrDataTestHelpers_h
#define dmrDataTestHelpers_h

// Shared pieces of the test/Data tests: where the real data lives, scratch directories, oblique test geometry and
// a small thorax-like CT phantom in HU.
#include "itkImage.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "itkNumericTraits.h"
#include "itkNumericTraitsVectorPixel.h"
#include "itksys/SystemTools.hxx"
#include "gtest/gtest.h"
#include <cmath>
#include <cstdlib>
#include <string>
#include <unistd.h>

#ifndef DMR_SHARED_DATA_DIR
#define DMR_SHARED_DATA_DIR ""
#endif

namespace dmrtest
{
/** The shared real-data folder: $DMR_SHARED_DATA_DIR when set, else the path compiled in (<source>/../shared/data). */
inline std::string
SharedDataDir()
{
  const char * env = std::getenv("DMR_SHARED_DATA_DIR");
  return env && *env ? std::string(env) : std::string(DMR_SHARED_DATA_DIR);
}

/** SharedDataDir()/name when that folder exists, else "" (callers GTEST_SKIP()). */
inline std::string
SharedDataFolder(const std::string & name)
{
  const std::string path = SharedDataDir() + "/" + name;
  return itksys::SystemTools::FileIsDirectory(path) ? path : std::string();
}

/** itk::Vector / itk::Point from three numbers (ITK 5.2 has no MakeVector/MakePoint). */
template <typename T = double>
itk::Vector<T, 3>
Vec(T a, T b, T c)
{
  itk::Vector<T, 3> v;
  v[0] = a;
  v[1] = b;
  v[2] = c;
  return v;
}

inline itk::Point<double, 3>
Pt(double a, double b, double c)
{
  itk::Point<double, 3> p;
  p[0] = a;
  p[1] = b;
  p[2] = c;
  return p;
}

/** A fresh empty scratch directory under GoogleTest's temporary directory, removed by the destructor. */
class ScratchDirectory
{
public:
  explicit ScratchDirectory(const std::string & tag)
  {
    const auto * info = ::testing::UnitTest::GetInstance()->current_test_info();
    m_Path = ::testing::TempDir() + "dmrData-" + tag + "-" + (info ? info->name() : "x") + "-" +
             std::to_string(static_cast<long>(::getpid()));
    itksys::SystemTools::RemoveADirectory(m_Path);
    itksys::SystemTools::MakeDirectory(m_Path);
  }
  ~ScratchDirectory() { itksys::SystemTools::RemoveADirectory(m_Path); }
  const std::string &
  Path() const
  {
    return m_Path;
  }

private:
  std::string m_Path;
};

/** A rotation by angle (radians) about the physical x axis times one about z: a non-identity, non-axis-aligned
 * direction that keeps z close to superior. */
inline itk::Matrix<double, 3, 3>
ObliqueDirection(double aboutX = 0.15, double aboutZ = 0.1)
{
  itk::Matrix<double, 3, 3> rx, rz;
  rx.SetIdentity();
  rz.SetIdentity();
  rx[1][1] = std::cos(aboutX);
  rx[1][2] = -std::sin(aboutX);
  rx[2][1] = std::sin(aboutX);
  rx[2][2] = std::cos(aboutX);
  rz[0][0] = std::cos(aboutZ);
  rz[0][1] = -std::sin(aboutZ);
  rz[1][0] = std::sin(aboutZ);
  rz[1][1] = std::cos(aboutZ);
  return rz * rx;
}

/** An empty image with the given geometry; centre of the physical box at centre. */
template <typename TImage>
typename TImage::Pointer
MakeImage(const itk::Size<3> &              size,
          const itk::Vector<double, 3> &    spacing,
          const itk::Matrix<double, 3, 3> & direction,
          const itk::Point<double, 3> &     centre)
{
  auto image = TImage::New();
  image->SetRegions(itk::ImageRegion<3>(size));
  image->SetSpacing(spacing);
  typename TImage::DirectionType d;
  for (unsigned int i = 0; i < 3; ++i)
  {
    for (unsigned int j = 0; j < 3; ++j)
    {
      d[i][j] = direction[i][j];
    }
  }
  image->SetDirection(d);
  // origin such that the centre voxel sits at centre
  itk::Vector<double, 3> half;
  for (unsigned int k = 0; k < 3; ++k)
  {
    half[k] = 0.5 * static_cast<double>(size[k] - 1) * spacing[k];
  }
  itk::Point<double, 3> origin = centre - direction * half;
  image->SetOrigin(origin);
  image->Allocate();
  image->FillBuffer(itk::NumericTraits<typename TImage::PixelType>::ZeroValue());
  return image;
}

/** Thorax-like CT phantom in HU (short), defined in the image's grid frame relative to its centre (so it follows
 * the direction): air (-1000) around an elliptic body cylinder (40 HU) along the slice axis, two lung ellipsoids
 * (-850 HU) with a vessel (60 HU) running through each, and a small gas pocket (-900 HU) in the "abdomen" below the
 * lungs. lungsToTop: the lungs reach the last slice (a scan that cuts through the lungs). Analytic lung volume
 * (without vessels, which the mask fills back) in mm^3 is returned through lungVolume. */
inline itk::Image<short, 3>::Pointer
MakeThoraxPhantom(const itk::Size<3> &              size,
                  const itk::Vector<double, 3> &    spacing,
                  const itk::Matrix<double, 3, 3> & direction,
                  bool                              lungsToTop = false,
                  double *                          lungVolume = nullptr)
{
  using ImageType = itk::Image<short, 3>;
  itk::Point<double, 3> centre;
  centre.Fill(0.0);
  centre[2] = -30.0;
  auto   image = MakeImage<ImageType>(size, spacing, direction, centre);
  double extent[3];
  for (unsigned int k = 0; k < 3; ++k)
  {
    extent[k] = static_cast<double>(size[k] - 1) * spacing[k];
  }
  const double bodyA = 0.42 * extent[0], bodyB = 0.32 * extent[1];
  const double lungA = 0.13 * extent[0], lungB = 0.2 * extent[1],
               lungC = lungsToTop ? 0.45 * extent[2] : 0.3 * extent[2];
  const double                                 lungZ = lungsToTop ? 0.1 * extent[2] : 0.08 * extent[2];
  const double                                 lungX = 0.18 * extent[0];
  itk::ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    double g[3]; // grid-frame mm relative to the centre voxel
    for (unsigned int k = 0; k < 3; ++k)
    {
      g[k] = static_cast<double>(it.GetIndex()[k]) * spacing[k] - 0.5 * extent[k];
    }
    short v = -1000;
    if ((g[0] / bodyA) * (g[0] / bodyA) + (g[1] / bodyB) * (g[1] / bodyB) <= 1.0)
    {
      v = 40;
      for (const double side : { -1.0, 1.0 })
      {
        const double x = (g[0] - side * lungX) / lungA, y = g[1] / lungB, z = (g[2] - lungZ) / lungC;
        if (x * x + y * y + z * z <= 1.0)
        {
          const double vx = g[0] - side * lungX, vy = g[1] - 0.2 * lungB;
          v = vx * vx + vy * vy <= 4.0 * spacing[0] * spacing[0] ? 60 : -850;
        }
      }
      const double gx = g[0] - 0.1 * extent[0], gy = g[1] + 0.1 * extent[1], gz = g[2] + 0.38 * extent[2];
      if (gx * gx + gy * gy + gz * gz <= 9.0 * spacing[0] * spacing[0])
      {
        v = -900;
      }
    }
    it.Set(v);
  }
  if (lungVolume)
  {
    // two ellipsoids, clipped at the image box when they reach past it: estimate the clipped part numerically
    double       inside = 0.0;
    const int    n = 200;
    const double top = 0.5 * extent[2];
    for (int i = 0; i < n; ++i) // slices of one ellipsoid, z in [lungZ - lungC, lungZ + lungC]
    {
      const double z = lungZ - lungC + (i + 0.5) * 2.0 * lungC / n;
      const double r = 1.0 - ((z - lungZ) / lungC) * ((z - lungZ) / lungC);
      if (z <= top + 0.5 * spacing[2] && r > 0)
      {
        inside += M_PI * lungA * lungB * r * 2.0 * lungC / n;
      }
    }
    *lungVolume = 2.0 * inside;
  }
  return image;
}
} // namespace dmrtest

#endif
