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
#ifndef itkFEMRegistrationMethod_h
#define itkFEMRegistrationMethod_h

#include "itkProcessObject.h"
#include "itkDataObjectDecorator.h"
#include "itkDisplacementFieldTransform.h"
#include "itkDynamicMeshRegistrationEnums.h"
#include "itkDensityFieldFilter.h"
#include "itkDiscreteCVTFilter.h"
#include "itkDualMeshFilter.h"
#include "itkLinearElasticFEMSolver.h"
#include "dmrBarycentricMap.h"
#include "dmrFieldOps.h"
#include "dmrRegistrationBackend.h"
#include <chrono>
#include <future>
#include <string>

namespace itk
{
/** \class FEMRegistrationMethod
 * \brief FEM-based deformable registration on a dynamic mesh (Cai, Guo, Zhong, Mao 2015).
 *
 * Finds W(x) = x + u(x) so that the moving (source) image S o W matches the fixed (target) image T, minimising
 * MSSD(T, S o W) + beta R(W) (paper Eq. 1, 3) with R the linear-elastic energy. Each iteration k (paper 3, 4.7):
 *  1. DensityFieldFilter: force f (Eq. 5) of T vs S o W over the pyramid and density d = |f|^2 + alpha (Eq. 9);
 *  2. mesh: Dynamic mode rebuilds it from d: DiscreteCVTFilter (contraction at k = 1, then warm-started swaps) and
 *     DualMeshFilter's construction (dmr::BuildDualMesh, fed the CVT's sites in the grid frame; the CUDA path sweeps
 *     on the device from the same contraction and builds the same mesh); Regular and Static modes keep one mesh;
 *  3. barycentric coordinates of every pixel; nodal forces f_a = sum_x phi_a(x) f(x) dV;
 *  4. LinearElasticFEMSolver: K u = f / beta with the boundary nodes fixed (Eq. 7); beta is set at k = 1 so that
 *     beta R / D = EnergyRatio (paper 5.1: 0.02). With u = K^-1 f / beta, R = f^T K^-1 f / (2 beta^2), hence
 *     beta = f^T K^-1 f / (2 EnergyRatio D);
 *  5. the nodal update is interpolated to the pixels and applied by the diffeomorphic rule W <- W o exp(u) (Eq. 8),
 *     exp by scaling and squaring. The step is safeguarded: when W o exp(s u) does not lower the MSSD by at least
 *     1e-4 of the first-order prediction s f.u (the nodal forces times the nodal update; Armijo's sufficient decrease),
 *     s is halved (at most MaximumStepHalvings times; if no step lowers the MSSD so, W is kept), so the MSSD never
 *     increases. The paper's fixed beta gives a fixed step length per unit force, which overshoots and oscillates
 *     once the force of a strongly deformed region grows (circle to leaf); and as u = K^-1 f D / (f K^-1 f) grows
 *     like D / |f|, a moving image with next to no contrast where the images differ gets steps of 1e16 pixels that
 *     leave the MSSD as it was (not lower), which the plain "not larger" test took. The MSSD of an accepted step is
 *     the next iteration's force evaluation, so only rejected steps cost extra. MaximumStepHalvings = 0 is the
 *     paper's plain iteration.
 * The force uses the gradient of the warped moving image by default (ForceGradient, see DensityFieldFilter).
 * Inputs: FixedImage, MovingImage (any grid: sampled through physical space; neither region needs to start at index
 * 0), optional FixedMask (region of interest on the fixed grid: the fixed image's region, origin, spacing and
 * direction), optional StaticMesh (physical itk::Mesh of triangles for MeshMode Static). Output 0: the transform
 * (DisplacementFieldTransform, decorated), output 1: its displacement field on the fixed grid in mm (ITK convention:
 * moving point = fixed point + u).
 * Fires IterationEvent after every iteration (GetCurrentIteration, GetCurrentMesh, GetHistory are valid then) and
 * ProgressEvent; honours AbortGenerateData between iterations.
 *
 * \par References
 * Y. Cai, X. Guo, Z. Zhong, W. Mao, "Dynamic meshing for deformable image registration", Computer-Aided Design 58
 * (2015) 141-150, doi:10.1016/j.cad.2014.08.009.
 * \ingroup DynamicMeshRegistration */
template <typename TFixedImage,
          typename TMovingImage = TFixedImage,
          typename TDisplacementField = Image<Vector<float, TFixedImage::ImageDimension>, TFixedImage::ImageDimension>>
class ITK_TEMPLATE_EXPORT FEMRegistrationMethod : public ProcessObject
{
public:
  ITK_DISALLOW_COPY_AND_MOVE(FEMRegistrationMethod);
  using Self = FEMRegistrationMethod;
  using Superclass = ProcessObject;
  using Pointer = SmartPointer<Self>;
  using ConstPointer = SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(FEMRegistrationMethod, ProcessObject);

