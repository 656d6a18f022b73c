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
#include "itkLinearElasticFEMSolver.h"
#include "dmrDelaunay3D.h"
#include "dmrDualMeshPhantom.h"
#include "dmrObjectChecks.h"
#include "dmrTestHelpers.h"
#include "gtest/gtest.h"

#include <cmath>
#include <limits>
#include <random>

namespace
{
constexpr double lambda = 2.5;
constexpr double mu = 0.8;

template <unsigned int D>
typename itk::LinearElasticFEMSolver<D>::Pointer
MakeSolver(const itk::dmr::SimplexMesh<D> & mesh)
{
  auto solver = itk::LinearElasticFEMSolver<D>::New();
  solver->SetLambda(lambda);
  solver->SetMu(mu);
  solver->SetMesh(mesh);
  return solver;
}

/** u_i = sum_j A[i][j] x_j + b_i at every node. */
template <unsigned int D>
std::vector<double>
AffineNodalField(const itk::dmr::SimplexMesh<D> & mesh, const double (&A)[D][D], const double (&b)[D])
{
  std::vector<double> u(mesh.NumberOfNodes() * D);
  for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
  {
    for (unsigned int i = 0; i < D; ++i)
    {
      u[a * D + i] = b[i];
      for (unsigned int j = 0; j < D; ++j)
      {
        u[a * D + i] += A[i][j] * mesh.nodes[a * D + j];
      }
    }
  }
  return u;
}

Eigen::VectorXd
Apply(const Eigen::SparseMatrix<double> & K, const std::vector<double> & u)
{
  return K * Eigen::Map<const Eigen::VectorXd>(u.data(), static_cast<Eigen::Index>(u.size()));
}

double
MaxAbs(const Eigen::SparseMatrix<double> & K)
{
  double m = 0.0;
  for (Eigen::Index c = 0; c < K.outerSize(); ++c)
  {
    for (Eigen::SparseMatrix<double>::InnerIterator it(K, c); it; ++it)
    {
      m = std::max(m, std::abs(it.value()));
    }
  }
  return m;
}

double
BoxMeasure(const itk::dmr::SimplexMesh<2> & mesh)
{
  double m = 0.0;
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    m += mesh.SignedMeasure(e);
  }
  return m;
}
double
BoxMeasure(const itk::dmr::SimplexMesh<3> & mesh)
{
  double m = 0.0;
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    m += mesh.SignedMeasure(e);
  }
  return m;
}

