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
// Time of one 3D dual mesh construction (itk::DualMeshFilter) on a CT-sized label image. Not a test (built only on
// request, never run by ctest):
//   cmake --build <build> --target dmrDualMeshBenchmark
//   <build>/bin/dmrDualMeshBenchmark [cells [nx ny nz [runs [noedges]]]]
// Labels: the discrete Voronoi diagram (physical distance) of 'cells' random sites, each site at a voxel centre, a
// cheap stand-in for a CVT (cells are convex, so the statistics pass sees realistic interfaces).
#include "itkDualMeshFilter.h"
#include "dmrDelaunay3D.h"
#include "itkImage.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <set>
#include <string>

namespace
{
using LabelImageType = itk::Image<int32_t, 3>;
using FilterType = itk::DualMeshFilter<LabelImageType>;

LabelImageType::Pointer
VoronoiLabels(const LabelImageType::SizeType & size, const LabelImageType::SpacingType & spacing, size_t cells)
{
  auto image = LabelImageType::New();
  image->SetRegions(size);
  image->SetSpacing(spacing);
  image->Allocate();
  const size_t                     nx = size[0], ny = size[1], nz = size[2];
  std::mt19937_64                  rng(20240611);
  std::set<std::array<long, 3>>    taken;
  std::vector<std::array<long, 3>> sites;
  while (sites.size() < cells)
  {
    const std::array<long, 3> s{ static_cast<long>(rng() % nx),
                                 static_cast<long>(rng() % ny),
                                 static_cast<long>(rng() % nz) };
    if (taken.insert(s).second)
    {
      sites.push_back(s);
    }
  }
  // buckets of about one site each; rings of buckets searched outwards until no closer site can exist
  const double volume = nx * spacing[0] * ny * spacing[1] * nz * spacing[2];
  const double h = std::cbrt(volume / static_cast<double>(cells));
  long         nb[3];
  for (unsigned int k = 0; k < 3; ++k)
  {
    nb[k] = std::max<long>(1, static_cast<long>(std::ceil(size[k] * spacing[k] / h)));
  }
  std::vector<std::vector<int32_t>> bucket(nb[0] * nb[1] * nb[2]);
  auto                              bucketOf = [&](const std::array<long, 3> & v, long(&b)[3]) {
    for (unsigned int k = 0; k < 3; ++k)
    {
      b[k] = std::min<long>(nb[k] - 1, static_cast<long>(v[k] * spacing[k] / h));
    }
  };
  for (size_t c = 0; c < sites.size(); ++c)
  {
    long b[3];
    bucketOf(sites[c], b);
    bucket[b[0] + nb[0] * (b[1] + nb[1] * b[2])].push_back(static_cast<int32_t>(c));
  }
  int32_t * L = image->GetBufferPointer();
  for (long z = 0; z < static_cast<long>(nz); ++z)
  {
    for (long y = 0; y < static_cast<long>(ny); ++y)
    {
      for (long x = 0; x < static_cast<long>(nx); ++x)
      {
        long b[3];
        bucketOf({ x, y, z }, b);
        double  best = 1e300;
        int32_t label = -1;
        for (long r = 0;; ++r)
        {
          for (long bz = b[2] - r; bz <= b[2] + r; ++bz)
          {
            for (long by = b[1] - r; by <= b[1] + r; ++by)
            {
              for (long bx = b[0] - r; bx <= b[0] + r; ++bx)
              {
                if (std::max({ std::abs(bx - b[0]), std::abs(by - b[1]), std::abs(bz - b[2]) }) != r || bx < 0 ||
                    by < 0 || bz < 0 || bx >= nb[0] || by >= nb[1] || bz >= nb[2])
                {
                  continue;
                }
                for (int32_t c : bucket[bx + nb[0] * (by + nb[1] * bz)])
                {
                  const double dx = (x - sites[c][0]) * spacing[0], dy = (y - sites[c][1]) * spacing[1],
                               dz = (z - sites[c][2]) * spacing[2];
                  const double d = dx * dx + dy * dy + dz * dz;
                  if (d < best || (d == best && c < label))
                  {
                    best = d;
                    label = c;
                  }
                }
              }
            }
          }
          if (label >= 0 && best <= (r * h) * (r * h))
          {
            break;
          }
        }
        L[x + nx * (y + ny * z)] = label;
      }
    }
  }
  return image;
}
} // namespace

