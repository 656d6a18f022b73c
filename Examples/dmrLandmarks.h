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
#ifndef dmrLandmarks_h
#define dmrLandmarks_h

// Landmark files and target registration error (TRE) for the command-line tools.
//
// File format (DIR-Lab): one landmark per line, D numbers "x y z" separated by blanks or tabs. Blank lines and lines
// starting with '#' are skipped. By default the numbers are 1-based voxel indices on the image grid (DIR-Lab's
// convention), so ITK index = value - 1; they may instead be ITK physical coordinates in mm (LandmarkUnits).
//
// Direction convention (ITK's): the displacement field u lives on the fixed image's grid, in mm, physical frame, and
// maps a fixed point to its moving counterpart, moving point = p_f + u(p_f). TRE_i = |p_f,i + u(p_f,i) - p_m,i|, with
// u linearly interpolated at p_f,i. Before registration (u = 0) this is the plain distance |p_f,i - p_m,i|.
#include "dmrErrorStatistics.h"
#include "itkImageBase.h"
#include "itkPoint.h"
#include "itkVectorLinearInterpolateImageFunction.h"
#include "itkMacro.h"
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace dmrtools
{
/** How the numbers in a landmark file are to be read. */
enum class LandmarkUnits
{
  OneBasedIndex,  ///< voxel indices counted from 1 (DIR-Lab): ITK index = value - 1
  ZeroBasedIndex, ///< ITK voxel indices (counted from 0)
  PhysicalMM      ///< ITK physical coordinates (LPS) in mm
};

template <unsigned int VDimension>
using LandmarkPointList = std::vector<itk::Point<double, VDimension>>;

/** Raw values of a landmark stream, one array of D numbers per landmark. sourceName names the stream in error
 * messages. Throws itk::ExceptionObject ("<source>:<line>: ...") for a line that does not hold exactly D finite
 * numbers, and when the stream holds no landmark at all. */
template <unsigned int VDimension>
std::vector<std::array<double, VDimension>>
ParseLandmarks(std::istream & in, const std::string & sourceName)
{
  std::vector<std::array<double, VDimension>> values;
  std::string                                 line;
  size_t                                      lineNumber = 0;
  while (std::getline(in, line))
  {
    ++lineNumber;
    if (lineNumber == 1 && line.compare(0, 3, "\xEF\xBB\xBF") == 0) // a UTF-8 byte order mark (Windows editors)
    {
      line.erase(0, 3);
    }
    if (!line.empty() && line.back() == '\r') // files written on Windows
    {
      line.pop_back();
    }
    const size_t first = line.find_first_not_of(" \t");
    if (first == std::string::npos || line[first] == '#')
    {
      continue;
    }
    std::istringstream       tokens(line);
    std::vector<std::string> words;
    for (std::string w; tokens >> w;)
    {
      words.push_back(w);
    }
    if (words.size() != VDimension)
    {
      itkGenericExceptionMacro(<< sourceName << ":" << lineNumber << ": expected " << VDimension
                               << " numbers separated by blanks, found " << words.size() << " fields in \"" << line
                               << "\"");
    }
    std::array<double, VDimension> v;
    for (unsigned int k = 0; k < VDimension; ++k)
    {
      const char * begin = words[k].c_str();
      char *       end = nullptr;
      errno = 0;
      v[k] = std::strtod(begin, &end);
      if (end == begin || *end != '\0' || errno == ERANGE || !std::isfinite(v[k]))
      {
        itkGenericExceptionMacro(<< sourceName << ":" << lineNumber << ": \"" << words[k]
                                 << "\" is not a finite number");
      }
    }
    values.push_back(v);
  }
  if (in.bad())
  {
    itkGenericExceptionMacro(<< sourceName << ": read error");
  }
  if (values.empty())
  {
    itkGenericExceptionMacro(<< sourceName << ": no landmarks (the file is empty or holds only blank/comment lines)");
  }
  return values;
}

/** Raw values of a landmark file; throws when it cannot be opened (see ParseLandmarks for the format errors). */
template <unsigned int VDimension>
std::vector<std::array<double, VDimension>>
ReadLandmarkValues(const std::string & path)
{
  std::ifstream in(path);
  if (!in)
  {
    itkGenericExceptionMacro(<< "cannot open landmark file " << path);
  }
  return ParseLandmarks<VDimension>(in, path);
}

/** Physical points (mm, ITK/LPS frame) of raw landmark values, through the geometry (origin, spacing, direction) of
 * image. With an index unit, landmarks outside the image's largest possible region (by more than half a voxel) are
 * an error, because they mean that the file does not belong to this grid. */
template <unsigned int VDimension>
LandmarkPointList<VDimension>
LandmarksToPhysical(const std::vector<std::array<double, VDimension>> & values,
                    const itk::ImageBase<VDimension> *                  image,
                    LandmarkUnits                                       units)
{
  LandmarkPointList<VDimension> points;
  points.reserve(values.size());
  const auto region = image->GetLargestPossibleRegion();
  for (size_t i = 0; i < values.size(); ++i)
  {
    itk::Point<double, VDimension> p;
    if (units == LandmarkUnits::PhysicalMM)
    {
      for (unsigned int k = 0; k < VDimension; ++k)
      {
        p[k] = values[i][k];
      }
    }
    else
    {
      itk::ContinuousIndex<double, VDimension> c;
      for (unsigned int k = 0; k < VDimension; ++k)
      {
        c[k] = values[i][k] - (units == LandmarkUnits::OneBasedIndex ? 1.0 : 0.0);
        const double lo = static_cast<double>(region.GetIndex(k)) - 0.5;
        const double hi = lo + static_cast<double>(region.GetSize(k));
        if (c[k] < lo || c[k] > hi)
        {
          itkGenericExceptionMacro(<< "landmark " << i + 1 << " lies outside the image grid: index "
                                   << (units == LandmarkUnits::OneBasedIndex ? "(1-based) " : "(0-based) ")
                                   << values[i][k] << " on axis " << k << ", image size " << region.GetSize());
        }
      }
      image->TransformContinuousIndexToPhysicalPoint(c, p);
    }
    points.push_back(p);
  }
  return points;
}

/** ReadLandmarkValues + LandmarksToPhysical. */
template <unsigned int VDimension>
LandmarkPointList<VDimension>
ReadLandmarks(const std::string &                path,
              const itk::ImageBase<VDimension> * image,
              LandmarkUnits                      units = LandmarkUnits::OneBasedIndex)
{
  return LandmarksToPhysical<VDimension>(ReadLandmarkValues<VDimension>(path), image, units);
}

/** Corresponding landmarks: fixed[i] matches moving[i]. */
template <unsigned int VDimension>
struct LandmarkPairs
{
  LandmarkPointList<VDimension> fixed;
  LandmarkPointList<VDimension> moving;
};

/** Throws unless both lists are non-empty and of equal length. */
template <unsigned int VDimension>
void
RequireCorrespondence(const LandmarkPointList<VDimension> & fixed,
                      const LandmarkPointList<VDimension> & moving,
                      const std::string &                   what = "landmarks")
{
  if (fixed.empty() || moving.empty())
  {
    itkGenericExceptionMacro(<< what << ": no landmarks");
  }
  if (fixed.size() != moving.size())
  {
    itkGenericExceptionMacro(<< what << ": the fixed set has " << fixed.size() << " landmarks and the moving set "
                             << moving.size() << "; line i of one file must match line i of the other");
  }
}

/** Reads a fixed and a moving landmark file (each converted through its own image's geometry) and checks that they
 * correspond (same count). */
template <unsigned int VDimension>
LandmarkPairs<VDimension>
ReadLandmarkPairs(const std::string &                fixedPath,
                  const std::string &                movingPath,
                  const itk::ImageBase<VDimension> * fixedImage,
                  const itk::ImageBase<VDimension> * movingImage,
                  LandmarkUnits                      units = LandmarkUnits::OneBasedIndex)
{
  LandmarkPairs<VDimension> pairs;
  pairs.fixed = ReadLandmarks<VDimension>(fixedPath, fixedImage, units);
  pairs.moving = ReadLandmarks<VDimension>(movingPath, movingImage, units);
  RequireCorrespondence<VDimension>(pairs.fixed, pairs.moving, fixedPath + " / " + movingPath);
  return pairs;
}

/** p + u(p) for every point: u (displacement image, any itk::Vector pixel, mm) interpolated linearly at p.
 * Throws when a point lies outside the field's grid (more than half a voxel beyond the outer voxel centres). */
template <typename TField>
LandmarkPointList<TField::ImageDimension>
MapThroughField(const LandmarkPointList<TField::ImageDimension> & points, const TField * field)
{
  constexpr unsigned int D = TField::ImageDimension;
  if (field == nullptr)
  {
    itkGenericExceptionMacro("MapThroughField: missing displacement field");
  }
  using InterpolatorType = itk::VectorLinearInterpolateImageFunction<TField, double>;
  auto interpolator = InterpolatorType::New();
  interpolator->SetInputImage(field);
  LandmarkPointList<D> mapped;
  mapped.reserve(points.size());
  for (size_t i = 0; i < points.size(); ++i)
  {
    if (!interpolator->IsInsideBuffer(points[i]))
    {
      itkGenericExceptionMacro(<< "landmark " << i + 1 << " at " << points[i]
                               << " mm lies outside the displacement field's grid");
    }
    const auto            u = interpolator->Evaluate(points[i]);
    itk::Point<double, D> q = points[i];
    for (unsigned int k = 0; k < D; ++k)
    {
      q[k] += static_cast<double>(u[k]);
    }
    mapped.push_back(q);
  }
  return mapped;
}

/** |fixed[i] + u(fixed[i]) - moving[i]| in mm, per landmark. */
template <typename TField>
std::vector<double>
LandmarkErrors(const LandmarkPointList<TField::ImageDimension> & fixed,
               const LandmarkPointList<TField::ImageDimension> & moving,
               const TField *                                    field)
{
  RequireCorrespondence<TField::ImageDimension>(fixed, moving);
  const auto          mapped = MapThroughField(fixed, field);
  std::vector<double> errors(fixed.size());
  for (size_t i = 0; i < fixed.size(); ++i)
  {
    errors[i] = mapped[i].EuclideanDistanceTo(moving[i]);
  }
  return errors;
}

/** |fixed[i] - moving[i]| in mm, per landmark: the errors of the identity (u = 0). */
template <unsigned int VDimension>
std::vector<double>
InitialLandmarkErrors(const LandmarkPointList<VDimension> & fixed, const LandmarkPointList<VDimension> & moving)
{
  RequireCorrespondence<VDimension>(fixed, moving);
  std::vector<double> errors(fixed.size());
  for (size_t i = 0; i < fixed.size(); ++i)
  {
    errors[i] = fixed[i].EuclideanDistanceTo(moving[i]);
  }
  return errors;
}

/** Mean of fixed[i] + u(fixed[i]) - moving[i] in mm along the physical axes (field == nullptr: u = 0): an offset
 * shared by the mapped landmarks, which the TRE's distances do not show (e.g. images that moved apart from their
 * landmarks). The mean TRE is at least its length. */
template <typename TField>
itk::Vector<double, TField::ImageDimension>
MeanLandmarkResidual(const LandmarkPointList<TField::ImageDimension> & fixed,
                     const LandmarkPointList<TField::ImageDimension> & moving,
                     const TField *                                    field)
{
  constexpr unsigned int D = TField::ImageDimension;
  RequireCorrespondence<D>(fixed, moving);
  const LandmarkPointList<D> mapped = field ? MapThroughField(fixed, field) : fixed;
  itk::Vector<double, D>     sum;
  sum.Fill(0.0);
  for (size_t i = 0; i < mapped.size(); ++i)
  {
    sum += mapped[i] - moving[i];
  }
  return mapped.empty() ? sum : sum / static_cast<double>(mapped.size());
}

/** TRE summary {mean, std, p95, max} of a displacement field on the fixed grid. */
template <typename TField>
ErrorStatistics
TargetRegistrationError(const LandmarkPointList<TField::ImageDimension> & fixed,
                        const LandmarkPointList<TField::ImageDimension> & moving,
                        const TField *                                    field)
{
  return SummarizeErrors(LandmarkErrors(fixed, moving, field));
}

/** TRE summary before registration (u = 0). */
template <unsigned int VDimension>
ErrorStatistics
InitialTargetRegistrationError(const LandmarkPointList<VDimension> & fixed,
                               const LandmarkPointList<VDimension> & moving)
{
  return SummarizeErrors(InitialLandmarkErrors<VDimension>(fixed, moving));
}
} // namespace dmrtools

#endif
