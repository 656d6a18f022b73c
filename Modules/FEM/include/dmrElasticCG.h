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
#ifndef dmrElasticCG_h
#define dmrElasticCG_h

#include "dmrElasticOperator.h"
#include "dmrSimplexMesh.h"
#include "dmrWorkerTeam.h"
#include "itkMacro.h"
#include "itkMultiThreaderBase.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace itk
{
namespace dmr
{
/** Matrix-free Jacobi-preconditioned conjugate gradients for LinearElasticFEMSolver's system, computed with the CUDA
 * back-end's arithmetic (the per-element and per-node functions of dmrElasticOperator.h, which its kernels call too) in
 * the CUDA back-end's order (dmrRegistrationBackend.cu: ElementGeometryKernel,
 * ElasticDiagonalKernel, ElementStresses, NodeApplyBlock, CGStartKernel, CGStepBlock, CGDirection and the fixed
 * reduction trees of BlockCombine/SumPartials), so that the two back-ends take the same iterates, bit for bit, and stop
 * after the same product. With different rounding, two CGs stopped at a tolerance differ by about that tolerance, and
 * over a registration with a large deformation that difference can tip a CVT swap decision and part the runs
 * (docs/benchmarks.md, "CPU and GPU build the same first mesh").
 *
 * K p at node a is sum_e V_e sigma_e g_a with G = sum_b p_b (x) g_b and sigma = lambda tr(G) I + mu (G + G^T): the
 * element matrix of LinearElasticFEMSolver applied to p. A node's incident elements are summed as one warp of 32 lanes
 * does it (lane l takes incidences l, l + 32, ... in element order, then a shuffle-down tree); a dot product is summed
 * per block of 256 values (a tree within each warp of 32, then the 8 warps in order), and the block partials by 256
 * strided sequential sums and one more block sum. Fixed nodes keep u = 0. Stops when |r|^2 < tolerance^2 |f|^2 (f
 * zeroed on fixed nodes), Eigen's rule. Needs IEEE double arithmetic without contraction into fused multiply-adds
 * (ISO C++ mode, as the project compiles; the CUDA code is compiled with --fmad=false). */
template <unsigned int D>
class ElasticCG
{
public:
  static constexpr int BlockThreads = 256; // CGThreads of the CUDA back-end
  static constexpr int Warp = 32;

  /** Element gradients and volumes, the node -> (element, vertex) incidence in element order and the inverse diagonal
   * of K, from the mesh (kept by pointer) with lambda and mu. */
  void
  SetSystem(const SimplexMesh<D> & mesh, double lambda, double mu)
  {
    constexpr unsigned int NV = D + 1;
    m_Mesh = &mesh;
    m_Lambda = lambda;
    m_Mu = mu;
    const size_t nn = mesh.NumberOfNodes(), ne = mesh.elements.size();
    m_Geometry.assign(ne * Stride, 0.0);
    for (size_t e = 0; e < ne; ++e)
    {
      double x0[D], inv[D][D];
      mesh.EdgeMatrix(e, x0, &inv); // the inverse edge matrix the GPU reads from BarycentricMap::ElementAffine
      ElasticElementGeometry<D>(&inv[0][0], mesh.nodes.data(), mesh.elements[e].data(), &m_Geometry[e * Stride]);
    }
    m_Start.assign(nn + 1, 0);
    for (size_t e = 0; e < ne; ++e)
    {
      for (unsigned int v = 0; v < NV; ++v)
      {
        ++m_Start[static_cast<size_t>(mesh.elements[e][v]) + 1];
      }
    }
    for (size_t a = 0; a < nn; ++a)
    {
      m_Start[a + 1] += m_Start[a];
    }
    m_Incidence.resize(ne * NV);
    std::vector<int64_t> fill(m_Start.begin(), m_Start.end() - 1);
    for (size_t e = 0; e < ne; ++e)
    {
      for (unsigned int v = 0; v < NV; ++v)
      {
        m_Incidence[fill[mesh.elements[e][v]]++] = static_cast<int64_t>(e * NV + v);
      }
    }
    m_InverseDiagonal.assign(nn * D, 0.0);
    for (size_t a = 0; a < nn; ++a)
    {
      double d[D] = {};
      for (int64_t i = m_Start[a]; i < m_Start[a + 1]; ++i)
      {
        AddElasticDiagonal<D>(&m_Geometry[static_cast<size_t>(m_Incidence[i] / NV) * Stride],
                              static_cast<unsigned int>(m_Incidence[i] % NV),
                              lambda,
                              mu,
                              d);
      }
      for (unsigned int k = 0; k < D; ++k)
      {
        m_InverseDiagonal[a * D + k] = Fixed(a) ? 0.0 : (d[k] != 0.0 ? 1.0 / d[k] : 1.0);
      }
    }
  }

  /** Solves K u = f (u = 0 on fixed nodes) from u = 0 with at most maximumProducts products of K; iterations is the
   * number of products taken. Returns whether |r|^2 fell below tolerance^2 |f|^2. With a threader, the element, node
   * and unknown loops of every product run on a team of its threads (TeamRunner, for this call only); every value is
   * still computed by one thread in the fixed order above, so the result does not depend on the threads. */
  bool
  Solve(const double *      f,
        double *            u,
        double              tolerance,
        size_t              maximumProducts,
        size_t &            iterations,
        MultiThreaderBase * threader = nullptr) const
  {
    if (!m_Mesh)
    {
      itkGenericExceptionMacro("ElasticCG: Solve() needs SetSystem() first");
    }
    const size_t        nn = m_Mesh->NumberOfNodes(), ndof = nn * D;
    const size_t        dofBlocks = (ndof + BlockThreads - 1) / BlockThreads;
    const size_t        nodeBlocks = (nn * Warp + BlockThreads - 1) / BlockThreads;
    std::vector<double> r(ndof), z(ndof), p(ndof), q(ndof), stress(m_Mesh->elements.size() * D * D);
    std::vector<double> rrPartials(dofBlocks), rzPartials(dofBlocks), pqPartials(nodeBlocks);
    TeamRunner          runner;
    // body(begin, end) over [0, n) in contiguous ranges of at least `grain`, at most four per thread
    const size_t threads = WorkerTeam::ThreadsOf(threader);
    auto         forRanges = [&](size_t n, size_t grain, auto && body) {
      const size_t chunks = std::max<size_t>(1, std::min((n + grain - 1) / grain, 4 * threads));
      const size_t size = (n + chunks - 1) / chunks;
      runner.Run(threader, chunks, [&](size_t c) {
        const size_t begin = c * size, end = std::min(n, begin + size);
        if (begin < end)
        {
          body(begin, end);
        }
      });
    };
    std::fill(u, u + ndof, 0.0);
    // CGStartKernel, then the host's sums of its partials
    for (size_t i = 0; i < ndof; ++i)
    {
      r[i] = Fixed(i / D) ? 0.0 : f[i];
    }
    forRanges(dofBlocks, 4, [&](size_t b0, size_t b1) { StoreResiduals(b0, b1, r, z, rrPartials, rzPartials); });
    p = z;
    double rhsNorm2 = 0.0, rz = 0.0;
    for (size_t b = 0; b < dofBlocks; ++b)
    {
      rhsNorm2 += rrPartials[b];
      rz += rzPartials[b];
    }
    iterations = 0;
    if (rhsNorm2 == 0.0)
    {
      return true;
    }
    const double threshold = std::max(tolerance * tolerance * rhsNorm2, std::numeric_limits<double>::min());
    double       scalars[2] = { rz, 0.0 }; // r.z by iteration parity
    const auto & elements = m_Mesh->elements;
    for (size_t k = 0; k < maximumProducts; ++k)
    {
      const int parity = static_cast<int>(k & 1);
      // q = K p: the element stresses (ElementStresses), then the nodes' sums (NodeApplyBlock)
      forRanges(elements.size(), 1024, [&](size_t e0, size_t e1) {
        for (size_t e = e0; e < e1; ++e)
        {
          ElasticElementStress<D>(
            &m_Geometry[e * Stride], elements[e].data(), p.data(), m_Lambda, m_Mu, &stress[e * D * D]);
        }
      });
      forRanges(nodeBlocks, 16, [&](size_t b0, size_t b1) { ApplyNodeBlocks(b0, b1, p, stress, q, pqPartials); });
      const double alpha = scalars[parity] / SumPartials(pqPartials);
      forRanges(dofBlocks, 4, [&](size_t b0, size_t b1) {
        for (size_t i = b0 * BlockThreads; i < std::min(ndof, b1 * BlockThreads); ++i)
        {
          u[i] += alpha * p[i];
          r[i] = r[i] - alpha * q[i];
        }
        StoreResiduals(b0, b1, r, z, rrPartials, rzPartials);
      });
      const double rr = SumPartials(rrPartials);
      const double rzNew = SumPartials(rzPartials);
      ++iterations;
      scalars[1 - parity] = rzNew;
      if (rr < threshold)
      {
        return true;
      }
      const double beta = rzNew / scalars[parity];
      for (size_t i = 0; i < ndof; ++i)
      {
        p[i] = z[i] + beta * p[i];
      }
    }
    return false;
  }

private:
  static constexpr size_t Stride = ElasticGeometryStride<D>(); // D + 1 gradients, then the volume

  bool
  Fixed(size_t node) const
  {
    return !m_Mesh->fixed.empty() && m_Mesh->fixed[node];
  }

  /** The shuffle-down tree of one warp (v_l += v_{l+o} for o = 16, 8, 4, 2, 1): lane 0's result, where only the first
   * `lanes` values are given and the others are +0. The additions with a +0 lane are left out: none of the values is
   * -0 (each starts at +0 and only gains terms, and x + (-x) is +0), so adding +0 leaves it as it is, and the result is
   * that of the whole tree, bit for bit. */
  static double
  WarpSum(double * v, int lanes)
  {
    if (lanes <= 0)
    {
      return 0.0;
    }
    for (int o = Warp / 2; o > 0; o >>= 1)
    {
      for (int l = 0; l < std::min(o, lanes - o); ++l)
      {
        v[l] = v[l] + v[l + o];
      }
      lanes = std::min(lanes, o);
    }
    return v[0];
  }

  /** BlockCombine's sum of BlockThreads values of which the first `count` are given (the others 0): each warp's tree,
   * then the warps in order. */
  static double
  BlockSum(double * v, size_t count)
  {
    double s = 0.0;
    for (int w = 0; w < BlockThreads / Warp; ++w)
    {
      const auto lanes =
        static_cast<int>(std::min<size_t>(Warp, count > static_cast<size_t>(w * Warp) ? count - w * Warp : 0));
      s = s + WarpSum(v + w * Warp, lanes);
    }
    return s;
  }

  /** SumPartials: thread t sums partials t, t + BlockThreads, ... in order, then the block sum. */
  static double
  SumPartials(const std::vector<double> & partials)
  {
    double       v[BlockThreads];
    const size_t count = std::min<size_t>(BlockThreads, partials.size());
    for (size_t t = 0; t < count; ++t)
    {
      v[t] = 0.0;
      for (size_t i = t; i < partials.size(); i += BlockThreads)
      {
        v[t] += partials[i];
      }
    }
    return BlockSum(v, count);
  }

  /** StoreResidual for the degrees of freedom of blocks [b0, b1): z = M^-1 r and each block's partial sums of r.r and
   * r.z. */
  void
  StoreResiduals(size_t                      b0,
                 size_t                      b1,
                 const std::vector<double> & r,
                 std::vector<double> &       z,
                 std::vector<double> &       rrPartials,
                 std::vector<double> &       rzPartials) const
  {
    const size_t ndof = r.size();
    double       rr[BlockThreads], rz[BlockThreads];
    for (size_t b = b0; b < b1; ++b)
    {
      const size_t count = std::min<size_t>(BlockThreads, ndof - b * BlockThreads);
      for (size_t t = 0; t < count; ++t)
      {
        const size_t i = b * BlockThreads + t;
        z[i] = m_InverseDiagonal[i] * r[i];
        rr[t] = r[i] * r[i];
        rz[t] = r[i] * z[i];
      }
      rrPartials[b] = BlockSum(rr, count);
      rzPartials[b] = BlockSum(rz, count);
    }
  }

  /** q = K p (0 on fixed nodes) at the nodes of node blocks [b0, b1) from the element stresses, and each block's
   * partial sum of p . q (NodeApplyBlock: one warp per node, lane l summing the node's incident elements l, l + 32, ...
   * in element order, then the warp's tree). */
  void
  ApplyNodeBlocks(size_t                      b0,
                  size_t                      b1,
                  const std::vector<double> & p,
                  const std::vector<double> & stress,
                  std::vector<double> &       q,
                  std::vector<double> &       pqPartials) const
  {
    constexpr unsigned int NV = D + 1;
    const size_t           nn = m_Mesh->NumberOfNodes();
    constexpr int          NodesPerBlock = BlockThreads / Warp;
    double                 pq[BlockThreads];
    for (size_t block = b0; block < b1; ++block)
    {
      for (int w = 0; w < NodesPerBlock; ++w)
      {
        const size_t a = block * NodesPerBlock + static_cast<size_t>(w);
        pq[w * Warp] = 0.0;
        if (a >= nn)
        {
          continue;
        }
        double y[Warp][D];
        int    lanes = 0;
        if (!Fixed(a))
        {
          lanes = static_cast<int>(std::min<int64_t>(Warp, m_Start[a + 1] - m_Start[a]));
          for (int lane = 0; lane < lanes; ++lane)
          {
            std::fill(y[lane], y[lane] + D, 0.0);
            for (int64_t i = m_Start[a] + lane; i < m_Start[a + 1]; i += Warp)
            {
              const size_t e = static_cast<size_t>(m_Incidence[i] / NV),
                           slot = static_cast<size_t>(m_Incidence[i] % NV);
              AddElasticNodeTerm<D>(&stress[e * D * D], &m_Geometry[e * Stride + slot * D], y[lane]);
            }
          }
        }
        double sum = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          double v[Warp];
          for (int lane = 0; lane < lanes; ++lane)
          {
            v[lane] = y[lane][k];
          }
          const double yk = WarpSum(v, lanes);
          q[a * D + k] = yk;
          sum += p[a * D + k] * yk;
        }
        pq[w * Warp] = sum;
      }
      // lane 0 of each warp holds its node's p . q, the other lanes 0
      double s = 0.0;
      for (int w = 0; w < NodesPerBlock; ++w)
      {
        s = s + WarpSum(pq + w * Warp, 1);
      }
      pqPartials[block] = s;
    }
  }

  const SimplexMesh<D> * m_Mesh{ nullptr };
  double                 m_Lambda{ 0.0 };
  double                 m_Mu{ 0.0 };
  std::vector<double>    m_Geometry;
  std::vector<int64_t>   m_Start, m_Incidence;
  std::vector<double>    m_InverseDiagonal;
};
} // namespace dmr
} // namespace itk

#endif
