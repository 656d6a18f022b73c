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
#ifndef itkDiscreteCVTFilter_hxx
#define itkDiscreteCVTFilter_hxx

#include "itkDiscreteCVTFilter.h"
#include "itkProgressReporter.h"
#include "dmrCudaBackend.h"
#include <memory>
#include <chrono>
#include <type_traits>

namespace itk
{
template <typename TDensityImage, typename TLabelImage>
DiscreteCVTFilter<TDensityImage, TLabelImage>::DiscreteCVTFilter()
{
  this->SetPrimaryInputName("DensityImage");
  this->AddOptionalInputName("InitialLabels");
  this->SetNumberOfRequiredOutputs(2);
  this->SetNthOutput(0, this->MakeOutput(0));
  this->SetNthOutput(1, this->MakeOutput(1));
}

template <typename TDensityImage, typename TLabelImage>
DataObject::Pointer
DiscreteCVTFilter<TDensityImage, TLabelImage>::MakeOutput(DataObjectPointerArraySizeType idx)
{
  if (idx == 1)
  {
    return SitesType::New().GetPointer();
  }
  return Superclass::MakeOutput(idx);
}

template <typename TDensityImage, typename TLabelImage>
auto
DiscreteCVTFilter<TDensityImage, TLabelImage>::GetSites() -> SitesType *
{
  return dynamic_cast<SitesType *>(this->ProcessObject::GetOutput(1));
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::VerifyPreconditions() ITKv5_CONST
{
  Superclass::VerifyPreconditions();
  if (std::isnan(m_Epsilon)) // passes itkSetClampMacro, and stopped no sweep
  {
    itkExceptionMacro("Epsilon must be a number in [0, 1], not NaN");
  }
  // the labels 0 .. NumberOfCells - 1 must fit the output's pixel type (e.g. at most 256 cells for unsigned char)
  if (static_cast<long double>(m_NumberOfCells - 1) > static_cast<long double>(NumericTraits<LabelType>::max()))
  {
    itkExceptionMacro("NumberOfCells (" << m_NumberOfCells << ") needs labels up to " << m_NumberOfCells - 1
                                        << ", more than the label pixel type holds ("
                                        << static_cast<long double>(NumericTraits<LabelType>::max()) << ")");
  }
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::VerifyInputInformation() ITKv5_CONST
{
  Superclass::VerifyInputInformation();
  // the CVT's distances are the grid's, scaled by the spacing: the physical ones only when the direction is a rotation
  const std::string skew = dmr::DirectionNotOrthonormal<ImageDimension>(this->GetInput(), "density image");
  if (!skew.empty())
  {
    itkExceptionMacro(<< skew);
  }
  const auto numberOfPixels = this->GetInput()->GetLargestPossibleRegion().GetNumberOfPixels();
  if (m_NumberOfCells > numberOfPixels)
  {
    itkExceptionMacro("NumberOfCells (" << m_NumberOfCells << ") exceeds the number of pixels (" << numberOfPixels
                                        << ")");
  }
  // read pixel for pixel with the density: its region (ImageToImageFilter checked origin, spacing and direction)
  if (const LabelImageType * initial = this->GetInitialLabels())
  {
    const std::string why = dmr::GridMismatch<ImageDimension>(
      this->GetInput(), initial, this->GetCoordinateTolerance(), this->GetDirectionTolerance(), "the density image");
    if (!why.empty())
    {
      itkExceptionMacro("InitialLabels must lie on the density image's grid: " << why);
    }
  }
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::GenerateInputRequestedRegion()
{
  Superclass::GenerateInputRequestedRegion();
  for (auto & input : this->GetInputs())
  {
    if (auto * image = dynamic_cast<ImageBase<ImageDimension> *>(input.GetPointer()))
    {
      image->SetRequestedRegionToLargestPossibleRegion();
    }
  }
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::EnlargeOutputRequestedRegion(DataObject * output)
{
  Superclass::EnlargeOutputRequestedRegion(output);
  if (auto * image = dynamic_cast<ImageBase<ImageDimension> *>(output))
  {
    image->SetRequestedRegionToLargestPossibleRegion();
  }
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::GenerateOutputInformation()
{
  const DensityImageType * input = this->GetInput();
  LabelImageType *         output = this->GetOutput();
  if (input && output)
  {
    output->CopyInformation(input);
    output->SetLargestPossibleRegion(input->GetLargestPossibleRegion());
  }
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::GenerateData()
{
  using Clock = std::chrono::steady_clock;
  ProgressReporter         progress(this, 0, 3);
  const DensityImageType * density = this->GetInput();
  const auto               grid = dmr::Grid<ImageDimension>::FromImage(density);
  // STYLE.md section 4: the contraction stays on the CPU, the swap optimisation runs on the GPU when one is used
  if (m_Backend != BackendEnum::CPU && dmr::cuda::DeviceAvailable())
  {
    m_BackendUsed = BackendEnum::CUDA;
  }
  else if (m_Backend == BackendEnum::CUDA)
  {
    itkExceptionMacro("CUDA back-end requested but " << dmr::cuda::UnavailableReason());
  }
  else
  {
    m_BackendUsed = BackendEnum::CPU;
  }

  // the input is whole (GenerateInputRequestedRegion): its buffer in pixel order, checked and converted on the threader
  MultiThreaderBase * threader = this->GetMultiThreader();
  const size_t        n = grid.numberOfPixels;
  if (density->GetBufferedRegion() != density->GetLargestPossibleRegion())
  {
    itkExceptionMacro("the density image's buffered region " << density->GetBufferedRegion()
                                                             << " is not its largest possible region");
  }
  const auto * densityIn = density->GetBufferPointer();
  const size_t badDensity = dmr::FirstIndexWhere(threader, n, [&](size_t i) {
    const double v = static_cast<double>(densityIn[i]);
    return !(v > 0.0) || !std::isfinite(v);
  });
  if (badDensity < n)
  {
    itkExceptionMacro("the density must be positive and finite everywhere; pixel "
                      << badDensity << " has " << static_cast<double>(densityIn[badDensity]));
  }
  m_DensityBuffer.resize(n);
  dmr::ParallelForChunks(threader, n, [&](size_t b, size_t e) {
    for (size_t i = b; i < e; ++i)
    {
      m_DensityBuffer[i] = static_cast<float>(static_cast<double>(densityIn[i]));
    }
  });
  m_Core.SetDensity(grid, m_DensityBuffer.data(), this->GetMultiThreader());
  // progress within the contraction (first third) and the CPU sweeps (second third); AbortGenerateData set by an
  // observer stops either within 65536 merges or one sweep
  float stageStart = 0.0f;
  struct ClearCheckpoint // the checkpoint refers to this call's locals: no later call of the core may reach it
  {
    CoreType & core;
    ~ClearCheckpoint() { core.SetCheckpoint(nullptr); }
  } clearCheckpoint{ m_Core };
  m_Core.SetCheckpoint([this, &stageStart](double fraction) {
    this->UpdateProgress(stageStart + static_cast<float>(fraction) / 3.0f);
    if (this->GetAbortGenerateData())
    {
      ProcessAborted aborted(__FILE__, __LINE__);
      aborted.SetDescription("DiscreteCVTFilter: AbortGenerateData was set");
      throw aborted;
    }
  });

  auto                   t0 = Clock::now();
  const LabelImageType * initial = this->GetInitialLabels();
  m_InitializationTime = 0.0;
  bool warm = false;
  if (initial)
  {
    if (initial->GetBufferedRegion() != initial->GetLargestPossibleRegion())
    {
      itkExceptionMacro("the initial labels' buffered region " << initial->GetBufferedRegion()
                                                               << " is not their largest possible region");
    }
    // the labels as the core's 32-bit type (the buffer itself when it has that type)
    std::vector<int32_t> converted;
    const int32_t *      labels = nullptr;
    using LabelPixelType = typename LabelImageType::PixelType;
    if constexpr (std::is_same<LabelPixelType, int32_t>::value)
    {
      labels = initial->GetBufferPointer();
    }
    else
    {
      converted.resize(n);
      const LabelPixelType * in = initial->GetBufferPointer();
      dmr::ParallelForChunks(threader, n, [&](size_t b, size_t e) {
        for (size_t i = b; i < e; ++i)
        {
          converted[i] = static_cast<int32_t>(in[i]);
        }
      });
      labels = converted.data();
    }
    const size_t         nChunks = 64;
    const size_t         chunk = (n + nChunks - 1) / nChunks;
    std::vector<int64_t> chunkMax(nChunks, -1);
    dmr::ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      const size_t end = std::min(n, (c + 1) * chunk);
      int64_t      m = -1;
      for (size_t i = std::min(n, c * chunk); i < end; ++i)
      {
        m = std::max<int64_t>(m, labels[i]);
      }
      chunkMax[c] = m;
    });
    const int64_t maxLabel = *std::max_element(chunkMax.begin(), chunkMax.end());
    if (maxLabel + 1 == static_cast<int64_t>(m_NumberOfCells))
    {
      m_Core.SetLabels(labels, m_NumberOfCells);
      warm = true;
    }
  }
  if (!warm)
  {
    m_Core.ContractionInitialize(m_NumberOfCells, m_BlockSize);
    m_InitializationTime = std::chrono::duration<double>(Clock::now() - t0).count();
  }
  progress.CompletedPixel();

  t0 = Clock::now();
  stageStart = 1.0f / 3.0f;
  m_InitialEnergy = m_Core.GetEnergy();
  typename CoreType::OptimizeResult result;
  result.energyBefore = result.energyAfter = m_Core.GetEnergy();
  if (m_SwapOptimization)
  {
    result = m_BackendUsed == BackendEnum::CUDA ? this->OptimizeOnDevice(grid)
                                                : m_Core.Optimize(m_Epsilon, m_MaximumNumberOfSweeps);
  }
  m_OptimizationTime = std::chrono::duration<double>(Clock::now() - t0).count();
  m_Energy = result.energyAfter;
  m_NumberOfSweeps = result.sweeps;
  m_NumberOfSwaps = result.swaps;
  progress.CompletedPixel();

  LabelImageType * output = this->GetOutput();
  output->SetBufferedRegion(output->GetLargestPossibleRegion());
  output->Allocate();
  std::copy(m_Core.GetLabels().begin(), m_Core.GetLabels().end(), output->GetBufferPointer());

  SitesType * sites = this->GetSites();
  sites->Initialize();
  const auto & centroids = m_Core.GetCentroids();
  const auto & masses = m_Core.GetMasses();
  const auto   start = density->GetLargestPossibleRegion().GetIndex();
  for (size_t c = 0; c < masses.size(); ++c)
  {
    ContinuousIndex<double, ImageDimension> ci;
    for (unsigned int k = 0; k < ImageDimension; ++k)
    {
      ci[k] = start[k] + centroids[c * ImageDimension + k] / grid.spacing[k];
    }
    typename SitesType::PointType point;
    density->TransformContinuousIndexToPhysicalPoint(ci, point);
    sites->SetPoint(c, point);
    sites->SetPointData(c, masses[c]);
  }
  progress.CompletedPixel();
}

template <typename TDensityImage, typename TLabelImage>
auto
DiscreteCVTFilter<TDensityImage, TLabelImage>::OptimizeOnDevice(const dmr::Grid<ImageDimension> & grid) ->
  typename CoreType::OptimizeResult
{
  if (!m_DeviceOptimizer)
  {
    m_DeviceOptimizer = std::make_unique<dmr::cuda::CVTSwapOptimizer>();
  }
  dmr::cuda::CVTSwapOptimizer & gpu = *m_DeviceOptimizer;
  auto                          check = [this](const dmr::cuda::Status & status) {
    if (!status.Ok())
    {
      itkExceptionMacro("CUDA swap optimisation failed: " << status.message);
    }
  };
  const size_t numberOfCells = m_Core.GetNumberOfCells();
  check(gpu.SetGrid(ImageDimension, grid.size.data(), grid.spacing.data()));
  check(gpu.SetDensity(m_DensityBuffer.data(), false));
  check(gpu.SetLabels(m_Core.GetLabels().data(), numberOfCells, false));
  dmr::cuda::CVTSwapResult result;
  check(gpu.Optimize(m_Epsilon, m_MaximumNumberOfSweeps, result));
  // the core takes the GPU's state, so GetCore() and the sites describe this update on both back-ends, bit for bit
  // alike (summing the masses and centroids again from the labels would round differently from the sweeps' updates)
  std::vector<int32_t> labels(grid.numberOfPixels);
  std::vector<double>  masses, centroids;
  check(gpu.DownloadLabels(labels.data()));
  check(gpu.GetCells(masses, centroids));
  m_Core.SetState(labels.data(), numberOfCells, masses.data(), centroids.data(), gpu.Energy());
  return { result.sweeps, result.swaps, result.rejectedBatches, result.energyBefore, result.energyAfter };
}

template <typename TDensityImage, typename TLabelImage>
void
DiscreteCVTFilter<TDensityImage, TLabelImage>::PrintSelf(std::ostream & os, Indent indent) const
{
  Superclass::PrintSelf(os, indent);
  os << indent << "NumberOfCells: " << m_NumberOfCells << std::endl;
  os << indent << "BlockSize: " << m_BlockSize << std::endl;
  os << indent << "Epsilon: " << m_Epsilon << std::endl;
  os << indent << "MaximumNumberOfSweeps: " << m_MaximumNumberOfSweeps << std::endl;
  os << indent << "SwapOptimization: " << m_SwapOptimization << std::endl;
  os << indent << "Backend: " << m_Backend << std::endl;
  os << indent << "BackendUsed: " << m_BackendUsed << std::endl;
  os << indent << "InitialEnergy: " << m_InitialEnergy << std::endl;
  os << indent << "Energy: " << m_Energy << std::endl;
  os << indent << "NumberOfSweeps: " << m_NumberOfSweeps << std::endl;
  os << indent << "NumberOfSwaps: " << m_NumberOfSwaps << std::endl;
  os << indent << "InitializationTime: " << m_InitializationTime << std::endl;
  os << indent << "OptimizationTime: " << m_OptimizationTime << std::endl;
}
} // namespace itk

#endif
