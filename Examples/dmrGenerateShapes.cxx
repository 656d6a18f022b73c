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
// dmrGenerateShapes: writes the paper's 2D test pairs (section 5.2) as NIfTI: fixed.nii.gz (target) and
// moving.nii.gz (source); for circle-to-epsilon also fidelity_mesh.vtk, the static "high fidelity" mesh of the
// comparison (CGAL Delaunay refinement of the target's contour, about --fidelity-nodes nodes). Two more pairs, circle
// to a C and circle to a star (256 x 256), try the method on shapes beyond the paper's.
#include "dmrSyntheticShapes.h"
#include "dmrFidelityMesh.h"
#include "dmrMeshFileIO.h"
#include "dmrToolErrors.h"
#include "dmrToolOutput.h"
#include <cerrno>
#include <cstdlib>
#include <iostream>

int
main(int argc, char * argv[])
{
  return dmrtools::RunReportingErrors("dmrGenerateShapes", [&]() {
    dmrtools::CatchInterruptSignals(); // an interrupted run commits nothing (Staging::Commit)
    dmrtools::StartItkThreadPool();
    using dmrtools::UsageError;
    std::string shape, outputDir;
    long        fidelityNodes = 100;
    for (int i = 1; i < argc; ++i)
    {
      const std::string a = argv[i];
      if (a == "--help" || a == "-h")
      {
        std::cout << "usage: dmrGenerateShapes --case epsilon|leaf|c|star --output-dir D [--fidelity-nodes N]\n"
                     "  writes D/fixed.nii.gz (target), D/moving.nii.gz (source) and, for epsilon, "
                     "D/fidelity_mesh.vtk (about N nodes, 8 <= N <= 100000, default 100); files appear only when all "
                     "of them were written\n"
                     "  epsilon: the paper's circle to epsilon (512 x 512); leaf: circle to leaf (1024 x 256);\n"
                     "  c: a disk to a C, a ring cut open by a gap (256 x 256); star: a disk to a five-armed star "
                     "(256 x 256)\n";
        return EXIT_SUCCESS;
      }
      if (i + 1 >= argc)
      {
        throw UsageError("missing value for " + a);
      }
      const std::string v = argv[++i];
      if (a == "--case")
        shape = v;
      else if (a == "--output-dir")
        outputDir = v;
      else if (a == "--fidelity-nodes")
      {
        char * end = nullptr;
        errno = 0;
        fidelityNodes = std::strtol(v.c_str(), &end, 10);
        if (end == v.c_str() || *end != '\0' || errno == ERANGE || fidelityNodes < 8 || fidelityNodes > 100000)
        {
          throw UsageError("--fidelity-nodes needs an integer in [8, 100000], got '" + v + "'");
        }
      }
      else
      {
        throw UsageError("unknown option " + a);
      }
    }
    if ((shape != "epsilon" && shape != "leaf" && shape != "c" && shape != "star") || outputDir.empty())
    {
      throw UsageError("need --case epsilon|leaf|c|star and --output-dir D (see --help)");
    }
    using namespace itk::dmr;
    dmrtools::Staging       staging(outputDir); // a file named like the directory is a usage error
    ShapeImageType::Pointer fixed, moving;
    if (shape == "epsilon")
    {
      fixed = RenderShape(CircleToEpsilon::Width, CircleToEpsilon::Height, CircleToEpsilon::Target);
      moving = RenderShape(CircleToEpsilon::Width, CircleToEpsilon::Height, CircleToEpsilon::Source);
    }
    else if (shape == "leaf")
    {
      fixed = RenderShape(CircleToLeaf::Width, CircleToLeaf::Height, CircleToLeaf::Target);
      moving = RenderShape(CircleToLeaf::Width, CircleToLeaf::Height, CircleToLeaf::Source);
    }
    else if (shape == "c")
    {
      fixed = RenderShape(CircleToC::Width, CircleToC::Height, CircleToC::Target);
      moving = RenderShape(CircleToC::Width, CircleToC::Height, CircleToC::Source);
    }
    else
    {
      fixed = RenderShape(CircleToStar::Width, CircleToStar::Height, CircleToStar::Target);
      moving = RenderShape(CircleToStar::Width, CircleToStar::Height, CircleToStar::Source);
    }
    // checked writes (ITK's NIfTI writer only prints when it cannot open or fill a file), committed together
    dmrtools::WriteImage(fixed.GetPointer(), staging.Path("fixed.nii.gz"));
    dmrtools::WriteImage(moving.GetPointer(), staging.Path("moving.nii.gz"));
    size_t nodes = 0, triangles = 0;
    if (shape == "epsilon")
    {
      const auto mesh = MakeFidelityMesh(fixed.GetPointer(), 0.5, static_cast<size_t>(fidelityNodes));
      using MeshType = itk::Mesh<double, 2>;
      auto itkMesh = ToItkMesh<2, MeshType>(mesh, fixed.GetPointer());
      dmrtools::WriteMeshFile(itkMesh.GetPointer(), staging.Path("fidelity_mesh.vtk"));
      nodes = mesh.NumberOfNodes();
      triangles = mesh.elements.size();
    }
    staging.Commit();
    std::cout << "wrote " << outputDir << "/fixed.nii.gz (target) and " << outputDir << "/moving.nii.gz (source)\n";
    if (shape == "epsilon")
    {
      std::cout << "wrote " << outputDir << "/fidelity_mesh.vtk (" << nodes << " nodes, " << triangles
                << " triangles)\n";
    }
    return EXIT_SUCCESS;
  });
}
