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
#ifndef itkDensityFieldFilter_h
#define itkDensityFieldFilter_h

#include "itkImageToImageFilter.h"
#include "itkVector.h"
#include "itkSimpleDataObjectDecorator.h"
#include "dmrGrid.h"
#include "dmrGaussianShrink.h"
#include "itkDynamicMeshRegistrationEnums.h"
#include <vector>

namespace itk
{
/** \class DensityFieldFilter
 * \brief Multi-resolution SSD force field and the registration density d = |f|^2 + alpha.
 *
 * Inputs: the fixed (target) image T, the moving (source) image S and, optionally, the current displacement field
 * u of the transformation W(x) = x + u(x) (physical units, on the fixed grid, ITK convention: moving point =
 * fixed point + u). The moving image may lie on any grid: it is sampled through physical space.
 *
 * The force is paper Eq. 5, f(x) = sum_i 2 (T^i(x) - S^i(W(x))) grad S^i(W(x)), summed over the levels i of a
 * Gaussian pyramid (3 by default; level 0 is the full-resolution image). Each level's images and gradients are
 * stored at the level's resolution and sampled (multilinear) at the full-resolution pixel positions, i.e. each
 * level's force is brought to the finest grid before |f|^2 is taken (METHOD-NOTES). Gradients are in physical
 * units (per mm), so anisotropic spacing gives the right direction and size.
 *
 * Output 0 is the density d(x) = |f(x)|^2 + alpha (paper Eq. 9) with alpha = AlphaFactor x mean |f|^2
 * (paper 5.1: AlphaFactor = 0.1), unless alpha is set explicitly. When the images already match (mean |f|^2 = 0)
 * alpha falls back to a floor relative to the moving image's intensity range so the density is never all zero.
 * Output 1 is the force field f (physical frame, per pixel). GetMSSD() is paper Eq. 3 evaluated on the finest
 * grid: each level's squared residuals are summed with weight (pixels of the level) / (fine pixels), i.e. as the
 * paper's sum over the level's own pixels. GetSSD() is the plain full-resolution term. The force is Eq. 5 with the
 * levels summed without weights.
 *
 * Which gradient Eq. 5 uses (ForceGradient): the registration updates W <- W o exp(u), so the derivative of the
 * MSSD with respect to the update at x is grad_x S^i(W(x)) = (I + grad u(x))^T (grad S^i)(W(x)), the gradient of the
 * warped moving image (WarpedMoving, the default). A literal reading of Eq. 5, (grad S^i)(W(x)) (MappedMoving), is the
 * same at W = identity but ignores how W has stretched and turned the moving image: once a shape has been deformed
 * far, its edges in the fixed frame are no longer perpendicular to the mapped gradient and the force stops pushing
 * them (docs/benchmarks.md, circle to epsilon: Dice 0.917 mapped vs 0.985 warped). grad u is taken by central
 * differences of the field (one-sided at the image border), per mm.
 *
 * Intensity scale: the density and the force are stored in single precision, and |f|^2 grows with the fourth power
 * of the intensities: an intensity range R beyond about 1e9 overflows it and one below about 1e-9 leaves nothing but
 * alpha. The method does not depend on the intensities' unit (beta and alpha follow the force), so when the force
 * scale 2 R^2 / (smallest fixed spacing), R the larger of the two images' ranges, lies outside [2^-40, 2^40], the
 * filter works on both images multiplied by a power of two s (GetIntensityScale(), 1 otherwise) that brings the force
 * scale to about 1. Every result then refers to the scaled images: the force is s^2 f, the density s^4 d, SSD and
 * MSSD are s^2 times the images', the mean |f|^2 and alpha s^4 times (a fixed Alpha is taken in these units too).
 * WarpMovingImage() gives the image's own intensities. Multiplying by a power of two is exact, so images whose
 * intensities differ by a power of two give the same density up to that factor and the same registration.
 *
 * \par References
 * Y. Cai, X. Guo, Z. Zhong, W. Mao, "Dynamic meshing for deformable image registration", Computer-Aided Design 58
 * (2015) 141-150, doi:10.1016/j.cad.2014.08.009.
 * \ingroup DynamicMeshRegistration */
template <typename TFixedImage,
          typename TMovingImage = TFixedImage,
          typename TDisplacementField = Image<Vector<float, TFixedImage::ImageDimension>, TFixedImage::ImageDimension>,
          typename TDensityImage = Image<float, TFixedImage::ImageDimension>>
class ITK_TEMPLATE_EXPORT DensityFieldFilter : public ImageToImageFilter<TFixedImage, TDensityImage>
{
public:
  ITK_DISALLOW_COPY_AND_MOVE(DensityFieldFilter);
  using Self = DensityFieldFilter;
  using Superclass = ImageToImageFilter<TFixedImage, TDensityImage>;
  using Pointer = SmartPointer<Self>;
  using ConstPointer = SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(DensityFieldFilter, ImageToImageFilter);

