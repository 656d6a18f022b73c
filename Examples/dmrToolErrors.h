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
#ifndef dmrToolErrors_h
#define dmrToolErrors_h

// Error reporting shared by the command-line tools: every failure is one line on stderr and a non-zero exit code
// (2 for bad input, 1 for a failure while running).
#include "itkMacro.h"
#include "itkObject.h"
#include <iostream>
#include <stdexcept>
#include <string>

namespace dmrtools
{
/** A bad-input error: reported as one line, exit code 2. */
struct UsageError : std::runtime_error
{
  using std::runtime_error::runtime_error;
};

/** The message on one line (ITK's exception texts can span several), without runs of spaces. */
inline std::string
OneLine(std::string message)
{
  for (char & c : message)
  {
    if (c == '\n' || c == '\r' || c == '\t')
    {
      c = ' ';
    }
  }
  std::string out;
  for (char c : message)
  {
    if (!(c == ' ' && !out.empty() && out.back() == ' '))
    {
      out += c;
    }
  }
  while (!out.empty() && out.back() == ' ')
  {
    out.pop_back();
  }
  return out;
}

/** Runs a tool's body and turns every exception into "<tool>: error: <one line>" on stderr and an exit code. */
template <typename TBody>
int
RunReportingErrors(const char * tool, TBody && body)
{
  itk::Object::GlobalWarningDisplayOff(); // warnings (e.g. GDCM's "no series found") would break one-line errors
  try
  {
    return body();
  }
  catch (const UsageError & e)
  {
    std::cerr << tool << ": error: " << OneLine(e.what()) << '\n';
    return 2;
  }
  catch (const itk::ExceptionObject & e)
  {
    std::cerr << tool << ": error: " << OneLine(e.GetDescription()) << '\n';
    return 1;
  }
  catch (const std::exception & e)
  {
    std::cerr << tool << ": error: " << OneLine(e.what()) << '\n';
    return 1;
  }
}
} // namespace dmrtools

#endif
