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
#ifndef dmrMeshFileIO_h
#define dmrMeshFileIO_h

// Mesh files for the command-line tools. ITK 5.2's legacy-VTK mesh IO does not round-trip meshes with 2D points (the
// reader spins on 2-coordinate POINTS, and 3-coordinate points read into a 2D mesh corrupt memory), so meshes are
// always stored with 3D points (z = 0 in 2D) and converted on reading.
#include "itkMesh.h"
#include "itkMeshFileReader.h"
#include "itkMeshFileWriter.h"
#include "itkTriangleCell.h"
#include "itkTetrahedronCell.h"
#include <cmath>
#include <stdexcept>
#include <string>

namespace dmrtools
{
using FileMeshType = itk::Mesh<double, 3>;

/** Copies the triangle and tetrahedron cells of in into out (renumbered from 0); with pointsPerCell != 0 only cells
 * with that many points. */
template <typename TIn, typename TOut>
void
CopySimplexCells(const TIn * in, TOut * out, unsigned int pointsPerCell)
{
  using CellType = typename TOut::CellType;
  typename TOut::CellIdentifier id = 0;
  for (auto c = in->GetCells()->Begin(); c != in->GetCells()->End(); ++c)
  {
    const unsigned int n = c.Value()->GetNumberOfPoints();
    if ((n != 3 && n != 4) || (pointsPerCell != 0 && n != pointsPerCell))
    {
      continue;
    }
    typename CellType::CellAutoPointer cell;
    if (n == 3)
    {
      cell.TakeOwnership(new itk::TriangleCell<CellType>);
    }
    else
    {
      cell.TakeOwnership(new itk::TetrahedronCell<CellType>);
    }
    unsigned int k = 0;
    for (auto p = c.Value()->PointIdsBegin(); p != c.Value()->PointIdsEnd(); ++p, ++k)
    {
      cell->SetPointId(k, *p);
    }
    out->SetCell(id++, cell);
  }
}

/** Writes a 2D or 3D mesh of simplices (points in physical space) as legacy VTK with 3D points. */
template <typename TMesh>
void
WriteMeshFile(const TMesh * mesh, const std::string & path)
{
  constexpr unsigned int D = TMesh::PointDimension;
  auto                   out = FileMeshType::New();
  for (auto it = mesh->GetPoints()->Begin(); it != mesh->GetPoints()->End(); ++it)
  {
    FileMeshType::PointType p;
    p.Fill(0.0);
    for (unsigned int k = 0; k < D; ++k)
    {
      p[k] = it.Value()[k];
    }
    out->SetPoint(it.Index(), p);
  }
  CopySimplexCells(mesh, out.GetPointer(), 0);
  auto writer = itk::MeshFileWriter<FileMeshType>::New();
  writer->SetInput(out);
  writer->SetFileName(path);
  writer->Update();
}

/** Reads a mesh file (3D points) into a mesh with D-dimensional points; in 2D every z must be 0. */
template <typename TMesh>
typename TMesh::Pointer
ReadMeshFile(const std::string & path)
{
  constexpr unsigned int D = TMesh::PointDimension;
  auto                   reader = itk::MeshFileReader<FileMeshType>::New();
  reader->SetFileName(path);
  reader->Update();
  const FileMeshType * in = reader->GetOutput();
  auto                 out = TMesh::New();
  for (auto it = in->GetPoints()->Begin(); it != in->GetPoints()->End(); ++it)
  {
    typename TMesh::PointType p;
    for (unsigned int k = 0; k < D; ++k)
    {
      p[k] = it.Value()[k];
    }
    if (D == 2 && std::abs(it.Value()[2]) > 1e-9)
    {
      throw std::runtime_error("mesh point " + std::to_string(it.Index()) + " has z != 0: not a 2D mesh");
    }
    out->SetPoint(it.Index(), p);
  }
  CopySimplexCells(in, out.GetPointer(), D + 1);
  return out;
}
} // namespace dmrtools

#endif
