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
// Compiled only with DMR_USE_CUDA=OFF: every launcher of the dual mesh stage reports that CUDA is unavailable.
#include "dmrDualMeshBackend.h"

namespace itk
{
namespace dmr
{
namespace cuda
{
namespace
{
Status
BuiltWithoutCuda()
{
  return Status::Error("the dual mesh CUDA back-end is unavailable: built without CUDA (DMR_USE_CUDA=OFF)");
}
} // namespace

struct LabelSummarizer::Impl
{
};

LabelSummarizer::LabelSummarizer()
  : m_Impl(nullptr)
{
}

LabelSummarizer::~LabelSummarizer() = default;

Status
LabelSummarizer::Summarize(unsigned int, const size_t *, const int32_t *, size_t, LabelSummary &)
{
  return BuiltWithoutCuda();
}

Status
LabelSummarizer::UploadLabels(const int32_t *, size_t)
{
  return BuiltWithoutCuda();
}

const int32_t *
LabelSummarizer::UploadedLabels() const
{
  return nullptr;
}

size_t
LabelSummarizer::AllocatedBytes() const
{
  return 0;
}

Status
LabelSummarizer::SummarizeHostLabels(unsigned int, const size_t *, const int32_t *, size_t, LabelSummary &)
{
  return BuiltWithoutCuda();
}

Status
SummarizeLabels(unsigned int, const size_t *, const int32_t *, size_t, LabelSummary &)
{
  return BuiltWithoutCuda();
}

Status
SummarizeHostLabels(unsigned int, const size_t *, const int32_t *, size_t, LabelSummary &)
{
  return BuiltWithoutCuda();
}
} // namespace cuda
} // namespace dmr
} // namespace itk
