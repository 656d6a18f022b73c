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
// Timing of dmr::DiscreteCVT on densities like the registration's (|grad| of a smoothed shape, squared, plus
// 0.1 x mean): 2D 512x512 with 100 cells (cold start, then warm starts on a slowly moving shape) and 3D
// 256x256x132 with 3000 cells (contraction from 4^3 blocks, first optimisation, warm starts).
// Usage: dmrCVTBenchmark 2d|3d [mode [maximum sweeps of the first optimisation [warm starts [warm-start mode]]]]
// mode: auto|full|scan|gather, the sweep mode where the header has them; defaults auto, 1000, 20 in 2D / 3 in
// 3D, the first mode.
// Prints times, sweeps, swaps, energies and a hash of the labels, so two builds can be compared for identity.
#include "dmrDiscreteCVT.h"
#include "itkMultiThreaderBase.h"

#include <chrono>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <string>
#include <vector>

namespace
{
using Clock = std::chrono::steady_clock;

double
Seconds(Clock::time_point t0)
{
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

/** CPU seconds of the process (all threads): less sensitive than wall time to other jobs on a shared machine. */
double
CPUSeconds()
{
  timespec t;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

/** Separable Gaussian blur (border clamped) of a float image, in place. */
template <unsigned int D>
void
Blur(const itk::dmr::Grid<D> & grid, std::vector<float> & image, double sigma)
{
  const int           radius = static_cast<int>(std::ceil(3.0 * sigma));
  std::vector<double> kernel(2 * radius + 1);
  double              sum = 0.0;
  for (int i = -radius; i <= radius; ++i)
  {
    kernel[i + radius] = std::exp(-0.5 * i * i / (sigma * sigma));
    sum += kernel[i + radius];
  }
  for (auto & k : kernel)
  {
    k /= sum;
  }
  std::vector<float> out(image.size());
  for (unsigned int axis = 0; axis < D; ++axis)
  {
    const int64_t n = static_cast<int64_t>(grid.size[axis]);
    const size_t  stride = grid.stride[axis];
    for (size_t p = 0; p < grid.numberOfPixels; ++p)
    {
      const int64_t i = static_cast<int64_t>((p / stride) % grid.size[axis]);
      double        v = 0.0;
      for (int o = -radius; o <= radius; ++o)
      {
        const int64_t j = std::min(n - 1, std::max<int64_t>(0, i + o));
        v += kernel[o + radius] *
             image[static_cast<size_t>(static_cast<int64_t>(p) + (j - i) * static_cast<int64_t>(stride))];
      }
      out[p] = static_cast<float>(v);
    }
    image.swap(out);
  }
}

/** |grad(G_sigma * indicator of an ellipsoid)|^2 + 0.1 x its mean: sharp ridges along the shape's outline. */
template <unsigned int D>
std::vector<float>
RidgeDensity(const itk::dmr::Grid<D> & grid, const double * centre, const double * radii, double sigma)
{
  std::vector<float> image(grid.numberOfPixels);
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    double     q = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const double d = (idx[k] * grid.spacing[k] - centre[k]) / radii[k];
      q += d * d;
    }
    image[p] = q <= 1.0 ? 100.0f : 0.0f;
  }
  Blur<D>(grid, image, sigma);
  std::vector<float> density(grid.numberOfPixels);
  double             mean = 0.0;
  for (size_t p = 0; p < grid.numberOfPixels; ++p)
  {
    const auto idx = grid.Index(p);
    double     g2 = 0.0;
    for (unsigned int k = 0; k < D; ++k)
    {
      const size_t s = grid.stride[k];
      const bool   lo = idx[k] > 0, hi = idx[k] + 1 < static_cast<int64_t>(grid.size[k]);
      const double a = image[hi ? p + s : p], b = image[lo ? p - s : p];
      const double g = (a - b) / ((lo && hi ? 2.0 : 1.0) * grid.spacing[k]);
      g2 += g * g;
    }
    density[p] = static_cast<float>(g2);
    mean += g2;
  }
  mean /= static_cast<double>(grid.numberOfPixels);
  for (auto & d : density)
  {
    d += static_cast<float>(0.1 * mean);
  }
  return density;
}

uint64_t
Hash(const std::vector<int32_t> & labels)
{
  uint64_t h = 1469598103934665603ull;
  for (int32_t l : labels)
  {
    h = (h ^ static_cast<uint32_t>(l)) * 1099511628211ull;
  }
  return h;
}

template <unsigned int D>
void
Report(const char *                                              what,
       const typename itk::dmr::DiscreteCVT<D>::OptimizeResult & r,
       double                                                    seconds,
       double                                                    cpuSeconds,
       const itk::dmr::DiscreteCVT<D> &                          cvt)
{
  std::printf("%-22s %8.3f s (cpu %8.3f s)  sweeps %4zu  swaps %9zu  rejected %4zu  E %.9e -> %.9e  hash %016llx\n",
              what,
              seconds,
              cpuSeconds,
              r.sweeps,
              r.swaps,
              r.rejectedBatches,
              r.energyBefore,
              r.energyAfter,
              static_cast<unsigned long long>(Hash(cvt.GetLabels())));
}

/** Selects the sweep mode where the header has them (older headers have only the full scan). */
template <typename TCVT>
auto
SelectSweepMode(TCVT & cvt, const std::string & mode, int)
  -> decltype(cvt.SetSweepMode(TCVT::SweepMode::FullScan), void())
{
  using ModeType = typename TCVT::SweepMode;
  cvt.SetSweepMode(mode == "full"     ? ModeType::FullScan
                   : mode == "scan"   ? ModeType::ActiveScan
                   : mode == "gather" ? ModeType::ActiveGather
                                      : ModeType::Auto);
}
template <typename TCVT>
void
SelectSweepMode(TCVT &, const std::string &, long)
{
  std::printf("this header has only the full scan\n");
}

template <unsigned int D>
int
Run(const std::array<size_t, D> & size,
    const std::array<double, D> & spacing,
    size_t                        numberOfCells,
    unsigned int                  blockSize,
    size_t                        maximumSweeps,
    size_t                        warmStarts,
    const double *                centre0,
    const double *                radii0,
    const double *                drift,
    const std::string &           sweepMode,
    const std::string &           warmSweepMode)
{
  auto threader = itk::MultiThreaderBase::New();
  std::printf("grid");
  for (unsigned int k = 0; k < D; ++k)
  {
    std::printf(" %zu", size[k]);
  }
  std::printf(", %zu cells, block %u, %u threads, %u work units, %s\n",
              numberOfCells,
              blockSize,
              threader->GetMaximumNumberOfThreads(),
              threader->GetNumberOfWorkUnits(),
              sweepMode.c_str());
  const itk::dmr::Grid<D> grid(size, spacing);
  auto                    t0 = Clock::now();
  auto                    density = RidgeDensity<D>(grid, centre0, radii0, 2.0);
  std::printf("density                %8.3f s\n", Seconds(t0));

  itk::dmr::DiscreteCVT<D> cvt;
  SelectSweepMode(cvt, sweepMode, 0);
  cvt.SetDensity(grid, density.data(), threader);
  t0 = Clock::now();
  double c0 = CPUSeconds();
  cvt.ContractionInitialize(numberOfCells, blockSize);
  std::printf("contraction            %8.3f s (cpu %8.3f s)  E %.9e  hash %016llx\n",
              Seconds(t0),
              CPUSeconds() - c0,
              cvt.GetEnergy(),
              static_cast<unsigned long long>(Hash(cvt.GetLabels())));
  t0 = Clock::now();
  c0 = CPUSeconds();
  auto result = cvt.Optimize(0.0, maximumSweeps);
  Report<D>("first optimisation", result, Seconds(t0), CPUSeconds() - c0, cvt);

  double totalSeconds = 0.0, totalCPUSeconds = 0.0;
  size_t totalSweeps = 0;
  for (size_t it = 1; it <= warmStarts; ++it)
  {
    double centre[D], radii[D];
    for (unsigned int k = 0; k < D; ++k)
    {
      centre[k] = centre0[k] + drift[k] * static_cast<double>(it);
      radii[k] = radii0[k] * (1.0 + 0.002 * static_cast<double>(it));
    }
    density = RidgeDensity<D>(grid, centre, radii, 2.0);
    SelectSweepMode(cvt, warmSweepMode, 0);
    const std::vector<int32_t> labels = cvt.GetLabels();
    cvt.SetDensity(grid, density.data(), threader);
    cvt.SetLabels(labels.data(), numberOfCells);
    t0 = Clock::now();
    c0 = CPUSeconds();
    result = cvt.Optimize(0.0, 1000);
    const double seconds = Seconds(t0), cpuSeconds = CPUSeconds() - c0;
    totalSeconds += seconds;
    totalCPUSeconds += cpuSeconds;
    totalSweeps += result.sweeps;
    const std::string name = "warm start " + std::to_string(it);
    Report<D>(name.c_str(), result, seconds, cpuSeconds, cvt);
  }
  if (warmStarts > 0)
  {
    std::printf("warm starts: mean %.4f s (cpu %.4f s), mean %.1f sweeps\n",
                totalSeconds / warmStarts,
                totalCPUSeconds / warmStarts,
                static_cast<double>(totalSweeps) / warmStarts);
  }
  return 0;
}
} // namespace

