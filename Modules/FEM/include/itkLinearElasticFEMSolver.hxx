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
#ifndef itkLinearElasticFEMSolver_hxx
#define itkLinearElasticFEMSolver_hxx

#include "itkLinearElasticFEMSolver.h"
#include <algorithm>

namespace itk
{
template <unsigned int D>
void
LinearElasticFEMSolver<D>::ElementStiffness(const MeshType & mesh, size_t element, double * Ke) const
{
  constexpr unsigned int NV = D + 1;
  // gradients of the barycentric shape functions: rows of J^-1 for phi_1..phi_D, phi_0 = -(sum)
  double       x0[D], inv[D][D];
  const double det = mesh.EdgeMatrix(element, x0, &inv);
  const double volume = std::abs(det) / (D == 2 ? 2.0 : 6.0);
  double       g[NV][D];
  for (unsigned int k = 0; k < D; ++k)
  {
    g[0][k] = 0.0;
  }
  for (unsigned int a = 1; a < NV; ++a)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      g[a][k] = inv[a - 1][k];
      g[0][k] -= g[a][k];
    }
  }
  for (unsigned int a = 0; a < NV; ++a)
  {
    for (unsigned int b = 0; b < NV; ++b)
    {
      double dot = 0.0;
      for (unsigned int k = 0; k < D; ++k)
      {
        dot += g[a][k] * g[b][k];
      }
      for (unsigned int i = 0; i < D; ++i)
      {
        for (unsigned int j = 0; j < D; ++j)
        {
          Ke[(a * D + i) * NV * D + b * D + j] =
            volume * (m_Lambda * g[a][i] * g[b][j] + m_Mu * g[a][j] * g[b][i] + (i == j ? m_Mu * dot : 0.0));
        }
      }
    }
  }
}