  static constexpr unsigned int ImageDimension = TFixedImage::ImageDimension;
  using FixedImageType = TFixedImage;
  using MovingImageType = TMovingImage;
  using DisplacementFieldType = TDisplacementField;
  using DensityImageType = Image<float, ImageDimension>;
  using LabelImageType = Image<int32_t, ImageDimension>;
  using MeshType =
    Mesh<double, ImageDimension, DefaultStaticMeshTraits<double, ImageDimension, ImageDimension, double>>;
  using TransformType = DisplacementFieldTransform<double, ImageDimension>;
  using DecoratedTransformType = DataObjectDecorator<TransformType>;
  using DensityFilterType =
    DensityFieldFilter<FixedImageType, MovingImageType, DisplacementFieldType, DensityImageType>;
  using CVTFilterType = DiscreteCVTFilter<DensityImageType, LabelImageType>;
  using DualMeshFilterType = DualMeshFilter<LabelImageType, MeshType>;
  using SolverType = LinearElasticFEMSolver<ImageDimension>;
  using SimplexMeshType = dmr::SimplexMesh<ImageDimension>;
  using MeshModeEnum = DynamicMeshRegistrationEnums::MeshMode;
  using BackendEnum = DynamicMeshRegistrationEnums::Backend;
  using DataObjectPointerArraySizeType = ProcessObject::DataObjectPointerArraySizeType;

  /** One row of the energy history (values at the start of the iteration, before its update). */
  struct IterationRecord
  {
    unsigned int iteration;
    double       mssd;    // paper Eq. 3 (x pixel volume)
    double       ssd;     // full-resolution SSD (x pixel volume)
    double       elastic; // R of the current transformation on this iteration's mesh
    double       total;   // mssd + beta * elastic
    size_t       nodes;
    size_t       sweeps;    // CVT sweeps of this iteration (dynamic mode)
    double       maxUpdate; // largest update displacement (pixels) of the accepted step
    double       stepScale; // fraction of the full step K^-1 f / beta taken (1, 1/2, ...; 0: no step lowered the MSSD)
    size_t       solverIterations; // conjugate-gradient products K p of this iteration's solve
    bool         deviceSolve;      // the solve ran on the GPU (CUDA back-end, see DeviceSolverMinimumDegreesOfFreedom)
    bool         directSolve;      // the system was factorised (see DirectSolverMaximumDegreesOfFreedom): no CG
  };
  /** Seconds per stage, summed over iterations (the breakdown of paper Table 1). */
  struct Timing
  {
    double initialTessellation{ 0 };
    double tessellationOptimization{ 0 };
    double meshConstruction{ 0 };
    double barycentric{ 0 };
    double registration{ 0 };
    double femSolve{ 0 }; // part of registration: stiffness set-up and solves (CPU assembly, or the device solve)
    // parts of registration as well: the force and density evaluations (the safeguard's included), the gathering of
    // the force to the nodes, and the update (u at the pixels, exp(u), W o exp(u), and the reverts of rejected steps)
    double force{ 0 };
    double gather{ 0 };
    double update{ 0 };
    double total{ 0 };
  };

