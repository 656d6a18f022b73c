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
#include "dmrDelaunay3D.h"

#include "dmrGrid.h"
#include "itkMacro.h"
#include "itkMultiThreaderBase.h"
#include <CGAL/Delaunay_triangulation_3.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_cell_base_with_info_3.h>
#include <CGAL/Triangulation_vertex_base_with_info_3.h>
#include <tetgen.h>
#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>
#include <numeric>

namespace itk
{
namespace dmr
{
namespace
{
/** Fewest nodes per block (owned region) of the block decomposition, and the most blocks. */
constexpr size_t       MinimumBlockNodes = 150;
constexpr unsigned int MaximumBlocks = 64;
constexpr unsigned int BlockRounds = 3;

/** For every node the first node at the same position (itself when it is the first). */
std::vector<int32_t>
FirstAtSamePosition(const std::vector<double> & xyz)
{
  const size_t         n = xyz.size() / 3;
  std::vector<int32_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int32_t a, int32_t b) {
    return std::lexicographical_compare(&xyz[3 * a], &xyz[3 * a] + 3, &xyz[3 * b], &xyz[3 * b] + 3);
  });
  std::vector<int32_t> first(n);
  for (size_t k = 0; k < n; ++k)
  {
    const int32_t i = order[k];
    const bool    same = k > 0 && std::equal(&xyz[3 * i], &xyz[3 * i] + 3, &xyz[3 * first[order[k - 1]]]);
    first[i] = same ? first[order[k - 1]] : i; // stable sort: the lowest index comes first in a run
  }
  return first;
}

/** How many blocks can run side by side: the threader's work units, at most its threads (an ITK 5.2 pool reports
 * the pool's size, which only grows), 1 without a threader. */
unsigned int
Parallelism(const MultiThreaderBase * threader)
{
  return threader ? std::max(1u, std::min(threader->GetNumberOfWorkUnits(), threader->GetMaximumNumberOfThreads()))
                  : 1u;
}

/** The nodes that are the first at their position, in node order. */
std::vector<int32_t>
UniqueNodes(const std::vector<double> & xyz)
{
  const std::vector<int32_t> first = FirstAtSamePosition(xyz);
  std::vector<int32_t>       unique;
  for (size_t i = 0; i < first.size(); ++i)
  {
    if (first[i] == static_cast<int32_t>(i))
    {
      unique.push_back(static_cast<int32_t>(i));
    }
  }
  return unique;
}

uint64_t
SplitMix64(uint64_t x)
{
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

/** True when the nodes span 3D space by more than 1e-12 of their extent (TetGen 1.5 crashes on a coplanar set). */
bool
SpansSpace(const std::vector<double> & xyz, const std::vector<int32_t> & nodes)
{
  auto sub = [&](int32_t a, int32_t b, double(&d)[3]) {
    for (unsigned int k = 0; k < 3; ++k)
    {
      d[k] = xyz[3 * a + k] - xyz[3 * b + k];
    }
  };
  auto cross = [](const double(&u)[3], const double(&v)[3], double(&w)[3]) {
    w[0] = u[1] * v[2] - u[2] * v[1];
    w[1] = u[2] * v[0] - u[0] * v[2];
    w[2] = u[0] * v[1] - u[1] * v[0];
  };
  auto          dot = [](const double(&u)[3], const double(&v)[3]) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; };
  const int32_t p0 = nodes[0];
  int32_t       p1 = p0, p2 = p0;
  double        best = 0.0, d[3], e[3], w[3];
  for (int32_t i : nodes)
  {
    sub(i, p0, d);
    if (dot(d, d) > best)
    {
      best = dot(d, d);
      p1 = i;
    }
  }
  if (best == 0.0)
  {
    return false;
  }
  const double length = std::sqrt(best);
  sub(p1, p0, e);
  best = 0.0;
  for (int32_t i : nodes)
  {
    sub(i, p0, d);
    cross(e, d, w);
    if (dot(w, w) > best)
    {
      best = dot(w, w);
      p2 = i;
    }
  }
  if (best == 0.0)
  {
    return false;
  }
  double normal[3];
  sub(p2, p0, d);
  cross(e, d, normal);
  const double area = std::sqrt(dot(normal, normal));
  double       height = 0.0;
  for (int32_t i : nodes)
  {
    sub(i, p0, d);
    height = std::max(height, std::abs(dot(normal, d)) / area);
  }
  return height > 1e-12 * length;
}

double
LongestEdge(const double * p[4])
{
  double longest = 0.0;
  for (unsigned int a = 0; a < 4; ++a)
  {
    for (unsigned int b = a + 1; b < 4; ++b)
    {
      double s = 0.0;
      for (unsigned int k = 0; k < 3; ++k)
      {
        s += (p[a][k] - p[b][k]) * (p[a][k] - p[b][k]);
      }
      longest = std::max(longest, s);
    }
  }
  return std::sqrt(longest);
}

/** Circumcentre and radius of a tetrahedron; false when it is flat (no finite circumsphere in double). */
bool
Circumsphere(const double * a, const double * b, const double * c, const double * d, double * centre, double & radius)
{
  double u[3], v[3], w[3];
  for (unsigned int k = 0; k < 3; ++k)
  {
    u[k] = b[k] - a[k];
    v[k] = c[k] - a[k];
    w[k] = d[k] - a[k];
  }
  const double uu = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
  const double vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  const double ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
  const double vxw[3] = { v[1] * w[2] - v[2] * w[1], v[2] * w[0] - v[0] * w[2], v[0] * w[1] - v[1] * w[0] };
  const double wxu[3] = { w[1] * u[2] - w[2] * u[1], w[2] * u[0] - w[0] * u[2], w[0] * u[1] - w[1] * u[0] };
  const double uxv[3] = { u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0] };
  const double det = 2.0 * (u[0] * vxw[0] + u[1] * vxw[1] + u[2] * vxw[2]);
  if (det == 0.0)
  {
    return false;
  }
  double o[3];
  for (unsigned int k = 0; k < 3; ++k)
  {
    o[k] = (uu * vxw[k] + vv * wxu[k] + ww * uxv[k]) / det;
    centre[k] = a[k] + o[k];
  }
  radius = std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
  return std::isfinite(radius) && std::isfinite(centre[0]) && std::isfinite(centre[1]) && std::isfinite(centre[2]);
}

/** Signed volume x 6: det [b - a, c - a, d - a]. */
double
SixVolume(const double * a, const double * b, const double * c, const double * d)
{
  double m[3][3];
  for (unsigned int r = 0; r < 3; ++r)
  {
    m[r][0] = b[r] - a[r];
    m[r][1] = c[r] - a[r];
    m[r][2] = d[r] - a[r];
  }
  return m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
         m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
}

/** The vertices in ascending order, then the last two swapped when that order has the other orientation: one
 * canonical form per oriented tetrahedron. */
std::array<int32_t, 4>
CanonicalTetrahedron(std::array<int32_t, 4> t)
{
  bool odd = false; // parity of the sorting permutation (insertion sort: one swap flips it)
  for (unsigned int i = 1; i < 4; ++i)
  {
    for (unsigned int j = i; j > 0 && t[j - 1] > t[j]; --j)
    {
      std::swap(t[j - 1], t[j]);
      odd = !odd;
    }
  }
  if (odd)
  {
    std::swap(t[2], t[3]);
  }
  return t;
}

/** The nodes' bounding box. */
void
BoundingBox(const std::vector<double> & xyz, double * lo, double * hi)
{
  for (unsigned int k = 0; k < 3; ++k)
  {
    lo[k] = hi[k] = xyz[k];
  }
  for (size_t i = 0; i < xyz.size() / 3; ++i)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      lo[k] = std::min(lo[k], xyz[3 * i + k]);
      hi[k] = std::max(hi[k], xyz[3 * i + k]);
    }
  }
}

/** Whether the convex hull of the distinct nodes `unique` is their bounding box [lo, hi] (its 8 corners are nodes,
 * every extent positive), as for the dual mesh's nodes. The box is that of all the nodes: the others lie on them. */
bool
HullIsBoundingBox(const std::vector<double> & xyz, const std::vector<int32_t> & unique, double * lo, double * hi)
{
  if (unique.empty())
  {
    return false;
  }
  BoundingBox(xyz, lo, hi);
  bool corner[8] = {};
  for (int32_t i : unique)
  {
    unsigned int mask = 0;
    bool         atCorner = true;
    for (unsigned int k = 0; k < 3 && atCorner; ++k)
    {
      const double x = xyz[3 * i + k];
      atCorner = x == lo[k] || x == hi[k];
      mask |= x == hi[k] ? 1u << k : 0u;
    }
    if (atCorner)
    {
      corner[mask] = true;
    }
  }
  return std::all_of(corner, corner + 8, [](bool c) { return c; }) && hi[0] > lo[0] && hi[1] > lo[1] && hi[2] > lo[2];
}

using BlockKernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using BlockVertex = CGAL::Triangulation_vertex_base_with_info_3<int32_t, BlockKernel>;
using BlockCell = CGAL::Triangulation_cell_base_with_info_3<int32_t, BlockKernel>;
using BlockTds = CGAL::Triangulation_data_structure_3<BlockVertex, BlockCell>;
using BlockTriangulation = CGAL::Delaunay_triangulation_3<BlockKernel, BlockTds>;

/** What one block contributes: its accepted tetrahedra (canonical, sorted), the faces it shares with other blocks'
 * tetrahedra, the volume it covers, and whether every tetrahedron it owns could be vouched for. */
struct BlockResult
{
  std::vector<std::array<int32_t, 4>> tetrahedra;
  std::vector<std::array<int32_t, 3>> crossFaces;
  double                              sixVolume{ 0.0 };
  bool                                complete{ false };
  double                              neededMargin{ 0.0 }; // when incomplete: the margin its spheres asked for
  std::vector<double>                 ownerNeeds;      // per block: the margin it needs to see a tetrahedron it owns
  bool                                failed{ false }; // threw
};

/** The block decomposition of Delaunay3D (see BlockDelaunay3D in the header): false when it does not apply or cannot
 * vouch for its result. `unique`: the distinct nodes, whose convex hull is their bounding box [lo, hi] (the callers
 * check it with HullIsBoundingBox). */
