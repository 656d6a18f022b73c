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
// The tools' .nii.gz writer (dmrtools::WriteImage, dmrtools::GzipFileParallel): what ITK reads back is the image
// written, bit for bit, with its geometry, and the file is a gzip stream of several members.
#include "dmrExampleTestDirectory.h"
#include "dmrToolOutput.h"
#include "itkImage.h"
#include "itkImageFileReader.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "itkVector.h"
#include "itksys/Directory.hxx"
#include "gtest/gtest.h"
#include <chrono>
#include <csignal>
#include <cstring>
#include <fstream>
#include <iterator>
#include <random>
#include <fcntl.h>
#include <sys/file.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

namespace
{
std::string
TemporaryDirectory()
{
  return dmrtools::test::TemporaryDirectory("dmrToolOutputGTest");
}

std::vector<unsigned char>
ReadBytes(const std::string & path)
{
  std::ifstream in(path, std::ios::binary);
  return std::vector<unsigned char>(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

/** The gzip members of a file (decompressed one after the other with zlib's inflate), and their total output. */
size_t
GzipMembers(const std::vector<unsigned char> & file, std::vector<unsigned char> & data)
{
  size_t                     members = 0, offset = 0;
  std::vector<unsigned char> buffer(1 << 16);
  while (offset < file.size())
  {
    z_stream z{};
    EXPECT_EQ(inflateInit2(&z, 15 + 16), Z_OK);
    z.next_in = const_cast<unsigned char *>(file.data() + offset);
    z.avail_in = static_cast<uInt>(file.size() - offset);
    int status = Z_OK;
    while (status == Z_OK)
    {
      z.next_out = buffer.data();
      z.avail_out = static_cast<uInt>(buffer.size());
      status = inflate(&z, Z_NO_FLUSH);
      data.insert(data.end(), buffer.data(), buffer.data() + (buffer.size() - z.avail_out));
    }
    EXPECT_EQ(status, Z_STREAM_END) << "member " << members << " at byte " << offset;
    offset += z.total_in;
    inflateEnd(&z);
    if (status != Z_STREAM_END)
    {
      break;
    }
    ++members;
  }
  return members;
}
} // namespace

TEST(ToolOutput, NiftiGzIsTheImageBitForBitInSeveralGzipMembers)
{
  using ImageType = itk::Image<itk::Vector<float, 3>, 3>;
  auto                     image = ImageType::New();
  ImageType::SizeType      size{ { 61, 47, 33 } }; // 1.1 MiB of voxels: two members of 1 MiB at least
  ImageType::SpacingType   spacing;
  ImageType::PointType     origin;
  ImageType::DirectionType direction;
  for (unsigned int k = 0; k < 3; ++k)
  {
    spacing[k] = 0.5 + 0.25 * k;
    origin[k] = -20.0 + 7.0 * k;
  }
  direction.SetIdentity();
  direction(0, 0) = 0.0;
  direction(0, 1) = -1.0;
  direction(1, 0) = 1.0;
  direction(1, 1) = 0.0;
  image->SetRegions(size);
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  image->SetDirection(direction);
  image->Allocate();
  std::mt19937                                 rng(7);
  std::uniform_real_distribution<float>        value(-50.0f, 50.0f);
  itk::ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    ImageType::PixelType v;
    for (unsigned int k = 0; k < 3; ++k)
    {
      v[k] = (it.GetIndex()[2] % 3 == 0) ? 0.0f : value(rng); // compressible and incompressible slices
    }
    it.Set(v);
  }

  const std::string dir = TemporaryDirectory();
  const std::string path = dir + "/field.nii.gz";
  dmrtools::WriteImage(image.GetPointer(), path);
  {
    // the temporary uncompressed file is gone: the output is the folder's only file
    itksys::Directory listing;
    listing.Load(dir);
    std::vector<std::string> files;
    for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
    {
      const std::string name = listing.GetFile(i);
      if (name != "." && name != "..")
      {
        files.push_back(name);
      }
    }
    EXPECT_EQ(files, std::vector<std::string>{ "field.nii.gz" });
  }

  std::vector<unsigned char> data;
  const auto                 file = ReadBytes(path);
  const size_t               members = GzipMembers(file, data);
  EXPECT_GE(members, 2u);
  EXPECT_LT(file.size(), data.size()) << "compressed";
  EXPECT_GT(data.size(), 61u * 47 * 33 * 12) << "the whole NIfTI file";

  auto reader = itk::ImageFileReader<ImageType>::New();
  reader->SetFileName(path);
  ASSERT_NO_THROW(reader->Update());
  const auto * back = reader->GetOutput();
  EXPECT_EQ(back->GetLargestPossibleRegion().GetSize(), size);
  for (unsigned int k = 0; k < 3; ++k)
  {
    EXPECT_NEAR(back->GetSpacing()[k], spacing[k], 1e-6);
    EXPECT_NEAR(back->GetOrigin()[k], origin[k], 1e-4);
    for (unsigned int j = 0; j < 3; ++j)
    {
      EXPECT_NEAR(back->GetDirection()[k][j], direction[k][j], 1e-6);
    }
  }
  const size_t n = image->GetLargestPossibleRegion().GetNumberOfPixels();
  EXPECT_EQ(std::memcmp(back->GetBufferPointer(), image->GetBufferPointer(), n * sizeof(ImageType::PixelType)), 0);
  itksys::SystemTools::RemoveADirectory(dir);
}

TEST(ToolOutput, GzipOfAnUnreadableFileThrowsAndWritesNothing)
{
  const std::string dir = TemporaryDirectory();
  EXPECT_THROW(dmrtools::GzipFileParallel(dir + "/missing.nii", dir + "/out.nii.gz"), std::runtime_error);
  EXPECT_FALSE(itksys::SystemTools::FileExists(dir + "/out.nii.gz"));
  itksys::SystemTools::RemoveADirectory(dir);
}

namespace
{
/** Runs body in a child process whose files may not grow beyond limit bytes (RLIMIT_FSIZE, with SIGXFSZ ignored, so a
 * write past it is cut short with EFBIG, as on a full disk). The child's exit code: 0 when body threw
 * std::runtime_error, 1 when it returned, 2 on another exception. */
template <typename TBody>
int
ExitCodeWithFileSizeLimit(rlim_t limit, TBody && body)
{
  const pid_t child = ::fork();
  if (child == 0)
  {
    std::signal(SIGXFSZ, SIG_IGN);
    const rlimit cap{ limit, limit };
    ::setrlimit(RLIMIT_FSIZE, &cap);
    int code = 1;
    try
    {
      body();
    }
    catch (const std::runtime_error &)
    {
      code = 0;
    }
    catch (...)
    {
      code = 2;
    }
    std::_Exit(code);
  }
  int status = 0;
  ::waitpid(child, &status, 0);
  return WIFEXITED(status) ? WEXITSTATUS(status) : 100 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
}
/** A 512 x 512 float image of zeros: 1 MiB of pixel data. */
itk::Image<float, 2>::Pointer
ZeroImage512()
{
  using ImageType = itk::Image<float, 2>;
  auto image = ImageType::New();
  image->SetRegions(ImageType::SizeType{ { 512, 512 } });
  image->Allocate();
  image->FillBuffer(0.0f);
  return image;
}
} // namespace

TEST(ToolOutput, WritesCutShortByAFullDiskThrow)
{
  // ITK's NIfTI writer and an unchecked std::ofstream do not notice a short write: a 1 MiB image cut at 64 KiB was
  // compressed (zeros: a few hundred bytes) into a .nii.gz that looked whole, and a cut energy.csv or report.json was
  // committed as a result
  const std::string dir = TemporaryDirectory();
  const auto        image = ZeroImage512();
  const rlim_t      limit = 64 << 10;
  EXPECT_EQ(ExitCodeWithFileSizeLimit(limit, [&] { dmrtools::WriteImage(image.GetPointer(), dir + "/cut.nii.gz"); }), 0)
    << "a NIfTI file cut short was not an error";
  const std::string text(256 << 10, 'x');
  EXPECT_EQ(ExitCodeWithFileSizeLimit(limit, [&] { dmrtools::WriteTextFile(dir + "/cut.csv", text); }), 0)
    << "a text file cut short was not an error";
  // ReplaceTextFile leaves the file it replaces as it was, and no temporary file
  dmrtools::WriteTextFile(dir + "/report.json", "{\"earlier\": 1}\n");
  EXPECT_EQ(ExitCodeWithFileSizeLimit(limit, [&] { dmrtools::ReplaceTextFile(dir + "/report.json", text); }), 0);
  EXPECT_EQ(ReadBytes(dir + "/report.json").size(), std::string("{\"earlier\": 1}\n").size());
  itksys::Directory listing;
  listing.Load(dir);
  for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
  {
    EXPECT_EQ(std::string(listing.GetFile(i)).find("dmr-partial"), std::string::npos) << listing.GetFile(i);
  }
  // within the limit, all three are written whole
  EXPECT_EQ(ExitCodeWithFileSizeLimit(limit,
                                      [&] {
                                        dmrtools::ReplaceTextFile(dir + "/report.json", "{\"later\": 2}\n");
                                        dmrtools::WriteTextFile(dir + "/small.csv", "a,b\n");
                                      }),
            1);
  EXPECT_EQ(ReadBytes(dir + "/report.json").size(), std::string("{\"later\": 2}\n").size());
  itksys::SystemTools::RemoveADirectory(dir);
}

// The NIfTI library prints a short write ("** ERROR: NWAD: wrote only ...") to stderr and goes on: with the tool's own
// error that made two lines. WriteImage takes the library's line into its message instead.
TEST(ToolOutput, AShortWriteIsOneMessageWithTheLibrarysReason)
{
  const std::string dir = TemporaryDirectory();
  const auto        image = ZeroImage512();
  const std::string stderrFile = dir + "/stderr.txt", messageFile = dir + "/message.txt";
  const pid_t       child = ::fork();
  if (child == 0)
  {
    const int captured = ::open(stderrFile.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
    ::dup2(captured, 2);
    std::signal(SIGXFSZ, SIG_IGN);
    const rlimit cap{ 1 << 20, 1 << 20 }; // the 1 MiB image does not fit with its header; the message does
    ::setrlimit(RLIMIT_FSIZE, &cap);
    std::string message = "no error";
    try
    {
      dmrtools::WriteImage(image.GetPointer(), dir + "/cut.nii.gz");
    }
    catch (const std::exception & e)
    {
      message = e.what();
    }
    std::ofstream(messageFile) << message;
    std::_Exit(0);
  }
  int status = 0;
  ::waitpid(child, &status, 0);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  const auto        message = ReadBytes(messageFile), printed = ReadBytes(stderrFile);
  const std::string text(message.begin(), message.end());
  EXPECT_NE(text.find("the file was cut short"), std::string::npos) << text;
  EXPECT_NE(text.find("(the writer said: ** ERROR: NWAD: wrote only"), std::string::npos) << text;
  EXPECT_EQ(std::string(printed.begin(), printed.end()), "") << "printed beside the message";
  itksys::SystemTools::RemoveADirectory(dir);
}

// ReplaceTextFile wrote a temporary file and renamed it onto the path, whatever the path named: a pipe or a device too
// (as root, `--report /dev/stdout` replaced /dev/stdout, a link to /proc/self/fd/1, for every process on the machine,
// and `--report /dev/full` hid the full disk). A link to a regular file is still replaced, not what it points to, as
// every output of the tools (the check of outputs over inputs relies on it).
TEST(ToolOutput, ReplaceTextFileWritesIntoPipesAndReplacesLinksToFiles)
{
  const std::string dir = TemporaryDirectory();
  auto              readText = [](const std::string & path) {
    const auto bytes = ReadBytes(path);
    return std::string(bytes.begin(), bytes.end());
  };
  // a named pipe with a reader, reached through a link as /dev/stdout is: the reader gets the text, the pipe stays a
  // pipe and the link a link
  const std::string fifo = dir + "/pipe";
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
  ASSERT_EQ(::symlink("pipe", (dir + "/pipe-link").c_str()), 0);
  const int reader = ::open(fifo.c_str(), O_RDONLY | O_NONBLOCK); // a reader, so that opening for writing does not wait
  ASSERT_GE(reader, 0);
  dmrtools::ReplaceTextFile(dir + "/pipe-link", "{\"piped\": 3}\n");
  char          buffer[64] = {};
  const ssize_t got = ::read(reader, buffer, sizeof(buffer) - 1);
  ::close(reader);
  EXPECT_EQ(std::string(buffer, got > 0 ? static_cast<size_t>(got) : 0), "{\"piped\": 3}\n");
  struct stat entry = {};
  ASSERT_EQ(::lstat(fifo.c_str(), &entry), 0);
  EXPECT_TRUE(S_ISFIFO(entry.st_mode)) << "the pipe was replaced";
  ASSERT_EQ(::lstat((dir + "/pipe-link").c_str(), &entry), 0);
  EXPECT_TRUE(S_ISLNK(entry.st_mode)) << "the link to the pipe was replaced";
  // a link to a regular file: the link is replaced by the new file, the file it named keeps its text
  dmrtools::WriteTextFile(dir + "/real.json", "{\"earlier\": 1}\n");
  ASSERT_EQ(::symlink("real.json", (dir + "/link.json").c_str()), 0);
  dmrtools::ReplaceTextFile(dir + "/link.json", "{\"later\": 2}\n");
  ASSERT_EQ(::lstat((dir + "/link.json").c_str(), &entry), 0);
  EXPECT_TRUE(S_ISREG(entry.st_mode));
  EXPECT_EQ(readText(dir + "/link.json"), "{\"later\": 2}\n");
  EXPECT_EQ(readText(dir + "/real.json"), "{\"earlier\": 1}\n");
  itksys::Directory listing;
  listing.Load(dir);
  for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
  {
    EXPECT_EQ(std::string(listing.GetFile(i)).find("dmr-partial"), std::string::npos) << listing.GetFile(i);
  }
  itksys::SystemTools::RemoveADirectory(dir);
}

// A tab, a newline or a Latin-1 byte in an input's file name made report.json invalid JSON (the names went in with only
// quotes and backslashes escaped).
TEST(ToolOutput, JsonEscapeGivesValidJsonStringsForAnyFileName)
{
  using dmrtools::JsonEscape;
  EXPECT_EQ(JsonEscape("plain/name.nii.gz"), "plain/name.nii.gz");
  EXPECT_EQ(JsonEscape("a\"b\\c"), "a\\\"b\\\\c");
  EXPECT_EQ(JsonEscape(std::string("t\tn\nr\r\x01\x1f")), "t\\u0009n\\u000ar\\u000d\\u0001\\u001f");
  // well-formed UTF-8 (2, 3 and 4 bytes) is kept; DEL (0x7f) needs no escape
  EXPECT_EQ(JsonEscape("\xc3\xa9t\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80 \x7f"),
            "\xc3\xa9t\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80 \x7f");
  // not UTF-8: a Latin-1 byte, a lone continuation byte, a cut sequence, an overlong form, a surrogate, beyond U+10FFFF
  EXPECT_EQ(JsonEscape("caf\xe9.nii"), "caf\\ufffd.nii");
  EXPECT_EQ(JsonEscape("\x80x"), "\\ufffdx");
  EXPECT_EQ(JsonEscape("ab\xe2\x82"), "ab\\ufffd\\ufffd");
  EXPECT_EQ(JsonEscape("\xc0\xaf"), "\\ufffd\\ufffd");
  EXPECT_EQ(JsonEscape("\xe0\x80\xaf"), "\\ufffd\\ufffd\\ufffd");
  EXPECT_EQ(JsonEscape("\xed\xa0\x80"), "\\ufffd\\ufffd\\ufffd");
  EXPECT_EQ(JsonEscape("\xf4\x90\x80\x80"), "\\ufffd\\ufffd\\ufffd\\ufffd");
  EXPECT_EQ(JsonEscape("\xff"), "\\ufffd");
}

// The tools' one-line errors: ITK's "ITK ERROR: " prefix and the object's address were left in messages that quote an
// ITK exception (e.g. "cannot read an image from F: ITK ERROR: ITK only supports orthonormal direction cosines...").
TEST(ToolErrors, ItkPrefixesAndAddressesAreRemovedEverywhereInAMessage)
{
  using dmrtools::WithoutItkPrefix;
  EXPECT_EQ(WithoutItkPrefix("ITK ERROR: FEMRegistrationMethod(0x55d0c0ffee00): Mu must be finite"),
            "FEMRegistrationMethod: Mu must be finite");
  EXPECT_EQ(WithoutItkPrefix("cannot read an image from f.nii: ITK ERROR: ITK only supports orthonormal direction "
                             "cosines. No orthonormal definition found!"),
            "cannot read an image from f.nii: ITK only supports orthonormal direction cosines. No orthonormal "
            "definition found!");
  EXPECT_EQ(WithoutItkPrefix("a: ITK ERROR: A(0x1): first; b: ITK ERROR: B(0x2a): second"),
            "a: A: first; b: B: second");
  EXPECT_EQ(WithoutItkPrefix("no prefix (0x12): kept"), "no prefix (0x12): kept");
}

TEST(ToolOutput, ACommitThatCannotGetTheLockGivesUpAfterItsPatienceAndLeavesNothing)
{
  // Another process that keeps the output directory's lock (a hung run, a stale lock on a network file system) makes
  // a finished run's commit fail with one message after its patience (120 s in the tools), instead of waiting forever;
  // its staged outputs are removed and the directory keeps what it had.
  const std::string dir = TemporaryDirectory();
  {
    std::ofstream(dir + "/report.json") << "earlier run\n";
  }
  const int holder = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC); // another open file description
  ASSERT_GE(holder, 0);
  ASSERT_EQ(::flock(holder, LOCK_EX | LOCK_NB), 0);
  std::string stage;
  {
    dmrtools::Staging staging(dir);
    stage = staging.stage;
    {
      std::ofstream(staging.Path("report.json")) << "this run\n";
    }
    staging.lockPatience = 0.5;
    const auto start = std::chrono::steady_clock::now();
    try
    {
      staging.Commit();
      ADD_FAILURE() << "the commit went on while another process held the lock";
    }
    catch (const std::runtime_error & e)
    {
      EXPECT_NE(std::string(e.what()).find("another process has held the output directory " + dir + " for 0.5 s"),
                std::string::npos)
        << e.what();
    }
    const double waited = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    EXPECT_GE(waited, 0.5);
    EXPECT_LT(waited, 30.0);                                  // it gave up (a generous bound for a loaded machine)
    EXPECT_TRUE(itksys::SystemTools::FileIsDirectory(stage)); // still staged until the run ends
  }
  EXPECT_FALSE(itksys::SystemTools::FileExists(stage)); // the ended run's staging is removed
  std::ifstream kept(dir + "/report.json");
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(kept), std::istreambuf_iterator<char>()), "earlier run\n");
  // once the lock is free, a commit goes through
  ::close(holder);
  {
    dmrtools::Staging staging(dir);
    {
      std::ofstream(staging.Path("report.json")) << "next run\n";
    }
    staging.lockPatience = 0.5;
    EXPECT_NO_THROW(staging.Commit());
  }
  std::ifstream next(dir + "/report.json");
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(next), std::istreambuf_iterator<char>()), "next run\n");
  itksys::SystemTools::RemoveADirectory(dir);
}