  itkSetInputMacro(FixedImage, FixedImageType);
  itkGetInputMacro(FixedImage, FixedImageType);
  itkSetInputMacro(MovingImage, MovingImageType);
  itkGetInputMacro(MovingImage, MovingImageType);
  itkSetInputMacro(StaticMesh, MeshType);
  itkGetInputMacro(StaticMesh, MeshType);
  /** Optional region of interest on the fixed grid (e.g. the lungs): forces and density only inside it
   * (see DensityFieldFilter::SetFixedMask). */
  using MaskImageType = typename DensityFilterType::MaskImageType;
  itkSetInputMacro(FixedMask, MaskImageType);
  itkGetInputMacro(FixedMask, MaskImageType);
  /** Optional transformation the registration starts from, W_0(x) = x + u_0(x): a displacement field on the fixed
   * image's grid, physical frame, mm, ITK convention (moving point = fixed point + u_0), e.g. an affine pre-alignment
   * made into a field by TransformToDisplacementFieldFilter. Every iteration composes onto it (W <- W o exp(u)), so
   * the outputs (displacement field, transform) hold W_0 and the registration's part together, and the first
   * iteration's force, SSD and beta are those at W_0. Without it W_0 is the identity. */
  itkSetInputMacro(InitialDisplacementField, DisplacementFieldType);
  itkGetInputMacro(InitialDisplacementField, DisplacementFieldType);
  /** Also compute the inverse transformation W^-1 (default off). Every accepted update W <- W o exp(s u) has the
   * inverse exp(-s u) (scaling and squaring of the negated update), so W^-1 <- exp(-s u) o W^-1 is carried along the
   * iterations: one more exponential and composition per iteration, and one more field in memory (both back-ends).
   * The result, GetInverseDisplacementField(), lies on the fixed image's grid (as ANTs' inverse warp does): a moving
   * point y maps to the fixed point y + v(y). Its consistency with the forward field, |u(x) + v(x + u(x))|, is of the
   * order of the interpolation error of the compositions (docs/benchmarks.md), also where the deformation is too large
   * for a fixed-point inversion of the final field. With an InitialDisplacementField, its inverse must be given as
   * InitialInverseDisplacementField. */
  itkSetMacro(ComputeInverse, bool);
  itkGetConstMacro(ComputeInverse, bool);
  itkBooleanMacro(ComputeInverse);
  /** The inverse of InitialDisplacementField, W_0^-1(y) = y + v_0(y) (fixed grid, physical frame, mm), where the
   * inverse transformation is computed (ComputeInverse); e.g. the inverse of an affine pre-alignment made into a
   * field, or dmr::InverseDisplacementField of the initial field (dmrFieldImage.h). Ignored otherwise. */
  itkSetInputMacro(InitialInverseDisplacementField, DisplacementFieldType);
  itkGetInputMacro(InitialInverseDisplacementField, DisplacementFieldType);

  itkSetClampMacro(NumberOfIterations, unsigned int, 1, NumericTraits<unsigned int>::max());
  itkGetConstMacro(NumberOfIterations, unsigned int);
  /** Number of mesh nodes (CVT cells) of the dynamic mesh. */
  itkSetClampMacro(NumberOfNodes, SizeValueType, 4, NumericTraits<SizeValueType>::max());
  itkGetConstMacro(NumberOfNodes, SizeValueType);
  itkSetClampMacro(NumberOfLevels, unsigned int, 1, 8);
  itkGetConstMacro(NumberOfLevels, unsigned int);
  /** The largest Lambda, Mu, EnergyRatio and AlphaFactor accepted (Update() refuses larger ones and NaN). */
  static constexpr double LargestParameterValue = 1e30;

