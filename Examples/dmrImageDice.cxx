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
#include "dmrImageMetrics.h"
#include "itkImageFileReader.h"
#include <iostream>

int
main(int argc, char * argv[])
{
  if (argc < 3 || argc > 4)
  {
    std::cerr << "usage: dmrImageDice A B [threshold]\n";
    return 2;
  }
  try
  {
    using ImageType = itk::Image<float, 3>; // 2D files read as one slice
    auto a = itk::ImageFileReader<ImageType>::New();
    a->SetFileName(argv[1]);
    a->Update();
    auto b = itk::ImageFileReader<ImageType>::New();
    b->SetFileName(argv[2]);
    b->Update();
    const double t = argc == 4 ? std::atof(argv[3]) : 0.5;
    std::cout << itk::dmr::DiceCoefficient(a->GetOutput(), b->GetOutput(), t) << '\n';
  }
  catch (const itk::ExceptionObject & e)
  {
    std::cerr << "dmrImageDice: error: " << e.GetDescription() << '\n';
    return 1;
  }
  return 0;
}
