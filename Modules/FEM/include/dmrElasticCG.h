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
 * strided sequential sums and one more block sum. On the CPU the element arithmetic runs on blocks of 4 elements with
 * the lanes innermost (the same operations for each element, which the compiler vectorises) and leaves each incidence's
 * node term for the nodes' sums; the test GPUOrderProductIsTheWarpOrderProduct compares this product with the literal
 * warp-order one, bit for bit. Fixed nodes keep u = 0. Stops when |r|^2 < tolerance^2 |f|^2 (f
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
    // the same gradients and volumes in blocks of Lanes elements, lane innermost, for ElementBlocks' loops (padding
    // lanes: zero geometry, vertex 0)
    const size_t blocks = NumberOfElementBlocks();
    m_BlockGeometry.assign(blocks * Stride * Lanes, 0.0);
    m_BlockVertices.assign(blocks * NV * Lanes, 0);
    for (size_t e = 0; e < ne; ++e)
    {
      const size_t block = e / Lanes, lane = e % Lanes;
      for (unsigned int c = 0; c < Stride; ++c)
      {
        m_BlockGeometry[(block * Stride + c) * Lanes + lane] = m_Geometry[e * Stride + c];
      }
      for (unsigned int v = 0; v < NV; ++v)
      {
        m_BlockVertices[(block * NV + v) * Lanes + lane] = mesh.elements[e][v];
      }
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
    m_TermOffset.resize(m_Incidence.size());
    for (size_t i = 0; i < m_Incidence.size(); ++i)
    {
      const size_t e = static_cast<size_t>(m_Incidence[i] / NV), slot = static_cast<size_t>(m_Incidence[i] % NV);
      m_TermOffset[i] = ((e / Lanes * NV + slot) * D) * Lanes + e % Lanes;
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
    std::vector<double> r(ndof), z(ndof), p(ndof), q(ndof), terms(NumberOfElementBlocks() * Lanes * (D + 1) * D);
    std::vector<double> rrPartials(dofBlocks), rzPartials(dofBlocks), pqPartials(nodeBlocks);
    TeamRunner          runner;
    auto forRanges = [&](size_t n, size_t grain, auto && body) { ForRanges(runner, threader, n, grain, body); };
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
    for (size_t k = 0; k < maximumProducts; ++k)
    {
      const int parity = static_cast<int>(k & 1);
      Product(runner, threader, p, terms, q, pqPartials);
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

  /** q = K p (0 on fixed nodes), the product Solve takes, computed the same way (ndof = D x nodes values each). */
  void
  Apply(const double * p, double * q, MultiThreaderBase * threader = nullptr) const
  {
    if (!m_Mesh)
    {
      itkGenericExceptionMacro("ElasticCG: Apply() needs SetSystem() first");
    }
    const size_t        nn = m_Mesh->NumberOfNodes(), ndof = nn * D;
    std::vector<double> pv(p, p + ndof), qv(ndof), terms(NumberOfElementBlocks() * Lanes * (D + 1) * D),
      pqPartials((nn * Warp + BlockThreads - 1) / BlockThreads);
    TeamRunner runner;
    Product(runner, threader, pv, terms, qv, pqPartials);
    std::copy(qv.begin(), qv.end(), q);
  }

private:
  static constexpr size_t       Stride = ElasticGeometryStride<D>(); // D + 1 gradients, then the volume
  static constexpr unsigned int Lanes = 4;                           // elements per step of ElementBlocks

  bool
  Fixed(size_t node) const
  {
    return !m_Mesh->fixed.empty() && m_Mesh->fixed[node];
  }

  /** body(begin, end) over [0, n) in contiguous ranges of at least `grain`, at most four per thread of the threader,
   * on the runner's team. */
  template <typename TBody>
  static void
  ForRanges(TeamRunner & runner, MultiThreaderBase * threader, size_t n, size_t grain, TBody && body)
  {
    const size_t chunks =
      std::max<size_t>(1, std::min<size_t>((n + grain - 1) / grain, 4 * WorkerTeam::ThreadsOf(threader)));
    const size_t size = (n + chunks - 1) / chunks;
    runner.Run(threader, chunks, [&](size_t c) {
      const size_t begin = c * size, end = std::min(n, begin + size);
      if (begin < end)
      {
        body(begin, end);
      }
    });
  }

  /** q = K p and the node blocks' partial sums of p . q: the element stresses (ElementStresses) with their node terms,
   * then the nodes' sums (NodeApplyBlock). */
  void
  Product(TeamRunner &                runner,
          MultiThreaderBase *         threader,
          const std::vector<double> & p,
          std::vector<double> &       terms,
          std::vector<double> &       q,
          std::vector<double> &       pqPartials) const
  {
    const size_t nodeBlocks = pqPartials.size();
    ForRanges(
      runner, threader, NumberOfElementBlocks(), 256, [&](size_t b0, size_t b1) { ElementBlocks(b0, b1, p, terms); });
    ForRanges(runner, threader, nodeBlocks, 16, [&](size_t b0, size_t b1) {
      ApplyNodeBlocks(b0, b1, p, terms, q, pqPartials);
    });
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

  /** Element blocks of Lanes elements (the last one part-filled). */
  size_t
  NumberOfElementBlocks() const
  {
    return (m_Mesh->elements.size() + Lanes - 1) / Lanes;
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

  /** ElasticElementStress for the elements of element blocks [b0, b1), Lanes elements at a time (the same operations in
   * the same order for every element, written lane-innermost so that the compiler can put the lanes in vector
   * registers), and each element's node terms: for element e = block Lanes + lane, terms[((block (D + 1) + slot) D + r)
   * Lanes + lane] = component r of AddElasticNodeTerm of its stress and gradient `slot` added to y = 0, which is what a
   * warp lane that takes only this incidence sums (m_TermOffset has each incidence's r = 0 position). The stresses are
   * not kept: the few lanes with a second incidence (nodes with more than 32 elements) recompute theirs. */
  void
  ElementBlocks(size_t b0, size_t b1, const std::vector<double> & p, std::vector<double> & terms) const
  {
    constexpr unsigned int NV = D + 1;
    for (size_t block = b0; block < b1; ++block)
    {
      const double *  g = &m_BlockGeometry[block * Stride * Lanes];
      const int32_t * vertices = &m_BlockVertices[block * NV * Lanes];
      double          pv[NV][D][Lanes], G[D][D][Lanes], trace[Lanes], S[D][D][Lanes];
      for (unsigned int b = 0; b < NV; ++b)
      {
        for (unsigned int l = 0; l < Lanes; ++l)
        {
          const double * pb = &p[static_cast<size_t>(vertices[b * Lanes + l]) * D];
          for (unsigned int i = 0; i < D; ++i)
          {
            pv[b][i][l] = pb[i];
          }
        }
      }
      for (unsigned int i = 0; i < D; ++i)
      {
        for (unsigned int j = 0; j < D; ++j)
        {
          for (unsigned int l = 0; l < Lanes; ++l)
          {
            G[i][j][l] = 0.0;
          }
          for (unsigned int b = 0; b < NV; ++b)
          {
            for (unsigned int l = 0; l < Lanes; ++l)
            {
              G[i][j][l] += pv[b][i][l] * g[(b * D + j) * Lanes + l];
            }
          }
        }
      }
      for (unsigned int l = 0; l < Lanes; ++l)
      {
        trace[l] = 0.0;
      }
      for (unsigned int i = 0; i < D; ++i)
      {
        for (unsigned int l = 0; l < Lanes; ++l)
        {
          trace[l] += G[i][i][l];
        }
      }
      const double * V = &g[(NV * D) * Lanes];
      for (unsigned int i = 0; i < D; ++i)
      {
        for (unsigned int j = 0; j < D; ++j)
        {
          for (unsigned int l = 0; l < Lanes; ++l)
          {
            S[i][j][l] = V[l] * ((i == j ? m_Lambda * trace[l] : 0.0) + m_Mu * (G[i][j][l] + G[j][i][l]));
          }
        }
      }
      double * t = &terms[block * Lanes * NV * D];
      for (unsigned int slot = 0; slot < NV; ++slot)
      {
        for (unsigned int r = 0; r < D; ++r)
        {
          double y[Lanes];
          for (unsigned int l = 0; l < Lanes; ++l)
          {
            y[l] = 0.0;
          }
          for (unsigned int c = 0; c < D; ++c)
          {
            for (unsigned int l = 0; l < Lanes; ++l)
            {
              y[l] += S[r][c][l] * g[(slot * D + c) * Lanes + l];
            }
          }
          for (unsigned int l = 0; l < Lanes; ++l)
          {
            t[(slot * D + r) * Lanes + l] = y[l];
          }
        }
      }
    }
  }

  /** q = K p (0 on fixed nodes) at the nodes of node blocks [b0, b1) from the element stresses and node terms, and each
   * block's partial sum of p . q (NodeApplyBlock: one warp per node, lane l summing the node's incident elements l,
   * l + 32, ... in element order, then the warp's tree). A lane's first incidence is its node term; only nodes with
   * more than 32 incident elements add further ones here. */
  void
  ApplyNodeBlocks(size_t                      b0,
                  size_t                      b1,
                  const std::vector<double> & p,
                  const std::vector<double> & terms,
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
          const int64_t begin = m_Start[a], end = m_Start[a + 1];
          lanes = static_cast<int>(std::min<int64_t>(Warp, end - begin));
          for (int lane = 0; lane < lanes; ++lane)
          {
            const double * t = &terms[m_TermOffset[begin + lane]];
            for (unsigned int k = 0; k < D; ++k)
            {
              y[lane][k] = t[k * Lanes];
            }
          }
          for (int64_t i = begin + Warp; i < end; ++i)
          {
            const size_t e = static_cast<size_t>(m_Incidence[i] / NV), slot = static_cast<size_t>(m_Incidence[i] % NV);
            double       S[D * D];
            ElasticElementStress<D>(&m_Geometry[e * Stride], m_Mesh->elements[e].data(), p.data(), m_Lambda, m_Mu, S);
            AddElasticNodeTerm<D>(S, &m_Geometry[e * Stride + slot * D], y[(i - begin) % Warp]);
          }
        }
        // the warp's shuffle-down tree for the D sums at once (WarpSum's additions, component by component; a WarpSum
        // generalised to D values per lane through a pointer made the product 4 % slower, so it is written out here)
        for (int o = Warp / 2, n = lanes; o > 0; o >>= 1)
        {
          for (int l = 0; l < std::min(o, n - o); ++l)
          {
            for (unsigned int k = 0; k < D; ++k)
            {
              y[l][k] = y[l][k] + y[l + o][k];
            }
          }
          n = std::min(n, o);
        }
        double sum = 0.0;
        for (unsigned int k = 0; k < D; ++k)
        {
          const double yk = lanes > 0 ? y[0][k] : 0.0;
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
  std::vector<double>    m_BlockGeometry; // m_Geometry in blocks of Lanes elements, lane innermost
  std::vector<int32_t>   m_BlockVertices; // the elements' vertices, likewise
  std::vector<size_t>    m_TermOffset;    // per incidence: where its node term starts in ElementBlocks' output
  std::vector<int64_t>   m_Start, m_Incidence;
  std::vector<double>    m_InverseDiagonal;
};
} // namespace dmr
} // namespace itk

#endif