bool
BlockDelaunay(const std::vector<double> &           xyz,
              const std::vector<int32_t> &          unique,
              const double *                        lo,
              const double *                        hi,
              MultiThreaderBase *                   threader,
              double                                marginFactor,
              std::vector<std::array<int32_t, 4>> & tetrahedra,
              BlockDelaunayStatistics *             statistics)
{
  BlockDelaunayStatistics   unused;
  BlockDelaunayStatistics & stats = statistics ? *statistics : unused;
  stats = BlockDelaunayStatistics{};
  const size_t n = unique.size();
  if (n < 4 || !(marginFactor > 0.0))
  {
    return false;
  }
  const double extent[3] = { hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2] };
  const double volume = extent[0] * extent[1] * extent[2];
  const double spacing = std::cbrt(volume / static_cast<double>(n)); // mean node spacing
  // The layout with the shortest critical path on the threader's threads (at least 2): waves of blocks times the
  // largest extended block's share of the box (about its share of the nodes), ties to fewer blocks; at least
  // MinimumBlockNodes nodes per block region, at most MaximumBlocks blocks.
  const double threads = std::max(2.0, static_cast<double>(Parallelism(threader)));
  const double firstMargin = marginFactor * spacing;
  int          blocks[3] = { 1, 1, 1 };
  double       best = std::numeric_limits<double>::infinity();
  for (int b0 = 1; b0 <= static_cast<int>(MaximumBlocks); ++b0)
  {
    for (int b1 = 1; b0 * b1 <= static_cast<int>(MaximumBlocks); ++b1)
    {
      for (int b2 = 1; b0 * b1 * b2 <= static_cast<int>(MaximumBlocks); ++b2)
      {
        const int b[3] = { b0, b1, b2 }, total = b0 * b1 * b2;
        if (total < 2 || static_cast<double>(n) / total < static_cast<double>(MinimumBlockNodes))
        {
          continue;
        }
        double share = 1.0;
        for (unsigned int k = 0; k < 3; ++k)
        {
          const double step = extent[k] / b[k];
          // the longest extended block along k (an inner one, or an end one when there are 1 or 2)
          const double inner = b[k] > 2 ? step + 2.0 * firstMargin : step + firstMargin;
          share *= b[k] == 1 ? 1.0 : std::min(extent[k], inner) / extent[k];
        }
        const double cost = std::ceil(total / threads) * share;
        if (cost < best)
        {
          best = cost;
          std::copy(b, b + 3, blocks);
        }
      }
    }
  }
  const int numberOfBlocks = blocks[0] * blocks[1] * blocks[2];
  if (numberOfBlocks < 2)
  {
    return false;
  }
  stats.numberOfBlocks = static_cast<unsigned int>(numberOfBlocks);
  const double diagonal = std::sqrt(extent[0] * extent[0] + extent[1] * extent[1] + extent[2] * extent[2]);
  auto         boundary = [&](unsigned int k, int j) {
    return j <= 0 ? lo[k] : (j >= blocks[k] ? hi[k] : lo[k] + extent[k] * static_cast<double>(j) / blocks[k]);
  };
  auto ownerOf = [&](const double * c) {
    int owner = 0, stride = 1;
    for (unsigned int k = 0; k < 3; ++k)
    {
      const double t = std::min(std::max(c[k], lo[k]), hi[k]);
      int          j = static_cast<int>(std::floor((t - lo[k]) / extent[k] * blocks[k]));
      j = std::min(std::max(j, 0), blocks[k] - 1);
      owner += j * stride;
      stride *= blocks[k];
    }
    return owner;
  };
  // a face whose three nodes lie on one plane of the box is on the hull
  auto onBox = [&](int32_t a, int32_t b, int32_t c) {
    for (unsigned int k = 0; k < 3; ++k)
    {
      for (const double plane : { lo[k], hi[k] })
      {
        if (xyz[3 * a + k] == plane && xyz[3 * b + k] == plane && xyz[3 * c + k] == plane)
        {
          return true;
        }
      }
    }
    return false;
  };

  std::vector<BlockResult> results(static_cast<size_t>(numberOfBlocks));
  std::vector<double>      margins(results.size(), marginFactor * spacing);
  auto                     runBlock = [&](size_t s, double margin) {
    BlockResult & result = results[s];
    result = BlockResult{};
    result.ownerNeeds.assign(results.size(), 0.0);
    const int j[3] = { static_cast<int>(s) % blocks[0],
                       (static_cast<int>(s) / blocks[0]) % blocks[1],
                       static_cast<int>(s) / (blocks[0] * blocks[1]) };
    // the block's region extended by the margin (closed), clipped to the box
    double elo[3], ehi[3];
    bool   clippedLo[3], clippedHi[3];
    for (unsigned int k = 0; k < 3; ++k)
    {
      elo[k] = boundary(k, j[k]) - margin;
      ehi[k] = boundary(k, j[k] + 1) + margin;
      clippedLo[k] = elo[k] <= lo[k];
      clippedHi[k] = ehi[k] >= hi[k];
    }
    std::vector<std::pair<BlockKernel::Point_3, int32_t>> points;
    for (int32_t i : unique)
    {
      const double * x = &xyz[3 * i];
      if (x[0] >= elo[0] && x[0] <= ehi[0] && x[1] >= elo[1] && x[1] <= ehi[1] && x[2] >= elo[2] && x[2] <= ehi[2])
      {
        points.emplace_back(BlockKernel::Point_3(x[0], x[1], x[2]), i);
      }
    }
    BlockTriangulation dt(points.begin(), points.end());
    if (dt.dimension() < 3)
    {
      return; // incomplete
    }
    // accepted: owned, and no node outside the extended region can lie in its circumsphere
    result.complete = true;
    for (auto c = dt.finite_cells_begin(); c != dt.finite_cells_end(); ++c)
    {
      c->info() = 0;
      // from the ascending vertices: every block that has this tetrahedron computes the same centre and owner
      std::array<int32_t, 4> t;
      for (int v = 0; v < 4; ++v)
      {
        t[v] = c->vertex(v)->info();
      }
      std::sort(t.begin(), t.end());
      const double * p[4] = { &xyz[3 * t[0]], &xyz[3 * t[1]], &xyz[3 * t[2]], &xyz[3 * t[3]] };
      double         centre[3], radius = 0.0;
      if (!Circumsphere(p[0], p[1], p[2], p[3], centre, radius))
      {
        result.complete = false; // cannot tell who owns it
        result.neededMargin = std::max(result.neededMargin, 2.0 * margin);
        continue;
      }
      // the part of the sphere inside the box lies in the box `cap`: along axis k within c_k +- sqrt(r^2 - the other
      // axes' squared distances from c to the box); its centre decides the owner, and the tetrahedron's nodes are in it
      radius += 1e-9 * (diagonal + radius); // room for the round-off of centre and radius
      double outside[3], cap[3][2], capCentre[3];
      for (unsigned int k = 0; k < 3; ++k)
      {
        outside[k] = centre[k] < lo[k] ? lo[k] - centre[k] : (centre[k] > hi[k] ? centre[k] - hi[k] : 0.0);
      }
      for (unsigned int k = 0; k < 3; ++k)
      {
        double q = radius * radius;
        for (unsigned int m = 0; m < 3; ++m)
        {
          q -= m == k ? 0.0 : outside[m] * outside[m];
        }
        const double half = q > 0.0 ? std::sqrt(q) : 0.0;
        cap[k][0] = std::max(centre[k] - half, lo[k]);
        cap[k][1] = std::min(centre[k] + half, hi[k]);
        capCentre[k] = 0.5 * (cap[k][0] + cap[k][1]);
      }
      const int owner = ownerOf(capCentre);
      // how far the cap reaches beyond block b's own region (only towards neighbouring blocks)
      auto reach = [&](int b) {
        const int jb[3] = { b % blocks[0], (b / blocks[0]) % blocks[1], b / (blocks[0] * blocks[1]) };
        double    r = 0.0;
        for (unsigned int k = 0; k < 3; ++k)
        {
          r = std::max(r, jb[k] > 0 ? boundary(k, jb[k]) - cap[k][0] : 0.0);
          r = std::max(r, jb[k] + 1 < blocks[k] ? cap[k][1] - boundary(k, jb[k] + 1) : 0.0);
        }
        return r;
      };
      if (reach(static_cast<int>(s)) > margin)
      {
        if (owner == static_cast<int>(s))
        {
          result.complete = false; // a node outside the extended region might be in its sphere
          result.neededMargin = std::max(result.neededMargin, reach(owner));
        }
        continue;
      }
      // a Delaunay tetrahedron of all the nodes
      if (owner != static_cast<int>(s))
      {
        // its owner must see it too: the owner's extended region must hold the cap
        const double needed = reach(owner);
        if (needed > margins[owner])
        {
          result.ownerNeeds[owner] = std::max(result.ownerNeeds[owner], needed);
        }
        continue;
      }
      c->info() = 1;
    }
    if (!result.complete)
    {
      return;
    }
    for (auto c = dt.finite_cells_begin(); c != dt.finite_cells_end(); ++c)
    {
      if (c->info() != 1)
      {
        continue;
      }
      std::array<int32_t, 4> t;
      for (int v = 0; v < 4; ++v)
      {
        t[v] = c->vertex(v)->info();
      }
      result.sixVolume += SixVolume(&xyz[3 * t[0]], &xyz[3 * t[1]], &xyz[3 * t[2]], &xyz[3 * t[3]]);
      result.tetrahedra.push_back(CanonicalTetrahedron(t));
      for (int f = 0; f < 4; ++f)
      {
        const auto neighbour = c->neighbor(f);
        if (!dt.is_infinite(neighbour) && neighbour->info() == 1)
        {
          continue; // shared with a tetrahedron of this block
        }
        std::array<int32_t, 3> face;
        for (int v = 0, m = 0; v < 4; ++v)
        {
          if (v != f)
          {
            face[m++] = t[v];
          }
        }
        if (dt.is_infinite(neighbour) && onBox(face[0], face[1], face[2]))
        {
          continue;
        }
        std::sort(face.begin(), face.end());
        result.crossFaces.push_back(face);
      }
    }
    std::sort(result.tetrahedra.begin(), result.tetrahedra.end());
  };

  std::vector<size_t> todo(results.size());
  std::iota(todo.begin(), todo.end(), size_t{ 0 });
  // Blocks that cannot vouch for a tetrahedron they own, or that another block found too small to see one they own,
  // are redone with the margin that tetrahedron asks for (at least twice the last one), up to BlockRounds rounds.
  for (unsigned int round = 0; round < BlockRounds && !todo.empty(); ++round)
  {
    ParallelForChunkIds(threader, todo.size(), [&](size_t a) {
      try
      {
        runBlock(todo[a], margins[todo[a]]);
      }
      catch (...) // e.g. out of memory: the one-run fallback reports what it meets
      {
        results[todo[a]].failed = true;
      }
    });
    stats.numberOfRuns += todo.size();
    if (std::any_of(results.begin(), results.end(), [](const BlockResult & r) { return r.failed; }))
    {
      return false;
    }
    std::vector<double> needed(results.size(), 0.0);
    for (size_t s = 0; s < results.size(); ++s)
    {
      if (!results[s].complete)
      {
        needed[s] = std::max({ needed[s], 2.0 * margins[s], results[s].neededMargin });
      }
      for (size_t b = 0; b < results.size(); ++b)
      {
        needed[b] = std::max(needed[b], results[s].ownerNeeds[b]);
      }
    }
    todo.clear();
    for (size_t s = 0; s < results.size(); ++s)
    {
      if (needed[s] > margins[s])
      {
        margins[s] = std::max(1.01 * needed[s], margins[s]);
        todo.push_back(s);
      }
    }
  }
  if (!todo.empty())
  {
    return false;
  }
  // every face between blocks is held by exactly two accepted tetrahedra, and together they fill the box
  std::vector<std::array<int32_t, 3>> cross;
  double                              sixVolume = 0.0;
  size_t                              total = 0;
  for (const auto & r : results)
  {
    if (!r.complete)
    {
      return false;
    }
    cross.insert(cross.end(), r.crossFaces.begin(), r.crossFaces.end());
    sixVolume += r.sixVolume;
    total += r.tetrahedra.size();
  }
  std::sort(cross.begin(), cross.end());
  for (size_t i = 0; i < cross.size(); i += 2)
  {
    if (i + 1 >= cross.size() || cross[i] != cross[i + 1] || (i + 2 < cross.size() && cross[i + 2] == cross[i]))
    {
      return false;
    }
  }
  if (!(std::abs(sixVolume - 6.0 * volume) <= 1e-9 * 6.0 * volume))
  {
    return false;
  }
  tetrahedra.clear();
  // the blocks' sorted lists merged: the order of the canonical tetrahedra, whatever the layout
  tetrahedra.reserve(total);
  for (const auto & r : results)
  {
    const auto middle = static_cast<std::ptrdiff_t>(tetrahedra.size());
    tetrahedra.insert(tetrahedra.end(), r.tetrahedra.begin(), r.tetrahedra.end());
    std::inplace_merge(tetrahedra.begin(), tetrahedra.begin() + middle, tetrahedra.end());
  }
  return true;
}

