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
#ifndef dmrImageFileCheck_h
#define dmrImageFileCheck_h

// Is an image file whole? ITK 5.2's readers do not all notice a file that ends early: an uncompressed NIfTI,
// MetaImage or VTK file, a JPEG, a BMP or a DICOM file is read as far as it goes and the rest left as it was (zeros or
// garbage), and a PNG cut within its first chunks makes libpng abort the process. The tools check these formats
// themselves, from the sizes their headers give, and refuse a short file with one line. (A .gz file is checked to its
// trailer separately; NRRD and TIFF files that end early are errors in ITK already.)
#include "itkImageIOBase.h"
#include "itkMacro.h"
#include "itksys/SystemTools.hxx"
#include "vnl/algo/vnl_svd.h"
#include "vnl/vnl_matrix.h"
#include <zlib.h>
#include <algorithm>
#include <array>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <future>
#include <iterator>
#include <limits>
#include <memory>
#include <sstream>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

namespace dmrtools
{
namespace detail
{
[[noreturn]] inline void
ThrowTruncated(const std::string & path, const std::string & why)
{
  throw itk::ExceptionObject(
    __FILE__, __LINE__, path + ": the file is truncated or corrupt (" + why + ")", ITK_LOCATION);
}

inline uint64_t
FileSize(const std::string & path)
{
  return static_cast<uint64_t>(itksys::SystemTools::FileLength(path));
}

inline std::string
Head(const std::string & path, size_t bytes)
{
  std::ifstream in(path, std::ios::binary);
  std::string   head(bytes, '\0');
  in.read(&head[0], static_cast<std::streamsize>(bytes));
  head.resize(static_cast<size_t>(std::max<std::streamsize>(0, in.gcount())));
  return head;
}

inline uint32_t
BigEndian32(const unsigned char * p)
{
  return (uint32_t{ p[0] } << 24) | (uint32_t{ p[1] } << 16) | (uint32_t{ p[2] } << 8) | uint32_t{ p[3] };
}

inline uint32_t
LittleEndian32(const unsigned char * p)
{
  return uint32_t{ p[0] } | (uint32_t{ p[1] } << 8) | (uint32_t{ p[2] } << 16) | (uint32_t{ p[3] } << 24);
}

/** PNG: the chunks (length, type, data, CRC) must follow each other to the end of an IEND chunk. */
inline void
CheckPng(const std::string & path)
{
  std::ifstream  in(path, std::ios::binary);
  const uint64_t size = FileSize(path);
  uint64_t       at = 8; // after the signature
  for (;;)
  {
    unsigned char chunk[8];
    in.seekg(static_cast<std::streamoff>(at));
    if (at + 12 > size || !in.read(reinterpret_cast<char *>(chunk), 8))
    {
      ThrowTruncated(path, "a PNG file must end with an IEND chunk");
    }
    const uint64_t length = BigEndian32(chunk);
    if (at + 12 + length > size)
    {
      ThrowTruncated(path, "a PNG chunk at byte " + std::to_string(at) + " ends after the end of the file");
    }
    if (std::memcmp(chunk + 4, "IEND", 4) == 0)
    {
      return;
    }
    at += 12 + length;
  }
}

/** JPEG: the last marker is EOI (FF D9); trailing zero bytes or line breaks are tolerated. */
inline void
CheckJpeg(const std::string & path)
{
  const uint64_t size = FileSize(path);
  std::ifstream  in(path, std::ios::binary);
  const uint64_t tail = std::min<uint64_t>(size, 4096);
  std::string    end(static_cast<size_t>(tail), '\0');
  in.seekg(static_cast<std::streamoff>(size - tail));
  in.read(&end[0], static_cast<std::streamsize>(tail));
  while (!end.empty() && (end.back() == '\0' || end.back() == '\n' || end.back() == '\r'))
  {
    end.pop_back();
  }
  if (end.size() < 2 || static_cast<unsigned char>(end[end.size() - 2]) != 0xFF ||
      static_cast<unsigned char>(end.back()) != 0xD9)
  {
    ThrowTruncated(path, "a JPEG file must end with the end-of-image marker");
  }
}

/** BMP without compression (BI_RGB, BI_BITFIELDS): the rows (padded to 4 bytes) from the pixel-data offset. */
inline void
CheckBmp(const std::string & path, const std::string & head)
{
  if (head.size() < 34)
  {
    ThrowTruncated(path, "shorter than a BMP header");
  }
  const auto *   h = reinterpret_cast<const unsigned char *>(head.data());
  const uint64_t offset = LittleEndian32(h + 10);
  const int64_t  width = static_cast<int32_t>(LittleEndian32(h + 18));
  const int64_t  height = static_cast<int32_t>(LittleEndian32(h + 22));
  const unsigned bits = h[28] | (h[29] << 8);
  const uint32_t compression = LittleEndian32(h + 30);
  if (LittleEndian32(h + 14) < 40 || (compression != 0 && compression != 3) || width <= 0 || bits == 0)
  {
    return; // an old or compressed variant: left to the reader
  }
  const uint64_t row = (static_cast<uint64_t>(width) * bits + 31) / 32 * 4;
  const uint64_t needed = offset + row * static_cast<uint64_t>(height < 0 ? -height : height);
  if (FileSize(path) < needed)
  {
    ThrowTruncated(path,
                   "its BMP header describes " + std::to_string(needed) + " bytes, the file has " +
                     std::to_string(FileSize(path)));
  }
}

inline void
RequireBytes(const std::string & dataPath, uint64_t offset, uint64_t bytes, const std::string & path)
{
  if (!itksys::SystemTools::FileExists(dataPath) || FileSize(dataPath) < offset + bytes)
  {
    ThrowTruncated(path,
                   "its header describes " + std::to_string(bytes) + " bytes of pixel data from byte " +
                     std::to_string(offset) + (dataPath == path ? "" : " of " + dataPath) + ", the file has " +
                     std::to_string(itksys::SystemTools::FileExists(dataPath) ? FileSize(dataPath) : 0));
  }
}

/** name in the folder of path (name itself when it is a full path or path has no folder). */
inline std::string
Beside(const std::string & path, const std::string & name)
{
  const std::string folder = itksys::SystemTools::GetFilenamePath(path);
  return folder.empty() || itksys::SystemTools::FileIsFullPath(name) ? name : folder + "/" + name;
}

/** Lower-case last extension of path. */
inline std::string
Extension(const std::string & path)
{
  return itksys::SystemTools::LowerCase(itksys::SystemTools::GetFilenameLastExtension(path));
}

/** Bytes per voxel of a NIfTI datatype code, as the NIfTI library sizes it (bitpix is not used there); 0 for a code
 * it does not know. DT_BINARY (1) is not sized in bytes either. */
inline uint64_t
NiftiBytesPerVoxel(int datatype)
{
  switch (datatype)
  {
    case 2:   // uint8
    case 256: // int8
      return 1;
    case 4:   // int16
    case 512: // uint16
      return 2;
    case 128: // RGB24
      return 3;
    case 8:    // int32
    case 16:   // float32
    case 768:  // uint32
    case 2304: // RGBA32
      return 4;
    case 32:   // complex64
    case 64:   // float64
    case 1024: // int64
    case 1280: // uint64
      return 8;
    case 1536: // float128
    case 1792: // complex128
      return 16;
    case 2048: // complex256
      return 32;
    default:
      return 0;
  }
}

/** The byte order of a NIfTI-1 header told by its dim[0] (offset 40), as the NIfTI library tells it for a header
 * whose sizeof_hdr it does not trust: swap when dim[0] is 1..7 only with its bytes swapped. False when it is in
 * neither order (the reader refuses such a header). */
inline bool
Nifti1SwapFromDim0(const unsigned char * p, bool & swap)
{
  const int little = static_cast<int16_t>(p[40] | (p[41] << 8)), big = static_cast<int16_t>((p[40] << 8) | p[41]);
  swap = !(little >= 1 && little <= 7);
  return !swap || (big >= 1 && big <= 7);
}

/** NIfTI-1/2 (and Analyze): vox_offset + the pixel bytes, in the .nii file or the .img beside a .hdr. The bytes are
 * the header's own (dim[1..dim[0]] x the size of its datatype), those of the type stored in the file: ITK reports a
 * NIfTI whose scl_slope/scl_inter scale the values (common for CT and MR from DICOM converters) as float pixels,
 * which would make a whole 16-bit file look short. A header whose size cannot be told that way (an unknown datatype,
 * dims the NIfTI library corrects) is checked against itkBytes, the size ITK reports. */
inline void
CheckNifti(const std::string & path, uint64_t itkBytes)
{
  const std::string ext = Extension(path);
  std::string       header = path, data = path;
  if (ext == ".hdr" || ext == ".img")
  {
    const std::string base = Beside(path, itksys::SystemTools::GetFilenameWithoutLastExtension(path));
    header = base + ".hdr";
    data = base + ".img";
  }
  else if (ext != ".nii" && ext != ".nia")
  {
    return; // compressed: the .gz check
  }
  const std::string h = Head(header, 176);
  if (h.size() < 112)
  {
    ThrowTruncated(path, "shorter than a NIfTI header");
  }
  const auto * p = reinterpret_cast<const unsigned char *>(h.data());
  uint32_t     sizeofHdr = LittleEndian32(p);
  bool         swap = sizeofHdr != 348 && sizeofHdr != 540;
  const bool   wrongSize = swap && BigEndian32(p) != 348 && BigEndian32(p) != 540;
  // a wrong sizeof_hdr: the NIfTI library reads the header as NIfTI-1 all the same, its byte order told by dim[0]
  if (wrongSize && !Nifti1SwapFromDim0(p, swap))
  {
    return; // the reader refuses it
  }
  auto word = [&](size_t at) { return swap ? BigEndian32(p + at) : LittleEndian32(p + at); };
  auto half = [&](size_t at) {
    return static_cast<int16_t>(swap ? (p[at] << 8) | p[at + 1] : p[at] | (p[at + 1] << 8));
  };
  auto dword = [&](size_t at) {
    const uint64_t lo = word(swap ? at + 4 : at), hi = word(swap ? at : at + 4);
    return static_cast<int64_t>((hi << 32) | lo);
  };
  sizeofHdr = wrongSize ? 348 : word(0);
  double  offset = 0.0;
  int64_t dim[8] = {};
  int     datatype = 0;
  if (sizeofHdr == 348)
  {
    const uint32_t bits = word(108);
    float          f;
    std::memcpy(&f, &bits, sizeof f);
    offset = f;
    for (unsigned int i = 0; i < 8; ++i)
    {
      dim[i] = half(40 + 2 * i);
    }
    datatype = half(70);
  }
  else if (sizeofHdr == 540 && h.size() >= 176)
  {
    offset = static_cast<double>(static_cast<uint64_t>(dword(168)));
    for (unsigned int i = 0; i < 8; ++i)
    {
      dim[i] = dword(16 + 8 * i);
    }
    datatype = half(12);
  }
  else
  {
    return; // not a header we know: left to the reader
  }
  if (!(offset >= 0.0) || offset > 1e15)
  {
    ThrowTruncated(path, "its NIfTI header has an invalid data offset");
  }
  uint64_t       bytes = NiftiBytesPerVoxel(datatype);
  const uint64_t limit = uint64_t{ 1 } << 62;
  if (dim[0] < 1 || dim[0] > 7)
  {
    bytes = 0;
  }
  for (int64_t i = 1; bytes > 0 && i <= dim[0]; ++i)
  {
    bytes = dim[i] > 0 && static_cast<uint64_t>(dim[i]) <= limit / bytes ? bytes * static_cast<uint64_t>(dim[i]) : 0;
  }
  RequireBytes(data, static_cast<uint64_t>(offset), bytes > 0 ? bytes : itkBytes, path);
}

/** The "Key = value" lines of a MetaImage header, key and value trimmed, to the ElementDataFile line (included): each
 * is given to field(key, value, end), end the file offset after its line, until field returns false. Lines without
 * "=" are skipped; a line of 4096 characters or more ends the header. */
template <typename TField>
void
ForEachMetaImageField(const std::string & path, TField && field)
{
  std::ifstream in(path, std::ios::binary);
  std::string   line;
  uint64_t      end = 0;
  auto          trim = [](std::string s) {
    s.erase(0, s.find_first_not_of(" \t\r"));
    s.erase(s.find_last_not_of(" \t\r") + 1);
    return s;
  };
  while (std::getline(in, line) && line.size() < 4096)
  {
    end += line.size() + 1;
    const size_t eq = line.find('=');
    if (eq == std::string::npos)
    {
      continue;
    }
    const std::string key = trim(line.substr(0, eq));
    if (!field(key, trim(line.substr(eq + 1)), end) || key == "ElementDataFile")
    {
      return;
    }
  }
}

/** MetaImage: from its "Key = value" header lines, the pixel data of an uncompressed file either follows the
 * ElementDataFile = LOCAL line or fills one external file (after HeaderSize bytes). */
inline void
CheckMetaImage(const std::string & path, uint64_t bytes)
{
  std::string dataFile;
  bool        compressed = false;
  long long   headerSize = 0;
  uint64_t    after = 0;
  ForEachMetaImageField(path, [&](const std::string & key, const std::string & value, uint64_t end) {
    if (key == "CompressedData")
    {
      compressed = value == "True" || value == "true" || value == "1";
    }
    else if (key == "HeaderSize")
    {
      headerSize = std::atoll(value.c_str());
    }
    else if (key == "ElementDataFile")
    {
      dataFile = value;
      after = end;
    }
    return true;
  });
  if (dataFile.empty() || compressed)
  {
    return; // no data line (left to the reader) or zlib-compressed data
  }
  if (dataFile == "LOCAL")
  {
    RequireBytes(path, after, bytes, path);
  }
  else if (dataFile.find(' ') == std::string::npos && dataFile.find('%') == std::string::npos && dataFile != "LIST")
  {
    const std::string data = Beside(path, dataFile);
    RequireBytes(data, headerSize > 0 ? static_cast<uint64_t>(headerSize) : 0, bytes, path);
  }
}

/** Legacy VTK structured points, binary: the pixel data follows the SCALARS' LOOKUP_TABLE line (or VECTORS). */
inline void
CheckVtk(const std::string & path, uint64_t bytes)
{
  std::ifstream in(path, std::ios::binary);
  std::string   line;
  uint64_t      after = 0;
  bool          binary = false;
  for (int lines = 0; lines < 64 && std::getline(in, line); ++lines)
  {
    after += line.size() + 1;
    if (line.rfind("BINARY", 0) == 0)
    {
      binary = true;
    }
    if (line.rfind("LOOKUP_TABLE", 0) == 0 || line.rfind("VECTORS", 0) == 0)
    {
      if (binary)
      {
        RequireBytes(path, after, bytes, path);
      }
      return;
    }
  }
}

/** A walk over a DICOM file's data elements (DICOM PS3.5 section 7), far enough to tell whether the file holds every
 * byte its elements describe. GDCM does not tell: a slice cut short is read with the declared length of its Pixel
 * Data, the missing part zeros, so a series with one slice cut by an interrupted transfer was registered with half of
 * that slice at -1024 HU and no error. The walk follows the encodings a CT or MR file uses (explicit and implicit VR
 * little endian, explicit big endian, sequences and items of defined and undefined length, encapsulated pixel data);
 * where it meets anything else (a deflated data set, an unknown VR, a tag out of place) it gives no verdict and leaves
 * the file to GDCM, so an unusual but readable file is never refused by it. */
struct DicomWalk
{
  static constexpr uint32_t Undefined = 0xFFFFFFFFu;

