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
#ifndef dmrReadImage_h
#define dmrReadImage_h

// Reading a 3D scan for the command-line tools: an image file (NIfTI, MetaImage, ...) or a directory holding one
// DICOM series. The series is read with GDCM's file-name generator, which orders the slices by their position along
// the slice normal (Image Position (Patient)), never by file name; ITK's series reader then takes the spacing along
// the normal from the slice positions and the direction from Image Orientation (Patient). Physical space is ITK's
// LPS patient frame.
#include "itkGDCMImageIO.h"
#include "itkGDCMSeriesFileNames.h"
#include "itkImageFileReader.h"
#include "itkImageSeriesReader.h"
#include "itkMacro.h"
#include "itkMath.h"
#include "itkMetaDataObject.h"
#include "itkImageIOFactory.h"
#include "itkBuildInformation.h"
#include "itkFloatingPointExceptions.h"
#include "itkMersenneTwisterRandomVariateGenerator.h"
#include "itkMetaImageIO.h"
#include "itkMultiThreaderBase.h"
#include "itkObjectFactoryBase.h"
#include "itkOutputWindow.h"
#include "itkTimeStamp.h"
#include "itk_zlib.h"
#include "dmrImageFileCheck.h"
#include "dmrImageMetrics.h"
#include "dmrToolErrors.h"
#include "itksys/Directory.hxx"
#include "itksys/SystemTools.hxx"
#include <algorithm>
#include <cstdio>
#include <cmath>
#include <future>
#include <sstream>
#include <string>
#include <vector>
#include <unistd.h>
#include <sys/stat.h>
#include <fstream>
#include <cstdlib>
#include <cstring>

