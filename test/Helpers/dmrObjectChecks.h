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
#ifndef dmrObjectChecks_h
#define dmrObjectChecks_h

#include "gtest/gtest.h"
#include <initializer_list>
#include <sstream>
#include <string>

namespace itk
{
namespace dmr
{
namespace test
{
/** What ITK_EXERCISE_BASIC_OBJECT_METHODS checks, as an AssertionResult usable inside TEST bodies: class and
 * superclass names, and Print() runs and names the class. */
template <typename TObject>
::testing::AssertionResult
BasicObjectMethods(TObject * object, const std::string & className, const std::string & superclassName)
{
  if (object == nullptr)
  {
    return ::testing::AssertionFailure() << "null object";
  }
  if (className != object->GetNameOfClass())
  {
    return ::testing::AssertionFailure() << "GetNameOfClass() is " << object->GetNameOfClass() << ", expected "
                                         << className;
  }
  if (superclassName != object->TObject::Superclass::GetNameOfClass())
  {
    return ::testing::AssertionFailure() << "superclass name is " << object->TObject::Superclass::GetNameOfClass()
                                         << ", expected " << superclassName;
  }
  std::ostringstream os;
  object->Print(os);
  if (os.str().find(className) == std::string::npos)
  {
    return ::testing::AssertionFailure() << "Print() does not name the class:\n" << os.str();
  }
  return ::testing::AssertionSuccess();
}

/** Print() output contains "<member>:" for every given member name. */
template <typename TObject>
::testing::AssertionResult
PrintMentions(const TObject * object, std::initializer_list<std::string> members)
{
  std::ostringstream os;
  object->Print(os);
  const std::string text = os.str();
  for (const auto & member : members)
  {
    if (text.find(member + ":") == std::string::npos)
    {
      return ::testing::AssertionFailure() << "Print() does not mention " << member << ":\n" << text;
    }
  }
  return ::testing::AssertionSuccess();
}
} // namespace test
} // namespace dmr
} // namespace itk

/** Set then Get one property (what ITK_TEST_SET_GET_VALUE does, usable inside TEST bodies). */
#define DMR_EXPECT_SET_GET(object, Name, value)                                                                        \
  do                                                                                                                   \
  {                                                                                                                    \
    (object)->Set##Name(value);                                                                                        \
    EXPECT_EQ((object)->Get##Name(), (value)) << "Set/Get" #Name;                                                      \
  } while (false)

#endif