  std::ifstream in;
  uint64_t      size = 0;
  bool          little = true;
  bool          explicitVR = true;
  std::string   problem;           // what is missing or wrong, when the walk found it
  bool          noVerdict = false; // an encoding the walk does not follow
  // the top-level image attributes
  uint64_t rows = 0, columns = 0, samples = 1, bitsAllocated = 0, frames = 1;
  bool     pixelData = false, encapsulated = false;
  bool     pixelComplete = false; // the top-level Pixel Data is whole (what follows it cannot spoil the image)
  uint64_t pixelBytes = 0;
  // the top-level geometry attributes as text, when present: Image Position (Patient) (0020,0032), Image Orientation
  // (Patient) (0020,0037), Pixel Spacing (0028,0030)
  struct Text
  {
    bool        present = false;
    std::string value;
  };
  Text position, orientation, pixelSpacing;

  explicit DicomWalk(const std::string & path)
    : in(path, std::ios::binary)
    , size(FileSize(path))
  {
  }

  uint64_t
  Position()
  {
    return static_cast<uint64_t>(in.tellg());
  }
  uint64_t
  Left()
  {
    const uint64_t at = Position();
    return at < size ? size - at : 0;
  }
  bool
  Read(unsigned char * p, size_t n)
  {
    return static_cast<bool>(in.read(reinterpret_cast<char *>(p), static_cast<std::streamsize>(n)));
  }
  void
  Skip(uint64_t n)
  {
    in.seekg(static_cast<std::streamoff>(Position() + n));
  }
  uint16_t
  U16(const unsigned char * p) const
  {
    return static_cast<uint16_t>(little ? p[0] | (p[1] << 8) : (p[0] << 8) | p[1]);
  }
  uint32_t
  U32(const unsigned char * p) const
  {
    return little ? LittleEndian32(p) : BigEndian32(p);
  }
  bool
  Stop(const std::string & why)
  {
    problem = why;
    return false;
  }
  /** what runs past the end of the file: its length from the current position. */
  bool
  PastTheEnd(const std::string & what, uint64_t length)
  {
    return Stop(what + " has " + std::to_string(length) + " bytes from byte " + std::to_string(Position()) +
                ", the file has " + std::to_string(size));
  }
  bool
  GiveUp()
  {
    noVerdict = true;
    return false;
  }