int
main(int argc, char * argv[])
{
  const std::string mode = argc > 1 ? argv[1] : "2d";
  const std::string sweepMode = argc > 2 ? argv[2] : "auto";
  const size_t      maximumSweeps = argc > 3 ? std::stoul(argv[3]) : 1000; // of the first optimisation
  const long        warmStarts = argc > 4 ? std::stol(argv[4]) : -1;       // -1: 20 in 2D, 3 in 3D
  const std::string warmSweepMode = argc > 5 ? argv[5] : sweepMode;
  if (mode == "2d")
  {
    const double centre[2] = { 256.0, 256.0 }, radii[2] = { 150.0, 120.0 }, drift[2] = { 0.5, 0.3 };
    return Run<2>({ 512, 512 },
                  { 1.0, 1.0 },
                  100,
                  1,
                  maximumSweeps,
                  warmStarts < 0 ? 20 : warmStarts,
                  centre,
                  radii,
                  drift,
                  sweepMode,
                  warmSweepMode);
  }
  if (mode == "3d")
  {
    const double centre[3] = { 128.0, 128.0, 66.0 }, radii[3] = { 90.0, 80.0, 45.0 }, drift[3] = { 0.5, 0.3, 0.2 };
    return Run<3>({ 256, 256, 132 },
                  { 1.0, 1.0, 1.0 },
                  3000,
                  4,
                  maximumSweeps,
                  warmStarts < 0 ? 3 : warmStarts,
                  centre,
                  radii,
                  drift,
                  sweepMode,
                  warmSweepMode);
  }
  std::fprintf(stderr, "usage: %s 2d|3d [auto|full|scan|gather [sweeps [warm starts [warm mode]]]]\n", argv[0]);
  return 1;
}
