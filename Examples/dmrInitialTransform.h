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
#include "itkMultiThreaderBase.h"
#include "itkNearestNeighborExtrapolateImageFunction.h"
#include "itkResampleImageFilter.h"
#include "itkTransformFactoryBase.h"
#include "itkTransformFileReader.h"
#include "itkTransformToDisplacementFieldFilter.h"
#include "itkVector.h"
#include "dmrFieldImage.h"
#include "dmrGrid.h"
#include "dmrImageMetrics.h"
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
/** The last extension of a file name, lower case (".tfm"). */
inline std::string
LowerCaseExtension(const std::string & path)
{
  return itksys::SystemTools::LowerCase(itksys::SystemTools::GetFilenameLastExtension(path));
}

/** True for the file names ITK's transform readers take (.tfm and .txt: ITK's text format; .mat: MATLAB, as ANTs
 * writes affine transforms; .h5, .hdf5: HDF5, e.g. ANTs' composite transforms); every other name is read as a
 * displacement field image. */
inline bool
IsTransformFileName(const std::string & path)
{
  const std::string extension = LowerCaseExtension(path);
  return extension == ".tfm" || extension == ".txt" || extension == ".mat" || extension == ".h5" ||
         extension == ".hdf5";
}

/** The values of a "Parameters:" or "FixedParameters:" line; throws when one is not a finite number. */
inline std::vector<double>
TransformFileValues(const std::string & path, const std::string & line, long index, bool fixed)
{
  std::istringstream  tokens(line.substr(line.find(':') + 1));
  std::string         token;
  std::vector<double> values;
  while (tokens >> token)
  {
    char *       end = nullptr;
    const double value = std::strtod(token.c_str(), &end);
    if (*end != '\0' || !std::isfinite(value))
    {
      itkGenericExceptionMacro(<< path << ": \"" << token << "\" in the " << (fixed ? "fixed " : "")
                               << "parameters of transform " << index << " is not a finite number");
    }
    values.push_back(value);
  }
  return values;
}

/** ITK 5.2's text transform reader takes what it can parse of a "Parameters:" line and hands that array to the
 * transform, which reads as many values as it has parameters: a short line, or one cut short by "NaN" or a typo, read
 * past the end of the array (AddressSanitizer: heap-buffer-overflow in TranslationTransform::SetParameters) and gave
 * another transform without a word. So the file is checked before ITK reads it: every transform block names a known
 * transform and (except a composite's, which has none) has a "Parameters:" and a "FixedParameters:" line of finite
 * numbers, as many as that transform takes (the fixed ones first: they set the size of, e.g., a B-spline's grid). */
