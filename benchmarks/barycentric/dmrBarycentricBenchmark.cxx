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
// Times dmr::BarycentricMap::Build (the owner element and weights of every pixel) on jittered regular meshes: 2D
// 512 x 512 with 10 x 10 nodes (the circle-to-epsilon size), 2D 1024 x 256 with 20 x 5 nodes (circle-to-leaf) and 3D
// 256 x 256 x 132 with 15 x 15 x 14 nodes (about 3000, thorax256). Prints the best and mean time of each and a hash
// of the elements and weights, so that two revisions can be checked for the same result.
// Usage: dmrBarycentricBenchmark [repetitions of the 2D builds (default 100; 3D: a twentieth, at least 3)] [threads]
#include "dmrBarycentricMap.h"
#include "dmrSimplexMesh.h"
#include "itkMultiThreaderBase.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <random>

namespace
{
using namespace itk::dmr;

template <unsigned int D>
uint64_t
Hash(const BarycentricMap<D> & map)
{
  uint64_t h = 1469598103934665603ull; // FNV-1a over the bytes
  auto     mix = [&](const void * data, size_t bytes) {
    const auto * c = static_cast<const unsigned char *>(data);
    for (size_t i = 0; i < bytes; ++i)
    {
      h = (h ^ c[i]) * 1099511628211ull;
    }
  };
  mix(map.GetElements().data(), map.GetElements().size() * sizeof(int32_t));
  mix(map.GetWeights().data(), map.GetWeights().size() * sizeof(float));
  return h;
}

template <unsigned int D>
void
Run(const char * name, const Grid<D> & grid, SimplexMesh<D> mesh, double jitter, int repetitions, unsigned threads)
{
  // move the interior nodes by up to +-jitter pixels, so that the elements are irregular
  std::mt19937                           rng(7);
  std::uniform_real_distribution<double> uniform(-jitter, jitter);
  for (size_t a = 0; a < mesh.NumberOfNodes(); ++a)
  {
    bool onBox = false;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double x = mesh.nodes[a * D + k];
      onBox = onBox || x <= 0.0 || x >= static_cast<double>(grid.size[k] - 1) * grid.spacing[k];
    }
    for (unsigned int k = 0; k < D && !onBox; ++k)
    {
      mesh.nodes[a * D + k] += uniform(rng) * grid.spacing[k];
    }
  }
  auto threader = itk::MultiThreaderBase::New();
  threader->SetMaximumNumberOfThreads(threads);
  threader->SetNumberOfWorkUnits(threads);
  BarycentricMap<D> map;
  map.Build(grid, mesh, threader); // warm-up: the buffers are allocated
  double best = 1e30, sum = 0.0;
  for (int r = 0; r < repetitions; ++r)
  {
    const auto t0 = std::chrono::steady_clock::now();
    map.Build(grid, mesh, threader);
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    best = std::min(best, s);
    sum += s;
  }
  std::printf("%-28s %zu elements, %u threads: best %8.3f ms, mean %8.3f ms, hash %016llx\n",
              name,
              mesh.elements.size(),
              threads,
              best * 1e3,
              sum / repetitions * 1e3,
              static_cast<unsigned long long>(Hash(map)));
}
} // namespace

int
main(int argc, char * argv[])
{
  const int      repetitions = argc > 1 ? std::max(1, std::atoi(argv[1])) : 100;
  const unsigned threads = argc > 2 ? static_cast<unsigned>(std::max(1, std::atoi(argv[2]))) : 2u;
  const Grid<2>  epsilon(std::array<size_t, 2>{ 512, 512 }, std::array<double, 2>{ 1.0, 1.0 });
  Run<2>("2D 512 x 512, 10 x 10", epsilon, MakeRegularMesh<2>(epsilon, { 10, 10 }), 15.0, repetitions, threads);
  const Grid<2> leaf(std::array<size_t, 2>{ 1024, 256 }, std::array<double, 2>{ 1.0, 1.0 });
  Run<2>("2D 1024 x 256, 20 x 5", leaf, MakeRegularMesh<2>(leaf, { 20, 5 }), 15.0, repetitions, threads);
  const Grid<3> thorax(std::array<size_t, 3>{ 256, 256, 132 }, std::array<double, 3>{ 1.2, 1.2, 2.5 });
  Run<3>("3D 256 x 256 x 132, 15^2 x 14",
         thorax,
         MakeRegularMesh<3>(thorax, { 15, 15, 14 }),
         3.0,
         std::max(3, repetitions / 20),
         threads);
  return EXIT_SUCCESS;
}
