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
// itkDynamicMeshRegistration: command-line FEM registration on a dynamic mesh (Cai et al. 2015).
// Reads any ITK-readable fixed/moving image (NIfTI, MetaImage, ..., or a DICOM series directory) and writes the
// warped image, the displacement field, its Jacobian determinant, the energy history, the meshes and a JSON report.
#include "itkFEMRegistrationMethod.h"
#include "dmrFieldImage.h"
#include "dmrCudaBackend.h"
#include "dmrConfigure.h"
#include "itkImageFileReader.h"
#include "itkImageFileWriter.h"
#include "itkImageSeriesReader.h"
#include "itkGDCMImageIO.h"
#include "itkGDCMSeriesFileNames.h"
#include "itkImageIOFactory.h"
#include "dmrMeshFileIO.h"
#include "dmrInitialTransform.h"
#include "dmrLandmarks.h"
#include "dmrReadImage.h"
#include "dmrToolErrors.h"
#include "dmrToolOutput.h"
#include "dmrErrorStatistics.h"
#include "itkResampleImageFilter.h"
#include "itkLinearInterpolateImageFunction.h"
#include "itkNearestNeighborInterpolateImageFunction.h"
#include "itkCommand.h"
#include "itkMultiThreaderBase.h"
#include "itksys/Directory.hxx"
#include "itksys/SystemTools.hxx"

#ifdef DMR_WITH_VTK
#include <vtkSmartPointer.h>
#include <vtkPoints.h>
#include <vtkCellArray.h>
#include <vtkUnsignedCharArray.h>
#include <vtkPointData.h>
#include <vtkUnstructuredGrid.h>
#include <vtkXMLUnstructuredGridWriter.h>
#include <vtkXMLUnstructuredGridReader.h>
#include <vtkUnstructuredGridReader.h>
#include <vtkCallbackCommand.h>
#include <vtkCellType.h>
#include <vtkOutputWindow.h>
#include <vtkLogger.h>
#include <vtkSMPTools.h>
#endif

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <fstream>
#include <future>
#include <tuple>
#include <iomanip>
#include <iostream>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <type_traits>
#include <unistd.h>
#include <vector>
#include <sys/resource.h>

