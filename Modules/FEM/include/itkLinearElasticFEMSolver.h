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
#ifndef itkLinearElasticFEMSolver_h
#define itkLinearElasticFEMSolver_h

#include "itkObject.h"
#include "itkObjectFactory.h"
#include "itkMultiThreaderBase.h"
#include "dmrElasticCG.h"
#include "dmrSimplexMesh.h"
#include "itk_eigen.h"
#include ITK_EIGEN(Sparse)
#include ITK_EIGEN(IterativeLinearSolvers)
#include <memory>

namespace itk
{
/** \class LinearElasticFEMSolver
 * \brief P1 (linear simplex) isotropic linear-elastic stiffness and sparse solve, boundary nodes fixed.
 *
 * Discretises the Navier-Lame operator of paper Eq. 4 on a triangle/tetrahedron mesh in the grid frame (mm):
 * K[(a,i),(b,j)] = sum_e V_e (lambda d_i phi_a d_j phi_b + mu d_j phi_a d_i phi_b + mu delta_ij grad phi_a . grad
 * phi_b), i.e. the bilinear form of lambda div u div v + 2 mu eps(u):eps(v). Nodes flagged fixed (the image border)
 * have u = 0 (paper 3): their degrees of freedom are eliminated, which leaves K symmetric positive definite.
 *
 * A system of at most DirectSolverMaximumDegreesOfFreedom free unknowns is factorised by SetMesh (sparse LDL^T,
 * ITK's bundled Eigen) and solved exactly to rounding. A larger one is solved by conjugate gradients with a diagonal
 * preconditioner to a relative residual of Tolerance (default 1e-12), warm-started from the previous solution when the
 * system size is unchanged, falling back to the factorisation if CG does not converge. For the 3D meshes of the paper
 * (3000 nodes) CG is about 20x faster than factorising every new mesh, and the dynamic mesh changes every iteration.
 * With GPUOrderSolve on, the CG is instead dmr::ElasticCG: matrix-free, from u = 0, with the CUDA back-end's
 * arithmetic in its order, so that a CPU run takes the GPU's iterates bit for bit; its loops run on MultiThreader's
 * threads.
 * A small system costs about the same either way, and the exact solve makes the result a continuous function of the
 * force: a CG stopped at a tolerance jumps by about that tolerance when a rounding difference in its input moves its
 * stopping iteration, and over many iterations of a large deformation such jumps grow into different registrations
 * (docs/benchmarks.md, "CPU and GPU on circle-to-leaf").
 * \ingroup DynamicMeshRegistration */
template <unsigned int VDimension>
class ITK_TEMPLATE_EXPORT LinearElasticFEMSolver : public Object
{
public:
  ITK_DISALLOW_COPY_AND_MOVE(LinearElasticFEMSolver);
  using Self = LinearElasticFEMSolver;
  using Superclass = Object;
  using Pointer = SmartPointer<Self>;
  using ConstPointer = SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(LinearElasticFEMSolver, Object);

  static constexpr unsigned int Dimension = VDimension;
  using MeshType = dmr::SimplexMesh<VDimension>;
  using SparseMatrixType = Eigen::SparseMatrix<double>;
  using VectorType = std::vector<double>;

  /** Lame's first parameter (paper Eq. 4's lambda). */
  itkSetClampMacro(Lambda, double, 0.0, NumericTraits<double>::max());
  itkGetConstMacro(Lambda, double);
  /** Shear modulus mu (> 0). */
  itkSetClampMacro(Mu, double, NumericTraits<double>::epsilon(), NumericTraits<double>::max());
  itkGetConstMacro(Mu, double);

  /** Assembles and factorises K for a mesh (kept by pointer: it must outlive the solver's use). Changing Lambda or
   * Mu afterwards requires another SetMesh(); Solve() refuses a stale factorisation. */
  void
  SetMesh(const MeshType & mesh);

  /** Element stiffness (row/col index = vertex * D + component). */
  void
  ElementStiffness(const MeshType & mesh, size_t element, double * Ke) const;