  static std::string
  Tag(uint16_t group, uint16_t element)
  {
    char text[16];
    std::snprintf(text, sizeof text, "(%04X,%04X)", group, element);
    return text;
  }
  static bool
  LongLengthVR(const char * vr)
  {
    static const char * const longs[] = {
      "OB", "OD", "OF", "OL", "OV", "OW", "SQ", "SV", "UC", "UN", "UR", "UT", "UV"
    };
    return std::any_of(std::begin(longs), std::end(longs), [vr](const char * l) { return std::memcmp(l, vr, 2) == 0; });
  }
  static bool
  ShortLengthVR(const char * vr)
  {
    static const char * const shorts[] = { "AE", "AS", "AT", "CS", "DA", "DS", "DT", "FD", "FL", "IS", "LO",
                                           "LT", "PN", "SH", "SL", "SS", "ST", "TM", "UI", "UL", "US" };
    return std::any_of(
      std::begin(shorts), std::end(shorts), [vr](const char * s) { return std::memcmp(s, vr, 2) == 0; });
  }

  /** The header of the data element at the current position (not an item tag): false when the file ends in it or
   * its VR is not one the walk knows. */
  bool
  Header(uint16_t & group, uint16_t & element, char * vr, uint32_t & length)
  {
    unsigned char h[8];
    if (Left() < 8 || !Read(h, 8))
    {
      return Stop("the file ends inside a data element's header, at byte " + std::to_string(Position()));
    }
    group = U16(h);
    element = U16(h + 2);
    vr[0] = vr[1] = '\0';
    if (group == 0xFFFE || !explicitVR)
    {
      length = U32(h + 4);
      return true;
    }
    vr[0] = static_cast<char>(h[4]);
    vr[1] = static_cast<char>(h[5]);
    if (ShortLengthVR(vr))
    {
      length = U16(h + 6);
      return true;
    }
    if (!LongLengthVR(vr))
    {
      return GiveUp();
    }
    unsigned char l[4];
    if (Left() < 4 || !Read(l, 4))
    {
      return Stop("the file ends inside the header of element " + Tag(group, element));
    }
    length = U32(l);
    return true;
  }