/** All the patch tests on one mesh. */
template <unsigned int D>
void
CheckPatchTests(const itk::dmr::SimplexMesh<D> & mesh)
{
  const auto   solver = MakeSolver<D>(mesh);
  const auto & K = solver->GetStiffnessMatrix();
  const size_t nDof = mesh.NumberOfNodes() * D;
  ASSERT_EQ(static_cast<size_t>(K.rows()), nDof);
  ASSERT_EQ(static_cast<size_t>(K.cols()), nDof);
  const double scale = MaxAbs(K);
  ASSERT_GT(scale, 0.0);

  // symmetric
  const Eigen::SparseMatrix<double> transpose = K.transpose();
  EXPECT_LE(MaxAbs(K - transpose), 1e-12 * scale);
  // positive diagonal
  for (size_t i = 0; i < nDof; ++i)
  {
    EXPECT_GT(K.coeff(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(i)), 0.0);
  }

  double extent = 0.0;
  for (double x : mesh.nodes)
  {
    extent = std::max(extent, std::abs(x));
  }

  // rigid translation: no force anywhere, no energy
  double zero[D][D] = {}, t[D];
  for (unsigned int i = 0; i < D; ++i)
  {
    t[i] = 0.7 - 0.4 * i;
  }
  const auto translation = AffineNodalField<D>(mesh, zero, t);
  EXPECT_LE(Apply(K, translation).template lpNorm<Eigen::Infinity>(), 1e-11 * scale);
  EXPECT_NEAR(solver->ElasticEnergy(translation), 0.0, 1e-11 * scale * nDof);

  // infinitesimal rotation (skew A): zero strain, so no force and no energy
  double W[D][D] = {}, b0[D] = {};
  W[0][1] = 0.02;
  W[1][0] = -0.02;
  if (D == 3)
  {
    W[0][D - 1] = -0.013;
    W[D - 1][0] = 0.013;
    W[1][D - 1] = 0.031;
    W[D - 1][1] = -0.031;
  }
  const auto rotation = AffineNodalField<D>(mesh, W, b0);
  EXPECT_LE(Apply(K, rotation).template lpNorm<Eigen::Infinity>(), 1e-11 * scale * extent);
  EXPECT_NEAR(solver->ElasticEnergy(rotation), 0.0, 1e-11 * scale * extent * extent * nDof);

  // constant strain u = A x: zero net force at every node not on the boundary, and the exact strain energy
  double A[D][D];
  for (unsigned int i = 0; i < D; ++i)
  {
    for (unsigned int j = 0; j < D; ++j)
    {
      A[i][j] = 0.01 * (1.0 + i + 2.0 * j) - (i == j ? 0.015 * (i + 1) : 0.0);
    }
  }
  const auto            strain = AffineNodalField<D>(mesh, A, b0);
  const Eigen::VectorXd force = Apply(K, strain);
  double                maxForce = 0.0, maxInterior = 0.0;
  size_t                interior = 0;
  for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
  {
    for (unsigned int i = 0; i < D; ++i)
    {
      maxForce = std::max(maxForce, std::abs(force[a * D + i]));
      if (!mesh.fixed[a])
      {
        maxInterior = std::max(maxInterior, std::abs(force[a * D + i]));
      }
    }
    interior += !mesh.fixed[a];
  }
  ASSERT_GT(interior, 0u);
  EXPECT_GT(maxForce, 1e-3 * scale * 0.01 * extent) << "the boundary carries the traction: forces there";
  EXPECT_LE(maxInterior, 1e-10 * scale * extent) << "constant-strain patch test failed at an interior node";
  // W = |Omega| (lambda/2 tr(eps)^2 + mu eps:eps), exact for a linear field
  double trace = 0.0, eps2 = 0.0;
  for (unsigned int i = 0; i < D; ++i)
  {
    trace += A[i][i];
    for (unsigned int j = 0; j < D; ++j)
    {
      const double e = 0.5 * (A[i][j] + A[j][i]);
      eps2 += e * e;
    }
  }
  const double expected = BoxMeasure(mesh) * (0.5 * lambda * trace * trace + mu * eps2);
  EXPECT_NEAR(solver->ElasticEnergy(strain), expected, 1e-9 * expected);

  // Solve: K u = f at the free nodes, u = 0 at the fixed ones
  std::mt19937                           engine(5u);
  std::uniform_real_distribution<double> uniform(-1.0, 1.0);
  std::vector<double>                    f(nDof), u;
  for (auto & v : f)
  {
    v = uniform(engine);
  }
  double fNorm = 0.0;
  for (double v : f)
  {
    fNorm = std::max(fNorm, std::abs(v));
  }
  // both ways: conjugate gradients (threshold 0; first, so that no earlier solution warm-starts it) and the
  // factorisation of a small system (the default)
  std::vector<double> iterative;
  for (const itk::SizeValueType maximum : { itk::SizeValueType{ 0 }, itk::SizeValueType{ 1000000 } })
  {
    solver->SetDirectSolverMaximumDegreesOfFreedom(maximum);
    solver->SetMesh(mesh);
    solver->Solve(f, u);
    EXPECT_EQ(solver->GetDirect(), maximum > 0);
    EXPECT_EQ(solver->GetLastIterations() > 0, maximum == 0) << "CG products " << solver->GetLastIterations();
    ASSERT_EQ(u.size(), nDof);
    const Eigen::VectorXd Ku = Apply(K, u);
    for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
    {
      for (unsigned int i = 0; i < D; ++i)
      {
        if (mesh.fixed[a])
        {
          EXPECT_EQ(u[a * D + i], 0.0) << "fixed node " << a;
        }
        else
        {
          EXPECT_NEAR(Ku[a * D + i], f[a * D + i], (maximum > 0 ? 1e-12 : 1e-9) * fNorm) << "free node " << a;
        }
      }
    }
    EXPECT_GT(solver->ElasticEnergy(u), 0.0);
    if (maximum == 0)
    {
      iterative = u;
    }
    else
    {
      for (size_t i = 0; i < nDof; ++i)
      {
        EXPECT_NEAR(u[i], iterative[i], 1e-9 * (1.0 + std::abs(iterative[i])));
      }
    }
  }
  EXPECT_EQ(solver->GetNumberOfFreeNodes(), interior);
}

