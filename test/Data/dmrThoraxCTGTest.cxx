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
// The real thoracic CT (shared data, thorax-ct-dicom): DICOM series geometry and the lung mask. Skipped when the
// shared data folder is absent.
#include "dmrReadImage.h"
#include "dmrLungMask.h"
#include "dmrBreathingDeformation.h"
#include "dmrDataTestHelpers.h"
#include "itkGDCMImageIO.h"
#include "itkGDCMSeriesFileNames.h"
#include "itkImageFileReader.h"
#include "itkImageFileWriter.h"
#include "itkImageSeriesReader.h"
#include "gtest/gtest.h"
#include <fstream>
#include <iterator>

namespace
{
using CTImageType = itk::Image<short, 3>;

std::string
ThoraxFolder()
{
  return dmrtest::SharedDataFolder("thorax-ct-dicom");
}

/** The bytes of a slice of the series (implicit VR little endian) and where the value of its top-level element `tag`
 * (4 bytes: group and element, little endian) lies; at is npos when the element is missing. */
struct SliceElement
{
  std::string bytes;
  size_t      at = std::string::npos; // the value's first byte
  uint32_t    length = 0;
};

SliceElement
FindSliceElement(const std::string & file, const std::string & tag)
{
  std::ifstream in(file, std::ios::binary);
  SliceElement  e;
  e.bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  const size_t header = e.bytes.find(tag);
  if (header != std::string::npos && header + 8 <= e.bytes.size())
  {
    e.at = header + 8;
    e.length = static_cast<uint8_t>(e.bytes[header + 4]) | (static_cast<uint8_t>(e.bytes[header + 5]) << 8);
  }
  return e;
}
} // namespace

TEST(ThoraxCT, DicomSeriesGeometryMatchesItsNiftiConversion)
{
  const std::string dir = ThoraxFolder();
  if (dir.empty())
  {
    GTEST_SKIP() << "no shared data (set DMR_SHARED_DATA_DIR): " << dmrtest::SharedDataDir();
  }
  // the series as ITK reads it: GDCM file names ordered by slice position, GDCM image IO
  auto names = itk::GDCMSeriesFileNames::New();
  names->SetUseSeriesDetails(true);
  names->SetDirectory(dir);
  const auto uids = names->GetSeriesUIDs();
  ASSERT_EQ(uids.size(), 1u);
  const auto files = names->GetFileNames(uids.front());
  ASSERT_EQ(files.size(), 141u);
  auto reader = itk::ImageSeriesReader<CTImageType>::New();
  auto io = itk::GDCMImageIO::New();
  reader->SetImageIO(io);
  reader->SetFileNames(files);
  reader->Update();
  CTImageType::Pointer dicom = reader->GetOutput();
  const auto           size = dicom->GetLargestPossibleRegion().GetSize();
  std::cout << "DICOM: size " << size << " spacing " << dicom->GetSpacing() << " origin " << dicom->GetOrigin()
            << "\ndirection\n"
            << dicom->GetDirection() << std::flush;
  EXPECT_EQ(size, (itk::Size<3>{ { 512, 512, 141 } }));
  EXPECT_NEAR(dicom->GetSpacing()[0], 0.977, 1e-3);
  EXPECT_NEAR(dicom->GetSpacing()[1], 0.977, 1e-3);
  EXPECT_NEAR(dicom->GetSpacing()[2], 2.0, 1e-3); // from the slice positions: wrong ordering would break this
  EXPECT_EQ(io->GetComponentType(), itk::IOComponentEnum::SHORT);
  // slices are ordered along the normal: each file's position lies one spacing further than the previous one
  {
    auto single = itk::ImageFileReader<CTImageType>::New();
    single->SetImageIO(itk::GDCMImageIO::New());
    for (size_t s = 0; s < files.size(); s += 35)
    {
      single->SetFileName(files[s]);
      single->UpdateOutputInformation();
      itk::Point<double, 3> expected;
      itk::Index<3>         idx{ { 0, 0, static_cast<itk::IndexValueType>(s) } };
      dicom->TransformIndexToPhysicalPoint(idx, expected);
      EXPECT_LT(single->GetOutput()->GetOrigin().EuclideanDistanceTo(expected), 1e-3) << files[s];
    }
  }
  // the helper the tools use reads the same image
  auto viaHelper = dmrtools::ReadImageOrDicomSeries<CTImageType>(dir);
  EXPECT_EQ(viaHelper->GetOrigin(), dicom->GetOrigin());
  EXPECT_EQ(viaHelper->GetDirection(), dicom->GetDirection());

  // NIfTI conversion written by ITK, read back
  dmrtest::ScratchDirectory scratch("thorax");
  const std::string         path = scratch.Path() + "/thorax.nii.gz";
  auto                      writer = itk::ImageFileWriter<CTImageType>::New();
  writer->SetInput(dicom);
  writer->SetFileName(path);
  writer->UseCompressionOn();
  writer->Update();
  auto nifti = itk::ImageFileReader<CTImageType>::New();
  nifti->SetFileName(path);
  nifti->Update();
  const auto * back = nifti->GetOutput();
  EXPECT_EQ(back->GetLargestPossibleRegion().GetSize(), size);
  for (unsigned int i = 0; i < 3; ++i)
  {
    EXPECT_NEAR(back->GetSpacing()[i], dicom->GetSpacing()[i], 1e-5) << "spacing " << i;
    EXPECT_NEAR(back->GetOrigin()[i], dicom->GetOrigin()[i], 1e-3) << "origin " << i;
    for (unsigned int j = 0; j < 3; ++j)
    {
      EXPECT_NEAR(back->GetDirection()[i][j], dicom->GetDirection()[i][j], 1e-5) << "direction " << i << j;
    }
  }
  EXPECT_TRUE(std::equal(dicom->GetBufferPointer(),
                         dicom->GetBufferPointer() + dicom->GetLargestPossibleRegion().GetNumberOfPixels(),
                         back->GetBufferPointer()))
    << "voxel values differ after the NIfTI round trip";
}

