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
// GPU registration iteration vs the CPU reference (issue 4): the force, the barycentric owner of every pixel, the
// gathered nodal forces and the final displacement field of whole runs (2D and 3D, dynamic and regular meshes,
// rotated geometry) must agree. Every test skips without a CUDA device.
#include "itkFEMRegistrationMethod.h"
#include "dmrCudaBackend.h"
#include "dmrElasticCG.h"
#include "dmrErrorStatistics.h"
#include "dmrFieldImage.h"
#include "dmrRegistrationBackend.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"
#include <cmath>
#include <cstring>
#include <iostream>

namespace
{
template <unsigned int D>
using ImageOf = itk::Image<float, D>;
template <unsigned int D>
using MethodOf = itk::FEMRegistrationMethod<ImageOf<D>, ImageOf<D>>;
using MeshMode = itk::DynamicMeshRegistrationEnums::MeshMode;
using Backend = itk::DynamicMeshRegistrationEnums::Backend;

#define DMR_REQUIRE_DEVICE()                                                                                           \
  if (!itk::dmr::cuda::DeviceAvailable())                                                                              \
  GTEST_SKIP() << "no CUDA device: " << itk::dmr::cuda::UnavailableReason()

/** Smooth ellipsoidal blob with a little texture; rotated direction, anisotropic spacing and an origin away from 0
 * so the physical-space paths are exercised. */
template <unsigned int D>
typename ImageOf<D>::Pointer
Blob(unsigned int n, const double * centre, const double * radii)
{
  using ImageType = ImageOf<D>;
  auto                            image = ImageType::New();
  typename ImageType::SizeType    size;
  typename ImageType::SpacingType spacing;
  typename ImageType::PointType   origin;
  for (unsigned int k = 0; k < D; ++k)
  {
    size[k] = n - 4 * k;
    spacing[k] = 1.0 + 0.25 * k;
    origin[k] = -10.0 + 3.0 * k;
  }
  image->SetRegions(size);
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  typename ImageType::DirectionType direction;
  direction.SetIdentity();
  const double a = 0.35;
  direction(0, 0) = std::cos(a);
  direction(0, 1) = -std::sin(a);
  direction(1, 0) = std::sin(a);
  direction(1, 1) = std::cos(a);
  image->SetDirection(direction);
  image->Allocate();
  itk::ImageRegionIteratorWithIndex<ImageType> it(image, image->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    double r2 = 0.0, texture = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double q = (it.GetIndex()[k] - centre[k]) / radii[k];
      r2 += q * q;
      texture += std::sin(0.45 * it.GetIndex()[k] + k);
    }
    const double inside = 1.0 / (1.0 + std::exp((std::sqrt(r2) - 1.0) * 8.0));
    it.Set(static_cast<float>(100.0 * inside * (1.0 + 0.1 * texture)));
  }
  return image;
}

template <unsigned int D>
typename MethodOf<D>::Pointer
Registration(Backend      backend,
             MeshMode     mode,
             unsigned int nodes,
             unsigned int iterations,
             unsigned int n,
             double       energyRatio = 0.1)
{
  const double cf[3] = { 0.45 * n, 0.5 * n, 0.45 * n }, rf[3] = { 0.3 * n, 0.22 * n, 0.25 * n };
  const double cm[3] = { 0.52 * n, 0.47 * n, 0.5 * n }, rm[3] = { 0.24 * n, 0.25 * n, 0.2 * n };
  auto         method = MethodOf<D>::New();
  method->SetFixedImage(Blob<D>(n, cf, rf));
  method->SetMovingImage(Blob<D>(n, cm, rm));
  method->SetNumberOfNodes(nodes);
  method->SetNumberOfIterations(iterations);
  method->SetMeshMode(mode);
  method->SetEnergyRatio(energyRatio);
  method->SetMaximumNumberOfSweeps(50);
  method->SetBackend(backend);
  return method;
}

/** Largest difference of two displacement fields in voxels (per axis, divided by the spacing along the image axis
 * closest to it: spacing is anisotropic, so use the smallest spacing: a conservative bound). */
template <typename TField>
double
MaxDifferenceInVoxels(const TField * a, const TField * b)
{
  constexpr unsigned int D = TField::ImageDimension;
  double                 h = a->GetSpacing()[0];
  for (unsigned int k = 1; k < D; ++k)
  {
    h = std::min(h, static_cast<double>(a->GetSpacing()[k]));
  }
  const size_t n = a->GetLargestPossibleRegion().GetNumberOfPixels();
  double       m = 0.0;
  for (size_t p = 0; p < n; ++p)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      m = std::max(m, std::abs(static_cast<double>(a->GetBufferPointer()[p][k]) - b->GetBufferPointer()[p][k]) / h);
    }
  }
  return m;
}

template <unsigned int D>
void
RunsAgree(MeshMode     mode,
          unsigned int nodes,
          unsigned int iterations,
          unsigned int n,
          double       energyRatio = 0.1,
          size_t *     halvedSteps = nullptr,
          bool         solveOnDevice = false,
          size_t       deviceSolveLimit = 0,
          double       solverTolerance = 0.0, // 0: the registration's default
          size_t *     gpuProducts = nullptr)
{
  auto cpu = Registration<D>(Backend::CPU, mode, nodes, iterations, n, energyRatio);
  auto gpu = Registration<D>(Backend::CUDA, mode, nodes, iterations, n, energyRatio);
  if (solverTolerance > 0.0)
  {
    cpu->SetSolverTolerance(solverTolerance);
    gpu->SetSolverTolerance(solverTolerance);
  }
  // every elastic system on the device, or (the default threshold, these meshes are small) every one on the CPU
  gpu->SetDeviceSolverMinimumDegreesOfFreedom(solveOnDevice ? 0 : 1000000);
  // a limit far below what the systems need: every device solve gives up and the CPU solver takes over
  gpu->SetDeviceSolverMaximumIterations(deviceSolveLimit);
  const bool fallBack = solveOnDevice && deviceSolveLimit > 0;
  cpu->Update();
  gpu->Update();
  for (const auto & r : gpu->GetHistory())
  {
    EXPECT_EQ(r.deviceSolve, solveOnDevice && !fallBack) << "iteration " << r.iteration;
    // a small system solved on the CPU is factorised (no CG products); every other solve takes CG products
    EXPECT_EQ(r.solverIterations > 0, !r.directSolve) << "iteration " << r.iteration;
    EXPECT_FALSE(r.directSolve && r.deviceSolve) << "iteration " << r.iteration;
    if (gpuProducts)
    {
      *gpuProducts += r.solverIterations;
    }
  }
  EXPECT_EQ(cpu->GetBackendUsed(), Backend::CPU);
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(gpu->GetHistory().size(), cpu->GetHistory().size());
  const double difference = MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField());
  double       maxDisplacement = 0.0;
  const auto * f = cpu->GetDisplacementField()->GetBufferPointer();
  for (size_t p = 0; p < cpu->GetDisplacementField()->GetLargestPossibleRegion().GetNumberOfPixels(); ++p)
  {
    maxDisplacement = std::max(maxDisplacement, static_cast<double>(f[p].GetNorm()));
  }
  std::cout << D << "D " << (mode == MeshMode::Dynamic ? "dynamic" : "regular") << ": max |u| " << maxDisplacement
            << " mm, CPU/GPU max difference " << difference << " voxel, SSD " << cpu->GetHistory().front().ssd
            << " -> CPU " << cpu->GetFinalSSD() << ", GPU " << gpu->GetFinalSSD() << std::endl;
  EXPECT_GT(maxDisplacement, 1.0); // the pair really moves
  EXPECT_LT(difference, 0.05);
  EXPECT_NEAR(gpu->GetFinalSSD(), cpu->GetFinalSSD(), 1e-3 * cpu->GetFinalSSD());
  EXPECT_LT(gpu->GetFinalSSD(), 0.5 * gpu->GetHistory().front().ssd);
  for (size_t i = 0; i < cpu->GetHistory().size(); ++i)
  {
    EXPECT_EQ(gpu->GetHistory()[i].nodes, cpu->GetHistory()[i].nodes) << "iteration " << i + 1;
    EXPECT_NEAR(gpu->GetHistory()[i].mssd, cpu->GetHistory()[i].mssd, 1e-6 * cpu->GetHistory()[i].mssd);
    EXPECT_EQ(gpu->GetHistory()[i].stepScale, cpu->GetHistory()[i].stepScale) << "iteration " << i + 1;
    EXPECT_NEAR(
      gpu->GetHistory()[i].elastic, cpu->GetHistory()[i].elastic, 1e-6 * std::abs(cpu->GetHistory()[i].elastic) + 1e-12)
      << "iteration " << i + 1;
  }
  size_t halved = 0;
  for (const auto & r : cpu->GetHistory())
  {
    halved += r.stepScale < 1.0 ? 1 : 0;
  }
  std::cout << "steps halved in " << halved << " of " << cpu->GetHistory().size() << " iterations" << std::endl;
  if (halvedSteps)
  {
    *halvedSteps = halved;
  }
  std::pair<double, double> range;
  itk::dmr::JacobianDeterminantImage(gpu->GetDisplacementField(), range, nullptr);
  EXPECT_GT(range.first, 0.0);
  EXPECT_GT(gpu->GetDeviceBytes(), 0u);
  // the counting allocator's peak holds at least what is held at the end, and the device's whole use at that moment
  // (with the CUDA context) more than that
  const auto peak = gpu->GetDevicePeakBytes();
  EXPECT_GE(peak, gpu->GetDeviceBytes());
  EXPECT_GT(gpu->GetDeviceUsedAtPeakBytes(), peak);
  std::cout << "device memory: held at the end " << gpu->GetDeviceBytes() << " B, peak " << peak
            << " B, device used at the peak " << gpu->GetDeviceUsedAtPeakBytes() << " B" << std::endl;
  // after the run only the buffers of objects still alive remain counted
  EXPECT_LE(itk::dmr::cuda::GetMemoryStatistics().allocatedBytes, peak);

  // a second Update() starts afresh: the same field, and stage times of that run only (they sum to at most the total)
  gpu->Modified();
  gpu->Update();
  EXPECT_LT(MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField()), 0.05);
  const auto & t = gpu->GetTiming();
  EXPECT_LE(t.initialTessellation + t.tessellationOptimization + t.meshConstruction + t.barycentric + t.registration,
            t.total);
  EXPECT_LE(t.femSolve, t.registration);
  EXPECT_GT(t.force, 0.0);
  EXPECT_GT(t.gather, 0.0);
  EXPECT_GT(t.update, 0.0);
  EXPECT_LE(t.force + t.gather + t.update + t.femSolve, t.registration);
}