/** One CGAL run on the distinct nodes `unique` (at least 4, spanning space): the triangulation every block of
 * BlockDelaunay takes its tetrahedra from (CGAL's symbolic perturbation, which decides among the tetrahedralizations of
 * cospherical nodes, depends on the nodes only, not on their order or on which others are in the run); canonical
 * tetrahedra, sorted. */
void
CGALOnUnique(const std::vector<double> &           xyz,
             const std::vector<int32_t> &          unique,
             std::vector<std::array<int32_t, 4>> & tetrahedra)
{
  try
  {
    std::vector<std::pair<BlockKernel::Point_3, int32_t>> points;
    points.reserve(unique.size());
    for (int32_t i : unique)
    {
      points.emplace_back(BlockKernel::Point_3(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]), i);
    }
    BlockTriangulation dt(points.begin(), points.end());
    tetrahedra.clear();
    tetrahedra.reserve(dt.number_of_finite_cells());
    for (auto c = dt.finite_cells_begin(); c != dt.finite_cells_end(); ++c)
    {
      std::array<int32_t, 4> t;
      for (int v = 0; v < 4; ++v)
      {
        t[v] = c->vertex(v)->info();
      }
      tetrahedra.push_back(CanonicalTetrahedron(t));
    }
  }
  catch (const std::exception & e)
  {
    itkGenericExceptionMacro("the Delaunay tetrahedralization of " << unique.size() << " nodes failed: " << e.what());
  }
  std::sort(tetrahedra.begin(), tetrahedra.end());
}

/** One TetGen run on the distinct nodes `unique` (at least 4, spanning space): canonical tetrahedra, sorted. */
void
TetGenOnUnique(const std::vector<double> &           xyz,
               const std::vector<int32_t> &          unique, // TetGen's point index -> our node index
               std::vector<std::array<int32_t, 4>> & tetrahedra)
{
  tetgenio in, out;
  in.numberofpoints = static_cast<int>(unique.size());
  in.pointlist = new REAL[3 * unique.size()]; // owned and deleted by tetgenio
  for (size_t k = 0; k < unique.size(); ++k)
  {
    for (unsigned int j = 0; j < 3; ++j)
    {
      in.pointlist[3 * k + j] = xyz[3 * unique[k] + j];
    }
  }
  // z: zero-based indices, Q: quiet, J: keep every input point (unused ones too) so that indices stay ours.
  // No -p: the Delaunay tetrahedralization of the point set, which fills its convex hull.
  char switches[] = "zQJ";
  try
  {
    // TetGen is not reentrant (its predicates' static filters, computed from each call's bounding box, are globals;
    // it seeds and draws the C library's rand()): one run at a time in the process, e.g. when two registrations run
    // on two threads of one program.
    static std::mutex           tetgenMutex;
    std::lock_guard<std::mutex> lock(tetgenMutex);
    tetrahedralize(switches, &in, &out);
  }
  catch (int code)
  {
    itkGenericExceptionMacro("TetGen failed (code " << code << ") on " << unique.size() << " nodes");
  }
  if (out.numberofcorners != 4 || (out.numberoftetrahedra > 0 && out.tetrahedronlist == nullptr))
  {
    itkGenericExceptionMacro("TetGen returned no linear tetrahedra");
  }
  tetrahedra.resize(static_cast<size_t>(out.numberoftetrahedra));
  for (size_t t = 0; t < tetrahedra.size(); ++t)
  {
    for (unsigned int v = 0; v < 4; ++v)
    {
      const int k = out.tetrahedronlist[4 * t + v];
      if (k < 0 || static_cast<size_t>(k) >= unique.size())
      {
        itkGenericExceptionMacro("TetGen returned a tetrahedron with point " << k << " of " << unique.size());
      }
      tetrahedra[t][v] = unique[k];
    }
    tetrahedra[t] = CanonicalTetrahedron(tetrahedra[t]);
  }
  std::sort(tetrahedra.begin(), tetrahedra.end()); // the order of BlockDelaunay3D
}

/** The flips of RepairDelaunay3D on a tetrahedralization whose tetrahedra are positively oriented (CGAL's exact
 * orientation predicate), with the neighbour opposite each vertex (-1 on the box). */
class FlipRepair
{
public:
  using Point = BlockKernel::Point_3;

  FlipRepair(std::vector<Point> & points, std::vector<std::array<int32_t, 4>> tetrahedra)
    : m_Points(points)
    , m_Vertices(std::move(tetrahedra))
    , m_Dead(m_Vertices.size(), 0)
    , m_Created(m_Vertices.size(), 0)
  {
  }

  /** Keeps the linked tetrahedra (after Link) for Reset. */
  void
  Save()
  {
    m_SavedVertices = m_Vertices;
    m_SavedNeighbours = m_Neighbours;
  }

  /** Back to the tetrahedra kept by Save, none dead or created. */
  void
  Reset()
  {
    ResetTo(m_SavedVertices, m_SavedNeighbours);
  }

  /** Back to the given tetrahedra and neighbours (those the repair started from, when they need not be saved: an
   * adopted list), none dead or created. */
  void
  ResetTo(const std::vector<std::array<int32_t, 4>> & vertices, const std::vector<std::array<int32_t, 4>> & neighbours)
  {
    m_Vertices = vertices;
    m_Neighbours = neighbours;
    m_Dead.assign(m_Vertices.size(), 0);
    m_Created.assign(m_Vertices.size(), 0);
    m_Free.clear();
  }

  /** Moves node j (not a vertex of any tetrahedron while it moves: see RemoveNode and InsertNode). */
  void
  SetPoint(int32_t j, const Point & p)
  {
    m_Points[j] = p;
  }

  /** Neighbours from matching faces (their sorted node triples packed into one integer, in three counting-sort
   * passes, one per node): false unless every face is held by one or two tetrahedra that give it opposite
   * orientations (as in a tetrahedralization whose tetrahedra are all positive). */
  bool
  Link(size_t numberOfNodes)
  {
    const size_t nt = m_Vertices.size(), nf = 4 * nt;
    unsigned int bits = 1;
    while ((size_t{ 1 } << bits) < numberOfNodes)
    {
      ++bits;
    }
    // (face key, face) pairs: the key is the sorted node triple a < b < c as (a << 2 bits | b << bits | c)
    std::vector<uint64_t> key(nf), keyOut(nf);
    std::vector<uint32_t> face(nf), faceOut(nf);
    for (size_t t = 0; t < nt; ++t)
    {
      for (unsigned int i = 0; i < 4; ++i)
      {
        uint32_t k[3] = { static_cast<uint32_t>(m_Vertices[t][(i + 1) % 4]),
                          static_cast<uint32_t>(m_Vertices[t][(i + 2) % 4]),
                          static_cast<uint32_t>(m_Vertices[t][(i + 3) % 4]) };
        if (k[0] > k[1])
        {
          std::swap(k[0], k[1]);
        }
        if (k[1] > k[2])
        {
          std::swap(k[1], k[2]);
        }
        if (k[0] > k[1])
        {
          std::swap(k[0], k[1]);
        }
        key[4 * t + i] = (uint64_t{ k[0] } << (2 * bits)) | (uint64_t{ k[1] } << bits) | uint64_t{ k[2] };
        face[4 * t + i] = static_cast<uint32_t>(4 * t + i);
      }
    }
    const uint64_t        mask = (uint64_t{ 1 } << bits) - 1;
    std::vector<uint32_t> count((size_t{ 1 } << bits) + 1);
    for (unsigned int pass = 0; pass < 3; ++pass)
    {
      const unsigned int shift = pass * bits;
      std::fill(count.begin(), count.end(), 0u);
      for (const uint64_t k : key)
      {
        ++count[((k >> shift) & mask) + 1];
      }
      std::partial_sum(count.begin(), count.end(), count.begin());
      for (size_t f = 0; f < nf; ++f)
      {
        const uint32_t to = count[(key[f] >> shift) & mask]++;
        keyOut[to] = key[f];
        faceOut[to] = face[f];
      }
      key.swap(keyOut);
      face.swap(faceOut);
    }
    m_Neighbours.assign(nt, { -1, -1, -1, -1 });
    for (size_t k = 0; k < nf;)
    {
      size_t e = k + 1;
      while (e < nf && key[e] == key[k])
      {
        ++e;
      }
      if (e - k > 2)
      {
        return false;
      }
      if (e - k == 2)
      {
        const uint32_t a = face[k], b = face[k + 1];
        if (!OppositelyOriented(a, b))
        {
          return false; // the two tetrahedra would lie on the same side of their face once both are positive
        }
        m_Neighbours[a / 4][a % 4] = static_cast<int32_t>(b / 4);
        m_Neighbours[b / 4][b % 4] = static_cast<int32_t>(a / 4);
      }
      k = e;
    }
    return true;
  }

  /** Takes the neighbours of an earlier call instead of Link; they are not trusted: CheckNeighbours must accept
   * every tetrahedron before anything else reads them. */
  bool
  Adopt(const std::vector<std::array<int32_t, 4>> & neighbours)
  {
    if (neighbours.size() != m_Vertices.size())
    {
      return false;
    }
    m_Neighbours = neighbours;
    return true;
  }

  /** Whether the adopted neighbours of the tetrahedra of [begin, end) are consistent: each names its tetrahedron
   * back across the same three nodes, which the two order oppositely. With the later checks (free faces on the box,
   * the volume) this proves a tiling as Link's matching does: the faces the neighbours leave free are then exactly
   * the boundary of the tetrahedra. */
  bool
  CheckNeighbours(size_t begin, size_t end) const
  {
    const size_t nt = m_Vertices.size();
    for (size_t t = begin; t < end; ++t)
    {
      for (int i = 0; i < 4; ++i)
      {
        const int32_t u = m_Neighbours[t][i];
        if (u < 0)
        {
          if (u != -1)
          {
            return false;
          }
          continue;
        }
        if (static_cast<size_t>(u) >= nt || static_cast<size_t>(u) == t)
        {
          return false;
        }
        int back = -1;
        for (int k = 0; k < 4; ++k)
        {
          back = m_Neighbours[u][k] == static_cast<int32_t>(t) ? k : back;
        }
        // u's node opposite the shared face is not one of t's, and t's is not one of u's: the other three are shared
        if (back < 0 || IndexOf(static_cast<int32_t>(t), m_Vertices[u][back]) >= 0 ||
            IndexOf(u, m_Vertices[t][i]) >= 0 ||
            !OppositelyOriented(static_cast<uint32_t>(4 * t + i), static_cast<uint32_t>(4 * u + back)))
        {
          return false;
        }
      }
    }
    return true;
  }

