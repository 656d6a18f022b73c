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
#ifndef dmrRegistrationBackend_h
#define dmrRegistrationBackend_h

#include "dmrCudaBackend.h"
#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

/** Plain C++ launcher API of the GPU registration iteration (STYLE.md section 4): no CUDA or ITK types. Kernels in
 * Registration/cuda/dmrRegistrationBackend.cu, stub in Registration/src/dmrRegistrationCudaStub.cxx. */
namespace itk
{
namespace dmr
{
namespace cuda
{
/** How a pyramid level's image is made from level 0's (dmr::GaussianShrinkPlan): per axis the kept level-0 positions
 * (one per level pixel along the axis) and the Gaussian coefficients (`width` of them, an odd number); the passes run
 * along the last axis first. */
struct ShrinkView
{
  const int64_t * kept[3]{ nullptr, nullptr, nullptr };
  const double *  coefficients[3]{ nullptr, nullptr, nullptr };
  size_t          width[3]{ 0, 0, 0 };
};

/** One pyramid level as the CPU path holds it (DensityFieldFilter::PyramidLevel), by host pointers; only the first
 * `dimension` entries of every array are read. Images the view does not hold are built on the device, the same floats
 * as the CPU's: a level's fixed or moving image from level 0's by its ShrinkView (level 0 must hold both), and the
 * moving gradient from the level's moving image, movingSpacing and R. */
struct PyramidLevelView
{
  size_t        fixedSize[3]{ 1, 1, 1 };
  size_t        movingSize[3]{ 1, 1, 1 };
  const float * fixed{ nullptr }; // level 0: the fixed image itself, on the registration grid
  const float * moving{ nullptr };
  const float * movingGradient{ nullptr }; // D interleaved, per mm, rotated into the fixed grid frame
  ShrinkView    fixedShrink, movingShrink; // read where fixed or moving is nullptr
  double        movingSpacing[3]{ 1.0, 1.0, 1.0 };
  double        R[3][3]{};  // moving grid frame -> fixed grid frame (DensityFieldFilter::PyramidLevel)
  double        FA[3][3]{}; // fixed-level continuous index = FA fineIndex + Fc
  double        Fc[3]{};
  double        MA[3][3]{}; // moving-level continuous index = MA fineIndex + Mc + MB u, u = float(Direction w)
  double        Mc[3]{};
  double        MB[3][3]{};        // per mm of the physical-frame displacement u (DensityFieldFilter::PyramidLevel)
  double        direction[3][3]{}; // the fixed image's direction (every level the same): u = Direction w, rounded to
                                   // float per component as the CPU path's field image holds it
  double weight{ 1.0 };            // MSSD weight of the level (paper Eq. 3)
};

/** Sums of one force evaluation (paper Eq. 3 and 5), before the pixel volume factor. */
struct ForceStatistics
{
  double mssd{ 0 };
  double ssd{ 0 };
  double sumSquaredForce{ 0 };
  size_t inside{ 0 };
};

/** The device-resident state of one registration: pyramids, mask, the current field w (grid frame, mm), force,
 * density, the update fields and the barycentric owner of every pixel. One instance per GenerateData(); all
 * per-pixel data stay on the device between calls, only nodal vectors and scalars cross. */
class DynamicMeshRegistration_EXPORT RegistrationContext
{
public:
  RegistrationContext();
  ~RegistrationContext();
  RegistrationContext(const RegistrationContext &) = delete;
  RegistrationContext &
  operator=(const RegistrationContext &) = delete;

  /** Uploads the pyramid and the mask (nullptr: every pixel), allocates the per-pixel fields and sets w = 0. What the
   * views do not hold is built on the device (see PyramidLevelView): the floats of dmr::GaussianShrink and
   * dmr::GradientInto, bit for bit. */
  Status
  Initialize(unsigned int                          dimension,
             const size_t *                        size,
             const double *                        spacing,
             const std::vector<PyramidLevelView> & levels,
             const uint8_t *                       mask);

  /** Force f of the fixed image vs the moving image warped by w, summed over the levels (grid frame), and
   * |f|^2 into the density buffer (0 outside the mask). warpedGradient: the gradient of the warped moving image,
   * (I + grad w)^T (grad S)(W(x)), as DensityFieldFilter's ForceGradient::WarpedMoving; otherwise (grad S)(W(x)). */
  Status
  ComputeForce(ForceStatistics & statistics, bool warpedGradient);
  /** density += alpha at every pixel (paper Eq. 9). */
  Status
  AddToDensity(double alpha);
  /** Device pointer of the density (numberOfPixels floats), for the GPU CVT. */
  const float *
  DeviceDensity() const;
  /** Host copy of the density (used where a CPU stage needs it, e.g. the initial contraction). */
  Status
  DownloadDensity(float * host) const;
  /** Host copy of the grid-frame force (numberOfPixels x dimension floats). */
  Status
  DownloadForce(float * host) const;

  /** Host copies of pyramid level `level` as the device holds it (uploaded or built there): its fixed and moving
   * images (the level's pixels each) and the moving gradient (moving pixels x dimension floats); nullptr: not read. */
  Status
  DownloadLevel(unsigned int level, float * fixed, float * moving, float * movingGradient) const;