  itkSetClampMacro(Lambda, double, 0.0, NumericTraits<double>::max());
  itkGetConstMacro(Lambda, double);
  itkSetClampMacro(Mu, double, NumericTraits<double>::epsilon(), NumericTraits<double>::max());
  itkGetConstMacro(Mu, double);
  /** beta R / D at the first iteration (paper 5.1: 0.02). */
  itkSetClampMacro(EnergyRatio, double, NumericTraits<double>::epsilon(), NumericTraits<double>::max());
  itkGetConstMacro(EnergyRatio, double);
  /** Largest number of times an update is halved because it would raise the MSSD (default 5; 0: no safeguard, every
   * full step is taken, as in the paper). */
  itkSetClampMacro(MaximumStepHalvings, unsigned int, 0, 30);
  itkGetConstMacro(MaximumStepHalvings, unsigned int);
  /** alpha = AlphaFactor x mean |f|^2 (paper 5.1: 0.1). */
  itkSetClampMacro(AlphaFactor, double, 0.0, NumericTraits<double>::max());
  itkGetConstMacro(AlphaFactor, double);
  /** Gradient in the force (DensityFieldFilter): WarpedMoving (default, the derivative for the compositional update)
   * or MappedMoving (a literal reading of paper Eq. 5). */
  using ForceGradientEnum = DynamicMeshRegistrationEnums::ForceGradient;
  itkSetEnumMacro(ForceGradient, ForceGradientEnum);
  itkGetEnumMacro(ForceGradient, ForceGradientEnum);
  /** Relative residual at which the conjugate-gradient solve of K u = f / beta stops, |r| < SolverTolerance |f| over
   * the free degrees of freedom (LinearElasticFEMSolver::Tolerance; the device solve uses the same rule). The paper
   * does not say. Default 1e-6: against 1e-12 it took 44 % fewer products on the 256 x 256 x 132 thorax pair (100
   * iterations) and moved the field by at most 0.009 voxel and the mean dense error by 3e-5 mm; on circle-to-epsilon
   * (400 iterations) 36 % fewer, 4e-4 pixel, the same Dice (docs/benchmarks.md). */
  itkSetClampMacro(SolverTolerance, double, 1e-16, 1e-2);
  itkGetConstMacro(SolverTolerance, double);
  /** CVT stopping tolerance (paper 5.1: 0). */
  itkSetClampMacro(CVTEpsilon, double, 0.0, 1.0);
  itkGetConstMacro(CVTEpsilon, double);
  itkSetClampMacro(MaximumNumberOfSweeps, SizeValueType, 1, NumericTraits<SizeValueType>::max());
  itkGetConstMacro(MaximumNumberOfSweeps, SizeValueType);
  /** Dynamic mode: re-run the contraction (paper 4.4) every this many iterations instead of warm-starting the swaps
   * from the previous labels (paper 4.7); 0 = always warm-start after the first iteration. */
  itkSetMacro(ReinitializationInterval, unsigned int);
  itkGetConstMacro(ReinitializationInterval, unsigned int);
  itkSetEnumMacro(MeshMode, MeshModeEnum);
  itkGetEnumMacro(MeshMode, MeshModeEnum);
  /** Nodes per axis of the Regular mesh; 0 = round(NumberOfNodes^(1/D)). At most the pixels along an axis; at least 3
   * along every axis, or no node would be free (border nodes are fixed). */
  itkSetMacro(RegularGridSize, unsigned int);
  itkGetConstMacro(RegularGridSize, unsigned int);
  itkSetEnumMacro(Backend, BackendEnum);
  itkGetEnumMacro(Backend, BackendEnum);
  itkGetConstMacro(BackendUsed, BackendEnum);
  /** Elastic systems solved on the CPU with at most this many free degrees of freedom are factorised (sparse LDL^T) and
   * solved exactly instead of by conjugate gradients to SolverTolerance. Below a few hundred unknowns the two cost the
   * same, and the exact solve keeps a registration from depending on the rounding of its sums: a CG stopped at 1e-6
   * jumps by about that much when a rounding difference moves its stopping iteration, and on a large deformation such
   * jumps grew into a different registration (circle-to-leaf: CPU and GPU ended up to 277 px apart in the
   * field; docs/benchmarks.md). 0: always CG. Default 300 (both 2D paper experiments, 142 unknowns, are below it). */
  itkSetMacro(DirectSolverMaximumDegreesOfFreedom, SizeValueType);
  itkGetConstMacro(DirectSolverMaximumDegreesOfFreedom, SizeValueType);
  /** CPU solves of systems above DirectSolverMaximumDegreesOfFreedom by the CUDA back-end's matrix-free CG with its
   * arithmetic in its order (LinearElasticFEMSolver::GPUOrderSolve, dmr::ElasticCG) instead of CG on the assembled
   * matrix (Eigen, warm-started): a CPU run then takes the GPU run's solves bit for bit, so the two back-ends give the
   * same field where the rounding of two different CGs would tip a CVT swap decision and part them (a large 3D
   * deformation: up to 0.77 mm apart otherwise, docs/benchmarks.md). Default on. Off, the solves took 0.75x the time on
   * 2 threads (sphere3d) and 1.25-1.75x on 16 (the 3D shape pairs; 32nd session in docs/benchmarks.md). */
  itkSetMacro(GPUOrderSolve, bool);
  itkGetConstMacro(GPUOrderSolve, bool);
  itkBooleanMacro(GPUOrderSolve);
  /** CUDA back-end: elastic systems with at least this many free degrees of freedom are solved on the device
   * (matrix-free Jacobi-preconditioned conjugate gradients, RegistrationContext::SolveElasticity, to the CPU solver's
   * tolerance; a solve that does not converge falls back to the CPU solver); smaller ones are assembled and solved on
   * the CPU, where they are faster (about 100 conjugate-gradient products of a few hundred unknowns cost less than the
   * kernel launches; crossover measured in docs/benchmarks.md). 0: always on the device. Default 301: the systems
   * above DirectSolverMaximumDegreesOfFreedom's default (300), which the CPU back-end solves by conjugate gradients
   * too; the ones it factorises are factorised by both back-ends. */
  itkSetMacro(DeviceSolverMinimumDegreesOfFreedom, SizeValueType);
  itkGetConstMacro(DeviceSolverMinimumDegreesOfFreedom, SizeValueType);
  /** CUDA back-end: the most conjugate-gradient products one device solve may take before it gives up and the CPU
   * solver (whose last resort is a factorisation) solves that system instead, and the rest of that mesh's systems.
   * 0 (default): max(1000, 4 x free degrees of freedom). */
  itkSetMacro(DeviceSolverMaximumIterations, SizeValueType);
  itkGetConstMacro(DeviceSolverMaximumIterations, SizeValueType);
  /** CUDA back-end, dynamic mesh, no initial displacement field, fixed and moving images of at most
   * HostContractionMaximumPixels pixels each: iteration 1's contraction runs on the CPU ahead of the device (the CPU
   * path's density at the identity, its block sums and the merges) while the device's context is still being created,
   * which reading small inputs does not cover. At iteration 1 the device's block sums of its own density must equal the
   * host's bit for bit for the host's merges to be taken; otherwise the merges run again on the device's sums, as they
   * do without this. The result is the same either way. AlwaysContractOnHost (default off; for tests and benchmarks):
   * also when the context is ready. */
  itkSetMacro(AlwaysContractOnHost, bool);
  itkGetConstMacro(AlwaysContractOnHost, bool);
  itkBooleanMacro(AlwaysContractOnHost);
  /** Whether the last run's iteration 1 took the contraction made on the CPU ahead of the device (see
   * AlwaysContractOnHost). */
  itkGetConstMacro(ContractedOnHost, bool);
  static constexpr SizeValueType HostContractionMaximumPixels = SizeValueType{ 1 } << 20;
  /** Device memory the CUDA back-end's buffers held at their peak (bytes; 0 on the CPU path): the registration
   * context's largest allocation plus the CVT optimiser's and the label summary's buffers, which are held throughout
   * the iterations. The CUDA context and the driver's own allocations are not included. */
  itkGetConstMacro(DeviceBytes, SizeValueType);
  /** The most device memory the back-end's buffers held at one moment of the last GPU run (bytes; 0 on the CPU
   * path), transient buffers included (every buffer goes through one counting allocator, dmr::cuda::
   * GetMemoryStatistics), and the whole device's use at that moment (total - free: with the CUDA context and the
   * driver's own memory, and any other process on the device). */
  itkGetConstMacro(DevicePeakBytes, SizeValueType);
  itkGetConstMacro(DeviceUsedAtPeakBytes, SizeValueType);