TEST(LinearElasticFEMSolver, PatchTestsOnARegularMesh2D)
{
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 24, 20 }, std::array<double, 2>{ 1.0, 1.5 });
  CheckPatchTests<2>(itk::dmr::MakeRegularMesh<2>(grid, { 6, 5 }));
}

TEST(LinearElasticFEMSolver, PatchTestsOnADualMesh2D)
{
  const auto phantom = itk::dmr::test::MakeUnitSpacingDualMeshPhantom();
  CheckPatchTests<2>(phantom.GetMesh());
}

// Regression test (see DualMeshFilter.BorderNodesLieExactlyOnTheBox): with spacing 0.8 x 1.3 the dual mesh has sliver
// triangles of area ~2e-13 along the border, K has entries ~1e13 and the constant-strain energy is off by 28%.
TEST(LinearElasticFEMSolver, PatchTestsOnAnAnisotropicDualMesh2D)
{
  const auto phantom = itk::dmr::test::MakeDualMeshPhantom();
  CheckPatchTests<2>(phantom.GetMesh());
}

TEST(LinearElasticFEMSolver, PatchTestsOnARegularMesh3D)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 10, 9, 8 }, std::array<double, 3>{ 1.0, 1.2, 0.9 });
  CheckPatchTests<3>(itk::dmr::MakeRegularMesh<3>(grid, { 5, 4, 4 }));
}

/** The compressed assembly equals the sum of the element matrices assembled from triplets, entry for entry (the same
 * additions in the same element order), and solving it reproduces K u = f on the free nodes. */
template <unsigned int D>
void
CheckAssemblyAgainstTriplets(const itk::dmr::SimplexMesh<D> & mesh)
{
  const auto                          solver = MakeSolver<D>(mesh);
  constexpr unsigned int              NV = D + 1;
  std::vector<Eigen::Triplet<double>> triplets;
  double                              Ke[NV * D * NV * D];
  for (size_t e = 0; e < mesh.elements.size(); ++e)
  {
    solver->ElementStiffness(mesh, e, Ke);
    for (unsigned int a = 0; a < NV; ++a)
      for (unsigned int i = 0; i < D; ++i)
        for (unsigned int b = 0; b < NV; ++b)
          for (unsigned int j = 0; j < D; ++j)
            triplets.emplace_back(
              mesh.elements[e][a] * D + i, mesh.elements[e][b] * D + j, Ke[(a * D + i) * NV * D + b * D + j]);
  }
  Eigen::SparseMatrix<double> reference(mesh.NumberOfNodes() * D, mesh.NumberOfNodes() * D);
  reference.setFromTriplets(triplets.begin(), triplets.end());
  const auto & K = solver->GetStiffnessMatrix();
  ASSERT_EQ(K.nonZeros(), reference.nonZeros());
  ASSERT_EQ(K.rows(), reference.rows());
  size_t differ = 0;
  for (Eigen::Index c = 0; c < reference.outerSize(); ++c)
  {
    for (Eigen::SparseMatrix<double>::InnerIterator it(reference, c); it; ++it)
    {
      differ += K.coeff(it.row(), it.col()) != it.value() ? 1 : 0;
    }
  }
  EXPECT_EQ(differ, 0u);
}

TEST(LinearElasticFEMSolver, CompressedAssemblyEqualsTripletAssembly)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 10, 9, 8 }, std::array<double, 3>{ 1.0, 1.2, 0.9 });
  CheckAssemblyAgainstTriplets<3>(itk::dmr::MakeRegularMesh<3>(grid, { 5, 4, 4 }));
  CheckAssemblyAgainstTriplets<2>(itk::dmr::test::MakeDualMeshPhantom().GetMesh());
}

