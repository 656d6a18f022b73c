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

namespace itk
{
template <unsigned int D>
void
LinearElasticFEMSolver<D>::ElementStiffness(const MeshType & mesh, size_t element, double * Ke) const
{
  constexpr unsigned int NV = D + 1;
  // gradients of the barycentric shape functions: rows of J^-1 for phi_1..phi_D, phi_0 = -(sum)
  double x0[D], inv[D][D];
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
  constexpr unsigned int NV = D + 1;
  const size_t           nDof = mesh.NumberOfNodes() * D;
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(mesh.elements.size() * NV * NV * D * D);
  double Ke[NV * D * NV * D];
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    ElementStiffness(mesh, e, Ke);
    for (unsigned int a = 0; a < NV; ++a)
    {
      for (unsigned int i = 0; i < D; ++i)
      {
        for (unsigned int b = 0; b < NV; ++b)
        {
          for (unsigned int j = 0; j < D; ++j)
          {
            triplets.emplace_back(mesh.elements[e][a] * D + i, mesh.elements[e][b] * D + j,
                                  Ke[(a * D + i) * NV * D + b * D + j]);
          }
        }
      }
    }
  }
  m_K.resize(static_cast<Eigen::Index>(nDof), static_cast<Eigen::Index>(nDof));
  m_K.setFromTriplets(triplets.begin(), triplets.end());

  m_FreeIndex.assign(nDof, -1);
  int64_t nFree = 0;
  m_NumberOfFreeNodes = 0;
  for (size_t i = 0; i < mesh.NumberOfNodes(); ++i)
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
  std::vector<Eigen::Triplet<double>> reduced;
  reduced.reserve(static_cast<size_t>(m_K.nonZeros()));
  for (Eigen::Index c = 0; c < m_K.outerSize(); ++c)
  {
    for (SparseMatrixType::InnerIterator it(m_K, c); it; ++it)
    {
      const int64_t r = m_FreeIndex[it.row()], cc = m_FreeIndex[it.col()];
      if (r >= 0 && cc >= 0)
      {
        reduced.emplace_back(r, cc, it.value());
      }
    }
  }
  m_Kf.resize(nFree, nFree);
  m_Kf.setFromTriplets(reduced.begin(), reduced.end());
  m_Factor.reset();
  m_CG.reset(new ConjugateGradientType());
  if (nFree > 0)
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
  if (m_AssembledLambda != m_Lambda || m_AssembledMu != m_Mu)
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
  // conjugate gradients (diagonal preconditioner), warm-started from the previous solution when the system has the
  // same size (the dynamic mesh keeps one node per CVT cell, so node a of the next mesh is near node a of this one)
  Eigen::VectorXd x;
  if (m_Warm.size() == rhs.size())
  {
    x = m_CG->solveWithGuess(rhs, m_Warm);
  }
  else
  {
    x = m_CG->solve(rhs);
  }
  m_LastIterations = static_cast<SizeValueType>(m_CG->iterations());
  if (m_CG->info() != Eigen::Success)
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
  os << indent << "LastIterations: " << m_LastIterations << std::endl;
}
} // namespace itk

#endif
