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
#ifndef dmrElasticOperator_h
#define dmrElasticOperator_h

#include "dmrFixedPointGather.h" // DMR_HOST_DEVICE

#include <cmath>

namespace itk
{
namespace dmr
{
/** The per-element and per-node arithmetic of the matrix-free elastic operator, one definition for the CUDA
 * back-end's kernels (dmrRegistrationBackend.cu) and the CPU's dmr::ElasticCG, so that both compute every value with
 * the same operations in the same order. K p at node a is sum_e V_e sigma_e g_a with G = sum_b p_b (x) g_b and
 * sigma = lambda tr(G) I + mu (G + G^T): LinearElasticFEMSolver's element matrix applied to p.
 * \ingroup DynamicMeshRegistration */

/** Doubles per element: the D + 1 gradients g_a of the barycentric shape functions, then the volume V. */
template <unsigned int D>
DMR_HOST_DEVICE constexpr unsigned int
ElasticGeometryStride()
{
  return (D + 1) * D + 1;
}

/** g and V of one element from its inverse edge matrix (D x D row-major: row r = grad phi_{r+1}) and the coordinates of
 * its vertices. */
template <unsigned int D, typename TIndex>
DMR_HOST_DEVICE inline void
ElasticElementGeometry(const double * inverseEdges, const double * nodes, const TIndex * vertices, double * g)
{
  for (unsigned int k = 0; k < D; ++k)
  {
    g[k] = 0.0;
  }
  for (unsigned int a = 1; a <= D; ++a)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      g[a * D + k] = inverseEdges[(a - 1) * D + k];
      g[k] -= g[a * D + k];
    }
  }
  double m[D][D];
  for (unsigned int r = 0; r < D; ++r)
  {
    for (unsigned int c = 0; c < D; ++c)
    {
      m[r][c] = nodes[vertices[c + 1] * D + r] - nodes[vertices[0] * D + r];
    }
  }
  double det;
  if (D == 2)
  {
    det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
  }
  else
  {
    det = m[0][0] * (m[1][1] * m[D - 1][D - 1] - m[1][D - 1] * m[D - 1][1]) -
          m[0][1] * (m[1][0] * m[D - 1][D - 1] - m[1][D - 1] * m[D - 1][0]) +
          m[0][D - 1] * (m[1][0] * m[D - 1][1] - m[1][1] * m[D - 1][0]);
  }
  g[(D + 1) * D] = fabs(det) / (D == 2 ? 2.0 : 6.0);
}

/** Adds the diagonal of K at the vertex `slot` of the element with geometry g to d (D values). */
template <unsigned int D>
DMR_HOST_DEVICE inline void
AddElasticDiagonal(const double * g, unsigned int slot, double lambda, double mu, double * d)
{
  const double V = g[(D + 1) * D];
  double       gg = 0.0;
  for (unsigned int k = 0; k < D; ++k)
  {
    gg += g[slot * D + k] * g[slot * D + k];
  }
  for (unsigned int k = 0; k < D; ++k)
  {
    d[k] += V * ((lambda + mu) * g[slot * D + k] * g[slot * D + k] + mu * gg);
  }
}

/** S = V sigma(G) (D x D row-major) of the element with geometry g and vertices `vertices`, for the nodal vector p. */
template <unsigned int D, typename TIndex>
DMR_HOST_DEVICE inline void
ElasticElementStress(const double * g, const TIndex * vertices, const double * p, double lambda, double mu, double * S)
{
  double G[D][D] = {};
  for (unsigned int b = 0; b <= D; ++b)
  {
    for (unsigned int i = 0; i < D; ++i)
    {
      const double pb = p[static_cast<long long>(vertices[b]) * D + i];
      for (unsigned int j = 0; j < D; ++j)
      {
        G[i][j] += pb * g[b * D + j];
      }
    }
  }
  double trace = 0.0;
  for (unsigned int i = 0; i < D; ++i)
  {
    trace += G[i][i];
  }
  const double V = g[(D + 1) * D];
  for (unsigned int i = 0; i < D; ++i)
  {
    for (unsigned int j = 0; j < D; ++j)
    {
      S[i * D + j] = V * ((i == j ? lambda * trace : 0.0) + mu * (G[i][j] + G[j][i]));
    }
  }
}

/** y += S g_slot: one incident element's contribution to K p at a node (gSlot = the node's gradient in the element). */
template <unsigned int D>
DMR_HOST_DEVICE inline void
AddElasticNodeTerm(const double * S, const double * gSlot, double * y)
{
  for (unsigned int r = 0; r < D; ++r)
  {
    for (unsigned int c = 0; c < D; ++c)
    {
      y[r] += S[r * D + c] * gSlot[c];
    }
  }
}
} // namespace dmr
} // namespace itk

#endif
