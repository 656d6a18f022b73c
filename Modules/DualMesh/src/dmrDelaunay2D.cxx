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
#include <CGAL/Triangulation_vertex_base_with_info_2.h>
#include <CGAL/Constrained_triangulation_face_base_2.h>
#include <CGAL/intersections.h>

namespace itk
{
namespace dmr
{
namespace
{
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using VertexBase = CGAL::Triangulation_vertex_base_with_info_2<int32_t, Kernel>;
using FaceBase = CGAL::Constrained_triangulation_face_base_2<Kernel>;
using DataStructure = CGAL::Triangulation_data_structure_2<VertexBase, FaceBase>;
using CDT = CGAL::Constrained_Delaunay_triangulation_2<Kernel,
                                                       DataStructure,
                                                       CGAL::No_constraint_intersection_requiring_constructions_tag>;
using Point = Kernel::Point_2;
using Segment = Kernel::Segment_2;
} // namespace

size_t
ConstrainedDelaunay2D(const std::vector<double> &                 xy,
                      const std::vector<std::array<int32_t, 2>> & constraints,
                      std::vector<std::array<int32_t, 3>> &       triangles)
{
  CDT                             cdt;
  const size_t                    n = xy.size() / 2;
  std::vector<int32_t>            merged(n);
  std::vector<CDT::Vertex_handle> handle(n);
  for (size_t i = 0; i < n; ++i)
  {
    const size_t before = cdt.number_of_vertices();
    handle[i] = cdt.insert(Point(xy[2 * i], xy[2 * i + 1]));
    if (cdt.number_of_vertices() > before)
    {
      handle[i]->info() = static_cast<int32_t>(i);
    }
    merged[i] = handle[i]->info();
  }
  std::vector<Segment>               accepted;
  std::vector<std::array<double, 4>> boxes;
  size_t                             skipped = 0;
  for (const auto & c : constraints)
  {
    const int32_t a = merged[c[0]], b = merged[c[1]];
    if (a == b)
    {
      ++skipped;
      continue;
    }
    const Point                 pa(xy[2 * a], xy[2 * a + 1]), pb(xy[2 * b], xy[2 * b + 1]);
    const Segment               s(pa, pb);
    const std::array<double, 4> box{
      std::min(pa.x(), pb.x()), std::max(pa.x(), pb.x()), std::min(pa.y(), pb.y()), std::max(pa.y(), pb.y())
    };
    bool crosses = false;
    for (size_t k = 0; k < accepted.size() && !crosses; ++k)
    {
      const auto & o = boxes[k];
      if (o[1] < box[0] || o[0] > box[1] || o[3] < box[2] || o[2] > box[3])
      {
        continue;
      }
      const Segment & t = accepted[k];
      const bool      shared = t.source() == pa || t.source() == pb || t.target() == pa || t.target() == pb;
      if (shared)
      {
        // sharing an endpoint is fine unless the segments overlap along a line
        if (CGAL::collinear(t.source(), t.target(), pa) && CGAL::collinear(t.source(), t.target(), pb))
        {
          const Point & other = (t.source() == pa || t.source() == pb) ? t.target() : t.source();
          const Point & mine = (pa == t.source() || pa == t.target()) ? pb : pa;
          const Point & common = (pa == t.source() || pa == t.target()) ? pa : pb;
          // overlap when both free ends lie on the same side of the common point
          crosses = (CGAL::collinear_are_ordered_along_line(common, other, mine) ||
                     CGAL::collinear_are_ordered_along_line(common, mine, other));
        }
      }
      else
      {
        crosses = CGAL::do_intersect(s, t);
      }
    }
    if (crosses)
    {
      ++skipped;
      continue;
    }
    accepted.push_back(s);
    boxes.push_back(box);
    cdt.insert_constraint(handle[a], handle[b]);
  }
  triangles.clear();
  triangles.reserve(cdt.number_of_faces());
  for (auto f = cdt.finite_faces_begin(); f != cdt.finite_faces_end(); ++f)
  {
    triangles.push_back({ f->vertex(0)->info(), f->vertex(1)->info(), f->vertex(2)->info() });
  }
  return skipped;
}
} // namespace dmr
} // namespace itk