  /** The tetrahedra of [begin, end) that are not positively oriented (flags in `positive`, the others listed). */
  void
  Orient(size_t begin, size_t end, std::vector<uint8_t> & positive, std::vector<int32_t> & others) const
  {
    for (size_t t = begin; t < end; ++t)
    {
      positive[t] =
        Orientation(m_Vertices[t][0], m_Vertices[t][1], m_Vertices[t][2], m_Vertices[t][3]) == CGAL::POSITIVE;
      if (!positive[t])
      {
        others.push_back(static_cast<int32_t>(t));
      }
    }
  }

  /** The faces (tetrahedron x 4 + face) of the positively oriented tetrahedra of [begin, end) that are not strictly
   * locally Delaunay (the opposite node inside the circumsphere or on it), each shared face tested once (from its lower
   * tetrahedron). (A face of a tetrahedron that is not positive is checked once the untangling has replaced it.) */
  void
  NonDelaunayFaces(size_t begin, size_t end, const std::vector<uint8_t> & positive, std::vector<uint32_t> & faces) const
  {
    for (size_t t = begin; t < end; ++t)
    {
      for (unsigned int i = 0; i < 4 && positive[t]; ++i)
      {
        const int32_t u = m_Neighbours[t][i];
        if (u > static_cast<int32_t>(t))
        {
          const CGAL::Bounded_side side = Side(static_cast<int32_t>(t), OppositeVertex(u, static_cast<int32_t>(t)));
          if (side != CGAL::ON_UNBOUNDED_SIDE)
          {
            faces.push_back(static_cast<uint32_t>(4 * t + i));
          }
        }
      }
    }
  }

  /** Replaces the tetrahedra that are not positively oriented (a node moved through a face) by flips whose new
   * tetrahedra are all positive: a 2-3 flip with a neighbour whose fourth node now lies on the same side, or a 3-2
   * flip around one of its edges. Flips keep the boundary of the tetrahedra and so the signed volume they cover. The
   * faces of the new tetrahedra go into `queue`. False when some cannot be replaced or after maximumFlips flips. */
  bool
  Untangle(std::vector<int32_t>       tangled,
           std::vector<uint32_t> &    queue,
           size_t                     maximumFlips,
           DelaunayRepairStatistics & stats,
           std::vector<int32_t> &     stuck)
  {
    while (!tangled.empty())
    {
      bool progress = false;
      stuck.clear();
      for (const int32_t t : tangled)
      {
        if (m_Dead[t] || m_Created[t])
        {
          continue; // replaced (its slot may hold a new, positive tetrahedron)
        }
        if (stats.flips23 + stats.flips32 >= maximumFlips)
        {
          stuck.push_back(t);
          return false;
        }
        if (UntangleOne(t, queue, stats))
        {
          progress = true;
        }
        else
        {
          stuck.push_back(t);
        }
      }
      if (!progress)
      {
        return stuck.empty();
      }
      tangled.swap(stuck);
    }
    stuck.clear();
    return true;
  }

  /** Flips from the faces in `queue` until every face they lead to is locally Delaunay (cospherical faces are left
   * alone), at most maximumFlips flips. False on a coplanar configuration inside the box (a 4-4 flip) or too many
   * flips; faces that cannot be flipped are left for the final check. */
  bool
  Flip(std::vector<uint32_t> queue, size_t maximumFlips, DelaunayRepairStatistics & stats)
  {
    while (!queue.empty())
    {
      const uint32_t f = queue.back();
      queue.pop_back();
      const int32_t t = static_cast<int32_t>(f / 4);
      const int     i = static_cast<int>(f % 4);
      const int32_t u = m_Neighbours[t][i];
      if (m_Dead[t] || u < 0)
      {
        continue;
      }
      const int32_t d = m_Vertices[t][i];
      const int32_t e = OppositeVertex(u, t);
      if (Side(t, e) != CGAL::ON_BOUNDED_SIDE)
      {
        continue;
      }
      if (stats.flips23 + stats.flips32 + stats.flips22 >= maximumFlips)
      {
        return false;
      }
      int32_t abc[3];
      FaceNodes(t, i, abc);
      int negative = 0, zero = 0, edge = -1;
      LineThroughFace(abc, d, e, negative, zero, edge);
      if (negative == 0 && zero == 0)
      {
        if (Flip23(t, u, abc, d, e, queue))
        {
          ++stats.flips23;
        }
        continue;
      }
      if (negative + zero != 1)
      {
        continue; // the line de passes beyond a vertex of the face: not flippable from here
      }
      const int32_t x = abc[edge], y = abc[(edge + 1) % 3], z = abc[(edge + 2) % 3];
      if (zero == 1)
      {
        // d, e, x, y coplanar: a 2-2 flip when that plane is the box's (both faces on it), else a 4-4 flip (not done)
        if (m_Neighbours[t][IndexOf(t, z)] >= 0 || m_Neighbours[u][IndexOf(u, z)] >= 0)
        {
          return false;
        }
        if (!Flip32(t, u, -1, x, y, z, d, e, queue))
        {
          continue;
        }
        ++stats.flips22;
        continue;
      }
      // the line de passes beyond the edge xy: a 3-2 flip when xy has exactly three tetrahedra around it
      const int32_t w = ThirdAroundEdge(t, u, z, d, e);
      if (w >= 0 && Flip32(t, u, w, x, y, z, d, e, queue))
      {
        ++stats.flips32;
      }
    }
    return true;
  }

  /** The box the tetrahedra tile (their free faces lie on its planes). */
  void
  SetBox(const double * lo, const double * hi)
  {
    std::copy(lo, lo + 3, m_Lo);
    std::copy(hi, hi + 3, m_Hi);
  }

  /** Six times the signed volume of the tetrahedron with these nodes. */
  double
  SixVolumeOf(const std::array<int32_t, 4> & t) const
  {
    double x[4][3];
    for (int k = 0; k < 4; ++k)
    {
      x[k][0] = m_Points[t[k]].x();
      x[k][1] = m_Points[t[k]].y();
      x[k][2] = m_Points[t[k]].z();
    }
    return SixVolume(x[0], x[1], x[2], x[3]);
  }