TEST(LinearElasticFEMSolver, ElementStiffnessOfTheReferenceTriangle)
{
  // unit right triangle, lambda = 0, mu = 1: K = |T| (grad phi_a . grad phi_b I + grad phi_b grad phi_a^T)
  itk::dmr::SimplexMesh<2> mesh;
  mesh.nodes = { 0, 0, 1, 0, 0, 1 };
  mesh.elements = { { 0, 1, 2 } };
  auto solver = itk::LinearElasticFEMSolver<2>::New();
  solver->SetLambda(0.0);
  solver->SetMu(1.0);
  double Ke[36];
  solver->ElementStiffness(mesh, 0, Ke);
  const double g[3][2] = { { -1, -1 }, { 1, 0 }, { 0, 1 } };
  for (unsigned int a = 0; a < 3; ++a)
  {
    for (unsigned int i = 0; i < 2; ++i)
    {
      for (unsigned int b = 0; b < 3; ++b)
      {
        for (unsigned int j = 0; j < 2; ++j)
        {
          const double dot = g[a][0] * g[b][0] + g[a][1] * g[b][1];
          const double expected = 0.5 * ((i == j ? dot : 0.0) + g[a][j] * g[b][i]);
          EXPECT_NEAR(Ke[(a * 2 + i) * 6 + b * 2 + j], expected, 1e-14) << a << i << b << j;
        }
      }
    }
  }
  // lambda adds |T| lambda d_i phi_a d_j phi_b
  solver->SetLambda(3.0);
  double Kl[36];
  solver->ElementStiffness(mesh, 0, Kl);
  EXPECT_NEAR(Kl[(1 * 2 + 0) * 6 + 2 * 2 + 1] - Ke[(1 * 2 + 0) * 6 + 2 * 2 + 1], 0.5 * 3.0 * g[1][0] * g[2][1], 1e-14);
}

/** A 3D solver that solves every system by conjugate gradients to 1e-10 (none factorised): in the GPU's order
 * (dmr::ElasticCG) or on the assembled matrix. */
itk::LinearElasticFEMSolver<3>::Pointer
ConjugateGradientSolver(bool gpuOrder)
{
  auto solver = itk::LinearElasticFEMSolver<3>::New();
  solver->SetLambda(lambda);
  solver->SetMu(mu);
  solver->SetTolerance(1e-10);
  solver->SetDirectSolverMaximumDegreesOfFreedom(0);
  solver->SetGPUOrderSolve(gpuOrder);
  return solver;
}

/** GPUOrderSolve (dmr::ElasticCG, the CUDA back-end's CG order on the CPU) solves the same system as the assembled
 * CG: on a 3D regular mesh with a smooth load, both solutions are within the tolerance's reach of the exact
 * (factorised) one, with u = 0 on fixed nodes; the solve takes some products and is repeatable bit for bit; stopped
 * before convergence, ElasticCG says so. (Its bit-for-bit agreement with the GPU is checked by the GPU tests.) */
TEST(LinearElasticFEMSolver, GPUOrderSolveSolvesTheSystem)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 12, 11, 10 }, std::array<double, 3>{ 1.0, 1.2, 0.9 });
  const auto              mesh = itk::dmr::MakeRegularMesh<3>(grid, { 6, 5, 5 });
  std::vector<double>     f(mesh.NumberOfNodes() * 3);
  for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      f[a * 3 + k] = std::sin(0.7 * mesh.nodes[a * 3] + 0.3 * k) * std::cos(0.5 * mesh.nodes[a * 3 + 1] - 0.2 * k);
    }
  }
  auto exact = itk::LinearElasticFEMSolver<3>::New();
  exact->SetLambda(lambda);
  exact->SetMu(mu);
  exact->SetDirectSolverMaximumDegreesOfFreedom(100000);
  exact->SetMesh(mesh);
  ASSERT_TRUE(exact->GetDirect());
  std::vector<double> reference;
  exact->Solve(f, reference);
  double largest = 0.0;
  for (const double v : reference)
  {
    largest = std::max(largest, std::abs(v));
  }
  ASSERT_GT(largest, 0.0);
  for (const bool gpuOrder : { false, true })
  {
    SCOPED_TRACE(gpuOrder ? "GPU order" : "assembled CG");
    auto solver = ConjugateGradientSolver(gpuOrder);
    solver->SetMesh(mesh);
    ASSERT_FALSE(solver->GetDirect());
    std::vector<double> u;
    solver->Solve(f, u);
    EXPECT_GT(solver->GetLastIterations(), 5u);
    double worst = 0.0;
    for (size_t i = 0; i < u.size(); ++i)
    {
      worst = std::max(worst, std::abs(u[i] - reference[i]));
      if (mesh.fixed[i / 3])
      {
        EXPECT_EQ(u[i], 0.0);
      }
    }
    EXPECT_LE(worst, 1e-6 * largest) << "largest |u| " << largest;
    std::vector<double> again;
    solver->Solve(f, again);
    EXPECT_EQ(again, u);
  }
  // the GPU-order CG directly: the products it reports, u = 0 for a zero load
  itk::dmr::ElasticCG<3> cg;
  cg.SetSystem(mesh, lambda, mu);
  std::vector<double> u(f.size(), 7.0), zero(f.size(), 0.0);
  size_t              products = 0;
  EXPECT_FALSE(cg.Solve(f.data(), u.data(), 1e-12, 3, products));
  EXPECT_EQ(products, 3u);
  EXPECT_TRUE(cg.Solve(zero.data(), u.data(), 1e-12, 100, products));
  EXPECT_EQ(products, 0u);
  EXPECT_EQ(u, zero);
}

