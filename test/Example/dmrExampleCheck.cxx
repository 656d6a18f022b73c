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
// dmrExampleCheck: small helper for the command-line smoke tests of the example tools (test/Example).
//   dmrExampleCheck same-grid A B          exit 0 iff A and B have the same dimension, size, spacing, origin and
//                                          direction (any pixel type, any number of components)
//   dmrExampleCheck components A N         exit 0 iff every pixel of A has N components
//   dmrExampleCheck min-above A T          exit 0 iff every pixel (every component) of A is > T
//   dmrExampleCheck border-equals A V1,V2[,V3]  exit 0 iff every pixel on A's border equals (V1, V2[, V3])
//   dmrExampleCheck make-3d OUT [SHIFT]    writes a 16x12x10 float image with a gradient and a bright cube (moved by
//                                          SHIFT voxels along x)
//   dmrExampleCheck make-3d-mask OUT [V]   writes a mask of the inner part of that image on a coarser grid (spacing 2),
//                                          float, V (default 1) inside and 0 outside
//   dmrExampleCheck make-3d-mask-fine OUT D  the same inner part as a 0/1 mask on the make-3d grid, its origin moved by
//                                          D mm along every axis (D = 0: exactly that grid)
//   dmrExampleCheck make-constant OUT      writes a 32x32 float image that is 7 everywhere
//   dmrExampleCheck make-2d OUT            writes a 32x32 float image with a gradient and a bright square
//   dmrExampleCheck make-2d-byte OUT [SHIFT]  the same as unsigned char (e.g. a .png), the square moved by SHIFT
//   dmrExampleCheck make-nonfinite OUT     the make-2d image with one pixel NaN (a format that keeps it: .mha)
#include "itkImage.h"
#include "itkVectorImage.h"
#include "itkImageFileReader.h"
#include "itkImageFileWriter.h"
#include "itkImageIOFactory.h"
#include "itkImageRegionConstIterator.h"
#include "itkImageRegionConstIteratorWithIndex.h"
#include "itkImageRegionIteratorWithIndex.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

