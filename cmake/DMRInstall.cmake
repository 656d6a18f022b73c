# Install rules of the standalone build (path c of CMakeLists.txt): the library, its public headers, the command-line
# tools and a CMake package, so that another project uses the module with
#   find_package(DynamicMeshRegistration REQUIRED)
#   target_link_libraries(app PRIVATE DynamicMeshRegistration::DynamicMeshRegistration)
# (test/Install builds such a project against an installed tree). Paths a and b install through ITK's module system.
include(GNUInstallDirs)
include(CMakePackageConfigHelpers)
set(DMR_INSTALL_INCLUDE_DIR ${CMAKE_INSTALL_INCLUDEDIR}/DynamicMeshRegistration)
set(DMR_INSTALL_CMAKE_DIR ${CMAKE_INSTALL_LIBDIR}/cmake/DynamicMeshRegistration)

target_include_directories(DynamicMeshRegistration PUBLIC $<INSTALL_INTERFACE:${DMR_INSTALL_INCLUDE_DIR}>)
install(TARGETS DynamicMeshRegistration EXPORT DynamicMeshRegistrationTargets
  ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR}
  LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR}
  RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})
file(GLOB _dmr_public_headers ${PROJECT_SOURCE_DIR}/Modules/*/include/*.h ${PROJECT_SOURCE_DIR}/Modules/*/include/*.hxx)
install(FILES ${_dmr_public_headers}
  ${PROJECT_BINARY_DIR}/Modules/include/dmrConfigure.h
  ${PROJECT_BINARY_DIR}/Modules/include/DynamicMeshRegistrationExport.h
  DESTINATION ${DMR_INSTALL_INCLUDE_DIR})
install(EXPORT DynamicMeshRegistrationTargets NAMESPACE DynamicMeshRegistration:: DESTINATION ${DMR_INSTALL_CMAKE_DIR})

# What the package's config finds again for its users: ITK with the module's components (PUBLIC), and for a static
# library also the PRIVATE link dependencies (CGAL, TetGen, the CUDA runtime), which then appear as link-only items.
get_target_property(_dmr_library_type DynamicMeshRegistration TYPE)
if(_dmr_library_type STREQUAL "STATIC_LIBRARY")
  set(DMR_CONFIG_STATIC ON)
else()
  set(DMR_CONFIG_STATIC OFF)
endif()
set(DMR_CONFIG_ITK_COMPONENTS ${DMR_ITK_DEPENDS})
configure_package_config_file(${PROJECT_SOURCE_DIR}/cmake/DynamicMeshRegistrationConfig.cmake.in
  ${PROJECT_BINARY_DIR}/DynamicMeshRegistrationConfig.cmake
  INSTALL_DESTINATION ${DMR_INSTALL_CMAKE_DIR})
write_basic_package_version_file(${PROJECT_BINARY_DIR}/DynamicMeshRegistrationConfigVersion.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES
  ${PROJECT_BINARY_DIR}/DynamicMeshRegistrationConfig.cmake
  ${PROJECT_BINARY_DIR}/DynamicMeshRegistrationConfigVersion.cmake
  ${PROJECT_SOURCE_DIR}/cmake/FindTetGen.cmake
  DESTINATION ${DMR_INSTALL_CMAKE_DIR})