TEST(ThoraxCT, IncompleteAndMixedSeriesAreRefused)
{
  const std::string dir = ThoraxFolder();
  if (dir.empty())
  {
    GTEST_SKIP() << "no shared data (set DMR_SHARED_DATA_DIR): " << dmrtest::SharedDataDir();
  }
  const auto                files = dmrtools::DicomSeriesFileNames(dir); // ordered by position
  dmrtest::ScratchDirectory scratch("series");
  auto                      link = [](const std::string & file, const std::string & into) {
    ASSERT_TRUE(itksys::SystemTools::CreateSymlink(file, into + "/" + itksys::SystemTools::GetFilenameName(file)));
  };
  // one slice missing in the middle: ITK's series reader spaces the slices evenly with the mean gap and only warns,
  // so the slices after the gap were put up to a whole spacing (2 mm) away from where they were scanned
  const std::string missing = scratch.Path() + "/missing";
  itksys::SystemTools::MakeDirectory(missing);
  for (size_t s = 0; s < files.size(); ++s)
  {
    if (s != files.size() / 2)
    {
      link(files[s], missing);
    }
  }
  try
  {
    dmrtools::ReadImageOrDicomSeries<CTImageType>(missing);
    ADD_FAILURE() << "a series with a missing slice was read";
  }
  catch (const itk::ExceptionObject & e)
  {
    EXPECT_NE(std::string(e.GetDescription()).find("missing slice"), std::string::npos) << e.GetDescription();
  }
  // two series in one directory: one slice carries another Series Instance UID (its last digit changed). GDCM's
  // first series was read without a word.
  const std::string mixed = scratch.Path() + "/mixed";
  itksys::SystemTools::MakeDirectory(mixed);
  for (size_t s = 1; s < files.size(); ++s)
  {
    link(files[s], mixed);
  }
  {
    SliceElement uid = FindSliceElement(files[0], std::string("\x20\x00\x0e\x00", 4)); // (0020,000E)
    ASSERT_NE(uid.at, std::string::npos);
    std::string & bytes = uid.bytes;
    size_t        last = uid.at + uid.length - 1;
    if (bytes[last] == '\0')
    {
      --last; // the padding of an odd-length UID
    }
    bytes[last] = bytes[last] == '7' ? '8' : '7';
    std::ofstream(mixed + "/" + itksys::SystemTools::GetFilenameName(files[0]), std::ios::binary) << bytes;
  }
  EXPECT_THROW(dmrtools::ImageDimensionOf(mixed), dmrtools::UsageError);
  try
  {
    dmrtools::ReadImageOrDicomSeries<CTImageType>(mixed);
    ADD_FAILURE() << "one of two series was read";
  }
  catch (const itk::ExceptionObject & e)
  {
    const std::string message = e.GetDescription();
    EXPECT_NE(message.find("holds 2 DICOM series"), std::string::npos) << message;
    EXPECT_NE(message.find("(140 slices)"), std::string::npos) << message;
    EXPECT_NE(message.find("(1 slices)"), std::string::npos) << message;
  }
  // one slice cut short, as by an interrupted transfer: GDCM read it with the missing half of its pixels as zeros
  // (-1024 HU after rescaling) and no error. Every slice of the real series (implicit VR little endian) passes the
  // check.
  const std::string cut = scratch.Path() + "/cut";
  itksys::SystemTools::MakeDirectory(cut);
  for (size_t s = 0; s < files.size(); ++s)
  {
    EXPECT_NO_THROW(dmrtools::CheckDicomFileIsComplete(files[s])) << files[s];
    if (s != files.size() / 2)
    {
      link(files[s], cut);
    }
  }
  const std::string cutSlice = cut + "/" + itksys::SystemTools::GetFilenameName(files[files.size() / 2]);
  {
    std::ifstream in(files[files.size() / 2], std::ios::binary);
    std::string   bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::ofstream(cutSlice, std::ios::binary) << bytes.substr(0, bytes.size() / 2);
  }
  try
  {
    dmrtools::ReadImageOrDicomSeries<CTImageType>(cut);
    ADD_FAILURE() << "a series with a slice cut short was read";
  }
  catch (const itk::ExceptionObject & e)
  {
    EXPECT_NE(std::string(e.GetDescription()).find(cutSlice + ": the file is truncated or corrupt"), std::string::npos)
      << e.GetDescription();
  }
  // one slice whose Image Position (Patient) is not a finite number: ITK aborted the process (vnl, "matrix has
  // non-finite elements") on a z of 1e999, and a "nan" was taken as a missing slice
  for (const std::string z : { "1e999", "nan" })
  {
    const std::string bad = scratch.Path() + "/position-" + z;
    itksys::SystemTools::MakeDirectory(bad);
    for (size_t s = 0; s < files.size(); ++s)
    {
      if (s != 5)
      {
        link(files[s], bad);
      }
    }
    const std::string badSlice = bad + "/" + itksys::SystemTools::GetFilenameName(files[5]);
    SliceElement      position = FindSliceElement(files[5], std::string("\x20\x00\x32\x00", 4)); // (0020,0032)
    ASSERT_NE(position.at, std::string::npos);
    std::string value = position.bytes.substr(position.at, position.length);
    value = value.substr(0, value.rfind('\\') + 1) + z;
    ASSERT_LE(value.size(), position.length);
    position.bytes.replace(position.at, position.length, value + std::string(position.length - value.size(), ' '));
    std::ofstream(badSlice, std::ios::binary) << position.bytes;
    EXPECT_THROW(dmrtools::ImageDimensionOf(bad), dmrtools::UsageError);
    try
    {
      dmrtools::ReadImageOrDicomSeries<CTImageType>(bad);
      ADD_FAILURE() << "a series with a position of " << z << " was read";
    }
    catch (const itk::ExceptionObject & e)
    {
      EXPECT_NE(std::string(e.GetDescription())
                  .find(badSlice + ": its Image Position (Patient) (0020,0032) is \"" + value + "\", not three finite"),
                std::string::npos)
        << e.GetDescription();
    }
  }
  // the complete series reads (DicomSeriesGeometryMatchesItsNiftiConversion checks its geometry)
  EXPECT_EQ(dmrtools::ImageDimensionOf(dir), 3u);
}