namespace
{
/** Dimension of an image file as stored (no squeezing of unit axes). */
unsigned int
FileDimension(const std::string & path)
{
  auto io = itk::ImageIOFactory::CreateImageIO(path.c_str(), itk::ImageIOFactory::IOFileModeEnum::ReadMode);
  if (!io)
  {
    throw std::runtime_error("cannot read an image from " + path);
  }
  io->SetFileName(path);
  io->ReadImageInformation();
  return io->GetNumberOfDimensions();
}

template <unsigned int D>
typename itk::VectorImage<double, D>::Pointer
Read(const std::string & path)
{
  auto reader = itk::ImageFileReader<itk::VectorImage<double, D>>::New();
  reader->SetFileName(path);
  reader->Update();
  return reader->GetOutput();
}

template <unsigned int D>
int
SameGrid(const std::string & pathA, const std::string & pathB)
{
  const auto a = Read<D>(pathA);
  const auto b = Read<D>(pathB);
  int        failures = 0;
  const auto sizeA = a->GetLargestPossibleRegion().GetSize();
  const auto sizeB = b->GetLargestPossibleRegion().GetSize();
  if (sizeA != sizeB)
  {
    std::cerr << "size differs: " << sizeA << " vs " << sizeB << '\n';
    ++failures;
  }
  if (a->GetLargestPossibleRegion().GetIndex() != b->GetLargestPossibleRegion().GetIndex())
  {
    std::cerr << "start index differs\n";
    ++failures;
  }
  const double tol = 1e-5;
  for (unsigned int i = 0; i < D; ++i)
  {
    const double scale = std::max(1.0, std::abs(a->GetSpacing()[i]));
    if (std::abs(a->GetSpacing()[i] - b->GetSpacing()[i]) > tol * scale)
    {
      std::cerr << "spacing differs: " << a->GetSpacing() << " vs " << b->GetSpacing() << '\n';
      ++failures;
      break;
    }
  }
  for (unsigned int i = 0; i < D; ++i)
  {
    const double scale = std::max(1.0, std::abs(a->GetOrigin()[i]));
    if (std::abs(a->GetOrigin()[i] - b->GetOrigin()[i]) > tol * scale)
    {
      std::cerr << "origin differs: " << a->GetOrigin() << " vs " << b->GetOrigin() << '\n';
      ++failures;
      break;
    }
  }
  for (unsigned int i = 0; i < D; ++i)
  {
    for (unsigned int j = 0; j < D; ++j)
    {
      if (std::abs(a->GetDirection()(i, j) - b->GetDirection()(i, j)) > tol)
      {
        std::cerr << "direction differs:\n" << a->GetDirection() << "vs\n" << b->GetDirection();
        ++failures;
        i = j = D;
      }
    }
  }
  if (failures == 0)
  {
    std::cout << "same grid: size " << sizeA << ", spacing " << a->GetSpacing() << ", origin " << a->GetOrigin()
              << '\n';
  }
  return failures == 0 ? EXIT_SUCCESS : EXIT_FAILURE;
}

template <unsigned int D>
int
Components(const std::string & path, unsigned int expected)
{
  const auto image = Read<D>(path);
  const auto n = image->GetNumberOfComponentsPerPixel();
  if (n != expected)
  {
    std::cerr << path << " has " << n << " components per pixel, expected " << expected << '\n';
    return EXIT_FAILURE;
  }
  std::cout << path << ": " << n << " components per pixel\n";
  return EXIT_SUCCESS;
}

/** Every pixel on the border of A (index 0 or last along some axis) equals the given components, to 1e-4 of their
 * size (at least 1e-4). */
template <unsigned int D>
int
BorderEquals(const std::string & path, const std::vector<double> & expected)
{
  const auto image = Read<D>(path);
  if (image->GetNumberOfComponentsPerPixel() != expected.size())
  {
    std::cerr << path << " has " << image->GetNumberOfComponentsPerPixel() << " components, " << expected.size()
              << " values given\n";
    return EXIT_FAILURE;
  }
  const auto region = image->GetLargestPossibleRegion();
  double     worst = 0.0;
  size_t     border = 0;
  for (itk::ImageRegionConstIteratorWithIndex<itk::VectorImage<double, D>> it(image, region); !it.IsAtEnd(); ++it)
  {
    bool onBorder = false;
    for (unsigned int k = 0; k < D; ++k)
    {
      onBorder = onBorder || it.GetIndex()[k] == region.GetIndex(k) || it.GetIndex()[k] == region.GetUpperIndex()[k];
    }
    if (!onBorder)
    {
      continue;
    }
    ++border;
    const auto v = it.Get();
    for (unsigned int c = 0; c < expected.size(); ++c)
    {
      const double error = std::abs(v[c] - expected[c]) / std::max(1.0, std::abs(expected[c]));
      worst = std::isfinite(error) ? std::max(worst, error) : std::numeric_limits<double>::infinity();
    }
  }
  if (!(worst <= 1e-4))
  {
    std::cerr << path << ": a border pixel differs from the expected value by " << worst << " (relative)\n";
    return EXIT_FAILURE;
  }
  std::cout << path << ": all " << border << " border pixels equal the expected value (largest relative difference "
            << worst << ")\n";
  return EXIT_SUCCESS;
}

template <unsigned int D>
int
MinAbove(const std::string & path, double threshold)
{
  const auto image = Read<D>(path);
  double     lowest = std::numeric_limits<double>::infinity();
  size_t     count = 0;
  for (itk::ImageRegionConstIterator<itk::VectorImage<double, D>> it(image, image->GetLargestPossibleRegion());
       !it.IsAtEnd();
       ++it)
  {
    const auto v = it.Get();
    for (unsigned int k = 0; k < v.GetSize(); ++k)
    {
      if (!std::isfinite(v[k]))
      {
        std::cerr << path << " holds a non-finite value\n";
        return EXIT_FAILURE;
      }
      lowest = std::min(lowest, v[k]);
      ++count;
    }
  }
  if (count == 0 || !(lowest > threshold))
  {
    std::cerr << path << ": minimum " << lowest << " over " << count << " values is not > " << threshold << '\n';
    return EXIT_FAILURE;
  }
  std::cout << path << ": minimum " << lowest << " > " << threshold << '\n';
  return EXIT_SUCCESS;
}

template <typename TImage>
void
Write(const TImage * image, const std::string & path)
{
  auto writer = itk::ImageFileWriter<TImage>::New();
  writer->SetInput(image);
  writer->SetFileName(path);
  writer->Update();
}

int
Make3D(const std::string & path, int shift, unsigned int depth = 10)
{
  using ImageType = itk::Image<float, 3>;
  auto                image = ImageType::New();
  ImageType::SizeType size{ { 16, 12, depth } };
  image->SetRegions(ImageType::RegionType(size));
  image->Allocate();
  for (itk::ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion()); !it.IsAtEnd(); ++it)
  {
    const auto & idx = it.GetIndex();
    const bool   cube =
      idx[0] >= 4 + shift && idx[0] < 10 + shift && idx[1] >= 3 && idx[1] < 8 && idx[2] >= 2 && idx[2] < 7;
    it.Set(static_cast<float>(0.01 * idx[0] + (cube ? 1.0 : 0.0)));
  }
  Write(image.GetPointer(), path);
  return FileDimension(path) == 3 ? EXIT_SUCCESS : EXIT_FAILURE;
}

