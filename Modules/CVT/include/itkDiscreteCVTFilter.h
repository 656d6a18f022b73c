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
#ifndef itkDiscreteCVTFilter_h
#define itkDiscreteCVTFilter_h

#include "itkImageToImageFilter.h"
#include "itkPointSet.h"
#include "itkDynamicMeshRegistrationEnums.h"
#include "dmrDiscreteCVT.h"
#include "dmrCVTBackend.h"
#include <memory>

namespace itk
{
/** \class DiscreteCVTFilter
 * \brief Splits the image domain into N face-connected cells that are the discrete centroidal Voronoi
 * tessellation of a density field.
 *
 * Input 0: the density d(x) > 0 (e.g. the output of DensityFieldFilter). Optional input "InitialLabels": a label
 * image with labels 0..N-1 to warm-start from (paper 4.7); without it the tessellation starts from the greedy
 * least-cost pair contraction of paper 4.4 (from BlockSize^D blocks: 1 in 2D, 4 in 3D by default, paper Table 1).
 * The tessellation is then optimised by the parallel boundary-pixel swaps of paper Algorithm 1 with a two-phase,
 * parity-coloured rule that never raises the energy and keeps every cell connected (see dmr::DiscreteCVT).
 *
 * Backend: CPU; CUDA (the contraction stays on the CPU, the swap optimisation runs on the GPU through
 * dmr::cuda::CVTSwapOptimizer with the same rule and arithmetic, hence the same labels; throws when no device is
 * usable); Auto (default): CUDA when a device is present, else CPU. GetBackendUsed() tells which one ran.
 *
 * Output 0: the label image (labels 0..N-1, same geometry as the density). Output 1: the sites, i.e. the
 * density-weighted centroids of the cells, as a PointSet in physical coordinates (point i = site of cell i, point
 * data = cell mass).
 *
 * \par References
 * Y. Cai, X. Guo, Z. Zhong, W. Mao, "Dynamic meshing for deformable image registration", Computer-Aided Design 58
 * (2015) 141-150, doi:10.1016/j.cad.2014.08.009.
 * \ingroup DynamicMeshRegistration */
template <typename TDensityImage, typename TLabelImage = Image<int32_t, TDensityImage::ImageDimension>>
class ITK_TEMPLATE_EXPORT DiscreteCVTFilter : public ImageToImageFilter<TDensityImage, TLabelImage>
{
public:
  ITK_DISALLOW_COPY_AND_MOVE(DiscreteCVTFilter);
  using Self = DiscreteCVTFilter;
  using Superclass = ImageToImageFilter<TDensityImage, TLabelImage>;
  using Pointer = SmartPointer<Self>;
  using ConstPointer = SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(DiscreteCVTFilter, ImageToImageFilter);

  static constexpr unsigned int ImageDimension = TDensityImage::ImageDimension;
  using DensityImageType = TDensityImage;
  using LabelImageType = TLabelImage;
  using LabelType = typename LabelImageType::PixelType;
  using SitesType =
    PointSet<double, ImageDimension, DefaultStaticMeshTraits<double, ImageDimension, ImageDimension, double, double>>;
  using BackendEnum = DynamicMeshRegistrationEnums::Backend;
  using CoreType = dmr::DiscreteCVT<ImageDimension>;
  using DataObjectPointerArraySizeType = typename Superclass::DataObjectPointerArraySizeType;

  itkSetInputMacro(InitialLabels, LabelImageType);
  itkGetInputMacro(InitialLabels, LabelImageType);

