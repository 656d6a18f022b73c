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
#ifndef dmrToolOutput_h
#define dmrToolOutput_h

// Output of the command-line tools: nothing half-written reaches the output directory.
#include "dmrToolErrors.h"
#include "itkImageFileWriter.h"
#include "itksys/Directory.hxx"
#include "itksys/SystemTools.hxx"
#include <cstdio>
#include <stdexcept>
#include <string>
#include <unistd.h>

namespace dmrtools
{
/** Everything is written into a private staging folder inside the output directory and moved into place only when
 * the run succeeded, so a failure never leaves half-written outputs. */
struct Staging
{
  std::string dir, stage;
  bool        createdDir{ false };
  bool        committed{ false };
  explicit Staging(const std::string & outputDir)
    : dir(outputDir)
  {
    if (!itksys::SystemTools::FileExists(dir))
    {
      createdDir = true;
    }
    else if (!itksys::SystemTools::FileIsDirectory(dir))
    {
      throw UsageError("--output-dir exists and is not a directory: " + dir);
    }
    stage = dir + "/.dmr-partial-" + std::to_string(::getpid());
    if (!itksys::SystemTools::MakeDirectory(stage))
    {
      throw UsageError("cannot create the output directory " + dir);
    }
  }
  std::string
  Path(const std::string & name) const
  {
    return stage + "/" + name;
  }
  void
  Commit()
  {
    itksys::Directory listing;
    listing.Load(stage);
    for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
    {
      const std::string name = listing.GetFile(i);
      if (name == "." || name == "..")
        continue;
      if (std::rename((stage + "/" + name).c_str(), (dir + "/" + name).c_str()) != 0)
      {
        throw std::runtime_error("could not move " + name + " into " + dir);
      }
    }
    itksys::SystemTools::RemoveADirectory(stage);
    committed = true;
  }
  ~Staging()
  {
    if (!committed)
    {
      itksys::SystemTools::RemoveADirectory(stage);
      if (createdDir)
      {
        itksys::SystemTools::RemoveADirectory(dir);
      }
    }
  }
};

/** Writes an image (compressed where the format allows). */
template <typename TImage>
void
WriteImage(const TImage * image, const std::string & path)
{
  auto writer = itk::ImageFileWriter<TImage>::New();
  writer->SetInput(image);
  writer->SetFileName(path);
  writer->UseCompressionOn();
  writer->Update();
}
} // namespace dmrtools

#endif