  /** Results. Energies (the history's MSSD, SSD and totals, the final SSD and MSSD, and beta, which weighs the
   * elastic energy against them) are in the images' own intensity units, also when the density filter works on
   * scaled images (DensityFieldFilter::GetIntensityScale()). */
  double
  GetBeta() const
  {
    return m_Beta * this->EnergyToImageUnits();
  }
  itkGetConstMacro(CurrentIteration, unsigned int);
  const std::vector<IterationRecord> &
  GetHistory() const
  {
    return m_History;
  }
  const Timing &
  GetTiming() const
  {
    return m_Timing;
  }
  /** Why the last run ended (as ITK's optimizers say it): it completed its iterations, was aborted, the images
   * already matched (no force at iteration 1), or a later dynamic mesh had no free node (the transformation reached
   * until then is the result). */
  std::string
  GetStopConditionDescription() const
  {
    return m_StopConditionDescription;
  }
  /** Final (after the last update) full-resolution SSD and MSSD, x pixel volume. */
  itkGetConstMacro(FinalSSD, double);
  itkGetConstMacro(FinalMSSD, double);
  /** The mesh of the current iteration (physical space), valid in an IterationEvent observer and after Update. */
  const MeshType *
  GetCurrentMesh();
  const SimplexMeshType &
  GetCurrentSimplexMesh() const
  {
    return *m_CurrentMesh;
  }
  /** The CVT labels of the current iteration (dynamic mode on the CPU back-end, in an IterationEvent observer;
   * nullptr otherwise, after the run, which frees them, and on the CUDA back-end, which keeps them on the device). */
  const LabelImageType *
  GetCurrentLabels() const
  {
    return m_Labels.GetPointer();
  }
  /** Current density (valid in an IterationEvent observer on the CPU back-end; the CUDA back-end keeps it on the
   * device and leaves this image empty). */
  const DensityImageType *
  GetCurrentDensity() const
  {
    return m_DensityFilter->GetOutput();
  }

