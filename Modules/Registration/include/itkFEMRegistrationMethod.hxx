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
#ifndef itkFEMRegistrationMethod_hxx
#define itkFEMRegistrationMethod_hxx

#include "itkFEMRegistrationMethod.h"
#include "itkImageRegionConstIterator.h"
#include "itkCommand.h"
#include "dmrCudaBackend.h"
#include "dmrFieldImage.h"
#include "dmrRegistrationBackend.h"
#include "dmrCVTBackend.h"
#include "dmrDualMeshBackend.h"
#include "dmrDualMeshBuilder.h"
#include "dmrImageMetrics.h"
#include "dmrBackEndRounding.h"
#include <chrono>
#include <cmath>
#include <future>
#include <sstream>
#include <string>
#include <type_traits>

namespace itk
{
template <typename TF, typename TM, typename TD>
FEMRegistrationMethod<TF, TM, TD>::FEMRegistrationMethod()
{
  this->SetPrimaryInputName("FixedImage");
  this->AddRequiredInputName("MovingImage");
  this->AddOptionalInputName("StaticMesh");
  this->AddOptionalInputName("FixedMask");
  this->AddOptionalInputName("InitialDisplacementField");
  this->AddOptionalInputName("InitialInverseDisplacementField");
  this->SetNumberOfRequiredOutputs(2);
  this->SetNthOutput(0, this->MakeOutput(0));
  this->SetNthOutput(1, this->MakeOutput(1));
  m_DensityFilter = DensityFilterType::New();
  m_CVTFilter = CVTFilterType::New();
  m_Solver = SolverType::New();
  // The CVT filter reports progress inside its long loops (the contraction, the CPU sweeps), which take minutes on a
  // large CT at the first iteration: the registration passes each report on as its own ProgressEvent (at the current
  // progress), so that an observer of the registration can set AbortGenerateData, and hands that on to the CVT filter,
  // which then stops with ProcessAborted. Before, an abort waited for the end of the iteration.
  auto forward = CStyleCommand::New();
  forward->SetClientData(this);
  forward->SetCallback([](Object *, const EventObject &, void * data) {
    auto * self = static_cast<Self *>(data);
    self->UpdateProgress(self->GetProgress());
    if (self->GetAbortGenerateData())
    {
      self->m_CVTFilter->AbortGenerateDataOn();
    }
  });
  m_CVTFilter->AddObserver(ProgressEvent(), forward);
}

template <typename TF, typename TM, typename TD>
DataObject::Pointer
FEMRegistrationMethod<TF, TM, TD>::MakeOutput(DataObjectPointerArraySizeType idx)
{
  if (idx == 0)
  {
    auto decorated = DecoratedTransformType::New();
    decorated->Set(TransformType::New());
    return decorated.GetPointer();
  }
  return DisplacementFieldType::New().GetPointer();
}

template <typename TF, typename TM, typename TD>
auto
FEMRegistrationMethod<TF, TM, TD>::GetTransformOutput() -> DecoratedTransformType *
{
  return static_cast<DecoratedTransformType *>(this->ProcessObject::GetOutput(0));
}

template <typename TF, typename TM, typename TD>
auto
FEMRegistrationMethod<TF, TM, TD>::GetTransform() -> const TransformType *
{
  return this->GetTransformOutput()->Get();
}

template <typename TF, typename TM, typename TD>
auto
FEMRegistrationMethod<TF, TM, TD>::GetDisplacementField() -> DisplacementFieldType *
{
  return static_cast<DisplacementFieldType *>(this->ProcessObject::GetOutput(1));
}

template <typename TF, typename TM, typename TD>
auto
FEMRegistrationMethod<TF, TM, TD>::GetCurrentMesh() -> const MeshType *
{
  if (m_CurrentMesh == nullptr)
  {
    return nullptr;
  }
  if (m_CurrentItkMesh.IsNull() || m_CurrentItkMeshVersion != m_CurrentMeshVersion)
  {
    m_CurrentItkMesh = dmr::ToItkMesh<ImageDimension, MeshType>(*m_CurrentMesh, this->GetFixedImage());
    m_CurrentItkMeshVersion = m_CurrentMeshVersion;
  }
  return m_CurrentItkMesh.GetPointer();
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::VerifyPreconditions() ITKv5_CONST
{
  Superclass::VerifyPreconditions();
  if (m_ComputeInverse && this->GetInitialDisplacementField() && !this->GetInitialInverseDisplacementField())
  {
    itkExceptionMacro("ComputeInverse with an InitialDisplacementField needs the inverse of that field "
                      "(SetInitialInverseDisplacementField): the inverse transformation starts from it");
  }
  // NaN passes itkSetClampMacro (every comparison with it is false), and infinity is clamped to the largest double: a
  // NaN EnergyRatio gave beta NaN and a run that moved nothing, an infinite Lambda a stiffness of infinities and the
  // stop condition "the images already match", an infinite EnergyRatio a NaN density. Values far beyond any use
  // (1e30) are refused as well, so that the products of the elastic constants, beta and the forces stay finite.
  for (const auto & [name, value] : { std::make_pair("Lambda", m_Lambda),
                                      std::make_pair("Mu", m_Mu),
                                      std::make_pair("EnergyRatio", m_EnergyRatio),
                                      std::make_pair("AlphaFactor", m_AlphaFactor) })
  {
    if (!(std::abs(value) <= LargestParameterValue))
    {
      itkExceptionMacro(<< name << " must be a finite number of at most " << LargestParameterValue << ", got "
                        << value);
    }
  }
  if (std::isnan(m_CVTEpsilon))
  {
    itkExceptionMacro("CVTEpsilon must be a number in [0, 1], got " << m_CVTEpsilon);
  }
  if (std::isnan(m_SolverTolerance))
  {
    itkExceptionMacro("SolverTolerance must be a number in [1e-16, 1e-2], got " << m_SolverTolerance);
  }
  if (m_MeshMode == MeshModeEnum::Static && this->GetStaticMesh() == nullptr)
  {
    itkExceptionMacro("MeshMode Static needs a mesh: call SetStaticMesh()");
  }
  if (m_Backend == BackendEnum::CUDA && !dmr::cuda::DeviceAvailable())
  {
    itkExceptionMacro("the CUDA back-end was requested but " << dmr::cuda::UnavailableReason());
  }
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::VerifyInputInformation() ITKv5_CONST
{
  Superclass::VerifyInputInformation();
  const std::string geometry =
    dmr::FixedAndMovingGeometryProblem<ImageDimension>(this->GetFixedImage(), this->GetMovingImage());
  if (!geometry.empty())
  {
    itkExceptionMacro(<< geometry);
  }
  const auto    size = this->GetFixedImage()->GetLargestPossibleRegion().GetSize();
  SizeValueType pixels = 1;
  for (unsigned int k = 0; k < ImageDimension; ++k)
  {
    if (size[k] < 4)
    {
      itkExceptionMacro("the fixed image needs at least 4 pixels along every axis; axis " << k << " has " << size[k]);
    }
    pixels *= size[k];
  }
  if (m_MeshMode == MeshModeEnum::Dynamic && m_NumberOfNodes > pixels)
  {
    itkExceptionMacro("NumberOfNodes (" << m_NumberOfNodes << ") exceeds the number of pixels (" << pixels << ")");
  }
  if (m_MeshMode == MeshModeEnum::Regular)
  {
    // border nodes are fixed: with 2 nodes along an axis every node lies on the border and nothing can move
    if (m_RegularGridSize == 1 || m_RegularGridSize == 2)
    {
      itkExceptionMacro("RegularGridSize (" << m_RegularGridSize
                                            << ") must be 0 (from NumberOfNodes) or at least 3: with fewer nodes per "
                                               "axis every node lies on the image border, where the displacement is "
                                               "fixed");
    }
    const auto nodes = this->RegularNodesPerAxis();
    for (unsigned int k = 0; k < ImageDimension; ++k)
    {
      if (nodes[k] < 3)
      {
        itkExceptionMacro("NumberOfNodes (" << m_NumberOfNodes << ") gives a Regular mesh of " << nodes[k]
                                            << " nodes along axis " << k
                                            << ", all on the image border, where the displacement is fixed: use at "
                                               "least 3 per axis (NumberOfNodes or RegularGridSize)");
      }
    }
  }
  // a static mesh whose data is already there (not the output of a reader that has not run) is checked now, so that a
  // caller learns of a mesh that cannot work before anything runs; otherwise when it is read (BuildStaticMesh)
  const MeshType * staticMesh = this->GetStaticMesh();
  if (m_MeshMode == MeshModeEnum::Static && staticMesh != nullptr && staticMesh->GetNumberOfPoints() > 0)
  {
    this->CheckStaticMeshHasAFreeNode(dmr::FromItkMesh<ImageDimension>(staticMesh, this->GetFixedImage()));
  }
  // the mask and the initial field are read pixel for pixel with the fixed image (the moving image may lie on any
  // grid)
  for (const auto & [image, name] :
       { std::make_pair(static_cast<const ImageBase<ImageDimension> *>(this->GetFixedMask()), "the fixed mask"),
         std::make_pair(static_cast<const ImageBase<ImageDimension> *>(this->GetInitialDisplacementField()),
                        "the initial displacement field"),
         std::make_pair(static_cast<const ImageBase<ImageDimension> *>(
                          m_ComputeInverse ? this->GetInitialInverseDisplacementField() : nullptr),
                        "the initial inverse displacement field") })
  {
    const std::string why =
      image ? dmr::GridMismatchAtDefaultTolerances<ImageDimension>(this->GetFixedImage(), image) : std::string();
    if (!why.empty())
    {
      itkExceptionMacro(<< name << " must lie on the fixed image grid: " << why);
    }
  }
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::GenerateInputRequestedRegion()
{
  for (auto & input : this->GetInputs())
  {
    if (auto * image = dynamic_cast<ImageBase<ImageDimension> *>(input.GetPointer()))
    {
      image->SetRequestedRegionToLargestPossibleRegion();
    }
  }
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::GenerateOutputInformation()
{
  Superclass::GenerateOutputInformation();
  DisplacementFieldType * field = this->GetDisplacementField();
  field->CopyInformation(this->GetFixedImage());
  field->SetRegions(this->GetFixedImage()->GetLargestPossibleRegion());
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::WriteGridFieldToImage(const std::vector<float> & grid,
                                                         DisplacementFieldType *    image) const
{
  dmr::FromGridFrame(grid.data(), this->GetFixedImage()->GetDirection(), image, this->GetMultiThreader());
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::GenerateData()
{
  constexpr unsigned int D = ImageDimension;
  using Clock = std::chrono::steady_clock;
  auto seconds = [](Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double>(b - a).count(); };
  const auto tStart = Clock::now();
  // the device's context (0.2-0.35 s on the H100 and H200 hosts) is created on a helper thread while the inputs are
  // checked and prepared; a failure there (no device: the CPU path runs) shows again, with its message, at the
  // context's Initialize
  std::future<dmr::cuda::Status> deviceContext;
  if (m_Backend != BackendEnum::CPU)
  {
    deviceContext = std::async(std::launch::async, [] { return dmr::cuda::CreateContext(); });
  }

  const FixedImageType *  fixed = this->GetFixedImage();
  const MovingImageType * moving = this->GetMovingImage();
  // "the <name> has a non-finite <quantity> (<value>) at index <index>"
  auto requireFinite = [this](const char * name, const char * quantity, const auto * image) {
    const auto p = image ? dmr::FirstNonFinitePixel(image, this->GetMultiThreader()) : -1;
    if (p >= 0)
    {
      itkExceptionMacro("the " << name << " has a non-finite " << quantity << " (" << image->GetBufferPointer()[p]
                               << ") at index " << image->ComputeIndex(static_cast<OffsetValueType>(p)));
    }
  };
  requireFinite("fixed image", "intensity", fixed);
  requireFinite("moving image", "intensity", moving);
  requireFinite("initial displacement field", "value", this->GetInitialDisplacementField());
  if (m_ComputeInverse)
  {
    requireFinite("initial inverse displacement field", "value", this->GetInitialInverseDisplacementField());
  }
  for (const auto & range :
       { dmr::IntensityRange(fixed, this->GetMultiThreader()), dmr::IntensityRange(moving, this->GetMultiThreader()) })
  {
    if (!(range.second > range.first))
    {
      itkExceptionMacro("an input image has constant intensity " << range.first
                                                                 << ": there is no force to register with (the "
                                                                    "density alpha would be 0)");
    }
  }
  m_DeviceBytes = 0;
  m_ContractedOnHost = false;
  m_DevicePeakBytes = 0;
  m_DeviceUsedAtPeakBytes = 0;
  if (m_Backend != BackendEnum::CPU && dmr::cuda::DeviceAvailable())
  {
    m_BackendUsed = BackendEnum::CUDA;
    dmr::cuda::ResetMemoryPeak();
    this->GenerateDataCUDA(tStart, deviceContext);
    return;
  }
  m_BackendUsed = BackendEnum::CPU;
  MultiThreaderBase * threader = this->GetMultiThreader();
  const auto          grid = dmr::Grid<D>::FromImage(fixed);
  const size_t        n = grid.numberOfPixels;
  const double        dV = grid.PixelVolume();

  // current transformation W(x) = x + w(x): grid-frame flat copy + physical image for the density filter
  // three full fields: w, the update (also the scratch of exp and the target of the composition) and exp(update)
  std::vector<float>      w(n * D, 0.0f), update(n * D), expUpdate(n * D);
  DisplacementFieldType * field = this->GetDisplacementField();
  this->ConfigureStages();
  if (this->GetInitialDisplacementField())
  {
    this->InitialGridField(this->GetInitialDisplacementField(), w);
    this->WriteGridFieldToImage(w, field); // the density filter reads W from the field image
  }
  // ComputeInverse: W^-1 in the grid frame, carried along as W^-1 <- exp(-s u) o W^-1
  std::vector<float> inverse;
  if (m_ComputeInverse)
  {
    inverse.assign(n * D, 0.0f);
    if (this->GetInitialDisplacementField())
    {
      this->InitialGridField(this->GetInitialInverseDisplacementField(), inverse);
    }
  }
  dmr::BarycentricMap<D> bary;
  std::vector<double>    nodalForce, nodalU, nodalW;

  if (m_MeshMode != MeshModeEnum::Dynamic)
  {
    this->BuildStaticMesh();
    auto t0 = Clock::now();
    t0 = Clock::now();
    bary.Build(grid, m_StaticSimplexMesh, threader); // throws when the static mesh does not cover the image
    m_Timing.barycentric += seconds(t0, Clock::now());
    this->SetSolverMesh(m_StaticSimplexMesh);
  }

  bool forceIsCurrent = false; // the density filter already holds the force at the current W (accepted step)
  for (unsigned int it = 1; it <= m_NumberOfIterations; ++it)
  {
    if (this->GetAbortGenerateData())
    {
      m_StopConditionDescription = "aborted (AbortGenerateData) before iteration " + std::to_string(it);
      break;
    }
    m_CurrentIteration = it;
    IterationRecord record{};
    record.iteration = it;

    // 1. force and density of T vs S o W
    auto t0 = Clock::now();
    if (!forceIsCurrent)
    {
      field->Modified();
      m_DensityFilter->Update();
    }
    forceIsCurrent = false;
    record.mssd = m_DensityFilter->GetMSSD() * dV;
    record.ssd = m_DensityFilter->GetSSD() * dV;
    const double forceSeconds = seconds(t0, Clock::now());
    m_Timing.force += forceSeconds;
    m_Timing.registration += forceSeconds;

    // 2. dynamic mesh
    if (m_MeshMode == MeshModeEnum::Dynamic)
    {
      m_CVTFilter->SetInput(m_DensityFilter->GetOutput());
      const bool reinitialize = m_ReinitializationInterval > 0 && it > 1 && (it - 1) % m_ReinitializationInterval == 0;
      // warm start (paper 4.7) unless a fresh contraction is due
      m_CVTFilter->SetInitialLabels(m_Labels && !reinitialize ? m_Labels.GetPointer() : nullptr);
      t0 = Clock::now();
      m_CVTFilter->Update();
      // the contraction is the initial tessellation; the rest of the update (the density and the warm start's labels
      // taken in, the swap sweeps, the output) is the tessellation optimisation, as on the CUDA path
      m_Timing.initialTessellation += m_CVTFilter->GetInitializationTime();
      m_Timing.tessellationOptimization +=
        std::max(0.0, seconds(t0, Clock::now()) - m_CVTFilter->GetInitializationTime());
      record.sweeps = m_CVTFilter->GetNumberOfSweeps();
      // take the labels out of the CVT pipeline (the next iteration's warm start)
      typename LabelImageType::Pointer labels = m_CVTFilter->GetOutput();
      labels->DisconnectPipeline();
      m_Labels = labels;

      // the dual mesh from the labels and the core's sites in the grid frame, as the CUDA path builds it: the sites
      // as physical points (DualMeshFilter's input) would come back from the round trip through origin, spacing and
      // direction rounded in the last bit, and the 3D tetrahedralization of near-degenerate node sets follows that bit
      t0 = Clock::now();
      const dmr::LabelSummary summary =
        dmr::SummarizeLabels<D>(grid, m_Labels->GetBufferPointer(), m_NumberOfNodes, threader);
      m_DynamicSimplexMesh = dmr::BuildDualMesh<D>(grid,
                                                   summary,
                                                   m_CVTFilter->GetCore().GetCentroids().data(),
                                                   dmr::DefaultSnapToBoxEdges,
                                                   nullptr,
                                                   threader,
                                                   &m_DelaunayWarmStart);
      m_CurrentMesh = &m_DynamicSimplexMesh;
      ++m_CurrentMeshVersion;
      m_Timing.meshConstruction += seconds(t0, Clock::now());

      t0 = Clock::now();
      bary.Build(grid, *m_CurrentMesh, threader);
      m_Timing.barycentric += seconds(t0, Clock::now());
      this->SetSolverMesh(*m_CurrentMesh);
    }
    record.nodes = m_CurrentMesh->NumberOfNodes();

    // 3-5. nodal forces, solve, beta, interpolate, exponential update
    t0 = Clock::now();
    bary.Gather(m_DensityFilter->GetGridForce().data(), dV, nodalForce, threader);
    m_Timing.gather += seconds(t0, Clock::now());
    if (!this->SolveAndSetBeta(nodalForce, nodalU, record.mssd, [&] {
          m_Solver->Solve(nodalForce, nodalU);
          record.solverIterations = m_Solver->GetLastIterations();
          record.directSolve = m_Solver->GetDirect();
        }))
    {
      // the images already match (no force), or a later dynamic mesh has no free node: nothing more to register
      this->AppendToHistory(record);
      m_Timing.registration += seconds(t0, Clock::now());
      break;
    }
    // R of the current transformation on this mesh: nodal values of w sampled at the nodes
    const SimplexMeshType & mesh = *m_CurrentMesh;
    nodalW.assign(mesh.NumberOfNodes() * D, 0.0);
    for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
    {
      double c[D];
      for (unsigned int k = 0; k < D; ++k)
      {
        c[k] = mesh.nodes[a * D + k] / grid.spacing[k];
      }
      dmr::InterpolateAdd<D, D>(grid, w.data(), c, 1.0, &nodalW[a * D]);
    }
    record.elastic = m_Solver->ElasticEnergy(nodalW);
    record.total = record.mssd + m_Beta * record.elastic;

    // W <- W o exp(s u), u = K^-1 f / beta at every pixel; the candidate is made in `update`
    forceIsCurrent = this->SafeguardedStep(
      record,
      this->PredictedDecrease(nodalForce, nodalU),
      [&](double scale) {
        const auto t1 = Clock::now();
        bary.Interpolate(nodalU, scale / m_Beta, update.data(), threader);
        dmr::FieldBounds bounds;
        dmr::ExponentialField<D>(grid, update.data(), expUpdate.data(), update, threader, &bounds);
        const double maxUpdate = bounds.displacement;
        dmr::ComposeFields<D>(grid, w.data(), expUpdate.data(), update.data(), threader);
        this->WriteGridFieldToImage(update, field);
        m_Timing.update += seconds(t1, Clock::now());
        return maxUpdate;
      },
      [&] {
        const auto t1 = Clock::now();
        field->Modified();
        m_DensityFilter->Update();
        m_Timing.force += seconds(t1, Clock::now());
        return m_DensityFilter->GetMSSD() * dV;
      },
      [] {}); // w still holds W
    if (record.stepScale > 0.0)
    {
      w.swap(update);
      if (m_ComputeInverse)
      {
        // W^-1 <- exp(-s u) o W^-1: the negated update has the same bounds, so the same number of squarings
        const auto t1 = Clock::now();
        bary.Interpolate(nodalU, -record.stepScale / m_Beta, update.data(), threader);
        dmr::ExponentialField<D>(grid, update.data(), expUpdate.data(), update, threader);
        dmr::ComposeFields<D>(grid, expUpdate.data(), inverse.data(), inverse.data(), threader);
        m_Timing.update += seconds(t1, Clock::now());
      }
    }
    else
    {
      this->WriteGridFieldToImage(w, field); // no step lowers the MSSD: keep W
    }
    m_Timing.registration += seconds(t0, Clock::now());

    this->AppendToHistory(record);
    this->InvokeEvent(IterationEvent());
    this->UpdateProgress(static_cast<float>(it) / static_cast<float>(m_NumberOfIterations));
  }

  // final similarity with the final field
  auto t0 = Clock::now();
  if (!forceIsCurrent)
  {
    field->Modified();
    m_DensityFilter->Update();
    m_Timing.force += seconds(t0, Clock::now());
  }
  if (m_StopConditionDescription.empty())
  {
    m_StopConditionDescription = "completed the " + std::to_string(m_NumberOfIterations) + " iterations";
  }
  const double energyToImageUnits = this->EnergyToImageUnits();
  m_FinalSSD = m_DensityFilter->GetSSD() * dV * energyToImageUnits;
  m_FinalMSSD = m_DensityFilter->GetMSSD() * dV * energyToImageUnits;
  m_Timing.registration += seconds(t0, Clock::now());
  // free the per-voxel working memory before the transform's double copy of the field is made (peak RSS)
  for (auto * v : { &w, &update, &expUpdate })
  {
    std::vector<float>().swap(*v);
  }
  if (m_ComputeInverse)
  {
    this->MakeInverseField(inverse);
    std::vector<float>().swap(inverse);
  }
  bary = dmr::BarycentricMap<D>();
  m_DensityFilter->ReleaseInternalBuffers();
  m_CVTFilter->GetOutput()->ReleaseData();
  m_Labels = nullptr;
  m_DelaunayWarmStart.clear();

  this->MakeTransformOutput();
  m_Timing.total = seconds(tStart, Clock::now());
  this->UpdateProgress(1.0f);
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::ConfigureDensityFilter(DensityFilterType & filter) const
{
  filter.SetFixedImage(this->GetFixedImage());
  filter.SetMovingImage(this->GetMovingImage());
  filter.SetFixedMask(this->GetFixedMask());
  filter.ComputeForceFieldOff(); // the registration reads the grid-frame force
  filter.SetNumberOfLevels(m_NumberOfLevels);
  filter.SetAlphaFactor(m_AlphaFactor);
  filter.SetForceGradient(m_ForceGradient);
  filter.SetNumberOfWorkUnits(this->GetNumberOfWorkUnits());
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::ConfigureStages()
{
  // the output field starts at 0; the CPU path's density filter reads it every iteration, the CUDA path keeps w on
  // the device and uses the density filter only for its pyramids and alpha rule
  const bool              cuda = m_BackendUsed == BackendEnum::CUDA;
  DisplacementFieldType * field = this->GetDisplacementField();
  field->SetBufferedRegion(field->GetLargestPossibleRegion());
  field->Allocate();
  {
    // FillBuffer on the work units (a CT's field is hundreds of MB, first touched here)
    auto *     buffer = field->GetBufferPointer();
    const auto zero = typename DisplacementFieldType::PixelType(0.0);
    dmr::ParallelForChunks(this->GetMultiThreader(),
                           field->GetBufferedRegion().GetNumberOfPixels(),
                           [buffer, &zero](size_t b, size_t e) { std::fill(buffer + b, buffer + e, zero); });
  }

  this->ConfigureDensityFilter(*m_DensityFilter);
  m_DensityFilter->SetDisplacementField(cuda ? nullptr : field);
  m_CVTFilter->SetNumberOfCells(m_NumberOfNodes);
  m_CVTFilter->SetEpsilon(m_CVTEpsilon);
  m_CVTFilter->SetMaximumNumberOfSweeps(m_MaximumNumberOfSweeps);
  m_CVTFilter->SetNumberOfWorkUnits(this->GetNumberOfWorkUnits());
  // the CUDA path uses the filter for the contraction only and sweeps on its own device optimiser
  m_CVTFilter->SetBackend(BackendEnum::CPU);
  m_CVTFilter->SetSwapOptimization(!cuda);
  m_Solver->SetLambda(m_Lambda);
  m_Solver->SetMu(m_Mu);
  m_Solver->SetTolerance(m_SolverTolerance);
  m_Solver->SetDirectSolverMaximumDegreesOfFreedom(m_DirectSolverMaximumDegreesOfFreedom);
  m_Solver->SetGPUOrderSolve(m_GPUOrderSolve);
  m_Solver->SetMultiThreader(this->GetMultiThreader());
  m_Labels = nullptr;
  m_DelaunayWarmStart.clear();
  m_InverseDisplacementField = nullptr;

  m_History.clear();
  m_Timing = Timing();
  m_StopConditionDescription.clear();
  m_Beta = 0.0;
  m_CurrentMesh = nullptr;
  ++m_CurrentMeshVersion;
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::AppendToHistory(IterationRecord record)
{
  const double toImageUnits = this->EnergyToImageUnits(); // the pyramids, built before any record, set the scale
  record.mssd *= toImageUnits;
  record.ssd *= toImageUnits;
  record.total *= toImageUnits;
  m_History.push_back(record);
}

template <typename TF, typename TM, typename TD>
template <typename TSolve>
bool
FEMRegistrationMethod<TF, TM, TD>::SolveAndSetBeta(const std::vector<double> & nodalForce,
                                                   std::vector<double> &       nodalU,
                                                   double                      mssd,
                                                   TSolve &&                   solve)
{
  // Border nodes are fixed, so a mesh without a free node cannot move anything. A static or regular mesh is refused
  // before the run; a dynamic mesh shows it only now: with few nodes every cell of the tessellation may touch the
  // border. At the first iteration nothing has been registered, so that is an error (not "the images match"); a later
  // mesh without a free node ends the run with the transformation reached so far, as no step is possible.
  const SimplexMeshType & mesh = *m_CurrentMesh;
  if (!mesh.HasFreeNode())
  {
    if (m_CurrentIteration <= 1)
    {
      // (the count of cells the user asked for: the mesh also has a node at each image corner that no cell holds)
      itkExceptionMacro("the dynamic mesh has no free node: all "
                        << m_NumberOfNodes
                        << " cells of the tessellation touch the border of the image, where the displacement is "
                           "fixed, so nothing can move; use more nodes");
    }
    std::ostringstream why;
    why << "the dynamic mesh of iteration " << m_CurrentIteration << " has no free node (all " << m_NumberOfNodes
        << " cells touch the border of the image, where the displacement is fixed): the transformation of "
           "iteration "
        << m_CurrentIteration - 1 << " is the result";
    m_StopConditionDescription = why.str();
    return false;
  }
  const auto t0 = std::chrono::steady_clock::now();
  solve();
  m_Timing.femSolve += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (m_Beta == 0.0)
  {
    const double fKf = NodalWork(nodalForce, nodalU);
    if (!(fKf > 0.0) || !(mssd > 0.0))
    {
      m_StopConditionDescription = "the images already match: there is no force to register with (the identity is "
                                   "the result)";
      return false;
    }
    // paper 5.1: beta R / D = EnergyRatio at iteration 1. The MSSD is a sum over the image whose last bits depend on
    // the order of summation (CPU chunks, GPU blocks); rounded to 24 bits, beta is the same on both back-ends (see
    // dmr::RoundToSingleSignificand)
    m_Beta = dmr::RoundToSingleSignificand(fKf / (2.0 * m_EnergyRatio * mssd));
  }
  return true;
}

template <typename TF, typename TM, typename TD>
double
FEMRegistrationMethod<TF, TM, TD>::NodalWork(const std::vector<double> & nodalForce, const std::vector<double> & nodalU)
{
  double fu = 0.0;
  for (size_t i = 0; i < nodalU.size(); ++i)
  {
    fu += nodalForce[i] * nodalU[i];
  }
  return fu;
}

template <typename TF, typename TM, typename TD>
double
FEMRegistrationMethod<TF, TM, TD>::PredictedDecrease(const std::vector<double> & nodalForce,
                                                     const std::vector<double> & nodalU) const
{
  const double fu = NodalWork(nodalForce, nodalU);
  return fu > 0.0 ? fu / m_Beta : 0.0;
}

template <typename TF, typename TM, typename TD>
template <typename TApply, typename TCandidateMSSD, typename TReject>
bool
FEMRegistrationMethod<TF, TM, TD>::SafeguardedStep(IterationRecord & record,
                                                   double            predictedDecrease,
                                                   TApply &&         apply,
                                                   TCandidateMSSD && candidateMSSD,
                                                   TReject &&        reject) const
{
  double scale = 1.0;
  for (unsigned int halving = 0;; ++halving, scale *= 0.5)
  {
    const double maxUpdate = apply(scale);
    // the force at an accepted candidate is the next iteration's force: only rejected steps cost an evaluation. A
    // step beyond single precision (an image with next to no contrast: 1e43 pixels) is not evaluated, its field is
    // not finite.
    if (m_MaximumStepHalvings == 0 ||
        (std::isfinite(maxUpdate) && candidateMSSD() <= record.mssd - SufficientDecrease * scale * predictedDecrease))
    {
      record.maxUpdate = maxUpdate;
      record.stepScale = scale;
      return m_MaximumStepHalvings > 0;
    }
    reject();
    if (halving == m_MaximumStepHalvings)
    {
      record.stepScale = 0.0; // no step lowers the MSSD: keep W
      return false;
    }
  }
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::SetSolverMesh(const SimplexMeshType & mesh)
{
  const auto t0 = std::chrono::steady_clock::now();
  m_Solver->SetMesh(mesh);
  const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  m_Timing.femSolve += elapsed;
  m_Timing.registration += elapsed;
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::BuildStaticMesh()
{
  constexpr unsigned int D = ImageDimension;
  const auto             t0 = std::chrono::steady_clock::now();
  const auto             grid = dmr::Grid<D>::FromImage(this->GetFixedImage());
  if (m_MeshMode == MeshModeEnum::Regular)
  {
    m_StaticSimplexMesh = dmr::MakeRegularMesh<D>(grid, this->RegularNodesPerAxis()); // checked: a node is free
  }
  else
  {
    m_StaticSimplexMesh = dmr::FromItkMesh<D>(this->GetStaticMesh(), this->GetFixedImage());
    this->CheckStaticMeshHasAFreeNode(m_StaticSimplexMesh);
  }
  m_CurrentMesh = &m_StaticSimplexMesh;
  m_Timing.meshConstruction += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::CheckStaticMeshHasAFreeNode(const SimplexMeshType & mesh) const
{
  if (!mesh.HasFreeNode())
  {
    itkExceptionMacro("the static mesh has no free node: all its "
                      << mesh.NumberOfNodes()
                      << " nodes lie on the border of the image, where the displacement is fixed, so nothing can move");
  }
}

template <typename TF, typename TM, typename TD>
auto
FEMRegistrationMethod<TF, TM, TD>::RegularNodesPerAxis() const -> std::array<size_t, ImageDimension>
{
  const auto   size = this->GetFixedImage()->GetLargestPossibleRegion().GetSize();
  unsigned int perAxis = m_RegularGridSize;
  if (perAxis == 0)
  {
    perAxis =
      static_cast<unsigned int>(std::lround(std::pow(static_cast<double>(m_NumberOfNodes), 1.0 / ImageDimension)));
  }
  std::array<size_t, ImageDimension> nodes;
  for (unsigned int k = 0; k < ImageDimension; ++k)
  {
    nodes[k] = std::max<size_t>(2, std::min<size_t>(perAxis, size[k]));
  }
  return nodes;
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::MakeTransformOutput()
{
  // transform output (double field, as ResampleImageFilter expects)
  constexpr unsigned int        D = ImageDimension;
  const DisplacementFieldType * field = this->GetDisplacementField();
  using TransformFieldType = typename TransformType::DisplacementFieldType;
  auto transformField = TransformFieldType::New();
  transformField->CopyInformation(field);
  transformField->SetRegions(field->GetLargestPossibleRegion());
  transformField->Allocate();
  const auto * src = field->GetBufferPointer();
  auto *       dst = transformField->GetBufferPointer();
  const size_t n = field->GetLargestPossibleRegion().GetNumberOfPixels();
  dmr::ParallelForChunks(this->GetMultiThreader(), n, [&](size_t b, size_t e) {
    for (size_t p = b; p < e; ++p)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        dst[p][k] = src[p][k];
      }
    }
  });
  auto transform = TransformType::New();
  transform->SetDisplacementField(transformField);
  if (m_InverseDisplacementField)
  {
    auto         inverseField = TransformFieldType::New();
    const auto * isrc = m_InverseDisplacementField->GetBufferPointer();
    inverseField->CopyInformation(field);
    inverseField->SetRegions(field->GetLargestPossibleRegion());
    inverseField->Allocate();
    auto * idst = inverseField->GetBufferPointer();
    dmr::ParallelForChunks(this->GetMultiThreader(), n, [&](size_t b, size_t e) {
      for (size_t p = b; p < e; ++p)
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          idst[p][k] = isrc[p][k];
        }
      }
    });
    transform->SetInverseDisplacementField(inverseField);
  }
  this->GetTransformOutput()->Set(transform);
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::MakeInverseField(const std::vector<float> & inverse)
{
  m_InverseDisplacementField = DisplacementFieldType::New();
  m_InverseDisplacementField->CopyInformation(this->GetFixedImage());
  m_InverseDisplacementField->SetRegions(this->GetFixedImage()->GetLargestPossibleRegion());
  m_InverseDisplacementField->Allocate();
  this->WriteGridFieldToImage(inverse, m_InverseDisplacementField);
}

namespace dmr
{
/** Throws an itk::ExceptionObject for a failed CUDA launcher. */
inline void
ThrowOnError(const cuda::Status & status, const char * stage)
{
  if (!status.Ok())
  {
    itkGenericExceptionMacro("CUDA back-end, " << stage << ": " << status.message);
  }
}

/** The device's view of the pyramid (DensityFieldFilter::PyramidLevel, complete or not): sizes, maps, MSSD weights,
 * the moving-level index per mm of the physical displacement (MB) and the fixed direction: the device evaluates the
 * force at u = float(Direction w), the floats of the CPU path's field image, with the CPU's formulas, so both back-ends
 * compute the same force for the same w, bit for bit. */
template <unsigned int D, typename TLevel, typename TDirection>
std::vector<cuda::PyramidLevelView>
PyramidLevelViews(const std::vector<TLevel> & pyramid, const TDirection & fixedDirection, size_t numberOfPixels)
{
  std::vector<cuda::PyramidLevelView> views(pyramid.size());
  for (size_t l = 0; l < pyramid.size(); ++l)
  {
    const TLevel &           L = pyramid[l];
    cuda::PyramidLevelView & v = views[l];
    for (unsigned int r = 0; r < D; ++r)
    {
      v.fixedSize[r] = L.fixedGrid.size[r];
      v.movingSize[r] = L.movingGrid.size[r];
      v.Fc[r] = L.Fc[r];
      v.Mc[r] = L.Mc[r];
      for (unsigned int k = 0; k < D; ++k)
      {
        v.FA[r][k] = L.FA[r][k];
        v.MA[r][k] = L.MA[r][k];
        v.MB[r][k] = L.MB[r][k];
        v.direction[r][k] = fixedDirection[r][k];
      }
    }
    // an incomplete pyramid (DensityFieldFilter::GetPyramid(false)): the device builds what is not here from the plans
    v.fixed = L.fixed.empty() ? L.fixedInput : L.fixed.data();
    v.moving = L.moving.empty() ? L.movingInput : L.moving.data();
    v.movingGradient = L.movingGradient.empty() ? nullptr : L.movingGradient.data();
    auto shrinkView = [](const auto & plan, cuda::ShrinkView & view) {
      for (unsigned int k = 0; k < D && !plan.kept[k].empty(); ++k)
      {
        view.kept[k] = plan.kept[k].data();
        view.coefficients[k] = plan.coefficients[k].data();
        view.width[k] = plan.coefficients[k].size();
      }
    };
    shrinkView(L.fixedPlan, v.fixedShrink);
    shrinkView(L.movingPlan, v.movingShrink);
    for (unsigned int r = 0; r < D; ++r)
    {
      v.movingSpacing[r] = L.movingGrid.spacing[r];
      for (unsigned int k = 0; k < D; ++k)
      {
        v.R[r][k] = L.R[r][k];
      }
    }
    v.weight = static_cast<double>(L.fixedGrid.numberOfPixels) / static_cast<double>(numberOfPixels);
  }
  return views;
}
} // namespace dmr

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::UploadMesh(dmr::cuda::RegistrationContext & context, const SimplexMeshType & mesh)
{
  static_assert(sizeof(mesh.elements.front()) == (ImageDimension + 1) * sizeof(int32_t),
                "the elements are contiguous node ids");
  dmr::ThrowOnError(context.SetMesh(mesh.nodes.data(),
                                    mesh.NumberOfNodes(),
                                    mesh.elements.empty() ? nullptr : mesh.elements.front().data(),
                                    mesh.elements.size()),
                    "barycentric rasterisation");
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::InitialGridField(const DisplacementFieldType * initial, std::vector<float> & w) const
{
  // w = Direction^T u_0: the grid frame of the fixed image (the inverse of WriteGridFieldToImage's rotation)
  const auto & dir = this->GetFixedImage()->GetDirection();
  const auto * u0 = initial->GetBufferPointer();
  const size_t n = initial->GetBufferedRegion().GetNumberOfPixels();
  w.resize(n * ImageDimension);
  dmr::ParallelForChunks(this->GetMultiThreader(), n, [&](size_t b, size_t e) {
    for (size_t p = b; p < e; ++p)
    {
      for (unsigned int k = 0; k < ImageDimension; ++k)
      {
        double v = 0.0;
        for (unsigned int r = 0; r < ImageDimension; ++r)
        {
          v += dir[r][k] * static_cast<double>(u0[p][r]);
        }
        w[p * ImageDimension + k] = static_cast<float>(v);
      }
    }
  });
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::GenerateDataCUDA(std::chrono::steady_clock::time_point tStart,
                                                    std::future<dmr::cuda::Status> &      deviceContext)
{
  constexpr unsigned int D = ImageDimension;
  using Clock = std::chrono::steady_clock;
  auto seconds = [](Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double>(b - a).count(); };

  const FixedImageType * fixed = this->GetFixedImage();
  MultiThreaderBase *    threader = this->GetMultiThreader();
  const auto             grid = dmr::Grid<D>::FromImage(fixed);
  const size_t           n = grid.numberOfPixels;
  const double           dV = grid.PixelVolume();

  DisplacementFieldType * field = this->GetDisplacementField();
  this->ConfigureStages();

  // the pyramids: level 0's images uploaded (float inputs from their own buffers, others converted to float on the
  // CPU), the coarser levels and the moving gradients built on the device from the density filter's plans (the same
  // floats as the CPU path's pyramids), while the device's context is still being created (GenerateData)
  auto       t0 = Clock::now();
  const auto views = dmr::PyramidLevelViews<D>(m_DensityFilter->GetPyramid(false), fixed->GetDirection(), n);
  // the mask as it is (on the fixed grid, VerifyInputInformation): the device reads it as the CPU path does, non-zero
  // inside
  static_assert(sizeof(typename MaskImageType::PixelType) == sizeof(uint8_t), "the device reads one byte per pixel");
  const auto * maskImage = this->GetFixedMask();
  if (maskImage && maskImage->GetBufferedRegion() != maskImage->GetLargestPossibleRegion())
  {
    itkExceptionMacro("the fixed mask is not buffered whole");
  }
  const auto * mask = maskImage ? reinterpret_cast<const uint8_t *>(maskImage->GetBufferPointer()) : nullptr;
  // the merges of a contraction report progress and stop on AbortGenerateData, as the CPU path's CVT filter does
  auto contractionCheckpoint = [this](double) {
    this->UpdateProgress(this->GetProgress());
    if (this->GetAbortGenerateData())
    {
      ProcessAborted aborted(__FILE__, __LINE__);
      aborted.SetDescription("FEMRegistrationMethod: AbortGenerateData was set (contraction)");
      throw aborted;
    }
  };
  // Iteration 1's contraction on the CPU while the device's context is still being created (AlwaysContractOnHost):
  // the CPU path's density at the identity, from a density filter of its own (this one's incomplete pyramids are the
  // device's), its block sums and their merges. Iteration 1 takes these merges only if the device's block sums are
  // the same, bit for bit.
  struct
  {
    std::vector<double>  mass, centroid;
    std::vector<int32_t> blockLabel;
  } host;
  if (m_MeshMode == MeshModeEnum::Dynamic && !this->GetInitialDisplacementField() &&
      n <= HostContractionMaximumPixels &&
      this->GetMovingImage()->GetLargestPossibleRegion().GetNumberOfPixels() <= HostContractionMaximumPixels &&
      (m_AlwaysContractOnHost ||
       (deviceContext.valid() && deviceContext.wait_for(std::chrono::seconds(0)) != std::future_status::ready)))
  {
    const auto t1 = Clock::now();
    auto       density = DensityFilterType::New();
    this->ConfigureDensityFilter(*density); // as the registration's own, at the identity (no displacement field)
    density->Update();
    dmr::DiscreteCVT<D> core;
    core.SetDensity(grid, density->GetOutput()->GetBufferPointer(), threader);
    const auto blocks =
      core.ContractionBlockSums(m_NumberOfNodes, m_CVTFilter->GetBlockSize(), host.mass, host.centroid);
    size_t numberOfLabels = 0;
    host.blockLabel = dmr::DiscreteCVT<D>::ContractBlocks(
      blocks.perAxis, host.mass.data(), host.centroid.data(), m_NumberOfNodes, contractionCheckpoint, numberOfLabels);
    m_Timing.initialTessellation += seconds(t1, Clock::now());
  }
  if (deviceContext.valid())
  {
    deviceContext.wait();
  }
  dmr::cuda::RegistrationContext context;
  dmr::ThrowOnError(context.Initialize(D, grid.size.data(), grid.spacing.data(), views, mask), "initialisation");
  if (this->GetInitialDisplacementField())
  {
    std::vector<float> w0(n * D);
    this->InitialGridField(this->GetInitialDisplacementField(), w0);
    dmr::ThrowOnError(context.UploadField(w0.data()), "initial field upload");
  }
  if (m_ComputeInverse)
  {
    std::vector<float> v0;
    if (this->GetInitialDisplacementField())
    {
      this->InitialGridField(this->GetInitialInverseDisplacementField(), v0);
    }
    dmr::ThrowOnError(context.EnableInverse(v0.empty() ? nullptr : v0.data()), "inverse field");
  }
  m_Timing.registration += seconds(t0, Clock::now());

  std::vector<double>         nodalForce, nodalU, nodalW;
  dmr::cuda::CVTSwapOptimizer cvt;
  dmr::cuda::LabelSummarizer  summarizer;
  dmr::LabelSummary           summary;
  summarizer.SetFindAdjacentPairs(D == 2); // the 3D dual mesh does not read them (no statistics asked for below)

  // the elastic system of a mesh: on the device when it is large enough (no assembly on the CPU), otherwise
  // assembled on the CPU; hostAssembled says whether m_Solver holds the current mesh's K
  bool   deviceSolve = false, hostAssembled = false;
  size_t freeDegrees = 0;
  auto   prepareSolve = [&](const SimplexMeshType & mesh) {
    freeDegrees = 0;
    for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
    {
      freeDegrees += (mesh.fixed.empty() || !mesh.fixed[a]) ? D : 0;
    }
    deviceSolve = freeDegrees >= m_DeviceSolverMinimumDegreesOfFreedom;
    hostAssembled = !deviceSolve;
    if (deviceSolve)
    {
      const auto t1 = Clock::now();
      dmr::ThrowOnError(context.SetElasticity(m_Lambda, m_Mu, mesh.fixed.empty() ? nullptr : mesh.fixed.data()),
                        "elastic system");
      const double elapsed = seconds(t1, Clock::now());
      m_Timing.femSolve += elapsed;
      m_Timing.registration += elapsed;
    }
    else
    {
      this->SetSolverMesh(mesh);
    }
  };

  if (m_MeshMode != MeshModeEnum::Dynamic)
  {
    this->BuildStaticMesh();
    t0 = Clock::now();
    this->UploadMesh(context, m_StaticSimplexMesh);
    m_Timing.barycentric += seconds(t0, Clock::now());
    prepareSolve(m_StaticSimplexMesh);
  }

  const bool                 warpedGradient = m_ForceGradient == ForceGradientEnum::WarpedMoving;
  bool                       forceIsCurrent = false;
  dmr::cuda::ForceStatistics statistics;
  for (unsigned int it = 1; it <= m_NumberOfIterations; ++it)
  {
    if (this->GetAbortGenerateData())
    {
      m_StopConditionDescription = "aborted (AbortGenerateData) before iteration " + std::to_string(it);
      break;
    }
    m_CurrentIteration = it;
    IterationRecord record{};
    record.iteration = it;

    // 1. force and density of T vs S o W, on the device (already there after an accepted, checked step)
    t0 = Clock::now();
    if (!forceIsCurrent)
    {
      dmr::ThrowOnError(context.ComputeForce(statistics, warpedGradient), "force");
    }
    forceIsCurrent = false;
    if (statistics.inside == 0)
    {
      itkExceptionMacro("the fixed mask is empty: no pixel to register");
    }
    record.mssd = statistics.mssd * dV;
    record.ssd = statistics.ssd * dV;
    const double alpha =
      m_DensityFilter->ComputeAlpha(statistics.sumSquaredForce / static_cast<double>(statistics.inside));
    dmr::ThrowOnError(context.AddToDensity(alpha), "density");
    const double forceSeconds = seconds(t0, Clock::now());
    m_Timing.force += forceSeconds;
    m_Timing.registration += forceSeconds;

    // 2. dynamic mesh: the swap optimisation reads the device density and keeps the labels on the device; the dual
    // mesh is built on the CPU from their small summary (counts, sums, adjacency)
    if (m_MeshMode == MeshModeEnum::Dynamic)
    {
      const bool reinitialize = m_ReinitializationInterval > 0 && it > 1 && (it - 1) % m_ReinitializationInterval == 0;
      t0 = Clock::now();
      if (it == 1 || reinitialize)
      {
        // initial tessellation (contraction, paper 4.4): the block sums and the labels on the device, the greedy
        // merges of the blocks on the CPU (dmr::DiscreteCVT::ContractBlocks, the CPU path's merges, so both back-ends
        // start from the same labels); the swaps then run on this run's device optimiser from the contraction's
        // labels, as the CPU path's sweeps run from the contraction's state. Only the block sums and labels cross.
        dmr::ThrowOnError(cvt.SetGrid(D, grid.size.data(), grid.spacing.data()), "CVT grid");
        dmr::ThrowOnError(cvt.SetDensity(context.DeviceDensity(), true), "CVT density");
        const auto blocks =
          dmr::DiscreteCVT<D>::ContractionBlocks(grid.size, m_NumberOfNodes, m_CVTFilter->GetBlockSize());
        std::vector<double> blockMass, blockCentroid;
        dmr::ThrowOnError(cvt.ContractionBlockSums(blocks.size, blockMass, blockCentroid), "contraction");
        std::vector<int32_t> blockLabel;
        if (it == 1 && !host.blockLabel.empty() && blockMass == host.mass && blockCentroid == host.centroid)
        {
          blockLabel.swap(host.blockLabel); // the merges of these very sums, made while the device started
          m_ContractedOnHost = true;
        }
        else
        {
          size_t numberOfLabels = 0;
          blockLabel = dmr::DiscreteCVT<D>::ContractBlocks(blocks.perAxis,
                                                           blockMass.data(),
                                                           blockCentroid.data(),
                                                           m_NumberOfNodes,
                                                           contractionCheckpoint,
                                                           numberOfLabels);
        }
        host = {};
        dmr::ThrowOnError(cvt.SetBlockLabels(blocks.size, blockLabel.data(), m_NumberOfNodes), "CVT labels");
        m_Timing.initialTessellation += seconds(t0, Clock::now());
      }
      else
      {
        dmr::ThrowOnError(cvt.SetDensity(context.DeviceDensity(), true), "CVT density");
        dmr::ThrowOnError(cvt.KeepLabels(m_NumberOfNodes), "CVT warm start");
        m_Timing.tessellationOptimization += seconds(t0, Clock::now());
      }
      t0 = Clock::now();
      dmr::cuda::CVTSwapResult result;
      dmr::ThrowOnError(cvt.Optimize(m_CVTEpsilon, m_MaximumNumberOfSweeps, result), "CVT optimisation");
      record.sweeps = result.sweeps;
      m_Timing.tessellationOptimization += seconds(t0, Clock::now());

      t0 = Clock::now();
      std::vector<double> masses, centroids;
      dmr::ThrowOnError(cvt.GetCells(masses, centroids), "CVT sites");
      dmr::ThrowOnError(summarizer.Summarize(D, grid.size.data(), cvt.DeviceLabels(), m_NumberOfNodes, summary),
                        "label summary");
      m_DynamicSimplexMesh = dmr::BuildDualMesh<D>(
        grid, summary, centroids.data(), dmr::DefaultSnapToBoxEdges, nullptr, threader, &m_DelaunayWarmStart);
      m_CurrentMesh = &m_DynamicSimplexMesh;
      ++m_CurrentMeshVersion;
      m_Timing.meshConstruction += seconds(t0, Clock::now());

      t0 = Clock::now();
      this->UploadMesh(context, *m_CurrentMesh);
      m_Timing.barycentric += seconds(t0, Clock::now());
      prepareSolve(*m_CurrentMesh);
    }
    record.nodes = m_CurrentMesh->NumberOfNodes();

    // 3-5. nodal forces (device), solve (device, or host for a small system), beta, interpolation and update (device)
    t0 = Clock::now();
    const SimplexMeshType & mesh = *m_CurrentMesh;
    nodalForce.resize(mesh.NumberOfNodes() * D);
    dmr::ThrowOnError(context.GatherForce(dV, nodalForce.data()), "force gathering");
    m_Timing.gather += seconds(t0, Clock::now());
    const bool solved = this->SolveAndSetBeta(nodalForce, nodalU, record.mssd, [&] {
      if (deviceSolve)
      {
        bool converged = false;
        nodalU.resize(nodalForce.size());
        dmr::ThrowOnError(context.SolveElasticity(nodalForce.data(),
                                                  nodalU.data(),
                                                  m_Solver->GetTolerance(),
                                                  m_DeviceSolverMaximumIterations > 0
                                                    ? static_cast<size_t>(m_DeviceSolverMaximumIterations)
                                                    : std::max<size_t>(1000, 4 * freeDegrees),
                                                  record.solverIterations,
                                                  converged),
                          "elastic solve");
        record.deviceSolve = converged;
        if (converged)
        {
          return;
        }
        // not converged (a very ill-conditioned mesh): the CPU solver, whose last resort is a factorisation, for
        // this mesh's remaining solves too (a static mesh keeps it)
        if (!hostAssembled)
        {
          m_Solver->SetMesh(mesh);
          hostAssembled = true;
        }
        deviceSolve = false;
      }
      m_Solver->Solve(nodalForce, nodalU);
      record.solverIterations = m_Solver->GetLastIterations();
      record.directSolve = m_Solver->GetDirect();
    });
    if (!solved)
    {
      // the images already match (no force), or a later dynamic mesh has no free node: nothing more to register
      this->AppendToHistory(record);
      m_Timing.registration += seconds(t0, Clock::now());
      break;
    }
    nodalW.resize(mesh.NumberOfNodes() * D);
    dmr::ThrowOnError(context.SampleFieldAtNodes(nodalW.data()), "nodal sampling");
    if (hostAssembled)
    {
      record.elastic = m_Solver->ElasticEnergy(nodalW);
    }
    else
    {
      dmr::ThrowOnError(context.ElasticEnergy(nodalW.data(), record.elastic), "elastic energy");
    }
    record.total = record.mssd + m_Beta * record.elastic;
    // W <- W o exp(s u) on the device; a rejected candidate is reverted
    forceIsCurrent = this->SafeguardedStep(
      record,
      this->PredictedDecrease(nodalForce, nodalU),
      [&](double scale) {
        const auto   t1 = Clock::now();
        unsigned int squarings = 0;
        double       maxUpdate = 0.0;
        dmr::ThrowOnError(context.ApplyUpdate(nodalU.data(), scale / m_Beta, maxUpdate, squarings), "update");
        m_Timing.update += seconds(t1, Clock::now());
        return maxUpdate;
      },
      [&] {
        const auto t1 = Clock::now();
        dmr::ThrowOnError(context.ComputeForce(statistics, warpedGradient), "force");
        m_Timing.force += seconds(t1, Clock::now());
        return statistics.mssd * dV;
      },
      [&] {
        const auto t1 = Clock::now();
        dmr::ThrowOnError(context.RevertUpdate(), "update");
        m_Timing.update += seconds(t1, Clock::now());
      });
    if (m_ComputeInverse && record.stepScale > 0.0)
    {
      // W^-1 <- exp(-s u) o W^-1 (as on the CPU)
      const auto t1 = Clock::now();
      dmr::ThrowOnError(context.ApplyInverseUpdate(nodalU.data(), -record.stepScale / m_Beta), "inverse update");
      m_Timing.update += seconds(t1, Clock::now());
    }
    m_Timing.registration += seconds(t0, Clock::now());

    this->AppendToHistory(record);
    this->InvokeEvent(IterationEvent());
    this->UpdateProgress(static_cast<float>(it) / static_cast<float>(m_NumberOfIterations));
  }

  // final similarity, and the field back to the host (the only full-volume download of the run)
  t0 = Clock::now();
  if (!forceIsCurrent)
  {
    dmr::ThrowOnError(context.ComputeForce(statistics, warpedGradient), "final force");
    m_Timing.force += seconds(t0, Clock::now());
  }
  if (m_StopConditionDescription.empty())
  {
    m_StopConditionDescription = "completed the " + std::to_string(m_NumberOfIterations) + " iterations";
  }
  const double energyToImageUnits = this->EnergyToImageUnits();
  m_FinalSSD = statistics.ssd * dV * energyToImageUnits;
  m_FinalMSSD = statistics.mssd * dV * energyToImageUnits;
  using FieldValueType = typename DisplacementFieldType::PixelType::ValueType;
  if constexpr (std::is_same_v<FieldValueType, float> &&
                sizeof(typename DisplacementFieldType::PixelType) == D * sizeof(float))
  {
    // rotated into the physical frame on the device and downloaded straight into the output (the same floats as
    // WriteGridFieldToImage)
    const auto & direction = fixed->GetDirection();
    double       M[D * D];
    for (unsigned int r = 0; r < D; ++r)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        M[r * D + k] = direction[r][k];
      }
    }
    dmr::ThrowOnError(context.DownloadPhysicalField(M, reinterpret_cast<float *>(field->GetBufferPointer())),
                      "field download");
  }
  else
  {
    std::vector<float> w(n * D);
    dmr::ThrowOnError(context.DownloadField(w.data()), "field download");
    this->WriteGridFieldToImage(w, field);
  }
  if (m_ComputeInverse)
  {
    std::vector<float> v(n * D);
    dmr::ThrowOnError(context.DownloadInverse(v.data()), "inverse field download");
    this->MakeInverseField(v);
  }
  // everything the back-end allocated: the registration context at its peak, and the CVT optimiser's and the label
  // summary's buffers, which it holds throughout the iterations
  m_DeviceBytes = context.AllocatedBytes() + cvt.AllocatedBytes() + summarizer.AllocatedBytes();
  // every buffer at once at the peak, the transient ones included, and the whole device's use at that moment
  const auto memory = dmr::cuda::GetMemoryStatistics();
  m_DevicePeakBytes = memory.peakAllocatedBytes;
  m_DeviceUsedAtPeakBytes = memory.deviceUsedAtPeakBytes;
  m_Timing.registration += seconds(t0, Clock::now());
  m_DensityFilter->ReleaseInternalBuffers();
  m_CVTFilter->GetOutput()->ReleaseData();
  m_Labels = nullptr;
  m_DelaunayWarmStart.clear();
  this->MakeTransformOutput();
  m_Timing.total = seconds(tStart, Clock::now());
  this->UpdateProgress(1.0f);
}

template <typename TF, typename TM, typename TD>
void
FEMRegistrationMethod<TF, TM, TD>::PrintSelf(std::ostream & os, Indent indent) const
{
  Superclass::PrintSelf(os, indent);
  os << indent << "NumberOfIterations: " << m_NumberOfIterations << std::endl;
  os << indent << "NumberOfNodes: " << m_NumberOfNodes << std::endl;
  os << indent << "NumberOfLevels: " << m_NumberOfLevels << std::endl;
  os << indent << "Lambda: " << m_Lambda << std::endl;
  os << indent << "Mu: " << m_Mu << std::endl;
  os << indent << "EnergyRatio: " << m_EnergyRatio << std::endl;
  os << indent << "AlphaFactor: " << m_AlphaFactor << std::endl;
  os << indent << "ForceGradient: " << m_ForceGradient << std::endl;
  os << indent << "MaximumStepHalvings: " << m_MaximumStepHalvings << std::endl;
  os << indent << "SolverTolerance: " << m_SolverTolerance << std::endl;
  os << indent << "CVTEpsilon: " << m_CVTEpsilon << std::endl;
  os << indent << "MaximumNumberOfSweeps: " << m_MaximumNumberOfSweeps << std::endl;
  os << indent << "ReinitializationInterval: " << m_ReinitializationInterval << std::endl;
  os << indent << "MeshMode: " << m_MeshMode << std::endl;
  os << indent << "RegularGridSize: " << m_RegularGridSize << std::endl;
  os << indent << "Backend: " << m_Backend << std::endl;
  os << indent << "BackendUsed: " << m_BackendUsed << std::endl;
  os << indent << "DeviceBytes: " << m_DeviceBytes << std::endl;
  os << indent << "DevicePeakBytes: " << m_DevicePeakBytes << std::endl;
  os << indent << "DeviceUsedAtPeakBytes: " << m_DeviceUsedAtPeakBytes << std::endl;
  os << indent << "DirectSolverMaximumDegreesOfFreedom: " << m_DirectSolverMaximumDegreesOfFreedom << std::endl;
  os << indent << "GPUOrderSolve: " << (m_GPUOrderSolve ? "true" : "false") << std::endl;
  os << indent << "AlwaysContractOnHost: " << (m_AlwaysContractOnHost ? "true" : "false") << std::endl;
  os << indent << "ContractedOnHost: " << (m_ContractedOnHost ? "true" : "false") << std::endl;
  os << indent << "DeviceSolverMinimumDegreesOfFreedom: " << m_DeviceSolverMinimumDegreesOfFreedom << std::endl;
  os << indent << "DeviceSolverMaximumIterations: " << m_DeviceSolverMaximumIterations << std::endl;
  os << indent << "ComputeInverse: " << m_ComputeInverse << std::endl;
  os << indent << "InverseDisplacementField: " << (m_InverseDisplacementField ? "computed" : "none") << std::endl;
  os << indent << "Beta: " << this->GetBeta() << std::endl;
  os << indent << "CurrentIteration: " << m_CurrentIteration << std::endl;
  os << indent << "FinalSSD: " << m_FinalSSD << std::endl;
  os << indent << "FinalMSSD: " << m_FinalMSSD << std::endl;
  os << indent << "History: " << m_History.size() << " iterations" << std::endl;
  os << indent << "StopConditionDescription: " << m_StopConditionDescription << std::endl;
  itkPrintSelfObjectMacro(DensityFilter);
  itkPrintSelfObjectMacro(CVTFilter);
  itkPrintSelfObjectMacro(Solver);
}
} // namespace itk

#endif
