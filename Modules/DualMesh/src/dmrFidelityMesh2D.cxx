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
#include "dmrDelaunay2D.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Constrained_Delaunay_triangulation_2.h>
#include <CGAL/Delaunay_mesher_2.h>
#include <CGAL/Delaunay_mesh_face_base_2.h>
#include <CGAL/Delaunay_mesh_size_criteria_2.h>
#include <cmath>
#include <map>

namespace itk
{
namespace dmr
{
namespace
{
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using VertexBase = CGAL::Triangulation_vertex_base_2<Kernel>;
using FaceBase = CGAL::Delaunay_mesh_face_base_2<Kernel>;
using DataStructure = CGAL::Triangulation_data_structure_2<VertexBase, FaceBase>;
// contours resampled coarsely may touch or cross themselves (e.g. across a narrow entrance): allow intersections
using CDT = CGAL::Constrained_Delaunay_triangulation_2<Kernel, DataStructure, CGAL::Exact_predicates_tag>;
using Criteria = CGAL::Delaunay_mesh_size_criteria_2<CDT>;
using Point = Kernel::Point_2;

/** Closed polygon resampled to vertices spaced about 'step' apart along its length. */
std::vector<Point>
Resample(const std::vector<double> & poly, double step)
{
  const size_t        n = poly.size() / 2;
  std::vector<double> arc(n + 1, 0.0);
  for (size_t i = 0; i < n; ++i)
  {
    const size_t j = (i + 1) % n;
    arc[i + 1] = arc[i] + std::hypot(poly[2 * j] - poly[2 * i], poly[2 * j + 1] - poly[2 * i + 1]);
  }
  const double       length = arc[n];
  const size_t       m = std::max<size_t>(3, static_cast<size_t>(std::round(length / step)));
  std::vector<Point> out;
  size_t             seg = 0;
  for (size_t k = 0; k < m; ++k)
  {
    const double s = length * static_cast<double>(k) / static_cast<double>(m);
    while (seg + 1 < n && arc[seg + 1] < s)
    {
      ++seg;
    }
    const size_t j = (seg + 1) % n;
    const double len = arc[seg + 1] - arc[seg];
    const double t = len > 0 ? (s - arc[seg]) / len : 0.0;
    out.emplace_back(poly[2 * seg] + t * (poly[2 * j] - poly[2 * seg]),
                     poly[2 * seg + 1] + t * (poly[2 * j + 1] - poly[2 * seg + 1]));
  }
  return out;
}

void
Mesh(const std::vector<std::vector<double>> & polygons, double width, double height, double step, CDT & cdt)
{
  cdt.clear();
  const Point corners[4] = { Point(0, 0), Point(width, 0), Point(width, height), Point(0, height) };
  for (int i = 0; i < 4; ++i)
  {
    cdt.insert_constraint(corners[i], corners[(i + 1) % 4]);
  }
  for (const auto & poly : polygons)
  {
    if (poly.size() < 6)
    {
      continue;
    }
    const auto pts = Resample(poly, step);
    for (size_t i = 0; i < pts.size(); ++i)
    {
      const Point & a = pts[i];
      const Point & b = pts[(i + 1) % pts.size()];
      if (a != b)
      {
        cdt.insert_constraint(a, b);
      }
    }
  }
  // shape criterion only (B = 0.125: minimum angle about 20.7 degrees); sizes follow the contour spacing
  CGAL::refine_Delaunay_mesh_2(cdt, Criteria(0.125, 0.0));
}
} // namespace

void
ContourFidelityMesh2D(const std::vector<std::vector<double>> & polygons,
                      double                                   width,
                      double                                   height,
                      size_t                                   targetNodes,
                      std::vector<double> &                    nodesXY,
                      std::vector<std::array<int32_t, 3>> &    triangles)
{
  double perimeter = 0.0;
  for (const auto & poly : polygons)
  {
    const size_t n = poly.size() / 2;
    for (size_t i = 0; i < n; ++i)
    {
      const size_t j = (i + 1) % n;
      perimeter += std::hypot(poly[2 * j] - poly[2 * i], poly[2 * j + 1] - poly[2 * i + 1]);
    }
  }
  // bisection on the contour spacing: larger spacing, fewer nodes
  double lo = 1.0, hi = std::max(2.0, perimeter / 3.0);
  CDT    cdt;
  double best = hi;
  size_t bestError = static_cast<size_t>(-1);
  for (int it = 0; it < 30; ++it)
  {
    const double step = std::sqrt(lo * hi);
    Mesh(polygons, width, height, step, cdt);
    const size_t nodes = cdt.number_of_vertices();
    const size_t error = nodes > targetNodes ? nodes - targetNodes : targetNodes - nodes;
    if (error < bestError)
    {
      bestError = error;
      best = step;
    }
    if (nodes > targetNodes)
    {
      lo = step;
    }
    else
    {
      hi = step;
    }
    if (hi / lo < 1.01)
    {
      break;
    }
  }
  Mesh(polygons, width, height, best, cdt);
  std::map<CDT::Vertex_handle, int32_t> index;
  nodesXY.clear();
  for (auto v = cdt.finite_vertices_begin(); v != cdt.finite_vertices_end(); ++v)
  {
    index[v] = static_cast<int32_t>(nodesXY.size() / 2);
    nodesXY.push_back(v->point().x());
    nodesXY.push_back(v->point().y());
  }
  triangles.clear();
  for (auto f = cdt.finite_faces_begin(); f != cdt.finite_faces_end(); ++f)
  {
    triangles.push_back({ index[f->vertex(0)], index[f->vertex(1)], index[f->vertex(2)] });
  }
}
} // namespace dmr
} // namespace itk