namespace dmrtools
{
/** Creates ITK's process-wide globals on the calling thread. ITK 5.2 creates each of them on first use and registers
 * it in the std::map of itk::SingletonIndex without a lock, so two threads that first use ITK side by side (the tool
 * reads its inputs on threads) can corrupt the map: runs crashed, or hung at exit in ~SingletonIndex. Call this on the
 * main thread, after any change of the global number of threads, before starting threads that run ITK code. These are
 * all the globals of the ITK 5.2 libraries the tools link (`nm -D` of each for itk::Singleton; ITKFFT's FFTW
 * configuration is not linked); the test ExampleItkGlobalsOnMainThread checks that none is left to a reader thread. */
inline void
InitializeItkGlobals()
{
  itk::TimeStamp().Modified();                      // GlobalTimeStamp
  itk::ObjectFactoryBase::GetRegisteredFactories(); // ObjectFactoryBase
  itk::Object::GetGlobalWarningDisplay();           // GlobalWarningDisplay
  itk::DataObject::GetGlobalReleaseDataFlag();      // GlobalReleaseDataFlag
  StartItkThreadPool(); // MultiThreaderBase, and ThreadPool for the pool threader (its threads checked first)
  itk::OutputWindow::GetInstance();                                      // OutputWindow
  itk::FloatingPointExceptions::GetEnabled();                            // ExceptionGlobals
  itk::MetaImageIO::GetDefaultDoublePrecision();                         // DefaultDoublePrecision
  itk::Statistics::MersenneTwisterRandomVariateGenerator::GetInstance(); // MersenneTwisterGlobals
  itk::BuildInformation::GetInstance();                                  // BuildInformationGlobals
}

namespace detail
{
/** Whether path is a regular file that starts like a DICOM file: the Part 10 preamble ("DICM" at byte 128), or, for
 * files written without it (ACR-NEMA style), a first element of group 0002 or 0008 in either byte order. Files
 * shorter than the preamble and files that are not regular (devices, FIFOs, /proc entries of size 0) are not read. */
inline bool
LooksLikeDicomFile(const std::string & path)
{
  struct stat info;
  if (stat(path.c_str(), &info) != 0 || !S_ISREG(info.st_mode) || info.st_size < 132)
  {
    return false;
  }
  std::ifstream in(path, std::ios::binary);
  char          head[132];
  if (!in.read(head, sizeof head))
  {
    return false;
  }
  const auto * u = reinterpret_cast<const unsigned char *>(head);
  if (std::memcmp(head + 128, "DICM", 4) == 0)
  {
    return true;
  }
  const unsigned little = u[0] | (u[1] << 8), big = (u[0] << 8) | u[1];
  return little == 0x0002 || little == 0x0008 || big == 0x0002 || big == 0x0008;
}

/** The entries of directory (no "." and ".."), sorted; empty when it cannot be listed. */
inline std::vector<std::string>
DirectoryEntries(const std::string & directory)
{
  std::vector<std::string> entries;
  itksys::Directory        listing;
  if (listing.Load(directory))
  {
    for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
    {
      const std::string name = listing.GetFile(i);
      if (name != "." && name != "..")
      {
        entries.push_back(name);
      }
    }
  }
  std::sort(entries.begin(), entries.end());
  return entries;
}

/** Folders below directory (breadth first, at most 4 levels and 64 folders looked at, symbolic links to folders not
 * followed) that hold a file that looks like DICOM: where a DICOM export (CD, PACS) keeps its series. */
inline std::vector<std::string>
FoldersWithDicomFilesBelow(const std::string & directory)
{
  std::vector<std::string> found, queue{ directory };
  std::vector<int>         depth{ 0 };
  for (size_t at = 0; at < queue.size() && at < 64; ++at)
  {
    bool dicom = false;
    for (const auto & name : DirectoryEntries(queue[at]))
    {
      const std::string child = queue[at] + "/" + name;
      if (itksys::SystemTools::FileIsDirectory(child))
      {
        if (depth[at] < 4 && !itksys::SystemTools::FileIsSymlink(child))
        {
          queue.push_back(child);
          depth.push_back(depth[at] + 1);
        }
      }
      else if (at > 0 && !dicom && LooksLikeDicomFile(child))
      {
        dicom = true;
        found.push_back(queue[at]);
      }
    }
  }
  return found;
}
} // namespace detail

/** Slice files of the one DICOM series in directory, ordered by position. Throws when there is none, and when there
 * are several: picking one of them (GDCM's first) registered another volume than the user meant without a word, e.g.
 * every other slice of a directory where two series are mixed. GDCM tells series apart by Series Instance UID and,
 * with its series details, by size, orientation and slice thickness, so a series whose slices differ there is
 * refused too. GDCM reads only the files that look like DICOM (detail::LooksLikeDicomFile): Debian's GDCM asserts,
 * aborting the process, on some other files (an 8-byte text file "Etc/UTC" does it), and would wait forever on a
 * FIFO. When other files are present, it scans a temporary folder of links to the DICOM ones. Every DICOM file is
 * checked first (CheckDicomFileIsComplete: whole, and its geometry attributes numbers), so that a slice cut short or
 * with a position of "nan" is refused by name before GDCM orders the slices by it. */
inline std::vector<std::string>
DicomSeriesFileNames(const std::string & directory)
{
  std::string base = directory;
  while (base.size() > 1 && base.back() == '/')
  {
    base.pop_back();
  }
  std::vector<std::string> dicom;
  bool                     others = false;
  for (const auto & name : detail::DirectoryEntries(base))
  {
    const std::string path = base + "/" + name;
    if (detail::LooksLikeDicomFile(path))
    {
      dicom.push_back(name);
    }
    else if (!itksys::SystemTools::FileIsDirectory(path))
    {
      others = true;
    }
  }
  if (dicom.empty())
  {
    const auto         folders = detail::FoldersWithDicomFilesBelow(base);
    std::ostringstream where;
    for (size_t i = 0; i < folders.size() && i < 4; ++i)
    {
      where << (i ? ", " : "") << folders[i];
    }
    itkGenericExceptionMacro(<< "directory holds no DICOM series: " << directory
                             << (folders.empty() ? std::string()
                                                 : "; its subdirectories hold DICOM files, give the folder of the "
                                                   "series to register: " +
                                                     where.str() + (folders.size() > 4 ? ", ..." : "")));
  }
  for (const auto & name : dicom)
  {
    CheckDicomFileIsComplete(base + "/" + name); // GDCM reads a slice cut short as if it were whole
  }
  // the folder GDCM scans: directory itself, or links to its DICOM files only
  std::string scanned = base, links;
  if (others)
  {
    const char *      tmp = std::getenv("TMPDIR");
    std::vector<char> pattern;
    const std::string templ = std::string(tmp && *tmp ? tmp : "/tmp") + "/dmr-dicom-XXXXXX";
    pattern.assign(templ.begin(), templ.end());
    pattern.push_back('\0');
    if (mkdtemp(pattern.data()))
    {
      links = pattern.data();
      bool linked = true;
      for (const auto & name : dicom)
      {
        const std::string target = itksys::SystemTools::CollapseFullPath(base + "/" + name);
        linked = linked && symlink(target.c_str(), (links + "/" + name).c_str()) == 0;
      }
      if (linked)
      {
        scanned = links;
      }
    }
  }
  struct RemoveLinks
  {
    std::string folder;
    ~RemoveLinks()
    {
      if (!folder.empty())
      {
        itksys::SystemTools::RemoveADirectory(folder);
      }
    }
  } removeLinks{ links };
  auto names = itk::GDCMSeriesFileNames::New();
  names->SetUseSeriesDetails(true);
  names->SetDirectory(scanned);
  const auto uids = names->GetSeriesUIDs();
  if (uids.empty())
  {
    itkGenericExceptionMacro(<< "directory holds no DICOM series: " << directory << " (" << dicom.size()
                             << " of its files look like DICOM, none is a slice of an image series)");
  }
  if (uids.size() > 1)
  {
    std::ostringstream list;
    for (size_t i = 0; i < uids.size() && i < 4; ++i)
    {
      list << (i ? "; " : "") << uids[i] << " (" << names->GetFileNames(uids[i]).size() << " slices)";
    }
    list << (uids.size() > 4 ? "; ..." : "");
    throw itk::ExceptionObject(__FILE__,
                               __LINE__,
                               directory + " holds " + std::to_string(uids.size()) +
                                 " DICOM series (told apart by Series Instance UID, size, orientation or slice "
                                 "thickness): " +
                                 list.str() + "; give a directory that holds only the series to register",
                               ITK_LOCATION);
  }
  auto files = names->GetFileNames(uids.front());
  if (files.empty())
  {
    itkGenericExceptionMacro(<< "DICOM series without files in " << directory);
  }
  if (scanned != base)
  {
    for (auto & file : files) // the links' names are the files' names in directory
    {
      file = base + "/" + itksys::SystemTools::GetFilenameName(file);
    }
  }
  return files;
}

/** Largest deviation of a DICOM series' slice gaps from its spacing (the mean gap) that is accepted, relative to the
 * spacing: the position strings' rounding stays far below it, a missing or repeated slice (a deviation of a whole
 * spacing) or a series with two slice spacings is far above it. */
constexpr double DicomSliceGapTolerance = 0.05;

/** Throws when the slices of a series just read by ITK's series reader (from files, ordered by position) do not
 * make the volume the reader built. The reader gives the volume its first slice's orthogonal axes and the mean gap as
 * the slice spacing, and only warns about uneven gaps (a warning the tools do not show). So a missing slice moved
 * every slice after it by up to a whole spacing in physical space, and a sheared series (slices offset within their
 * own plane from one to the next, as after a gantry tilt) was stacked straight, its last slice put where the first
 * one's normal leads instead of where it was scanned: both silently. */
template <typename TImage>
void
CheckDicomSliceGeometry(const std::string & directory, const std::vector<std::string> & files, const TImage * image)
{
  constexpr unsigned int sliceAxis = TImage::ImageDimension - 1;
  const double           spacing = image->GetSpacing()[sliceAxis];
  double                 deviation = 0.0;
  if (itk::ExposeMetaData<double>(image->GetMetaDataDictionary(), "ITK_non_uniform_sampling_deviation", deviation) &&
      deviation > DicomSliceGapTolerance * spacing)
  {
    std::ostringstream message;
    message << "the DICOM series in " << directory
            << " has a missing slice or uneven slice positions: a gap between neighbouring slices differs from the "
               "mean gap ("
            << spacing << " mm) by " << deviation << " mm; give a complete series, or resample it to an even spacing "
            << "first";
    throw itk::ExceptionObject(__FILE__, __LINE__, message.str(), ITK_LOCATION);
  }
  if (files.size() < 2)
  {
    return;
  }
  // the last slice's position (Image Position (Patient), which GDCM gives as the origin; its header only) against the
  // first one's, which the series reader made the volume's origin
  auto last = itk::ImageFileReader<TImage>::New();
  last->SetImageIO(itk::GDCMImageIO::New());
  last->SetFileName(files.back());
  last->UpdateOutputInformation();
  const auto   stack = last->GetOutput()->GetOrigin() - image->GetOrigin();
  const auto & direction = image->GetDirection();
  double       along = 0.0;
  for (unsigned int r = 0; r < TImage::ImageDimension; ++r)
  {
    along += stack[r] * direction[r][sliceAxis];
  }
  double across = 0.0; // the stack's offset within the slice plane
  for (unsigned int r = 0; r < TImage::ImageDimension; ++r)
  {
    const double c = stack[r] - along * direction[r][sliceAxis];
    across += c * c;
  }
  across = std::sqrt(across);
  double inPlane = image->GetSpacing()[0];
  for (unsigned int k = 1; k < sliceAxis; ++k)
  {
    inPlane = std::min(inPlane, static_cast<double>(image->GetSpacing()[k]));
  }
  if (across > 0.5 * inPlane)
  {
    std::ostringstream message;
    message << "the DICOM series in " << directory << " is sheared: from the first slice to the last the slices move "
            << across << " mm within their own plane besides " << std::abs(along)
            << " mm along its normal (a gantry tilt of " << std::atan2(across, std::abs(along)) * 180.0 / itk::Math::pi
            << " degrees?), which a volume with orthogonal axes cannot hold; resample the series onto an orthogonal "
               "grid first";
    throw itk::ExceptionObject(__FILE__, __LINE__, message.str(), ITK_LOCATION);
  }
}

/** True when the gzip file at path decompresses to the end of its stream with a valid trailer. ITK's readers do not
 * notice a stream that ends early (they return what they got). */
inline bool
GzipStreamIsComplete(const std::string & path)
{
  gzFile file = gzopen(path.c_str(), "rb");
  if (!file)
  {
    return false;
  }
  std::string buffer(1 << 20, '\0');
  int         got = 0;
  while ((got = gzread(file, &buffer[0], static_cast<unsigned int>(buffer.size()))) > 0)
  {
  }
  const bool closed = gzclose(file) == Z_OK; // closed on every path
  return got == 0 && closed;
}

/** The image at path: a DICOM series when path is a directory, otherwise any file ITK can read. A .gz file is
 * checked to its trailer (GzipStreamIsComplete) on another thread while ITK reads it, so a truncated file is an
 * error and the check costs no extra time; uncompressed NIfTI, MetaImage and VTK files, PNG, JPEG and BMP files are
 * checked against the sizes their headers give (dmrImageFileCheck.h). Throws itk::ExceptionObject on failure (missing
 * path, unknown format, empty directory, truncated or corrupt file). */
template <typename TImage>
typename TImage::Pointer
ReadImageOrDicomSeries(const std::string & path)
{
  if (!itksys::SystemTools::FileExists(path))
  {
    itkGenericExceptionMacro(<< "no such file or directory: " << path);
  }
  if (itksys::SystemTools::FileIsDirectory(path))
  {
    auto reader = itk::ImageSeriesReader<TImage>::New();
    reader->SetImageIO(itk::GDCMImageIO::New());
    const auto files = DicomSeriesFileNames(path); // checks every file (CheckDicomFileIsComplete)
    reader->SetFileNames(files);
    reader->Update();
    CheckDicomSliceGeometry(path, files, reader->GetOutput());
    return reader->GetOutput();
  }
  std::future<bool> complete;
  if (itksys::SystemTools::GetFilenameLastExtension(path) == ".gz")
  {
    complete = std::async(std::launch::async, [path] { return GzipStreamIsComplete(path); });
  }
  CheckImageFileBeforeReading(path, false); // the sform's decompositions: ImageDimensionOf, with stderr captured
  auto reader = itk::ImageFileReader<TImage>::New();
  reader->SetFileName(path);
  // the header's geometry is checked before the reader gives it to the image, which aborts on one that is not finite
  auto io = itk::ImageIOFactory::CreateImageIO(path.c_str(), itk::ImageIOFactory::IOFileModeEnum::ReadMode);
  if (io)
  {
    io->SetFileName(path);
    io->ReadImageInformation();
    CheckImageGeometryIsFinite(path, io);
    reader->SetImageIO(io);
  }
  reader->UpdateOutputInformation(); // the header: is the pixel data all there?
  CheckRawPixelDataIsComplete(path, reader->GetImageIO());
  reader->Update(); // on an exception, the future's destructor waits for the check
  if (complete.valid() && !complete.get())
  {
    throw itk::ExceptionObject(
      __FILE__, __LINE__, path + ": the compressed file is truncated or corrupt", ITK_LOCATION);
  }
  return reader->GetOutput();
}
/** Dimension of an image file (unit trailing axes squeezed: a one-slice 3D file is 2D) or 3 for a directory that
 * holds a DICOM series; components per pixel into *components and whether they are an RGB(A) colour into *colour
 * when given (1 and false for DICOM). Reads the header only, and checks the file's length where the format allows (a
 * truncated .gz file is found by ReadImageOrDicomSeries). Throws UsageError (bad input) otherwise. */
inline unsigned int
ImageDimensionOf(const std::string & path, unsigned int * components = nullptr, bool * colour = nullptr)
{
  if (components)
  {
    *components = 1;
  }
  if (colour)
  {
    *colour = false;
  }
  if (!itksys::SystemTools::FileExists(path))
  {
    throw UsageError("no such file or directory: " + path);
  }
  if (itksys::SystemTools::FileIsDirectory(path))
  {
    try
    {
      DicomSeriesFileNames(path); // one series (the slices' headers are read again with the images)
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError(e.GetDescription());
    }
    return 3;
  }
  // what the image libraries print about the file goes into the message (one line), not beside it
  StandardErrorCapture libraries;
  auto                 said = [&libraries] {
    const std::string text = libraries.Release();
    return text.empty() ? std::string() : " (the reader said: " + text + ")";
  };
  auto io = itk::ImageIOFactory::CreateImageIO(path.c_str(), itk::ImageIOFactory::IOFileModeEnum::ReadMode);
  if (!io)
  {
    throw UsageError("cannot read an image from " + path + " (unknown or unsupported format)" + said());
  }
  io->SetFileName(path);
  // a short file: the checks' messages name the file
  auto checked = [](auto && check) {
    try
    {
      check();
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError(e.GetDescription());
    }
  };
  // before the header read: libpng aborts on some short files, ITK's NIfTI reader on a sform that is not finite
  checked([&] { CheckImageFileBeforeReading(path); });
  try
  {
    io->ReadImageInformation();
  }
  catch (const itk::ExceptionObject & e)
  {
    throw UsageError("cannot read an image from " + path + ": " + e.GetDescription() + said());
  }
  libraries.Release(); // a header that reads: what was printed about it is not an error (ITK's warnings are off too)
  checked([&] { CheckImageGeometryIsFinite(path, io); }); // ITK aborts when an image takes such a geometry
  checked([&] { CheckRawPixelDataIsComplete(path, io); });
  if (components)
  {
    *components = io->GetNumberOfComponents();
  }
  if (colour)
  {
    *colour = io->GetPixelType() == itk::IOPixelEnum::RGB || io->GetPixelType() == itk::IOPixelEnum::RGBA;
  }
  unsigned int d = io->GetNumberOfDimensions();
  // a 3D file with a single slice is a 2D image
  while (d > 2 && io->GetDimensions(d - 1) == 1)
  {
    --d;
  }
  return d;
}
/** Finds the first NaN or infinite pixel of an image as read: its index as text ("[5, 3]") and its value. Returns false
 * when every pixel is finite. The tools refuse such images, naming the voxel. */
template <typename TImage>
bool
FindNonFiniteVoxel(const TImage * image, std::string & index, double & value)
{
  const auto p = itk::dmr::FirstNonFinitePixel(image);
  if (p < 0)
  {
    return false;
  }
  std::ostringstream where;
  where << image->ComputeIndex(static_cast<itk::OffsetValueType>(p));
  index = where.str();
  value = static_cast<double>(image->GetBufferPointer()[p]);
  return true;
}
} // namespace dmrtools

#endif