  /** Whether the three nodes lie on one plane of the box. */
  bool
  OnOneBoxPlane(const std::array<int32_t, 3> & v) const
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      const double x = m_Points[v[0]][static_cast<int>(k)];
      if ((x == m_Lo[k] || x == m_Hi[k]) && m_Points[v[1]][static_cast<int>(k)] == x &&
          m_Points[v[2]][static_cast<int>(k)] == x)
      {
        return true;
      }
    }
    return false;
  }

  /** Removes node j from a Delaunay tetrahedralization: its tetrahedra (the star) give way to the Delaunay tetrahedra
   * of the star's other nodes that fill the same region, found from the star's outer faces (the link) by a flood fill
   * in CGAL's tetrahedralization of those nodes that stops at the link and at the box. The filling must meet every
   * link face once from j's side, consist of positive tetrahedra and have the star's volume; false otherwise (nothing
   * changed). nearby: one of the new tetrahedra. */
  bool
  RemoveNode(int32_t j, std::vector<uint32_t> & queue, int32_t & nearby)
  {
    std::vector<int32_t> star;
    if (!Star(j, star))
    {
      return false;
    }
    struct LinkFace
    {
      std::array<int32_t, 3> key; // sorted nodes
      int32_t                outer;
      int                    uses;
    };
    std::vector<LinkFace>                                 link;
    std::vector<std::pair<BlockKernel::Point_3, int32_t>> nodes;
    double                                                starVolume = 0.0;
    for (const int32_t t : star)
    {
      const int              i = IndexOf(t, j);
      std::array<int32_t, 3> key = { m_Vertices[t][(i + 1) % 4],
                                     m_Vertices[t][(i + 2) % 4],
                                     m_Vertices[t][(i + 3) % 4] };
      std::sort(key.begin(), key.end());
      link.push_back({ key, m_Neighbours[t][i], 0 });
      for (const int32_t v : key)
      {
        if (std::none_of(nodes.begin(), nodes.end(), [v](const auto & n) { return n.second == v; }))
        {
          nodes.emplace_back(m_Points[v], v);
        }
      }
      starVolume += SixVolumeOf(m_Vertices[t]);
    }
    std::sort(link.begin(), link.end(), [](const LinkFace & a, const LinkFace & b) { return a.key < b.key; });
    if (nodes.size() < 4 || std::adjacent_find(link.begin(), link.end(), [](const LinkFace & a, const LinkFace & b) {
                              return a.key == b.key;
                            }) != link.end())
    {
      return false;
    }
    BlockTriangulation dt(nodes.begin(), nodes.end());
    if (dt.dimension() != 3 || dt.number_of_vertices() != nodes.size())
    {
      return false;
    }
    std::vector<std::pair<int32_t, BlockTriangulation::Vertex_handle>> handles;
    for (auto v = dt.finite_vertices_begin(); v != dt.finite_vertices_end(); ++v)
    {
      handles.emplace_back(v->info(), v);
    }
    std::sort(handles.begin(), handles.end(), [](const auto & a, const auto & b) { return a.first < b.first; });
    const auto handleOf = [&](int32_t v) {
      return std::lower_bound(handles.begin(), handles.end(), v, [](const auto & h, int32_t x) { return h.first < x; })
        ->second;
    };
    const auto linkFaceOf = [&](const std::array<int32_t, 3> & key) -> LinkFace * {
      auto it = std::lower_bound(
        link.begin(), link.end(), key, [](const LinkFace & f, const std::array<int32_t, 3> & k) { return f.key < k; });
      return it != link.end() && it->key == key ? &*it : nullptr;
    };
    // the sorted nodes of face k (opposite vertex k) of a finite cell
    const auto cellFace = [](BlockTriangulation::Cell_handle c, int k) {
      std::array<int32_t, 3> key = { c->vertex((k + 1) % 4)->info(),
                                     c->vertex((k + 2) % 4)->info(),
                                     c->vertex((k + 3) % 4)->info() };
      std::sort(key.begin(), key.end());
      return key;
    };
    for (auto c = dt.all_cells_begin(); c != dt.all_cells_end(); ++c)
    {
      c->info() = 0;
    }
    // seeds: the cell on j's side of each link face
    std::vector<BlockTriangulation::Cell_handle> fill;
    for (const LinkFace & f : link)
    {
      BlockTriangulation::Cell_handle c;
      int                             i0 = 0, i1 = 0, i2 = 0;
      if (!dt.is_facet(handleOf(f.key[0]), handleOf(f.key[1]), handleOf(f.key[2]), c, i0, i1, i2))
      {
        return false;
      }
      const int               k = 6 - i0 - i1 - i2;
      const CGAL::Orientation side =
        CGAL::orientation(m_Points[f.key[0]], m_Points[f.key[1]], m_Points[f.key[2]], m_Points[j]);
      if (dt.is_infinite(c->vertex(k)) ||
          CGAL::orientation(m_Points[f.key[0]], m_Points[f.key[1]], m_Points[f.key[2]], c->vertex(k)->point()) != side)
      {
        c = c->neighbor(k);
      }
      if (dt.is_infinite(c))
      {
        return false;
      }
      if (c->info() == 0)
      {
        c->info() = 1;
        fill.push_back(c);
      }
    }
    const size_t maximumFill = 8 * star.size() + 64;
    for (size_t m = 0; m < fill.size(); ++m)
    {
      const auto c = fill[m];
      for (int k = 0; k < 4; ++k)
      {
        const std::array<int32_t, 3> key = cellFace(c, k);
        if (LinkFace * f = linkFaceOf(key))
        {
          ++f->uses;
          continue;
        }
        const auto n = c->neighbor(k);
        if (dt.is_infinite(n))
        {
          if (!OnOneBoxPlane(key))
          {
            return false;
          }
          continue;
        }
        if (n->info() == 0)
        {
          if (fill.size() == maximumFill)
          {
            return false;
          }
          n->info() = 1;
          fill.push_back(n);
        }
      }
    }
    double                              fillVolume = 0.0;
    std::vector<std::array<int32_t, 4>> tetrahedra(fill.size());
    for (size_t m = 0; m < fill.size(); ++m)
    {
      for (int k = 0; k < 4; ++k)
      {
        tetrahedra[m][k] = fill[m]->vertex(k)->info();
      }
      if (Orientation(tetrahedra[m][0], tetrahedra[m][1], tetrahedra[m][2], tetrahedra[m][3]) != CGAL::POSITIVE)
      {
        return false;
      }
      fillVolume += SixVolumeOf(tetrahedra[m]);
    }
    if (std::any_of(link.begin(), link.end(), [](const LinkFace & f) { return f.uses != 1; }) ||
        !(std::abs(fillVolume - starVolume) <= 1e-9 * starVolume))
    {
      return false;
    }
    // commit: the star out, the filling in, linked to each other, to the outer tetrahedra and to the box
    const std::vector<int32_t> id = Replace(star, tetrahedra);
    for (size_t m = 0; m < fill.size(); ++m)
    {
      fill[m]->info() = static_cast<int32_t>(m) + 2;
    }
    for (size_t m = 0; m < fill.size(); ++m)
    {
      const auto c = fill[m];
      for (int k = 0; k < 4; ++k)
      {
        const std::array<int32_t, 3> key = cellFace(c, k);
        const LinkFace *             f = linkFaceOf(key);
        const auto                   n = c->neighbor(k);
        const int32_t                across = f ? f->outer : (n->info() >= 2 ? id[n->info() - 2] : -1);
        Attach(id[m], tetrahedra[m][k], across);
      }
      QueueFaces(id[m], queue);
    }
    nearby = id.empty() ? -1 : id[0];
    return !id.empty();
  }

  /** Inserts node j (not a vertex of any tetrahedron) into a Delaunay tetrahedralization where it lies now: a walk
   * from tetrahedron `start` to the tetrahedron that holds it, then the tetrahedra whose circumsphere holds it (the
   * cavity) give way to the tetrahedra that join j to the cavity's faces (Bowyer-Watson); a face on a box plane
   * through j is left out. False (nothing changed) when j lies outside the box or on a vertex, when the walk takes
   * more than maximumSteps, or when a new tetrahedron would not be positive. */
  bool
  InsertNode(int32_t j, int32_t start, std::vector<uint32_t> & queue, size_t maximumSteps)
  {
    int32_t t = start;
    for (size_t step = 0;; ++step)
    {
      if (t < 0 || m_Dead[t] || step > maximumSteps)
      {
        return false;
      }
      int32_t next = -2;
      for (int k = 0; k < 4 && next == -2; ++k)
      {
        const int i = static_cast<int>((static_cast<size_t>(k) + step) % 4); // rotated: no cycling
        int32_t   abc[3];
        FaceNodes(t, i, abc);
        if (Orientation(abc[0], abc[1], abc[2], j) == CGAL::NEGATIVE)
        {
          next = m_Neighbours[t][i];
          if (next < 0)
          {
            return false; // outside the box
          }
        }
      }
      if (next == -2)
      {
        break; // j lies in t or on its boundary
      }
      t = next;
    }
    if (Side(t, j) != CGAL::ON_BOUNDED_SIDE)
    {
      return false;
    }
    std::vector<int32_t> cavity{ t }, outside;
    const auto           contains = [](const std::vector<int32_t> & list, int32_t x) {
      return std::find(list.begin(), list.end(), x) != list.end();
    };
    for (size_t m = 0; m < cavity.size(); ++m)
    {
      for (int i = 0; i < 4; ++i)
      {
        const int32_t u = m_Neighbours[cavity[m]][i];
        if (u < 0 || contains(cavity, u) || contains(outside, u))
        {
          continue;
        }
        (Side(u, j) == CGAL::ON_BOUNDED_SIDE ? cavity : outside).push_back(u);
      }
    }
    // the cavity's faces seen from j: each with the tetrahedron beyond it (-1: the box)
    std::vector<std::array<int32_t, 4>> created; // a, b, c, j
    std::vector<int32_t>                beyond;
    double                              cavityVolume = 0.0, createdVolume = 0.0;
    for (const int32_t c : cavity)
    {
      cavityVolume += SixVolumeOf(m_Vertices[c]);
      for (int i = 0; i < 4; ++i)
      {
        const int32_t u = m_Neighbours[c][i];
        if (u >= 0 && contains(cavity, u))
        {
          continue;
        }
        int32_t abc[3];
        FaceNodes(c, i, abc);
        const CGAL::Orientation o = Orientation(abc[0], abc[1], abc[2], j);
        if (o == CGAL::POSITIVE)
        {
          created.push_back({ abc[0], abc[1], abc[2], j });
          beyond.push_back(u);
          createdVolume += SixVolumeOf(created.back());
        }
        else if (o != CGAL::ZERO || u >= 0)
        {
          return false; // the cavity is not star-shaped from j
        }
      }
    }
    // the faces through j: matched by their edge (twice) or on a box plane (once)
    struct EdgeFace
    {
      std::array<int32_t, 2> edge;
      size_t                 tetrahedron;
      int32_t                opposite;
    };
    std::vector<EdgeFace> faces;
    for (size_t m = 0; m < created.size(); ++m)
    {
      for (int k = 0; k < 3; ++k)
      {
        std::array<int32_t, 2> e = { created[m][(k + 1) % 3], created[m][(k + 2) % 3] };
        std::sort(e.begin(), e.end());
        faces.push_back({ e, m, created[m][k] });
      }
    }
    std::sort(faces.begin(), faces.end(), [](const EdgeFace & a, const EdgeFace & b) { return a.edge < b.edge; });
    for (size_t k = 0; k < faces.size();)
    {
      size_t e = k + 1;
      while (e < faces.size() && faces[e].edge == faces[k].edge)
      {
        ++e;
      }
      if (e - k > 2 || (e - k == 1 && !OnOneBoxPlane({ faces[k].edge[0], faces[k].edge[1], j })))
      {
        return false;
      }
      k = e;
    }
    if (created.empty() || !(std::abs(createdVolume - cavityVolume) <= 1e-9 * cavityVolume))
    {
      return false;
    }
    const std::vector<int32_t> id = Replace(cavity, created);
    for (size_t m = 0; m < created.size(); ++m)
    {
      Attach(id[m], j, beyond[m]);
    }
    for (size_t k = 0; k < faces.size();)
    {
      const bool pair = k + 1 < faces.size() && faces[k + 1].edge == faces[k].edge;
      Attach(id[faces[k].tetrahedron], faces[k].opposite, pair ? id[faces[k + 1].tetrahedron] : -1);
      k += pair ? 2 : 1;
    }
    for (const int32_t n : id)
    {
      QueueFaces(n, queue);
    }
    return true;
  }

  const std::vector<std::array<int32_t, 4>> &
  Vertices() const
  {
    return m_Vertices;
  }
  const std::vector<std::array<int32_t, 4>> &
  Neighbours() const
  {
    return m_Neighbours;
  }
  bool
  Dead(size_t t) const
  {
    return m_Dead[t] != 0;
  }
  bool
  Created(size_t t) const
  {
    return m_Created[t] != 0;
  }
  /** Whether each of the faces (tetrahedron x 4 + face) is on the box or strictly locally Delaunay. */
  bool
  StrictlyDelaunay(const std::vector<uint32_t> & faces) const
  {
    for (const uint32_t f : faces)
    {
      const int32_t t = static_cast<int32_t>(f / 4), u = m_Neighbours[t][f % 4];
      if (u >= 0 && Side(t, OppositeVertex(u, t)) != CGAL::ON_UNBOUNDED_SIDE)
      {
        return false;
      }
    }
    return true;
  }