/** The device elastic solve (matrix-free CG) against LinearElasticFEMSolver on the same mesh: the solution, u = 0 on
 * fixed nodes, the number of CG products, u^T K u / 2 over all nodes, and the errors. The context holds the mesh. */
template <unsigned int D>
void
ElasticSolveAgrees(itk::dmr::cuda::RegistrationContext & context, const itk::dmr::SimplexMesh<D> & mesh)
{
  const double        lambda = 0.7, mu = 1.3;
  const size_t        ndof = mesh.NumberOfNodes() * D;
  std::vector<double> f(ndof), uGpu(ndof, 7.0), uCpu;
  for (size_t i = 0; i < ndof; ++i)
  {
    f[i] = std::sin(0.37 * static_cast<double>(i) + 0.2) + 0.3 * std::cos(1.9 * static_cast<double>(i));
  }
  size_t iterations = 0;
  bool   converged = false;
  EXPECT_FALSE(context.SolveElasticity(f.data(), uGpu.data(), 1e-12, 1000, iterations, converged).Ok())
    << "a solve before SetElasticity is refused";
  ASSERT_TRUE(context.SetElasticity(lambda, mu, mesh.fixed.data()).Ok());
  ASSERT_TRUE(context.SolveElasticity(f.data(), uGpu.data(), 1e-12, 4 * ndof + 1000, iterations, converged).Ok());
  EXPECT_TRUE(converged);

  auto solver = itk::LinearElasticFEMSolver<D>::New();
  solver->SetLambda(lambda);
  solver->SetMu(mu);
  solver->SetDirectSolverMaximumDegreesOfFreedom(0); // the CPU's conjugate gradients, the GPU's algorithm
  solver->SetMesh(mesh);
  solver->Solve(f, uCpu);
  double largest = 0.0, largestDiff = 0.0;
  size_t fixedNodes = 0;
  for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      largest = std::max(largest, std::abs(uCpu[a * D + k]));
      largestDiff = std::max(largestDiff, std::abs(uCpu[a * D + k] - uGpu[a * D + k]));
      if (mesh.fixed[a])
      {
        EXPECT_EQ(uGpu[a * D + k], 0.0) << "fixed node " << a;
      }
    }
    fixedNodes += mesh.fixed[a] ? 1 : 0;
  }
  std::cout << D << "D elastic solve, " << mesh.NumberOfNodes() << " nodes (" << fixedNodes << " fixed): GPU "
            << iterations << " CG products, CPU " << solver->GetLastIterations() << " iterations; max |u| " << largest
            << ", max difference " << largestDiff << std::endl;
  EXPECT_GT(fixedNodes, 0u);
  EXPECT_GT(largest, 0.0);
  EXPECT_LE(largestDiff, 1e-8 * largest);
  // the same algorithm and stopping rule: Eigen counts the products before the converging one
  EXPECT_NEAR(static_cast<double>(iterations),
              static_cast<double>(solver->GetLastIterations() + 1),
              std::max(3.0, 0.1 * static_cast<double>(solver->GetLastIterations())));

  // the CPU's GPU-order CG (dmr::ElasticCG, LinearElasticFEMSolver::GPUOrderSolve) takes the device's products: the
  // same iterate, bit for bit, after the same number of products, converged (at two tolerances) or stopped early
  for (const double tolerance : { 1e-12, 1e-6 })
  {
    for (const size_t limit : { size_t{ 7 }, 4 * ndof + 1000 })
    {
      std::vector<double> uDevice(ndof, 3.0), uOrdered(ndof, 5.0);
      size_t              deviceProducts = 0, orderedProducts = 0;
      bool                deviceConverged = false;
      ASSERT_TRUE(
        context.SolveElasticity(f.data(), uDevice.data(), tolerance, limit, deviceProducts, deviceConverged).Ok());
      itk::dmr::ElasticCG<D> ordered;
      ordered.SetSystem(mesh, lambda, mu);
      const bool orderedConverged = ordered.Solve(f.data(), uOrdered.data(), tolerance, limit, orderedProducts);
      EXPECT_EQ(orderedProducts, deviceProducts) << "tolerance " << tolerance << ", limit " << limit;
      EXPECT_EQ(orderedConverged, deviceConverged) << "tolerance " << tolerance << ", limit " << limit;
      EXPECT_EQ(uOrdered, uDevice) << "tolerance " << tolerance << ", limit " << limit;
    }
  }
  solver->SetGPUOrderSolve(true);
  solver->SetTolerance(1e-6);
  solver->SetMesh(mesh);
  std::vector<double> uSolver, uDevice(ndof);
  solver->Solve(f, uSolver);
  ASSERT_TRUE(context.SolveElasticity(f.data(), uDevice.data(), 1e-6, 4 * ndof + 1000, iterations, converged).Ok());
  EXPECT_EQ(uSolver, uDevice) << "LinearElasticFEMSolver with GPUOrderSolve";
  EXPECT_EQ(static_cast<size_t>(solver->GetLastIterations()), iterations);

  // the one-launch (cooperative) CG loop and the separate launches take the same products: the same iterate, bit for
  // bit, after the same number of products, converged or stopped early
  for (const size_t limit : { size_t{ 7 }, 4 * ndof + 1000 })
  {
    std::vector<double> uSeparate(ndof, 3.0), uFused(ndof, 5.0);
    size_t              separateIterations = 0, fusedIterations = 0;
    bool                separateConverged = false, fusedConverged = true;
    context.SetCooperativeSolve(false);
    ASSERT_TRUE(
      context.SolveElasticity(f.data(), uSeparate.data(), 1e-12, limit, separateIterations, separateConverged).Ok());
    context.SetCooperativeSolve(true);
    ASSERT_TRUE(context.SolveElasticity(f.data(), uFused.data(), 1e-12, limit, fusedIterations, fusedConverged).Ok());
    EXPECT_EQ(fusedIterations, separateIterations) << "limit " << limit;
    EXPECT_EQ(fusedConverged, separateConverged) << "limit " << limit;
    EXPECT_EQ(fusedConverged, limit > 7) << "limit " << limit;
    EXPECT_EQ(uFused, uSeparate) << "limit " << limit;
  }

  // u^T K u / 2 over all nodes, fixed ones included (f is not zero there)
  double energy = 0.0;
  ASSERT_TRUE(context.ElasticEnergy(f.data(), energy).Ok());
  const double cpuEnergy = solver->ElasticEnergy(f);
  EXPECT_GT(cpuEnergy, 0.0);
  EXPECT_NEAR(energy, cpuEnergy, 1e-10 * cpuEnergy);

  // too few products: reported as not converged (the registration then falls back to the CPU solver)
  ASSERT_TRUE(context.SolveElasticity(f.data(), uGpu.data(), 1e-12, 3, iterations, converged).Ok());
  EXPECT_FALSE(converged);
  EXPECT_EQ(iterations, 3u);
  // a zero load gives u = 0 at once
  std::vector<double> zero(ndof, 0.0);
  ASSERT_TRUE(context.SolveElasticity(zero.data(), uGpu.data(), 1e-12, 100, iterations, converged).Ok());
  EXPECT_TRUE(converged);
  EXPECT_EQ(iterations, 0u);
  EXPECT_EQ(uGpu, zero);
  EXPECT_FALSE(context.SetElasticity(lambda, 0.0, mesh.fixed.data()).Ok()) << "mu = 0 is refused";
}