/** The Delaunay tetrahedralization of random nodes in a box, some of them on its faces, border nodes fixed: nodes with
 * from a few to more than 32 incident elements. */
itk::dmr::SimplexMesh<3>
RandomBoxMesh(const itk::dmr::Grid<3> & grid, std::mt19937 & rng)
{
  std::vector<double> xyz;
  for (unsigned int q = 0; q < 8; ++q)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      xyz.push_back((q >> k) & 1u ? static_cast<double>(grid.size[k] - 1) * grid.spacing[k] : 0.0);
    }
  }
  for (int i = 0; i < 700; ++i)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      // some nodes on the faces (fixed), the others inside
      const double extent = static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
      const double t = std::uniform_real_distribution<double>(0.0, 1.0)(rng);
      xyz.push_back(i % 7 == k ? 0.0 : (i % 11 == k ? extent : t * extent));
    }
  }
  itk::dmr::SimplexMesh<3> mesh;
  mesh.nodes = xyz;
  std::vector<std::array<int32_t, 4>> tetrahedra;
  itk::dmr::Delaunay3D(xyz, tetrahedra);
  mesh.elements = tetrahedra;
  mesh.OrientPositively();
  mesh.MarkBorderNodes(grid);
  return mesh;
}

/** The largest number of elements that share a node. */
size_t
MostIncidentElements(const itk::dmr::SimplexMesh<3> & mesh)
{
  std::vector<size_t> incident(mesh.NumberOfNodes(), 0);
  for (const auto & t : mesh.elements)
  {
    for (const int32_t v : t)
    {
      ++incident[v];
    }
  }
  return *std::max_element(incident.begin(), incident.end());
}

/** K p as the CUDA back-end's NodeApplyBlock defines it, written out from the shared per-element and per-node functions
 * of dmrElasticOperator.h: the stress of every element, then per node one warp of 32 lanes, lane l summing the node's
 * incident elements l, l + 32, ... in element order, and the whole shuffle-down tree over the 32 lanes (unused lanes
 * +0); fixed nodes 0. */