  /** Unsigned integer value of a top-level image attribute (US, or IS text for Number of Frames), read from the
   * current position (the caller moves past the element). */
  void
  Attribute(uint16_t element, uint32_t length)
  {
    if (length == 0 || length > 16)
    {
      return;
    }
    unsigned char v[16];
    if (!Read(v, length))
    {
      return;
    }
    const uint64_t value =
      element == 0x0008
        ? static_cast<uint64_t>(std::strtoull(std::string(reinterpret_cast<char *>(v), length).c_str(), nullptr, 10))
        : (length >= 2 ? U16(v) : 0);
    switch (element)
    {
      case 0x0002:
        samples = value;
        break;
      case 0x0008:
        frames = value > 0 ? value : 1;
        break;
      case 0x0010:
        rows = value;
        break;
      case 0x0011:
        columns = value;
        break;
      case 0x0100:
        bitsAllocated = value;
        break;
      default:
        break;
    }
  }

  /** The text of a geometry attribute from the current position (the caller moves past the element), at most 4096
   * bytes (six DS values take at most 101). */
  void
  ReadText(Text & text, uint32_t length)
  {
    text.present = true;
    text.value.assign(std::min<uint32_t>(length, 4096), '\0');
    if (!text.value.empty() && !in.read(&text.value[0], static_cast<std::streamsize>(text.value.size())))
    {
      text.value.clear();
    }
  }

  /** The fragments of encapsulated pixel data, to the sequence delimiter. */
  bool
  Fragments()
  {
    for (int items = 0;; ++items)
    {
      unsigned char h[8];
      if (Left() == 0 && items >= 2)
      {
        return GiveUp(); // the offset table and a fragment, then no delimiter: some writers leave it out at the end
      }
      if (Left() < 8 || !Read(h, 8))
      {
        return Stop("the file ends inside its encapsulated pixel data");
      }
      const uint16_t group = U16(h), element = U16(h + 2);
      const uint32_t length = U32(h + 4);
      if (group != 0xFFFE || (element != 0xE000 && element != 0xE0DD) || length == Undefined)
      {
        return GiveUp();
      }
      if (element == 0xE0DD)
      {
        return true;
      }
      if (length > Left())
      {
        return PastTheEnd("a fragment of its encapsulated pixel data", length);
      }
      Skip(length);
    }
  }

  /** The items of a sequence of undefined length, to its delimiter; items of undefined length are walked. A UN
   * element's items are implicit VR little endian. */
  bool
  Sequence(int depth, bool implicitLittle)
  {
    const bool wasLittle = little, wasExplicit = explicitVR;
    if (implicitLittle)
    {
      little = true; // item tags carry no VR, so the items' data sets can be read this way throughout
      explicitVR = false;
    }
    bool ok = true;
    for (;;)
    {
      unsigned char h[8];
      if (Left() < 8 || !Read(h, 8))
      {
        ok = Stop("the file ends inside a sequence");
        break;
      }
      const uint16_t group = U16(h), element = U16(h + 2);
      const uint32_t length = U32(h + 4);
      if (group != 0xFFFE || (element != 0xE000 && element != 0xE0DD))
      {
        ok = GiveUp();
        break;
      }
      if (element == 0xE0DD)
      {
        break;
      }
      if (length != Undefined)
      {
        if (length > Left())
        {
          ok = PastTheEnd("a sequence item", length);
          break;
        }
        Skip(length);
        continue;
      }
      ok = DataSet(depth + 1, true);
      if (!ok)
      {
        break;
      }
    }
    little = wasLittle;
    explicitVR = wasExplicit;
    return ok;
  }