  static constexpr unsigned int ImageDimension = TFixedImage::ImageDimension;
  using FixedImageType = TFixedImage;
  using MovingImageType = TMovingImage;
  using DisplacementFieldType = TDisplacementField;
  using ForceFieldType = TDisplacementField;
  using DensityImageType = TDensityImage;
  using MaskImageType = Image<unsigned char, ImageDimension>;
  using GridType = dmr::Grid<ImageDimension>;
  using DataObjectPointerArraySizeType = typename Superclass::DataObjectPointerArraySizeType;

  itkSetInputMacro(FixedImage, FixedImageType);
  itkGetInputMacro(FixedImage, FixedImageType);
  itkSetInputMacro(MovingImage, MovingImageType);
  itkGetInputMacro(MovingImage, MovingImageType);
  /** Optional: current displacement field on the fixed grid (identity when absent). */
  itkSetInputMacro(DisplacementField, DisplacementFieldType);
  itkGetInputMacro(DisplacementField, DisplacementFieldType);
  /** Optional: a mask on the fixed grid (same size; non-zero = inside). Outside it the force is 0, the density is
   * alpha alone (few nodes), and SSD, MSSD and the mean |f|^2 that sets alpha are taken over the mask only
   * (e.g. the lungs of a thoracic CT). */
  itkSetInputMacro(FixedMask, MaskImageType);
  itkGetInputMacro(FixedMask, MaskImageType);

  /** Number of pyramid levels summed in the MSSD (paper 5.1: 3). */
  static constexpr unsigned int MaximumNumberOfLevels = 8;
  itkSetClampMacro(NumberOfLevels, unsigned int, 1, MaximumNumberOfLevels);
  itkGetConstMacro(NumberOfLevels, unsigned int);
  /** alpha = AlphaFactor x mean |f|^2 (paper 5.1: 0.1). Ignored when UseFixedAlpha is on. */
  itkSetClampMacro(AlphaFactor, double, 0.0, NumericTraits<double>::max());
  itkGetConstMacro(AlphaFactor, double);
  /** Use Alpha as given instead of AlphaFactor x mean |f|^2. */
  itkSetMacro(UseFixedAlpha, bool);
  itkGetConstMacro(UseFixedAlpha, bool);
  itkBooleanMacro(UseFixedAlpha);
  /** The alpha used by the last update (or the fixed value to use when UseFixedAlpha is on). */
  itkSetClampMacro(Alpha, double, 0.0, NumericTraits<double>::max());
  itkGetConstMacro(Alpha, double);

  /** Gradient used in the force (see the class description): WarpedMoving (default) or MappedMoving. */
  using ForceGradientEnum = DynamicMeshRegistrationEnums::ForceGradient;
  itkSetEnumMacro(ForceGradient, ForceGradientEnum);
  itkGetEnumMacro(ForceGradient, ForceGradientEnum);

  /** Fill the physical-frame force field output (on by default). The registration turns it off and reads
   * GetGridForce(): at 512x512x141 voxels the second copy of the force would cost 450 MB. */
  itkSetMacro(ComputeForceField, bool);
  itkGetConstMacro(ComputeForceField, bool);
  itkBooleanMacro(ComputeForceField);

  /** Free the pyramids, the grid force and the outputs' buffers (the next Update rebuilds them). */
  void
  ReleaseInternalBuffers();

  /** Results of the last update (of the images scaled by GetIntensityScale()). */
  itkGetConstMacro(MSSD, double);
  itkGetConstMacro(SSD, double);
  itkGetConstMacro(MeanSquaredForce, double);
  /** The power of two the images are multiplied by (see the class description): 1 unless their intensity range
   * would take |f|^2 out of single precision. Set when the pyramids are built (GetPyramid or Update). */
  itkGetConstMacro(IntensityScale, double);

  /** The force field f (physical frame). */
  ForceFieldType *
  GetForceField();

  /** Force of the last update in the grid frame (axes of the fixed image, per pixel, D interleaved floats):
   * what the FEM stage consumes without a round trip through the physical frame. */
  const std::vector<float> &
  GetGridForce() const
  {
    return m_GridForce;
  }