/** The first dynamic mesh of a CUDA run is the CPU run's, bit for bit (nodes, elements, fixed nodes), on a pair with
 * a rotated direction, anisotropic spacing and an origin away from 0: the density is the same, so are the contraction
 * and the sweeps (the device optimiser updates the same sums in the same order from the contraction's state), and both
 * paths build the mesh from the sites in the grid frame. Before, the CUDA path took its first sites summed again from
 * the swept labels, and the CPU path took its sites through physical points and back: both rounded the last bit of
 * the nodes differently, which decides the tetrahedralization of near-degenerate node sets (issue 4: on a 3D pair
 * with a large deformation the meshes had 15 163 and 15 145 tetrahedra at iteration 1). */
template <unsigned int D>
void
FirstMeshIsTheCPUs(unsigned int nodes, unsigned int n)
{
  auto cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, 1, n);
  auto gpu = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, 1, n);
  cpu->Update();
  gpu->Update();
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(gpu->GetHistory().size(), 1u);
  EXPECT_EQ(gpu->GetHistory()[0].sweeps, cpu->GetHistory()[0].sweeps);
  EXPECT_GT(cpu->GetHistory()[0].sweeps, 0u);
  const auto & a = cpu->GetCurrentSimplexMesh();
  const auto & b = gpu->GetCurrentSimplexMesh();
  ASSERT_EQ(b.NumberOfNodes(), a.NumberOfNodes());
  size_t differ = 0;
  double largest = 0.0;
  for (size_t i = 0; i < a.nodes.size(); ++i)
  {
    differ += a.nodes[i] != b.nodes[i] ? 1u : 0u;
    largest = std::max(largest, std::abs(a.nodes[i] - b.nodes[i]));
  }
  EXPECT_EQ(differ, 0u) << "node coordinates differ, by up to " << largest << " mm";
  EXPECT_EQ(b.elements.size(), a.elements.size());
  EXPECT_TRUE(b.elements == a.elements) << "the elements differ";
  EXPECT_EQ(b.fixed, a.fixed);
  std::cout << D << "D: the first meshes have " << a.NumberOfNodes() << " nodes and " << a.elements.size()
            << " elements on both back-ends" << std::endl;
}

/** A run that contracts afresh every few iterations (ReinitializationInterval) agrees with the CPU's: the CUDA path
 * contracts through the filter and sweeps on its device optimiser from that state at every reinitialization too. */
template <unsigned int D>
void
ReinitializedRunMatchesCPU(unsigned int nodes, unsigned int n)
{
  auto cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, 10, n);
  auto gpu = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, 10, n);
  cpu->SetReinitializationInterval(4); // fresh contractions at iterations 5 and 9
  gpu->SetReinitializationInterval(4);
  cpu->Update();
  gpu->Update();
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(gpu->GetHistory().size(), cpu->GetHistory().size());
  for (size_t i = 0; i < cpu->GetHistory().size(); ++i)
  {
    EXPECT_EQ(gpu->GetHistory()[i].sweeps, cpu->GetHistory()[i].sweeps) << "iteration " << i + 1;
    EXPECT_EQ(gpu->GetHistory()[i].nodes, cpu->GetHistory()[i].nodes) << "iteration " << i + 1;
  }
  // the fresh contractions change the run (against the same run warm-started throughout)
  auto plain = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, 10, n);
  plain->Update();
  EXPECT_GT(MaxDifferenceInVoxels(cpu->GetDisplacementField(), plain->GetDisplacementField()), 0.0);
  const double difference = MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField());
  std::cout << D << "D, contractions at iterations 1, 5 and 9: CPU/GPU max difference " << difference << " voxel"
            << std::endl;
  EXPECT_LT(difference, 0.05);
}

/** Every elastic system solved by CG on both back-ends, the CPU's in the GPU's order (GPUOrderSolve): the runs take
 * the same solves, so their fields agree far more closely than two CGs at the default tolerance would (what is left is
 * the last bits of the MSSD sums in beta). */
template <unsigned int D>
void
GPUOrderCPURunMatchesDeviceSolves(unsigned int nodes, unsigned int iterations, unsigned int n)
{
  auto cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, iterations, n);
  auto gpu = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  cpu->SetDirectSolverMaximumDegreesOfFreedom(0);
  cpu->SetGPUOrderSolve(true);
  gpu->SetDirectSolverMaximumDegreesOfFreedom(0);
  gpu->SetDeviceSolverMinimumDegreesOfFreedom(0);
  cpu->Update();
  gpu->Update();
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(gpu->GetHistory().size(), cpu->GetHistory().size());
  for (size_t i = 0; i < cpu->GetHistory().size(); ++i)
  {
    EXPECT_TRUE(gpu->GetHistory()[i].deviceSolve) << "iteration " << i + 1;
    EXPECT_FALSE(cpu->GetHistory()[i].directSolve) << "iteration " << i + 1;
    EXPECT_EQ(gpu->GetHistory()[i].solverIterations, cpu->GetHistory()[i].solverIterations) << "iteration " << i + 1;
    EXPECT_EQ(gpu->GetHistory()[i].sweeps, cpu->GetHistory()[i].sweeps) << "iteration " << i + 1;
  }
  const double difference = MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField());
  std::cout << D << "D, every system by CG, the CPU's in the GPU's order: CPU/GPU max difference " << difference
            << " voxel" << std::endl;
  EXPECT_LT(difference, 1e-4);
}

/** The pieces one by one on a mesh from the CPU run: force (vs DensityFieldFilter), owner (vs BarycentricMap,
 * identical), nodal forces (vs BarycentricMap::Gather on the same force, identical). */
