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
#ifndef dmrBreathingDeformation_h
#define dmrBreathingDeformation_h

// A known, smooth, breathing-like deformation of a 3D CT, to make a registration pair with a ground truth.
//
// Frame and direction. Everything is in ITK's physical space, the LPS patient frame (x: right -> left, y: anterior ->
// posterior, z: inferior -> superior) that ITK's DICOM and NIfTI readers produce; the image's direction matrix maps
// its axes into that frame, so the motion is the same for any slice orientation. The displacement u(x) is given in
// closed form at every physical point x of the fixed image, in mm, with ITK's registration convention:
//     the fixed point x corresponds to the moving point x + u(x),   so   moving(x + u(x)) = fixed(x).
// The moving image is made by pulling back: moving(y) = fixed(y + w(y)) with w the inverse displacement
// (y + w(y) + u(y + w(y)) = y), solved per voxel by the fixed-point iteration w <- -u(y + w), which converges
// because u is a contraction (max |grad u| < 1, checked).
//
// Motion (the moving image is the fixed one "breathed in" further):
//  - diaphragm: u_z = -A G(z; z_base, 0.4 H) G(x; c_x, a_x) G(y; c_y, a_y): inferior, peak A at the lung bases
//    (the level of the diaphragm domes), decaying upward to about 0.04 A at the apex (H: lung height from base to
//    apex, c and a: centre and half-widths of the lungs, G(t; m, s) = exp(-(t - m)^2 / (2 s^2)));
//  - expansion: u_x = B_lr h((x - c_x) / a_x) G(y; c_y, a_y) E(z), u_y = B_ap h((y - c_y) / a_y) G(x; c_x, a_x) E(z)
//    with h(t) = t exp((1 - t^2) / 2) (odd, peak 1 at the lung walls t = +-1), E(z) = G(z; z_base + 0.3 H, 0.5 H),
//    B_lr = 0.2 A, B_ap = 0.33 A: the chest wall moves outward laterally and anteriorly by a few mm;
//  - everything times a border window W(x): 0 within borderZeroMM of the outer voxel layer of the image along every
//    image axis, rising with a C2 smoothstep to 1 over the ramp (borderRampMM, lengthened for large amplitudes so
//    that the window cannot fold the field). Where the lungs reach the image border (a scan that starts at the
//    diaphragm), the motion there is damped accordingly: max |u| is then below A.
// The lung box (c, a, z_base, z_apex) comes from a lung mask (LungBoxFromMask) or, without one, is a central part
// of the image (DefaultLungBox). Diffeomorphism: x -> x + u(x) is injective with det(I + grad u) > 0 when the
// Lipschitz constant of u is below 1; AnalyzeDisplacementField reports max |grad u| (Frobenius, an upper bound of
// the spectral norm) and det J on every voxel.
#include "dmrErrorStatistics.h"
#include "dmrLungMask.h"
#include "itkImage.h"
#include "itkImageRegionConstIteratorWithIndex.h"
#include "itkImageRegionIteratorWithIndex.h"
#include "itkLinearInterpolateImageFunction.h"
#include "itkMultiThreaderBase.h"
#include "itkPoint.h"
#include "itkVector.h"
#include "itkMacro.h"
#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <mutex>
#include <vector>
#include <string>