  /** The full stiffness matrix over all nodes (fixed ones included), index = node * D + component. */
  const SparseMatrixType &
  GetStiffnessMatrix() const
  {
    return m_K;
  }

  /** Solves K u = f for the free nodes with u = 0 on fixed nodes; f and u are node * D + component. */
  void
  Solve(const VectorType & f, VectorType & u) const;

  /** Elastic energy u^T K u / 2. */
  double
  ElasticEnergy(const VectorType & u) const;

  itkGetConstMacro(NumberOfFreeNodes, SizeValueType);
  /** Relative residual |K u - f| / |f| at which conjugate gradients stop (takes effect at the next SetMesh). */
  itkSetClampMacro(Tolerance, double, 1e-16, 1e-2);
  itkGetConstMacro(Tolerance, double);
  /** Systems with at most this many free unknowns are factorised and solved exactly; larger ones by CG (takes effect
   * at the next SetMesh; 0: always CG). */
  itkSetMacro(DirectSolverMaximumDegreesOfFreedom, SizeValueType);
  itkGetConstMacro(DirectSolverMaximumDegreesOfFreedom, SizeValueType);
  /** Whether the current mesh's system is solved by its factorisation (see DirectSolverMaximumDegreesOfFreedom). */
  itkGetConstMacro(Direct, bool);
  /** Solve the systems above DirectSolverMaximumDegreesOfFreedom by dmr::ElasticCG, the CUDA back-end's CG in its
   * order (the GPU's iterates bit for bit; slower), instead of CG on the assembled matrix (default off; takes effect
   * at the next SetMesh). */
  itkSetMacro(GPUOrderSolve, bool);
  itkGetConstMacro(GPUOrderSolve, bool);
  itkBooleanMacro(GPUOrderSolve);
  /** The threader whose threads the GPU-order CG (GPUOrderSolve) runs its element and node loops on (none: one
   * thread); the result does not depend on it. */
  itkSetObjectMacro(MultiThreader, MultiThreaderBase);
  itkGetModifiableObjectMacro(MultiThreader, MultiThreaderBase);
  /** CG iterations of the last Solve(): 0 for a direct solve (the fallback factorisation ran when it equals the
   * limit). */
  itkGetConstMacro(LastIterations, SizeValueType);

protected:
  LinearElasticFEMSolver() = default;
  ~LinearElasticFEMSolver() override = default;
  void
  PrintSelf(std::ostream & os, Indent indent) const override;

private:
  double               m_Lambda{ 1.0 };
  double               m_Mu{ 1.0 };
  SizeValueType        m_NumberOfFreeNodes{ 0 };
  const MeshType *     m_Mesh{ nullptr };
  double               m_AssembledLambda{ 0.0 };
  double               m_AssembledMu{ 0.0 };
  SparseMatrixType     m_K;
  std::vector<int64_t> m_FreeIndex; // dof -> index in the reduced system, -1 when fixed
  using ConjugateGradientType = Eigen::ConjugateGradient<SparseMatrixType, Eigen::Lower | Eigen::Upper>;
  double                                                           m_Tolerance{ 1e-12 };
  SizeValueType                                                    m_DirectSolverMaximumDegreesOfFreedom{ 300 };
  bool                                                             m_Direct{ false };
  bool                                                             m_GPUOrderSolve{ false };
  bool                                                             m_GPUOrderSystem{ false }; // set by SetMesh
  dmr::ElasticCG<VDimension>                                       m_ElasticCG;
  MultiThreaderBase::Pointer                                       m_MultiThreader;
  SparseMatrixType                                                 m_Kf; // reduced to the free degrees of freedom
  std::unique_ptr<ConjugateGradientType>                           m_CG;
  mutable std::unique_ptr<Eigen::SimplicialLDLT<SparseMatrixType>> m_Factor;
  mutable Eigen::VectorXd                                          m_Warm;
  mutable SizeValueType                                            m_LastIterations{ 0 };
};
} // namespace itk

#ifndef ITK_MANUAL_INSTANTIATION
#include "itkLinearElasticFEMSolver.hxx"
#endif

#endif
