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
#ifndef dmrFieldImage_h
#define dmrFieldImage_h

#include "dmrFieldOps.h"
#include "itkImage.h"
#include <vector>

namespace itk
{
namespace dmr
{
/** Physical-frame displacement image -> grid-frame flat field (u_grid = Direction^T u_phys). */
template <typename TField>
std::vector<float>
ToGridFrame(const TField * field)
{
  constexpr unsigned int D = TField::ImageDimension;
  const auto &           dir = field->GetDirection();
  const size_t           n = field->GetLargestPossibleRegion().GetNumberOfPixels();
  std::vector<float>     out(n * D);
  const auto *           in = field->GetBufferPointer();
  for (size_t p = 0; p < n; ++p)
  {
    for (unsigned int r = 0; r < D; ++r)
    {
      double v = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        v += dir[k][r] * in[p][k];
      }
      out[p * D + r] = static_cast<float>(v);
    }
  }
  return out;
}

/** Grid-frame flat field -> the buffer of a physical displacement image of as many pixels (u_phys = Direction
 * u_grid, the inverse rotation of ToGridFrame), on the threader. */
template <typename TField>
void
FromGridFrame(const float *                          grid,
              const typename TField::DirectionType & dir,
              TField *                               image,
              MultiThreaderBase *                    threader)
{
  constexpr unsigned int D = TField::ImageDimension;
  auto *                 out = image->GetBufferPointer();
  ParallelForChunks(threader, image->GetBufferedRegion().GetNumberOfPixels(), [&](size_t b, size_t e) {
    for (size_t p = b; p < e; ++p)
    {
      for (unsigned int r = 0; r < D; ++r)
      {
        double v = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          v += dir[r][k] * grid[p * D + k];
        }
        out[p][r] = static_cast<typename TField::PixelType::ValueType>(v);
      }
    }
  });
}

/** The inverse of the transformation x -> x + u(x) of a physical displacement field, on the field's own grid:
 * y -> y + v(y) with v(y) = -u(y + v(y)) (InvertField in the grid frame, u interpolated multilinearly and clamped to
 * the border, as the registration composes fields). Throws an ExceptionObject for a folded field, det(I + grad u)
 * <= 0 somewhere (central differences, as JacobianDeterminant): it has no inverse, although the iteration of every
 * voxel, which looks for one point that maps onto it, may well converge there. Throws too when the iteration leaves a
 * residual |v(y) + u(y + v(y))| above `tolerance` voxels after `maximumIterations`. outcome, when given, receives
 * the residual and the number of iterations. */
template <typename TField>
typename TField::Pointer
InverseDisplacementField(const TField *      field,
                         MultiThreaderBase * threader,
                         FieldInversion *    outcome = nullptr,
                         unsigned int        maximumIterations = 200,
                         double              tolerance = 1e-3)
{
  constexpr unsigned int D = TField::ImageDimension;
  const auto             grid = Grid<D>::FromImage(field);
  const auto             u = ToGridFrame(field);
  const auto             detRange = JacobianDeterminant<D>(grid, u.data(), nullptr, threader);
  if (!(detRange.first > 0.0))
  {
    itkGenericExceptionMacro("the displacement field is folded (det(I + grad u) down to " << detRange.first
                                                                                          << "): it has no inverse");
  }
  std::vector<float>   v(u.size());
  const FieldInversion result = InvertField<D>(grid, u.data(), v.data(), threader, maximumIterations, tolerance);
  if (outcome)
  {
    *outcome = result;
  }
  if (!(result.residual <= tolerance))
  {
    itkGenericExceptionMacro("no inverse of the displacement field was found: after "
                             << result.iterations << " fixed-point iterations v(y) = -u(y + v(y)) is still off by "
                             << result.residual << " voxel somewhere (more than " << tolerance << ")");
  }
  auto inverse = TField::New();
  inverse->CopyInformation(field);
  inverse->SetRegions(field->GetLargestPossibleRegion());
  inverse->Allocate();
  FromGridFrame(v.data(), field->GetDirection(), inverse.GetPointer(), threader);
  return inverse;
}

/** det(I + grad u) of a physical displacement field as an image on the field's grid (equal to the determinant in
 * the grid frame, since the direction is a rotation/reflection). minMax receives the extreme values. */
template <typename TField>
typename Image<float, TField::ImageDimension>::Pointer
JacobianDeterminantImage(const TField * field, std::pair<double, double> & minMax, MultiThreaderBase * threader)
{
  constexpr unsigned int D = TField::ImageDimension;
  auto                   jac = Image<float, D>::New();
  jac->CopyInformation(field);
  jac->SetRegions(field->GetLargestPossibleRegion());
  jac->Allocate();
  const auto grid = Grid<D>::FromImage(field);
  const auto u = ToGridFrame(field);
  minMax = JacobianDeterminant<D>(grid, u.data(), jac->GetBufferPointer(), threader);
  return jac;
}
} // namespace dmr
} // namespace itk

#endif
