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
#ifndef dmrCudaUtils_cuh
#define dmrCudaUtils_cuh

/** Shared helpers of the .cu files (never included by a .h/.hxx): error checking into dmr::cuda::Status and an RAII
 * device buffer. */
#include "dmrCudaBackend.h"
#include <cuda_runtime.h>
#include <cstddef>
#include <sstream>
#include <stdexcept>
#include <string>

namespace itk
{
namespace dmr
{
namespace cuda
{
/** Thrown inside the .cu files only, caught at the launcher boundary and turned into a Status. */
class CudaError : public std::runtime_error
{
public:
  explicit CudaError(const std::string & what)
    : std::runtime_error(what)
  {
  }
};

/** The allocator's bookkeeping (dmrCudaDevice.cu, dmr::cuda::GetMemoryStatistics): DeviceBuffer reports every
 * allocation and free. */
void
RecordDeviceAllocation(size_t bytes);
void
RecordDeviceFree(size_t bytes) noexcept;

inline void
Check(cudaError_t status, const char * what)
{
  if (status != cudaSuccess)
  {
    cudaGetLastError(); // clear a non-sticky error so later calls are not poisoned
    std::ostringstream os;
    if (status == cudaErrorMemoryAllocation)
    {
      os << "out of GPU memory in " << what;
      size_t freeBytes = 0, totalBytes = 0;
      if (cudaMemGetInfo(&freeBytes, &totalBytes) == cudaSuccess)
      {
        os << " (" << (freeBytes >> 20) << " of " << (totalBytes >> 20) << " MiB free)";
      }
    }
    else
    {
      os << "CUDA error in " << what << ": " << cudaGetErrorString(status);
    }
    throw CudaError(os.str());
  }
}

/** Checks the last kernel launch (configuration errors); execution errors surface at the next synchronising call. */
inline void
CheckLaunch(const char * kernel)
{
  Check(cudaGetLastError(), kernel);
}

/** Runs body() and turns any exception into a Status (the launcher boundary). */
template <typename TBody>
Status
Guard(TBody && body)
{
  try
  {
    body();
    return Status::Success();
  }
  catch (const std::bad_alloc &)
  {
    return Status::Error("out of host memory in the CUDA back-end");
  }
  catch (const std::exception & e)
  {
    return Status::Error(e.what());
  }
}

/** Owning device allocation of n elements of T (cudaMalloc; no managed memory). Resizing discards the contents. */
template <typename T>
class DeviceBuffer
{
public:
  DeviceBuffer() = default;
  explicit DeviceBuffer(size_t n) { Resize(n); }
  DeviceBuffer(const DeviceBuffer &) = delete;
  DeviceBuffer &
  operator=(const DeviceBuffer &) = delete;
  DeviceBuffer(DeviceBuffer && other) noexcept
    : m_Data(other.m_Data)
    , m_Size(other.m_Size)
  {
    other.m_Data = nullptr;
    other.m_Size = 0;
  }
  DeviceBuffer &
  operator=(DeviceBuffer && other) noexcept
  {
    if (this != &other)
    {
      Free();
      m_Data = other.m_Data;
      m_Size = other.m_Size;
      other.m_Data = nullptr;
      other.m_Size = 0;
    }
    return *this;
  }
  ~DeviceBuffer() { Free(); }

  /** Allocates exactly n elements unless the current allocation already has n. */
  void
  Resize(size_t n)
  {
    if (n == m_Size)
    {
      return;
    }
    Free();
    if (n > 0)
    {
      void * p = nullptr;
      Check(cudaMalloc(&p, n * sizeof(T)), "cudaMalloc");
      m_Data = static_cast<T *>(p);
      m_Size = n;
      RecordDeviceAllocation(n * sizeof(T));
    }
  }
  /** Grows (never shrinks) to at least n elements; the contents are discarded when it grows. */
  void
  Reserve(size_t n)
  {
    if (n > m_Size)
    {
      Resize(n);
    }
  }
  void
  Free() noexcept
  {
    if (m_Data)
    {
      cudaFree(m_Data);
      RecordDeviceFree(m_Size * sizeof(T));
    }
    m_Data = nullptr;
    m_Size = 0;
  }
  void
  Upload(const T * host, size_t n, cudaStream_t stream = nullptr)
  {
    Reserve(n);
    Check(cudaMemcpyAsync(m_Data, host, n * sizeof(T), cudaMemcpyHostToDevice, stream), "upload");
  }
  void
  Download(T * host, size_t n, cudaStream_t stream = nullptr) const
  {
    Check(cudaMemcpyAsync(host, m_Data, n * sizeof(T), cudaMemcpyDeviceToHost, stream), "download");
    Check(cudaStreamSynchronize(stream), "download (synchronise)");
  }
  void
  Zero(cudaStream_t stream = nullptr)
  {
    if (m_Size)
    {
      Check(cudaMemsetAsync(m_Data, 0, m_Size * sizeof(T), stream), "cudaMemset");
    }
  }
  T *
  Data()
  {
    return m_Data;
  }
  const T *
  Data() const
  {
    return m_Data;
  }
  size_t
  Size() const
  {
    return m_Size;
  }
  size_t
  Bytes() const
  {
    return m_Size * sizeof(T);
  }

private:
  T *    m_Data{ nullptr };
  size_t m_Size{ 0 };
};

/** The bytes held by the given buffers, of any element types. */
template <typename... TBuffers>
size_t
BytesOf(const TBuffers &... buffers)
{
  return (size_t{ 0 } + ... + buffers.Bytes());
}

inline unsigned int
Blocks(size_t n, unsigned int threads)
{
  return static_cast<unsigned int>((n + threads - 1) / threads);
}
} // namespace cuda
} // namespace dmr
} // namespace itk

#endif