template <unsigned int D>
void
LinearElasticFEMSolver<D>::SetMesh(const MeshType & mesh)
{
  // NaN passes itkSetClampMacro (every comparison with it is false); an infinite lambda + 2 mu fills K with inf
  if (!std::isfinite(m_Lambda) || !std::isfinite(m_Mu) || !std::isfinite(m_Lambda + 2.0 * m_Mu))
  {
    itkExceptionMacro("Lambda (" << m_Lambda << ") and Mu (" << m_Mu << ") must be finite, and so must Lambda + 2 Mu");
  }
  constexpr unsigned int NV = D + 1;
  const size_t           nNodes = mesh.NumberOfNodes();
  const size_t           nDof = nNodes * D;
  const size_t           nElements = mesh.elements.size();
  // Direct compressed assembly (the mesh changes every iteration, so this runs every iteration): the node adjacency
  // pattern from the elements, then every element's block added at its place, in element order (the same sums, in
  // the same order, as assembling from triplets). K is stored column by column; entry (row (a,i), column (b,j)) of
  // element e is added to column (b,j).
  std::vector<int64_t> incidenceStart, incidence;
  dmr::ElementsAroundNodes(mesh.elements, nNodes, incidenceStart, incidence);
  // neighbours of every node (itself included), sorted: the block pattern of its column
  std::vector<int64_t> patternStart(nNodes + 1, 0), pattern;
  pattern.reserve(nElements * NV * 2);
  std::vector<int64_t> scratch;
  for (size_t b = 0; b < nNodes; ++b)
  {
    scratch.clear();
    for (int64_t k = incidenceStart[b]; k < incidenceStart[b + 1]; ++k)
    {
      for (unsigned int v = 0; v < NV; ++v)
      {
        scratch.push_back(static_cast<int64_t>(mesh.elements[incidence[k]][v]));
      }
    }
    std::sort(scratch.begin(), scratch.end());
    scratch.erase(std::unique(scratch.begin(), scratch.end()), scratch.end());
    pattern.insert(pattern.end(), scratch.begin(), scratch.end());
    patternStart[b + 1] = static_cast<int64_t>(pattern.size());
  }
  const size_t nnz = pattern.size() * D * D;
  m_K.resize(static_cast<Eigen::Index>(nDof), static_cast<Eigen::Index>(nDof));
  m_K.resizeNonZeros(static_cast<Eigen::Index>(nnz));
  auto * outer = m_K.outerIndexPtr();
  auto * inner = m_K.innerIndexPtr();
  auto * value = m_K.valuePtr();
  outer[0] = 0;
  for (size_t b = 0; b < nNodes; ++b)
  {
    const int64_t blocks = patternStart[b + 1] - patternStart[b];
    for (unsigned int j = 0; j < D; ++j)
    {
      const size_t column = b * D + j;
      const auto   first = outer[column];
      outer[column + 1] = first + static_cast<typename SparseMatrixType::StorageIndex>(blocks * D);
      for (int64_t q = 0; q < blocks; ++q)
      {
        for (unsigned int i = 0; i < D; ++i)
        {
          inner[first + q * D + i] =
            static_cast<typename SparseMatrixType::StorageIndex>(pattern[patternStart[b] + q] * D + i);
        }
      }
    }
  }
  std::fill(value, value + nnz, 0.0);
  double Ke[NV * D * NV * D];
  for (size_t e = 0; e < nElements; ++e)
  {
    ElementStiffness(mesh, e, Ke);
    for (unsigned int b = 0; b < NV; ++b)
    {
      const int64_t nb = static_cast<int64_t>(mesh.elements[e][b]);
      for (unsigned int a = 0; a < NV; ++a)
      {
        const int64_t na = static_cast<int64_t>(mesh.elements[e][a]);
        const int64_t q =
          std::lower_bound(pattern.begin() + patternStart[nb], pattern.begin() + patternStart[nb + 1], na) -
          (pattern.begin() + patternStart[nb]);
        for (unsigned int j = 0; j < D; ++j)
        {
          double * column = value + outer[nb * D + j] + q * D;
          for (unsigned int i = 0; i < D; ++i)
          {
            column[i] += Ke[(a * D + i) * NV * D + b * D + j];
          }
        }
      }
    }
  }

  m_FreeIndex.assign(nDof, -1);
  int64_t nFree = 0;
  m_NumberOfFreeNodes = 0;
  for (size_t i = 0; i < nNodes; ++i)
  {
    if (mesh.fixed.empty() || !mesh.fixed[i])
    {
      ++m_NumberOfFreeNodes;
      for (unsigned int k = 0; k < D; ++k)
      {
        m_FreeIndex[i * D + k] = nFree++;
      }
    }
  }
  // the free rows and columns, in order (the free numbering is increasing, so columns stay sorted)
  size_t freeNonZeros = 0;
  for (size_t c = 0; c < nDof; ++c)
  {
    if (m_FreeIndex[c] >= 0)
    {
      for (auto k = outer[c]; k < outer[c + 1]; ++k)
      {
        freeNonZeros += m_FreeIndex[inner[k]] >= 0 ? 1 : 0;
      }
    }
  }
  m_Kf.resize(nFree, nFree);
  m_Kf.resizeNonZeros(static_cast<Eigen::Index>(freeNonZeros));
  auto *                                  fOuter = m_Kf.outerIndexPtr();
  auto *                                  fInner = m_Kf.innerIndexPtr();
  auto *                                  fValue = m_Kf.valuePtr();
  typename SparseMatrixType::StorageIndex position = 0;
  fOuter[0] = 0;
  for (size_t c = 0; c < nDof; ++c)
  {
    if (m_FreeIndex[c] < 0)
    {
      continue;
    }
    for (auto k = outer[c]; k < outer[c + 1]; ++k)
    {
      const int64_t r = m_FreeIndex[inner[k]];
      if (r >= 0)
      {
        fInner[position] = static_cast<typename SparseMatrixType::StorageIndex>(r);
        fValue[position] = value[k];
        ++position;
      }
    }
    fOuter[m_FreeIndex[c] + 1] = position;
  }
  m_Factor.reset();
  m_CG.reset(new ConjugateGradientType());
  m_Direct = false;
  if (nFree > 0 && static_cast<SizeValueType>(nFree) <= m_DirectSolverMaximumDegreesOfFreedom)
  {
    // a small system: factorised once per mesh and solved exactly (see the class comment)
    m_Factor.reset(new Eigen::SimplicialLDLT<SparseMatrixType>());
    m_Factor->compute(m_Kf);
    m_Direct = m_Factor->info() == Eigen::Success;
    if (!m_Direct)
    {
      m_Factor.reset();
    }
  }
  m_GPUOrderSystem = nFree > 0 && !m_Direct && m_GPUOrderSolve;
  if (m_GPUOrderSystem)
  {
    m_ElasticCG.SetSystem(mesh, m_Lambda, m_Mu);
  }
  else if (nFree > 0 && !m_Direct)
  {
    m_CG->setTolerance(m_Tolerance);
    m_CG->setMaxIterations(std::max<Eigen::Index>(1000, 4 * nFree));
    m_CG->compute(m_Kf);
  }
  m_LastIterations = 0;
  m_Mesh = &mesh;
  m_AssembledLambda = m_Lambda;
  m_AssembledMu = m_Mu;
  this->Modified();
}