template <unsigned int D>
void
StagesAgree(unsigned int nodes, unsigned int n)
{
  auto cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, 1, n);
  cpu->Update();
  const auto & mesh = cpu->GetCurrentSimplexMesh();
  const auto * fixed = cpu->GetFixedImage();
  const auto   grid = itk::dmr::Grid<D>::FromImage(fixed);

  using DensityFilter =
    itk::DensityFieldFilter<ImageOf<D>, ImageOf<D>, itk::Image<itk::Vector<float, D>, D>, ImageOf<D>>;
  auto density = DensityFilter::New();
  density->SetFixedImage(fixed);
  density->SetMovingImage(cpu->GetMovingImage());
  density->ComputeForceFieldOff();
  density->Update();
  const auto views = itk::dmr::PyramidLevelViews<D>(density->GetPyramid(), fixed->GetDirection(), grid.numberOfPixels);
  itk::dmr::cuda::RegistrationContext context;
  ASSERT_TRUE(context.Initialize(D, grid.size.data(), grid.spacing.data(), views, nullptr).Ok());
  itk::dmr::cuda::ForceStatistics statistics;
  ASSERT_TRUE(context.ComputeForce(statistics, true).Ok());
  EXPECT_NEAR(statistics.mssd, density->GetMSSD(), 1e-9 * density->GetMSSD());
  EXPECT_NEAR(statistics.ssd, density->GetSSD(), 1e-9 * density->GetSSD());
  std::vector<float> force(grid.numberOfPixels * D);
  ASSERT_TRUE(context.DownloadForce(force.data()).Ok());
  const auto & cpuForce = density->GetGridForce();
  double       maxForce = 0.0, maxDiff = 0.0;
  for (size_t i = 0; i < force.size(); ++i)
  {
    maxForce = std::max(maxForce, std::abs(static_cast<double>(cpuForce[i])));
    maxDiff = std::max(maxDiff, std::abs(static_cast<double>(cpuForce[i]) - force[i]));
  }
  EXPECT_GT(maxForce, 0.0);
  EXPECT_LE(maxDiff, 1e-6 * maxForce);

  // the elements' set-up made on the device: BarycentricMap::ElementAffine's numbers, bit for bit
  const size_t affineSize = D * D + D;
  ASSERT_TRUE(
    context.SetMesh(mesh.nodes.data(), mesh.NumberOfNodes(), mesh.elements.front().data(), mesh.elements.size()).Ok());
  {
    std::vector<double>  affine(mesh.elements.size() * affineSize), hostAffine(affine.size());
    std::vector<int64_t> bounds(mesh.elements.size() * 2 * D), hostBounds(bounds.size());
    ASSERT_TRUE(context.DownloadElementRaster(affine.data(), bounds.data()).Ok());
    size_t nonEmpty = 0;
    for (size_t e = 0; e < mesh.elements.size(); ++e)
    {
      itk::dmr::BarycentricMap<D>::ElementAffine(grid,
                                                 mesh,
                                                 e,
                                                 hostAffine.data() + e * affineSize,
                                                 hostBounds.data() + e * 2 * D,
                                                 hostBounds.data() + e * 2 * D + D);
      nonEmpty += hostBounds[e * 2 * D] <= hostBounds[e * 2 * D + D] ? 1 : 0;
    }
    // (an element may lie between pixel rows: its box is empty, lo[0] > hi[0]; the 3D mesh here has 2 of 652)
    EXPECT_GT(nonEmpty, mesh.elements.size() / 2);
    EXPECT_EQ(std::memcmp(affine.data(), hostAffine.data(), affine.size() * sizeof(double)), 0)
      << "inverse edge matrices or first vertices differ from BarycentricMap::ElementAffine's";
    EXPECT_EQ(bounds, hostBounds) << "pixel bounding boxes differ from BarycentricMap::ElementAffine's";
  }
  // owner of every pixel: identical to the CPU rasterisation
  itk::dmr::BarycentricMap<D> bary;
  bary.Build(grid, mesh, nullptr);
  std::vector<int32_t> owner(grid.numberOfPixels);
  ASSERT_TRUE(context.DownloadElementOfPixels(owner.data()).Ok());
  size_t differ = 0;
  for (size_t p = 0; p < owner.size(); ++p)
  {
    differ += owner[p] != bary.GetElements()[p] ? 1 : 0;
  }
  EXPECT_EQ(differ, 0u) << "pixels whose owning element differs";

  // nodal forces of the same (GPU) force
  std::vector<double> gpuNodal(mesh.NumberOfNodes() * D), cpuNodal;
  ASSERT_TRUE(context.GatherForce(grid.PixelVolume(), gpuNodal.data()).Ok());
  bary.Gather(force.data(), grid.PixelVolume(), cpuNodal, nullptr);
  double maxNodal = 0.0, maxNodalDiff = 0.0;
  for (size_t i = 0; i < cpuNodal.size(); ++i)
  {
    maxNodal = std::max(maxNodal, std::abs(cpuNodal[i]));
    maxNodalDiff = std::max(maxNodalDiff, std::abs(cpuNodal[i] - gpuNodal[i]));
  }
  EXPECT_GT(maxNodal, 0.0);
  // both gathers sum in the same fixed point (dmrFixedPointGather.h) over the same float weights: identical
  EXPECT_EQ(std::memcmp(cpuNodal.data(), gpuNodal.data(), cpuNodal.size() * sizeof(double)), 0)
    << "nodal forces differ from the CPU's, by up to " << maxNodalDiff << " (largest " << maxNodal << ")";
  // deterministic: the gather's fixed-point sums and the force's per-block partials do not depend on the order in
  // which the parallel additions happen, so a second evaluation is identical bit for bit
  std::vector<double> again(gpuNodal.size());
  ASSERT_TRUE(context.GatherForce(grid.PixelVolume(), again.data()).Ok());
  EXPECT_EQ(std::memcmp(again.data(), gpuNodal.data(), again.size() * sizeof(double)), 0) << "gather not repeatable";
  itk::dmr::cuda::ForceStatistics statisticsAgain;
  ASSERT_TRUE(context.ComputeForce(statisticsAgain, true).Ok());
  EXPECT_EQ(statisticsAgain.mssd, statistics.mssd);
  EXPECT_EQ(statisticsAgain.ssd, statistics.ssd);
  EXPECT_EQ(statisticsAgain.sumSquaredForce, statistics.sumSquaredForce);
  EXPECT_EQ(statisticsAgain.inside, statistics.inside);

  ElasticSolveAgrees<D>(context, mesh);

  // RevertUpdate (the rejected step of the safeguarded iteration) restores w bit for bit, once
  std::vector<float> before(grid.numberOfPixels * D), after(grid.numberOfPixels * D);
  ASSERT_TRUE(context.DownloadField(before.data()).Ok());
  double       maxUpdate = 0.0;
  unsigned int squarings = 0;
  ASSERT_TRUE(context.ApplyUpdate(gpuNodal.data(), 2.0 / maxNodal, maxUpdate, squarings).Ok());
  EXPECT_GT(maxUpdate, 0.1);
  ASSERT_TRUE(context.DownloadField(after.data()).Ok());
  EXPECT_NE(after, before);
  // the field rotated into the physical frame on the device: FEMRegistrationMethod::WriteGridFieldToImage's floats
  {
    const auto &       direction = fixed->GetDirection();
    double             M[D * D];
    std::vector<float> expected(after.size()), physical(after.size());
    for (unsigned int r = 0; r < D; ++r)
    {
      for (unsigned int k = 0; k < D; ++k)
      {
        M[r * D + k] = direction[r][k];
      }
    }
    for (size_t p = 0; p < grid.numberOfPixels; ++p)
    {
      for (unsigned int r = 0; r < D; ++r)
      {
        double v = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          v += direction[r][k] * after[p * D + k];
        }
        expected[p * D + r] = static_cast<float>(v);
      }
    }
    ASSERT_TRUE(context.DownloadPhysicalField(M, physical.data()).Ok());
    EXPECT_EQ(std::memcmp(physical.data(), expected.data(), expected.size() * sizeof(float)), 0);
    EXPECT_NE(physical, after) << "the direction is a rotation: the frames differ";
  }
  ASSERT_TRUE(context.RevertUpdate().Ok());
  ASSERT_TRUE(context.DownloadField(after.data()).Ok());
  EXPECT_EQ(after, before);
  EXPECT_FALSE(context.RevertUpdate().Ok());

  // a mesh that does not cover the image is refused with a message, not a crash
  auto partial = mesh;
  partial.elements.resize(partial.elements.size() / 2);
  const auto status = context.SetMesh(
    partial.nodes.data(), partial.NumberOfNodes(), partial.elements.front().data(), partial.elements.size());
  EXPECT_FALSE(status.Ok());
  EXPECT_NE(status.message.find("not covered"), std::string::npos) << status.message;
  // an element with a node id out of range is refused before anything is uploaded
  auto bad = mesh;
  bad.elements[bad.elements.size() / 2][1] = static_cast<int32_t>(bad.NumberOfNodes());
  const auto badStatus =
    context.SetMesh(bad.nodes.data(), bad.NumberOfNodes(), bad.elements.front().data(), bad.elements.size());
  EXPECT_FALSE(badStatus.Ok());
  EXPECT_NE(badStatus.message.find("does not exist"), std::string::npos) << badStatus.message;

  // the force under a non-zero field, with both gradient rules (the warped moving gradient reads grad w): a smooth
  // swirl of a few pixels, given to the CPU filter in the physical frame and to the context in the grid frame
  using FieldType = itk::Image<itk::Vector<float, D>, D>;
  auto field = FieldType::New();
  field->CopyInformation(fixed);
  field->SetRegions(fixed->GetLargestPossibleRegion());
  field->Allocate();
  std::vector<float> gridField(grid.numberOfPixels * D);
  const auto &       direction = fixed->GetDirection();
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    for (unsigned int k = 0; k < D; ++k)
    {
      gridField[p * D + k] = static_cast<float>(3.0 * std::sin(0.11 * static_cast<double>(idx[(k + 1) % D]) + 0.7 * k) *
                                                std::cos(0.07 * static_cast<double>(idx[k])));
    }
    for (unsigned int m = 0; m < D; ++m)
    {
      double v = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        v += direction[m][k] * gridField[p * D + k];
      }
      field->GetBufferPointer()[p][m] = static_cast<float>(v);
    }
  }
  ASSERT_TRUE(context.UploadField(gridField.data()).Ok());
  density->SetDisplacementField(field);
  std::vector<float> forceOf[2];
  for (const bool warped : { true, false })
  {
    density->SetForceGradient(warped ? itk::DynamicMeshRegistrationEnums::ForceGradient::WarpedMoving
                                     : itk::DynamicMeshRegistrationEnums::ForceGradient::MappedMoving);
    density->Update();
    ASSERT_TRUE(context.ComputeForce(statistics, warped).Ok());
    EXPECT_NEAR(statistics.mssd, density->GetMSSD(), 1e-6 * density->GetMSSD());
    std::vector<float> & gpu = forceOf[warped ? 0 : 1];
    gpu.resize(grid.numberOfPixels * D);
    ASSERT_TRUE(context.DownloadForce(gpu.data()).Ok());
    const auto & cpu = density->GetGridForce();
    double       largest = 0.0, largestDiff = 0.0;
    for (size_t i = 0; i < gpu.size(); ++i)
    {
      largest = std::max(largest, std::abs(static_cast<double>(cpu[i])));
      largestDiff = std::max(largestDiff, std::abs(static_cast<double>(cpu[i]) - gpu[i]));
    }
    EXPECT_GT(largest, 0.0);
    EXPECT_LE(largestDiff, 1e-5 * largest) << (warped ? "warped" : "mapped") << " moving gradient";
  }
  // the two rules differ under this field (the flag reaches the kernel)
  double largest = 0.0, largestDiff = 0.0;
  for (size_t i = 0; i < forceOf[0].size(); ++i)
  {
    largest = std::max(largest, std::abs(static_cast<double>(forceOf[0][i])));
    largestDiff = std::max(largestDiff, std::abs(static_cast<double>(forceOf[0][i]) - forceOf[1][i]));
  }
  EXPECT_GT(largestDiff, 0.05 * largest);
}