namespace
{
using dmrtools::UsageError;

/** Without --nodes, an image gets at most one mesh node per this many pixels (voxels). */
constexpr long DefaultPixelsPerNode = 8;

struct Options
{
  std::string fixed, moving, outputDir, report, mesh{ "dynamic" }, backend{ "auto" };
  long        nodes{ 0 };
  bool        nodesGiven{ false };
  long        iterations{ 100 };
  long        levels{ 3 };
  long        threads{ 0 };
  long        saveMeshEvery{ 0 };
  long        regularSize{ 0 };
  long        cvtMaxSweeps{ 1000 };
  double      cvtEpsilon{ 0.0 };
  double      lambda{ 1.0 }, mu{ 1.0 };
  double      energyRatio{ 0.02 }, alphaFactor{ 0.1 };
  std::string forceGradient{ "warped" };
  long        stepHalvings{ 5 };
  long        deviceSolveMinDofs{ 301 };
  long        directSolveMaxDofs{ 300 };
  double      femTolerance{ 1e-6 };
  std::string fixedMask, fixedLandmarks, movingLandmarks, truthDisplacement, initialTransform;
  bool        landmarksInMM{ false };
  bool        inverse{ false };
  bool        gpuOrderSolve{ true };
  bool        window{ false };
  double      windowLow{ 0.0 }, windowHigh{ 0.0 };
};

const char * const Usage =
  "usage: itkDynamicMeshRegistration --fixed F --moving M --output-dir D [options]\n"
  "  FEM deformable registration with a dynamic mesh (Cai, Guo, Zhong, Mao 2015).\n"
  "  F, M: any ITK-readable image (NIfTI .nii/.nii.gz, .mha, ...) or a DICOM series directory; 2D or 3D.\n"
  "options:\n"
  "  --nodes N              mesh nodes (default 100 in 2D, 3000 in 3D; on small images at most one per 8 pixels)\n"
  "  --iterations K         registration iterations (default 100)\n"
  "  --levels L             pyramid levels summed in the MSSD (default 3)\n"
  "  --mesh MODE            dynamic (default) | regular | a mesh file (.vtk, .vtu) used as a static mesh\n"
  "  --regular-size n       nodes per axis of the regular mesh, at least 3 (default round(N^(1/dim)))\n"
  "  --lambda V, --mu V     Lame parameters of the elastic regulariser (default 1, 1)\n"
  "  --energy-ratio R       beta is set at iteration 1 so that beta R / D = R (default 0.02, paper 5.1)\n"
  "  --alpha-factor A       density base value alpha = A x mean |f|^2 (default 0.1, paper 5.1)\n"
  "  --force-gradient G     warped (default: gradient of the warped moving image, the derivative for W o exp(u))\n"
  "                         | mapped (moving image gradient at W(x), a literal reading of paper Eq. 5)\n"
  "  --step-halvings H      halve an update at most H times while it would not lower the MSSD by 1e-4 of its\n"
  "                         first-order decrease; if none does, keep the transformation (default 5; 0: always take\n"
  "                         the full step, as in the paper)\n"
  "  --cvt-max-sweeps S     at most S swap sweeps of the CVT optimisation per iteration (default 1000: converge)\n"
  "  --cvt-epsilon E        stop the CVT sweeps when a sweep lowers the energy by at most E x energy (default 0)\n"
  "  --fem-tolerance T      stop the conjugate-gradient solve of the elastic system at |r| < T |f| (default 1e-6;\n"
  "                         1e-16 to 1e-2)\n"
  "  --direct-solve-max-dofs N  solve elastic systems of at most N free unknowns on the CPU exactly (factorised)\n"
  "                         instead of by conjugate gradients (default 300; 0: always conjugate gradients)\n"
  "  --gpu-order-solve      solve the larger elastic systems on the CPU by the GPU's conjugate gradients, in its\n"
  "                         arithmetic order, so that a cpu run takes the cuda run's solves bit for bit (default)\n"
  "  --assembled-solve      solve them by conjugate gradients on the assembled matrix instead: a little faster on\n"
  "                         few cores, but cpu and cuda runs can then part on a large 3D deformation\n"
  "  --threads T            worker threads (default: all cores)\n"
  "  --backend B            auto (default) | cpu | cuda\n"
  "  --device-solve-min-dofs N  cuda back-end: solve the elastic system on the GPU when it has at least N free\n"
  "                         unknowns, on the CPU otherwise (default 301: the systems --direct-solve-max-dofs does\n"
  "                         not factorise; 0: always on the GPU)\n"
  "  --save-mesh-every K    also write the mesh every K iterations (first and last are always written)\n"
  "  --inverse              also write inverse-displacement.nii.gz, the inverse transformation (on the fixed grid:\n"
  "                         a moving point y maps to the fixed point y + v(y)), carried along the iterations as\n"
  "                         W^-1 <- exp(-u) o W^-1; the report gets inverse_consistency_mm\n"
  "  --initial-transform FILE  start from this transformation (e.g. an affine pre-alignment): an ITK transform file\n"
  "                         (.tfm, .txt, .mat, .h5: ITK, ANTs, elastix's ITK export) or a displacement field image\n"
  "                         (mm, moving point = fixed point + u, LPS); the outputs hold it composed with the\n"
  "                         registration's part. With --inverse the inverse starts from its inverse (a field's by\n"
  "                         fixed-point iteration; a folded field, det J <= 0 somewhere, has none and is refused)\n"
  "  --fixed-mask FILE      region of interest on the fixed image (non-zero = inside, e.g. the lungs): forces,\n"
  "                         density and SSD only inside it; resampled (nearest) onto the fixed grid if needed\n"
  "  --intensity-window LO,HI  register the images clamped to [LO, HI] and scaled to [0, 1] (e.g. -1000,200 for\n"
  "                         lung CT in HU); warped.nii.gz keeps the moving image's own intensities\n"
  "  --fixed-landmarks FILE, --moving-landmarks FILE\n"
  "                         corresponding points (DIR-Lab format: 'x y z' per line, 1-based voxel indices of the\n"
  "                         fixed / moving image): the report gets tre_mm and tre_initial_mm {mean, std, p95, max}\n"
  "                         and the mean of fixed + u - moving, tre_mean_residual_mm [x, y, z] (and _initial_)\n"
  "  --landmarks-in-mm      the landmark files hold physical coordinates (mm) instead of voxel indices\n"
  "  --truth-displacement FILE  a known displacement field on the fixed grid (mm, ITK convention): the report gets\n"
  "                         dense_error_mm and dense_error_initial_mm {mean, p95, max} inside the fixed mask (or all)\n"
  "  --report FILE          JSON report (default D/report.json)\n"
  "  --help, --version\n"
  "outputs in D: warped.nii.gz, displacement.nii.gz (mm, on the fixed grid, moving point = fixed point + u; in ITK's\n"
  "  LPS frame: RAS tools such as nibabel or FSL must negate x and y),\n"
  "  jacobian.nii.gz (det of I + grad u), with --inverse inverse-displacement.nii.gz, energy.csv, mesh_NNNN.vtu +\n"
  "  mesh.pvd, report.json; they replace those of an earlier run in D (its other mesh_NNNN.vtu files and, without\n"
  "  --inverse, its inverse-displacement.nii.gz are removed), and an output that would replace an input is refused\n";

long
ParseInteger(const std::string & flag, const std::string & value)
{
  char * end = nullptr;
  errno = 0;
  const long v = std::strtol(value.c_str(), &end, 10);
  if (value.empty() || *end != '\0')
  {
    throw UsageError(flag + " expects an integer, got '" + value + "'");
  }
  if (errno == ERANGE)
  {
    throw UsageError(flag + ": " + value + " is out of range");
  }
  return v;
}

double
ParseReal(const std::string & flag, const std::string & value)
{
  char *       end = nullptr;
  const double v = std::strtod(value.c_str(), &end);
  if (value.empty() || *end != '\0' || !std::isfinite(v))
  {
    throw UsageError(flag + " expects a number, got '" + value + "'");
  }
  return v;
}

/** The directory --report names (absolute). */
std::string
ReportDirectory(const Options & opt)
{
  return itksys::SystemTools::GetFilenamePath(itksys::SystemTools::CollapseFullPath(opt.report));
}

/** True when --report names a file in the output directory (which the tool creates and commits its outputs to). */
bool
ReportInOutputDirectory(const Options & opt)
{
  return !opt.outputDir.empty() && ReportDirectory(opt) == itksys::SystemTools::CollapseFullPath(opt.outputDir);
}

/** The run reads its inputs before it writes anything, so an output named like an input would go through and destroy
 * that input (a --report naming the fixed image overwrote it with the JSON; D/warped.nii.gz given as the moving image
 * was replaced). Throws a UsageError naming both. */
void
RefuseOutputsOverInputs(const Options & opt)
{
  std::vector<std::pair<std::string, std::string>> inputs = { { "--fixed", opt.fixed },
                                                              { "--moving", opt.moving },
                                                              { "--fixed-mask", opt.fixedMask },
                                                              { "--fixed-landmarks", opt.fixedLandmarks },
                                                              { "--moving-landmarks", opt.movingLandmarks },
                                                              { "--truth-displacement", opt.truthDisplacement },
                                                              { "--initial-transform", opt.initialTransform } };
  if (opt.mesh != "dynamic" && opt.mesh != "regular")
  {
    inputs.emplace_back("--mesh", opt.mesh);
  }
  const std::string              report = opt.report.empty() ? "" : dmrtools::DirectoryEntry(opt.report);
  const std::vector<std::string> written = { "warped.nii.gz",   "displacement.nii.gz", "inverse-displacement.nii.gz",
                                             "jacobian.nii.gz", "energy.csv",          "mesh.pvd",
                                             "report.json" };
  // the name of the output in D that path is (empty if none)
  auto outputNamed = [&](const std::string & path) -> std::string {
    const std::string name = dmrtools::NameInDirectory(opt.outputDir, path);
    const bool        ours = std::find(written.begin(), written.end(), name) != written.end();
    return ours || dmrtools::IsNumberedMeshName(name) ? name : "";
  };
  const std::string reportOver = opt.report.empty() ? "" : outputNamed(opt.report);
  if (!reportOver.empty() && reportOver != "report.json") // D/report.json is the report already
  {
    throw UsageError("--report " + opt.report + " would replace the output " + reportOver +
                     ": choose another file name");
  }
  for (const auto & [flag, path] : inputs)
  {
    if (path.empty())
    {
      continue;
    }
    std::string output;
    if (dmrtools::DirectoryEntry(path) == report)
    {
      output = "--report";
    }
    else if (!outputNamed(path).empty())
    {
      output = "the output " + outputNamed(path) + " in --output-dir";
    }
    if (!output.empty())
    {
      throw UsageError(output + " would replace the input " + flag + " " + path +
                       ": choose another output directory or file name");
    }
  }
}

Options
ParseArguments(int argc, char * argv[])
{
  Options opt;
  for (int i = 1; i < argc; ++i)
  {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h")
    {
      std::cout << Usage;
      std::exit(EXIT_SUCCESS);
    }
    if (a == "--landmarks-in-mm")
    {
      opt.landmarksInMM = true;
      continue;
    }
    if (a == "--gpu-order-solve" || a == "--assembled-solve")
    {
      opt.gpuOrderSolve = a == "--gpu-order-solve";
      continue;
    }
    if (a == "--inverse")
    {
      opt.inverse = true;
      continue;
    }
    if (a == "--version")
    {
      std::cout << "itkDynamicMeshRegistration " << DMR_VERSION_STRING << " (ITK " << ITK_VERSION_STRING
                << ", CUDA: " << itk::dmr::cuda::DeviceDescription() << ")\n";
      std::exit(EXIT_SUCCESS);
    }
    if (i + 1 >= argc)
    {
      throw UsageError("unknown option or missing value: " + a + " (see --help)");
    }
    const std::string v = argv[++i];
    if (a == "--fixed")
      opt.fixed = v;
    else if (a == "--moving")
      opt.moving = v;
    else if (a == "--output-dir")
      opt.outputDir = v;
    else if (a == "--report")
      opt.report = v;
    else if (a == "--mesh")
      opt.mesh = v;
    else if (a == "--backend")
      opt.backend = v;
    else if (a == "--nodes")
    {
      opt.nodes = ParseInteger(a, v);
      opt.nodesGiven = true;
    }
    else if (a == "--iterations")
      opt.iterations = ParseInteger(a, v);
    else if (a == "--levels")
      opt.levels = ParseInteger(a, v);
    else if (a == "--threads")
      opt.threads = ParseInteger(a, v);
    else if (a == "--save-mesh-every")
      opt.saveMeshEvery = ParseInteger(a, v);
    else if (a == "--regular-size")
      opt.regularSize = ParseInteger(a, v);
    else if (a == "--cvt-max-sweeps")
      opt.cvtMaxSweeps = ParseInteger(a, v);
    else if (a == "--cvt-epsilon")
      opt.cvtEpsilon = ParseReal(a, v);
    else if (a == "--lambda")
      opt.lambda = ParseReal(a, v);
    else if (a == "--mu")
      opt.mu = ParseReal(a, v);
    else if (a == "--energy-ratio")
      opt.energyRatio = ParseReal(a, v);
    else if (a == "--alpha-factor")
      opt.alphaFactor = ParseReal(a, v);
    else if (a == "--step-halvings")
      opt.stepHalvings = ParseInteger(a, v);
    else if (a == "--fem-tolerance")
      opt.femTolerance = ParseReal(a, v);
    else if (a == "--device-solve-min-dofs")
      opt.deviceSolveMinDofs = ParseInteger(a, v);
    else if (a == "--direct-solve-max-dofs")
      opt.directSolveMaxDofs = ParseInteger(a, v);
    else if (a == "--force-gradient")
      opt.forceGradient = v;
    else if (a == "--fixed-mask")
      opt.fixedMask = v;
    else if (a == "--fixed-landmarks")
      opt.fixedLandmarks = v;
    else if (a == "--moving-landmarks")
      opt.movingLandmarks = v;
    else if (a == "--truth-displacement")
      opt.truthDisplacement = v;
    else if (a == "--initial-transform")
      opt.initialTransform = v;
    else if (a == "--intensity-window")
    {
      const auto comma = v.find(',');
      if (comma == std::string::npos)
        throw UsageError("--intensity-window expects LO,HI, got '" + v + "'");
      opt.windowLow = ParseReal(a, v.substr(0, comma));
      opt.windowHigh = ParseReal(a, v.substr(comma + 1));
      opt.window = true;
    }
    else
      throw UsageError("unknown option " + a + " (see --help)");
  }
  if (opt.fixed.empty() || opt.moving.empty() || opt.outputDir.empty())
  {
    throw UsageError("--fixed, --moving and --output-dir are required (see --help)");
  }
  if (opt.iterations < 1)
    throw UsageError("--iterations must be at least 1");
  // the registration takes these as unsigned int: a larger value would wrap around
  constexpr long largest = std::numeric_limits<unsigned int>::max();
  for (const auto & [flag, value] : { std::make_pair("--iterations", opt.iterations),
                                      std::make_pair("--regular-size", opt.regularSize),
                                      std::make_pair("--threads", opt.threads) })
  {
    if (value > largest)
      throw UsageError(std::string(flag) + " must be at most " + std::to_string(largest) + ", got " +
                       std::to_string(value));
  }
  if (opt.levels < 1 || opt.levels > 8)
    throw UsageError("--levels must be between 1 and 8");
  if (opt.threads < 0)
    throw UsageError("--threads must be positive");
  if (opt.saveMeshEvery < 0)
    throw UsageError("--save-mesh-every must be 0 or positive");
  if (opt.lambda < 0 || opt.mu <= 0)
    throw UsageError("--lambda must be >= 0 and --mu > 0");
  if (opt.energyRatio <= 0 || opt.alphaFactor <= 0)
    throw UsageError("--energy-ratio and --alpha-factor must be positive");
  for (const auto & [flag, value] : { std::make_pair("--lambda", opt.lambda),
                                      std::make_pair("--mu", opt.mu),
                                      std::make_pair("--energy-ratio", opt.energyRatio),
                                      std::make_pair("--alpha-factor", opt.alphaFactor) })
  {
    constexpr double largest =
      itk::FEMRegistrationMethod<itk::Image<float, 2>, itk::Image<float, 2>>::LargestParameterValue;
    if (value > largest)
    {
      std::ostringstream message;
      message << flag << " must be at most " << largest << ", got " << value;
      throw UsageError(message.str());
    }
  }
  if (opt.deviceSolveMinDofs < 0)
    throw UsageError("--device-solve-min-dofs must be 0 or more");
  if (opt.directSolveMaxDofs < 0)
    throw UsageError("--direct-solve-max-dofs must be 0 or more");
  if (opt.stepHalvings < 0 || opt.stepHalvings > 30)
    throw UsageError("--step-halvings must be between 0 and 30");
  if (opt.forceGradient != "warped" && opt.forceGradient != "mapped")
    throw UsageError("--force-gradient must be warped or mapped");
  if (opt.backend != "auto" && opt.backend != "cpu" && opt.backend != "cuda")
    throw UsageError("--backend must be auto, cpu or cuda");
  if (opt.regularSize < 0) // 1 and 2 the registration refuses (with the reason)
    throw UsageError("--regular-size must not be negative");
  if (opt.cvtMaxSweeps < 1)
    throw UsageError("--cvt-max-sweeps must be at least 1");
  if (!(opt.cvtEpsilon >= 0.0 && opt.cvtEpsilon <= 1.0))
    throw UsageError("--cvt-epsilon must be in [0, 1]");
  if (!(opt.femTolerance >= 1e-16 && opt.femTolerance <= 1e-2))
    throw UsageError("--fem-tolerance must be in [1e-16, 1e-2]");
  if (opt.window && !(opt.windowHigh > opt.windowLow))
    throw UsageError("--intensity-window: HI must be greater than LO");
  if (opt.fixedLandmarks.empty() != opt.movingLandmarks.empty())
    throw UsageError("--fixed-landmarks and --moving-landmarks go together");
  for (const std::string * f :
       { &opt.fixedMask, &opt.fixedLandmarks, &opt.movingLandmarks, &opt.truthDisplacement, &opt.initialTransform })
  {
    if (!f->empty() && !itksys::SystemTools::FileExists(*f, true))
      throw UsageError("no such file: " + *f);
  }
  if (!opt.report.empty())
  {
    // the output directory may not exist yet: the tool creates it
    const std::string dir = ReportDirectory(opt);
    if (!ReportInOutputDirectory(opt) && !itksys::SystemTools::FileIsDirectory(dir))
      throw UsageError("--report: no such directory: " + dir);
    if (itksys::SystemTools::FileIsDirectory(opt.report))
      throw UsageError("--report names a directory: " + opt.report);
  }
  RefuseOutputsOverInputs(opt);
  return opt;
}

using dmrtools::ImageDimensionOf;

/** True when the file is a legacy VTK file of an unstructured grid (what ITK's mesh reader cannot read). */
bool
IsLegacyUnstructuredGrid(const std::string & path)
{
  std::ifstream in(path);
  std::string   line;
  for (int k = 0; k < 4 && std::getline(in, line); ++k)
  {
    if (line.rfind("DATASET", 0) == 0)
    {
      return line.find("UNSTRUCTURED_GRID") != std::string::npos;
    }
  }
  return false;
}

/** Reads a VTK unstructured grid (XML .vtu, as this tool writes its meshes, or legacy .vtk) into a mesh of triangles
 * (2D: every z must be 0) or tetrahedra (3D); cells of other types are left out. VTK's messages are caught and
 * thrown as one std::runtime_error. */
template <unsigned int D, typename TMesh>
typename TMesh::Pointer
ReadUnstructuredGrid(const std::string & path, bool xml)
{
#ifdef DMR_WITH_VTK
  std::string errors;
  auto        onError = vtkSmartPointer<vtkCallbackCommand>::New();
  onError->SetClientData(&errors);
  onError->SetCallback([](vtkObject *, unsigned long, void * data, void * message) {
    // VTK's text: "ERROR: In FILE, line N\nCLASS (ADDRESS): MESSAGE\n\n"; keep the first MESSAGE
    auto & text = *static_cast<std::string *>(data);
    if (text.empty() && message)
    {
      std::string       full = static_cast<const char *>(message);
      const std::size_t colon = full.find("): ");
      full = colon == std::string::npos ? full : full.substr(colon + 3);
      text = full.substr(0, full.find('\n'));
      text = text.empty() ? "VTK could not read the file" : text;
    }
  });
  // no VTK messages on the terminal (the tool's errors are one line): the reader's reach onError, those of the objects
  // it uses (its XML parser, the pipeline's executive) are dropped; VTK's logger stays quiet for the rest of the run
  struct QuietVTK
  {
    vtkOutputWindow * window = vtkOutputWindow::GetInstance();
    int               mode = window->GetDisplayMode();
    QuietVTK()
    {
      window->SetDisplayModeToNever();
      vtkLogger::SetStderrVerbosity(vtkLogger::VERBOSITY_OFF); // VTK 9 logs the same messages through its logger
    }
    ~QuietVTK() { window->SetDisplayMode(mode); }
  } quiet;
  auto read = [&](auto reader) {
    reader->AddObserver(vtkCommand::ErrorEvent, onError);
    reader->AddObserver(vtkCommand::WarningEvent, onError);
    reader->SetFileName(path.c_str());
    reader->Update();
    return vtkSmartPointer<vtkUnstructuredGrid>(reader->GetOutput());
  };
  const vtkSmartPointer<vtkUnstructuredGrid> grid = xml ? read(vtkSmartPointer<vtkXMLUnstructuredGridReader>::New())
                                                        : read(vtkSmartPointer<vtkUnstructuredGridReader>::New());
  if (!errors.empty())
  {
    throw std::runtime_error(errors);
  }
  if (!grid || grid->GetNumberOfPoints() == 0)
  {
    throw std::runtime_error("no points in the unstructured grid");
  }
  auto mesh = TMesh::New();
  for (vtkIdType i = 0; i < grid->GetNumberOfPoints(); ++i)
  {
    double xyz[3];
    grid->GetPoint(i, xyz);
    if (D == 2 && std::abs(xyz[2]) > 1e-9)
    {
      throw std::runtime_error("point " + std::to_string(i) + " has z != 0: not a 2D mesh");
    }
    typename TMesh::PointType p;
    for (unsigned int k = 0; k < D; ++k)
    {
      p[k] = xyz[k];
    }
    mesh->SetPoint(static_cast<typename TMesh::PointIdentifier>(i), p);
  }
  using CellType = typename TMesh::CellType;
  using SimplexCellType = std::conditional_t<D == 2, itk::TriangleCell<CellType>, itk::TetrahedronCell<CellType>>;
  const int                      simplex = D == 2 ? VTK_TRIANGLE : VTK_TETRA;
  typename TMesh::CellIdentifier id = 0;
  for (vtkIdType c = 0; c < grid->GetNumberOfCells(); ++c)
  {
    if (grid->GetCellType(c) != simplex)
    {
      continue;
    }
    vtkIdType         n = 0;
    const vtkIdType * ids = nullptr;
    grid->GetCellPoints(c, n, ids);
    typename CellType::CellAutoPointer cell;
    cell.TakeOwnership(new SimplexCellType);
    for (vtkIdType k = 0; k < n; ++k)
    {
      cell->SetPointId(static_cast<unsigned int>(k), static_cast<typename TMesh::PointIdentifier>(ids[k]));
    }
    mesh->SetCell(id++, cell);
  }
  return mesh;
#else
  (void)xml;
  throw std::runtime_error("this build reads VTK unstructured grids only with VTK (DMR_USE_VTK): " + path);
#endif
}

template <unsigned int D, typename TMesh>
void
WriteMeshVTU(const TMesh * mesh, const std::string & path)
{
#ifdef DMR_WITH_VTK
  auto points = vtkSmartPointer<vtkPoints>::New();
  auto fixed = vtkSmartPointer<vtkUnsignedCharArray>::New();
  fixed->SetName("fixed");
  for (auto it = mesh->GetPoints()->Begin(); it != mesh->GetPoints()->End(); ++it)
  {
    const auto & p = it.Value();
    points->InsertNextPoint(p[0], p[1], p[D - 1] * (D > 2 ? 1.0 : 0.0)); // z = 0 in 2D
    double flag = 0.0;
    mesh->GetPointData(it.Index(), &flag);
    fixed->InsertNextValue(flag > 0.5 ? 1 : 0);
  }
  auto grid = vtkSmartPointer<vtkUnstructuredGrid>::New();
  grid->SetPoints(points);
  grid->GetPointData()->AddArray(fixed);
  for (auto c = mesh->GetCells()->Begin(); c != mesh->GetCells()->End(); ++c)
  {
    vtkIdType ids[4];
    int       k = 0;
    for (auto p = c.Value()->PointIdsBegin(); p != c.Value()->PointIdsEnd(); ++p)
    {
      ids[k++] = static_cast<vtkIdType>(*p);
    }
    grid->InsertNextCell(D == 2 ? VTK_TRIANGLE : VTK_TETRA, k, ids);
  }
  auto writer = vtkSmartPointer<vtkXMLUnstructuredGridWriter>::New();
  writer->SetFileName(path.c_str());
  writer->SetInputData(grid);
  if (writer->Write() != 1)
  {
    throw std::runtime_error("could not write " + path);
  }
#else
  (void)mesh;
  (void)path;
#endif
}

/** Share of the reference image's pixels whose physical point lies inside the image's buffer, where ResampleOnto
 * interpolates it (outside, it gets the default value): estimated on a grid of at most 64 points per axis; when none
 * of those is inside, counted over every pixel, so 0 means that none is inside. */
template <typename TImage,
          typename TReference,
          typename TField = itk::Image<itk::Vector<float, TReference::ImageDimension>, TReference::ImageDimension>>
double
CoveredFraction(const TImage * image, const TReference * reference, const TField * through = nullptr)
{
  auto interpolator = itk::LinearInterpolateImageFunction<TImage, double>::New();
  interpolator->SetInputImage(image);
  const auto             region = reference->GetLargestPossibleRegion();
  constexpr unsigned int D = TReference::ImageDimension;
  auto                   covered = [&](const itk::Size<D> & step) {
    std::array<itk::IndexValueType, D> count;
    size_t                             total = 1;
    for (unsigned int k = 0; k < D; ++k)
    {
      count[k] = (static_cast<itk::IndexValueType>(region.GetSize(k)) + step[k] - 1) / step[k];
      total *= static_cast<size_t>(count[k]);
    }
    size_t inside = 0;
    for (size_t s = 0; s < total; ++s)
    {
      typename TReference::IndexType index;
      size_t                         rest = s;
      for (unsigned int k = 0; k < D; ++k)
      {
        index[k] = region.GetIndex(k) + static_cast<itk::IndexValueType>(rest % count[k]) * step[k];
        rest /= count[k];
      }
      typename TReference::PointType point;
      reference->TransformIndexToPhysicalPoint(index, point);
      if (through)
      {
        point += through->GetPixel(index);
      }
      inside += interpolator->IsInsideBuffer(point) ? 1 : 0;
    }
    return static_cast<double>(inside) / static_cast<double>(total);
  };
  itk::Size<D> sparse, every;
  for (unsigned int k = 0; k < D; ++k)
  {
    sparse[k] = std::max<itk::SizeValueType>(1, (region.GetSize(k) + 63) / 64);
    every[k] = 1;
  }
  const double estimate = covered(sparse);
  return estimate > 0.0 ? estimate : covered(every); // a small overlap that the sparse grid missed is counted exactly
}

/** Resample an image onto the grid of a reference image through physical space (identity transform). */
template <typename TImage, typename TReference>
typename TImage::Pointer
ResampleOnto(const TImage * image, const TReference * reference, bool nearest, typename TImage::PixelType outside)
{
  auto resample = itk::ResampleImageFilter<TImage, TImage, double>::New();
  resample->SetInput(image);
  resample->SetOutputParametersFromImage(reference);
  resample->SetDefaultPixelValue(outside);
  if (nearest)
  {
    resample->SetInterpolator(itk::NearestNeighborInterpolateImageFunction<TImage, double>::New());
  }
  resample->Update();
  typename TImage::Pointer out = resample->GetOutput();
  out->DisconnectPipeline();
  return out;
}

/** Peak resident set size of this process so far, in MiB. */
double
PeakRSSMiB()
{
  struct rusage usage
  {
  };
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0; // ru_maxrss is in KiB on Linux
}

template <unsigned int D>
int
Run(const Options & opt)
{
  using ImageType = itk::Image<float, D>;
  using MethodType = itk::FEMRegistrationMethod<ImageType, ImageType>;
  using MeshType = typename MethodType::MeshType;
  const auto tRead = std::chrono::steady_clock::now();
  using MaskType = typename MethodType::MaskImageType;
  using FieldType = typename MethodType::DisplacementFieldType;

  // The device's context (0.2-0.35 s on the H100 and H200 hosts, docs/benchmarks.md) is created on its own thread while
  // the inputs are read; the registration then finds it ready. Its time is reported apart (timing_s.device_warm_up);
  // whatever of it the reading did not cover counts in the registration's total.
  std::future<double> deviceWarmUp;
  if (opt.backend != "cpu")
  {
    deviceWarmUp = std::async(std::launch::async, [] {
      const auto t0 = std::chrono::steady_clock::now();
      itk::dmr::cuda::CreateContext(); // without a device it fails at once; the back-end choice below reports why
      return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    });
  }

  // The input files are read side by side, each on its own thread (decompressing a .gz file is single-threaded and
  // takes seconds for a CT); their results, errors included, are taken below in the order of the checks. DICOM
  // directories are read on this thread when their result is taken (GDCM's global state is not known to be safe to
  // share between threads).
  auto launch = [](const std::string & path) {
    return itksys::SystemTools::FileIsDirectory(path) ? std::launch::deferred : std::launch::async;
  };
  auto fixedRead =
    std::async(launch(opt.fixed), [&] { return dmrtools::ReadImageOrDicomSeries<ImageType>(opt.fixed); });
  auto movingRead =
    std::async(launch(opt.moving), [&] { return dmrtools::ReadImageOrDicomSeries<ImageType>(opt.moving); });
  // an optional input of dimension D, read on its own thread like the images once its header is checked here (the
  // header check takes what the image libraries print about a bad header into its one-line message)
  auto readOptional = [&launch](auto pointerTag, const std::string & path, const std::string & what) {
    using ReadType = typename decltype(pointerTag)::ObjectType;
    constexpr bool isField = std::is_same_v<ReadType, FieldType>;
    unsigned int   components = 1;
    if (ImageDimensionOf(path, &components) != D)
    {
      throw UsageError(what + " is not a " + std::to_string(D) + "D " + (isField ? "field: " : "image: ") + path);
    }
    // ITK would fill a field's components from a scalar image, or take a mask from a vector image's first one
    const unsigned int expected = isField ? D : 1;
    if (components != expected)
    {
      throw UsageError(what + " must have " + std::to_string(expected) + " component" + (expected > 1 ? "s" : "") +
                       " per voxel" + (isField ? " (a displacement field)" : "") + ", " + path + " has " +
                       std::to_string(components));
    }
    return std::async(launch(path), [&path] { return dmrtools::ReadImageOrDicomSeries<ReadType>(path); });
  };
  // The mask is read as float and taken as non-zero = inside here: read as unsigned char, ITK's cast made a soft mask's
  // 0.7 and a label 256 zero (outside) and a NaN undefined.
  using MaskReadType = itk::Image<float, D>;
  std::future<typename MaskReadType::Pointer> maskRead;
  if (!opt.fixedMask.empty())
  {
    maskRead = readOptional(typename MaskReadType::Pointer(), opt.fixedMask, "--fixed-mask");
  }
  std::future<typename FieldType::Pointer> truthRead;
  if (!opt.truthDisplacement.empty())
  {
    truthRead = readOptional(typename FieldType::Pointer(), opt.truthDisplacement, "--truth-displacement");
  }

  typename ImageType::Pointer fixed, moving;
  try
  {
    fixed = fixedRead.get();
    moving = movingRead.get();
  }
  catch (const itk::ExceptionObject & e)
  {
    throw UsageError(std::string("cannot read the input images: ") + e.GetDescription());
  }
  dmrtools::ThrowIfInterrupted();
  // NaN or infinite intensities, reported at the voxel of the file as read (before any window or resampling); a
  // header whose coordinates cannot tell the pixels apart (the registration and the resampling below work in them) or
  // whose spacing the registration's single-precision fields cannot hold
  for (const auto & named : { std::make_pair(std::string("fixed"), fixed.GetPointer()),
                              std::make_pair(std::string("moving"), moving.GetPointer()) })
  {
    const std::string geometry = itk::dmr::GeometryOutsidePrecision<D>(named.second, (named.first + " image").c_str());
    if (!geometry.empty())
    {
      throw UsageError(geometry + ": " + (named.first == "fixed" ? opt.fixed : opt.moving));
    }
    std::string index;
    double      value;
    if (dmrtools::FindNonFiniteVoxel(named.second, index, value))
    {
      throw UsageError("the " + named.first + " image has a non-finite intensity (" + std::to_string(value) +
                       ") at voxel " + index + ": replace NaN and infinite values first");
    }
  }
  // --initial-transform: W_0 as a displacement field on the fixed grid (a transform file is evaluated there)
  typename FieldType::Pointer initialField, initialInverseField;
  std::string                 initialKind;
  if (!opt.initialTransform.empty())
  {
    try
    {
      initialField = dmrtools::InitialFieldOnGrid<D>(opt.initialTransform, fixed.GetPointer(), initialKind);
      if (opt.inverse)
      {
        initialInverseField =
          dmrtools::InitialInverseFieldOnGrid<D>(opt.initialTransform, fixed.GetPointer(), initialField.GetPointer());
      }
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError("--initial-transform: " + std::string(e.GetDescription()));
    }
    catch (const UsageError & e)
    {
      throw UsageError("--initial-transform: " + std::string(e.what()));
    }
  }
  dmrtools::ThrowIfInterrupted();
  typename ImageType::Pointer movingInput = moving; // as read: warped.nii.gz samples it (original intensities)
  std::pair<double, double>   fixedRangeAsRead, movingRangeAsRead; // for the message when a window leaves nothing
  if (opt.window)
  {
    fixedRangeAsRead = itk::dmr::IntensityRange(fixed.GetPointer());
    movingRangeAsRead = itk::dmr::IntensityRange(moving.GetPointer());
    // CT: clamp to the window and scale to [0, 1] so that the SSD (and beta) are well scaled for HU; the moving
    // image is windowed in a copy so that the warped output keeps the input's intensities
    auto copy = ImageType::New();
    copy->CopyInformation(moving);
    copy->SetRegions(moving->GetLargestPossibleRegion());
    copy->Allocate();
    std::copy(moving->GetBufferPointer(),
              moving->GetBufferPointer() + moving->GetBufferedRegion().GetNumberOfPixels(),
              copy->GetBufferPointer());
    moving = copy;
    const float lo = static_cast<float>(opt.windowLow), hi = static_cast<float>(opt.windowHigh);
    const float scale = static_cast<float>(1.0 / (opt.windowHigh - opt.windowLow));
    for (ImageType * image : { fixed.GetPointer(), moving.GetPointer() })
    {
      float *      v = image->GetBufferPointer();
      const size_t count = image->GetBufferedRegion().GetNumberOfPixels();
      for (size_t p = 0; p < count; ++p)
      {
        v[p] = (std::min(std::max(v[p], lo), hi) - lo) * scale;
      }
      image->Modified();
    }
  }
  // With an initial transformation the moving image stays on its own grid (the registration samples it through
  // physical space at W_0(x), which may lie beyond the fixed image's box); without one, it is resampled onto the
  // fixed grid when it lies on another.
  const bool   movingResampled = !initialField && !dmrtools::SameGrid<D>(fixed.GetPointer(), moving.GetPointer());
  const double movingOverlap = initialField
                                 ? CoveredFraction(moving.GetPointer(), fixed.GetPointer(), initialField.GetPointer())
                                 : (movingResampled ? CoveredFraction(moving.GetPointer(), fixed.GetPointer()) : 1.0);
  if (movingOverlap == 0.0 && initialField)
  {
    throw UsageError("--initial-transform maps no voxel of the fixed image into the moving image: check it (its "
                     "direction: fixed to moving, in ITK's LPS frame) and the images' origins and directions");
  }
  if (movingOverlap == 0.0)
  {
    throw UsageError("the moving image does not overlap the fixed image in physical space: check their origins and "
                     "directions (e.g. one of them flipped, LPS against RAS)");
  }
  // the share of the fixed image the moving image covers, in words ("less than 1" or a whole percentage)
  const std::string share =
    movingOverlap < 0.01 ? std::string("less than 1") : std::to_string(std::lround(100.0 * movingOverlap));
  if (movingOverlap < 0.5)
  {
    if (initialField)
    {
      std::cout << "note: --initial-transform maps only " << share
                << " % of the fixed image into the moving image (beyond its border the moving image takes its "
                   "nearest border value): check the transform if that is not intended\n";
    }
    else
    {
      std::cout << "note: the moving image covers only " << share
                << " % of the fixed image in physical space (outside it, it counts as its lowest intensity): check "
                   "their origins and directions if that is not intended\n";
    }
  }
  if (movingResampled)
  {
    // a moving image on another grid is brought onto the fixed grid first (linear, outside = its minimum)
    moving =
      ResampleOnto(moving.GetPointer(), fixed.GetPointer(), false, itk::dmr::IntensityRange(moving.GetPointer()).first);
  }
  typename MaskType::Pointer mask;
  if (maskRead.valid())
  {
    typename MaskReadType::Pointer values;
    try
    {
      values = maskRead.get();
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError("cannot read --fixed-mask: " + std::string(e.GetDescription()));
    }
    std::string index;
    double      value;
    if (dmrtools::FindNonFiniteVoxel(values.GetPointer(), index, value))
    {
      throw UsageError("--fixed-mask has a non-finite value at voxel " + index + ": " + opt.fixedMask);
    }
    mask = MaskType::New();
    mask->CopyInformation(values);
    mask->SetRegions(values->GetLargestPossibleRegion());
    mask->Allocate();
    {
      const float *   v = values->GetBufferPointer();
      unsigned char * m = mask->GetBufferPointer();
      for (size_t p = 0, count = mask->GetBufferedRegion().GetNumberOfPixels(); p < count; ++p)
      {
        m[p] = v[p] != 0.0f ? 1 : 0;
      }
    }
    values = nullptr;
    // on the fixed grid as FEMRegistrationMethod checks it (its tolerances): taken as it is, otherwise resampled
    // (nearest neighbour), also when its header differs from the fixed image's only by a rounding
    if (!itk::dmr::GridMismatchAtDefaultTolerances<D>(fixed.GetPointer(), mask.GetPointer()).empty())
    {
      mask = ResampleOnto(mask.GetPointer(), fixed.GetPointer(), true, 0);
    }
    size_t                inside = 0;
    const unsigned char * m = mask->GetBufferPointer();
    for (size_t p = 0, count = mask->GetBufferedRegion().GetNumberOfPixels(); p < count; ++p)
    {
      inside += m[p] != 0 ? 1 : 0;
    }
    if (inside == 0)
    {
      throw UsageError("--fixed-mask has no voxel inside the fixed image: " + opt.fixedMask);
    }
  }
  // Default: the paper's node counts (100 in 2D, 3000 in 3D), at most one node per DefaultPixelsPerNode pixels on a
  // small image (a 16 x 12 x 10 volume gets 240 nodes instead of an error), at least 4.
  const auto pixels = static_cast<long>(fixed->GetLargestPossibleRegion().GetNumberOfPixels());
  const long nodes =
    opt.nodesGiven ? opt.nodes : std::max(4L, std::min<long>(D == 2 ? 100 : 3000, pixels / DefaultPixelsPerNode));
  if (nodes < 4 || nodes > pixels)
  {
    throw UsageError("--nodes must be between 4 and the number of pixels (" + std::to_string(pixels) + "), got " +
                     std::to_string(nodes));
  }
  for (const auto & named : { std::make_tuple(std::string("fixed"), fixed.GetPointer(), fixedRangeAsRead),
                              std::make_tuple(std::string("moving"), moving.GetPointer(), movingRangeAsRead) })
  {
    const auto range = itk::dmr::IntensityRange(std::get<1>(named));
    if (!(range.second > range.first))
    {
      std::ostringstream message;
      if (opt.window)
      {
        // the window, not the image, is what is constant: say so (it read "constant intensity 0.000000")
        message << "the " << std::get<0>(named) << " image is constant inside --intensity-window " << opt.windowLow
                << "," << opt.windowHigh << " (its intensities lie in [" << std::get<2>(named).first << ", "
                << std::get<2>(named).second << "]): nothing to register; choose a window that overlaps them";
      }
      else if (std::get<1>(named) == moving.GetPointer() && movingResampled)
      {
        // the image as read is not constant: the part of it that lies on the fixed grid is (it named the image)
        message << "the moving image has constant intensity " << range.first
                << " where it lies on the fixed image's grid (it covers " << share
                << " % of it): nothing to register; check the images' origins, spacings and directions";
      }
      else
      {
        message << "the " << std::get<0>(named) << " image has constant intensity " << range.first
                << ": nothing to register (the density would be zero)";
      }
      throw UsageError(message.str());
    }
  }

  dmrtools::LandmarkPairs<D> landmarks;
  if (!opt.fixedLandmarks.empty())
  {
    try
    {
      landmarks = dmrtools::ReadLandmarkPairs<D>(opt.fixedLandmarks,
                                                 opt.movingLandmarks,
                                                 fixed.GetPointer(),
                                                 movingInput.GetPointer(),
                                                 opt.landmarksInMM ? dmrtools::LandmarkUnits::PhysicalMM
                                                                   : dmrtools::LandmarkUnits::OneBasedIndex);
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError(std::string("landmarks: ") + e.GetDescription());
    }
    const auto size = fixed->GetLargestPossibleRegion().GetSize();
    for (size_t i = 0; i < landmarks.fixed.size(); ++i)
    {
      const auto ci = fixed->template TransformPhysicalPointToContinuousIndex<double, double>(landmarks.fixed[i]);
      for (unsigned int k = 0; k < D; ++k)
      {
        if (!(ci[k] >= -0.5 && ci[k] <= static_cast<double>(size[k]) - 0.5))
        {
          throw UsageError("landmarks: fixed landmark " + std::to_string(i + 1) + " of " + opt.fixedLandmarks +
                           " lies outside the fixed image");
        }
      }
    }
  }
  typename FieldType::Pointer truth;
  if (truthRead.valid())
  {
    try
    {
      truth = truthRead.get();
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError("cannot read --truth-displacement: " + std::string(e.GetDescription()));
    }
    if (!dmrtools::SameGrid<D>(fixed.GetPointer(), truth.GetPointer()))
    {
      throw UsageError("--truth-displacement must lie on the fixed image grid: " + opt.truthDisplacement);
    }
  }

  auto method = MethodType::New();
  method->SetFixedImage(fixed);
  method->SetMovingImage(moving);
  if (mask)
  {
    method->SetFixedMask(mask);
  }
  method->SetInitialDisplacementField(initialField);
  method->SetInitialInverseDisplacementField(initialInverseField);
  method->SetComputeInverse(opt.inverse);
  method->SetGPUOrderSolve(opt.gpuOrderSolve);
  method->SetNumberOfNodes(static_cast<itk::SizeValueType>(nodes));
  method->SetNumberOfIterations(static_cast<unsigned int>(opt.iterations));
  method->SetNumberOfLevels(static_cast<unsigned int>(opt.levels));
  method->SetLambda(opt.lambda);
  method->SetMu(opt.mu);
  method->SetEnergyRatio(opt.energyRatio);
  method->SetAlphaFactor(opt.alphaFactor);
  method->SetMaximumStepHalvings(static_cast<unsigned int>(opt.stepHalvings));
  method->SetDeviceSolverMinimumDegreesOfFreedom(static_cast<itk::SizeValueType>(opt.deviceSolveMinDofs));
  method->SetDirectSolverMaximumDegreesOfFreedom(static_cast<itk::SizeValueType>(opt.directSolveMaxDofs));
  method->SetForceGradient(opt.forceGradient == "mapped"
                             ? itk::DynamicMeshRegistrationEnums::ForceGradient::MappedMoving
                             : itk::DynamicMeshRegistrationEnums::ForceGradient::WarpedMoving);
  method->SetRegularGridSize(static_cast<unsigned int>(opt.regularSize));
  method->SetMaximumNumberOfSweeps(static_cast<itk::SizeValueType>(opt.cvtMaxSweeps));
  method->SetCVTEpsilon(opt.cvtEpsilon);
  method->SetSolverTolerance(opt.femTolerance);
  if (opt.threads > 0)
  {
    method->SetNumberOfWorkUnits(static_cast<itk::ThreadIdType>(opt.threads));
  }
  using Backend = itk::DynamicMeshRegistrationEnums::Backend;
  if (opt.backend == "cuda")
  {
    if (!itk::dmr::cuda::DeviceAvailable())
    {
      throw UsageError("--backend cuda: " + itk::dmr::cuda::UnavailableReason());
    }
    method->SetBackend(Backend::CUDA);
  }
  else if (opt.backend == "cpu")
  {
    method->SetBackend(Backend::CPU);
  }
  else
  {
    method->SetBackend(Backend::Auto);
    if (!itk::dmr::cuda::DeviceAvailable())
    {
      std::cout << "note: running on the CPU (" << itk::dmr::cuda::UnavailableReason() << ")\n";
    }
  }
  std::string meshMode = opt.mesh;
  if (opt.mesh == "dynamic")
  {
    method->SetMeshMode(itk::DynamicMeshRegistrationEnums::MeshMode::Dynamic);
  }
  else if (opt.mesh == "regular")
  {
    method->SetMeshMode(itk::DynamicMeshRegistrationEnums::MeshMode::Regular);
  }
  else
  {
    if (!itksys::SystemTools::FileExists(opt.mesh, true))
    {
      throw UsageError("--mesh: no such mesh file: " + opt.mesh);
    }
    typename MeshType::Pointer mesh;
    try
    {
      // ITK reads legacy VTK polydata; VTK reads unstructured grids (the tool's own .vtu meshes, tetrahedral meshes)
      const std::string extension =
        itksys::SystemTools::LowerCase(itksys::SystemTools::GetFilenameLastExtension(opt.mesh));
      if (extension == ".vtu" || (extension == ".vtk" && IsLegacyUnstructuredGrid(opt.mesh)))
      {
        mesh = ReadUnstructuredGrid<D, MeshType>(opt.mesh, extension == ".vtu");
      }
      else
      {
        mesh = dmrtools::ReadMeshFile<MeshType>(opt.mesh);
      }
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError("--mesh: cannot read " + opt.mesh + " as a mesh: " + e.GetDescription());
    }
    catch (const std::exception & e)
    {
      throw UsageError("--mesh: cannot read " + opt.mesh + " as a mesh: " + e.what());
    }
    method->SetMeshMode(itk::DynamicMeshRegistrationEnums::MeshMode::Static);
    method->SetStaticMesh(mesh);
    meshMode = "static";
  }

  // the registration's own checks of its inputs and settings (e.g. at least 4 pixels along every axis of the fixed
  // image) run before the outputs are staged: what they reject is bad input, a usage error like the others
  try
  {
    method->UpdateOutputInformation();
  }
  catch (const itk::ExceptionObject & e)
  {
    throw UsageError(e.GetDescription());
  }

  dmrtools::ThrowIfInterrupted();
  dmrtools::Staging                                 staging(opt.outputDir);
  std::vector<std::pair<unsigned int, std::string>> meshFiles;
  // The mesh files are written on a helper thread, one at a time and in iteration order, so that the registration does
  // not wait for them (a 3D mesh of 3000 nodes took 25-30 ms per file: its itk::Mesh, then VTK's XML writer). The
  // observer copies the iteration's mesh; the next write, or the end of the run, waits for the last one and rethrows
  // its error. On an error elsewhere the future's destructor waits for the write before the staging is cleaned up. The
  // helper reads a geometry-only copy of the fixed image (the pipeline may touch the image itself meanwhile).
  typename ImageType::Pointer meshGeometry = ImageType::New();
  meshGeometry->CopyInformation(method->GetFixedImage());
  std::future<void> meshWrite;
  auto              finishMeshWrite = [&] {
    if (meshWrite.valid())
    {
      meshWrite.get();
    }
  };
  auto saveMesh = [&](unsigned int iteration) {
    std::ostringstream name;
    name << "mesh_" << std::setw(4) << std::setfill('0') << iteration << ".vtu";
    finishMeshWrite();
    auto mesh = std::make_shared<const typename MethodType::SimplexMeshType>(method->GetCurrentSimplexMesh());
    meshWrite =
      std::async(std::launch::async,
                 [mesh, image = typename ImageType::ConstPointer(meshGeometry), path = staging.Path(name.str())] {
                   const auto itkMesh = itk::dmr::ToItkMesh<D, MeshType>(*mesh, image.GetPointer());
                   WriteMeshVTU<D>(itkMesh.GetPointer(), path);
                 });
    meshFiles.emplace_back(iteration, name.str());
  };
  auto observer = itk::CStyleCommand::New();
  struct Context
  {
    decltype(saveMesh) * save;
    MethodType *         method;
    long                 every;
    unsigned int         last;
  } context{ &saveMesh, method.GetPointer(), opt.saveMeshEvery, static_cast<unsigned int>(opt.iterations) };
  observer->SetClientData(&context);
  observer->SetCallback([](itk::Object *, const itk::EventObject &, void * data) {
    auto *             c = static_cast<Context *>(data);
    const unsigned int it = c->method->GetCurrentIteration();
    if (it == 1 || it == c->last || (c->every > 0 && it % c->every == 0))
    {
      (*c->save)(it);
    }
  });
  method->AddObserver(itk::IterationEvent(), observer);
  // Ctrl-C or SIGTERM: an abort set at the progress report that ends an iteration ends the run before the next one;
  // one set at a report from inside an iteration's long steps (the CVT) stops it there (a first iteration on a CT took
  // minutes to notice a SIGTERM)
  auto onProgress = itk::CStyleCommand::New();
  onProgress->SetClientData(method.GetPointer());
  onProgress->SetCallback([](itk::Object *, const itk::EventObject &, void * data) {
    if (dmrtools::InterruptSignal() != 0)
    {
      static_cast<MethodType *>(data)->AbortGenerateDataOn();
    }
  });
  method->AddObserver(itk::ProgressEvent(), onProgress);

  try
  {
    method->Update();
  }
  catch (const itk::ExceptionObject & e)
  {
    dmrtools::ThrowIfInterrupted(); // the registration stopped because of it (ProcessAborted)
    throw std::runtime_error(std::string("registration failed: ") + e.GetDescription());
  }
  dmrtools::ThrowIfInterrupted();
  const auto & history = method->GetHistory();
  size_t       deviceSolves = 0, directSolves = 0, cgProducts = 0;
  for (const auto & r : history)
  {
    deviceSolves += r.deviceSolve ? 1 : 0;
    directSolves += r.directSolve ? 1 : 0;
    cgProducts += r.solverIterations;
  }
  if (!history.empty() && (meshFiles.empty() || meshFiles.back().first != history.back().iteration))
  {
    saveMesh(history.back().iteration); // stopped early: keep the last mesh
  }
  finishMeshWrite();
  if (history.size() < static_cast<size_t>(opt.iterations))
  {
    // the run ended before its iterations (the summary line says how many): say why
    std::cout << "note: the registration stopped after " << history.size() << " of " << opt.iterations
              << " iterations: " << method->GetStopConditionDescription() << "\n";
  }
  else
  {
    // every iteration ran, but did anything move? (e.g. an --energy-ratio far from the data: every step rejected by
    // the safeguard, or steps of 1e-11 pixels; the summary line alone looked like a registration)
    double       moved = 0.0; // the accepted steps' largest updates added up: a bound on any voxel's displacement
    unsigned int rejected = 0;
    for (const auto & r : history)
    {
      moved += r.stepScale > 0.0 ? r.maxUpdate : 0.0;
      rejected += r.stepScale > 0.0 ? 0 : 1;
    }
    if (moved < 0.01)
    {
      std::cout << "note: the registration hardly moved anything: its steps add up to at most " << moved
                << " pixels, and " << rejected << " of " << history.size()
                << " steps were rejected because they would not have lowered the MSSD (by 1e-4 of its first-order "
                   "decrease); check --energy-ratio (default 0.02), --lambda and --mu, and that the moving image has "
                   "contrast where the images differ\n";
    }
  }

  // outputs
  auto field = method->GetDisplacementField();
  using ResampleType = itk::ResampleImageFilter<ImageType, ImageType, double>;
  auto resample = ResampleType::New();
  resample->SetInput(movingInput);
  resample->SetTransform(method->GetTransform());
  resample->SetOutputParametersFromImage(fixed);
  resample->SetInterpolator(itk::LinearInterpolateImageFunction<ImageType, double>::New());
  resample->Update();
  dmrtools::WriteImage(resample->GetOutput(), staging.Path("warped.nii.gz"));
  dmrtools::ThrowIfInterrupted();
  dmrtools::WriteImage(field, staging.Path("displacement.nii.gz"));
  dmrtools::ThrowIfInterrupted();
  // --inverse: |u(x) + v(x + u(x))| and |v(y) + u(y + v(y))| (mm), 0 for an exact inverse
  std::pair<dmrtools::ErrorStatistics, dmrtools::ErrorStatistics> inverseConsistency;
  if (opt.inverse)
  {
    const auto * inverse = method->GetInverseDisplacementField();
    dmrtools::WriteImage(inverse, staging.Path("inverse-displacement.nii.gz"));
    inverseConsistency = dmrtools::InverseConsistency(field, inverse, method->GetMultiThreader());
    dmrtools::ThrowIfInterrupted();
  }
  std::pair<double, double> jacobianRange;
  auto jacobian = itk::dmr::JacobianDeterminantImage(field, jacobianRange, method->GetMultiThreader());
  dmrtools::WriteImage(jacobian.GetPointer(), staging.Path("jacobian.nii.gz"));

  {
    std::ostringstream csv;
    csv << "iteration,mssd,ssd,elastic,total,nodes,cvt_sweeps,max_update_px,step_scale\n";
    csv << std::setprecision(10);
    for (const auto & r : history)
    {
      csv << r.iteration << ',' << r.mssd << ',' << r.ssd << ',' << r.elastic << ',' << r.total << ',' << r.nodes << ','
          << r.sweeps << ',' << r.maxUpdate << ',' << r.stepScale << '\n';
    }
    dmrtools::WriteTextFile(staging.Path("energy.csv"), csv.str());
  }
#ifdef DMR_WITH_VTK
  {
    std::ostringstream pvd;
    pvd << "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n  <Collection>\n";
    for (const auto & m : meshFiles)
    {
      pvd << "    <DataSet timestep=\"" << m.first << "\" file=\"" << m.second << "\"/>\n";
    }
    pvd << "  </Collection>\n</VTKFile>\n";
    dmrtools::WriteTextFile(staging.Path("mesh.pvd"), pvd.str());
  }
#endif
  auto statisticsJson = [](const dmrtools::ErrorStatistics & e) {
    std::ostringstream o;
    o << std::setprecision(6) << "{\"mean\": " << e.mean << ", \"std\": " << e.std << ", \"p95\": " << e.p95
      << ", \"max\": " << e.max << ", \"count\": " << e.count << "}";
    return o.str();
  };
  std::string evaluation;
  if (opt.inverse)
  {
    evaluation +=
      "  \"inverse_consistency_mm\": {\"forward_then_inverse\": " + statisticsJson(inverseConsistency.first) +
      ", \"inverse_then_forward\": " + statisticsJson(inverseConsistency.second) + "},\n";
  }
  if (!landmarks.fixed.empty())
  {
    try
    {
      evaluation += "  \"tre_initial_mm\": " +
                    statisticsJson(dmrtools::InitialTargetRegistrationError<D>(landmarks.fixed, landmarks.moving)) +
                    ",\n";
      if (initialField)
      {
        evaluation += "  \"tre_initial_transform_mm\": " +
                      statisticsJson(dmrtools::TargetRegistrationError(
                        landmarks.fixed, landmarks.moving, initialField.GetPointer())) +
                      ",\n";
      }
      evaluation +=
        "  \"tre_mm\": " + statisticsJson(dmrtools::TargetRegistrationError(landmarks.fixed, landmarks.moving, field)) +
        ",\n";
      const auto residualJson = [](const auto & r) {
        std::ostringstream o;
        o << std::setprecision(6) << "[";
        for (unsigned int k = 0; k < D; ++k)
        {
          o << (k ? ", " : "") << r[k];
        }
        return o.str() + "]";
      };
      evaluation +=
        "  \"tre_initial_mean_residual_mm\": " +
        residualJson(dmrtools::MeanLandmarkResidual<FieldType>(landmarks.fixed, landmarks.moving, nullptr)) +
        ",\n  \"tre_mean_residual_mm\": " +
        residualJson(dmrtools::MeanLandmarkResidual(landmarks.fixed, landmarks.moving, field)) + ",\n";
    }
    catch (const itk::ExceptionObject & e)
    {
      throw UsageError(std::string("landmarks: ") + e.GetDescription());
    }
  }
  if (truth)
  {
    evaluation += "  \"dense_error_initial_mm\": " +
                  statisticsJson(dmrtools::DisplacementMagnitudeInMask(truth.GetPointer(), mask.GetPointer())) + ",\n";
    if (initialField)
    {
      evaluation += "  \"dense_error_initial_transform_mm\": " +
                    statisticsJson(dmrtools::DisplacementErrorInMask(
                      initialField.GetPointer(), truth.GetPointer(), mask.GetPointer())) +
                    ",\n";
    }
    evaluation += "  \"dense_error_mm\": " +
                  statisticsJson(dmrtools::DisplacementErrorInMask(field, truth.GetPointer(), mask.GetPointer())) +
                  ",\n";
  }
  const auto &       t = method->GetTiming();
  const double       ssdInitial = history.empty() ? method->GetFinalSSD() : history.front().ssd;
  const double       mssdInitial = history.empty() ? method->GetFinalMSSD() : history.front().mssd;
  std::ostringstream json;
  json << std::setprecision(10) << "{\n"
       << "  \"tool\": \"itkDynamicMeshRegistration\",\n"
       << "  \"version\": \"" << DMR_VERSION_STRING << "\",\n"
       << "  \"fixed\": \"" << dmrtools::JsonEscape(opt.fixed) << "\",\n"
       << "  \"moving\": \"" << dmrtools::JsonEscape(opt.moving) << "\",\n"
       << "  \"dimension\": " << D << ",\n"
       << "  \"size\": [";
  for (unsigned int k = 0; k < D; ++k)
  {
    json << (k ? ", " : "") << fixed->GetLargestPossibleRegion().GetSize()[k];
  }
  json << "],\n"
       << "  \"nodes\": " << nodes << ",\n"
       << "  \"final_mesh_nodes\": " << (history.empty() ? 0 : history.back().nodes) << ",\n"
       << "  \"iterations\": " << history.size() << ",\n"
       << "  \"stop_condition\": \"" << dmrtools::JsonEscape(method->GetStopConditionDescription()) << "\",\n"
       << "  \"iterations_requested\": " << opt.iterations << ",\n"
       << "  \"levels\": " << opt.levels << ",\n"
       << "  \"mesh_mode\": \"" << meshMode << "\",\n"
       << "  \"backend\": \"" << method->GetBackendUsed() << "\",\n"
       << "  \"device\": "
       << (method->GetBackendUsed() == itk::DynamicMeshRegistrationEnums::Backend::CUDA
             ? "\"" + dmrtools::JsonEscape(itk::dmr::cuda::DeviceDescription()) + "\""
             : std::string("null"))
       << ",\n"
       << "  \"gpu_memory_mb\": " << static_cast<double>(method->GetDeviceBytes()) / (1024.0 * 1024.0) << ",\n"
       << "  \"gpu_memory_peak_mb\": " << static_cast<double>(method->GetDevicePeakBytes()) / (1024.0 * 1024.0) << ",\n"
       << "  \"gpu_device_used_at_peak_mb\": "
       << static_cast<double>(method->GetDeviceUsedAtPeakBytes()) / (1024.0 * 1024.0) << ",\n"
       << "  \"threads\": " << method->GetNumberOfWorkUnits() << ",\n"
       << "  \"lambda\": " << opt.lambda << ",\n"
       << "  \"mu\": " << opt.mu << ",\n"
       << "  \"energy_ratio\": " << opt.energyRatio << ",\n"
       << "  \"alpha_factor\": " << opt.alphaFactor << ",\n"
       << "  \"force_gradient\": \"" << opt.forceGradient << "\",\n"
       << "  \"step_halvings\": " << opt.stepHalvings << ",\n"
       << "  \"device_solve_min_dofs\": " << opt.deviceSolveMinDofs << ",\n"
       << "  \"fem_tolerance\": " << opt.femTolerance << ",\n"
       << "  \"direct_solve_max_dofs\": " << opt.directSolveMaxDofs << ",\n"
       << "  \"gpu_order_solve\": " << (opt.gpuOrderSolve ? "true" : "false") << ",\n"
       << "  \"contraction_on_host\": " << (method->GetContractedOnHost() ? "true" : "false") << ",\n"
       << "  \"device_solves\": " << deviceSolves << ",\n"
       << "  \"direct_solves\": " << directSolves << ",\n"
       << "  \"cg_products\": " << cgProducts << ",\n"
       << "  \"beta\": " << method->GetBeta() << ",\n"
       << "  \"cvt_max_sweeps\": " << opt.cvtMaxSweeps << ",\n"
       << "  \"cvt_epsilon\": " << opt.cvtEpsilon << ",\n"
       << "  \"timing_s\": {\"total\": " << t.total << ", \"initial_tessellation\": " << t.initialTessellation
       << ", \"tessellation_optimization\": " << t.tessellationOptimization
       << ", \"mesh_construction\": " << t.meshConstruction << ", \"barycentric\": " << t.barycentric
       << ", \"registration\": " << t.registration << ", \"fem_solve\": " << t.femSolve
       << ", \"registration_force\": " << t.force << ", \"registration_gather\": " << t.gather
       << ", \"registration_update\": " << t.update
       << ", \"device_warm_up\": " << (deviceWarmUp.valid() ? deviceWarmUp.get() : 0.0) << "},\n"
       << "  \"ssd_initial\": " << ssdInitial << ",\n"
       << "  \"ssd_final\": " << method->GetFinalSSD() << ",\n"
       << "  \"mssd_initial\": " << mssdInitial << ",\n"
       << "  \"mssd_final\": " << method->GetFinalMSSD() << ",\n"
       << "  \"jacobian_min\": " << jacobianRange.first << ",\n"
       << "  \"jacobian_max\": " << jacobianRange.second << ",\n"
       << evaluation << "  \"initial_transform\": "
       << (initialField ? "{\"file\": \"" + dmrtools::JsonEscape(opt.initialTransform) + "\", \"kind\": \"" +
                            dmrtools::JsonEscape(initialKind) + "\"}"
                        : std::string("null"))
       << ",\n"
       << "  \"moving_resampled\": " << (movingResampled ? "true" : "false") << ",\n"
       << "  \"moving_overlap\": " << movingOverlap << ",\n"
       << "  \"fixed_mask\": " << (opt.fixedMask.empty() ? "null" : "\"" + dmrtools::JsonEscape(opt.fixedMask) + "\"")
       << ",\n"
       << "  \"peak_rss_mb\": " << PeakRSSMiB() << ",\n"
       << "  \"wall_time_s\": " << std::chrono::duration<double>(std::chrono::steady_clock::now() - tRead).count()
       << "\n"
       << "}\n";
  const std::string reportName = "report.json";
  dmrtools::WriteTextFile(staging.Path(reportName), json.str());
  dmrtools::ThrowIfInterrupted(); // before a --report outside D is written
  if (!opt.report.empty())
  {
    // A report inside the output directory is staged and committed with the outputs. One elsewhere is written before
    // the outputs are committed, so a failure here leaves nothing behind in the output directory, and through a
    // temporary file, so that it never holds a part of the report (it was written in place: a full disk left it cut
    // or empty, over an earlier report).
    try
    {
      if (ReportInOutputDirectory(opt))
      {
        dmrtools::WriteTextFile(staging.Path(itksys::SystemTools::GetFilenameName(opt.report)), json.str());
      }
      else
      {
        dmrtools::ReplaceTextFile(opt.report, json.str());
      }
    }
    catch (const std::runtime_error & e)
    {
      throw std::runtime_error("could not write the report " + opt.report + ": " + e.what());
    }
  }
  // numbered meshes of an earlier run in D that this run did not write would pass for this run's (a run with
  // --save-mesh-every 10 and a shorter one after it left mesh_0010.vtu ... beside the new mesh.pvd); removed under the
  // directory's lock, so that a run committing into D at the same time keeps its own
  staging.Commit([&] {
    itksys::Directory listing;
    listing.Load(opt.outputDir);
    for (unsigned long i = 0; i < listing.GetNumberOfFiles(); ++i)
    {
      const std::string name = listing.GetFile(i);
      if (dmrtools::IsNumberedMeshName(name) &&
          std::none_of(meshFiles.begin(), meshFiles.end(), [&](const auto & m) { return m.second == name; }))
      {
        std::remove((opt.outputDir + "/" + name).c_str());
      }
    }
    if (!opt.inverse) // an earlier run's inverse is not this run's
    {
      std::remove((opt.outputDir + "/inverse-displacement.nii.gz").c_str());
    }
  });
  std::cout << "registered " << opt.moving << " -> " << opt.fixed << " in " << t.total << " s (" << history.size()
            << " iterations, " << meshMode << " mesh, SSD " << ssdInitial << " -> " << method->GetFinalSSD()
            << ", det J in [" << jacobianRange.first << ", " << jacobianRange.second << "])\n"
            << "outputs in " << opt.outputDir << ": warped.nii.gz displacement.nii.gz "
            << (opt.inverse ? "inverse-displacement.nii.gz " : "")
            << "jacobian.nii.gz energy.csv mesh.pvd report.json\n";
  return EXIT_SUCCESS;
}
} // namespace