  /** Data elements to the end of the file (depth 0) or to an item delimiter (inItem). */
  bool
  DataSet(int depth, bool inItem)
  {
    if (depth > 32)
    {
      return GiveUp();
    }
    for (;;)
    {
      if (Left() == 0)
      {
        return inItem ? Stop("the file ends inside a sequence item") : true;
      }
      uint16_t group = 0, element = 0;
      uint32_t length = 0;
      char     vr[2];
      if (!Header(group, element, vr, length))
      {
        return false;
      }
      if (group == 0xFFFE)
      {
        return inItem && element == 0xE00D ? true : GiveUp();
      }
      const bool pixel = depth == 0 && group == 0x7FE0 && (element == 0x0010 || element == 0x0008 || element == 0x0009);
      if (length == Undefined)
      {
        if (pixel)
        {
          pixelData = encapsulated = true;
          if (!Fragments())
          {
            return false;
          }
          pixelComplete = true;
        }
        else if (!Sequence(depth, explicitVR && std::memcmp(vr, "UN", 2) == 0))
        {
          return false;
        }
        continue;
      }
      if (length > Left())
      {
        return PastTheEnd("element " + Tag(group, element), length);
      }
      const uint64_t valueAt = Position();
      if (pixel)
      {
        pixelData = pixelComplete = true;
        pixelBytes = length;
      }
      else if (depth == 0 && group == 0x0028 && element == 0x0030)
      {
        ReadText(pixelSpacing, length);
      }
      else if (depth == 0 && group == 0x0028)
      {
        Attribute(element, length); // reads the value
      }
      else if (depth == 0 && group == 0x0020 && (element == 0x0032 || element == 0x0037))
      {
        ReadText(element == 0x0032 ? position : orientation, length);
      }
      in.seekg(static_cast<std::streamoff>(valueAt + length));
    }
  }
};

/** The numbers of a DICOM decimal string (DS) attribute: backslash-separated values, each a decimal number with
 * optional spaces around it (longer than the standard's 16 characters too: some writers exceed it, and GDCM reads
 * them). False when a value is empty, not such a number or not finite ("nan", "inf" and "1e999" are not). */
inline bool
DicomDecimals(const std::string & text, std::vector<double> & values)
{
  values.clear();
  std::string trimmed = text;
  while (!trimmed.empty() && (trimmed.back() == ' ' || trimmed.back() == '\0'))
  {
    trimmed.pop_back();
  }
  size_t begin = 0;
  for (;;)
  {
    const size_t end = std::min(trimmed.find('\\', begin), trimmed.size());
    std::string  item = trimmed.substr(begin, end - begin);
    const size_t first = item.find_first_not_of(' '), last = item.find_last_not_of(' ');
    if (first == std::string::npos || item.find_first_not_of("0123456789+-.eE", first) <= last)
    {
      return false;
    }
    item = item.substr(first, last - first + 1);
    char *       stop = nullptr;
    const double v = std::strtod(item.c_str(), &stop);
    if (stop != item.c_str() + item.size() || !std::isfinite(v))
    {
      return false;
    }
    values.push_back(v);
    if (end == trimmed.size())
    {
      return true;
    }
    begin = end + 1;
  }
}

/** Throws itk::ExceptionObject when a geometry attribute the walk read has a value but an unusable one: Pixel Spacing
 * not two finite numbers above 0, Image Position (Patient) not three finite numbers, Image Orientation (Patient) not
 * six finite numbers making two unit vectors (within 1 %) at a right angle (within 0.01). GDCM reads such values
 * without an error and puts defaults or garbage in their place (a spacing of 1 mm, a negative spacing as a flipped
 * axis, positions at 0), and ITK aborts the process on a position of 1e999. */
inline void
CheckDicomGeometry(const std::string & path, const DicomWalk & w)
{
  auto refuse = [&path](const char * name, const char * tag, const std::string & value, const char * wanted) {
    std::string shown = value.substr(0, 64);
    while (!shown.empty() && (shown.back() == ' ' || shown.back() == '\0'))
    {
      shown.pop_back();
    }
    for (char & c : shown)
    {
      c = std::isprint(static_cast<unsigned char>(c)) ? c : '?';
    }
    throw itk::ExceptionObject(__FILE__,
                               __LINE__,
                               path + ": its " + name + " " + tag + " is \"" + shown + "\", not " + wanted +
                                 ": the file's geometry is corrupt",
                               ITK_LOCATION);
  };
  auto given = [](const DicomWalk::Text & t) { // an empty value means "unknown", as if the attribute were absent
    return t.present && t.value.find_first_not_of(std::string(" \0", 2)) != std::string::npos;
  };
  std::vector<double> v;
  if (given(w.pixelSpacing) && !(DicomDecimals(w.pixelSpacing.value, v) && v.size() == 2 && v[0] > 0.0 && v[1] > 0.0))
  {
    refuse("Pixel Spacing", "(0028,0030)", w.pixelSpacing.value, "two finite numbers above 0 (mm)");
  }
  if (given(w.position) && !(DicomDecimals(w.position.value, v) && v.size() == 3))
  {
    refuse("Image Position (Patient)", "(0020,0032)", w.position.value, "three finite numbers (mm)");
  }
  if (given(w.orientation))
  {
    bool ok = DicomDecimals(w.orientation.value, v) && v.size() == 6;
    if (ok)
    {
      const double rr = v[0] * v[0] + v[1] * v[1] + v[2] * v[2], cc = v[3] * v[3] + v[4] * v[4] + v[5] * v[5];
      const double rc = v[0] * v[3] + v[1] * v[4] + v[2] * v[5];
      ok = std::abs(std::sqrt(rr) - 1.0) <= 0.01 && std::abs(std::sqrt(cc) - 1.0) <= 0.01 && std::abs(rc) <= 0.01;
    }
    if (!ok)
    {
      refuse("Image Orientation (Patient)",
             "(0020,0037)",
             w.orientation.value,
             "six finite numbers giving two perpendicular unit vectors");
    }
  }
}

/** DICOM (a Part 10 file or a bare data set): every element whole, Pixel Data present and, uncompressed grey values,
 * as long as rows x columns x frames x bytes per sample. No verdict (no exception) on encodings the walk does not
 * follow (DicomWalk). */
inline void
CheckDicom(const std::string & path)
{
  DicomWalk w(path);
  if (!w.in)
  {
    return; // left to GDCM, which says why it cannot read the file
  }
  unsigned char head[132];
  uint64_t      start = 0;
  if (w.size >= 132 && w.Read(head, 132) && std::memcmp(head + 128, "DICM", 4) == 0)
  {
    start = 132;
  }
  w.in.clear();
  w.in.seekg(static_cast<std::streamoff>(start));
  // the file meta information (group 0002), explicit VR little endian, names the data set's transfer syntax
  std::string syntax;
  bool        meta = false;
  for (;;)
  {
    unsigned char g[2];
    if (w.Left() < 2 || !w.Read(g, 2))
    {
      break;
    }
    w.in.seekg(static_cast<std::streamoff>(w.Position() - 2));
    if ((g[0] | (g[1] << 8)) != 0x0002)
    {
      break;
    }
    meta = true;
    uint16_t group = 0, element = 0;
    uint32_t length = 0;
    char     vr[2];
    if (!w.Header(group, element, vr, length))
    {
      if (!w.problem.empty())
      {
        ThrowTruncated(path, w.problem);
      }
      return;
    }
    if (length == DicomWalk::Undefined)
    {
      return;
    }
    if (length > w.Left())
    {
      w.PastTheEnd("element " + DicomWalk::Tag(group, element), length);
      ThrowTruncated(path, w.problem);
    }
    if (element == 0x0010 && length <= 64)
    {
      std::string value(length, '\0');
      w.in.read(&value[0], length);
      syntax = value.substr(0, value.find_last_not_of(std::string(" \0", 2)) + 1);
    }
    else
    {
      w.Skip(length);
    }
  }
  if (syntax == "1.2.840.10008.1.2.1.99")
  {
    return; // a deflated data set
  }
  if (w.Left() < 8)
  {
    if (start == 132 || meta)
    {
      ThrowTruncated(path,
                     w.Left() == 0
                       ? "it holds no data set after its file meta information"
                       : "the file ends inside a data element's header, at byte " + std::to_string(w.Position()));
    }
    return; // not a DICOM file the walk can tell anything about: left to GDCM
  }
  if (syntax == "1.2.840.10008.1.2")
  {
    w.explicitVR = false;
  }
  else if (syntax == "1.2.840.10008.1.2.2")
  {
    w.little = false;
  }
  else if (!meta || syntax.empty())
  {
    // no meta information: a bare data set; its first element tells the byte order and whether VRs are explicit
    unsigned char h[6];
    if (!w.Read(h, 6))
    {
      return;
    }
    w.in.seekg(static_cast<std::streamoff>(w.Position() - 6));
    w.little = !((h[0] << 8 | h[1]) == 0x0008 && (h[0] | (h[1] << 8)) != 0x0008);
    const char vr[2] = { static_cast<char>(h[4]), static_cast<char>(h[5]) };
    w.explicitVR = DicomWalk::ShortLengthVR(vr) || DicomWalk::LongLengthVR(vr);
  }
  if (!w.DataSet(0, false) && !w.problem.empty() && !w.pixelComplete)
  {
    ThrowTruncated(path, w.problem); // (after a whole Pixel Data: trailing bytes some writers add, left to GDCM)
  }
  CheckDicomGeometry(path, w); // the attributes read before any stop are whole
  if (w.noVerdict && !w.pixelComplete)
  {
    return;
  }
  if (!w.pixelData)
  {
    ThrowTruncated(path, "it holds no Pixel Data element (7FE0,0010)");
  }
  // uncompressed grey values (one sample per pixel: colour may be stored subsampled, as YBR_FULL_422)
  if (!w.encapsulated && w.samples == 1 && w.rows > 0 && w.columns > 0 && w.frames <= (uint64_t(1) << 24) &&
      w.bitsAllocated > 0 && w.bitsAllocated % 8 == 0)
  {
    const uint64_t expected = w.rows * w.columns * w.frames * (w.bitsAllocated / 8);
    if (w.pixelBytes < expected)
    {
      ThrowTruncated(path,
                     "its Pixel Data has " + std::to_string(w.pixelBytes) + " bytes, its header describes " +
                       std::to_string(expected) + ": " + std::to_string(w.rows) + " rows x " +
                       std::to_string(w.columns) + " columns x " + std::to_string(w.frames) + " frames x " +
                       std::to_string(w.bitsAllocated / 8) + " bytes");
    }
  }
}

/** The first `bytes` bytes of path, decompressed when it is a gzip file (zlib reads other files as they are). */
inline std::string
DecompressedHead(const std::string & path, size_t bytes)
{
  std::string head(bytes, '\0');
  gzFile      file = gzopen(path.c_str(), "rb");
  if (!file)
  {
    return std::string();
  }
  const int got = gzread(file, &head[0], static_cast<unsigned int>(bytes));
  gzclose(file);
  head.resize(got > 0 ? static_cast<size_t>(got) : 0);
  return head;
}

/** MetaImage: MetaIO reads NDims values for DimSize, ElementSpacing and Offset and NDims x NDims for TransformMatrix,
 * from whatever NDims says; a header with NDims = -1e308 (or -2147483649) kept ITK 5.2's reader in that loop for
 * good. Throws itk::ExceptionObject for a .mha/.mhd header whose NDims is not a number from 1 to 10. */
inline void
CheckMetaImageDimensions(const std::string & path)
{
  const std::string ext = Extension(path);
  if (ext != ".mha" && ext != ".mhd")
  {
    return;
  }
  unsigned int fields = 0;
  ForEachMetaImageField(path, [&](const std::string & key, const std::string & value, uint64_t) {
    if (key == "NDims")
    {
      char *       end = nullptr;
      const double n = std::strtod(value.c_str(), &end);
      if (end == value.c_str() || !(n >= 1.0 && n < 11.0))
      {
        throw itk::ExceptionObject(__FILE__,
                                   __LINE__,
                                   path + ": the MetaImage header's NDims (" + value +
                                     ") is not a number of dimensions from 1 to 10: the header is corrupt",
                                   ITK_LOCATION);
      }
    }
    return ++fields < 1000;
  });
}

/** Whether ITK 5.2's single-precision SVDs of a finite sform return: its NIfTI reader checks that the sform is an
 * invertible affine transformation (IsAffine) by inverting the 4 x 4 matrix (sto_xyz: srow_x/y/z over 0 0 0 1) and,
 * when that is well conditioned, its upper 3 x 3 part with vnl_svd<float> while it reads the header, and for some
 * finite matrices LINPACK's ssvdc there never returns: entries whose squares overflow single precision (3e38, offsets
 * included), and nearly singular matrices whose entries span 20 or more orders of magnitude (1e10 over 1.5e-33; found
 * by mutating header fields, mapped with random matrices). No simple rule on the entries separates them, so the same
 * two decompositions run here on a thread of their own, on a copy: when they have not returned within `wait`, the
 * thread is left to spin until the process ends (the tools end with the error) and the answer is no. */
inline bool
SformDecompositionsReturn(const std::array<float, 12> & srow, std::chrono::milliseconds wait)
{
  auto        done = std::make_shared<std::promise<void>>();
  const auto  returned = done->get_future();
  std::thread probe;
  try
  {
    probe = std::thread([srow, done] {
      try
      {
        vnl_matrix<float> m(4, 4, 0.0f), top(3, 3);
        for (unsigned int r = 0; r < 3; ++r)
        {
          for (unsigned int c = 0; c < 4; ++c)
          {
            m(r, c) = srow[4 * r + c];
            if (c < 3)
            {
              top(r, c) = srow[4 * r + c];
            }
          }
        }
        m(3, 3) = 1.0f;
        // the 3 x 3 part is inverted only when the 4 x 4 matrix is well enough conditioned to be invertible
        vnl_svd<float> four(m);
        if (four.well_condition() > std::numeric_limits<float>::epsilon())
        {
          vnl_svd<float> three(top);
        }
      }
      catch (...) // (out of memory) the decompositions returned: ITK's reader reports what it meets
      {
      }
      done->set_value();
    });
  }
  catch (const std::system_error &)
  {
    return true; // no thread to spare (a limit on threads): ITK's reader is left to read the file, as before
  }
  probe.detach();
  return returned.wait_for(wait) == std::future_status::ready;
}

/** The NIfTI-1 geometry, before ITK 5.2's reader sees it. The sform: a NaN or infinite entry anywhere in srow_x/y/z
 * aborts the process in that reader (vnl's assert_finite in the SVDs of SformDecompositionsReturn), and some finite
 * sforms keep it from ever returning (tried when `decompose`). The voxel sizes pixdim[1..3] and, with qform_code > 0,
 * the qform's parameters: the NIfTI library reads NaN or infinite ones as 1 mm or as some rotation. Throws
 * itk::ExceptionObject for any of these, for a .nii, .nia, .hdr or .img file (gzipped or not); Analyze headers (no
 * NIfTI magic) have only the voxel sizes, and headers with sform_code 0 have no sform. */
inline void
CheckNiftiSform(const std::string & path, bool decompose)
{
  std::string lower = itksys::SystemTools::LowerCase(path);
  if (lower.size() > 3 && lower.compare(lower.size() - 3, 3, ".gz") == 0)
  {
    lower.resize(lower.size() - 3);
  }
  const std::string        ext = Extension(lower);
  std::vector<std::string> headers;
  if (ext == ".nii" || ext == ".nia" || ext == ".hdr")
  {
    headers.push_back(path);
  }
  else if (ext == ".img")
  {
    const std::string base = path.substr(0, lower.size() - 4); // the name as given, without .img[.gz]
    headers = { base + ".hdr", base + ".hdr.gz", base + ".HDR" };
  }
  for (const std::string & header : headers)
  {
    if (!itksys::SystemTools::FileExists(header, true))
    {
      continue;
    }
    const std::string h = DecompressedHead(header, 348);
    if (h.size() < 348)
    {
      return; // short: the reader and the size checks say so
    }
    const auto * p = reinterpret_cast<const unsigned char *>(h.data());
    // the byte order as the NIfTI library tells it: from dim[0] (1..7), from sizeof_hdr only when dim[0] is 0 (it
    // reads headers whose sizeof_hdr is wrong)
    bool swap = false;
    if (p[40] != 0 || p[41] != 0)
    {
      if (!Nifti1SwapFromDim0(p, swap))
      {
        return; // the reader refuses it
      }
    }
    else if (LittleEndian32(p) != 348)
    {
      if (BigEndian32(p) != 348)
      {
        return; // the reader refuses it
      }
      swap = true;
    }
    auto floatAt = [&](size_t at) {
      const uint32_t bits = swap ? BigEndian32(p + at) : LittleEndian32(p + at);
      float          f;
      std::memcpy(&f, &bits, sizeof f);
      return f;
    };
    auto halfAt = [&](size_t at) {
      return static_cast<int16_t>(swap ? (p[at] << 8) | p[at + 1] : p[at] | (p[at + 1] << 8));
    };
    // the voxel sizes of the image's axes (pixdim[1..3]): the NIfTI library puts 1 in place of a NaN or infinite one,
    // so a corrupt header was read as a 1 mm grid without a word
    const int16_t axes = std::min<int16_t>(halfAt(40), 3);
    for (int16_t i = 1; i <= axes; ++i)
    {
      const float v = floatAt(76 + 4 * static_cast<size_t>(i));
      if (!std::isfinite(v))
      {
        std::ostringstream what;
        what << path << ": the NIfTI header's voxel size pixdim[" << i << "] = " << v
             << " is not a finite number: the header is corrupt";
        throw itk::ExceptionObject(__FILE__, __LINE__, what.str(), ITK_LOCATION);
      }
    }
    if (!(p[344] == 'n' && (p[345] == 'i' || p[345] == '+') && p[346] == '1' && p[347] == 0))
    {
      return; // Analyze 7.5: no qform, no sform
    }
    // the qform (quatern_b, c, d, qoffset_x, y, z), when used: the NIfTI library reads NaN parameters as a rotation
    const int16_t qformCode = halfAt(252);
    for (unsigned int i = 0; qformCode > 0 && i < 6; ++i)
    {
      const float v = floatAt(256 + 4 * i);
      if (!std::isfinite(v))
      {
        static const char * const names[] = { "quatern_b", "quatern_c", "quatern_d",
                                              "qoffset_x", "qoffset_y", "qoffset_z" };
        std::ostringstream        what;
        what << path << ": the NIfTI header's qform (qform_code " << qformCode << ") has " << names[i] << " = " << v
             << ", not a finite number: the header is corrupt";
        throw itk::ExceptionObject(__FILE__, __LINE__, what.str(), ITK_LOCATION);
      }
    }
    const int16_t sformCode = halfAt(254);
    if (sformCode <= 0)
    {
      return;
    }
    std::array<float, 12> srow;
    for (unsigned int i = 0; i < 12; ++i)
    {
      srow[i] = floatAt(280 + 4 * i);
      if (!std::isfinite(srow[i]))
      {
        std::ostringstream what;
        what << path << ": the NIfTI header's sform (sform_code " << sformCode << ") has srow_"
             << static_cast<char>('x' + i / 4) << "[" << i % 4 << "] = " << srow[i]
             << ", not a finite number: the header is corrupt";
        throw itk::ExceptionObject(__FILE__, __LINE__, what.str(), ITK_LOCATION);
      }
    }
    if (decompose && !SformDecompositionsReturn(srow, std::chrono::seconds(2)))
    {
      std::ostringstream what;
      what << path << ": the NIfTI header's sform (sform_code " << sformCode << ") is (";
      for (unsigned int i = 0; i < 12; ++i)
      {
        what << (i == 0 ? "" : (i % 4 == 0 ? "; " : ", ")) << srow[i];
      }
      what << "), which ITK's reader cannot take apart (its SVD does not return): the header is corrupt";
      throw itk::ExceptionObject(__FILE__, __LINE__, what.str(), ITK_LOCATION);
    }
    return;
  }
}
} // namespace detail

/** Before any ITK reader opens path: throws itk::ExceptionObject when a PNG, JPEG or BMP file (told by its first
 * bytes) ends early. */
inline void
CheckEncodedImageFileIsComplete(const std::string & path)
{
  if (itksys::SystemTools::FileIsDirectory(path))
  {
    return;
  }
  const std::string head = detail::Head(path, 64);
  if (head.compare(0, 8, "\x89PNG\r\n\x1a\n") == 0)
  {
    detail::CheckPng(path);
  }
  else if (head.size() >= 3 && head.compare(0, 3, "\xFF\xD8\xFF") == 0)
  {
    detail::CheckJpeg(path);
  }
  else if (head.compare(0, 2, "BM") == 0 && detail::Extension(path) == ".bmp")
  {
    detail::CheckBmp(path, head);
  }
}

/** Throws itk::ExceptionObject when the DICOM file at path ends before its data elements do, has no Pixel Data or
 * less uncompressed grey pixel data than rows x columns x frames (detail::DicomWalk), or a Pixel Spacing, Image
 * Position or Image Orientation (Patient) whose value is not made of usable numbers (detail::CheckDicomGeometry).
 * Run on every slice of a series: GDCM reads a slice cut short without an error, the missing pixels zeros, and such
 * geometry as defaults or garbage. */
inline void
CheckDicomFileIsComplete(const std::string & path)
{
  detail::CheckDicom(path);
}

/** Before any ITK reader opens path: the checks that must come first because ITK's readers abort the process or never
 * return on such files (CheckEncodedImageFileIsComplete; a NIfTI sform ITK cannot take apart, detail::CheckNiftiSform;
 * a MetaImage NDims out of range, detail::CheckMetaImageDimensions).
 * With decomposeSform, a finite sform is also taken apart as ITK's reader does, on a thread of its own: vnl prints a
 * warning to stderr for a singular one, so run it where stderr is captured (ImageDimensionOf, which the tools run on
 * every input first). Throws itk::ExceptionObject. */
inline void
CheckImageFileBeforeReading(const std::string & path, bool decomposeSform = true)
{
  if (itksys::SystemTools::FileIsDirectory(path))
  {
    return;
  }
  CheckEncodedImageFileIsComplete(path);
  detail::CheckNiftiSform(path, decomposeSform);
  detail::CheckMetaImageDimensions(path);
}

/** After io has read path's header, before an image takes its geometry: throws itk::ExceptionObject when the spacing,
 * origin or direction holds a value that is not a finite number, or the spacing a subnormal one. ITK 5.2 aborts the
 * process when a geometry that is not finite is set on an image (the SVD of direction x spacing asserts finite
 * entries), e.g. for a legacy VTK file with SPACING nan; its readers do not refuse it. */
inline void
CheckImageGeometryIsFinite(const std::string & path, const itk::ImageIOBase * io)
{
  const unsigned int d = io->GetNumberOfDimensions();
  auto               refuse = [&](const char * what, const std::vector<double> & values) {
    for (const double v : values)
    {
      if (!std::isfinite(v))
      {
        std::ostringstream text;
        text << path << ": the header's " << what << " is not made of finite numbers (";
        for (size_t i = 0; i < values.size(); ++i)
        {
          text << (i ? ", " : "") << values[i];
        }
        text << "): the header is corrupt";
        throw itk::ExceptionObject(__FILE__, __LINE__, text.str(), ITK_LOCATION);
      }
    }
  };
  std::vector<double> spacing, origin, direction;
  for (unsigned int i = 0; i < d; ++i)
  {
    spacing.push_back(io->GetSpacing(i));
    origin.push_back(io->GetOrigin(i));
    const std::vector<double> column = io->GetDirection(i);
    direction.insert(direction.end(), column.begin(), column.end());
  }
  refuse("spacing", spacing);
  refuse("origin", origin);
  refuse("direction", direction);
  // a subnormal spacing (1e-320) makes vnl print its SVD's warnings while ITK inverts the image's geometry
  for (const double v : spacing)
  {
    if (v != 0.0 && !std::isnormal(v))
    {
      std::ostringstream text;
      text << path << ": the header's spacing holds " << v
           << ", below the smallest normal double precision number: the header is corrupt";
      throw itk::ExceptionObject(__FILE__, __LINE__, text.str(), ITK_LOCATION);
    }
  }
}

/** After io has read path's header: throws itk::ExceptionObject when an uncompressed NIfTI, MetaImage or legacy VTK
 * file holds less pixel data than its header describes, or a DICOM file less than its elements describe. */
inline void
CheckRawPixelDataIsComplete(const std::string & path, const itk::ImageIOBase * io)
{
  const std::string name = io->GetNameOfClass();
  const uint64_t    bytes = static_cast<uint64_t>(io->GetImageSizeInBytes());
  if (name == "NiftiImageIO")
  {
    detail::CheckNifti(path, bytes);
  }
  else if (name == "MetaImageIO")
  {
    detail::CheckMetaImage(path, bytes);
  }
  else if (name == "VTKImageIO")
  {
    detail::CheckVtk(path, bytes);
  }
  else if (name == "GDCMImageIO")
  {
    detail::CheckDicom(path);
  }
}
} // namespace dmrtools

#endif