/** The pyramid the device builds at Initialize from an incomplete one (DensityFieldFilter::GetPyramid(false), as the
 * registration passes it: level 0's images and the plans) is the CPU's complete pyramid bit for bit: every level's
 * fixed and moving image (dmr::GaussianShrink) and moving gradient (GradientInto). A moving image of another size and
 * direction than the fixed image (R is a real rotation), anisotropic spacing, odd sizes, and `thin` pixels along the
 * last axis (no shrink there, one-sided differences; a level of one pixel when thin is 1). */
template <unsigned int D>
void
DevicePyramidEqualsCPU(unsigned int n, unsigned int thin)
{
  const double c[3] = { 0.45 * n, 0.5 * n, 0.45 * n }, r[3] = { 0.3 * n, 0.22 * n, 0.25 * n };
  auto         fixed = Blob<D>(n, c, r);
  auto         moving = Blob<D>(n + 3, c, r);
  if (thin > 0)
  {
    for (auto * image : { &fixed, &moving })
    {
      auto size = (*image)->GetLargestPossibleRegion().GetSize();
      size[D - 1] = thin;
      auto cut = ImageOf<D>::New();
      cut->CopyInformation(*image);
      cut->SetRegions(size);
      cut->Allocate();
      itk::ImageRegionIteratorWithIndex<ImageOf<D>> it(cut, cut->GetLargestPossibleRegion());
      for (it.GoToBegin(); !it.IsAtEnd(); ++it)
      {
        it.Set((*image)->GetPixel(it.GetIndex()));
      }
      *image = cut;
    }
  }
  auto         direction = moving->GetDirection();
  const double a = -0.6; // moving rotated the other way round than the fixed image (Blob: +0.35)
  direction(0, 0) = std::cos(a);
  direction(0, 1) = -std::sin(a);
  direction(1, 0) = std::sin(a);
  direction(1, 1) = std::cos(a);
  moving->SetDirection(direction);

  using DensityFilter =
    itk::DensityFieldFilter<ImageOf<D>, ImageOf<D>, itk::Image<itk::Vector<float, D>, D>, ImageOf<D>>;
  auto density = DensityFilter::New();
  density->SetFixedImage(fixed);
  density->SetMovingImage(moving);
  const auto                          grid = itk::dmr::Grid<D>::FromImage(fixed.GetPointer());
  itk::dmr::cuda::RegistrationContext context;
  {
    const auto views =
      itk::dmr::PyramidLevelViews<D>(density->GetPyramid(false), fixed->GetDirection(), grid.numberOfPixels);
    ASSERT_EQ(views.size(), 3u);
    for (size_t l = 0; l < views.size(); ++l)
    {
      ASSERT_EQ(views[l].movingGradient, nullptr);
      ASSERT_EQ(views[l].fixed == nullptr, l > 0);
      ASSERT_EQ(views[l].moving == nullptr, l > 0);
    }
    ASSERT_TRUE(context.Initialize(D, grid.size.data(), grid.spacing.data(), views, nullptr).Ok());
  }
  const auto & pyramid = density->GetPyramid(true); // rebuilt, complete, on the CPU
  EXPECT_GT(std::abs(pyramid[0].R[0][1]), 0.5) << "the moving and fixed grid frames should differ";
  EXPECT_LT(pyramid[2].movingGrid.numberOfPixels, pyramid[0].movingGrid.numberOfPixels / (thin > 0 ? 2 : 8));
  auto countDifferent = [](const std::vector<float> & cpu, const std::vector<float> & gpu) {
    size_t differ = 0;
    for (size_t i = 0; i < cpu.size(); ++i)
    {
      differ += std::memcmp(&cpu[i], &gpu[i], sizeof(float)) != 0 ? 1 : 0;
    }
    return differ;
  };
  for (unsigned int l = 0; l < pyramid.size(); ++l)
  {
    const auto & L = pyramid[l];
    ASSERT_EQ(L.fixed.size(), L.fixedGrid.numberOfPixels);
    ASSERT_EQ(L.moving.size(), L.movingGrid.numberOfPixels);
    ASSERT_EQ(L.movingGradient.size(), L.movingGrid.numberOfPixels * D);
    std::vector<float> f(L.fixed.size()), m(L.moving.size()), g(L.movingGradient.size());
    ASSERT_TRUE(context.DownloadLevel(l, f.data(), m.data(), g.data()).Ok());
    EXPECT_EQ(countDifferent(L.fixed, f), 0u) << "level " << l << ": fixed floats that differ from the CPU's";
    EXPECT_EQ(countDifferent(L.moving, m), 0u) << "level " << l << ": moving floats that differ from the CPU's";
    EXPECT_EQ(countDifferent(L.movingGradient, g), 0u) << "level " << l << ": gradient floats that differ";
    double largest = 0.0;
    for (const float x : L.movingGradient)
    {
      largest = std::max(largest, std::abs(static_cast<double>(x)));
    }
    EXPECT_GT(largest, 0.0) << "level " << l;
  }
  float none = 0.0f;
  EXPECT_FALSE(context.DownloadLevel(static_cast<unsigned int>(pyramid.size()), &none, nullptr, nullptr).Ok());
}
/** The pair with both images multiplied by 2^70 and by 2^-70 (beyond single precision's |f|^2 without the density
 * filter's intensity scale) on the GPU: the fields of the unscaled pair on the GPU, energies in the images' units. */