int
main(int argc, char * argv[])
{
  return dmrtools::RunReportingErrors("itkDynamicMeshRegistration", [&]() {
    // Ctrl-C or a scheduler's SIGTERM: the run stops at its next step and leaves no staged outputs behind
    dmrtools::CatchInterruptSignals();
    const Options opt = ParseArguments(argc, argv);
    if (opt.threads > 0)
    {
      itk::MultiThreaderBase::SetGlobalDefaultNumberOfThreads(static_cast<itk::ThreadIdType>(opt.threads));
    }
    dmrtools::InitializeItkGlobals(); // before the inputs are read on threads
#ifdef DMR_WITH_VTK
    // VTK only reads and writes the small meshes here. Its default SMP back-end (TBB in Debian's VTK) starts a worker
    // per core on first use, and a worker that fails to start (a limit on threads or on virtual memory) ends the
    // process by std::terminate from inside TBB, with no message and no way to catch it (seen on the 16-core GPU
    // machine under ulimit -v 2000000).
    vtkSMPTools::SetBackend("Sequential");
#endif
    // scalar images; a colour image (RGB, RGBA) is read as its luminance (ITK's conversion), anything else with several
    // components per pixel (e.g. a displacement field) is not an image to register
    auto dimensionOfScalarImage = [](const std::string & what, const std::string & path) {
      unsigned int       components = 1;
      bool               colour = false;
      const unsigned int d = ImageDimensionOf(path, &components, &colour);
      if (components > 1 && !colour)
      {
        throw UsageError("the " + what + " image has " + std::to_string(components) +
                         " components per pixel and is not an RGB or RGBA colour image; the registration needs "
                         "scalar images (colour images are read as their luminance): " +
                         path);
      }
      if (colour)
      {
        std::cout << "note: the " << what << " image is a colour image; it is registered as its luminance\n";
      }
      return d;
    };
    const unsigned int dFixed = dimensionOfScalarImage("fixed", opt.fixed);
    const unsigned int dMoving = dimensionOfScalarImage("moving", opt.moving);
    if (dFixed != dMoving)
    {
      throw UsageError("the fixed image is " + std::to_string(dFixed) + "D but the moving image is " +
                       std::to_string(dMoving) + "D");
    }
    if (dFixed == 2)
    {
      return Run<2>(opt);
    }
    if (dFixed == 3)
    {
      return Run<3>(opt);
    }
    throw UsageError("only 2D and 3D images are supported, got " + std::to_string(dFixed) + "D");
  });
}
