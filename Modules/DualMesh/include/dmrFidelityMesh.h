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
#ifndef dmrFidelityMesh_h
#define dmrFidelityMesh_h

#include "dmrDelaunay2D.h"
#include "dmrSimplexMesh.h"
#include "itkContourExtractor2DImageFilter.h"

namespace itk
{
namespace dmr
{
/** The static "high fidelity" mesh of paper 5.2 (Fig. 5b) for a 2D image: the iso-contours of the image at
 * contourValue (e.g. 0.5 for a binary shape) become constraints of a CGAL Delaunay refinement over the image box,
 * with about targetNodes nodes. Returned in the image's grid frame, fixed nodes on the border marked. */
template <typename TImage>
SimplexMesh<2>
MakeFidelityMesh(const TImage * image, double contourValue, size_t targetNodes)
{
  static_assert(TImage::ImageDimension == 2, "the fidelity mesh is 2D");
  auto contours = ContourExtractor2DImageFilter<TImage>::New();
  contours->SetInput(image);
  contours->SetContourValue(contourValue);
  contours->Update();
  const auto                       grid = Grid<2>::FromImage(image);
  const auto                       start = image->GetLargestPossibleRegion().GetIndex();
  std::vector<std::vector<double>> polygons;
  for (unsigned int c = 0; c < contours->GetNumberOfIndexedOutputs(); ++c)
  {
    std::vector<double> poly;
    for (const auto & v : *contours->GetOutput(c)->GetVertexList())
    {
      // contour vertices are continuous indices: to the grid frame (mm)
      poly.push_back((v[0] - start[0]) * grid.spacing[0]);
      poly.push_back((v[1] - start[1]) * grid.spacing[1]);
    }
    polygons.push_back(poly);
  }
  SimplexMesh<2>                      mesh;
  std::vector<std::array<int32_t, 3>> triangles;
  ContourFidelityMesh2D(polygons,
                        static_cast<double>(grid.size[0] - 1) * grid.spacing[0],
                        static_cast<double>(grid.size[1] - 1) * grid.spacing[1],
                        targetNodes,
                        mesh.nodes,
                        triangles);
  for (const auto & t : triangles)
  {
    mesh.elements.push_back({ t[0], t[1], t[2] });
  }
  mesh.OrientPositively();
  mesh.MarkBorderNodes(grid);
  return mesh;
}
} // namespace dmr
} // namespace itk

#endif
