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
// comparison (CGAL Delaunay refinement of the target's contour, about --fidelity-nodes nodes).
#include "dmrSyntheticShapes.h"
#include "dmrFidelityMesh.h"
#include "itkImageFileWriter.h"
#include "dmrMeshFileIO.h"
#include "itksys/SystemTools.hxx"
#include <iostream>

int
main(int argc, char * argv[])
{
  std::string shape, outputDir;
  long        fidelityNodes = 100;
  for (int i = 1; i < argc; ++i)
  {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h")
    {
      std::cout << "usage: dmrGenerateShapes --case epsilon|leaf --output-dir D [--fidelity-nodes N]\n"
                   "  writes D/fixed.nii.gz (target), D/moving.nii.gz (source) and, for epsilon, D/fidelity_mesh.vtk\n";
      return EXIT_SUCCESS;
    }
    if (i + 1 >= argc)
    {
      std::cerr << "dmrGenerateShapes: error: missing value for " << a << '\n';
      return 2;
    }
    const std::string v = argv[++i];
    if (a == "--case")
      shape = v;
    else if (a == "--output-dir")
      outputDir = v;
    else if (a == "--fidelity-nodes")
      fidelityNodes = std::atol(v.c_str());
    else
    {
      std::cerr << "dmrGenerateShapes: error: unknown option " << a << '\n';
      return 2;
    }
  }
  if ((shape != "epsilon" && shape != "leaf") || outputDir.empty() || fidelityNodes < 8)
  {
    std::cerr << "dmrGenerateShapes: error: need --case epsilon|leaf and --output-dir D (see --help)\n";
    return 2;
  }
  try
  {
    using namespace itk::dmr;
    itksys::SystemTools::MakeDirectory(outputDir);
    ShapeImageType::Pointer fixed, moving;
    if (shape == "epsilon")
    {
      fixed = RenderShape(CircleToEpsilon::Width, CircleToEpsilon::Height, CircleToEpsilon::Target);
      moving = RenderShape(CircleToEpsilon::Width, CircleToEpsilon::Height, CircleToEpsilon::Source);
    }
    else
    {
      fixed = RenderShape(CircleToLeaf::Width, CircleToLeaf::Height, CircleToLeaf::Target);
      moving = RenderShape(CircleToLeaf::Width, CircleToLeaf::Height, CircleToLeaf::Source);
    }
    auto writer = itk::ImageFileWriter<ShapeImageType>::New();
    writer->UseCompressionOn();
    writer->SetInput(fixed);
    writer->SetFileName(outputDir + "/fixed.nii.gz");
    writer->Update();
    writer->SetInput(moving);
    writer->SetFileName(outputDir + "/moving.nii.gz");
    writer->Update();
    std::cout << "wrote " << outputDir << "/fixed.nii.gz (target) and " << outputDir << "/moving.nii.gz (source)\n";
    if (shape == "epsilon")
    {
      const auto mesh = MakeFidelityMesh(fixed.GetPointer(), 0.5, static_cast<size_t>(fidelityNodes));
      using MeshType = itk::Mesh<double, 2>;
      auto itkMesh = ToItkMesh<2, MeshType>(mesh, fixed.GetPointer());
      dmrtools::WriteMeshFile(itkMesh.GetPointer(), outputDir + "/fidelity_mesh.vtk");
      std::cout << "wrote " << outputDir << "/fidelity_mesh.vtk (" << mesh.NumberOfNodes() << " nodes, "
                << mesh.elements.size() << " triangles)\n";
    }
  }
  catch (const std::exception & e)
  {
    std::cerr << "dmrGenerateShapes: error: " << e.what() << '\n';
    return 1;
  }
  return EXIT_SUCCESS;
}