template <unsigned int D>
void
IntensityUnitDoesNotChangeTheRun(unsigned int nodes, unsigned int iterations, unsigned int n, bool deviceSolve)
{
  auto reference = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  if (deviceSolve)
  {
    reference->SetDeviceSolverMinimumDegreesOfFreedom(0);
  }
  reference->Update();
  for (const int exponent : { 70, -70 })
  {
    auto method = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
    method->SetFixedImage(itk::dmr::test::ScaledByPowerOfTwo(reference->GetFixedImage(), exponent));
    method->SetMovingImage(itk::dmr::test::ScaledByPowerOfTwo(reference->GetMovingImage(), exponent));
    if (deviceSolve)
    {
      method->SetDeviceSolverMinimumDegreesOfFreedom(0);
    }
    ASSERT_NO_THROW(method->Update()) << exponent;
    EXPECT_EQ(method->GetBackendUsed(), Backend::CUDA);
    const double difference = MaxDifferenceInVoxels(reference->GetDisplacementField(), method->GetDisplacementField());
    std::cout << "2^" << exponent << " x intensities: field difference " << difference << " voxel, SSD "
              << method->GetFinalSSD() << " = 2^" << 2 * exponent << " x "
              << std::ldexp(method->GetFinalSSD(), -2 * exponent) << " (unscaled " << reference->GetFinalSSD() << ")"
              << std::endl;
    EXPECT_LT(difference, 1e-4) << exponent;
    const double energyUnit = std::ldexp(1.0, 2 * exponent);
    EXPECT_NEAR(
      method->GetFinalSSD(), reference->GetFinalSSD() * energyUnit, 1e-6 * reference->GetFinalSSD() * energyUnit);
    EXPECT_NEAR(method->GetBeta(), reference->GetBeta() * energyUnit, 1e-6 * reference->GetBeta() * energyUnit);
    ASSERT_EQ(method->GetHistory().size(), reference->GetHistory().size());
    EXPECT_NEAR(method->GetHistory().front().ssd,
                reference->GetHistory().front().ssd * energyUnit,
                1e-6 * reference->GetHistory().front().ssd * energyUnit);
  }
  EXPECT_LT(reference->GetFinalSSD(), 0.8 * reference->GetHistory().front().ssd); // it registered
}

/** A mask on the fixed image's grid: the pixels beyond a quarter of the first axis inside, with the value 7 (any
 * value but 0 is inside, on both back-ends). */
template <unsigned int D>
typename MethodOf<D>::MaskImageType::Pointer
SlabMask(const ImageOf<D> * fixed, unsigned int n)
{
  using MaskType = typename MethodOf<D>::MaskImageType;
  auto mask = MaskType::New();
  mask->CopyInformation(fixed);
  mask->SetRegions(fixed->GetLargestPossibleRegion());
  mask->Allocate();
  itk::ImageRegionIteratorWithIndex<MaskType> it(mask, mask->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    it.Set(it.GetIndex()[0] > static_cast<itk::IndexValueType>(n / 4) ? 7 : 0);
  }
  return mask;
}

/** A run with a fixed mask (values 0 and 7) agrees with the CPU's: the device reads the mask's own bytes, non-zero
 * inside, as the CPU path does. */
template <unsigned int D>
void
MaskedRunMatchesCPU(unsigned int nodes, unsigned int iterations, unsigned int n)
{
  auto       cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, iterations, n);
  auto       gpu = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  const auto mask = SlabMask<D>(cpu->GetFixedImage(), n);
  cpu->SetFixedMask(mask);
  gpu->SetFixedMask(mask);
  auto unmasked = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  cpu->Update();
  gpu->Update();
  unmasked->Update();
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(gpu->GetHistory().size(), cpu->GetHistory().size());
  for (size_t i = 0; i < cpu->GetHistory().size(); ++i)
  {
    EXPECT_EQ(gpu->GetHistory()[i].nodes, cpu->GetHistory()[i].nodes) << "iteration " << i + 1;
    EXPECT_EQ(gpu->GetHistory()[i].sweeps, cpu->GetHistory()[i].sweeps) << "iteration " << i + 1;
    EXPECT_NEAR(gpu->GetHistory()[i].mssd, cpu->GetHistory()[i].mssd, 1e-6 * cpu->GetHistory()[i].mssd)
      << "iteration " << i + 1;
  }
  const double difference = MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField());
  std::cout << D << "D with a mask: CPU/GPU max difference " << difference << " voxel" << std::endl;
  EXPECT_LT(difference, 0.05);
  // the mask matters: the first iteration's MSSD counts only the pixels inside
  EXPECT_LT(gpu->GetHistory().front().mssd, 0.99 * unmasked->GetHistory().front().mssd);
}

/** Iteration 1's contraction made on the CPU ahead of the device (AlwaysContractOnHost: the CPU path's density, its
 * block sums and merges) is taken, as the device's block sums of its own density equal the host's, and the run is the
 * one the device's own contraction gives, bit for bit; with a fixed mask too (the density outside it is alpha on both
 * back-ends). The images have a rotated direction, anisotropic spacing and an origin away from 0. */
template <unsigned int D>
void
HostContractionGivesTheSameRun(unsigned int nodes, unsigned int iterations, unsigned int n, bool masked)
{
  SCOPED_TRACE(std::to_string(D) + (masked ? "D, masked" : "D"));
  auto ahead = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  auto device = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  if (masked)
  {
    const auto mask = SlabMask<D>(ahead->GetFixedImage(), n);
    ahead->SetFixedMask(mask);
    device->SetFixedMask(mask);
  }
  EXPECT_FALSE(ahead->GetAlwaysContractOnHost()); // the default
  ahead->AlwaysContractOnHostOn();
  ahead->Update();
  device->Update();
  ASSERT_EQ(ahead->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(device->GetBackendUsed(), Backend::CUDA);
  EXPECT_TRUE(ahead->GetContractedOnHost()) << "the device's block sums differ from the host's";
  ASSERT_EQ(ahead->GetHistory().size(), device->GetHistory().size());
  for (size_t i = 0; i < ahead->GetHistory().size(); ++i)
  {
    EXPECT_EQ(ahead->GetHistory()[i].sweeps, device->GetHistory()[i].sweeps) << "iteration " << i + 1;
    EXPECT_EQ(ahead->GetHistory()[i].mssd, device->GetHistory()[i].mssd) << "iteration " << i + 1;
  }
  const auto * a = ahead->GetDisplacementField();
  const auto * b = device->GetDisplacementField();
  const size_t bytes = a->GetLargestPossibleRegion().GetNumberOfPixels() * sizeof(a->GetBufferPointer()[0]);
  EXPECT_EQ(std::memcmp(a->GetBufferPointer(), b->GetBufferPointer(), bytes), 0) << "the fields differ";
  EXPECT_LT(ahead->GetFinalSSD(), 0.8 * ahead->GetHistory().front().ssd); // it registered
  // the same method run again on the CPU does not report the earlier run's contraction
  ahead->SetBackend(Backend::CPU);
  ahead->SetNumberOfIterations(1);
  ahead->Update();
  ASSERT_EQ(ahead->GetBackendUsed(), Backend::CPU);
  EXPECT_FALSE(ahead->GetContractedOnHost());
}
} // namespace

TEST(CudaRegistration, DevicePyramidEqualsCPU2D)
{
  DMR_REQUIRE_DEVICE();
  DevicePyramidEqualsCPU<2>(97, 0);
  DevicePyramidEqualsCPU<2>(97, 3);
}

