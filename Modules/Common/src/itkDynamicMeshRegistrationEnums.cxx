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
#include "itkDynamicMeshRegistrationEnums.h"

namespace itk
{
std::ostream &
operator<<(std::ostream & out, const DynamicMeshRegistrationEnums::Backend value)
{
  switch (value)
  {
    case DynamicMeshRegistrationEnums::Backend::CPU:
      return out << "cpu";
    case DynamicMeshRegistrationEnums::Backend::CUDA:
      return out << "cuda";
    case DynamicMeshRegistrationEnums::Backend::Auto:
      return out << "auto";
  }
  return out << "INVALID Backend";
}

std::ostream &
operator<<(std::ostream & out, const DynamicMeshRegistrationEnums::MeshMode value)
{
  switch (value)
  {
    case DynamicMeshRegistrationEnums::MeshMode::Dynamic:
      return out << "dynamic";
    case DynamicMeshRegistrationEnums::MeshMode::Regular:
      return out << "regular";
    case DynamicMeshRegistrationEnums::MeshMode::Static:
      return out << "static";
  }
  return out << "INVALID MeshMode";
}

std::ostream &
operator<<(std::ostream & out, const DynamicMeshRegistrationEnums::ForceGradient value)
{
  switch (value)
  {
    case DynamicMeshRegistrationEnums::ForceGradient::WarpedMoving:
      return out << "warped";
    case DynamicMeshRegistrationEnums::ForceGradient::MappedMoving:
      return out << "mapped";
  }
  return out << "INVALID ForceGradient";
}
} // namespace itk
