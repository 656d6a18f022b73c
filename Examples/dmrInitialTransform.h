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
#ifndef dmrInitialTransform_h
#define dmrInitialTransform_h

// The tool's --initial-transform: a pre-alignment (e.g. affine, from ITK, ANTs or elastix's ITK export) or a
// displacement field, made into the displacement field u_0 on the fixed grid that FEMRegistrationMethod starts from
// (SetInitialDisplacementField). Physical space is ITK's LPS frame, as everywhere in ITK: a transform maps a fixed
// point to its moving point, u_0(x) = T(x) - x.
#include "itkCompositeTransform.h"
#include "itkImage.h"
#include "itkNearestNeighborExtrapolateImageFunction.h"
#include "itkResampleImageFilter.h"
#include "itkTransformFileReader.h"
#include "itkTransformToDisplacementFieldFilter.h"
#include "itkVector.h"
#include "dmrReadImage.h"
#include "itksys/SystemTools.hxx"
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace dmrtools
{
/** True for the file names ITK's transform readers take (.tfm and .txt: ITK's text format; .mat: MATLAB, as ANTs
 * writes affine transforms; .h5, .hdf5: HDF5, e.g. ANTs' composite transforms); every other name is read as a
 * displacement field image. */
inline bool
IsTransformFileName(const std::string & path)
{
  const std::string extension = itksys::SystemTools::LowerCase(itksys::SystemTools::GetFilenameLastExtension(path));
  return extension == ".tfm" || extension == ".txt" || extension == ".mat" || extension == ".h5" ||
         extension == ".hdf5";
}

/** ITK's text transform reader takes what it can parse of a "Parameters:" line and leaves the rest as it was: a line
 * that is short, or holds "NaN" or a typo, gave another transform without a word (and a short line leaves parameters
 * unset). Checks every "Parameters:" and "FixedParameters:" line of the file against the transforms read (in file
 * order): each value a finite number, as many as the transform has. */
inline void
CheckTextTransformParameters(const std::string &                                                 path,
                             const itk::TransformFileReaderTemplate<double>::TransformListType & list)
{
  // the file's blocks: a composite transform's block, then those of its parts (the reader moved them into it)
  std::vector<const itk::TransformBaseTemplate<double> *> blocks;
  for (const auto & transform : list)
  {
    blocks.push_back(transform.GetPointer());
    auto addParts = [&blocks](const auto * composite) {
      for (size_t i = 0; composite && i < composite->GetNumberOfTransforms(); ++i)
      {
        blocks.push_back(composite->GetNthTransformConstPointer(i));
      }
    };
    addParts(dynamic_cast<const itk::CompositeTransform<double, 2> *>(transform.GetPointer()));
    addParts(dynamic_cast<const itk::CompositeTransform<double, 3> *>(transform.GetPointer()));
  }
  std::ifstream in(path);
  std::string   line;
  long          index = -1; // the transform of the current block
  while (std::getline(in, line))
  {
    if (line.rfind("Transform:", 0) == 0)
    {
      ++index;
      continue;
    }
    const bool fixed = line.rfind("FixedParameters:", 0) == 0;
    if (!fixed && line.rfind("Parameters:", 0) != 0)
    {
      continue;
    }
    if (index < 0 || static_cast<size_t>(index) >= blocks.size())
    {
      itkGenericExceptionMacro(<< path << ": parameters outside a transform block");
    }
    std::istringstream tokens(line.substr(line.find(':') + 1));
    std::string        token;
    size_t             count = 0;
    while (tokens >> token)
    {
      char *       end = nullptr;
      const double value = std::strtod(token.c_str(), &end);
      if (*end != '\0' || !std::isfinite(value))
      {
        itkGenericExceptionMacro(<< path << ": \"" << token << "\" in the " << (fixed ? "fixed " : "")
                                 << "parameters of transform " << index << " is not a finite number");
      }
      ++count;
    }
    const auto * transform = blocks[static_cast<size_t>(index)];
    const size_t expected = fixed ? transform->GetFixedParameters().size() : transform->GetNumberOfParameters();
    if (count != expected)
    {
      itkGenericExceptionMacro(<< path << ": transform " << index << " (" << transform->GetTransformTypeAsString()
                               << ") has " << count << (fixed ? " fixed" : "") << " parameters, it takes " << expected);
    }
  }
}

/** The one transform of an ITK transform file as a Transform<double, D, D>. A file of a composite transform lists the
 * composite first and then its parts (TransformFileReader fills the composite from them): the composite is the
 * transform. Throws itk::ExceptionObject: unreadable file, no transform, several transforms that are not the parts of
 * a composite, a transform of another dimension. */
template <unsigned int D>
typename itk::Transform<double, D, D>::Pointer
ReadTransformFile(const std::string & path)
{
  auto reader = itk::TransformFileReaderTemplate<double>::New();
  reader->SetFileName(path);
  try
  {
    reader->Update();
  }
  catch (const itk::ExceptionObject & e)
  {
    // elastix writes its own parameter format ("(Transform ...)" lines) into .txt files, which ITK cannot read
    std::ifstream in(path);
    std::string   word;
    if (in >> word && word.front() == '(')
    {
      itkGenericExceptionMacro(<< path
                               << " is an elastix transform parameter file, which ITK cannot read: give the "
                                  "deformation field transformix writes (transformix -def all) instead");
    }
    itkGenericExceptionMacro(<< "cannot read a transform from " << path << ": " << e.GetDescription());
  }
  const auto &      list = *reader->GetTransformList();
  const std::string extension = itksys::SystemTools::LowerCase(itksys::SystemTools::GetFilenameLastExtension(path));
  if (extension == ".tfm" || extension == ".txt")
  {
    CheckTextTransformParameters(path, list);
  }
  if (list.empty())
  {
    itkGenericExceptionMacro(<< "no transform in " << path);
  }
  const std::string firstName = list.front()->GetNameOfClass();
  if (list.size() > 1 && firstName != "CompositeTransform")
  {
    itkGenericExceptionMacro(<< path << " holds " << list.size()
                             << " transforms; give one (or one composite transform of them)");
  }
  auto * transform = dynamic_cast<itk::Transform<double, D, D> *>(list.front().GetPointer());
  if (!transform)
  {
    itkGenericExceptionMacro(<< path << " holds a " << list.front()->GetInputSpaceDimension() << "D "
                             << list.front()->GetTransformTypeAsString() << ", the images are " << D << "D");
  }
  return transform;
}

/** u_0 on the grid of `reference` (physical frame, mm, float vectors) from `path`: an ITK transform file
 * (IsTransformFileName), u_0(x) = T(x) - x, or a displacement field image of D components (mm, moving point = fixed
 * point + u), resampled linearly onto the reference grid where it lies on another one (nearest value beyond its
 * border). `kind` says which. Throws itk::ExceptionObject on unreadable input, a wrong dimension or number of
 * components, and a displacement that is not finite. */
template <unsigned int D, typename TReference>
typename itk::Image<itk::Vector<float, D>, D>::Pointer
InitialFieldOnGrid(const std::string & path, const TReference * reference, std::string & kind)
{
  using FieldType = itk::Image<itk::Vector<float, D>, D>;
  typename FieldType::Pointer field;
  if (IsTransformFileName(path))
  {
    if (!itksys::SystemTools::FileExists(path, true))
    {
      itkGenericExceptionMacro(<< "no such file: " << path);
    }
    const auto transform = ReadTransformFile<D>(path);
    kind = "transform " + transform->GetTransformTypeAsString();
    auto toField = itk::TransformToDisplacementFieldFilter<FieldType, double>::New();
    toField->SetTransform(transform);
    toField->SetReferenceImage(reference);
    toField->UseReferenceImageOn();
    toField->Update();
    field = toField->GetOutput();
  }
  else
  {
    unsigned int components = 1;
    // ImageDimensionOf throws a UsageError (a std::runtime_error): the caller's message
    if (ImageDimensionOf(path, &components) != D || components != D)
    {
      itkGenericExceptionMacro(<< path << " is neither an ITK transform file (.tfm, .txt, .mat, .h5) nor a " << D
                               << "D displacement field of " << D << " components per voxel");
    }
    kind = "displacement field";
    field = ReadImageOrDicomSeries<FieldType>(path);
    const auto & region = field->GetLargestPossibleRegion();
    const auto & referenceRegion = reference->GetLargestPossibleRegion();
    const double tolerance = 1e-6 * reference->GetSpacing()[0];
    const bool   sameGrid =
      region == referenceRegion &&
      field->GetOrigin().GetVnlVector().is_equal(reference->GetOrigin().GetVnlVector(), tolerance) &&
      field->GetSpacing().GetVnlVector().is_equal(reference->GetSpacing().GetVnlVector(), tolerance) &&
      field->GetDirection().GetVnlMatrix().as_ref().is_equal(reference->GetDirection().GetVnlMatrix().as_ref(), 1e-6);
    if (!sameGrid)
    {
      auto resample = itk::ResampleImageFilter<FieldType, FieldType>::New();
      resample->SetInput(field);
      // the default interpolator, LinearInterpolateImageFunction, interpolates every component linearly
      resample->SetExtrapolator(itk::NearestNeighborExtrapolateImageFunction<FieldType, double>::New());
      resample->SetOutputParametersFromImage(reference);
      resample->Update();
      field = resample->GetOutput();
      kind = "displacement field (resampled onto the fixed grid)";
    }
  }
  const auto * u = field->GetBufferPointer();
  for (size_t p = 0, n = field->GetBufferedRegion().GetNumberOfPixels(); p < n; ++p)
  {
    for (unsigned int k = 0; k < D; ++k)
    {
      if (!std::isfinite(static_cast<double>(u[p][k])))
      {
        itkGenericExceptionMacro(<< "the initial displacement is not finite (" << u[p][k] << ") at voxel "
                                 << field->ComputeIndex(static_cast<itk::OffsetValueType>(p)) << " of the fixed grid");
      }
    }
  }
  return field;
}
} // namespace dmrtools

#endif
