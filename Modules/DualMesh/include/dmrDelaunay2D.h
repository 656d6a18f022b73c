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
#ifndef dmrDelaunay2D_h
#define dmrDelaunay2D_h

#include "DynamicMeshRegistrationExport.h"
#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace itk
{
namespace dmr
{
/** Constrained Delaunay triangulation (CGAL) of 2D nodes (x, y interleaved) with constraint segments given as node
 * index pairs. Constraints that would cross (or overlap) one accepted earlier are skipped, so the result never
 * needs constructed intersection points. Nodes at the same position are merged: triangles refer to the first node
 * at a position. Triangles are counter-clockwise; there are no degenerate ones.
 * Returns the number of constraints skipped. (CGAL stays out of every public header: this is the only interface.) */
DynamicMeshRegistration_EXPORT std::size_t
                               ConstrainedDelaunay2D(const std::vector<double> &                 xy,
                                                     const std::vector<std::array<int32_t, 2>> & constraints,
                                                     std::vector<std::array<int32_t, 3>> &       triangles);

/** A "high fidelity" mesh (paper 5.2, Fig. 5b): the closed polygons (x, y interleaved, each resampled to a common
 * spacing) inserted as constraints together with the rectangle [0,width] x [0,height], then refined by CGAL's
 * Delaunay refinement (Delaunay_mesher_2, minimum-angle criterion). The contour spacing is chosen so that the
 * final mesh has about targetNodes nodes. */
DynamicMeshRegistration_EXPORT void
ContourFidelityMesh2D(const std::vector<std::vector<double>> & polygons,
                      double                                   width,
                      double                                   height,
                      std::size_t                              targetNodes,
                      std::vector<double> &                    nodesXY,
                      std::vector<std::array<int32_t, 3>> &    triangles);
} // namespace dmr
} // namespace itk

#endif
