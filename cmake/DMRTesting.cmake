# dmr_add_gtest(<name> LABEL unit|e2e SOURCES ...): one GoogleTest executable, discovered by ctest.
include(GoogleTest)
find_package(GTest REQUIRED)
function(dmr_add_gtest name)
  cmake_parse_arguments(_t "" "LABEL" "SOURCES" ${ARGN})
  add_executable(${name} ${_t_SOURCES})
  target_link_libraries(${name} PRIVATE DynamicMeshRegistration dmrTestHelpers GTest::gtest GTest::gtest_main)
  gtest_discover_tests(${name} DISCOVERY_TIMEOUT 60
    PROPERTIES LABELS "${_t_LABEL}" ENVIRONMENT "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS=2")
endfunction()