TEST(CudaRegistration, DevicePyramidEqualsCPU3D)
{
  DMR_REQUIRE_DEVICE();
  DevicePyramidEqualsCPU<3>(41, 0);
  DevicePyramidEqualsCPU<3>(41, 1);
}

TEST(CudaRegistration, FirstMeshIsTheCPUs2D)
{
  DMR_REQUIRE_DEVICE();
  FirstMeshIsTheCPUs<2>(40, 96);
}

TEST(CudaRegistration, FirstMeshIsTheCPUs3D)
{
  DMR_REQUIRE_DEVICE();
  FirstMeshIsTheCPUs<3>(150, 40);
}

TEST(CudaRegistration, ReinitializedRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  ReinitializedRunMatchesCPU<2>(40, 96);
}

TEST(CudaRegistration, ReinitializedRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  ReinitializedRunMatchesCPU<3>(150, 40);
}

TEST(CudaRegistration, GPUOrderCPURunMatchesDeviceSolves2D)
{
  DMR_REQUIRE_DEVICE();
  GPUOrderCPURunMatchesDeviceSolves<2>(40, 60, 96);
}

TEST(CudaRegistration, GPUOrderCPURunMatchesDeviceSolves3D)
{
  DMR_REQUIRE_DEVICE();
  GPUOrderCPURunMatchesDeviceSolves<3>(150, 30, 40);
}

TEST(CudaRegistration, StagesAgreeWithCPU2D)
{
  DMR_REQUIRE_DEVICE();
  StagesAgree<2>(40, 96);
}

TEST(CudaRegistration, StagesAgreeWithCPU3D)
{
  DMR_REQUIRE_DEVICE();
  StagesAgree<3>(150, 40);
}

TEST(CudaRegistration, DynamicMeshRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<2>(MeshMode::Dynamic, 40, 60, 96);
}

// 30 times the usual step: the safeguard halves about half of the steps (GPU: RevertUpdate) and both back-ends must
// take the same ones
TEST(CudaRegistration, SafeguardedStepsMatchCPU2D)
{
  DMR_REQUIRE_DEVICE();
  size_t halved = 0;
  RunsAgree<2>(MeshMode::Dynamic, 40, 40, 96, 3.0, &halved);
  EXPECT_GT(halved, 5u);
}

namespace
{
/** ComputeInverse on both back-ends: the same inverse field (the device carries it with the CPU's rule), which
 * undoes the forward field; the forward field is the one of a run without the inverse. energyRatio 3.0 makes the
 * safeguard halve steps (the inverse must follow the accepted step only). */
template <unsigned int D>
void
InversesAgree(unsigned int nodes, unsigned int iterations, unsigned int n, double energyRatio)
{
  auto cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, iterations, n, energyRatio);
  auto gpu = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n, energyRatio);
  auto plain = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n, energyRatio);
  cpu->ComputeInverseOn();
  gpu->ComputeInverseOn();
  cpu->Update();
  gpu->Update();
  plain->Update();
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_NE(cpu->GetInverseDisplacementField(), nullptr);
  ASSERT_NE(gpu->GetInverseDisplacementField(), nullptr);
  EXPECT_EQ(plain->GetInverseDisplacementField(), nullptr);
  size_t halved = 0;
  for (const auto & r : gpu->GetHistory())
  {
    halved += r.stepScale < 1.0 ? 1 : 0;
  }
  const double inverseDifference =
    MaxDifferenceInVoxels(cpu->GetInverseDisplacementField(), gpu->GetInverseDisplacementField());
  const double forwardDifference = MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField());
  const double plainDifference = MaxDifferenceInVoxels(plain->GetDisplacementField(), gpu->GetDisplacementField());
  const auto   consistency =
    dmrtools::InverseConsistency(gpu->GetDisplacementField(), gpu->GetInverseDisplacementField(), nullptr).first;
  double h = gpu->GetDisplacementField()->GetSpacing()[0];
  double maxV = 0.0;
  for (size_t p = 0; p < gpu->GetDisplacementField()->GetLargestPossibleRegion().GetNumberOfPixels(); ++p)
  {
    maxV = std::max(maxV, static_cast<double>(gpu->GetInverseDisplacementField()->GetBufferPointer()[p].GetNorm()));
  }
  std::cout << D << "D inverse: max |v| " << maxV << " mm, CPU/GPU max difference " << inverseDifference
            << " voxel (forward " << forwardDifference << ", against a run without the inverse " << plainDifference
            << "); |u(x) + v(x + u(x))| mean " << consistency.mean << " max " << consistency.max << " mm; " << halved
            << " steps halved" << std::endl;
  EXPECT_GT(maxV, 1.0);
  EXPECT_LT(inverseDifference, 0.05);
  EXPECT_LT(forwardDifference, 0.05);
  EXPECT_EQ(plainDifference, 0.0);       // the inverse does not change the registration
  EXPECT_LT(consistency.mean, 0.25 * h); // 2D at 30 times the usual step: 0.125 voxel; 3D: 0.012 voxel
  if (energyRatio > 1.0)
  {
    EXPECT_GT(halved, 3u);
  }
}
} // namespace

TEST(CudaRegistration, InverseMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  InversesAgree<2>(40, 40, 96, 3.0);
}

TEST(CudaRegistration, InverseMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  InversesAgree<3>(150, 20, 40, 0.1);
}

// the elastic systems solved on the device (matrix-free CG) instead of the CPU: the same runs
TEST(CudaRegistration, DeviceSolveRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<2>(MeshMode::Dynamic, 40, 60, 96, 0.1, nullptr, true);
}

// device solves stopped after 3 products: the CPU solver takes over (a dynamic mesh: every iteration's system; a
// regular mesh: its one system, assembled on the CPU at the first fallback and kept), and the runs still agree
TEST(CudaRegistration, DeviceSolveFallbackRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<2>(MeshMode::Dynamic, 40, 30, 96, 0.1, nullptr, true, 3);
}

TEST(CudaRegistration, DeviceSolveFallbackRegularMeshRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<3>(MeshMode::Regular, 125, 20, 40, 0.1, nullptr, true, 3);
}

TEST(CudaRegistration, DeviceSolveRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<3>(MeshMode::Dynamic, 150, 30, 40, 0.1, nullptr, true);
}

// a looser stopping rule reaches the device solve: fewer products, and still the CPU's run at that tolerance
TEST(CudaRegistration, DeviceSolveFollowsTheSolverTolerance3D)
{
  DMR_REQUIRE_DEVICE();
  size_t tight = 0, loose = 0;
  RunsAgree<3>(MeshMode::Dynamic, 150, 20, 40, 0.1, nullptr, true, 0, 1e-12, &tight);
  RunsAgree<3>(MeshMode::Dynamic, 150, 20, 40, 0.1, nullptr, true, 0, 1e-6, &loose);
  std::cout << "device CG products: " << tight << " at 1e-12, " << loose << " at 1e-6" << std::endl;
  EXPECT_LT(static_cast<double>(loose), 0.8 * static_cast<double>(tight));
}

TEST(CudaRegistration, DeviceSolveRegularMeshRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<3>(MeshMode::Regular, 125, 30, 40, 0.1, nullptr, true);
}

/** A fixed image whose region does not start at 0 and a moving image on another grid (another start, size, spacing
 * and origin): both back-ends sample the moving pyramid through the same maps, so the runs still agree. */
