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
#ifndef itkDynamicMeshRegistrationEnums_h
#define itkDynamicMeshRegistrationEnums_h

#include "DynamicMeshRegistrationExport.h"
#include <ostream>
#include <cstdint>

namespace itk
{
/** \class DynamicMeshRegistrationEnums
 * \brief Enumerations shared by the DynamicMeshRegistration filters.
 * \ingroup DynamicMeshRegistration */
class DynamicMeshRegistrationEnums
{
public:
  /** Which implementation runs a stage. Auto picks CUDA when a device is present. */
  enum class Backend : uint8_t
  {
    CPU = 0,
    CUDA = 1,
    Auto = 2
  };

  /** How FEMRegistrationMethod obtains its mesh. */
  enum class MeshMode : uint8_t
  {
    /** rebuilt every iteration from the density field (the paper's method) */
    Dynamic = 0,
    /** static regular grid of nodes, each quad/hex split into simplices */
    Regular = 1,
    /** static mesh supplied by the user (SetStaticMesh) */
    Static = 2
  };

  /** Which image gradient the force f = 2 (T - S o W) grad (paper Eq. 5) uses at a fixed-grid point x. */
  enum class ForceGradient : uint8_t
  {
    /** grad of the warped moving image, grad_x S(W(x)) = (I + grad u)^T (grad S)(W(x)): the derivative of the MSSD
     * with respect to the compositional update W <- W o exp(u) (default) */
    WarpedMoving = 0,
    /** the moving image's gradient mapped through W, (grad S)(W(x)): a literal reading of Eq. 5, which ignores the
     * stretch and rotation of the current transformation */
    MappedMoving = 1
  };
};

extern DynamicMeshRegistration_EXPORT std::ostream &
                                      operator<<(std::ostream & out, const DynamicMeshRegistrationEnums::Backend value);
extern DynamicMeshRegistration_EXPORT std::ostream &
operator<<(std::ostream & out, const DynamicMeshRegistrationEnums::MeshMode value);
extern DynamicMeshRegistration_EXPORT std::ostream &
operator<<(std::ostream & out, const DynamicMeshRegistrationEnums::ForceGradient value);
} // namespace itk

#endif
