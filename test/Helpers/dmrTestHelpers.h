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
#ifndef dmrTestHelpers_h
#define dmrTestHelpers_h

#include "gtest/gtest.h"
#include "dmrGrid.h"
#include "dmrSimplexMesh.h"
#include "itkImage.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "itkMultiThreaderBase.h"
#include "itkProcessObject.h"
#include <array>
#include <cmath>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

namespace itk
{
namespace dmr
{
namespace test
{
/** A threader of at most `threads` threads and `workUnits` work units, for the tests that compare threaded results
 * with serial ones. */
inline MultiThreaderBase::Pointer
Threader(unsigned int threads, unsigned int workUnits)
{
  auto threader = MultiThreaderBase::New();
  threader->SetMaximumNumberOfThreads(threads);
  threader->SetNumberOfWorkUnits(workUnits);
  return threader;
}

/** Success when process->Update() throws an itk::ExceptionObject whose description contains every one of `texts`. */
inline ::testing::AssertionResult
UpdateThrowsMentioning(ProcessObject * process, std::initializer_list<std::string> texts)
{
  try
  {
    process->Update();
  }
  catch (const ExceptionObject & e)
  {
    const std::string description = e.GetDescription();
    for (const auto & text : texts)
    {
      if (description.find(text) == std::string::npos)
      {
        return ::testing::AssertionFailure() << "the exception does not mention '" << text << "': " << description;
      }
    }
    return ::testing::AssertionSuccess();
  }
  return ::testing::AssertionFailure() << "Update() did not throw";
}

/** Positive random density in [low, high), one value per pixel, from a fixed seed. */
inline std::vector<float>
RandomDensity(size_t numberOfPixels, uint32_t seed, float low = 0.2f, float high = 1.0f)
{
  std::mt19937                          engine(seed);
  std::uniform_real_distribution<float> uniform(low, high);
  std::vector<float>                    density(numberOfPixels);
  for (auto & d : density)
  {
    d = uniform(engine);
  }
  return density;
}

/** Labels are 0..numberOfCells-1 and every one of them is used. */
inline ::testing::AssertionResult
LabelsAreCompact(const std::vector<int32_t> & labels, size_t numberOfCells)
{
  std::vector<size_t> count(numberOfCells, 0);
  for (size_t p = 0; p < labels.size(); ++p)
  {
    if (labels[p] < 0 || static_cast<size_t>(labels[p]) >= numberOfCells)
    {
      return ::testing::AssertionFailure()
             << "pixel " << p << " has label " << labels[p] << ", outside [0, " << numberOfCells << ")";
    }
    ++count[labels[p]];
  }
  for (size_t c = 0; c < numberOfCells; ++c)
  {
    if (count[c] == 0)
    {
      return ::testing::AssertionFailure() << "label " << c << " is not used";
    }
  }
  return ::testing::AssertionSuccess();
}

/** Every label's pixels form one face-connected (4-connected in 2D, 6-connected in 3D) component. Independent
 * of the library: a plain flood fill over the whole grid. */
template <unsigned int D>
::testing::AssertionResult
CellsAreFaceConnected(const Grid<D> & grid, const std::vector<int32_t> & labels)
{
  if (labels.size() != grid.numberOfPixels)
  {
    return ::testing::AssertionFailure() << "label count " << labels.size() << " != pixel count "
                                         << grid.numberOfPixels;
  }
  int32_t maxLabel = -1;
  for (int32_t l : labels)
  {
    maxLabel = std::max(maxLabel, l);
  }
  std::vector<uint8_t> componentSeen(static_cast<size_t>(maxLabel + 1), 0);
  std::vector<uint8_t> visited(grid.numberOfPixels, 0);
  std::vector<size_t>  stack;
  for (size_t seed = 0; seed < grid.numberOfPixels; ++seed)
  {
    if (visited[seed])
    {
      continue;
    }
    const int32_t label = labels[seed];
    if (label >= 0)
    {
      if (componentSeen[label])
      {
        return ::testing::AssertionFailure() << "cell " << label << " has a second component containing pixel " << seed;
      }
      componentSeen[label] = 1;
    }
    visited[seed] = 1;
    stack.assign(1, seed);
    while (!stack.empty())
    {
      const size_t p = stack.back();
      stack.pop_back();
      const auto idx = grid.Index(p);
      for (unsigned int k = 0; k < D; ++k)
      {
        for (int s = -1; s <= 1; s += 2)
        {
          const int64_t c = idx[k] + s;
          if (c < 0 || c >= static_cast<int64_t>(grid.size[k]))
          {
            continue;
          }
          const size_t q = s < 0 ? p - grid.stride[k] : p + grid.stride[k];
          if (!visited[q] && labels[q] == label)
          {
            visited[q] = 1;
            stack.push_back(q);
          }
        }
      }
    }
  }
  return ::testing::AssertionSuccess();
}

/** Grid-frame position of pixel p (index x spacing), as the library defines it. */
template <unsigned int D>
std::array<double, D>
PixelPosition(const Grid<D> & grid, size_t p)
{
  const auto            idx = grid.Index(p);
  std::array<double, D> x;
  for (unsigned int k = 0; k < D; ++k)
  {
    x[k] = static_cast<double>(idx[k]) * grid.spacing[k];
  }
  return x;
}

/** Reference statistics of a labelling computed pixel by pixel: masses, centroids (D interleaved), energy
 * sum_x d(x) |x - centroid|^2. */
template <unsigned int D>
struct CellStatistics
{
  std::vector<double> mass;
  std::vector<double> centroid;
  double              energy{ 0.0 };
};

template <unsigned int D>
CellStatistics<D>
ComputeCellStatistics(const Grid<D> &              grid,
                      const float *                density,
                      const std::vector<int32_t> & labels,
                      size_t                       numberOfCells)
{
  CellStatistics<D> s;
  s.mass.assign(numberOfCells, 0.0);
  s.centroid.assign(numberOfCells * D, 0.0);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = PixelPosition<D>(grid, p);
    s.mass[labels[p]] += density[p];
    for (unsigned int k = 0; k < D; ++k)
    {
      s.centroid[labels[p] * D + k] += density[p] * x[k];
    }
  }
  for (size_t c = 0; c < numberOfCells; ++c)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      s.centroid[c * D + k] /= s.mass[c];
    }
  }
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto x = PixelPosition<D>(grid, p);
    double     d2 = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double d = x[k] - s.centroid[labels[p] * D + k];
      d2 += d * d;
    }
    s.energy += density[p] * d2;
  }
  return s;
}