private:
  /** Face i of a positively oriented tetrahedron (v0, v1, v2, v3): the other three vertices in an order that is
   * an even permutation with v_i last, so that orientation(face, v_i) is positive. */
  static constexpr int FaceIndex[4][3] = { { 2, 1, 3 }, { 0, 2, 3 }, { 1, 0, 3 }, { 0, 1, 2 } };

  CGAL::Orientation
  Orientation(int32_t a, int32_t b, int32_t c, int32_t d) const
  {
    return CGAL::orientation(m_Points[a], m_Points[b], m_Points[c], m_Points[d]);
  }

  /** Where node e lies against the circumsphere of the positively oriented tetrahedron t. */
  CGAL::Bounded_side
  Side(int32_t t, int32_t e) const
  {
    const auto & v = m_Vertices[t];
    const auto   s =
      CGAL::side_of_oriented_sphere(m_Points[v[0]], m_Points[v[1]], m_Points[v[2]], m_Points[v[3]], m_Points[e]);
    return s == CGAL::ON_POSITIVE_SIDE ? CGAL::ON_BOUNDED_SIDE
                                       : (s == CGAL::ON_NEGATIVE_SIDE ? CGAL::ON_UNBOUNDED_SIDE : CGAL::ON_BOUNDARY);
  }

  /** The live tetrahedra that have node j as a vertex (face-connected through the faces that hold j). */
  bool
  Star(int32_t j, std::vector<int32_t> & star) const
  {
    star.clear();
    for (size_t t = 0; t < m_Vertices.size() && star.empty(); ++t)
    {
      if (!m_Dead[t] && IndexOf(static_cast<int32_t>(t), j) >= 0)
      {
        star.push_back(static_cast<int32_t>(t));
      }
    }
    for (size_t m = 0; m < star.size(); ++m)
    {
      const int32_t t = star[m];
      for (int i = 0; i < 4; ++i)
      {
        const int32_t u = m_Neighbours[t][i];
        if (m_Vertices[t][i] != j && u >= 0 && std::find(star.begin(), star.end(), u) == star.end())
        {
          star.push_back(u);
        }
      }
    }
    return !star.empty();
  }

  int
  IndexOf(int32_t t, int32_t v) const
  {
    for (int k = 0; k < 4; ++k)
    {
      if (m_Vertices[t][k] == v)
      {
        return k;
      }
    }
    return -1;
  }

  /** Whether faces a and b (tetrahedron x 4 + face) of two tetrahedra, the same three nodes, are ordered oppositely
   * (FaceIndex order: the tetrahedra, if positive, lie on the two sides of the face). */
  bool
  OppositelyOriented(uint32_t a, uint32_t b) const
  {
    const auto & p = FaceIndex[a % 4];
    const auto & q = FaceIndex[b % 4];
    const auto & tp = m_Vertices[a / 4];
    const auto & tq = m_Vertices[b / 4];
    for (int r = 0; r < 3; ++r)
    {
      // the same cyclic order (a rotation) is the same orientation
      if (tq[q[0]] == tp[p[r]] && tq[q[1]] == tp[p[(r + 1) % 3]] && tq[q[2]] == tp[p[(r + 2) % 3]])
      {
        return false;
      }
    }
    return true;
  }

  /** The nodes of face i of tetrahedron t in FaceIndex order (the tetrahedron's node i on their positive side). */
  void
  FaceNodes(int32_t t, int i, int32_t * abc) const
  {
    for (int k = 0; k < 3; ++k)
    {
      abc[k] = m_Vertices[t][FaceIndex[i][k]];
    }
  }

  /** Where the line from d (on the positive side of face abc) to e meets the face's plane: for each edge
   * (abc[k], abc[k + 1]), the orientation of (edge, e, d) is positive when it passes on the face's side of it. Counts
   * the negative and zero ones; edge: the last such k. All positive: the line crosses the face's interior. */
  void
  LineThroughFace(const int32_t * abc, int32_t d, int32_t e, int & negative, int & zero, int & edge) const
  {
    for (int k = 0; k < 3; ++k)
    {
      const CGAL::Orientation side = Orientation(abc[k], abc[(k + 1) % 3], e, d);
      negative += side == CGAL::NEGATIVE ? 1 : 0;
      zero += side == CGAL::ZERO ? 1 : 0;
      edge = side != CGAL::POSITIVE ? k : edge;
    }
  }

  /** The tetrahedron (x, y, d, e) that closes the ring of three around the edge xy of the face (x, y, z) that t (with
   * d) and u (with e) share: the neighbour of both across their faces opposite z, holding d and e; -1 if none. */
  int32_t
  ThirdAroundEdge(int32_t t, int32_t u, int32_t z, int32_t d, int32_t e) const
  {
    const int32_t w = m_Neighbours[t][IndexOf(t, z)];
    return w >= 0 && w == m_Neighbours[u][IndexOf(u, z)] && IndexOf(w, d) >= 0 && IndexOf(w, e) >= 0 ? w : -1;
  }

  /** The vertex of u that is not in its face shared with t. */
  int32_t
  OppositeVertex(int32_t u, int32_t t) const
  {
    for (int k = 0; k < 4; ++k)
    {
      if (m_Neighbours[u][k] == t)
      {
        return m_Vertices[u][k];
      }
    }
    return -1;
  }

  int32_t
  NewTetrahedron(const std::array<int32_t, 4> & v)
  {
    if (!m_Free.empty())
    {
      const int32_t t = m_Free.back();
      m_Free.pop_back();
      m_Vertices[t] = v;
      m_Dead[t] = 0;
      m_Created[t] = 1;
      return t;
    }
    m_Vertices.push_back(v);
    m_Neighbours.push_back({ -1, -1, -1, -1 });
    m_Dead.push_back(0);
    m_Created.push_back(1);
    return static_cast<int32_t>(m_Vertices.size() - 1);
  }

  void
  Kill(int32_t t)
  {
    m_Dead[t] = 1;
    m_Free.push_back(t);
  }

  /** The tetrahedra `gone` out, new ones with the nodes of `made` in (not yet linked); their slots. */
  std::vector<int32_t>
  Replace(const std::vector<int32_t> & gone, const std::vector<std::array<int32_t, 4>> & made)
  {
    for (const int32_t t : gone)
    {
      Kill(t);
    }
    std::vector<int32_t> id(made.size());
    for (size_t m = 0; m < made.size(); ++m)
    {
      id[m] = NewTetrahedron(made[m]);
    }
    return id;
  }

  /** Whether tetrahedron o (-1: none) has node v: a new tetrahedron attached to o across the face opposite v would
   * then have o's four nodes. */
  bool
  HoldsNode(int32_t o, int32_t v) const
  {
    return o >= 0 && IndexOf(o, v) >= 0;
  }

  /** The neighbour of old tetrahedron `from` opposite its vertex v (-1 on the box). */
  int32_t
  Across(int32_t from, int32_t v) const
  {
    return from < 0 ? -1 : m_Neighbours[from][IndexOf(from, v)];
  }

  /** Makes the face of new tetrahedron t opposite its vertex v face outer tetrahedron o (or the box), and o's face
   * back. */
  void
  Attach(int32_t t, int32_t v, int32_t o)
  {
    const int k = IndexOf(t, v);
    m_Neighbours[t][k] = o;
    if (o >= 0)
    {
      // the vertex of o that is not on the shared face
      for (int j = 0; j < 4; ++j)
      {
        if (IndexOf(t, m_Vertices[o][j]) < 0)
        {
          m_Neighbours[o][j] = t;
          break;
        }
      }
    }
  }

  void
  QueueFaces(int32_t t, std::vector<uint32_t> & queue) const
  {
    for (uint32_t i = 0; i < 4; ++i)
    {
      queue.push_back(static_cast<uint32_t>(4 * t) + i);
    }
  }

  /** One flip that removes tetrahedron t, which is not positive (see Untangle); false when none applies. */
  bool
  UntangleOne(int32_t t, std::vector<uint32_t> & queue, DelaunayRepairStatistics & stats)
  {
    for (int i = 0; i < 4; ++i)
    {
      const int32_t u = m_Neighbours[t][i];
      if (u < 0)
      {
        continue;
      }
      const int32_t d = m_Vertices[t][i], e = OppositeVertex(u, t);
      int32_t       abc[3];
      FaceNodes(t, i, abc);
      int negative = 0, zero = 0, edge = -1;
      LineThroughFace(abc, d, e, negative, zero, edge);
      if (negative == 0 && zero == 0 && Flip23(t, u, abc, d, e, queue))
      {
        ++stats.flips23;
        return true;
      }
      for (int k = 0; k < 3; ++k)
      {
        const int32_t x = abc[k], y = abc[(k + 1) % 3], z = abc[(k + 2) % 3];
        const int32_t w = ThirdAroundEdge(t, u, z, d, e);
        if (w >= 0 && Flip32(t, u, w, x, y, z, d, e, queue))
        {
          ++stats.flips32;
          return true;
        }
      }
    }
    return false;
  }

  /** Tetrahedra (a, b, c, d) and (a, b, c, e) -> (a, b, e, d), (b, c, e, d), (c, a, e, d) around the edge de. */
  bool
  Flip23(int32_t t, int32_t u, const int32_t * abc, int32_t d, int32_t e, std::vector<uint32_t> & queue)
  {
    const int32_t a = abc[0], b = abc[1], c = abc[2];
    // outer neighbours, read before the old tetrahedra are replaced
    const int32_t tA = Across(t, a), tB = Across(t, b), tC = Across(t, c);
    const int32_t uA = Across(u, a), uB = Across(u, b), uC = Across(u, c);
    if (HoldsNode(tA, e) || HoldsNode(tB, e) || HoldsNode(tC, e) || HoldsNode(uA, d) || HoldsNode(uB, d) ||
        HoldsNode(uC, d))
    {
      return false; // a new tetrahedron would be an outer one again (only where tetrahedra are tangled)
    }
    Kill(t);
    Kill(u);
    const int32_t n1 = NewTetrahedron({ a, b, e, d }), n2 = NewTetrahedron({ b, c, e, d }),
                  n3 = NewTetrahedron({ c, a, e, d });
    Attach(n1, a, n2);
    Attach(n1, b, n3);
    Attach(n1, e, tC);
    Attach(n1, d, uC);
    Attach(n2, b, n3);
    Attach(n2, c, n1);
    Attach(n2, e, tA);
    Attach(n2, d, uA);
    Attach(n3, c, n1);
    Attach(n3, a, n2);
    Attach(n3, e, tB);
    Attach(n3, d, uB);
    QueueFaces(n1, queue);
    QueueFaces(n2, queue);
    QueueFaces(n3, queue);
    return true;
  }

  /** The tetrahedra around the edge xy, (x, y, z, d), (x, y, z, e) and (x, y, d, e) (w; -1 for a 2-2 flip on the
   * box) -> (z, d, e, y) and (z, d, x, e); false (nothing changed) unless both are positively oriented. */
  bool
  Flip32(int32_t                 t,
         int32_t                 u,
         int32_t                 w,
         int32_t                 x,
         int32_t                 y,
         int32_t                 z,
         int32_t                 d,
         int32_t                 e,
         std::vector<uint32_t> & queue)
  {
    if (Orientation(z, d, e, y) != CGAL::POSITIVE || Orientation(z, d, x, e) != CGAL::POSITIVE)
    {
      return false;
    }
    const int32_t tX = Across(t, x), tY = Across(t, y), uX = Across(u, x), uY = Across(u, y);
    const int32_t wX = Across(w, x), wY = Across(w, y);
    if (HoldsNode(wX, z) || HoldsNode(uX, d) || HoldsNode(tX, e) || HoldsNode(wY, z) || HoldsNode(uY, d) ||
        HoldsNode(tY, e))
    {
      return false; // a new tetrahedron would be an outer one again (only where tetrahedra are tangled)
    }
    Kill(t);
    Kill(u);
    if (w >= 0)
    {
      Kill(w);
    }
    const int32_t n1 = NewTetrahedron({ z, d, e, y }), n2 = NewTetrahedron({ z, d, x, e });
    Attach(n1, z, wX);
    Attach(n1, d, uX);
    Attach(n1, e, tX);
    Attach(n1, y, n2);
    Attach(n2, z, wY);
    Attach(n2, d, uY);
    Attach(n2, e, tY);
    Attach(n2, x, n1);
    QueueFaces(n1, queue);
    QueueFaces(n2, queue);
    return true;
  }

  std::vector<Point> &                m_Points;
  std::vector<std::array<int32_t, 4>> m_Vertices;
  std::vector<std::array<int32_t, 4>> m_Neighbours;
  std::vector<uint8_t>                m_Dead;
  std::vector<uint8_t>                m_Created;
  std::vector<int32_t>                m_Free;
  std::vector<std::array<int32_t, 4>> m_SavedVertices;
  std::vector<std::array<int32_t, 4>> m_SavedNeighbours;
  double                              m_Lo[3]{ 0.0, 0.0, 0.0 };
  double                              m_Hi[3]{ 0.0, 0.0, 0.0 };
};
} // namespace

