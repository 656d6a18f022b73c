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
#include "dmrImageFileCheck.h"
#include "itkImageFileWriter.h"
#include "itkMultiThreaderBase.h"
#include "itksys/Directory.hxx"
#include "itksys/SystemTools.hxx"
#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <functional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <fcntl.h> // open (POSIX)
#include <signal.h>
#include <sys/file.h> // flock
#include <sys/stat.h> // stat (POSIX)
#include <unistd.h>
#include <vector>
#include <zlib.h>

namespace dmrtools
{
/** Everything is written into a private staging folder inside the output directory and moved into place only when
 * the run succeeded, so a failure never leaves half-written outputs. */
struct Staging
{
  std::string             dir, stage;
  bool                    createdDir{ false };
  bool                    committed{ false };
  static constexpr double DefaultLockPatience = 120;
  double                  lockPatience{ DefaultLockPatience }; // seconds Commit waits for the directory's lock
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
    else
    {
      RemoveStagingOfEndedRuns();
    }
    stage = dir + "/" + StagingName(::getpid());
    if (!itksys::SystemTools::MakeDirectory(stage))
    {
      throw UsageError("cannot create the output directory " + dir);
    }
  }
  /** The name of the staging folder of process pid on this host: ".dmr-partial-HOST-PID". The host is part of it
   * because D may lie on storage that runs on other hosts share, where a process number means nothing here. */
  static std::string
  StagingName(long pid)
  {
    char host[256] = {};
    if (::gethostname(host, sizeof(host) - 1) != 0)
    {
      host[0] = '\0';
    }
    std::string name = ".dmr-partial-";
    for (const char * c = host; *c; ++c)
    {
      const bool plain = (*c >= 'a' && *c <= 'z') || (*c >= 'A' && *c <= 'Z') || (*c >= '0' && *c <= '9') || *c == '.';
      name += plain ? *c : '_';
    }
    return name + "-" + std::to_string(pid);
  }

