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

// The tools' check that an image file holds all the pixel data its header describes (Examples/dmrImageFileCheck.h).
// Regression test (a fixed bug): ITK read truncated uncompressed NIfTI, MetaImage and VTK files, JPEGs and BMPs
// without an error (the missing pixels left as zeros or garbage), and a PNG cut within its first chunks made libpng
// abort the process.
#include "dmrExampleTestDirectory.h"
#include "dmrImageFileCheck.h"
#include "dmrReadImage.h"
#include "itkImage.h"
#include "itkImageFileWriter.h"
#include "itkImageIOFactory.h"
#include "itksys/SystemTools.hxx"
#include "itkGDCMImageIO.h"
#include "itkMetaDataObject.h"
#include "gtest/gtest.h"
#include <array>
#include <cstring>
#include <limits>
#include <zlib.h>
#include <sstream>
#include <vector>
#include <sys/stat.h>
#include <fstream>
#include <string>

namespace
{
using Image2DType = itk::Image<float, 2>;

std::string
WorkDir()
{
  return dmrtools::test::TemporaryDirectory("dmrImageFileCheckGTest");
}

template <typename TPixel>
void
WriteTestImage(const std::string & path)
{
  using ImageType = itk::Image<TPixel, 2>;
  auto image = ImageType::New();
  image->SetRegions(typename ImageType::SizeType{ { 40, 30 } });
  image->Allocate();
  for (unsigned int y = 0; y < 30; ++y)
  {
    for (unsigned int x = 0; x < 40; ++x)
    {
      image->SetPixel({ { x, y } }, static_cast<TPixel>((x * 7 + y * 13) % 200 + 20));
    }
  }
  auto writer = itk::ImageFileWriter<ImageType>::New();
  writer->SetInput(image);
  writer->SetFileName(path);
  writer->Update();
}

std::string
ReadBytes(const std::string & path)
{
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

void
WriteBytes(const std::string & path, const std::string & bytes)
{
  std::ofstream(path, std::ios::binary) << bytes;
}

/** Both checks, as the tools run them: the encoded formats before ITK, the raw ones after ITK's header read. */
void
CheckFile(const std::string & path)
{
  dmrtools::CheckEncodedImageFileIsComplete(path);
  auto io = itk::ImageIOFactory::CreateImageIO(path.c_str(), itk::ImageIOFactory::IOFileModeEnum::ReadMode);
  ASSERT_NE(io, nullptr) << path;
  io->SetFileName(path);
  io->ReadImageInformation();
  dmrtools::CheckRawPixelDataIsComplete(path, io);
}

bool
ThrowsTruncated(const std::string & path)
{
  try
  {
    CheckFile(path);
  }
  catch (const itk::ExceptionObject & e)
  {
    return std::string(e.GetDescription()).find("the file is truncated or corrupt") != std::string::npos;
  }
  return false;
}
} // namespace

TEST(ImageFileCheck, WholeFilesPassAndShortOnesAreRefused)
{
  const std::string dir = WorkDir();
  struct Case
  {
    std::string name; // the file written by ITK
    std::string data; // the file that holds its pixel data
    bool        bytePixels;
  };
  for (const Case & c : { Case{ "f.nii", "f.nii", false },
                          Case{ "f.hdr", "f.img", false },
                          Case{ "f.mha", "f.mha", false },
                          Case{ "f.mhd", "f.raw", false },
                          Case{ "f.vtk", "f.vtk", false },
                          Case{ "f.png", "f.png", true },
                          Case{ "f.jpg", "f.jpg", true },
                          Case{ "f.bmp", "f.bmp", true } })
  {
    SCOPED_TRACE(c.name);
    const std::string path = dir + "/" + c.name, data = dir + "/" + c.data;
    if (c.bytePixels)
    {
      WriteTestImage<unsigned char>(path);
    }
    else
    {
      WriteTestImage<float>(path);
    }
    EXPECT_NO_THROW(CheckFile(path));
    const std::string whole = ReadBytes(data);
    // one byte short, and cut in the middle of the pixel data
    for (const size_t keep : { whole.size() - 1, whole.size() / 2 })
    {
      WriteBytes(data, whole.substr(0, keep));
      EXPECT_TRUE(ThrowsTruncated(path)) << "kept " << keep << " of " << whole.size() << " bytes";
    }
    WriteBytes(data, whole);
    EXPECT_NO_THROW(CheckFile(path));
  }
}

TEST(ImageFileCheck, PngCutInItsHeaderIsRefusedBeforeLibpngSeesIt)
{
  // 40 bytes: the signature, IHDR and part of the next chunk; libpng aborted the process on such a file
  const std::string path = WorkDir() + "/cut.png";
  WriteTestImage<unsigned char>(path);
  WriteBytes(path, ReadBytes(path).substr(0, 40));
  EXPECT_TRUE(ThrowsTruncated(path));
  // the tools' header read, which ran into libpng, refuses it with a usage error first
  EXPECT_THROW(dmrtools::ImageDimensionOf(path), dmrtools::UsageError);
  EXPECT_THROW(dmrtools::ReadImageOrDicomSeries<Image2DType>(path), itk::ExceptionObject);
}

TEST(ImageFileCheck, JpegWithTrailingPaddingPasses)
{
  const std::string path = WorkDir() + "/padded.jpg";
  WriteTestImage<unsigned char>(path);
  WriteBytes(path, ReadBytes(path) + std::string("\r\n\0\0", 4));
  EXPECT_NO_THROW(CheckFile(path));
}

TEST(ImageFileCheck, ScaledNiftiIsCheckedByTheTypeItStores)
{
  // Regression test (a fixed bug): a 16-bit NIfTI whose scl_slope/scl_inter scale its values, as DICOM converters
  // write CT (inter -1024) and MR, was refused as truncated: ITK reports such a file as float pixels, twice the bytes
  // the file stores. The check now takes the size from the header's dim and bitpix.
  const std::string dir = WorkDir();
  const std::string path = dir + "/scaled.nii";
  WriteTestImage<short>(path);
  std::string bytes = ReadBytes(path);
  ASSERT_GE(bytes.size(), 352u);
  const float slope = 2.0f, inter = -1024.0f;
  std::memcpy(&bytes[112], &slope, sizeof slope);
  std::memcpy(&bytes[116], &inter, sizeof inter);
  WriteBytes(path, bytes);
  EXPECT_NO_THROW(CheckFile(path));
  const auto image = dmrtools::ReadImageOrDicomSeries<Image2DType>(path);
  for (unsigned int y = 0; y < 30; y += 7)
  {
    for (unsigned int x = 0; x < 40; x += 9)
    {
      EXPECT_EQ(image->GetPixel({ { x, y } }), 2.0f * static_cast<float>((x * 7 + y * 13) % 200 + 20) - 1024.0f);
    }
  }
  for (const size_t keep : { bytes.size() - 1, bytes.size() - 40 * 30 })
  {
    WriteBytes(path, bytes.substr(0, keep));
    EXPECT_TRUE(ThrowsTruncated(path)) << "kept " << keep << " of " << bytes.size() << " bytes";
  }
  // the NIfTI library sizes a voxel by its datatype, not by bitpix: a wrong bitpix does not make the file short
  std::string   wrongBitpix = bytes;
  const int16_t bitpix = 32;
  std::memcpy(&wrongBitpix[72], &bitpix, sizeof bitpix);
  WriteBytes(path, wrongBitpix);
  EXPECT_NO_THROW(CheckFile(path));
}

namespace
{
/** The description of the itk::ExceptionObject (or the text of the UsageError) that f throws; "" if none. */
template <typename TFunction>
std::string
ErrorOf(TFunction && f)
{
  try
  {
    f();
  }
  catch (const itk::ExceptionObject & e)
  {
    return e.GetDescription();
  }
  catch (const dmrtools::UsageError & e)
  {
    return e.what();
  }
  return std::string();
}

void
SetFloat(std::string & bytes, size_t at, float value)
{
  std::memcpy(&bytes[at], &value, sizeof value);
}
} // namespace

TEST(ImageFileCheck, ReadersRefuseTruncatedRawFiles)
{
  const std::string path = WorkDir() + "/short.nii";
  WriteTestImage<float>(path);
  const std::string whole = ReadBytes(path);
  EXPECT_NO_THROW(dmrtools::ReadImageOrDicomSeries<Image2DType>(path));
  WriteBytes(path, whole.substr(0, whole.size() - 100));
  EXPECT_THROW(dmrtools::ReadImageOrDicomSeries<Image2DType>(path), itk::ExceptionObject);
  EXPECT_THROW(dmrtools::ImageDimensionOf(path), dmrtools::UsageError);
  // a header whose sizeof_hdr is wrong, which the NIfTI library reads all the same (in either byte order): the check
  // did not, and a file cut short was read with zeros in place of its missing pixels
  for (const bool bigEndian : { false, true })
  {
    std::string wrong = whole;
    std::memset(&wrong[0], 0xff, 4);
    if (bigEndian)
    {
      auto swapBytes = [&wrong](size_t at, size_t n) { std::reverse(wrong.begin() + at, wrong.begin() + at + n); };
      for (size_t at = 40; at < 56; at += 2) // dim[0..7]
      {
        swapBytes(at, 2);
      }
      swapBytes(70, 2);  // datatype
      swapBytes(72, 2);  // bitpix
      swapBytes(108, 4); // vox_offset
      for (size_t at = 352; at < wrong.size(); at += 4)
      {
        swapBytes(at, 4); // the float pixels
      }
    }
    WriteBytes(path, wrong);
    SCOPED_TRACE(bigEndian ? "big endian" : "little endian");
    EXPECT_EQ(dmrtools::ReadImageOrDicomSeries<Image2DType>(path)->GetPixel({ { 3, 2 } }), 3.0f * 7 + 2 * 13 + 20);
    WriteBytes(path, wrong.substr(0, wrong.size() - 100));
    EXPECT_NE(ErrorOf([&] {
                dmrtools::ReadImageOrDicomSeries<Image2DType>(path);
              }).find("the file is truncated or corrupt (its header describes 4800 bytes of pixel data from byte 352"),
              std::string::npos)
      << ErrorOf([&] { dmrtools::ReadImageOrDicomSeries<Image2DType>(path); });
    EXPECT_THROW(dmrtools::ImageDimensionOf(path), dmrtools::UsageError);
  }
}

namespace
{
/** Writes a small CT-like DICOM series (16 x 12 slices of 1 x 1 mm, axial orientation, one Series Instance UID) into
 * dir, one file per entry of positions (Image Position (Patient), mm), named in reverse order so that only the
 * positions order them. `attributes` (tag "gggg|eeee" -> value) replace the written ones in every slice. */
void
WriteDicomSeries(const std::string &                                      dir,
                 const std::vector<std::array<double, 3>> &               positions,
                 bool                                                     compressed = false,
                 const std::vector<std::pair<std::string, std::string>> & attributes = {})
{
  using SliceType = itk::Image<short, 2>;
  itksys::SystemTools::MakeDirectory(dir);
  for (size_t k = 0; k < positions.size(); ++k)
  {
    auto slice = SliceType::New();
    slice->SetRegions(SliceType::SizeType{ { 16, 12 } });
    slice->Allocate();
    for (unsigned int y = 0; y < 12; ++y)
    {
      for (unsigned int x = 0; x < 16; ++x)
      {
        slice->SetPixel({ { x, y } }, static_cast<short>((x * 37 + y * 11 + k * 5) % 300 - 100));
      }
    }
    auto & dictionary = slice->GetMetaDataDictionary();
    auto   set = [&dictionary](const std::string & tag, const std::string & value) {
      itk::EncapsulateMetaData<std::string>(dictionary, tag, value);
    };
    std::ostringstream position;
    position << positions[k][0] << "\\" << positions[k][1] << "\\" << positions[k][2];
    set("0008|0016", "1.2.840.10008.5.1.4.1.1.2"); // CT Image Storage
    set("0008|0018", "1.2.826.0.1.3680043.2.1143.777.2." + std::to_string(k + 1));
    set("0008|0060", "CT");
    set("0020|000d", "1.2.826.0.1.3680043.2.1143.777.1");
    set("0020|000e", "1.2.826.0.1.3680043.2.1143.777.1.1");
    set("0020|0013", std::to_string(k + 1));
    set("0020|0032", position.str());
    set("0020|0037", "1\\0\\0\\0\\1\\0");
    set("0028|0030", "1\\1");
    set("0018|0050", "1");
    for (const auto & attribute : attributes)
    {
      set(attribute.first, attribute.second);
    }
    auto io = itk::GDCMImageIO::New();
    io->KeepOriginalUIDOn();
    auto writer = itk::ImageFileWriter<SliceType>::New();
    writer->SetImageIO(io);
    if (compressed)
    {
      io->SetCompressionType(itk::GDCMImageIO::JPEG); // encapsulated pixel data (fragments)
      writer->UseCompressionOn();
    }
    writer->SetInput(slice);
    writer->SetFileName(dir + "/slice" + std::to_string(positions.size() - k) + ".dcm");
    writer->Update();
  }
}
} // namespace

namespace
{
/** Image Positions (Patient) of n axial slices 2.5 mm apart from z = 0, for WriteDicomSeries. */
std::vector<std::array<double, 3>>
AxialPositions(int n)
{
  std::vector<std::array<double, 3>> positions;
  for (int k = 0; k < n; ++k)
  {
    positions.push_back({ -8.0, -6.0, 2.5 * k });
  }
  return positions;
}
} // namespace

TEST(ImageFileCheck, DicomSeriesMustStackItsSlicesEvenlyAlongTheirNormal)
{
  // ITK's series reader builds a volume with the first slice's orthogonal axes and the mean gap as spacing, and only
  // warns about uneven gaps: a missing slice and a sheared series (gantry tilt) were read into the wrong place
  using CTType = itk::Image<float, 3>;
  const std::string                  dir = WorkDir();
  std::vector<std::array<double, 3>> even, missing, sheared;
  for (int k = 0; k < 10; ++k)
  {
    even.push_back({ -8.0, -6.0, 2.5 * k - 20.0 });
    if (k != 6)
    {
      missing.push_back(even.back());
    }
    sheared.push_back({ -8.0, -6.0 + 0.4 * k, 2.5 * k - 20.0 }); // 3.6 mm across 22.5 mm: a 9 degree tilt
  }
  WriteDicomSeries(dir + "/even", even);
  WriteDicomSeries(dir + "/missing", missing);
  WriteDicomSeries(dir + "/sheared", sheared);
  const auto volume = dmrtools::ReadImageOrDicomSeries<CTType>(dir + "/even");
  EXPECT_EQ(volume->GetLargestPossibleRegion().GetSize(), (itk::Size<3>{ { 16, 12, 10 } }));
  EXPECT_NEAR(volume->GetSpacing()[2], 2.5, 1e-6);
  EXPECT_NEAR(volume->GetOrigin()[2], -20.0, 1e-6); // ordered by position, not by file name
  EXPECT_EQ(volume->GetPixel({ { 3, 2, 9 } }), static_cast<float>((3 * 37 + 2 * 11 + 9 * 5) % 300 - 100));
  auto message = [](const std::string & path) -> std::string {
    try
    {
      dmrtools::ReadImageOrDicomSeries<CTType>(path);
    }
    catch (const itk::ExceptionObject & e)
    {
      return e.GetDescription();
    }
    return "read without an error";
  };
  EXPECT_NE(message(dir + "/missing").find("has a missing slice or uneven slice positions"), std::string::npos)
    << message(dir + "/missing");
  EXPECT_NE(message(dir + "/sheared").find("is sheared"), std::string::npos) << message(dir + "/sheared");
  // a folder whose series lie in subfolders (as DICOM exports keep them) names those that hold one
  WriteDicomSeries(dir + "/export/patient/study/series1", even);
  itksys::SystemTools::MakeDirectory(dir + "/export/patient/notes");
  const std::string outer = message(dir + "/export");
  EXPECT_NE(outer.find("holds no DICOM series: " + dir + "/export; its subdirectories hold DICOM files"),
            std::string::npos)
    << outer;
  EXPECT_NE(outer.find(dir + "/export/patient/study/series1"), std::string::npos) << outer;
  EXPECT_EQ(outer.find("notes"), std::string::npos) << outer;
  const std::string empty = message(dir + "/export/patient/notes");
  EXPECT_NE(empty.find("holds no DICOM series"), std::string::npos) << empty;
  EXPECT_EQ(empty.find("subdirectories"), std::string::npos) << empty;
  // other files beside the slices: an 8-byte text file on which Debian's GDCM asserted (the process aborted), a
  // FIFO that GDCM would have waited on forever, a short file and a hidden one; the series is read from its own files
  WriteBytes(dir + "/even/timezone", "Etc/UTC\n");
  WriteBytes(dir + "/even/short", "DICM");
  WriteBytes(dir + "/even/.DS_Store", std::string(300, '\1'));
  ASSERT_EQ(mkfifo((dir + "/even/pipe").c_str(), 0600), 0);
  const auto files = dmrtools::DicomSeriesFileNames(dir + "/even");
  ASSERT_EQ(files.size(), 10u);
  for (const auto & file : files)
  {
    EXPECT_EQ(itksys::SystemTools::GetFilenamePath(file), dir + "/even");
    EXPECT_TRUE(itksys::SystemTools::FileExists(file, true)) << file;
  }
  const auto again = dmrtools::ReadImageOrDicomSeries<CTType>(dir + "/even");
  EXPECT_EQ(again->GetLargestPossibleRegion().GetSize(), (itk::Size<3>{ { 16, 12, 10 } }));
  EXPECT_EQ(again->GetPixel({ { 3, 2, 9 } }), volume->GetPixel({ { 3, 2, 9 } }));
  const std::string onlyText = dir + "/text";
  itksys::SystemTools::MakeDirectory(onlyText);
  WriteBytes(onlyText + "/timezone", "Etc/UTC\n");
  EXPECT_NE(message(onlyText).find("holds no DICOM series"), std::string::npos) << message(onlyText);
  itksys::SystemTools::RemoveADirectory(dir);
}

TEST(ImageFileCheck, DicomFileCutShortIsRefusedWhereverItIsCut)
{
  // GDCM reads a DICOM slice that ends early as if it were whole, with the missing pixels zeros: a series with one
  // slice cut by an interrupted transfer was registered with that slice partly at 0 (-1024 HU after rescaling)
  using CTType = itk::Image<float, 3>;
  const std::string                        dir = WorkDir();
  const std::vector<std::array<double, 3>> positions = AxialPositions(6);
  for (const bool jpeg : { false, true }) // implicit VR little endian, and explicit with JPEG fragments
  {
    const std::string series = dir + (jpeg ? "/jpeg" : "/native");
    WriteDicomSeries(series, positions, jpeg);
    const auto whole = dmrtools::ReadImageOrDicomSeries<CTType>(series);
    ASSERT_EQ(whole->GetLargestPossibleRegion().GetSize(), (itk::Size<3>{ { 16, 12, 6 } }));
    const std::string file = series + "/slice3.dcm"; // the fourth slice by position
    const std::string bytes = ReadBytes(file);
    EXPECT_NO_THROW(dmrtools::CheckDicomFileIsComplete(file));
    EXPECT_FALSE(ThrowsTruncated(file)) << file; // as the single-file read checks it
    // bytes after a whole Pixel Data (some writers pad files) do not spoil the image: not refused
    WriteBytes(file, bytes + std::string("\0\0\0", 3));
    EXPECT_NO_THROW(dmrtools::CheckDicomFileIsComplete(file));
    // every cut after the preamble is found: in the meta information, in any element, in the pixel data. (Only
    // encapsulated pixel data that ends after a whole fragment without its 8-byte sequence delimiter is left to GDCM:
    // some writers leave the delimiter out.)
    size_t missed = 0;
    for (size_t length = 132; length < bytes.size(); ++length)
    {
      if (jpeg && length == bytes.size() - 8)
      {
        ASSERT_EQ(bytes.substr(length), std::string("\xfe\xff\xdd\xe0\0\0\0\0", 8));
        continue;
      }
      WriteBytes(file, bytes.substr(0, length));
      try
      {
        dmrtools::CheckDicomFileIsComplete(file);
        ++missed;
        ADD_FAILURE() << (jpeg ? "JPEG" : "native") << " file cut to " << length << " of " << bytes.size()
                      << " bytes passed";
      }
      catch (const itk::ExceptionObject & e)
      {
        EXPECT_NE(std::string(e.GetDescription()).find(file + ": the file is truncated or corrupt"), std::string::npos)
          << e.GetDescription();
      }
      if (missed > 3)
      {
        break;
      }
    }
    if (!jpeg)
    {
      // a Pixel Data element whose own length is short of rows x columns x 2 bytes (the file ends with it)
      const std::string pixelTag("\xe0\x7f\x10\x00", 4); // (7FE0,0010), implicit VR little endian as GDCM writes
      const size_t      at = bytes.rfind(pixelTag);
      ASSERT_NE(at, std::string::npos);
      ASSERT_EQ(bytes.size(), at + 8 + 16 * 12 * 2);
      std::string shorter = bytes.substr(0, bytes.size() - 100);
      shorter[at + 4] = static_cast<char>((16 * 12 * 2 - 100) & 0xff);
      shorter[at + 5] = static_cast<char>((16 * 12 * 2 - 100) >> 8);
      WriteBytes(file, shorter);
      try
      {
        dmrtools::CheckDicomFileIsComplete(file);
        ADD_FAILURE() << "a Pixel Data element shorter than its image passed";
      }
      catch (const itk::ExceptionObject & e)
      {
        EXPECT_NE(std::string(e.GetDescription()).find("its Pixel Data has 284 bytes, its header describes 384"),
                  std::string::npos)
          << e.GetDescription();
      }
    }
    // the series with that slice cut in its pixel data is refused, naming the slice
    WriteBytes(file, bytes.substr(0, bytes.size() - 100));
    try
    {
      dmrtools::ReadImageOrDicomSeries<CTType>(series);
      ADD_FAILURE() << "a series with a slice cut short was read";
    }
    catch (const itk::ExceptionObject & e)
    {
      EXPECT_NE(std::string(e.GetDescription()).find(file + ": the file is truncated or corrupt"), std::string::npos)
        << e.GetDescription();
    }
    // and so is the slice read alone
    EXPECT_TRUE(ThrowsTruncated(file)) << file;
    WriteBytes(file, bytes);
    EXPECT_EQ(dmrtools::ReadImageOrDicomSeries<CTType>(series)->GetPixel({ { 5, 4, 3 } }),
              whole->GetPixel({ { 5, 4, 3 } }));
  }
  itksys::SystemTools::RemoveADirectory(dir);
}

TEST(ImageFileCheck, NiftiSformThatItkCannotTakeApartIsRefusedBeforeItkReadsIt)
{
  // Regression test (a fixed bug): ITK 5.2's NIfTI reader takes the sform apart with single-precision SVDs while it
  // reads the header. A NaN or infinite srow entry aborted the tool (vnl's assert_finite, no message, exit 134), and
  // an entry of 3e38 or a nearly singular sform spanning 43 orders of magnitude kept the SVD busy for good (found by
  // mutating header fields). Offsets 280..327: srow_x, srow_y, srow_z (4 floats each); 254: sform_code.
  const std::string dir = WorkDir();
  const std::string path = dir + "/sform.nii";
  WriteTestImage<float>(path);
  std::string whole = ReadBytes(path);
  ASSERT_GE(whole.size(), 352u);
  const int16_t one = 1, zero = 0;
  std::memcpy(&whole[254], &one, sizeof one); // sform_code 1 (scanner anatomy), as ITK writes it
  WriteBytes(path, whole);
  ASSERT_NO_THROW(dmrtools::CheckImageFileBeforeReading(path));
  ASSERT_EQ(dmrtools::ImageDimensionOf(path), 2u);
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  struct Case
  {
    size_t      at;
    float       value;
    std::string said;
  };
  for (const Case & c : { Case{ 280, nan, "srow_x[0] = nan, not a finite number" },
                          Case{ 300, inf, "srow_y[1] = inf, not a finite number" },
                          Case{ 324, nan, "srow_z[3] = nan, not a finite number" },
                          Case{ 292, 3e38f, "is (1, 0, 0, 3e+38; " },
                          Case{ 296, -1e10f, "is (1, 0, 0, 0; -1e+10, 1, 0, 0; -1.5e-33, 0, 1, 0)" } })
  {
    std::string bytes = whole;
    for (unsigned int i = 0; i < 12; ++i)
    {
      SetFloat(bytes, 280 + 4 * i, i % 5 == 0 ? 1.0f : 0.0f); // the identity, as ITK writes this image
    }
    SetFloat(bytes, c.at, c.value);
    if (c.value == -1e10f)
    {
      SetFloat(bytes, 312, -1.5e-33f); // with srow_z[0]: a mutated header that kept ITK's SVD busy for good
    }
    const std::string expected =
      "the NIfTI header's sform (sform_code 1) " +
      (c.said.compare(0, 3, "is ") == 0 ? c.said : "has " + c.said + ": the header is corrupt");
    // as a .nii, a .nii.gz and a .hdr/.img pair (named by either file)
    const std::string gz = dir + "/sform.nii.gz", hdr = dir + "/pair.hdr", img = dir + "/pair.img";
    WriteBytes(path, bytes);
    gzFile file = gzopen(gz.c_str(), "wb");
    ASSERT_NE(file, nullptr);
    ASSERT_EQ(gzwrite(file, bytes.data(), static_cast<unsigned int>(bytes.size())), static_cast<int>(bytes.size()));
    ASSERT_EQ(gzclose(file), Z_OK);
    std::string header = bytes.substr(0, 348);
    header[345] = 'i'; // "ni1": the header of a pair
    WriteBytes(hdr, header);
    WriteBytes(img, bytes.substr(352));
    const bool hangs = c.said.compare(0, 3, "is ") == 0;
    if (hangs)
    {
      // each refusal leaves a thread in the SVD for 2 s and for good: one file
      SCOPED_TRACE(c.said);
      EXPECT_NE(ErrorOf([&] { dmrtools::ImageDimensionOf(gz); }).find(expected), std::string::npos);
    }
    for (const std::string & name : hangs ? std::vector<std::string>{} : std::vector<std::string>{ path, gz, hdr, img })
    {
      SCOPED_TRACE(name + ": " + c.said);
      EXPECT_NE(ErrorOf([&] { dmrtools::CheckImageFileBeforeReading(name); }).find(expected), std::string::npos);
      EXPECT_THROW(dmrtools::ImageDimensionOf(name), dmrtools::UsageError);
      EXPECT_NE(ErrorOf([&] { dmrtools::ReadImageOrDicomSeries<Image2DType>(name); }).find(expected),
                std::string::npos);
    }
    // with sform_code 0 the sform is not used: the file reads
    std::memcpy(&bytes[254], &zero, sizeof zero);
    WriteBytes(path, bytes);
    EXPECT_NO_THROW(dmrtools::CheckImageFileBeforeReading(path)) << c.said;
    EXPECT_EQ(dmrtools::ReadImageOrDicomSeries<Image2DType>(path)->GetPixel({ { 3, 2 } }), 3.0f * 7 + 2 * 13 + 20);
  }
  // the NIfTI library reads a header whose sizeof_hdr is wrong (it tells the byte order from dim[0]): so does the check
  std::string wrongSize = whole;
  SetFloat(wrongSize, 296, -std::numeric_limits<float>::infinity());
  std::memset(&wrongSize[0], 0xff, 4);
  WriteBytes(path, wrongSize);
  EXPECT_NE(ErrorOf([&] { dmrtools::ImageDimensionOf(path); }).find("has srow_y[0] = -inf, not a finite number"),
            std::string::npos);
  // a singular sform that ITK's SVDs take apart (all zeros, as some writers leave it) is not refused: ITK reads the
  // file
  std::string zeros = whole;
  for (unsigned int i = 0; i < 12; ++i)
  {
    SetFloat(zeros, 280 + 4 * i, 0.0f);
  }
  WriteBytes(path, zeros);
  EXPECT_EQ(dmrtools::ImageDimensionOf(path), 2u);
  EXPECT_EQ(dmrtools::ReadImageOrDicomSeries<Image2DType>(path)->GetPixel({ { 3, 2 } }), 3.0f * 7 + 2 * 13 + 20);
  itksys::SystemTools::RemoveADirectory(dir);
}

TEST(ImageFileCheck, NiftiVoxelSizeOrQformThatIsNotFiniteIsRefused)
{
  // Regression test (a fixed bug): the NIfTI library reads a NaN or infinite voxel size (pixdim[1..3], offsets 80..88)
  // as 1 mm and NaN or infinite qform parameters (quatern_b..qoffset_z, offsets 256..276, used with qform_code > 0 at
  // offset 252) as some rotation or offset; the tool registered such files without a word
  const std::string dir = WorkDir();
  const std::string path = dir + "/qform.nii";
  WriteTestImage<float>(path);
  const std::string whole = ReadBytes(path);
  ASSERT_GE(whole.size(), 352u);
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  struct Case
  {
    size_t      at;
    float       value;
    int16_t     qformCode;
    std::string said; // "" when the file reads
  };
  for (const Case & c :
       { Case{ 80, nan, 0, "the NIfTI header's voxel size pixdim[1] = nan is not a finite number" },
         Case{ 84, -inf, 1, "the NIfTI header's voxel size pixdim[2] = -inf is not a finite number" },
         Case{ 256, nan, 1, "the NIfTI header's qform (qform_code 1) has quatern_b = nan, not a finite" },
         Case{ 264, inf, 2, "has quatern_d = inf, not a finite number: the header is corrupt" },
         Case{ 268, -inf, 1, "has qoffset_x = -inf, not a finite number" },
         Case{ 276, nan, 1, "has qoffset_z = nan" }, // a 2D image's qform is 3D all the same
         Case{ 256, nan, 0, "" },                    // qform_code 0: the qform is not used
         Case{ 88, nan, 1, "" },                     // pixdim[3] of a 2D image
         Case{ 80, 0.0f, 0, "" } })                  // 0: the NIfTI library's 1 mm, as other readers take it
  {
    std::string bytes = whole;
    SetFloat(bytes, c.at, c.value);
    std::memcpy(&bytes[252], &c.qformCode, sizeof c.qformCode);
    WriteBytes(path, bytes);
    SCOPED_TRACE(std::to_string(c.at) + " " + std::to_string(c.value) + " qform_code " + std::to_string(c.qformCode));
    if (c.said.empty())
    {
      EXPECT_NO_THROW(dmrtools::CheckImageFileBeforeReading(path));
      EXPECT_EQ(dmrtools::ReadImageOrDicomSeries<Image2DType>(path)->GetPixel({ { 3, 2 } }), 3.0f * 7 + 2 * 13 + 20);
      continue;
    }
    const std::string said = ErrorOf([&] { dmrtools::CheckImageFileBeforeReading(path); });
    EXPECT_EQ(said.rfind(path + ": the NIfTI header's ", 0), 0u) << said;
    EXPECT_NE(said.find(c.said), std::string::npos) << said;
    EXPECT_THROW(dmrtools::ImageDimensionOf(path), dmrtools::UsageError);
    EXPECT_NE(ErrorOf([&] { dmrtools::ReadImageOrDicomSeries<Image2DType>(path); }).find(c.said), std::string::npos);
  }
  itksys::SystemTools::RemoveADirectory(dir);
}

TEST(ImageFileCheck, GeometryThatIsNotFiniteIsRefusedBeforeAnImageTakesIt)
{
  // Regression test (a fixed bug): a legacy VTK file with SPACING nan aborted the tool (ITK 5.2 asserts finite
  // entries when an image takes such a spacing; its reader passes it on).
  const std::string dir = WorkDir();
  const std::string path = dir + "/spacing.vtk";
  WriteTestImage<float>(path);
  const std::string whole = ReadBytes(path);
  ASSERT_NO_THROW(dmrtools::ReadImageOrDicomSeries<Image2DType>(path));
  for (const std::string & key : { std::string("SPACING"), std::string("ORIGIN") })
  {
    SCOPED_TRACE(key);
    const size_t at = whole.find("\n" + key + " ");
    ASSERT_NE(at, std::string::npos);
    const size_t end = whole.find('\n', at + 1);
    WriteBytes(path, whole.substr(0, at) + "\n" + key + " nan 1 1" + whole.substr(end));
    const std::string expected = std::string("the header's ") + (key == "SPACING" ? "spacing" : "origin") +
                                 " is not made of finite numbers (nan, 1): the header is corrupt";
    EXPECT_NE(ErrorOf([&] { dmrtools::ImageDimensionOf(path); }).find(expected), std::string::npos);
    EXPECT_NE(ErrorOf([&] { dmrtools::ReadImageOrDicomSeries<Image2DType>(path); }).find(expected), std::string::npos);
  }
  itksys::SystemTools::RemoveADirectory(dir);
}

TEST(ImageFileCheck, MetaImageHeaderWhoseDimensionsMetaIOWouldLoopOverIsRefused)
{
  // Regression test (a fixed bug): MetaIO reads NDims x NDims TransformMatrix values and NDims of the other arrays
  // from whatever NDims says; NDims = -1e308 kept ITK 5.2's reader busy for good (found by mutating header lines).
  const std::string dir = WorkDir();
  const std::string path = dir + "/dims.mha";
  WriteTestImage<float>(path);
  const std::string whole = ReadBytes(path);
  const size_t      at = whole.find("NDims = 2\n");
  ASSERT_NE(at, std::string::npos);
  EXPECT_EQ(dmrtools::ImageDimensionOf(path), 2u);
  for (const std::string & value : { "-1e308", "-2147483649", "0", "11", "nan", "two" })
  {
    SCOPED_TRACE(value);
    WriteBytes(path, whole.substr(0, at) + "NDims = " + value + whole.substr(at + 9));
    const std::string expected =
      "the MetaImage header's NDims (" + value + ") is not a number of dimensions from 1 to 10: the header is corrupt";
    EXPECT_NE(ErrorOf([&] { dmrtools::ImageDimensionOf(path); }).find(expected), std::string::npos);
    EXPECT_NE(ErrorOf([&] { dmrtools::ReadImageOrDicomSeries<Image2DType>(path); }).find(expected), std::string::npos);
  }
  // a subnormal spacing is refused before ITK inverts the geometry (vnl printed its SVD's warnings there)
  const size_t spacing = whole.find("ElementSpacing = ");
  ASSERT_NE(spacing, std::string::npos);
  const size_t end = whole.find('\n', spacing);
  WriteBytes(path, whole.substr(0, spacing) + "ElementSpacing = 1e-320 1" + whole.substr(end));
  EXPECT_NE(ErrorOf([&] { dmrtools::ImageDimensionOf(path); }).find("below the smallest normal double"),
            std::string::npos);
  itksys::SystemTools::RemoveADirectory(dir);
}

namespace
{
/** Replaces the value of the top-level element (group,element) of an implicit VR little endian DICOM file (as
 * WriteDicomSeries writes them) by `value`, padded with a space to an even length. */
void
SetDicomText(const std::string & file, uint16_t group, uint16_t element, std::string value)
{
  if (value.size() % 2)
  {
    value += ' ';
  }
  std::string       bytes = ReadBytes(file);
  const std::string tag{ static_cast<char>(group & 0xff),
                         static_cast<char>(group >> 8),
                         static_cast<char>(element & 0xff),
                         static_cast<char>(element >> 8) };
  const size_t      at = bytes.find(tag, 132);
  ASSERT_NE(at, std::string::npos) << file;
  uint32_t length = 0;
  std::memcpy(&length, &bytes[at + 4], 4);
  const uint32_t newLength = static_cast<uint32_t>(value.size());
  bytes.replace(at + 8, length, value);
  std::memcpy(&bytes[at + 4], &newLength, 4);
  WriteBytes(file, bytes);
}
} // namespace

TEST(ImageFileCheck, DicomGeometryThatIsNotANumberIsRefusedNamingTheElement)
{
  // Regression test (a fixed bug): GDCM reads a Pixel Spacing that is not two numbers above 0 without an error and
  // gives 1 mm instead (a negative one flips the axis), a series whose positions are not numbers at 1 mm from 0, and a
  // position of 1e999 in one slice made ITK abort the process (vnl: "matrix has non-finite elements")
  using CTType = itk::Image<float, 3>;
  const std::string                        dir = WorkDir();
  const std::vector<std::array<double, 3>> positions = AxialPositions(4);
  struct Case
  {
    uint16_t    group, element;
    std::string value;
    bool        allSlices;
    std::string expected; // in the message; "" when the series reads
  };
  const std::string spacing = "Pixel Spacing (0028,0030) is \"",
                    position = "Image Position (Patient) (0020,0032) is \"";
  const std::string       orientation = "Image Orientation (Patient) (0020,0037) is \"";
  const std::vector<Case> cases{
    { 0x0028, 0x0030, "nan\\nan", true, spacing + "nan\\nan\", not two finite numbers above 0 (mm)" },
    { 0x0028, 0x0030, "0\\0", true, spacing + "0\\0\"" },
    { 0x0028, 0x0030, "-1\\1", true, spacing + "-1\\1\"" },
    { 0x0028, 0x0030, "inf\\1", true, spacing + "inf\\1\"" },
    { 0x0028, 0x0030, "1\\one", true, spacing + "1\\one\"" },
    { 0x0028, 0x0030, "1", true, spacing + "1\"" },
    { 0x0028, 0x0030, "1\\1\\1", true, spacing + "1\\1\\1\"" },
    { 0x0028, 0x0030, "nan\\nan", false, "slice1.dcm: its " + spacing + "nan\\nan\"" },
    { 0x0020, 0x0037, "nan\\0\\0\\0\\1\\0", true, orientation + "nan\\0\\0\\0\\1\\0\", not six finite numbers" },
    { 0x0020, 0x0037, "0\\0\\0\\0\\0\\0", true, orientation + "0\\0\\0\\0\\0\\0\"" },
    { 0x0020, 0x0037, "1\\0\\0\\1\\0\\0", true, orientation + "1\\0\\0\\1\\0\\0\"" },
    { 0x0020,
      0x0032,
      "nan\\0\\0",
      false,
      "slice1.dcm: its " + position + "nan\\0\\0\", not three finite numbers (mm)" },
    { 0x0020, 0x0032, "nan\\0\\0", true, position + "nan\\0\\0\"" },
    { 0x0020, 0x0032, "-8\\-6\\1e999", false, position + "-8\\-6\\1e999\"" },
    // what reads: values with spaces and exponents, empty values (unknown, as if absent), attributes not used
    { 0x0028, 0x0030, " 1.0 \\+1E0", true, "" },
    { 0x0028, 0x0030, "1.00000000000000000\\1.00000000000000000", true, "" }, // 19 characters: longer than DS allows
    { 0x0028, 0x0030, "", true, "" },
    { 0x0020, 0x0037, "1\\0\\0\\0\\0.99999\\0", true, "" },
    { 0x0018, 0x0050, "nan", true, "" }
  };
  for (size_t i = 0; i < cases.size(); ++i)
  {
    const Case &      c = cases[i];
    const std::string series = dir + "/case" + std::to_string(i);
    WriteDicomSeries(series, positions);
    for (int k = 1; k <= (c.allSlices ? 4 : 1); ++k)
    {
      SetDicomText(series + "/slice" + std::to_string(k) + ".dcm", c.group, c.element, c.value);
    }
    const std::string what = ErrorOf([&] {
      const auto volume = dmrtools::ReadImageOrDicomSeries<CTType>(series);
      EXPECT_NEAR(volume->GetSpacing()[0], 1.0, 1e-5) << c.value;
      EXPECT_NEAR(volume->GetSpacing()[2], 2.5, 1e-6) << c.value;
      EXPECT_NEAR(volume->GetOrigin()[2], 0.0, 1e-6) << c.value;
    });
    if (c.expected.empty())
    {
      EXPECT_EQ(what, "") << c.value;
    }
    else
    {
      EXPECT_NE(what.find(c.expected), std::string::npos) << c.value << ": " << what;
      EXPECT_NE(what.find("the file's geometry is corrupt"), std::string::npos) << what;
    }
  }
  itksys::SystemTools::RemoveADirectory(dir);
}