namespace dmrtools
{
struct BreathingParameters
{
  double amplitudeMM{ 15.0 };       ///< peak superior-inferior (diaphragm) displacement, mm
  double lateralFraction{ 0.2 };    ///< peak lateral expansion as a fraction of amplitudeMM
  double anteriorFraction{ 0.33 };  ///< peak anterior-posterior expansion as a fraction of amplitudeMM
  double borderZeroMM{ 5.0 };       ///< u = 0 within this distance of the image's outer voxel layer
  double borderRampMM{ 40.0 };      ///< then rising smoothly to full strength over (at least) this distance
  double maximumWindowSlope{ 0.4 }; ///< the ramp is lengthened to 1.875 amplitudeMM / maximumWindowSlope when
                                    ///< longer, so that the window alone adds at most this much to |grad u|
                                    ///< (1.875: the steepest slope of the smoothstep)
};

/** Axis-aligned box in physical (LPS) space, mm. */
struct PhysicalBox
{
  itk::Point<double, 3> lower;
  itk::Point<double, 3> upper;
};

/** Physical bounding box of the centres of the voxels where mask != 0; throws when the mask is empty. */
template <typename TMask>
PhysicalBox
MaskBoundingBox(const TMask * mask)
{
  PhysicalBox box;
  box.lower.Fill(std::numeric_limits<double>::max());
  box.upper.Fill(-std::numeric_limits<double>::max());
  bool                                          any = false;
  itk::ImageRegionConstIteratorWithIndex<TMask> it(mask, mask->GetLargestPossibleRegion());
  for (; !it.IsAtEnd(); ++it)
  {
    if (it.Get() == 0)
    {
      continue;
    }
    any = true;
    itk::Point<double, 3> p;
    mask->TransformIndexToPhysicalPoint(it.GetIndex(), p);
    for (unsigned int k = 0; k < 3; ++k)
    {
      box.lower[k] = std::min(box.lower[k], p[k]);
      box.upper[k] = std::max(box.upper[k], p[k]);
    }
  }
  if (!any)
  {
    itkGenericExceptionMacro("MaskBoundingBox: the mask is empty");
  }
  return box;
}

/** Lung box of a lung mask: the physical bounding box in x (left-right) and y (anterior-posterior); in z, from the
 * base (the lowest axial slice whose lung area is at least baseAreaFraction of the largest slice area: the level of
 * the diaphragm domes, above the thin costophrenic recesses) to the apex (the highest slice with at least
 * apexAreaFraction of it: above it only the trachea is left). Throws when the mask is empty. */
template <typename TMask>
PhysicalBox
LungBoxFromMask(const TMask * mask, double baseAreaFraction = 0.5, double apexAreaFraction = 0.05)
{
  PhysicalBox                                   box = MaskBoundingBox(mask);
  const unsigned int                            axis = SuperiorInferiorAxis(mask);
  const auto                                    region = mask->GetLargestPossibleRegion();
  const size_t                                  slices = region.GetSize(axis);
  std::vector<size_t>                           area(slices, 0);
  itk::ImageRegionConstIteratorWithIndex<TMask> it(mask, region);
  for (; !it.IsAtEnd(); ++it)
  {
    if (it.Get() != 0)
    {
      ++area[static_cast<size_t>(it.GetIndex()[axis] - region.GetIndex(axis))];
    }
  }
  const double largest = static_cast<double>(*std::max_element(area.begin(), area.end()));
  // physical z of each slice (its centre voxel), and which end is inferior
  auto sliceZ = [&](size_t s) {
    itk::ContinuousIndex<double, 3> c;
    for (unsigned int k = 0; k < 3; ++k)
    {
      c[k] = static_cast<double>(region.GetIndex(k)) + 0.5 * static_cast<double>(region.GetSize(k) - 1);
    }
    c[axis] = static_cast<double>(region.GetIndex(axis)) + static_cast<double>(s);
    itk::Point<double, 3> p;
    mask->TransformContinuousIndexToPhysicalPoint(c, p);
    return p[2];
  };
  double base = std::numeric_limits<double>::max(), apex = -std::numeric_limits<double>::max();
  for (size_t s = 0; s < slices; ++s)
  {
    const double a = static_cast<double>(area[s]);
    if (a >= baseAreaFraction * largest)
    {
      base = std::min(base, sliceZ(s));
    }
    if (a >= apexAreaFraction * largest)
    {
      apex = std::max(apex, sliceZ(s));
    }
  }
  if (apex > base)
  {
    box.lower[2] = base;
    box.upper[2] = apex;
  }
  return box;
}

/** Physical bounding box of the image's outer voxel centres. */
inline PhysicalBox
ImageBoundingBox(const itk::ImageBase<3> * image)
{
  PhysicalBox box;
  box.lower.Fill(std::numeric_limits<double>::max());
  box.upper.Fill(-std::numeric_limits<double>::max());
  const auto region = image->GetLargestPossibleRegion();
  for (unsigned int corner = 0; corner < 8; ++corner)
  {
    itk::Index<3> idx;
    for (unsigned int k = 0; k < 3; ++k)
    {
      idx[k] = region.GetIndex(k) + ((corner >> k) & 1u ? static_cast<itk::IndexValueType>(region.GetSize(k)) - 1 : 0);
    }
    itk::Point<double, 3> p;
    image->TransformIndexToPhysicalPoint(idx, p);
    for (unsigned int k = 0; k < 3; ++k)
    {
      box.lower[k] = std::min(box.lower[k], p[k]);
      box.upper[k] = std::max(box.upper[k], p[k]);
    }
  }
  return box;
}

/** Where the lungs of a thorax scan roughly are when no mask is given: the middle 70% (left-right), 60%
 * (anterior-posterior) and 60% (superior-inferior) of the image's physical bounding box. */
inline PhysicalBox
DefaultLungBox(const itk::ImageBase<3> * image)
{
  const PhysicalBox b = ImageBoundingBox(image);
  const double      fraction[3] = { 0.7, 0.6, 0.6 };
  PhysicalBox       box;
  for (unsigned int k = 0; k < 3; ++k)
  {
    const double c = 0.5 * (b.lower[k] + b.upper[k]);
    const double h = 0.5 * fraction[k] * (b.upper[k] - b.lower[k]);
    box.lower[k] = c - h;
    box.upper[k] = c + h;
  }
  return box;
}

/** \brief The closed-form breathing displacement u(x) on a fixed image grid (see the file comment). */
class BreathingDeformation
{
public:
  using PointType = itk::Point<double, 3>;
  using VectorType = itk::Vector<double, 3>;

