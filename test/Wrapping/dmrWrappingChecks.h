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
#ifndef dmrWrappingChecks_h
#define dmrWrappingChecks_h

#include "dmrObjectChecks.h"
#include "itkDynamicMeshRegistrationEnums.h"
#include "itkImage.h" // the image and vector types the .wrap files name (WrapITK includes them from ITKCommon)
#include "itkProcessObject.h"
#include "itkVector.h"
#include <set>
#include <sstream>
#include <string>
#include <type_traits>

namespace itk
{
namespace dmr
{
namespace test
{
/** What Python gets from a wrapped filter template: New() gives an object of the named class, a ProcessObject with
 * its ITK object methods (names, Print), whose pipeline can be asked for its outputs. */
template <typename TWrapped>
::testing::AssertionResult
IsWrappableProcessObject(const std::string & className)
{
  static_assert(std::is_base_of_v<ProcessObject, TWrapped>, "the module wraps pipeline objects");
  typename TWrapped::Pointer object = TWrapped::New();
  const auto basic = BasicObjectMethods(object.GetPointer(), className, object->Superclass::GetNameOfClass());
  if (!basic)
  {
    return basic;
  }
  if (object->GetNumberOfIndexedOutputs() == 0)
  {
    return ::testing::AssertionFailure() << className << " has no output";
  }
  return ::testing::AssertionSuccess();
}

/** The enums class: every value prints a distinct name (Python shows these). */
template <typename TEnums>
::testing::AssertionResult
IsWrappableSimpleClass()
{
  static_assert(std::is_same_v<TEnums, DynamicMeshRegistrationEnums>, "the enums class is the one simple class");
  std::set<std::string> names;
  size_t                values = 0;
  auto                  add = [&](auto value) {
    std::ostringstream os;
    os << value;
    names.insert(os.str());
    ++values;
  };
  using E = DynamicMeshRegistrationEnums;
  for (auto v : { E::Backend::CPU, E::Backend::CUDA, E::Backend::Auto })
  {
    add(v);
  }
  for (auto v : { E::MeshMode::Dynamic, E::MeshMode::Regular, E::MeshMode::Static })
  {
    add(v);
  }
  for (auto v : { E::ForceGradient::WarpedMoving, E::ForceGradient::MappedMoving })
  {
    add(v);
  }
  if (names.size() != values || names.count("") != 0)
  {
    return ::testing::AssertionFailure() << values << " enum values print " << names.size() << " distinct names";
  }
  return ::testing::AssertionSuccess();
}
} // namespace test
} // namespace dmr
} // namespace itk

#endif
