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

#include "itkMacro.h"
#include <tetgen.h>
#include <algorithm>
#include <cmath>
#include <numeric>

namespace itk
{
namespace dmr
{
namespace
{
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
} // namespace

double
TetrahedronShape(const double * a, const double * b, const double * c, const double * d)
{
  double m[3][3];
  for (unsigned int r = 0; r < 3; ++r)
  {
    m[r][0] = b[r] - a[r];
    m[r][1] = c[r] - a[r];
    m[r][2] = d[r] - a[r];
  }
  const double det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
                     m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
                     m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
  const double * p[4] = { a, b, c, d };
  const double   longest = LongestEdge(p);
  // 6 sqrt(2) V / L^3 with V = det / 6
  return longest > 0.0 ? std::sqrt(2.0) * det / (longest * longest * longest) : 0.0;
}

size_t
Delaunay3D(const std::vector<double> & xyz, std::vector<std::array<int32_t, 4>> & tetrahedra)
{
  tetrahedra.clear();
  const size_t               n = xyz.size() / 3;
  const std::vector<int32_t> first = FirstAtSamePosition(xyz);
  std::vector<int32_t>       unique; // TetGen's point index -> our node index
  for (size_t i = 0; i < n; ++i)
  {
    if (first[i] == static_cast<int32_t>(i))
    {
      unique.push_back(static_cast<int32_t>(i));
    }
  }
  const size_t merged = n - unique.size();
  if (unique.size() < 4 || !SpansSpace(xyz, unique))
  {
    return merged;
  }
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
  }
  return merged;
}

size_t
NonDegenerateDelaunay3D(std::vector<double> &                 xyz,
                        const std::vector<uint8_t> &          freeAxes,
                        double                                maximumStep,
                        std::vector<std::array<int32_t, 4>> & tetrahedra,
                        double                                minimumShape,
                        unsigned int                          maximumRounds)
{
  const size_t n = xyz.size() / 3;
  if (freeAxes.size() != n)
  {
    itkGenericExceptionMacro("NonDegenerateDelaunay3D: " << freeAxes.size() << " free-axis masks for " << n
                                                         << " nodes");
  }
  const std::vector<int32_t> first = FirstAtSamePosition(xyz);
  const std::vector<double>  original = xyz;
  for (unsigned int round = 0;; ++round)
  {
    Delaunay3D(xyz, tetrahedra);
    // the step each node of a flat tetrahedron takes this round (the smallest its flat tetrahedra ask for)
    std::vector<double> step(n, 0.0);
    size_t              flat = 0;
    for (const auto & t : tetrahedra)
    {
      const double * p[4] = { &xyz[3 * t[0]], &xyz[3 * t[1]], &xyz[3 * t[2]], &xyz[3 * t[3]] };
      if (TetrahedronShape(p[0], p[1], p[2], p[3]) >= minimumShape)
      {
        continue;
      }
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
  for (size_t i = 0; i < n; ++i)
  {
    moved += std::equal(&xyz[3 * i], &xyz[3 * i] + 3, &original[3 * i]) ? 0 : 1;
  }
  return moved;
}
} // namespace dmr
} // namespace itk
