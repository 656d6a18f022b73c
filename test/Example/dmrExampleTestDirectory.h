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
#ifndef dmrExampleTestDirectory_h
#define dmrExampleTestDirectory_h

#include "itksys/SystemTools.hxx"
#include <string>
#include <unistd.h>

namespace dmrtools
{
namespace test
{
/** A scratch directory for one test binary's files, <working directory>/<name>-<process id>, created if needed. */
inline std::string
TemporaryDirectory(const std::string & name)
{
  const std::string dir =
    itksys::SystemTools::GetCurrentWorkingDirectory() + "/" + name + "-" + std::to_string(::getpid());
  itksys::SystemTools::MakeDirectory(dir);
  return dir;
}
} // namespace test
} // namespace dmrtools

#endif