int
Make3DMask(const std::string & path, double inside)
{
  // float, so that an inside value such as 0.5 or 256 is stored as given
  using MaskType = itk::Image<float, 3>;
  auto               mask = MaskType::New();
  MaskType::SizeType size{ { 8, 6, 5 } };
  mask->SetRegions(MaskType::RegionType(size));
  MaskType::SpacingType spacing;
  spacing.Fill(2.0);
  mask->SetSpacing(spacing);
  MaskType::PointType origin;
  origin.Fill(0.5);
  mask->SetOrigin(origin);
  mask->Allocate();
  for (itk::ImageRegionIteratorWithIndex<MaskType> it(mask, mask->GetLargestPossibleRegion()); !it.IsAtEnd(); ++it)
  {
    const auto & idx = it.GetIndex();
    it.Set(idx[0] >= 1 && idx[0] < 7 && idx[1] >= 1 && idx[1] < 5 && idx[2] >= 1 && idx[2] < 4 ? inside : 0.0);
  }
  auto writer = itk::ImageFileWriter<MaskType>::New();
  writer->SetInput(mask);
  writer->SetFileName(path);
  writer->Update();
  return EXIT_SUCCESS;
}

/** The inner part of the make-3d image (voxels 2..13 x 2..9 x 2..7) as a 0/1 mask on its 16x12x10 grid (spacing 1,
 * origin 0), the origin moved by `shift` mm along every axis: a header that differs from the image's by a rounding. */
int
Make3DMaskFine(const std::string & path, double shift)
{
  using MaskType = itk::Image<unsigned char, 3>;
  auto               mask = MaskType::New();
  MaskType::SizeType size{ { 16, 12, 10 } };
  mask->SetRegions(MaskType::RegionType(size));
  MaskType::PointType origin;
  origin.Fill(shift);
  mask->SetOrigin(origin);
  mask->Allocate();
  for (itk::ImageRegionIteratorWithIndex<MaskType> it(mask, mask->GetLargestPossibleRegion()); !it.IsAtEnd(); ++it)
  {
    const auto & idx = it.GetIndex();
    it.Set(idx[0] >= 2 && idx[0] < 14 && idx[1] >= 2 && idx[1] < 10 && idx[2] >= 2 && idx[2] < 8 ? 1 : 0);
  }
  Write(mask.GetPointer(), path);
  return EXIT_SUCCESS;
}