  /** A run that was killed (SIGKILL after a scheduler's grace period, the out-of-memory killer) leaves its staging
   * folder behind; the folders of this host's runs whose process no longer exists are removed (a live one may be
   * another run's, and another host's processes cannot be checked from here). */
  void
  RemoveStagingOfEndedRuns() const
  {
    const std::string ours = StagingName(0);
    const std::string prefix = ours.substr(0, ours.size() - 1); // ".dmr-partial-HOST-"
    itksys::Directory listing;
    listing.Load(dir);
    for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
    {
      const std::string name = listing.GetFile(i);
      const std::string digits = name.compare(0, prefix.size(), prefix) == 0 ? name.substr(prefix.size()) : "";
      if (digits.empty() || digits.size() > 9 || digits.find_first_not_of("0123456789") != std::string::npos ||
          !itksys::SystemTools::FileIsDirectory(dir + "/" + name))
      {
        continue;
      }
      const pid_t pid = static_cast<pid_t>(std::stol(digits));
      if (pid > 0 && ::kill(pid, 0) != 0 && errno == ESRCH)
      {
        itksys::SystemTools::RemoveADirectory(dir + "/" + name);
      }
    }
  }
  std::string
  Path(const std::string & name) const
  {
    return stage + "/" + name;
  }
  /** Holds an exclusive flock(2) on the output directory while it lives, so that runs into the same directory commit
   * one after the other: two runs that ended together renamed their files in turn and could leave a mix of both (the
   * warped image of one beside the field of the other), and one's removal of stale numbered meshes could take the
   * other's. A holder that keeps the lock for the patience (DefaultLockPatience seconds in the tools) makes the commit
   * fail rather than hang; where the file system has no such locks (some network file systems) the commit goes on
   * without. */
  struct DirectoryLock
  {
    int fd{ -1 };
    /** Waits at most patience seconds (of wall-clock time) for the lock. */
    explicit DirectoryLock(const std::string & directory, double patience = DefaultLockPatience)
    {
      fd = ::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
      if (fd < 0)
      {
        return;
      }
      const auto start = std::chrono::steady_clock::now();
      for (;;)
      {
        if (::flock(fd, LOCK_EX | LOCK_NB) == 0)
        {
          return;
        }
        if (errno != EWOULDBLOCK && errno != EINTR)
        {
          Release(); // no locks here
          return;
        }
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() >= patience)
        {
          Release();
          std::ostringstream waited;
          waited << patience;
          throw std::runtime_error("another process has held the output directory " + directory + " for " +
                                   waited.str() + " s while this run waited to move its outputs in");
        }
        if (InterruptSignal() != 0)
        {
          Release();
          ThrowIfInterrupted();
        }
        ::usleep(50000);
      }
    }
    void
    Release()
    {
      if (fd >= 0)
      {
        ::close(fd); // closing the last descriptor releases the lock
        fd = -1;
      }
    }
    ~DirectoryLock() { Release(); }
    DirectoryLock(const DirectoryLock &) = delete;
    DirectoryLock &
    operator=(const DirectoryLock &) = delete;
  };

  /** Moves the staged outputs into the directory, then runs afterMove (e.g. the removal of an earlier run's outputs
   * that this run did not write), both under the directory's lock. */
  void
  Commit(const std::function<void()> & afterMove = {})
  {
    ThrowIfInterrupted(); // an interrupted run commits nothing (the destructor removes the staged outputs)
    const DirectoryLock lock(dir, lockPatience);
    ThrowIfInterrupted();
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
    if (afterMove)
    {
      afterMove();
    }
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

/** The directory entry that path names, as an absolute path: its folder with symbolic links and ".." resolved, its own
 * name kept (a link is an entry of its own). Writing to one path replaces what another names exactly when their
 * entries are equal: the tools move finished files into place, and a rename replaces the entry, not what a link at it
 * points to. A folder that does not exist is kept as written (collapsed to an absolute path). */
inline std::string
DirectoryEntry(const std::string & path)
{
  const std::string full = itksys::SystemTools::CollapseFullPath(path);
  std::string       folder = itksys::SystemTools::GetFilenamePath(full);
  if (itksys::SystemTools::FileIsDirectory(folder))
  {
    folder = itksys::SystemTools::GetRealPath(folder);
  }
  return folder + "/" + itksys::SystemTools::GetFilenameName(full);
}

/** The name under which path lies directly in directory (compared as directory entries, see DirectoryEntry), or ""
 * when it lies elsewhere: writing that name into directory would replace what path names. */
inline std::string
NameInDirectory(const std::string & directory, const std::string & path)
{
  std::string folder = DirectoryEntry(directory + "/x"); // the directory (links resolved) + "/x"
  folder.pop_back();
  const std::string entry = DirectoryEntry(path);
  const bool        inside =
    entry.compare(0, folder.size(), folder) == 0 && entry.find('/', folder.size()) == std::string::npos;
  return inside ? entry.substr(folder.size()) : "";
}

/** Throws a UsageError when writing one of the files `names` into outputDir would replace the input at `path` (given
 * with `flag`): the tools read their inputs before they write, so such a run went through and destroyed the input. */
inline void
RefuseOutputOverInput(const std::string &              outputDir,
                      const std::vector<std::string> & names,
                      const std::string &              flag,
                      const std::string &              path)
{
  const std::string name = NameInDirectory(outputDir, path);
  if (!name.empty() && std::find(names.begin(), names.end(), name) != names.end())
  {
    throw UsageError("the output " + name + " in --output-dir would replace the input " + flag + " " + path +
                     ": choose another output directory");
  }
}

/** True when name is one of the numbered meshes the registration tool writes: mesh_NNNN.vtu (four or more digits). */
inline bool
IsNumberedMeshName(const std::string & name)
{
  const std::string head = "mesh_", tail = ".vtu";
  if (name.size() < head.size() + 4 + tail.size() || name.compare(0, head.size(), head) != 0 ||
      name.compare(name.size() - tail.size(), tail.size(), tail) != 0)
  {
    return false;
  }
  return std::all_of(name.begin() + head.size(), name.end() - tail.size(), [](char c) { return c >= '0' && c <= '9'; });
}

/** s as the contents of a JSON string: quotes, backslashes and control characters escaped, and every byte that is not
 * part of a valid UTF-8 sequence replaced by U+FFFD. A file name may hold any byte but '/' and NUL: a tab, a newline or
 * a Latin-1 byte in an input's name made report.json invalid JSON. */
inline std::string
JsonEscape(const std::string & s)
{
  std::string out;
  for (size_t i = 0; i < s.size();)
  {
    const auto c = static_cast<unsigned char>(s[i]);
    if (c == '"' || c == '\\')
    {
      out += '\\';
      out += static_cast<char>(c);
      ++i;
    }
    else if (c < 0x20)
    {
      const char * hex = "0123456789abcdef";
      out += "\\u00";
      out += hex[c >> 4];
      out += hex[c & 15];
      ++i;
    }
    else if (c < 0x80)
    {
      out += static_cast<char>(c);
      ++i;
    }
    else
    {
      // a well-formed sequence (RFC 3629: no overlong forms, no surrogates, at most U+10FFFF) is kept as it is
      const size_t n = c >= 0xC2 && c <= 0xDF ? 2 : c >= 0xE0 && c <= 0xEF ? 3 : c >= 0xF0 && c <= 0xF4 ? 4 : 0;
      bool         valid = n > 0 && i + n <= s.size();
      for (size_t k = 1; valid && k < n; ++k)
      {
        valid = (static_cast<unsigned char>(s[i + k]) & 0xC0) == 0x80;
      }
      const auto second = valid ? static_cast<unsigned char>(s[i + 1]) : 0;
      valid = valid && !(c == 0xE0 && second < 0xA0) && !(c == 0xED && second >= 0xA0) &&
              !(c == 0xF0 && second < 0x90) && !(c == 0xF4 && second >= 0x90);
      out += valid ? s.substr(i, n) : std::string("\\ufffd");
      i += valid ? n : 1;
    }
  }
  return out;
}

/** Writes text into the file at path and checks that all of it got there: a full disk shows only when the stream is
 * flushed, and an unchecked std::ofstream left a cut energy.csv or report.json that was then committed as a result.
 * Throws std::runtime_error when any of it could not be written. */
inline void
WriteTextFile(const std::string & path, const std::string & text)
{
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << text;
  out.close();
  if (!out)
  {
    throw std::runtime_error("could not write " + path + " (not writable, or the disk is full)");
  }
}

/** Writes text into the file at path through a temporary file next to it that is renamed onto path once all of it is
 * written: path is either left as it was (an earlier report, or nothing) or holds the whole text, never a part. Like
 * every output of the tools, a link at path is replaced, not what it points to (see DirectoryEntry), except where it
 * points to something that is not a regular file: a path that names a terminal, a pipe or a device (/dev/stdout, a
 * link to /proc/self/fd/1) is written into, since renaming onto it replaced the device or the link with a file (as
 * root, `--report /dev/stdout` replaced /dev/stdout for every process, and `--report /dev/full` hid the full disk).
 * Throws std::runtime_error (after removing the temporary file) otherwise. */
inline void
ReplaceTextFile(const std::string & path, const std::string & text)
{
  struct stat target = {};
  if (::stat(path.c_str(), &target) == 0 && !S_ISREG(target.st_mode) && !S_ISDIR(target.st_mode))
  {
    WriteTextFile(path, text);
    return;
  }
  const std::string partial = path + ".dmr-partial-" + std::to_string(::getpid());
  try
  {
    WriteTextFile(partial, text);
    if (std::rename(partial.c_str(), path.c_str()) != 0)
    {
      throw std::runtime_error("could not move " + partial + " onto " + path);
    }
  }
  catch (...)
  {
    std::remove(partial.c_str());
    throw;
  }
}

/** Copies the file `in` to `out` gzip-compressed on all of ITK's work units: the data in chunks of `chunk` bytes, each
 * a complete gzip member, the members concatenated in order. RFC 1952 allows several members in one file and gzip
 * readers (zlib's gzread, which ITK's NIfTI reader uses, Python's gzip, gunzip) read them as one stream. The default
 * zlib level 1 (Z_BEST_SPEED): on the thorax256 outputs (float images and fields) it gives files within 1-9 % of the
 * default level 6's at 1.2-4.6 times its speed. Throws std::runtime_error on a read, compression or write failure. */
inline void
GzipFileParallel(const std::string & in, const std::string & out, size_t chunk = size_t(1) << 20, int level = 1)
{
  std::FILE * source = std::fopen(in.c_str(), "rb");
  if (!source)
  {
    throw std::runtime_error("cannot read " + in);
  }
  std::FILE * target = std::fopen(out.c_str(), "wb");
  if (!target)
  {
    std::fclose(source);
    throw std::runtime_error("cannot write " + out);
  }
  const auto   threader = itk::MultiThreaderBase::New();
  const size_t batch = std::max<size_t>(1, threader->GetNumberOfWorkUnits()); // chunks compressed at once
  std::vector<std::vector<unsigned char>> raw(batch), packed(batch);
  std::vector<int>                        status(batch);
  std::string                             error;
  for (bool more = true; more && error.empty();)
  {
    size_t n = 0; // chunks read in this batch
    for (; n < batch; ++n)
    {
      raw[n].resize(chunk);
      raw[n].resize(std::fread(raw[n].data(), 1, chunk, source));
      if (raw[n].size() < chunk)
      {
        more = false;
        if (std::ferror(source))
        {
          error = "cannot read " + in;
        }
        n += raw[n].empty() ? 0 : 1;
        break;
      }
    }
    threader->ParallelizeArray(
      0,
      n,
      [&](size_t i) {
        z_stream z{};
        status[i] = deflateInit2(&z, level, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY); // 15 + 16: gzip wrapper
        if (status[i] != Z_OK)
        {
          return;
        }
        packed[i].resize(deflateBound(&z, static_cast<uLong>(raw[i].size())));
        z.next_in = raw[i].data();
        z.avail_in = static_cast<uInt>(raw[i].size());
        z.next_out = packed[i].data();
        z.avail_out = static_cast<uInt>(packed[i].size());
        status[i] = deflate(&z, Z_FINISH) == Z_STREAM_END ? Z_OK : Z_BUF_ERROR;
        packed[i].resize(z.total_out);
        deflateEnd(&z);
      },
      nullptr);
    for (size_t i = 0; i < n && error.empty(); ++i)
    {
      if (status[i] != Z_OK)
      {
        error = "gzip compression failed for " + out;
      }
      else if (std::fwrite(packed[i].data(), 1, packed[i].size(), target) != packed[i].size())
      {
        error = "cannot write " + out;
      }
    }
  }
  std::fclose(source);
  if (std::fclose(target) != 0 && error.empty())
  {
    error = "cannot write " + out;
  }
  if (!error.empty())
  {
    std::remove(out.c_str());
    throw std::runtime_error(error);
  }
}

/** Writes an image (compressed where the format allows). A .nii.gz is written by ITK uncompressed into a temporary
 * file beside it, then compressed on all work units (GzipFileParallel): ITK 5.2's NIfTI writer compresses on one
 * thread, which took longer than the 3D GPU registration itself. */
template <typename TImage>
void
WriteImage(const TImage * image, const std::string & path)
{
  const std::string gz = ".nii.gz";
  const bool        nifti = path.size() > gz.size() && path.compare(path.size() - gz.size(), gz.size(), gz) == 0;
  const std::string raw = nifti ? path.substr(0, path.size() - gz.size()) + ".uncompressed.nii" : path;
  auto              writer = itk::ImageFileWriter<TImage>::New();
  writer->SetInput(image);
  writer->SetFileName(raw);
  writer->SetUseCompression(!nifti);
  std::string said; // what the image library printed while writing (NIfTI: "** ERROR: NWAD: wrote only ..."), for
                    // the one-line message
  {
    StandardErrorCapture library;
    try
    {
      writer->Update();
    }
    catch (const itk::ExceptionObject & e)
    {
      said = library.Release();
      if (said.empty())
      {
        throw;
      }
      itk::ExceptionObject withReason(e);
      withReason.SetDescription(std::string(e.GetDescription()) + " (the writer said: " + said + ")");
      throw withReason;
    }
    said = library.Release();
  }
  if (nifti)
  {
    try
    {
      // ITK's NIfTI writer does not notice a short write (the NIfTI library only prints it): a full disk gave a cut
      // file, which the compression would have carried into the output
      try
      {
        CheckRawPixelDataIsComplete(raw, writer->GetImageIO());
      }
      catch (const itk::ExceptionObject &)
      {
        throw std::runtime_error("cannot write " + path + ": the file was cut short (is the disk full?)" +
                                 (said.empty() ? std::string() : " (the writer said: " + said + ")"));
      }
      GzipFileParallel(raw, path);
    }
    catch (...)
    {
      std::remove(raw.c_str());
      throw;
    }
    std::remove(raw.c_str());
  }
}
} // namespace dmrtools

#endif