double
TetrahedronShape(const double * a, const double * b, const double * c, const double * d)
{
  const double   det = SixVolume(a, b, c, d);
  const double * p[4] = { a, b, c, d };
  const double   longest = LongestEdge(p);
  // 6 sqrt(2) V / L^3 with V = det / 6
  return longest > 0.0 ? std::sqrt(2.0) * det / (longest * longest * longest) : 0.0;
}

size_t
Delaunay3D(const std::vector<double> &           xyz,
           std::vector<std::array<int32_t, 4>> & tetrahedra,
           MultiThreaderBase *                   threader)
{
  tetrahedra.clear();
  const std::vector<int32_t> unique = UniqueNodes(xyz);
  const size_t               merged = xyz.size() / 3 - unique.size();
  if (unique.size() < 4 || !SpansSpace(xyz, unique))
  {
    return merged;
  }
  // A box hull (the dual mesh): blocks where they can run side by side, else (one thread, too few nodes, or blocks
  // that cannot vouch for their result) the one CGAL run the blocks take their tetrahedra from, so that the list does
  // not depend on the threads where cospherical nodes leave a choice. Other hulls: one TetGen run.
  double lo[3], hi[3];
  if (!HullIsBoundingBox(xyz, unique, lo, hi))
  {
    TetGenOnUnique(xyz, unique, tetrahedra);
  }
  else if (Parallelism(threader) <= 1 ||
           !BlockDelaunay(xyz, unique, lo, hi, threader, DefaultBlockMargin, tetrahedra, nullptr))
  {
    CGALOnUnique(xyz, unique, tetrahedra);
  }
  return merged;
}

size_t
TetGenDelaunay3D(const std::vector<double> & xyz, std::vector<std::array<int32_t, 4>> & tetrahedra)
{
  tetrahedra.clear();
  const std::vector<int32_t> unique = UniqueNodes(xyz);
  if (unique.size() >= 4 && SpansSpace(xyz, unique))
  {
    TetGenOnUnique(xyz, unique, tetrahedra);
  }
  return xyz.size() / 3 - unique.size();
}

bool
BlockDelaunay3D(const std::vector<double> &           xyz,
                std::vector<std::array<int32_t, 4>> & tetrahedra,
                MultiThreaderBase *                   threader,
                double                                marginFactor,
                BlockDelaunayStatistics *             statistics)
{
  tetrahedra.clear();
  if (statistics)
  {
    *statistics = BlockDelaunayStatistics{};
  }
  const std::vector<int32_t> unique = UniqueNodes(xyz);
  double                     lo[3], hi[3];
  return unique.size() >= 4 && SpansSpace(xyz, unique) && HullIsBoundingBox(xyz, unique, lo, hi) &&
         BlockDelaunay(xyz, unique, lo, hi, threader, marginFactor, tetrahedra, statistics);
}

namespace
{
/** Which box planes node i lies on (bit 2k: lo[k], bit 2k + 1: hi[k]). */
unsigned int
BoxPlanes(const double * x, const double * lo, const double * hi)
{
  // with ifs: GCC 12 at -O2 with -fsanitize=undefined miscompiles `planes |= (x[k] == hi[k] ? 1u : 0u) << (2 * k + 1)`
  // (a node on two planes came out on one), so the sanitizer build would not test this code as built
  unsigned int planes = 0;
  for (unsigned int k = 0; k < 3; ++k)
  {
    if (x[k] == lo[k])
    {
      planes |= 1u << (2 * k);
    }
    if (x[k] == hi[k])
    {
      planes |= 2u << (2 * k);
    }
  }
  return planes;
}

} // namespace

namespace
{
bool
Repair(const std::vector<double> &                 xyz,
       const std::vector<std::array<int32_t, 4>> & previous,
       const std::vector<double> *                 previousXyz,
       const std::vector<std::array<int32_t, 4>> * previousNeighbours,
       std::vector<std::array<int32_t, 4>> &       tetrahedra,
       std::vector<std::array<int32_t, 4>> *       neighbours,
       MultiThreaderBase *                         threader,
       DelaunayRepairStatistics *                  statistics)
{
  if (neighbours)
  {
    neighbours->clear();
  }
  DelaunayRepairStatistics   unused;
  DelaunayRepairStatistics & stats = statistics ? *statistics : unused;
  stats = DelaunayRepairStatistics{};
  tetrahedra.clear();
  const size_t n = xyz.size() / 3;
  if (previous.empty() || n < 4 || n >= (size_t{ 1 } << 21))
  {
    return false;
  }
  // every node a vertex (no node merged, none left out: the Delaunay tetrahedralization uses them all)
  std::vector<uint8_t> used(n, 0);
  for (const auto & t : previous)
  {
    for (const int32_t v : t)
    {
      if (v < 0 || static_cast<size_t>(v) >= n)
      {
        return false;
      }
      used[v] = 1;
    }
  }
  if (std::find(used.begin(), used.end(), uint8_t{ 0 }) != used.end())
  {
    return false;
  }
  double lo[3], hi[3];
  BoundingBox(xyz, lo, hi);
  // With the earlier positions: the nodes that moved onto or off a box plane (a cell's node that snapped to the box
  // border or left it) are moved by removal and insertion instead of flips; they start where they were.
  const bool           fromEarlier = previousXyz && previousXyz->size() == xyz.size();
  std::vector<double>  start = xyz;
  std::vector<int32_t> jumped;
  if (fromEarlier)
  {
    double earlierLo[3], earlierHi[3];
    BoundingBox(*previousXyz, earlierLo, earlierHi);
    if (!std::equal(lo, lo + 3, earlierLo) || !std::equal(hi, hi + 3, earlierHi))
    {
      return false;
    }
    for (size_t i = 0; i < n; ++i)
    {
      if (BoxPlanes(&xyz[3 * i], lo, hi) != BoxPlanes(&(*previousXyz)[3 * i], lo, hi))
      {
        jumped.push_back(static_cast<int32_t>(i));
        std::copy(&(*previousXyz)[3 * i], &(*previousXyz)[3 * i] + 3, &start[3 * i]);
      }
    }
  }
  const auto                        pointOf = [](const double * x) { return BlockKernel::Point_3(x[0], x[1], x[2]); };
  std::vector<BlockKernel::Point_3> points(n);
  for (size_t i = 0; i < n; ++i)
  {
    points[i] = pointOf(&start[3 * i]);
  }
  FlipRepair   repair(points, previous);
  const size_t nt = previous.size();
  const bool   adopted = previousNeighbours && repair.Adopt(*previousNeighbours); // checked in the first round
  if (!adopted && !repair.Link(n))
  {
    return false;
  }
  repair.SetBox(lo, hi);
  if (fromEarlier && !adopted)
  {
    repair.Save(); // an adopted start is previous and *previousNeighbours: ResetTo restores it without a copy
  }
  const size_t          maximumJumps = std::max<size_t>(16, n / 32);
  const size_t          maximumFlips = 4 * nt + 1000;
  std::vector<uint32_t> queue, initiallyBad;
  for (unsigned int round = 0;; ++round)
  {
    if (jumped.size() > maximumJumps)
    {
      return false;
    }
    // a tiling of the box: positive tetrahedra whose free faces lie on the box and whose volumes sum to the box's
    // (the winding number of the boundary is then 1 everywhere inside: every point is covered once)
    const size_t                       nChunks = std::max<size_t>(1, std::min<size_t>(64, nt / 256));
    std::vector<uint8_t>               positive(nt, 0);
    std::vector<std::vector<int32_t>>  tangled(nChunks);
    std::vector<double>                sixVolume(nChunks, 0.0);
    std::vector<uint8_t>               onBox(nChunks, 1);
    std::vector<std::vector<uint32_t>> bad(nChunks);
    const auto &                       v = repair.Vertices();
    const auto &                       nb = repair.Neighbours();
    ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      const size_t begin = nt * c / nChunks, end = nt * (c + 1) / nChunks;
      if (adopted && round == 0 && !repair.CheckNeighbours(begin, end))
      {
        onBox[c] = 0; // refused below
        return;
      }
      repair.Orient(begin, end, positive, tangled[c]);
      for (size_t t = begin; t < end; ++t)
      {
        sixVolume[c] += repair.SixVolumeOf(v[t]);
        for (unsigned int i = 0; i < 4; ++i)
        {
          onBox[c] = onBox[c] && (nb[t][i] >= 0 ||
                                  repair.OnOneBoxPlane({ v[t][(i + 1) % 4], v[t][(i + 2) % 4], v[t][(i + 3) % 4] }));
        }
      }
      if (onBox[c])
      {
        repair.NonDelaunayFaces(begin, end, positive, bad[c]);
      }
    });
    double               total = 0.0;
    std::vector<int32_t> notPositive;
    for (size_t c = 0; c < nChunks; ++c)
    {
      if (!onBox[c])
      {
        return false;
      }
      total += sixVolume[c];
      notPositive.insert(notPositive.end(), tangled[c].begin(), tangled[c].end());
    }
    // the signed volumes (the boundary's) sum to the box's
    const double box = 6.0 * (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2]);
    if (!(box > 0.0) || !(std::abs(total - box) <= 1e-9 * box))
    {
      return false;
    }
    stats = DelaunayRepairStatistics{};
    stats.tangledTetrahedra = notPositive.size();
    stats.rounds = round + 1;
    queue.clear();
    for (size_t c = 0; c < nChunks; ++c)
    {
      queue.insert(queue.end(), bad[c].begin(), bad[c].end());
    }
    stats.nonDelaunayFaces = queue.size();
    initiallyBad = queue;
    std::vector<int32_t> stuck;
    if (repair.Untangle(std::move(notPositive), queue, maximumFlips, stats, stuck))
    {
      break;
    }
    // Untangling got stuck: the moved nodes of the stuck tetrahedra start where they were, and are moved by removal
    // and insertion; the flips start again from the earlier tetrahedra.
    const size_t before = jumped.size();
    for (const int32_t t : stuck)
    {
      for (const int32_t i : repair.Vertices()[t])
      {
        if (fromEarlier && !std::equal(&xyz[3 * i], &xyz[3 * i] + 3, &(*previousXyz)[3 * i]) &&
            std::find(jumped.begin(), jumped.end(), i) == jumped.end())
        {
          jumped.push_back(i);
          std::copy(&(*previousXyz)[3 * i], &(*previousXyz)[3 * i] + 3, &start[3 * i]);
          repair.SetPoint(i, pointOf(&start[3 * i]));
        }
      }
    }
    if (jumped.size() == before || round == 2)
    {
      return false;
    }
    if (adopted)
    {
      repair.ResetTo(previous, *previousNeighbours);
    }
    else
    {
      repair.Reset();
    }
  }
  if (!repair.Flip(std::move(queue), maximumFlips, stats))
  {
    return false;
  }
  // the jumped nodes, one at a time: out of the (now Delaunay) tetrahedralization where they were, in where they are
  std::sort(jumped.begin(), jumped.end());
  for (const int32_t j : jumped)
  {
    std::vector<uint32_t> changed;
    int32_t               nearby = -1;
    if (!repair.RemoveNode(j, changed, nearby))
    {
      return false;
    }
    repair.SetPoint(j, pointOf(&xyz[3 * j]));
    if (!repair.InsertNode(j, nearby, changed, repair.Vertices().size()) ||
        !repair.Flip(std::move(changed), maximumFlips, stats))
    {
      return false;
    }
    ++stats.movedByRemoval;
  }
  const auto & v = repair.Vertices();
  // The faces to check again: those of the tetrahedra the flips made and the initially non-Delaunay faces of old
  // tetrahedra that are still there; every other face lies between two old tetrahedra and was strictly Delaunay
  // (a face of an old tetrahedron of a jumped node was not tested where the node ended up, but the node's
  // tetrahedra were all removed).
  std::vector<uint32_t> check;
  for (size_t t = 0; t < v.size(); ++t)
  {
    if (!repair.Dead(t) && repair.Created(t))
    {
      for (uint32_t i = 0; i < 4; ++i)
      {
        check.push_back(static_cast<uint32_t>(4 * t) + i);
      }
    }
  }
  for (const uint32_t f : initiallyBad)
  {
    if (!repair.Dead(f / 4) && !repair.Created(f / 4))
    {
      check.push_back(f);
    }
  }
  if (!repair.StrictlyDelaunay(check))
  {
    return false;
  }
  // canonical and sorted: the old tetrahedra keep their order (previous is usually Delaunay3D's sorted list), the
  // new ones are sorted and merged in; slot[k]: the repair's slot of tetrahedron k, for the neighbours
  using Tetrahedron = std::array<int32_t, 4>;
  using Entry = std::pair<Tetrahedron, int32_t>;
  std::vector<int32_t> oldSlots;
  std::vector<Entry>   created;
  oldSlots.reserve(v.size());
  bool oldInOrder = true; // every old tetrahedron canonical as it is, in ascending order: merged without a copy
  for (size_t t = 0; t < v.size(); ++t)
  {
    if (repair.Dead(t))
    {
      continue;
    }
    if (repair.Created(t))
    {
      created.emplace_back(CanonicalTetrahedron(v[t]), static_cast<int32_t>(t));
    }
    else
    {
      oldInOrder = oldInOrder && CanonicalTetrahedron(v[t]) == v[t] && (oldSlots.empty() || v[oldSlots.back()] < v[t]);
      oldSlots.push_back(static_cast<int32_t>(t));
    }
  }
  const auto byTetrahedron = [](const Entry & a, const Entry & b) { return a.first < b.first; };
  std::sort(created.begin(), created.end(), byTetrahedron);
  // the old tetrahedra in canonical form and order, copied only where they are not so already
  std::vector<Entry> reordered;
  if (!oldInOrder)
  {
    reordered.reserve(oldSlots.size());
    for (const int32_t t : oldSlots)
    {
      reordered.emplace_back(CanonicalTetrahedron(v[t]), t);
    }
    if (!std::is_sorted(reordered.begin(), reordered.end(), byTetrahedron))
    {
      std::sort(reordered.begin(), reordered.end(), byTetrahedron);
    }
  }
  const auto oldTetrahedron = [&](size_t i) -> const Tetrahedron & {
    return oldInOrder ? v[oldSlots[i]] : reordered[i].first;
  };
  // the two sorted lists merged into the output, an old tetrahedron first on a tie (as a stable merge)
  const size_t         total = oldSlots.size() + created.size();
  std::vector<int32_t> slot(total);
  tetrahedra.resize(total);
  for (size_t k = 0, i = 0, j = 0; k < total; ++k)
  {
    if (j == created.size() || (i < oldSlots.size() && !(created[j].first < oldTetrahedron(i))))
    {
      slot[k] = oldInOrder ? oldSlots[i] : reordered[i].second;
      tetrahedra[k] = oldTetrahedron(i++);
    }
    else
    {
      slot[k] = created[j].second;
      tetrahedra[k] = created[j++].first;
    }
  }
  if (neighbours)
  {
    // the neighbour opposite each node of the canonical tetrahedron, as positions in the list
    std::vector<int32_t> position(v.size(), -1);
    for (size_t k = 0; k < total; ++k)
    {
      position[slot[k]] = static_cast<int32_t>(k);
    }
    const auto & nb = repair.Neighbours();
    neighbours->resize(total);
    for (size_t k = 0; k < total; ++k)
    {
      const int32_t s = slot[k];
      for (int m = 0; m < 4; ++m)
      {
        int i = m; // the node's place in the repair's order (the same unless the tetrahedron was reordered)
        while (v[s][i] != tetrahedra[k][m])
        {
          i = (i + 1) % 4;
        }
        const int32_t u = nb[s][i];
        (*neighbours)[k][m] = u < 0 ? -1 : position[u];
      }
    }
  }
  return true;
}

} // namespace

