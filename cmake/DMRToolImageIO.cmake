# The image formats the command-line tools read and write besides the library's own (NIfTI, MetaImage, DICOM through
# GDCM): PNG, JPEG, TIFF, BMP (2D images), NRRD, VTK legacy images, GIPL, MRC; and the transform file formats of
# --initial-transform (ITK's text format, MATLAB, HDF5). Included by the directories that build tools (Examples/,
# test/Example/): the second find_package(ITK) adds these IO modules and ITK_USE_FILE writes the IO factory
# registrations for this directory only, so the library keeps its own dependency list (itk-module.cmake).
# Sets DMR_TOOL_IMAGE_IO_LIBRARIES for the tools to link.
set(DMR_TOOL_IMAGE_IO_MODULES ITKIOPNG ITKIOJPEG ITKIOTIFF ITKIOBMP ITKIONRRD ITKIOVTK ITKIOGIPL ITKIOMRC
  ITKIOTransformInsightLegacy ITKIOTransformMatlab ITKIOTransformHDF5)
find_package(ITK 5.2 REQUIRED COMPONENTS ${DMR_ITK_DEPENDS} ${DMR_TOOL_IMAGE_IO_MODULES})
include(${ITK_USE_FILE})
set(DMR_TOOL_IMAGE_IO_LIBRARIES ${ITK_LIBRARIES})