/** 2D rotation by angle (radians) as an image direction. */
template <typename TImage>
typename TImage::DirectionType
RotationDirection2D(double angle)
{
  typename TImage::DirectionType direction;
  direction(0, 0) = std::cos(angle);
  direction(0, 1) = -std::sin(angle);
  direction(1, 0) = std::sin(angle);
  direction(1, 1) = std::cos(angle);
  return direction;
}

/** Image with the given geometry whose pixel at index i is value(physical point of i). Start index 0. */
template <typename TImage, typename TFunction>
typename TImage::Pointer
MakeImage(const typename TImage::SizeType &      size,
          const typename TImage::SpacingType &   spacing,
          const typename TImage::PointType &     origin,
          const typename TImage::DirectionType & direction,
          TFunction &&                           value)
{
  auto image = TImage::New();
  image->SetRegions(typename TImage::RegionType(size));
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  image->SetDirection(direction);
  image->Allocate();
  ImageRegionIteratorWithIndex<TImage> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    typename TImage::PointType point;
    image->TransformIndexToPhysicalPoint(it.GetIndex(), point);
    it.Set(value(point));
  }
  return image;
}

/** Gives the image's largest (and buffered) region the start index `start` and moves its origin so that every pixel
 * keeps its physical point: the same image, indexed differently (as CropImageFilter or ExtractImageFilter leave it). */
template <typename TImage>
void
ShiftRegionStart(TImage * image, const typename TImage::IndexType & start)
{
  const typename TImage::IndexType old = image->GetLargestPossibleRegion().GetIndex();
  typename TImage::PointType       first;
  image->TransformIndexToPhysicalPoint(old, first);
  typename TImage::RegionType region = image->GetLargestPossibleRegion();
  region.SetIndex(start);
  image->SetRegions(region); // the buffer keeps its pixels: only their indices change
  typename TImage::PointType now;
  image->TransformIndexToPhysicalPoint(start, now);
  typename TImage::PointType origin = image->GetOrigin();
  for (unsigned int k = 0; k < TImage::ImageDimension; ++k)
  {
    origin[k] += first[k] - now[k];
  }
  image->SetOrigin(origin);
}