  /** Number of cells N (= mesh nodes before boundary/corner handling). */
  itkSetClampMacro(NumberOfCells, SizeValueType, 4, NumericTraits<SizeValueType>::max());
  itkGetConstMacro(NumberOfCells, SizeValueType);
  /** Edge length in pixels of the blocks the contraction starts from. */
  itkSetClampMacro(BlockSize, unsigned int, 1, 64);
  itkGetConstMacro(BlockSize, unsigned int);
  /** Stop when a sweep lowers the energy by no more than Epsilon x E (paper 5.1: 0, the exact local minimum). */
  itkSetClampMacro(Epsilon, double, 0.0, 1.0);
  itkGetConstMacro(Epsilon, double);
  /** Safety cap on the number of sweeps of one update. */
  itkSetClampMacro(MaximumNumberOfSweeps, SizeValueType, 1, NumericTraits<SizeValueType>::max());
  itkGetConstMacro(MaximumNumberOfSweeps, SizeValueType);
  /** Whether the swap optimisation runs (default on). Off: the output is the tessellation it starts from (the
   * contraction's, or the initial labels), e.g. for a caller that optimises on a device optimiser of its own. */
  itkSetMacro(SwapOptimization, bool);
  itkGetConstMacro(SwapOptimization, bool);
  itkBooleanMacro(SwapOptimization);
  itkSetEnumMacro(Backend, BackendEnum);
  itkGetEnumMacro(Backend, BackendEnum);
  itkGetConstMacro(BackendUsed, BackendEnum);

  /** Statistics of the last update. */
  itkGetConstMacro(InitialEnergy, double);
  itkGetConstMacro(Energy, double);
  itkGetConstMacro(NumberOfSweeps, SizeValueType);
  itkGetConstMacro(NumberOfSwaps, SizeValueType);
  /** Seconds spent in the contraction (0 on a warm start) and in the swap optimisation. */
  itkGetConstMacro(InitializationTime, double);
  itkGetConstMacro(OptimizationTime, double);

  /** The sites (output 1). */
  SitesType *
  GetSites();

  /** The CPU core of the last update: labels, masses and centroids in the grid frame (on the CUDA back-end it takes
   * the GPU's state, which equals the CPU back-end's bit for bit). */
  const CoreType &
  GetCore() const
  {
    return m_Core;
  }

protected:
  DiscreteCVTFilter();
  ~DiscreteCVTFilter() override = default;
  void
  PrintSelf(std::ostream & os, Indent indent) const override;
  /** Checks of the parameters and of which inputs are set (before the inputs' information is updated). */
  void
  VerifyPreconditions() ITKv5_CONST override;
  /** Checks of the inputs' sizes, once the pipeline's information pass has updated them (an input may be the
   * output of a filter that has not run yet). */
  void
  VerifyInputInformation() ITKv5_CONST override;
  void
  GenerateInputRequestedRegion() override;
  void
  EnlargeOutputRequestedRegion(DataObject * output) override;
  /** Only output 0 is an image (output 1 is the sites' PointSet). */
  void
  GenerateOutputInformation() override;
  void
  GenerateData() override;
  using Superclass::MakeOutput;
  DataObject::Pointer
  MakeOutput(DataObjectPointerArraySizeType idx) override;

private:
  /** The swap optimisation on the GPU, from the core's labels; the core then takes the GPU's labels, masses,
   * centroids and energy. */
  typename CoreType::OptimizeResult
  OptimizeOnDevice(const dmr::Grid<ImageDimension> & grid);

  SizeValueType                                m_NumberOfCells{ 2000 };
  unsigned int                                 m_BlockSize{ ImageDimension == 2 ? 1u : 4u };
  double                                       m_Epsilon{ 0.0 };
  SizeValueType                                m_MaximumNumberOfSweeps{ 1000 };
  bool                                         m_SwapOptimization{ true };
  BackendEnum                                  m_Backend{ BackendEnum::Auto };
  BackendEnum                                  m_BackendUsed{ BackendEnum::CPU };
  double                                       m_InitialEnergy{ 0.0 };
  double                                       m_Energy{ 0.0 };
  SizeValueType                                m_NumberOfSweeps{ 0 };
  SizeValueType                                m_NumberOfSwaps{ 0 };
  double                                       m_InitializationTime{ 0.0 };
  double                                       m_OptimizationTime{ 0.0 };
  CoreType                                     m_Core;
  std::vector<float>                           m_DensityBuffer;
  std::unique_ptr<dmr::cuda::CVTSwapOptimizer> m_DeviceOptimizer; // kept between updates (device allocations)
};
} // namespace itk

#ifndef ITK_MANUAL_INSTANTIATION
#include "itkDiscreteCVTFilter.hxx"
#endif

#endif