/** 32x32 image: a gradient along y (gradient per row) plus a bright square of value `square` (columns 8..19 moved by
 * shift along x, rows 10..23). */
template <typename TPixel>
typename itk::Image<TPixel, 2>::Pointer
GradientAndSquare(int shift, double gradient, double square)
{
  using ImageType = itk::Image<TPixel, 2>;
  auto                         image = ImageType::New();
  typename ImageType::SizeType size{ { 32, 32 } };
  image->SetRegions(typename ImageType::RegionType(size));
  image->Allocate();
  for (itk::ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion()); !it.IsAtEnd(); ++it)
  {
    const auto & idx = it.GetIndex();
    const bool   inside = idx[0] >= 8 + shift && idx[0] < 20 + shift && idx[1] >= 10 && idx[1] < 24;
    it.Set(static_cast<TPixel>(gradient * idx[1] + (inside ? square : 0.0)));
  }
  return image;
}

int
Make2D(const std::string & path, bool constant)
{
  auto image = GradientAndSquare<float>(0, 0.01, 1.0);
  if (constant)
  {
    image->FillBuffer(7.0f);
  }
  Write(image.GetPointer(), path);
  return FileDimension(path) == 2 ? EXIT_SUCCESS : EXIT_FAILURE;
}

int
Make2DByte(const std::string & path, int shift)
{
  Write(GradientAndSquare<unsigned char>(shift, 2.0, 180.0).GetPointer(), path);
  return FileDimension(path) == 2 ? EXIT_SUCCESS : EXIT_FAILURE;
}

int
MakeNonFinite(const std::string & path)
{
  using ImageType = itk::Image<float, 2>;
  auto image = GradientAndSquare<float>(0, 0.01, 1.0);
  image->SetPixel({ { 5, 3 } }, std::numeric_limits<float>::quiet_NaN());
  Write(image.GetPointer(), path);
  // the format must keep the NaN, or the check is void
  auto reader = itk::ImageFileReader<ImageType>::New();
  reader->SetFileName(path);
  reader->Update();
  return std::isnan(reader->GetOutput()->GetPixel({ { 5, 3 } })) ? EXIT_SUCCESS : EXIT_FAILURE;
}

/** A folded 2D displacement field on the grid of the 2D image `reference`: u_x = 3 sin(2 pi i_0 / 6) pixels along
 * the image's first axis (det(I + grad u) down to about -1.7), mm, physical frame. */
int
MakeFoldedField(const std::string & path, const std::string & reference)
{
  using FieldType = itk::Image<itk::Vector<float, 2>, 2>;
  auto reader = itk::ImageFileReader<itk::Image<float, 2>>::New();
  reader->SetFileName(reference);
  reader->Update();
  const auto * image = reader->GetOutput();
  auto         field = FieldType::New();
  field->CopyInformation(image);
  field->SetRegions(image->GetLargestPossibleRegion());
  field->Allocate();
  itk::ImageRegionIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    const double a = 3.0 * std::sin(2.0 * M_PI * static_cast<double>(it.GetIndex()[0]) / 6.0) * image->GetSpacing()[0];
    FieldType::PixelType u;
    for (unsigned int k = 0; k < 2; ++k)
    {
      u[k] = static_cast<float>(a * image->GetDirection()[k][0]);
    }
    it.Set(u);
  }
  Write(field.GetPointer(), path);
  return EXIT_SUCCESS;
}