template <unsigned int D>
void
LinearElasticFEMSolver<D>::Solve(const VectorType & f, VectorType & u) const
{
  if (m_Mesh == nullptr)
  {
    itkExceptionMacro("Solve() needs SetMesh() first");
  }
  if (!(m_AssembledLambda == m_Lambda && m_AssembledMu == m_Mu))
  {
    itkExceptionMacro("Lambda or Mu changed after SetMesh(): call SetMesh() again to re-assemble K");
  }
  const size_t    nDof = m_FreeIndex.size();
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(m_NumberOfFreeNodes * D));
  for (size_t i = 0; i < nDof; ++i)
  {
    if (m_FreeIndex[i] >= 0)
    {
      rhs[m_FreeIndex[i]] = f[i];
    }
  }
  u.assign(nDof, 0.0);
  if (rhs.size() == 0)
  {
    return;
  }
  // a small system: its factorisation (exact to rounding; no iterations)
  Eigen::VectorXd x;
  if (m_Direct)
  {
    x = m_Factor->solve(rhs);
    m_LastIterations = 0;
  }
  else
  {
    bool converged = true;
    if (m_GPUOrderSystem)
    {
      // matrix-free CG from u = 0 in the CUDA back-end's order, with the device's product limit
      std::vector<double> full(nDof);
      size_t              products = 0;
      converged = m_ElasticCG.Solve(f.data(),
                                    full.data(),
                                    m_Tolerance,
                                    std::max<size_t>(1000, 4 * static_cast<size_t>(rhs.size())),
                                    products,
                                    m_MultiThreader.GetPointer());
      m_LastIterations = static_cast<SizeValueType>(products);
      x.resize(rhs.size());
      for (size_t i = 0; i < nDof; ++i)
      {
        if (m_FreeIndex[i] >= 0)
        {
          x[m_FreeIndex[i]] = full[i];
        }
      }
    }
    else
    {
      // conjugate gradients (diagonal preconditioner), warm-started from the previous solution when the system has the
      // same size (the dynamic mesh keeps one node per CVT cell, so node a of the next mesh is near node a of this one)
      if (m_Warm.size() == rhs.size())
      {
        x = m_CG->solveWithGuess(rhs, m_Warm);
      }
      else
      {
        x = m_CG->solve(rhs);
      }
      m_LastIterations = static_cast<SizeValueType>(m_CG->iterations());
      converged = m_CG->info() == Eigen::Success;
    }
    if (!converged)
    {
      // not converged (a very ill-conditioned mesh): the exact sparse factorisation
      if (!m_Factor)
      {
        m_Factor.reset(new Eigen::SimplicialLDLT<SparseMatrixType>());
        m_Factor->compute(m_Kf);
        if (m_Factor->info() != Eigen::Success)
        {
          itkExceptionMacro("the stiffness matrix could not be factorised (mesh with "
                            << m_Mesh->NumberOfNodes() << " nodes, " << m_Kf.rows() << " free degrees of freedom)");
        }
      }
      x = m_Factor->solve(rhs);
    }
  }
  m_Warm = x;
  for (size_t i = 0; i < nDof; ++i)
  {
    if (m_FreeIndex[i] >= 0)
    {
      u[i] = x[m_FreeIndex[i]];
    }
  }
}

template <unsigned int D>
double
LinearElasticFEMSolver<D>::ElasticEnergy(const VectorType & u) const
{
  Eigen::Map<const Eigen::VectorXd> x(u.data(), static_cast<Eigen::Index>(u.size()));
  return 0.5 * x.dot(m_K * x);
}

template <unsigned int D>
void
LinearElasticFEMSolver<D>::PrintSelf(std::ostream & os, Indent indent) const
{
  Superclass::PrintSelf(os, indent);
  os << indent << "Lambda: " << m_Lambda << std::endl;
  os << indent << "Mu: " << m_Mu << std::endl;
  os << indent << "NumberOfFreeNodes: " << m_NumberOfFreeNodes << std::endl;
  os << indent << "NumberOfDegreesOfFreedom: " << m_K.rows() << std::endl;
  os << indent << "Tolerance: " << m_Tolerance << std::endl;
  os << indent << "DirectSolverMaximumDegreesOfFreedom: " << m_DirectSolverMaximumDegreesOfFreedom << std::endl;
  os << indent << "Direct: " << (m_Direct ? "true" : "false") << std::endl;
  os << indent << "GPUOrderSolve: " << (m_GPUOrderSolve ? "true" : "false") << std::endl;
  os << indent << "MultiThreader: " << m_MultiThreader.GetPointer() << std::endl;
  os << indent << "LastIterations: " << m_LastIterations << std::endl;
}
} // namespace itk

#endif