  /** One pyramid level: images at the level's resolution and the affine maps from fine-grid indices. */
  struct PyramidLevel
  {
    GridType           fixedGrid;
    GridType           movingGrid;
    std::vector<float> fixed;
    std::vector<float> moving;
    std::vector<float> movingGradient; // grid frame of the fixed image, per mm, D interleaved
    // incomplete pyramid (GetPyramid(false)), level 0: the input's own buffer where the input is a float image buffered
    // whole and not scaled (fixed or moving is then empty); valid while the input is
    const float * fixedInput{ nullptr };
    const float * movingInput{ nullptr };
    // moving grid frame -> fixed grid frame (the rotation the gradient is taken through; the same for every level)
    double R[ImageDimension][ImageDimension];
    // incomplete pyramid (GetPyramid(false)), levels above 0: how to build fixed and moving from level 0's images
    dmr::GaussianShrinkPlan<ImageDimension> fixedPlan, movingPlan;
    // fixed-level continuous index = FA * fineIndex + Fc
    double FA[ImageDimension][ImageDimension];
    double Fc[ImageDimension];
    // moving-level continuous index = MA * fineIndex + Mc + MB * u_phys
    double MA[ImageDimension][ImageDimension];
    double Mc[ImageDimension];
    double MB[ImageDimension][ImageDimension];
  };

  /** The pyramids of the current inputs (built on first use, kept while the images are unchanged). Level l weighs
   * (pixels of level l) / (fixed pixels) in the MSSD (see GenerateData).
   * complete (default): every level's images and moving gradient, as GenerateData uses them.
   * Incomplete (what the GPU back-end uploads): level 0's fixed and moving images, every level's grids, maps and R, and
   * above level 0 the plans of the smoothing and shrinking instead of the images; no moving gradients. The device
   * builds the rest from them, the same floats. A later complete call rebuilds the pyramids completely. */
  const std::vector<PyramidLevel> &
  GetPyramid(bool complete = true)
  {
    this->BuildPyramids(complete);
    return m_Levels;
  }

  /** alpha for a given mean |f|^2 (paper 5.1: AlphaFactor x mean, with the floor used when the images match), or the
   * fixed Alpha when UseFixedAlpha is on. Needs the pyramids (GetPyramid or Update). */
  double
  ComputeAlpha(double meanSquaredForce) const;

  /** Warp the (full-resolution, unsmoothed) moving image by the given field onto the fixed grid. */
  void
  WarpMovingImage(const DisplacementFieldType * field, std::vector<float> & out) const;

protected:
  DensityFieldFilter();
  ~DensityFieldFilter() override = default;
  void
  PrintSelf(std::ostream & os, Indent indent) const override;
  /** Checks of the inputs' geometry, once the pipeline's information pass has updated them (an input may be the
   * output of a filter that has not run yet). Not ImageToImageFilter's check, which wants every input in the fixed
   * image's physical space: the moving image may lie on any grid. The displacement field and the mask are read pixel
   * for pixel with the fixed image, so they must have its region (start and size), origin, spacing and direction
   * (to the filter's CoordinateTolerance and DirectionTolerance). */
  void
  VerifyInputInformation() ITKv5_CONST override;
  void
  GenerateInputRequestedRegion() override;
  void
  EnlargeOutputRequestedRegion(DataObject * output) override;
  void
  GenerateOutputInformation() override;
  void
  GenerateData() override;
  using Superclass::MakeOutput;
  DataObject::Pointer
  MakeOutput(DataObjectPointerArraySizeType idx) override;

private:
  void
  BuildPyramids(bool complete);

  unsigned int      m_NumberOfLevels{ 3 };
  double            m_AlphaFactor{ 0.1 };
  ForceGradientEnum m_ForceGradient{ ForceGradientEnum::WarpedMoving };
  bool              m_UseFixedAlpha{ false };
  bool              m_ComputeForceField{ true };
  double            m_Alpha{ 0.0 };
  double            m_MSSD{ 0.0 };
  double            m_SSD{ 0.0 };
  double            m_MeanSquaredForce{ 0.0 };
  double            m_IntensityScale{ 1.0 };

  std::vector<PyramidLevel> m_Levels;
  ModifiedTimeType          m_PyramidTime{ 0 };
  unsigned int              m_PyramidLevels{ 0 };
  bool                      m_PyramidComplete{ false }; // every level holds its images and moving gradient
  const void *              m_PyramidFixed{ nullptr };  // identity of the inputs the pyramids were built from
  const void *              m_PyramidMoving{ nullptr };
  double                    m_MovingForceScale{ 0.0 }; // 2 R^2 / h of the moving image's range, times scale^2
  std::vector<float>        m_GridForce;
  // levels 1.. of the fixed pyramid interpolated at every fine pixel (they do not depend on the field; built on the
  // first GenerateData after the pyramids where they take at most 256 MiB, else interpolated every time)
  std::vector<std::vector<double>> m_FixedAtFinePixels;
};
} // namespace itk

#ifndef ITK_MANUAL_INSTANTIATION
#include "itkDensityFieldFilter.hxx"
#endif

#endif