bool
RepairDelaunay3D(const std::vector<double> &                 xyz,
                 const std::vector<std::array<int32_t, 4>> & previous,
                 std::vector<std::array<int32_t, 4>> &       tetrahedra,
                 MultiThreaderBase *                         threader,
                 DelaunayRepairStatistics *                  statistics,
                 const std::vector<double> *                 previousXyz)
{
  return Repair(xyz, previous, previousXyz, nullptr, tetrahedra, nullptr, threader, statistics);
}

bool
RepairDelaunay3D(const std::vector<double> &           xyz,
                 const DelaunayWarmStart &             warmStart,
                 std::vector<std::array<int32_t, 4>> & tetrahedra,
                 MultiThreaderBase *                   threader,
                 DelaunayRepairStatistics *            statistics,
                 std::vector<std::array<int32_t, 4>> * neighbours)
{
  return Repair(xyz,
                warmStart.tetrahedra,
                warmStart.nodes.empty() ? nullptr : &warmStart.nodes,
                warmStart.neighbours.empty() ? nullptr : &warmStart.neighbours,
                tetrahedra,
                neighbours,
                threader,
                statistics);
}

size_t
NonDegenerateDelaunay3D(std::vector<double> &                 xyz,
                        const std::vector<uint8_t> &          freeAxes,
                        double                                maximumStep,
                        std::vector<std::array<int32_t, 4>> & tetrahedra,
                        double                                minimumShape,
                        unsigned int                          maximumRounds,
                        MultiThreaderBase *                   threader,
                        const DelaunayWarmStart *             warmStart,
                        bool *                                repaired,
                        std::vector<std::array<int32_t, 4>> * neighbours)
{
  if (repaired)
  {
    *repaired = false;
  }
  if (neighbours)
  {
    neighbours->clear();
  }
  const size_t n = xyz.size() / 3;
  if (freeAxes.size() != n)
  {
    itkGenericExceptionMacro("NonDegenerateDelaunay3D: " << freeAxes.size() << " free-axis masks for " << n
                                                         << " nodes");
  }
  std::vector<int32_t> first;    // for each node the first at its position (once nodes are moved)
  std::vector<double>  original; // the input positions (once nodes are moved)
  for (unsigned int round = 0;; ++round)
  {
    // the first round from the warm start where it can vouch for the result (the same list as Delaunay3D's)
    const bool fromWarmStart =
      round == 0 && warmStart && RepairDelaunay3D(xyz, *warmStart, tetrahedra, threader, nullptr, neighbours);
    if (repaired && round == 0)
    {
      *repaired = fromWarmStart;
    }
    if (!fromWarmStart)
    {
      Delaunay3D(xyz, tetrahedra, threader);
      if (neighbours)
      {
        neighbours->clear(); // known for the repaired tetrahedra only
      }
    }
    // the flat tetrahedra (found side by side), then the step each of their nodes takes this round (the smallest
    // its flat tetrahedra ask for)
    const size_t                      nt = tetrahedra.size();
    const size_t                      nChunks = std::max<size_t>(1, std::min<size_t>(64, nt / 1024));
    std::vector<std::vector<int32_t>> flatIn(nChunks);
    ParallelForChunkIds(threader, nChunks, [&](size_t c) {
      for (size_t e = nt * c / nChunks; e < nt * (c + 1) / nChunks; ++e)
      {
        const auto &   t = tetrahedra[e];
        const double * p[4] = { &xyz[3 * t[0]], &xyz[3 * t[1]], &xyz[3 * t[2]], &xyz[3 * t[3]] };
        if (TetrahedronShape(p[0], p[1], p[2], p[3]) < minimumShape)
        {
          flatIn[c].push_back(static_cast<int32_t>(e));
        }
      }
    });
    std::vector<double> step;
    size_t              flat = 0;
    for (const auto & list : flatIn)
    {
      if (!list.empty() && step.empty())
      {
        step.assign(n, 0.0);
      }
      for (const int32_t e : list)
      {
        const auto &   t = tetrahedra[e];
        const double * p[4] = { &xyz[3 * t[0]], &xyz[3 * t[1]], &xyz[3 * t[2]], &xyz[3 * t[3]] };
        ++flat;
        const double s = std::min(maximumStep, 0.01 * std::ldexp(LongestEdge(p), static_cast<int>(round)));
        bool         movable = false;
        for (int32_t v : t)
        {
          if (freeAxes[v] & 7u)
          {
            movable = true;
            step[v] = step[v] > 0.0 ? std::min(step[v], s) : s;
          }
        }
        if (!movable)
        {
          itkGenericExceptionMacro("a flat tetrahedron (shape below " << minimumShape
                                                                      << ") consists of pinned nodes only");
        }
      }
    }
    if (flat == 0)
    {
      break;
    }
    if (round == maximumRounds)
    {
      itkGenericExceptionMacro("NonDegenerateDelaunay3D: " << flat << " tetrahedra are still flat (shape below "
                                                           << minimumShape << ") after " << maximumRounds
                                                           << " rounds of node perturbation");
    }
    if (original.empty())
    {
      original = xyz; // nothing moved yet
      first = FirstAtSamePosition(xyz);
    }
    for (size_t i = 0; i < n; ++i)
    {
      if (!(step[i] > 0.0))
      {
        continue;
      }
      double   u[3] = { 0.0, 0.0, 0.0 };
      double   largest = 0.0;
      uint64_t h = SplitMix64((static_cast<uint64_t>(i) << 8) ^ round);
      for (unsigned int k = 0; k < 3; ++k)
      {
        h = SplitMix64(h);
        if (freeAxes[i] & (1u << k))
        {
          u[k] = static_cast<double>(h >> 11) * 0x1.0p-52 - 1.0; // [-1, 1)
          largest = std::max(largest, std::abs(u[k]));
        }
      }
      for (unsigned int k = 0; k < 3; ++k)
      {
        // a fresh offset from the input position each round: never more than maximumStep away from it
        xyz[3 * i + k] = original[3 * i + k] + (largest > 0.0 ? step[i] * u[k] / largest : 0.0);
      }
    }
    // nodes merged into a moved node move with it
    for (size_t i = 0; i < n; ++i)
    {
      if (first[i] != static_cast<int32_t>(i) && step[first[i]] > 0.0)
      {
        std::copy(&xyz[3 * first[i]], &xyz[3 * first[i]] + 3, &xyz[3 * i]);
      }
    }
  }
  size_t moved = 0;
  for (size_t i = 0; i < n && !original.empty(); ++i)
  {
    moved += std::equal(&xyz[3 * i], &xyz[3 * i] + 3, &original[3 * i]) ? 0 : 1;
  }
  return moved;
}
} // namespace dmr
} // namespace itk