inline void
CheckTextTransformFile(const std::string & path)
{
  itk::TransformFactoryBase::RegisterDefaultTransforms();
  std::ifstream in(path);
  if (!in)
  {
    itkGenericExceptionMacro(<< "cannot open " << path);
  }
  struct Block
  {
    std::string name, parameters, fixedParameters;
    bool        hasParameters{ false }, hasFixedParameters{ false };
  };
  std::vector<Block> blocks;
  std::string        line;
  while (std::getline(in, line))
  {
    if (!line.empty() && line.back() == '\r')
    {
      line.pop_back();
    }
    if (line.rfind("Transform:", 0) == 0)
    {
      const auto first = line.find_first_not_of(" \t", 10);
      const auto last = line.find_last_not_of(" \t");
      blocks.emplace_back();
      blocks.back().name = first == std::string::npos ? std::string() : line.substr(first, last - first + 1);
    }
    else if (line.rfind("Parameters:", 0) == 0 || line.rfind("FixedParameters:", 0) == 0)
    {
      if (blocks.empty())
      {
        itkGenericExceptionMacro(<< path << ": parameters before the first \"Transform:\" line");
      }
      const bool fixed = line[0] == 'F';
      (fixed ? blocks.back().fixedParameters : blocks.back().parameters) = line;
      (fixed ? blocks.back().hasFixedParameters : blocks.back().hasParameters) = true;
    }
  }
  for (size_t i = 0; i < blocks.size(); ++i)
  {
    const Block & block = blocks[i];
    const long    index = static_cast<long>(i);
    std::string   name = block.name; // the reader reads a float transform as its double twin
    for (auto at = name.find("_float_"); at != std::string::npos; at = name.find("_float_"))
    {
      name.replace(at, 7, "_double_");
    }
    itk::LightObject::Pointer object = itk::ObjectFactoryBase::CreateInstance(name.c_str());
    auto *                    transform = dynamic_cast<itk::TransformBaseTemplate<double> *>(object.GetPointer());
    if (!transform)
    {
      itkGenericExceptionMacro(<< path << ": transform " << index << " is a \"" << block.name
                               << "\", which this ITK does not know");
    }
    if (name.rfind("CompositeTransform", 0) == 0)
    {
      continue; // its parts follow as blocks of their own
    }
    if (!block.hasParameters || !block.hasFixedParameters)
    {
      itkGenericExceptionMacro(<< path << ": transform " << index << " (" << block.name << ") has no "
                               << (block.hasParameters ? "\"FixedParameters:\"" : "\"Parameters:\"") << " line");
    }
    const auto fixed = TransformFileValues(path, block.fixedParameters, index, true);
    if (fixed.size() != transform->GetFixedParameters().size())
    {
      itkGenericExceptionMacro(<< path << ": transform " << index << " (" << block.name << ") has " << fixed.size()
                               << " fixed parameters, it takes " << transform->GetFixedParameters().size());
    }
    itk::TransformBaseTemplate<double>::FixedParametersType fixedParameters(fixed.size());
    for (size_t k = 0; k < fixed.size(); ++k)
    {
      fixedParameters[k] = fixed[k];
    }
    transform->SetFixedParameters(fixedParameters);
    const auto parameters = TransformFileValues(path, block.parameters, index, false);
    if (parameters.size() != transform->GetNumberOfParameters())
    {
      itkGenericExceptionMacro(<< path << ": transform " << index << " (" << block.name << ") has " << parameters.size()
                               << " parameters, it takes " << transform->GetNumberOfParameters());
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
  const std::string extension = LowerCaseExtension(path);
  if (extension == ".tfm" || extension == ".txt")
  {
    std::ifstream in(path);
    std::string   word;
    // elastix writes its own parameter format ("(Transform ...)" lines) into .txt files, which ITK cannot read
    if (in >> word && word.front() == '(')
    {
      itkGenericExceptionMacro(<< path
                               << " is an elastix transform parameter file, which ITK cannot read: give the "
                                  "deformation field transformix writes (transformix -def all) instead");
    }
    CheckTextTransformFile(path);
  }
  auto reader = itk::TransformFileReaderTemplate<double>::New();
  reader->SetFileName(path);
  try
  {
    reader->Update();
  }
  catch (const itk::ExceptionObject & e)
  {
    itkGenericExceptionMacro(<< "cannot read a transform from " << path << ": " << e.GetDescription());
  }
  const auto & list = *reader->GetTransformList();
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

/** T(x) - x at the pixels of `reference` (physical frame, mm, float vectors). */
template <unsigned int D, typename TReference>
typename itk::Image<itk::Vector<float, D>, D>::Pointer
TransformFieldOnGrid(const itk::Transform<double, D, D> * transform, const TReference * reference)
{
  using FieldType = itk::Image<itk::Vector<float, D>, D>;
  auto toField = itk::TransformToDisplacementFieldFilter<FieldType, double>::New();
  toField->SetTransform(transform);
  toField->SetReferenceImage(reference);
  toField->UseReferenceImageOn();
  toField->Update();
  return toField->GetOutput();
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
    field = TransformFieldOnGrid<D>(transform, reference);
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
    // on the fixed grid as FEMRegistrationMethod checks it (its tolerances): taken as it is, otherwise resampled
    if (!itk::dmr::GridMismatchAtDefaultTolerances<D>(reference, field.GetPointer()).empty())
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
  const auto p = itk::dmr::FirstNonFinitePixel(field.GetPointer());
  if (p >= 0)
  {
    itkGenericExceptionMacro(<< "the initial displacement is not finite (" << field->GetBufferPointer()[p]
                             << ") at voxel " << field->ComputeIndex(static_cast<itk::OffsetValueType>(p))
                             << " of the fixed grid");
  }
  return field;
}
/** The inverse of the initial transformation on the grid of `reference` (physical frame, mm, float vectors): what
 * FEMRegistrationMethod's ComputeInverse starts from. For a transform file, v_0(y) = T^-1(y) - y; it throws
 * itk::ExceptionObject for a transform without an inverse (e.g. a B-spline), with a message that says so. For a
 * displacement field image, `forward` (the field as InitialFieldOnGrid put it on the reference grid) is inverted by
 * fixed-point iteration (dmr::InverseDisplacementField), which throws for a folded field. */
template <unsigned int D, typename TReference>
typename itk::Image<itk::Vector<float, D>, D>::Pointer
InitialInverseFieldOnGrid(const std::string &                          path,
                          const TReference *                           reference,
                          const itk::Image<itk::Vector<float, D>, D> * forward)
{
  if (!IsTransformFileName(path))
  {
    // a displacement field (on the fixed grid by now, as `forward`): its inverse by fixed-point iteration, refused
    // where there is none (a folded field)
    auto threader = itk::MultiThreaderBase::New();
    return itk::dmr::InverseDisplacementField(forward, threader.GetPointer());
  }
  const auto transform = ReadTransformFile<D>(path);
  const auto inverse = transform->GetInverseTransform();
  if (!inverse)
  {
    itkGenericExceptionMacro(<< "the " << transform->GetTransformTypeAsString()
                             << " of the initial transformation has no inverse transform in ITK: give an invertible "
                                "one (e.g. an affine) or leave out --inverse");
  }
  const auto field = TransformFieldOnGrid<D>(inverse, reference);
  const auto p = itk::dmr::FirstNonFinitePixel(field.GetPointer());
  if (p >= 0)
  {
    itkGenericExceptionMacro(<< "the inverse of the initial transformation is not finite at voxel "
                             << field->ComputeIndex(static_cast<itk::OffsetValueType>(p)) << " of the fixed grid");
  }
  return field;
}
} // namespace dmrtools

#endif