std::vector<double>
WarpOrderProduct(const itk::dmr::SimplexMesh<3> & mesh, const std::vector<double> & p)
{
  constexpr unsigned int           D = 3, NV = 4, Stride = itk::dmr::ElasticGeometryStride<D>();
  const size_t                     ne = mesh.elements.size(), nn = mesh.NumberOfNodes();
  std::vector<double>              geometry(ne * Stride), stress(ne * D * D);
  std::vector<std::vector<size_t>> incidences(nn);
  for (size_t e = 0; e < ne; ++e)
  {
    double x0[D], inv[D][D];
    mesh.EdgeMatrix(e, x0, &inv);
    itk::dmr::ElasticElementGeometry<D>(&inv[0][0], mesh.nodes.data(), mesh.elements[e].data(), &geometry[e * Stride]);
    itk::dmr::ElasticElementStress<D>(
      &geometry[e * Stride], mesh.elements[e].data(), p.data(), lambda, mu, &stress[e * D * D]);
    for (unsigned int v = 0; v < NV; ++v)
    {
      incidences[mesh.elements[e][v]].push_back(e * NV + v);
    }
  }
  std::vector<double> q(nn * D, 0.0);
  for (size_t a = 0; a < nn; ++a)
  {
    if (mesh.fixed[a])
    {
      continue;
    }
    double y[32][D] = {};
    for (size_t i = 0; i < incidences[a].size(); ++i)
    {
      const size_t e = incidences[a][i] / NV, slot = incidences[a][i] % NV;
      itk::dmr::AddElasticNodeTerm<D>(&stress[e * D * D], &geometry[e * Stride + slot * D], y[i % 32]);
    }
    for (int o = 16; o > 0; o >>= 1)
    {
      for (int l = 0; l < o; ++l)
      {
        for (unsigned int k = 0; k < D; ++k)
        {
          y[l][k] = y[l][k] + y[l + o][k];
        }
      }
    }
    for (unsigned int k = 0; k < D; ++k)
    {
      q[a * D + k] = y[0][k];
    }
  }
  return q;
}

/** The GPU-order CG's product (its elements in vector-friendly blocks, its node terms precomputed) is the product of
 * the CUDA back-end's definition, bit for bit, on one thread and on several. */
TEST(LinearElasticFEMSolver, GPUOrderProductIsTheWarpOrderProduct)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 21, 17, 13 }, std::array<double, 3>{ 1.0, 1.3, 2.1 });
  std::mt19937            rng(20261124);
  const auto              mesh = RandomBoxMesh(grid, rng);
  ASSERT_GT(MostIncidentElements(mesh), 32u);
  ASSERT_NE(mesh.elements.size() % 4, 0u); // a part-filled last block of elements
  itk::dmr::ElasticCG<3> cg;
  cg.SetSystem(mesh, lambda, mu);
  for (int trial = 0; trial < 3; ++trial)
  {
    std::vector<double> p(mesh.NumberOfNodes() * 3);
    for (double & v : p)
    {
      v = std::uniform_real_distribution<double>(-1.0, 1.0)(rng);
    }
    const auto          expected = WarpOrderProduct(mesh, p);
    std::vector<double> q(p.size(), 7.0);
    cg.Apply(p.data(), q.data());
    EXPECT_EQ(q, expected);
    auto threader = itk::MultiThreaderBase::New();
    threader->SetMaximumNumberOfThreads(3);
    threader->SetNumberOfWorkUnits(3);
    std::fill(q.begin(), q.end(), 7.0);
    cg.Apply(p.data(), q.data(), threader);
    EXPECT_EQ(q, expected);
  }
}

/** The GPU-order CG's loops on a threader give the result of one thread, bit for bit, on a mesh whose nodes have from
 * a few to more than 32 incident elements (a node's sum then takes more than one element per lane). */
TEST(LinearElasticFEMSolver, GPUOrderSolveDoesNotDependOnTheThreads)
{
  const itk::dmr::Grid<3> grid(std::array<size_t, 3>{ 21, 17, 13 }, std::array<double, 3>{ 1.0, 1.3, 2.1 });
  std::mt19937            rng(20261124);
  const auto              mesh = RandomBoxMesh(grid, rng);
  ASSERT_GT(MostIncidentElements(mesh), 32u);
  std::vector<double> f(mesh.NumberOfNodes() * 3);
  for (double & v : f)
  {
    v = std::uniform_real_distribution<double>(-1.0, 1.0)(rng);
  }
  itk::dmr::ElasticCG<3> cg;
  cg.SetSystem(mesh, lambda, mu);
  std::vector<double> serial(f.size());
  size_t              serialProducts = 0;
  ASSERT_TRUE(cg.Solve(f.data(), serial.data(), 1e-10, 5000, serialProducts));
  EXPECT_GT(serialProducts, 20u);
  for (const unsigned int units : { 1u, 2u, 3u, 7u })
  {
    SCOPED_TRACE(units);
    auto threader = itk::MultiThreaderBase::New();
    threader->SetMaximumNumberOfThreads(std::max(units, 2u));
    threader->SetNumberOfWorkUnits(units);
    std::vector<double> u(f.size());
    size_t              products = 0;
    ASSERT_TRUE(cg.Solve(f.data(), u.data(), 1e-10, 5000, products, threader));
    EXPECT_EQ(products, serialProducts);
    EXPECT_EQ(u, serial);
  }
  // through the solver, with the registration's threader
  auto solver = ConjugateGradientSolver(true);
  auto threader = itk::MultiThreaderBase::New();
  threader->SetNumberOfWorkUnits(3);
  solver->SetMultiThreader(threader);
  EXPECT_EQ(solver->GetMultiThreader(), threader.GetPointer());
  solver->SetMesh(mesh);
  std::vector<double> u;
  solver->Solve(f, u);
  for (size_t i = 0; i < u.size(); ++i)
  {
    ASSERT_EQ(u[i], mesh.fixed[i / 3] ? 0.0 : serial[i]) << i;
  }
}