  DecoratedTransformType *
  GetTransformOutput();
  const TransformType *
  GetTransform();
  DisplacementFieldType *
  GetDisplacementField();
  /** The inverse of the transformation's displacement field (see ComputeInverse), on the fixed grid in mm, after a run
   * with ComputeInverse on (nullptr otherwise). The transform output carries it too
   * (DisplacementFieldTransform::GetInverseDisplacementField, so that GetInverseTransform() works). */
  const DisplacementFieldType *
  GetInverseDisplacementField() const
  {
    return m_InverseDisplacementField.GetPointer();
  }

protected:
  FEMRegistrationMethod();
  ~FEMRegistrationMethod() override = default;
  void
  PrintSelf(std::ostream & os, Indent indent) const override;
  /** Checks of the parameters and of which inputs are set (before the inputs' information is updated). */
  void
  VerifyPreconditions() ITKv5_CONST override;
  /** Checks of the inputs' sizes, once the pipeline's information pass has updated them (an input may be the
   * output of a filter that has not run yet). */
  void
  VerifyInputInformation() ITKv5_CONST override;
  void
  GenerateOutputInformation() override;
  void
  GenerateInputRequestedRegion() override;
  void
  GenerateData() override;
  using Superclass::MakeOutput;
  DataObject::Pointer
  MakeOutput(DataObjectPointerArraySizeType idx) override;

private:
  void
  WriteGridFieldToImage(const std::vector<float> & grid, DisplacementFieldType * image) const;
  /** A displacement field on the fixed grid (the initial field or its inverse) in the fixed grid frame (n x D
   * floats), for w (or the inverse) at the start. */
  void
  InitialGridField(const DisplacementFieldType * initial, std::vector<float> & w) const;
  /** The inverse field image from its grid-frame floats (ComputeInverse). */
  void
  MakeInverseField(const std::vector<float> & inverse);
  void
  MakeTransformOutput();
  /** The Regular or Static mode's mesh into m_StaticSimplexMesh (timed as mesh construction). */
  void
  BuildStaticMesh();
  /** Throws when every node of the mesh is fixed (on the image border): such a mesh cannot move anything. */
  void
  CheckStaticMeshHasAFreeNode(const SimplexMeshType & mesh) const;
  /** Nodes per axis of the Regular mesh on the fixed image's grid. */
  std::array<size_t, ImageDimension>
  RegularNodesPerAxis() const;
  /** Both back-ends: zero output field, the stages' settings, history/timing/beta reset (needs m_BackendUsed). */
  void
  ConfigureStages();
  /** Gives a density filter the registration's inputs and settings, all but the displacement field (ConfigureStages,
   * and the CUDA path's contraction on the host ahead of the device). */
  void
  ConfigureDensityFilter(DensityFilterType & filter) const;
  /** nodalU = K^-1 nodalForce by solve() (timed as FEM solve); while beta is unset (the first iteration) sets it so
   * that beta R / D = EnergyRatio. False when there is no force to register with (beta cannot be set) or when a
   * dynamic mesh after the first has no free node; throws when the first mesh has none. */
  template <typename TSolve>
  bool
  SolveAndSetBeta(const std::vector<double> & nodalForce, std::vector<double> & nodalU, double mssd, TSolve && solve);
  /** Appends an iteration's record to the history with its energies converted to the images' intensity units (the
   * iteration itself works in the density filter's units, in which the force, beta and the MSSD agree). */
  void
  AppendToHistory(IterationRecord record);
  /** 1 / the density filter's intensity scale squared: its energies to the images' units (1 before any run). */
  double
  EnergyToImageUnits() const
  {
    const double scale = m_DensityFilter->GetIntensityScale();
    return 1.0 / (scale * scale);
  }
  /** The step safeguard, one rule for both back-ends: tries W o exp(s u) for s = 1, 1/2, ... while the candidate's
   * MSSD is above record.mssd - SufficientDecrease s predictedDecrease (at most MaximumStepHalvings halvings; none
   * checked when it is 0). predictedDecrease is the first-order decrease of the full step, f.u (nodal forces times
   * the nodal update, x pixel volume, as the MSSD). apply(s) makes the candidate for s and returns its largest update
   * (pixels); candidateMSSD() evaluates the force at the candidate and returns its MSSD (x pixel volume); reject()
   * drops the candidate. Sets record.maxUpdate and record.stepScale (0: no step taken, W unchanged). Returns true when
   * the force at the new W has been evaluated (the next iteration's). */
  template <typename TApply, typename TCandidateMSSD, typename TReject>
  bool
  SafeguardedStep(IterationRecord & record,
                  double            predictedDecrease,
                  TApply &&         apply,
                  TCandidateMSSD && candidateMSSD,
                  TReject &&        reject) const;
  /** The share of the first-order decrease an accepted step must reach (Armijo's constant). */
  static constexpr double SufficientDecrease = 1e-4;
  /** f.u of an iteration's solve (f^T K^-1 f): the nodal forces times the solution of K u = f. */
  static double
  NodalWork(const std::vector<double> & nodalForce, const std::vector<double> & nodalU);
  /** f.u / beta of an iteration's solve: the first-order decrease of the MSSD for the full step (at least 0). */
  double
  PredictedDecrease(const std::vector<double> & nodalForce, const std::vector<double> & nodalU) const;
  /** Assembles the stiffness of a new mesh (timed as FEM solve, part of registration). */
  void
  SetSolverMesh(const SimplexMeshType & mesh);
  /** The iteration loop with every per-pixel stage on the GPU (BackendUsed CUDA); deviceContext: the creation of the
   * device's context, started by GenerateData. */
  void
  GenerateDataCUDA(std::chrono::steady_clock::time_point tStart, std::future<dmr::cuda::Status> & deviceContext);
  void
  UploadMesh(dmr::cuda::RegistrationContext & context, const SimplexMeshType & mesh);