int
Usage()
{
  std::cerr << "usage: dmrExampleCheck same-grid A B | components A N | min-above A T | border-equals A V1,V2[,V3] | "
               "make-3d OUT [SHIFT] | "
               "make-3d-thin OUT | make-3d-mask OUT [VALUE] | make-3d-mask-fine OUT SHIFT | "
               "make-2d OUT | make-2d-byte OUT [SHIFT] | make-nonfinite OUT | make-folded-field OUT REFERENCE | "
               "make-constant OUT\n";
  return 2;
}
} // namespace

int
main(int argc, char * argv[])
{
  if (argc < 3)
  {
    return Usage();
  }
  const std::string mode = argv[1];
  try
  {
    if (mode == "make-3d" && (argc == 3 || argc == 4))
    {
      return Make3D(argv[2], argc == 4 ? std::atoi(argv[3]) : 0);
    }
    if (mode == "make-3d-thin" && argc == 3)
    {
      return Make3D(argv[2], 0, 3); // 16 x 12 x 3: fewer than the 4 voxels per axis a registration needs
    }
    if (mode == "make-3d-mask" && (argc == 3 || argc == 4))
    {
      return Make3DMask(argv[2], argc == 4 ? std::atof(argv[3]) : 1.0);
    }
    if (mode == "make-3d-mask-fine" && argc == 4)
    {
      return Make3DMaskFine(argv[2], std::atof(argv[3]));
    }
    if (mode == "make-constant" && argc == 3)
    {
      return Make2D(argv[2], true);
    }
    if (mode == "make-2d" && argc == 3)
    {
      return Make2D(argv[2], false);
    }
    if (mode == "make-2d-byte" && (argc == 3 || argc == 4))
    {
      return Make2DByte(argv[2], argc == 4 ? std::atoi(argv[3]) : 0);
    }
    if (mode == "make-nonfinite" && argc == 3)
    {
      return MakeNonFinite(argv[2]);
    }
    if (mode == "make-folded-field" && argc == 4)
    {
      return MakeFoldedField(argv[2], argv[3]);
    }
    if (argc != 4)
    {
      return Usage();
    }
    const unsigned int d = FileDimension(argv[2]);
    if (mode == "same-grid")
    {
      const unsigned int dB = FileDimension(argv[3]);
      if (d != dB)
      {
        std::cerr << "dimension differs: " << d << "D vs " << dB << "D\n";
        return EXIT_FAILURE;
      }
      if (d == 2)
        return SameGrid<2>(argv[2], argv[3]);
      if (d == 3)
        return SameGrid<3>(argv[2], argv[3]);
    }
    else if (mode == "border-equals")
    {
      std::vector<double> values;
      std::string         list = argv[3];
      for (size_t start = 0; start <= list.size();)
      {
        const size_t comma = std::min(list.find(',', start), list.size());
        const auto   item = list.substr(start, comma - start);
        char *       end = nullptr;
        values.push_back(std::strtod(item.c_str(), &end));
        if (item.empty() || *end != '\0')
        {
          return Usage();
        }
        start = comma + 1;
      }
      if (d == 2)
        return BorderEquals<2>(argv[2], values);
      if (d == 3)
        return BorderEquals<3>(argv[2], values);
    }
    else if (mode == "components" || mode == "min-above")
    {
      char *       end = nullptr;
      const double value = std::strtod(argv[3], &end);
      if (*end != '\0')
      {
        return Usage();
      }
      if (mode == "components")
      {
        if (d == 2)
          return Components<2>(argv[2], static_cast<unsigned int>(value));
        if (d == 3)
          return Components<3>(argv[2], static_cast<unsigned int>(value));
      }
      else
      {
        if (d == 2)
          return MinAbove<2>(argv[2], value);
        if (d == 3)
          return MinAbove<3>(argv[2], value);
      }
    }
    else
    {
      return Usage();
    }
    std::cerr << "unsupported dimension " << d << '\n';
    return EXIT_FAILURE;
  }
  catch (const std::exception & e)
  {
    std::cerr << "dmrExampleCheck: " << e.what() << '\n';
    return EXIT_FAILURE;
  }
}
