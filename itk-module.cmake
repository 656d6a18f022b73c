# The ONE ITK module of this project. Its dependency lists also drive the standalone build
# (cmake/DMRStandalone.cmake reads DEPENDS/TEST_DEPENDS from here).
get_filename_component(MY_CURRENT_DIR "${CMAKE_CURRENT_LIST_FILE}" PATH)
set(DOCUMENTATION "FEM-based deformable image registration with a dynamic mesh rebuilt every iteration from a
density field (discrete centroidal Voronoi tessellation + dual triangulation/tetrahedralization).
Cai, Guo, Zhong, Mao, Dynamic meshing for deformable image registration, Computer-Aided Design 58 (2015) 141-150.")

itk_module(DynamicMeshRegistration
  DEPENDS
    ITKCommon
    ITKImageFilterBase
    ITKImageGradient
    ITKImageGrid
    ITKImageFunction
    ITKSmoothing
    ITKDisplacementField
    ITKTransform
    ITKMesh
    ITKPath
    ITKIOImageBase
    ITKIONIFTI
    ITKIOMeta
    ITKIOGDCM
    ITKIOMeshBase
    ITKIOMeshVTK
    ITKIOTransformBase
    ITKEigen3
  TEST_DEPENDS
    ITKTestKernel
    ITKGoogleTest
  DESCRIPTION
    "${DOCUMENTATION}"
  EXCLUDE_FROM_DEFAULT
  ENABLE_SHARED
)