TEST(ThoraxCT, LungMaskHasPlausibleVolume)
{
  const std::string dir = ThoraxFolder();
  if (dir.empty())
  {
    GTEST_SKIP() << "no shared data (set DMR_SHARED_DATA_DIR): " << dmrtest::SharedDataDir();
  }
  auto                     ct = dmrtools::ReadImageOrDicomSeries<CTImageType>(dir);
  dmrtools::LungMaskReport report;
  auto                     mask = dmrtools::LungMask(ct.GetPointer(), {}, &report);
  std::cout << "thorax CT lung mask: " << report.voxels << " voxels, " << report.volumeLitres << " l, "
            << report.components << " component(s), slice axis " << report.axialAxis << std::endl;
  ::testing::Test::RecordProperty("lung_volume_ml", static_cast<int>(report.volumeLitres * 1000.0 + 0.5));
  EXPECT_EQ(report.axialAxis, 2u);
  EXPECT_GE(report.volumeLitres, 2.0);
  EXPECT_LE(report.volumeLitres, 8.0);
  // the lungs sit inside the body, left and right of the midline, away from the in-plane border
  const auto box = dmrtools::MaskBoundingBox(mask.GetPointer());
  const auto image = dmrtools::ImageBoundingBox(ct);
  EXPECT_GT(box.lower[0] - image.lower[0], 30.0);
  EXPECT_GT(image.upper[0] - box.upper[0], 30.0);
  EXPECT_GT(box.upper[0] - box.lower[0], 200.0); // both lungs: wider than one
}