template <unsigned int D>
void
ShiftedAndOtherGridRunsAgree(unsigned int nodes, unsigned int iterations, unsigned int n)
{
  const double                   cf[3] = { 0.45 * n, 0.5 * n, 0.45 * n }, rf[3] = { 0.3 * n, 0.22 * n, 0.25 * n };
  const double                   cm[3] = { 0.55 * n, 0.5 * n, 0.5 * n }, rm[3] = { 0.24 * n, 0.25 * n, 0.2 * n };
  auto                           fixed = Blob<D>(n, cf, rf);
  typename ImageOf<D>::IndexType fixedStart, movingStart;
  for (unsigned int k = 0; k < D; ++k)
  {
    fixedStart[k] = k == 0 ? 7 : -3 - static_cast<int>(k);
    movingStart[k] = k == 1 ? 4 : -5;
  }
  itk::dmr::test::ShiftRegionStart(fixed.GetPointer(), fixedStart);
  auto moving = Blob<D>(n + 6, cm, rm);
  auto region = moving->GetLargestPossibleRegion();
  region.SetIndex(movingStart);
  moving->SetRegions(region);
  auto spacing = moving->GetSpacing();
  auto origin = moving->GetOrigin();
  for (unsigned int k = 0; k < D; ++k)
  {
    spacing[k] *= 1.1;
    origin[k] += 5.0 + k;
  }
  moving->SetSpacing(spacing);
  moving->SetOrigin(origin);
  std::array<typename MethodOf<D>::Pointer, 2> runs;
  for (int b = 0; b < 2; ++b)
  {
    runs[b] = MethodOf<D>::New();
    runs[b]->SetFixedImage(fixed);
    runs[b]->SetMovingImage(moving);
    runs[b]->SetNumberOfNodes(nodes);
    runs[b]->SetNumberOfIterations(iterations);
    runs[b]->SetEnergyRatio(0.1);
    runs[b]->SetMaximumNumberOfSweeps(50);
    runs[b]->SetBackend(b == 0 ? Backend::CPU : Backend::CUDA);
    runs[b]->Update();
  }
  ASSERT_EQ(runs[1]->GetBackendUsed(), Backend::CUDA);
  const auto * field = runs[1]->GetDisplacementField();
  EXPECT_EQ(field->GetLargestPossibleRegion(), fixed->GetLargestPossibleRegion());
  const double difference = MaxDifferenceInVoxels(runs[0]->GetDisplacementField(), field);
  std::cout << D << "D shifted/other grid: SSD " << runs[0]->GetHistory().front().ssd << " -> CPU "
            << runs[0]->GetFinalSSD() << ", GPU " << runs[1]->GetFinalSSD() << ", max difference " << difference
            << " voxel" << std::endl;
  EXPECT_LT(difference, 0.05);
  EXPECT_NEAR(runs[1]->GetFinalSSD(), runs[0]->GetFinalSSD(), 1e-3 * runs[0]->GetFinalSSD());
  EXPECT_LT(runs[1]->GetFinalSSD(), 0.5 * runs[1]->GetHistory().front().ssd);
}

/** A smooth initial field (a swirl-free sine displacement of up to 0.1 n mm, physical frame, on the rotated fixed
 * grid): both back-ends start from it (the CPU through the field image, the GPU by one upload) and agree. */
template <unsigned int D>
void
InitialFieldRunsAgree(unsigned int nodes, unsigned int iterations, unsigned int n)
{
  auto cpu = Registration<D>(Backend::CPU, MeshMode::Dynamic, nodes, iterations, n);
  auto gpu = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, iterations, n);
  auto without = Registration<D>(Backend::CUDA, MeshMode::Dynamic, nodes, 1, n);
  using FieldType = typename MethodOf<D>::DisplacementFieldType;
  auto field = FieldType::New();
  field->CopyInformation(cpu->GetFixedImage());
  field->SetRegions(cpu->GetFixedImage()->GetLargestPossibleRegion());
  field->Allocate();
  itk::ImageRegionIteratorWithIndex<FieldType> it(field, field->GetLargestPossibleRegion());
  for (it.GoToBegin(); !it.IsAtEnd(); ++it)
  {
    typename FieldType::PixelType u;
    for (unsigned int k = 0; k < D; ++k)
    {
      u[k] = static_cast<float>(0.1 * n * std::sin(3.14159 * it.GetIndex()[(k + 1) % D] / n) * (k == 0 ? 1.0 : -0.5));
    }
    it.Set(u);
  }
  cpu->SetInitialDisplacementField(field);
  gpu->SetInitialDisplacementField(field);
  cpu->Update();
  gpu->Update();
  without->Update();
  ASSERT_EQ(gpu->GetBackendUsed(), Backend::CUDA);
  ASSERT_EQ(gpu->GetHistory().size(), cpu->GetHistory().size());
  const double difference = MaxDifferenceInVoxels(cpu->GetDisplacementField(), gpu->GetDisplacementField());
  std::cout << D << "D with an initial field: SSD " << cpu->GetHistory().front().ssd << " (without it "
            << without->GetHistory().front().ssd << ") -> CPU " << cpu->GetFinalSSD() << ", GPU " << gpu->GetFinalSSD()
            << ", max difference " << difference << " voxel" << std::endl;
  // the field is really where both start
  EXPECT_GT(std::abs(cpu->GetHistory().front().ssd - without->GetHistory().front().ssd),
            0.05 * without->GetHistory().front().ssd);
  for (size_t i = 0; i < cpu->GetHistory().size(); ++i)
  {
    const auto & c = cpu->GetHistory()[i];
    const auto & g = gpu->GetHistory()[i];
    EXPECT_NEAR(g.mssd, c.mssd, 1e-6 * c.mssd) << "iteration " << i + 1;
    EXPECT_EQ(g.stepScale, c.stepScale) << "iteration " << i + 1;
    EXPECT_EQ(g.sweeps, c.sweeps) << "iteration " << i + 1;
  }
  EXPECT_LT(difference, 0.05);
  EXPECT_NEAR(gpu->GetFinalSSD(), cpu->GetFinalSSD(), 1e-3 * cpu->GetFinalSSD());
  EXPECT_LT(gpu->GetFinalSSD(), 0.5 * gpu->GetHistory().front().ssd);
}

TEST(CudaRegistration, InitialFieldRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  InitialFieldRunsAgree<2>(40, 40, 96);
}

TEST(CudaRegistration, InitialFieldRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  InitialFieldRunsAgree<3>(150, 20, 40);
}

TEST(CudaRegistration, ShiftedRegionsAndMovingOnAnotherGridMatchCPU2D)
{
  DMR_REQUIRE_DEVICE();
  ShiftedAndOtherGridRunsAgree<2>(40, 40, 96);
}

TEST(CudaRegistration, ShiftedRegionsAndMovingOnAnotherGridMatchCPU3D)
{
  DMR_REQUIRE_DEVICE();
  ShiftedAndOtherGridRunsAgree<3>(150, 20, 40);
}

TEST(CudaRegistration, RegularMeshRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<2>(MeshMode::Regular, 49, 60, 96);
}

TEST(CudaRegistration, DynamicMeshRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<3>(MeshMode::Dynamic, 150, 30, 40);
}

TEST(CudaRegistration, RegularMeshRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  RunsAgree<3>(MeshMode::Regular, 125, 30, 40);
}

TEST(CudaRegistration, TheIntensityUnitDoesNotChangeTheRegistration2D)
{
  DMR_REQUIRE_DEVICE();
  IntensityUnitDoesNotChangeTheRun<2>(40, 30, 96, false);
}

TEST(CudaRegistration, TheIntensityUnitDoesNotChangeTheRegistration3D)
{
  DMR_REQUIRE_DEVICE();
  IntensityUnitDoesNotChangeTheRun<3>(150, 20, 40, true);
}

TEST(CudaRegistration, HostContractionGivesTheSameRun2D)
{
  DMR_REQUIRE_DEVICE();
  HostContractionGivesTheSameRun<2>(40, 20, 96, false);
  HostContractionGivesTheSameRun<2>(40, 20, 96, true);
}

TEST(CudaRegistration, HostContractionGivesTheSameRun3D)
{
  DMR_REQUIRE_DEVICE();
  HostContractionGivesTheSameRun<3>(150, 10, 40, false);
  HostContractionGivesTheSameRun<3>(150, 10, 40, true);
}

TEST(CudaRegistration, MaskedRunMatchesCPU2D)
{
  DMR_REQUIRE_DEVICE();
  MaskedRunMatchesCPU<2>(40, 20, 96);
}

TEST(CudaRegistration, MaskedRunMatchesCPU3D)
{
  DMR_REQUIRE_DEVICE();
  MaskedRunMatchesCPU<3>(150, 10, 40);
}
