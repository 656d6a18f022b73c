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
// dmrImageDice A B [threshold]: Dice overlap of {A > t} and {B > t} (t = 0.5 by default), e.g. of a warped
// binary/label image and its target.
#include "dmrErrorStatistics.h"
#include "dmrImageMetrics.h"
#include "dmrReadImage.h"
#include "dmrToolErrors.h"
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <string>

int
main(int argc, char * argv[])
{
  return dmrtools::RunReportingErrors("dmrImageDice", [&]() {
    const std::string usage = "usage: dmrImageDice A B [threshold]";
    if (argc == 2 && (std::string(argv[1]) == "--help" || std::string(argv[1]) == "-h"))
    {
      std::cout << usage
                << "\n  Dice overlap of {A > threshold} and {B > threshold} (default 0.5); A and B must lie "
                   "on one grid (2D or 3D images, or DICOM series directories)\n";
      return 0;
    }
    if (argc < 3 || argc > 4)
    {
      throw dmrtools::UsageError(usage);
    }
    double threshold = 0.5;
    if (argc == 4)
    {
      // the whole argument, a finite number: atof took 'nan' (every comparison false: Dice 1 of two empty sets)
      char * end = nullptr;
      errno = 0;
      threshold = std::strtod(argv[3], &end);
      if (end == argv[3] || *end != '\0' || errno == ERANGE || !std::isfinite(threshold))
      {
        throw dmrtools::UsageError("the threshold must be a finite number, got '" + std::string(argv[3]) + "'");
      }
    }
    dmrtools::StartItkThreadPool();
    using ImageType = itk::Image<float, 3>; // 2D files are read as one slice
    auto read = [](const std::string & path) {
      unsigned int components = 1;
      if (dmrtools::ImageDimensionOf(path, &components) > 3 || components != 1)
      {
        throw dmrtools::UsageError("not a scalar 2D or 3D image: " + path);
      }
      ImageType::Pointer image;
      try
      {
        image = dmrtools::ReadImageOrDicomSeries<ImageType>(path);
      }
      catch (const itk::ExceptionObject & e)
      {
        throw dmrtools::UsageError("cannot read " + path + ": " + e.GetDescription());
      }
      // a NaN compares false with the threshold: it was counted as outside without a word
      std::string index;
      double      value;
      if (dmrtools::FindNonFiniteVoxel(image.GetPointer(), index, value))
      {
        throw dmrtools::UsageError(path + " has a non-finite value (" + std::to_string(value) + ") at voxel " + index);
      }
      return image;
    };
    const auto a = read(argv[1]);
    const auto b = read(argv[2]);
    // voxel by voxel: the grids must be one (a same-sized image elsewhere in space gave a Dice without a word)
    if (!dmrtools::SameGrid<3>(a.GetPointer(), b.GetPointer()))
    {
      throw dmrtools::UsageError(
        std::string("the images lie on different grids (size, spacing, origin or direction): ") + argv[1] + ", " +
        argv[2]);
    }
    std::cout << itk::dmr::DiceCoefficient(a.GetPointer(), b.GetPointer(), threshold) << '\n';
    return 0;
  });
}
