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