  unsigned int      m_NumberOfIterations{ 100 };
  SizeValueType     m_NumberOfNodes{ 100 };
  unsigned int      m_NumberOfLevels{ 3 };
  double            m_Lambda{ 1.0 };
  double            m_Mu{ 1.0 };
  double            m_EnergyRatio{ 0.02 };
  double            m_AlphaFactor{ 0.1 };
  ForceGradientEnum m_ForceGradient{ ForceGradientEnum::WarpedMoving };
  unsigned int      m_MaximumStepHalvings{ 5 };
  double            m_CVTEpsilon{ 0.0 };
  SizeValueType     m_MaximumNumberOfSweeps{ 1000 };
  unsigned int      m_ReinitializationInterval{ 0 };
  MeshModeEnum      m_MeshMode{ MeshModeEnum::Dynamic };
  unsigned int      m_RegularGridSize{ 0 };
  BackendEnum       m_Backend{ BackendEnum::Auto };
  BackendEnum       m_BackendUsed{ BackendEnum::CPU };
  size_t            m_DeviceBytes{ 0 };
  size_t            m_DevicePeakBytes{ 0 };
  size_t            m_DeviceUsedAtPeakBytes{ 0 };
  double            m_SolverTolerance{ 1e-6 };
  SizeValueType     m_DeviceSolverMinimumDegreesOfFreedom{ 301 };
  SizeValueType     m_DirectSolverMaximumDegreesOfFreedom{ 300 };
  bool              m_GPUOrderSolve{ true };
  SizeValueType     m_DeviceSolverMaximumIterations{ 0 };
  bool              m_AlwaysContractOnHost{ false };
  bool              m_ContractedOnHost{ false };
  bool              m_ComputeInverse{ false };