  /** grid: the fixed image (its geometry sets the border window); lungBox: where the lungs are. */
  BreathingDeformation(const itk::ImageBase<3> * grid, const PhysicalBox & lungBox, const BreathingParameters & p = {})
    : m_Parameters(p)
  {
    if (!(p.amplitudeMM >= 0.0) || !std::isfinite(p.amplitudeMM))
    {
      itkGenericExceptionMacro("BreathingDeformation: the amplitude must be a finite number >= 0, not "
                               << p.amplitudeMM);
    }
    if (!(p.borderRampMM > 0.0) || !(p.borderZeroMM >= 0.0))
    {
      itkGenericExceptionMacro("BreathingDeformation: border distances must be positive");
    }
    for (unsigned int k = 0; k < 3; ++k)
    {
      if (!(lungBox.upper[k] > lungBox.lower[k]))
      {
        itkGenericExceptionMacro("BreathingDeformation: the lung box is empty along physical axis " << k);
      }
      m_Center[k] = 0.5 * (lungBox.lower[k] + lungBox.upper[k]);
      m_HalfWidth[k] = 0.5 * (lungBox.upper[k] - lungBox.lower[k]);
    }
    const double height = lungBox.upper[2] - lungBox.lower[2];
    m_RampMM = std::max(p.borderRampMM, 1.875 * p.amplitudeMM / std::max(p.maximumWindowSlope, 1e-6));
    m_DiaphragmZ = lungBox.lower[2];
    m_DiaphragmSigma = 0.4 * height;
    m_ExpansionZ = lungBox.lower[2] + 0.3 * height;
    m_ExpansionSigma = 0.5 * height;
    // physical point -> continuous index: ci = M (x - origin), M = diag(1/spacing) Direction^T
    const auto region = grid->GetLargestPossibleRegion();
    for (unsigned int i = 0; i < 3; ++i)
    {
      m_Origin[i] = grid->GetOrigin()[i];
      m_Spacing[i] = grid->GetSpacing()[i];
      m_IndexLow[i] = static_cast<double>(region.GetIndex(i));
      m_IndexHigh[i] =
        static_cast<double>(region.GetIndex(i) + static_cast<itk::IndexValueType>(region.GetSize(i)) - 1);
      for (unsigned int j = 0; j < 3; ++j)
      {
        m_PhysicalToIndex[i][j] = grid->GetDirection()[j][i] / m_Spacing[i];
      }
    }
  }

  const BreathingParameters &
  GetParameters() const
  {
    return m_Parameters;
  }

  /** Length of the border ramp actually used, mm (see BreathingParameters::maximumWindowSlope). */
  double
  GetRampMM() const
  {
    return m_RampMM;
  }

  /** Border window W(x) in [0, 1]. */
  double
  Window(const PointType & x) const
  {
    double w = 1.0;
    for (unsigned int i = 0; i < 3; ++i)
    {
      double ci = 0.0;
      for (unsigned int j = 0; j < 3; ++j)
      {
        ci += m_PhysicalToIndex[i][j] * (x[j] - m_Origin[j]);
      }
      const double d = std::min(ci - m_IndexLow[i], m_IndexHigh[i] - ci) * m_Spacing[i]; // mm to the outer layer
      w *= SmoothStep((d - m_Parameters.borderZeroMM) / m_RampMM);
    }
    return w;
  }