int
main(int argc, char * argv[])
{
  const size_t             cells = argc > 1 ? std::strtoul(argv[1], nullptr, 10) : 3000;
  LabelImageType::SizeType size{ { 256, 256, 132 } };
  if (argc > 4)
  {
    for (unsigned int k = 0; k < 3; ++k)
    {
      size[k] = std::strtoul(argv[2 + k], nullptr, 10);
    }
  }
  const int                   runs = argc > 5 ? std::atoi(argv[5]) : 5;
  LabelImageType::SpacingType spacing;
  spacing[0] = 0.7;
  spacing[1] = 0.7;
  spacing[2] = 2.5;
  using Clock = std::chrono::steady_clock;
  auto       t0 = Clock::now();
  const auto labels = VoronoiLabels(size, spacing, cells);
  std::printf("labels: %zu x %zu x %zu voxels, %zu cells (Voronoi of random sites), generated in %.2f s\n",
              static_cast<size_t>(size[0]),
              static_cast<size_t>(size[1]),
              static_cast<size_t>(size[2]),
              cells,
              std::chrono::duration<double>(Clock::now() - t0).count());
  auto filter = FilterType::New();
  filter->SetInput(labels);
  filter->SetSnapToBoxEdges(!(argc > 6 && std::string(argv[6]) == "noedges"));
  std::vector<double> times;
  for (int r = 0; r < runs; ++r)
  {
    filter->Modified();
    t0 = Clock::now();
    filter->Update();
    times.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
  }
  std::sort(times.begin(), times.end());
  const auto & mesh = filter->GetSimplexMesh();
  // the Delaunay share: the same nodes tetrahedralized again, by blocks on the filter's work units (Delaunay3D) and
  // by one TetGen run; min and median of max(5, runs) runs (the median shows the scheduling noise of a loaded host)
  std::vector<std::array<int32_t, 4>> tetrahedra;
  std::vector<double>                 blocks, tetgen;
  for (int r = 0; r < std::max(5, runs); ++r)
  {
    t0 = Clock::now();
    itk::dmr::Delaunay3D(mesh.nodes, tetrahedra, filter->GetMultiThreader());
    blocks.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
    t0 = Clock::now();
    itk::dmr::TetGenDelaunay3D(mesh.nodes, tetrahedra);
    tetgen.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
  }
  std::sort(blocks.begin(), blocks.end());
  std::sort(tetgen.begin(), tetgen.end());
  std::vector<double> shapes;
  for (const auto & t : mesh.elements)
  {
    shapes.push_back(itk::dmr::TetrahedronShape(
      &mesh.nodes[3 * t[0]], &mesh.nodes[3 * t[1]], &mesh.nodes[3 * t[2]], &mesh.nodes[3 * t[3]]));
  }
  std::sort(shapes.begin(), shapes.end());
  std::printf("dual mesh: %zu nodes (%zu fixed), %zu tetrahedra, %zu nudged nodes, %zu of %zu inner adjacency "
              "edges missing\n",
              mesh.NumberOfNodes(),
              static_cast<size_t>(filter->GetNumberOfBoundaryNodes()),
              mesh.elements.size(),
              static_cast<size_t>(filter->GetNumberOfPerturbedNodes()),
              static_cast<size_t>(filter->GetNumberOfMissingAdjacencyEdges()),
              static_cast<size_t>(filter->GetNumberOfInnerAdjacencyEdges()));
  std::printf("shape 6 sqrt(2) V / L^3 (edge snapping %s): min %.3g, 1%% %.3g, median %.3g\n",
              filter->GetSnapToBoxEdges() ? "on" : "off",
              shapes.front(),
              shapes[shapes.size() / 100],
              shapes[shapes.size() / 2]);
  std::printf("construction time over %d runs (%u work units): min %.3f s, median %.3f s, max %.3f s; the Delaunay "
              "tetrahedralization alone over %zu runs: Delaunay3D min %.4f s, median %.4f s; one TetGen run min %.4f "
              "s, median %.4f s\n",
              runs,
              filter->GetNumberOfWorkUnits(),
              times.front(),
              times[times.size() / 2],
              times.back(),
              blocks.size(),
              blocks.front(),
              blocks[blocks.size() / 2],
              tetgen.front(),
              tetgen[tetgen.size() / 2]);
  return 0;
}
