# Standalone build against an installed ITK (Debian's libinsighttoolkit5-dev). itk-module.cmake stays the single
# dependency list: a local itk_module() records DEPENDS/TEST_DEPENDS, then ITK is found with those components.
macro(itk_module _name)
  cmake_parse_arguments(_dmr "EXCLUDE_FROM_DEFAULT;ENABLE_SHARED" "DESCRIPTION" "DEPENDS;TEST_DEPENDS;COMPILE_DEPENDS" ${ARGN})
  set(DMR_ITK_DEPENDS ${_dmr_DEPENDS})
  set(DMR_ITK_TEST_DEPENDS ${_dmr_TEST_DEPENDS})
endmacro()
include(${PROJECT_SOURCE_DIR}/itk-module.cmake)
list(REMOVE_ITEM DMR_ITK_TEST_DEPENDS ITKGoogleTest) # Debian's ITKGoogleTest is an empty stub: use system GTest

include(CTest)
if(BUILD_TESTING)
  find_package(ITK 5.2 REQUIRED COMPONENTS ${DMR_ITK_DEPENDS} ${DMR_ITK_TEST_DEPENDS})
else()
  find_package(ITK 5.2 REQUIRED COMPONENTS ${DMR_ITK_DEPENDS})
endif()
include(${ITK_USE_FILE})

list(APPEND CMAKE_MODULE_PATH ${PROJECT_SOURCE_DIR}/cmake)
include(DMRCuda)
find_package(CGAL 5.5 REQUIRED)
find_package(TetGen REQUIRED)

option(DMR_BUILD_EXAMPLES "Build the command-line tools in Examples/" ON)
find_package(VTK 9.1 QUIET COMPONENTS CommonCore CommonDataModel IOXML IOLegacy)
include(CMakeDependentOption)
cmake_dependent_option(DMR_USE_VTK "Write meshes as VTK XML (.vtu/.pvd) and read unstructured-grid meshes through VTK" ON "VTK_FOUND" OFF)

set(CMAKE_RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/bin)
set(CMAKE_LIBRARY_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/lib)
set(CMAKE_ARCHIVE_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/lib)

add_subdirectory(Modules)
include(DMRInstall)
if(DMR_BUILD_EXAMPLES)
  add_subdirectory(Examples)
endif()
if(BUILD_TESTING)
  add_subdirectory(test)
endif()