  /** u(x) in mm (LPS): the moving point of the fixed point x is x + u(x). */
  VectorType
  Displacement(const PointType & x) const
  {
    VectorType u;
    u.Fill(0.0);
    const double w = Window(x);
    if (w == 0.0 || m_Parameters.amplitudeMM == 0.0)
    {
      return u;
    }
    const double A = m_Parameters.amplitudeMM;
    const double tx = (x[0] - m_Center[0]) / m_HalfWidth[0];
    const double ty = (x[1] - m_Center[1]) / m_HalfWidth[1];
    const double gx = std::exp(-0.5 * tx * tx);
    const double gy = std::exp(-0.5 * ty * ty);
    const double dz = (x[2] - m_DiaphragmZ) / m_DiaphragmSigma;
    const double ez = (x[2] - m_ExpansionZ) / m_ExpansionSigma;
    const double E = std::exp(-0.5 * ez * ez);
    u[2] = -A * std::exp(-0.5 * dz * dz) * gx * gy * w;
    u[0] = m_Parameters.lateralFraction * A * Wall(tx) * gy * E * w;
    u[1] = m_Parameters.anteriorFraction * A * Wall(ty) * gx * E * w;
    return u;
  }

  /** w(y) with y + w(y) = the fixed point that moves to y, i.e. y + w + u(y + w) = y; fixed-point iteration to
   * tolerance (mm). Throws when it does not converge (u not a contraction). */
  VectorType
  InverseDisplacement(const PointType & y, double tolerance = 1e-5, unsigned int maximumIterations = 200) const
  {
    VectorType w = -Displacement(y);
    for (unsigned int it = 0; it < maximumIterations; ++it)
    {
      const VectorType next = -Displacement(y + w);
      const double     change = (next - w).GetNorm();
      w = next;
      if (change <= tolerance)
      {
        return w;
      }
    }
    itkGenericExceptionMacro("BreathingDeformation: the inverse did not converge at " << y
                                                                                      << " (amplitude too large?)");
  }

private:
  /** C2 smoothstep: 0 for t <= 0, 1 for t >= 1. */
  static double
  SmoothStep(double t)
  {
    if (t <= 1e-12) // also absorbs rounding in the point -> index conversion at the edge of the zero band
    {
      return 0.0;
    }
    if (t >= 1.0)
    {
      return 1.0;
    }
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0);
  }

  /** Odd profile of the wall motion: t exp((1 - t^2) / 2), peak +-1 at t = +-1. */
  static double
  Wall(double t)
  {
    return t * std::exp(0.5 * (1.0 - t * t));
  }

  BreathingParameters m_Parameters;
  double              m_RampMM{ 40.0 };
  double              m_Center[3]{};
  double              m_HalfWidth[3]{};
  double              m_DiaphragmZ{ 0.0 };
  double              m_DiaphragmSigma{ 1.0 };
  double              m_ExpansionZ{ 0.0 };
  double              m_ExpansionSigma{ 1.0 };
  double              m_Origin[3]{};
  double              m_Spacing[3]{};
  double              m_IndexLow[3]{};
  double              m_IndexHigh[3]{};
  double              m_PhysicalToIndex[3][3]{};
};

/** u sampled at the voxel centres of grid: a displacement image (mm, physical frame) with grid's geometry. */
template <typename TField = itk::Image<itk::Vector<float, 3>, 3>>
typename TField::Pointer
SampleDisplacementField(const BreathingDeformation & deformation, const itk::ImageBase<3> * grid)
{
  auto field = TField::New();
  field->CopyInformation(grid);
  field->SetRegions(grid->GetLargestPossibleRegion());
  field->Allocate();
  itk::MultiThreaderBase::New()->ParallelizeImageRegion<3>(
    field->GetLargestPossibleRegion(),
    [&](const itk::ImageRegion<3> & region) {
      itk::ImageRegionIteratorWithIndex<TField> it(field, region);
      for (; !it.IsAtEnd(); ++it)
      {
        itk::Point<double, 3> x;
        field->TransformIndexToPhysicalPoint(it.GetIndex(), x);
        const auto                 u = deformation.Displacement(x);
        typename TField::PixelType v;
        for (unsigned int k = 0; k < 3; ++k)
        {
          v[k] = static_cast<typename TField::PixelType::ValueType>(u[k]);
        }
        it.Set(v);
      }
    },
    nullptr);
  return field;
}

