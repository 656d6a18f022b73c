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
// A program built against an installed DynamicMeshRegistration (test/Install): the stage filters chained into an
// ITK pipeline, and the registration method, on a small 2D pair. Exit 0 only when the results have the properties the
// library promises: a mesh that tiles the image, a registration that lowers the SSD with det J > 0.
#include "itkDensityFieldFilter.h"
#include "itkDiscreteCVTFilter.h"
#include "itkDualMeshFilter.h"
#include "itkFEMRegistrationMethod.h"
#include "dmrFieldImage.h"
#include <cmath>
#include <cstdio>
#include <exception>

namespace
{
using ImageType = itk::Image<float, 2>;

/** A smooth ellipse (logistic edge) centred at (cx, cy) with radii (rx, ry) on a 64 x 56 grid of spacing 0.8 mm. */
ImageType::Pointer
Blob(double cx, double cy, double rx, double ry)
{
  auto image = ImageType::New();
  image->SetRegions(ImageType::SizeType{ { 64, 56 } });
  ImageType::SpacingType spacing;
  spacing.Fill(0.8);
  image->SetSpacing(spacing);
  image->Allocate();
  for (unsigned int y = 0; y < 56; ++y)
  {
    for (unsigned int x = 0; x < 64; ++x)
    {
      const double r = std::hypot((x - cx) / rx, (y - cy) / ry);
      image->SetPixel({ { x, y } }, static_cast<float>(1.0 / (1.0 + std::exp((r - 1.0) * 8.0))));
    }
  }
  return image;
}

int
Check(bool ok, const char * what)
{
  std::printf("%s: %s\n", ok ? "ok" : "FAILED", what);
  return ok ? 0 : 1;
}
} // namespace

int
main()
{
  try
  {
    const auto fixed = Blob(30, 28, 16, 12);
    const auto moving = Blob(34, 27, 12, 12);
    int        failures = 0;

    // the stages as a pipeline: density -> discrete CVT -> dual mesh
    using DensityFilterType = itk::DensityFieldFilter<ImageType>;
    using CVTFilterType = itk::DiscreteCVTFilter<DensityFilterType::DensityImageType>;
    using DualMeshFilterType = itk::DualMeshFilter<CVTFilterType::LabelImageType>;
    auto density = DensityFilterType::New();
    density->SetFixedImage(fixed);
    density->SetMovingImage(moving);
    auto cvt = CVTFilterType::New();
    cvt->SetInput(density->GetOutput());
    cvt->SetNumberOfCells(30);
    auto dual = DualMeshFilterType::New();
    dual->SetInput(cvt->GetOutput());
    dual->SetSites(cvt->GetSites());
    dual->Update();
    const auto & simplexMesh = dual->GetSimplexMesh();
    double       area = 0.0;
    for (const auto & t : simplexMesh.elements)
    {
      const double * a = &simplexMesh.nodes[2 * t[0]];
      const double * b = &simplexMesh.nodes[2 * t[1]];
      const double * c = &simplexMesh.nodes[2 * t[2]];
      area += 0.5 * ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]));
    }
    const double box = (63 * 0.8) * (55 * 0.8);
    std::printf("dual mesh: %zu nodes, %zu triangles, area %.6g of %.6g mm^2\n",
                simplexMesh.NumberOfNodes(),
                simplexMesh.elements.size(),
                area,
                box);
    failures +=
      Check(dual->GetOutput()->GetNumberOfCells() == simplexMesh.elements.size() && std::abs(area - box) <= 1e-9 * box,
            "the dual mesh tiles the image");

    // the registration method
    using MethodType = itk::FEMRegistrationMethod<ImageType, ImageType>;
    auto method = MethodType::New();
    method->SetFixedImage(fixed);
    method->SetMovingImage(moving);
    method->SetNumberOfNodes(30);
    method->SetNumberOfIterations(60);
    method->Update();
    std::pair<double, double> range;
    itk::dmr::JacobianDeterminantImage(method->GetDisplacementField(), range, nullptr);
    const double initial = method->GetHistory().front().ssd;
    std::printf("registration: SSD %.6g -> %.6g, det J in [%.4g, %.4g]\n",
                initial,
                method->GetFinalSSD(),
                range.first,
                range.second);
    failures += Check(method->GetFinalSSD() < 0.5 * initial, "the registration halves the SSD");
    failures += Check(range.first > 0.0, "det J > 0 everywhere");
    return failures == 0 ? 0 : 1;
  }
  catch (const std::exception & e)
  {
    std::printf("FAILED: %s\n", e.what());
    return 1;
  }
}