  double                       m_Beta{ 0.0 }; // in the density filter's units; GetBeta() converts
  unsigned int                 m_CurrentIteration{ 0 };
  double                       m_FinalSSD{ 0.0 };
  double                       m_FinalMSSD{ 0.0 };
  std::vector<IterationRecord> m_History;
  std::string                  m_StopConditionDescription;
  Timing                       m_Timing;

  typename DensityFilterType::Pointer     m_DensityFilter;
  typename CVTFilterType::Pointer         m_CVTFilter;
  typename SolverType::Pointer            m_Solver;
  typename LabelImageType::Pointer        m_Labels;
  typename DisplacementFieldType::Pointer m_InverseDisplacementField;
  SimplexMeshType                         m_StaticSimplexMesh;
  SimplexMeshType                         m_DynamicSimplexMesh; // the current dual mesh (Dynamic mode)
  const SimplexMeshType *                 m_CurrentMesh{ nullptr };
  typename MeshType::Pointer              m_CurrentItkMesh;
  size_t                                  m_CurrentMeshVersion{ 0 };
  size_t                                  m_CurrentItkMeshVersion{ 0 };
  // the last 3D dual mesh's tetrahedra (cell indices) and nodes, which the next one is repaired from
  // (dmr::RepairDelaunay3D)
  dmr::DelaunayWarmStart m_DelaunayWarmStart;
};
} // namespace itk

#ifndef ITK_MANUAL_INSTANTIATION
#include "itkFEMRegistrationMethod.hxx"
#endif

#endif