/** The moving image of the pair: moving(y) = fixed(y + w(y)) on the fixed grid (linear interpolation of fixed,
 * rounded when the pixel type is an integer), so that moving(x + u(x)) = fixed(x). */
template <typename TImage>
typename TImage::Pointer
WarpWithBreathing(const TImage * fixed, const BreathingDeformation & deformation)
{
  auto interpolator = itk::LinearInterpolateImageFunction<TImage, double>::New();
  interpolator->SetInputImage(fixed);
  auto moving = TImage::New();
  moving->CopyInformation(fixed);
  moving->SetRegions(fixed->GetLargestPossibleRegion());
  moving->Allocate();
  const auto        region = fixed->GetLargestPossibleRegion();
  std::atomic<bool> failed{ false };
  std::mutex        errorMutex;
  std::string       error;
  itk::MultiThreaderBase::New()->ParallelizeImageRegion<3>(
    region,
    [&](const itk::ImageRegion<3> & part) {
      itk::ImageRegionIteratorWithIndex<TImage> it(moving, part);
      for (; !it.IsAtEnd() && !failed; ++it)
      {
        itk::Point<double, 3> y;
        moving->TransformIndexToPhysicalPoint(it.GetIndex(), y);
        double value;
        try
        {
          const auto w = deformation.InverseDisplacement(y);
          if (w.GetNorm() == 0.0)
          {
            it.Set(fixed->GetPixel(it.GetIndex()));
            continue;
          }
          itk::ContinuousIndex<double, 3> c;
          fixed->TransformPhysicalPointToContinuousIndex(y + w, c);
          for (unsigned int k = 0; k < 3; ++k) // stay on the grid (w vanishes near the border anyway)
          {
            c[k] = std::clamp(
              c[k],
              static_cast<double>(region.GetIndex(k)),
              static_cast<double>(region.GetIndex(k) + static_cast<itk::IndexValueType>(region.GetSize(k)) - 1));
          }
          value = interpolator->EvaluateAtContinuousIndex(c);
        }
        catch (const itk::ExceptionObject & e)
        {
          std::lock_guard<std::mutex> lock(errorMutex);
          error = e.GetDescription();
          failed = true;
          break;
        }
        using PixelType = typename TImage::PixelType;
        if (std::numeric_limits<PixelType>::is_integer)
        {
          value = std::clamp(std::round(value),
                             static_cast<double>(std::numeric_limits<PixelType>::lowest()),
                             static_cast<double>(std::numeric_limits<PixelType>::max()));
        }
        it.Set(static_cast<PixelType>(value));
      }
    },
    nullptr);
  if (failed)
  {
    itkGenericExceptionMacro(<< error);
  }
  return moving;
}

/** Checks of a displacement field on its grid (central differences, one-sided at the border). */
struct DisplacementFieldReport
{
  double        maximumMagnitude{ 0.0 };        ///< max |u|, mm
  double        maximumBorderMagnitude{ 0.0 };  ///< max |u| on the outer voxel layer of the image, mm
  double        minimumJacobian{ 0.0 };         ///< min det(I + grad u)
  itk::Index<3> minimumJacobianIndex{};         ///< where it is reached
  double        maximumJacobian{ 0.0 };         ///< max det(I + grad u)
  double        maximumGradientNorm{ 0.0 };     ///< max Frobenius norm of grad u (>= spectral norm; < 1: contraction)
  double        maximumSecondDifference{ 0.0 }; ///< max |u(x+h) - 2u(x) + u(x-h)| / h^2 over axes, 1/mm
};

