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
#ifndef dmrDelaunay3D_h
#define dmrDelaunay3D_h

#include "DynamicMeshRegistrationExport.h"
#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace itk
{
class MultiThreaderBase;

namespace dmr
{
/** Margin of BlockDelaunay3D as Delaunay3D uses it, in mean node spacings. A smaller one is faster while no block
 * needs a second round (1.5 took about 20 % less time on the node sets of 14 thorax256 iterations on 16 threads), but a
 * graded node set (Delaunay3D's test) already needs one at 1.5, and the dynamic mesh is graded by design
 * (docs/benchmarks.md, 30th session). */
constexpr double DefaultBlockMargin = 2.0;

/** Delaunay tetrahedralization (exact predicates) of 3D nodes (x, y, z interleaved). It fills the convex
 * hull of the nodes. Nodes at the same position are merged: tetrahedra refer to the first node at a position. Every
 * tetrahedron is positively oriented (det [x1 - x0, x2 - x0, x3 - x0] > 0 in exact arithmetic); no tetrahedron has
 * exactly zero volume, but near-coplanar nodes can give near-flat ones (see NonDegenerateDelaunay3D).
 * Node sets whose convex hull is their bounding box (its 8 corners are nodes, as in the dual mesh) go through
 * BlockDelaunay3D with a threader of two or more threads, otherwise (one thread, or blocks that cannot vouch for their
 * result) through one CGAL run, the triangulation the blocks take their tetrahedra from: where cospherical nodes leave
 * a choice of tetrahedralization, CGAL's symbolic perturbation decides from the nodes alone, so the output is the same
 * however many threads. Other node sets go through one TetGen 1.5 run (TetGenDelaunay3D), which perturbs otherwise:
 * for nodes without cospherical subsets (whose Delaunay tetrahedralization is unique) it gives the same list. Every
 * path writes each tetrahedron with its vertices ascending (the last two swapped where that keeps it positive) and
 * sorts the list.
 * Fewer than 4 distinct nodes, or all of them within 1e-12 of their extent from one plane, give no tetrahedra
 * (TetGen 1.5 crashes on a coplanar set). Throws an itk::ExceptionObject when TetGen or CGAL fails. Returns the number
 * of nodes merged into an earlier one. (TetGen stays out of every public header: this file is its only interface.)
 *
 * Why no constraints: the 2D dual mesh inserts the inner-cell adjacency edges as constraints of a CGAL constrained
 * Delaunay triangulation (paper 4.6). TetGen 1.5 takes constraints only as a piecewise linear complex of facets
 * and segments, and adjacency edges between inner sites are neither (recovering a free segment needs Steiner
 * points). The unconstrained Delaunay tetrahedralization of the nodes is the dual of the Voronoi diagram of the
 * sites, so it holds most of the discrete CVT's adjacency edges anyway; DualMeshFilter reports how many it misses. */
DynamicMeshRegistration_EXPORT size_t
Delaunay3D(const std::vector<double> &           xyz,
           std::vector<std::array<int32_t, 4>> & tetrahedra,
           MultiThreaderBase *                   threader = nullptr);

/** Delaunay3D by one TetGen 1.5 run, whatever the nodes (Delaunay3D's path for hulls other than the bounding box). */
DynamicMeshRegistration_EXPORT size_t
TetGenDelaunay3D(const std::vector<double> & xyz, std::vector<std::array<int32_t, 4>> & tetrahedra);

/** The Delaunay tetrahedralization of nodes whose convex hull is their bounding box, by blocks (false, with no
 * tetrahedra, when the hull is not the box or no layout of two or more blocks fits). The box is cut into the grid of
 * blocks (at most 64, at least 150 nodes each) with the shortest critical path on the threader's work units (its
 * threads at most; at least 2): waves of blocks times the largest extended block's share of the box. Each block, in
 * parallel, triangulates (CGAL, exact predicates, symbolic perturbation: one triangulation per node set even when nodes
 * are cospherical) the nodes of its region extended by marginFactor mean node spacings, (volume / nodes)^(1/3), and
 * keeps the tetrahedra it owns (the centre of the box around the circumsphere's part inside the node box lies in its
 * region) whose circumsphere, within the node box, lies inside the extended region: no node outside it can be in that
 * sphere, so each kept tetrahedron is a Delaunay tetrahedron of all the nodes. A block that owns a tetrahedron it
 * cannot vouch for, or that another block finds too small to see a tetrahedron it owns, is redone, up to twice, with
 * the margin that tetrahedron asks for (at least double). The result is accepted only when every face shared with
 * another block's tetrahedron is held by exactly two kept tetrahedra, box faces aside, and the kept volume equals the
 * box's to 1e-9: then the kept tetrahedra are the whole Delaunay tetrahedralization. Otherwise false (no tetrahedra).
 * Output as Delaunay3D's (canonical tetrahedra, sorted): it depends only on the nodes, not on the layout. */
struct BlockDelaunayStatistics
{
  unsigned int numberOfBlocks{ 0 }; // 0: not applicable
  size_t       numberOfRuns{ 0 };   // block triangulations, the redone ones included
};
DynamicMeshRegistration_EXPORT bool
BlockDelaunay3D(const std::vector<double> &           xyz,
                std::vector<std::array<int32_t, 4>> & tetrahedra,
                MultiThreaderBase *                   threader,
                double                                marginFactor = DefaultBlockMargin,
                BlockDelaunayStatistics *             statistics = nullptr);

/** What RepairDelaunay3D did. */
struct DelaunayRepairStatistics
{
  size_t tangledTetrahedra{ 0 }; // earlier tetrahedra that the moved nodes turned inside out (or flat)
  size_t nonDelaunayFaces{ 0 };  // faces of the others that the moved nodes left not strictly Delaunay
  size_t flips23{ 0 };
  size_t flips32{ 0 };
  size_t flips22{ 0 };        // on a box face
  size_t movedByRemoval{ 0 }; // nodes moved by removal and insertion (see RepairDelaunay3D)
  size_t rounds{ 0 };         // untangling rounds (more than one when it got stuck and nodes were set aside)
};

/** A tetrahedralization and the node positions it is the Delaunay tetrahedralization of: the warm start of
 * NonDegenerateDelaunay3D (and BuildDualMesh) for nodes that have moved since. */
struct DelaunayWarmStart
{
  std::vector<double>                 nodes; // x, y, z per node
  std::vector<std::array<int32_t, 4>> tetrahedra;
  // optional: for each tetrahedron the one opposite each of its nodes (-1 on the box), as RepairDelaunay3D gives them;
  // checked before use, and found again from the faces when absent
  std::vector<std::array<int32_t, 4>> neighbours;

  bool
  empty() const
  {
    return tetrahedra.empty();
  }
  void
  clear()
  {
    std::vector<double>().swap(nodes);
    std::vector<std::array<int32_t, 4>>().swap(tetrahedra);
    std::vector<std::array<int32_t, 4>>().swap(neighbours);
  }
};

/** Delaunay3D of nodes that moved since an earlier tetrahedralization of them (previous: node indices, e.g. the last
 * iteration's dual mesh; the registration's nodes move a little each iteration), by flips instead of a new run.
 * It applies when previous, with the nodes where they are now, still tiles the nodes' bounding box (every node a
 * vertex, every tetrahedron positively oriented, the free faces on the box, the volumes summing to the box's). From
 * there, every face that is not locally Delaunay is flipped (2-3 and 3-2 flips, 2-2 flips on a box face; exact
 * predicates) until none is left. A tiling whose every inner face is *strictly* locally Delaunay (no opposite node on
 * the circumsphere) is the unique Delaunay tetrahedralization of its nodes, so the result is then Delaunay3D's list
 * exactly (canonical tetrahedra, sorted), whatever the threads. Returns false, with no tetrahedra, when it cannot
 * vouch for that: previous does not tile the box with the nodes as they are now, a flip would need a coplanar
 * configuration inside the box, flips get stuck, or cospherical nodes leave a choice (Delaunay3D then decides by
 * CGAL's symbolic perturbation). The caller then runs Delaunay3D. threader: the work units of the checks.
 * previousXyz (optional; same number of nodes): where the nodes were when previous was their Delaunay
 * tetrahedralization. With it, a node that moved onto or off a box plane (the dual mesh snaps a cell's node to the
 * box border when the cell reaches it), and the moved nodes of tetrahedra that the flips cannot untangle, start where
 * they were; once the others are repaired, each of them is removed (its tetrahedra replaced by the Delaunay
 * tetrahedra of its neighbours that fill the same region) and inserted where it is now (Bowyer-Watson). The same
 * final check applies, so the result is still exactly Delaunay3D's list or false. */
DynamicMeshRegistration_EXPORT bool
RepairDelaunay3D(const std::vector<double> &                 xyz,
                 const std::vector<std::array<int32_t, 4>> & previous,
                 std::vector<std::array<int32_t, 4>> &       tetrahedra,
                 MultiThreaderBase *                         threader = nullptr,
                 DelaunayRepairStatistics *                  statistics = nullptr,
                 const std::vector<double> *                 previousXyz = nullptr);

/** RepairDelaunay3D from a warm start: its tetrahedra, its nodes (previousXyz; none when empty) and, when given, its
 * neighbours, which spare finding them from the faces (they are checked first). neighbours (optional): set to those
 * of the result (for the next call's warm start); empty when it returns false. */
DynamicMeshRegistration_EXPORT bool
RepairDelaunay3D(const std::vector<double> &           xyz,
                 const DelaunayWarmStart &             warmStart,
                 std::vector<std::array<int32_t, 4>> & tetrahedra,
                 MultiThreaderBase *                   threader = nullptr,
                 DelaunayRepairStatistics *            statistics = nullptr,
                 std::vector<std::array<int32_t, 4>> * neighbours = nullptr);

/** Threshold of NonDegenerateDelaunay3D as DualMeshFilter uses it: a tetrahedron with shape below 1e-6 counts as flat.
 * Its four nodes are then coplanar to within a millionth of its size: its volume is still far above double round-off
 * (about 1e-14 relative for images up to a few thousand voxels across), but its FEM stiffness would scale as 1/shape.
 */
constexpr double DefaultMinimumTetrahedronShape = 1e-6;

/** Shape measure of a tetrahedron: 6 sqrt(2) V / L^3 with V its signed volume and L its longest edge; 1 for the
 * regular tetrahedron, 0 for a flat one, negative for a negatively oriented one. Scale invariant. */
DynamicMeshRegistration_EXPORT double
TetrahedronShape(const double * a, const double * b, const double * c, const double * d);

/** Delaunay3D without near-flat tetrahedra. Near-flat Delaunay tetrahedra come from near-degenerate node sets (four
 * nodes nearly coplanar and cocircular, e.g. a symmetric CVT whose centroids were rounded); exactly coplanar nodes
 * (such as nodes snapped onto one box face) never form one. Each round, every node of a tetrahedron with shape below
 * minimumShape is moved by a small deterministic pseudo-random step (a hash of node and round, no global random
 * state) along the axes it may move on (bit k of freeAxes[i]: axis k; 0 pins a node, e.g. a box corner), and the
 * nodes are tetrahedralized again. Each time a node is moved it is put at a fresh offset from its input position:
 * 1% of that tetrahedron's longest edge along its largest axis, doubling each round, never more than maximumStep.
 * No node is added (no Steiner points). xyz is updated in place; returns the number of nodes that ended up off their
 * input position (0 for generic input, which is then exactly Delaunay3D). Throws an itk::ExceptionObject when a flat
 * tetrahedron remains after maximumRounds rounds or consists of pinned nodes only.
 * warmStart (optional): an earlier tetrahedralization of these nodes and where they were then, tried first through
 * RepairDelaunay3D; the result does not depend on it. repaired (optional): set to whether the first round's
 * tetrahedralization came from it. neighbours (optional): set to the result's neighbours where it came from the warm
 * start unchanged (for the next warm start), else cleared. */
DynamicMeshRegistration_EXPORT size_t
NonDegenerateDelaunay3D(std::vector<double> &                 xyz,
                        const std::vector<uint8_t> &          freeAxes,
                        double                                maximumStep,
                        std::vector<std::array<int32_t, 4>> & tetrahedra,
                        double                                minimumShape,
                        unsigned int                          maximumRounds,
                        MultiThreaderBase *                   threader = nullptr,
                        const DelaunayWarmStart *             warmStart = nullptr,
                        bool *                                repaired = nullptr,
                        std::vector<std::array<int32_t, 4>> * neighbours = nullptr);
} // namespace dmr
} // namespace itk

#endif
