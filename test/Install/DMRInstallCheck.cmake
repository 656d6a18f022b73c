# cmake -P script of the test InstalledPackageBuildsAndRunsAConsumer (test/Install/CMakeLists.txt). Fails with a
# message naming the step: install, the installed tool, configure, build, a path into the source or build tree in the
# consumer's compile flags (it must see only the installed package), or the consumer's own checks.
foreach(_v BUILD_DIR WORK_DIR CONSUMER_DIR SOURCE_DIR C_COMPILER CXX_COMPILER)
  if(NOT DEFINED ${_v} OR "${${_v}}" STREQUAL "")
    message(FATAL_ERROR "DMRInstallCheck.cmake: ${_v} is not set")
  endif()
endforeach()
file(REMOVE_RECURSE ${WORK_DIR})
set(_prefix ${WORK_DIR}/prefix)
set(_build ${WORK_DIR}/consumer-build)

function(dmr_step name)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE _rc OUTPUT_VARIABLE _out ERROR_VARIABLE _out)
  if(NOT _rc EQUAL 0)
    message(FATAL_ERROR "${name} failed (${_rc}):\n${_out}")
  endif()
  message(STATUS "${name}: ok")
  set(DMR_STEP_OUTPUT "${_out}" PARENT_SCOPE)
endfunction()

dmr_step("install" ${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${_prefix})
foreach(_f lib/cmake/DynamicMeshRegistration/DynamicMeshRegistrationConfig.cmake
    include/DynamicMeshRegistration/itkFEMRegistrationMethod.h include/DynamicMeshRegistration/dmrConfigure.h
    bin/itkDynamicMeshRegistration)
  if(NOT EXISTS ${_prefix}/${_f})
    message(FATAL_ERROR "install: ${_f} is missing from the prefix")
  endif()
endforeach()
dmr_step("installed tool --version" ${_prefix}/bin/itkDynamicMeshRegistration --version)

set(_launcher)
if(CXX_LAUNCHER)
  set(_launcher -DCMAKE_CXX_COMPILER_LAUNCHER=${CXX_LAUNCHER})
endif()
dmr_step("configure the consumer" ${CMAKE_COMMAND} -S ${CONSUMER_DIR} -B ${_build} -DCMAKE_BUILD_TYPE=Release
  -DCMAKE_PREFIX_PATH=${_prefix} -DCMAKE_C_COMPILER=${C_COMPILER} -DCMAKE_CXX_COMPILER=${CXX_COMPILER} ${_launcher})
dmr_step("build the consumer" ${CMAKE_COMMAND} --build ${_build})

# the consumer must have compiled against the installed headers only
file(GLOB_RECURSE _flags ${_build}/CMakeFiles/dmrConsumer.dir/flags.make)
file(READ ${_flags} _flag_text)
foreach(_tree ${SOURCE_DIR}/Modules ${BUILD_DIR}/Modules)
  string(FIND "${_flag_text}" "${_tree}" _at)
  if(NOT _at EQUAL -1)
    message(FATAL_ERROR "the consumer compiled against ${_tree}, not the installed package:\n${_flag_text}")
  endif()
endforeach()

dmr_step("run the consumer" ${_build}/dmrConsumer)
message(STATUS "${DMR_STEP_OUTPUT}")