template <typename TField>
DisplacementFieldReport
AnalyzeDisplacementField(const TField * field)
{
  static_assert(TField::ImageDimension == 3, "3D fields only");
  const auto              region = field->GetLargestPossibleRegion();
  const itk::Index<3>     lo = region.GetIndex();
  const itk::Size<3>      size = region.GetSize();
  const auto &            dir = field->GetDirection();
  const auto &            spacing = field->GetSpacing();
  DisplacementFieldReport total;
  total.minimumJacobian = std::numeric_limits<double>::max();
  total.maximumJacobian = -std::numeric_limits<double>::max();
  std::mutex mutex;
  itk::MultiThreaderBase::New()->ParallelizeImageRegion<3>(
    region,
    [&](const itk::ImageRegion<3> & part) {
      DisplacementFieldReport r;
      r.minimumJacobian = std::numeric_limits<double>::max();
      r.maximumJacobian = -std::numeric_limits<double>::max();
      itk::ImageRegionConstIteratorWithIndex<TField> it(field, part);
      for (; !it.IsAtEnd(); ++it)
      {
        const auto idx = it.GetIndex();
        const auto u = it.Get();
        double     norm = 0.0;
        bool       border = false;
        for (unsigned int k = 0; k < 3; ++k)
        {
          norm += static_cast<double>(u[k]) * u[k];
          border = border || idx[k] == lo[k] || idx[k] == lo[k] + static_cast<itk::IndexValueType>(size[k]) - 1;
        }
        norm = std::sqrt(norm);
        r.maximumMagnitude = std::max(r.maximumMagnitude, norm);
        if (border)
        {
          r.maximumBorderMagnitude = std::max(r.maximumBorderMagnitude, norm);
        }
        // G[r][a] = d u_r / d (image axis a), then physical gradient = G diag(1/h) Direction^T
        double G[3][3];
        for (unsigned int a = 0; a < 3; ++a)
        {
          auto       minus = idx, plus = idx;
          const bool hasMinus = idx[a] > lo[a];
          const bool hasPlus = idx[a] + 1 < lo[a] + static_cast<itk::IndexValueType>(size[a]);
          minus[a] -= hasMinus ? 1 : 0;
          plus[a] += hasPlus ? 1 : 0;
          const double steps = (hasMinus ? 1.0 : 0.0) + (hasPlus ? 1.0 : 0.0);
          const auto   um = field->GetPixel(minus);
          const auto   up = field->GetPixel(plus);
          for (unsigned int c = 0; c < 3; ++c)
          {
            G[c][a] = steps > 0 ? (static_cast<double>(up[c]) - um[c]) / (steps * spacing[a]) : 0.0;
          }
          if (hasMinus && hasPlus)
          {
            for (unsigned int c = 0; c < 3; ++c)
            {
              const double second = (static_cast<double>(up[c]) - 2.0 * u[c] + um[c]) / (spacing[a] * spacing[a]);
              r.maximumSecondDifference = std::max(r.maximumSecondDifference, std::abs(second));
            }
          }
        }
        double J[3][3];
        double frobenius = 0.0;
        for (unsigned int c = 0; c < 3; ++c)
        {
          for (unsigned int j = 0; j < 3; ++j)
          {
            double g = 0.0;
            for (unsigned int a = 0; a < 3; ++a)
            {
              g += G[c][a] * dir[j][a];
            }
            frobenius += g * g;
            J[c][j] = (c == j ? 1.0 : 0.0) + g;
          }
        }
        const double det = J[0][0] * (J[1][1] * J[2][2] - J[1][2] * J[2][1]) -
                           J[0][1] * (J[1][0] * J[2][2] - J[1][2] * J[2][0]) +
                           J[0][2] * (J[1][0] * J[2][1] - J[1][1] * J[2][0]);
        if (det < r.minimumJacobian)
        {
          r.minimumJacobian = det;
          r.minimumJacobianIndex = idx;
        }
        r.maximumJacobian = std::max(r.maximumJacobian, det);
        r.maximumGradientNorm = std::max(r.maximumGradientNorm, std::sqrt(frobenius));
      }
      std::lock_guard<std::mutex> lock(mutex);
      total.maximumMagnitude = std::max(total.maximumMagnitude, r.maximumMagnitude);
      total.maximumBorderMagnitude = std::max(total.maximumBorderMagnitude, r.maximumBorderMagnitude);
      if (r.minimumJacobian < total.minimumJacobian)
      {
        total.minimumJacobian = r.minimumJacobian;
        total.minimumJacobianIndex = r.minimumJacobianIndex;
      }
      total.maximumJacobian = std::max(total.maximumJacobian, r.maximumJacobian);
      total.maximumGradientNorm = std::max(total.maximumGradientNorm, r.maximumGradientNorm);
      total.maximumSecondDifference = std::max(total.maximumSecondDifference, r.maximumSecondDifference);
    },
    nullptr);
  return total;
}
} // namespace dmrtools

#endif