  /** Uploads a simplex mesh and rasterises it: every pixel gets the lowest-id element containing it (the CPU
   * BarycentricMap rule, same per-pixel test). nodes: grid frame, mm; elements: dimension+1 node ids each. The
   * elements' rasterisation set-up (inverse edge matrix, first vertex, pixel bounding box) is computed on the device
   * with BarycentricMap::ElementAffine's arithmetic (dmrSimplexGeometry.h). Fails when an element refers to a node that
   * does not exist or when a pixel is not covered. */
  Status
  SetMesh(const double * nodes, size_t numberOfNodes, const int32_t * elements, size_t numberOfElements);
  /** Test hook: host copies of the last SetMesh's rasterisation set-up, per element the inverse edge matrix (D x D,
   * row-major) then the first vertex (D) into affine, and the pixel bounding box lo[D], hi[D] into bounds (empty when
   * lo[0] > hi[0]): what BarycentricMap::ElementAffine gives for the same mesh. */
  Status
  DownloadElementRaster(double * affine, int64_t * bounds) const;
  /** Prepares the linear-elastic system of the mesh of the last SetMesh() for SolveElasticity(): the system of
   * LinearElasticFEMSolver (P1, Lame lambda and mu, grid frame in mm, u = 0 on the nodes flagged in `fixed`), kept
   * matrix-free: K p is sum_e V_e sigma_e(grad p) grad phi_a (no assembly, no sparse pattern). */
  Status
  SetElasticity(double lambda, double mu, const uint8_t * fixed);
  /** Solves K u = f on the device by Jacobi-preconditioned conjugate gradients from u = 0, with the CPU solver's
   * stopping rule (|r| < tolerance |f| over the free degrees of freedom, Eigen's ConjugateGradient). f and u are
   * node * D + component; u = 0 on fixed nodes. converged is false when maxIterations products did not reach the
   * tolerance (the caller falls back to the CPU solver); iterations: the products K p taken. */
  Status
  SolveElasticity(const double * f,
                  double *       u,
                  double         tolerance,
                  size_t         maxIterations,
                  size_t &       iterations,
                  bool &         converged);
  /** true (default): SolveElasticity runs its whole CG loop as one cooperative launch (grid barriers between the
   * phases of a product) where the device allows it; false: one launch per phase, the host checking every 16 products.
   * Both give the same iterates, bit for bit. */
  void
  SetCooperativeSolve(bool on);
  /** u^T K u / 2 over all nodes (fixed ones included), as LinearElasticFEMSolver::ElasticEnergy. */
  Status
  ElasticEnergy(const double * u, double & energy);
  /** Host copy of the owning element of every pixel. */
  Status
  DownloadElementOfPixels(int32_t * host) const;
  /** nodal[a * D + k] = scale x sum_x phi_a(x) f_k(x) (consistent load vector of the last force). Deterministic: every
   * term is rounded to a power of two q with max|f| x pixels < 2^62 q and summed as a 64-bit integer (so the order of
   * the parallel additions does not matter; each term is off by at most q / 2, far below the double rounding of the
   * CPU's sum for any real image). A force that is not finite gives NaN everywhere. */
  Status
  GatherForce(double scale, double * nodal);
  /** nodal[a * D + k] = w_k at node a (multilinear, clamped). */
  Status
  SampleFieldAtNodes(double * nodal);
  /** u(x) = scale x sum_a phi_a(x) nodalU_a; w <- w o exp(u) by scaling and squaring (the CPU rule for the number of
   * squarings). Returns the largest |u_k| / spacing_k and the number of squarings. */
  Status
  ApplyUpdate(const double * nodalU, double scale, double & maxUpdatePixels, unsigned int & squarings);
  /** Undoes the last ApplyUpdate (w returns to its value before it; no copy: the previous w is still held by a
   * scratch buffer). Only valid right after ApplyUpdate, with no other ApplyUpdate or UploadField in between. */
  Status
  RevertUpdate();
  /** Host copy of w (numberOfPixels x dimension floats, grid frame). */
  Status
  DownloadField(float * host) const;
  /** Host copy of w in the physical frame: direction (dimension x dimension, row-major) times w at every pixel, D
   * floats per pixel: the floats of the CPU's rotation (double sums in column order, rounded once), bit for bit. */
  Status
  DownloadPhysicalField(const double * direction, float * host) const;
  /** Sets w from the host (grid frame). */
  Status
  UploadField(const float * host);
  /** Keeps the inverse transformation's field v on the device from now on (one more field): v = the host's values
   * (grid frame), or 0 for nullptr. */
  Status
  EnableInverse(const float * host);
  /** v <- exp(u) o v, with u(x) = scale x sum_a phi_a(x) nodalU_a (the CPU's ComposeFields(exp(u), v)); called with
   * the accepted update's negated scale after ApplyUpdate, whose RevertUpdate is no longer possible afterwards. */
  Status
  ApplyInverseUpdate(const double * nodalU, double scale);
  /** Host copy of v (numberOfPixels x dimension floats, grid frame). */
  Status
  DownloadInverse(float * host) const;

  /** Largest device memory this context held at once (bytes), and the device's used memory peak seen (bytes). */
  size_t
  AllocatedBytes() const;

private:
  struct Impl;
  std::unique_ptr<Impl> m_Impl;
};
} // namespace cuda
} // namespace dmr
} // namespace itk

#endif