TEST(LinearElasticFEMSolver, ObjectMethodsSetGetAndBadUse)
{
  auto solver = itk::LinearElasticFEMSolver<2>::New();
  EXPECT_TRUE(itk::dmr::test::BasicObjectMethods(solver.GetPointer(), "LinearElasticFEMSolver", "Object"));
  EXPECT_TRUE(itk::dmr::test::PrintMentions(solver.GetPointer(),
                                            { "Lambda",
                                              "Mu",
                                              "NumberOfFreeNodes",
                                              "NumberOfDegreesOfFreedom",
                                              "DirectSolverMaximumDegreesOfFreedom",
                                              "GPUOrderSolve",
                                              "MultiThreader" }));
  DMR_EXPECT_SET_GET(solver, Lambda, 4.5);
  DMR_EXPECT_SET_GET(solver, Mu, 0.25);
  EXPECT_EQ(solver->GetDirectSolverMaximumDegreesOfFreedom(), 300u); // the default
  DMR_EXPECT_SET_GET(solver, DirectSolverMaximumDegreesOfFreedom, 12u);
  EXPECT_FALSE(solver->GetGPUOrderSolve()); // the default
  DMR_EXPECT_SET_GET(solver, GPUOrderSolve, true);
  solver->SetLambda(-1.0);
  EXPECT_EQ(solver->GetLambda(), 0.0);
  solver->SetMu(0.0);
  EXPECT_GT(solver->GetMu(), 0.0);
  std::vector<double> f(8, 1.0), u;
  EXPECT_THROW(solver->Solve(f, u), itk::ExceptionObject);
  // a mesh with only fixed nodes solves to zero
  const itk::dmr::Grid<2> grid(std::array<size_t, 2>{ 5, 5 }, std::array<double, 2>{ 1.0, 1.0 });
  const auto              mesh = itk::dmr::MakeRegularMesh<2>(grid, { 2, 2 });
  solver->SetMu(1.0);
  solver->SetMesh(mesh);
  EXPECT_EQ(solver->GetNumberOfFreeNodes(), 0u);
  solver->Solve(f, u);
  EXPECT_EQ(u, std::vector<double>(8, 0.0));
  // NaN passes the clamping setters, and an infinite one is clamped to the largest double (lambda + 2 mu is then
  // infinite): SetMesh refuses both, where Solve said "Lambda or Mu changed after SetMesh()" (NaN != NaN)
  for (const auto & [lambda, mu] : { std::make_pair(std::nan(""), 1.0),
                                     std::make_pair(1.0, std::nan("")),
                                     std::make_pair(1.0, std::numeric_limits<double>::infinity()) })
  {
    auto bad = itk::LinearElasticFEMSolver<2>::New();
    bad->SetLambda(lambda);
    bad->SetMu(mu);
    try
    {
      bad->SetMesh(mesh);
      ADD_FAILURE() << "SetMesh accepted lambda " << lambda << ", mu " << mu;
    }
    catch (const itk::ExceptionObject & e)
    {
      EXPECT_NE(std::string(e.GetDescription()).find("must be finite"), std::string::npos) << e.GetDescription();
    }
  }
}
} // namespace