/** Image with identity direction and zero origin from a flat buffer (first index fastest). */
template <typename TImage>
typename TImage::Pointer
ImageFromBuffer(const typename TImage::SizeType &               size,
                const typename TImage::SpacingType &            spacing,
                const std::vector<typename TImage::PixelType> & buffer)
{
  auto image = TImage::New();
  image->SetRegions(typename TImage::RegionType(size));
  image->SetSpacing(spacing);
  image->Allocate();
  std::copy(buffer.begin(), buffer.end(), image->GetBufferPointer());
  return image;
}

/** Mesh elements all have positive measure and sum to the measure of the box [0,(size-1) spacing]. */
template <unsigned int D>
::testing::AssertionResult
MeshTilesTheBox(const Grid<D> & grid, const SimplexMesh<D> & mesh, double relativeTolerance = 1e-9)
{
  double total = 0.0, box = 1.0;
  for (unsigned int k = 0; k < D; ++k)
  {
    box *= static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
  }
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    const double m = mesh.SignedMeasure(e);
    if (!(m > 0.0))
    {
      return ::testing::AssertionFailure() << "element " << e << " has measure " << m;
    }
    total += m;
  }
  if (std::abs(total - box) > relativeTolerance * box)
  {
    return ::testing::AssertionFailure() << "element measures sum to " << total << ", the box is " << box;
  }
  return ::testing::AssertionSuccess();
}

/** Nodes lie inside the box and a node is fixed exactly when it lies on the box border. */
template <unsigned int D>
::testing::AssertionResult
FixedNodesAreTheBorderNodes(const Grid<D> & grid, const SimplexMesh<D> & mesh)
{
  if (mesh.fixed.size() != mesh.NumberOfNodes())
  {
    return ::testing::AssertionFailure() << "fixed flags: " << mesh.fixed.size() << ", nodes: " << mesh.NumberOfNodes();
  }
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
  {
    bool onBorder = false;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double x = mesh.nodes[i * D + k];
      const double hi = static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
      const double tol = 1e-6 * grid.spacing[k];
      if (x < -tol || x > hi + tol)
      {
        return ::testing::AssertionFailure() << "node " << i << " lies outside the box along axis " << k << ": " << x;
      }
      onBorder = onBorder || std::abs(x) <= tol || std::abs(x - hi) <= tol;
    }
    if (onBorder != (mesh.fixed[i] != 0))
    {
      return ::testing::AssertionFailure()
             << "node " << i << (onBorder ? " on" : " off") << " the border has fixed = " << int(mesh.fixed[i]);
    }
  }
  return ::testing::AssertionSuccess();
}

/** FromItkMesh(output) (physical itk::Mesh back to the grid frame of image) gives the mesh again: nodes within 1e-9,
 * the same elements and fixed flags. */
template <unsigned int D, typename TItkMesh, typename TImage>
::testing::AssertionResult
ItkMeshConvertsBackTo(const TItkMesh * output, const TImage * image, const SimplexMesh<D> & mesh)
{
  const auto back = FromItkMesh<D>(output, image);
  if (back.NumberOfNodes() != mesh.NumberOfNodes())
  {
    return ::testing::AssertionFailure() << back.NumberOfNodes() << " nodes back, " << mesh.NumberOfNodes()
                                         << " expected";
  }
  for (size_t i = 0; i < mesh.nodes.size(); ++i)
  {
    if (!(std::abs(back.nodes[i] - mesh.nodes[i]) <= 1e-9))
    {
      return ::testing::AssertionFailure()
             << "node coordinate " << i << ": " << back.nodes[i] << " back, " << mesh.nodes[i] << " expected";
    }
  }
  if (back.elements != mesh.elements)
  {
    return ::testing::AssertionFailure() << "the elements differ";
  }
  if (back.fixed != mesh.fixed)
  {
    return ::testing::AssertionFailure() << "the fixed flags differ";
  }
  return ::testing::AssertionSuccess();
}
/** A copy of a scalar image (whole buffer) with every intensity multiplied by 2^exponent: exact, so the method must
 * give the same field for it (the density filter's intensity scale). */
template <typename TImage>
typename TImage::Pointer
ScaledByPowerOfTwo(const TImage * image, int exponent)
{
  auto out = TImage::New();
  out->CopyInformation(image);
  out->SetRegions(image->GetLargestPossibleRegion());
  out->Allocate();
  const size_t n = image->GetLargestPossibleRegion().GetNumberOfPixels();
  for (size_t p = 0; p < n; ++p)
  {
    out->GetBufferPointer()[p] = std::ldexp(image->GetBufferPointer()[p], exponent);
  }
  return out;
}

} // namespace test
} // namespace dmr
} // namespace itk

#endif
