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
// The tools' error reporting (dmrToolErrors.h): what a run that runs out of memory or of threads prints and returns.
// The smoke test ExampleBadInputThreadLimit runs the tool itself under such a limit.
#include "dmrToolErrors.h"
#include "gtest/gtest.h"
#include <new>
#include <sstream>
#include <system_error>

namespace
{
/** RunReportingErrors(body) with std::cerr captured: {exit code, what it printed}. */
template <typename TBody>
std::pair<int, std::string>
Report(TBody && body)
{
  std::ostringstream captured;
  auto *             previous = std::cerr.rdbuf(captured.rdbuf());
  const int          code = dmrtools::RunReportingErrors("tool", std::forward<TBody>(body));
  std::cerr.rdbuf(previous);
  return { code, captured.str() };
}
} // namespace

TEST(ToolErrors, OutOfMemoryIsSaidAsSuch)
{
  const auto [code, text] = Report([]() -> int { throw std::bad_alloc(); });
  EXPECT_EQ(code, 1);
  EXPECT_EQ(text.rfind("tool: error: out of memory (std::bad_alloc)", 0), 0u) << text;
  EXPECT_EQ(text.find('\n'), text.size() - 1) << "one line: " << text;

  const auto [itkCode, itkText] = Report([]() -> int {
    throw itk::MemoryAllocationError(__FILE__, __LINE__, "Failed to allocate memory for image.", ITK_LOCATION);
  });
  EXPECT_EQ(itkCode, 1);
  EXPECT_EQ(itkText, "tool: error: out of memory: Failed to allocate memory for image.\n");
}

TEST(ToolErrors, AThreadThatCannotStartIsSaidAsSuch)
{
  const auto [code, text] =
    Report([]() -> int { throw std::system_error(std::make_error_code(std::errc::resource_unavailable_try_again)); });
  EXPECT_EQ(code, 1);
  EXPECT_NE(text.find("a thread could not start"), std::string::npos) << text;
  EXPECT_EQ(text.find('\n'), text.size() - 1) << "one line: " << text;
  // another system error keeps its own message only
  const auto [otherCode, otherText] =
    Report([]() -> int { throw std::system_error(std::make_error_code(std::errc::permission_denied)); });
  EXPECT_EQ(otherCode, 1);
  EXPECT_EQ(otherText.find("thread"), std::string::npos) << otherText;
}

TEST(ToolErrors, RequireThreadsStartsThemAllAtOnce)
{
  // within any limit a test machine has; the refusal itself is the smoke test's (a limit set for the tool only)
  EXPECT_NO_THROW(dmrtools::RequireThreads(16));
  EXPECT_NO_THROW(dmrtools::RequireThreads(0));
}
