# Generates C++ (target ftcal_lcmtypes), Python and, when a JDK is present, a jar for
# lcm-spy from lcmtypes/*.lcm at build time. Generated code lives only in the build tree.
file(GLOB FTCAL_LCM_FILES CONFIGURE_DEPENDS "${PROJECT_SOURCE_DIR}/lcmtypes/*.lcm")
set(FTCAL_LCM_CPP_DIR "${PROJECT_BINARY_DIR}/lcmtypes")
set(FTCAL_LCM_PY_DIR "${PROJECT_BINARY_DIR}/python")
set(FTCAL_LCM_JAVA_DIR "${PROJECT_BINARY_DIR}/java")

set(_hpp "")
set(_py "")
set(_java "")
foreach(_lcm ${FTCAL_LCM_FILES})
  get_filename_component(_name "${_lcm}" NAME_WE)
  list(APPEND _hpp "${FTCAL_LCM_CPP_DIR}/ftcal/${_name}.hpp")
  list(APPEND _py "${FTCAL_LCM_PY_DIR}/ftcal/${_name}.py")
  list(APPEND _java "${FTCAL_LCM_JAVA_DIR}/ftcal/${_name}.java")
endforeach()

add_custom_command(
  OUTPUT ${_hpp}
  COMMAND ${LCM_GEN} --cpp --cpp-hpath "${FTCAL_LCM_CPP_DIR}" ${FTCAL_LCM_FILES}
  DEPENDS ${FTCAL_LCM_FILES}
  COMMENT "lcm-gen: C++ message types"
  VERBATIM)
add_custom_command(
  OUTPUT ${_py}
  COMMAND ${LCM_GEN} --python --ppath "${FTCAL_LCM_PY_DIR}" ${FTCAL_LCM_FILES}
  DEPENDS ${FTCAL_LCM_FILES}
  COMMENT "lcm-gen: Python message types"
  VERBATIM)
add_custom_target(ftcal_lcmtypes_gen ALL DEPENDS ${_hpp} ${_py})

add_library(ftcal_lcmtypes INTERFACE)
add_dependencies(ftcal_lcmtypes ftcal_lcmtypes_gen)
target_include_directories(ftcal_lcmtypes INTERFACE "${FTCAL_LCM_CPP_DIR}")
target_link_libraries(ftcal_lcmtypes INTERFACE lcm::lcm)

# lcm-spy decodes our channels when our types are on its classpath.
find_package(Java COMPONENTS Development QUIET)
find_file(LCM_JAR lcm.jar PATHS /usr/share/java /usr/local/share/java NO_DEFAULT_PATH)
if(Java_FOUND AND LCM_JAR)
  set(FTCAL_LCM_JAR "${PROJECT_BINARY_DIR}/ftcal_lcmtypes.jar")
  add_custom_command(
    OUTPUT "${FTCAL_LCM_JAR}"
    COMMAND ${CMAKE_COMMAND} -E rm -rf "${FTCAL_LCM_JAVA_DIR}"
    COMMAND ${CMAKE_COMMAND} -E make_directory "${FTCAL_LCM_JAVA_DIR}"
    COMMAND ${LCM_GEN} --java --jpath "${FTCAL_LCM_JAVA_DIR}" ${FTCAL_LCM_FILES}
    COMMAND ${Java_JAVAC_EXECUTABLE} -nowarn -cp "${LCM_JAR}" -d "${FTCAL_LCM_JAVA_DIR}/classes"
            ${_java}
    COMMAND ${Java_JAR_EXECUTABLE} cf "${FTCAL_LCM_JAR}" -C "${FTCAL_LCM_JAVA_DIR}/classes" .
    DEPENDS ${FTCAL_LCM_FILES}
    COMMENT "lcm-gen: Java message types for lcm-spy"
    VERBATIM)
  add_custom_target(ftcal_lcmtypes_jar ALL DEPENDS "${FTCAL_LCM_JAR}")
else()
  message(STATUS "No JDK or lcm.jar: the lcm-spy jar is not built (scripts/spy will say so)")
endif()

# Older versions of the logged types (lcmtypes/legacy/<package>/, README there): C++ only, for
# ftcal-log-upgrade, in a tree of their own. Not in FTCAL_LCM_FILES (lcm-spy's jar, the current
# wire schemas).
file(GLOB FTCAL_LEGACY_LCM_FILES CONFIGURE_DEPENDS "${PROJECT_SOURCE_DIR}/lcmtypes/legacy/*/*.lcm")
set(FTCAL_LEGACY_CPP_DIR "${PROJECT_BINARY_DIR}/lcmtypes-legacy")
set(_legacy_hpp "")
foreach(_lcm ${FTCAL_LEGACY_LCM_FILES})
  get_filename_component(_name "${_lcm}" NAME_WE)
  get_filename_component(_dir "${_lcm}" DIRECTORY)
  get_filename_component(_package "${_dir}" NAME)
  list(APPEND _legacy_hpp "${FTCAL_LEGACY_CPP_DIR}/${_package}/${_name}.hpp")
endforeach()
add_custom_command(
  OUTPUT ${_legacy_hpp}
  COMMAND ${LCM_GEN} --cpp --cpp-hpath "${FTCAL_LEGACY_CPP_DIR}" ${FTCAL_LEGACY_LCM_FILES}
  DEPENDS ${FTCAL_LEGACY_LCM_FILES}
  COMMENT "lcm-gen: C++ legacy message types"
  VERBATIM)
add_custom_target(ftcal_legacy_lcmtypes_gen DEPENDS ${_legacy_hpp})
add_library(ftcal_legacy_lcmtypes INTERFACE)
add_dependencies(ftcal_legacy_lcmtypes ftcal_legacy_lcmtypes_gen)
target_include_directories(ftcal_legacy_lcmtypes INTERFACE "${FTCAL_LEGACY_CPP_DIR}")
target_link_libraries(ftcal_legacy_lcmtypes INTERFACE lcm::lcm)

# Wire schemas for services/common/wire_guard (the checks before LCM's decoder runs):
# ftcal_wire_schemas(FUNCTION OUT_CC FILES... [LEGACY FILES...]) writes OUT_CC defining
# `const std::vector<const ftcal::wire::Schema*>& FUNCTION()` from the .lcm FILES, and
# `FUNCTIONLegacy()`, the older versions among the LEGACY files (for the guard's refusal to
# name them; empty without).
set(FTCAL_WIRE_SCHEMA_PY "${CMAKE_CURRENT_LIST_DIR}/lcm_wire_schema.py")
function(ftcal_wire_schemas function out_cc)
  cmake_parse_arguments(A "" "" "LEGACY" ${ARGN})
  set(legacy "")
  if(A_LEGACY)
    set(legacy --legacy ${A_LEGACY})
  endif()
  add_custom_command(
    OUTPUT "${out_cc}"
    COMMAND "${FTCAL_PYTHON}" "${FTCAL_WIRE_SCHEMA_PY}" ${function} "${out_cc}"
            ${A_UNPARSED_ARGUMENTS} ${legacy}
    DEPENDS ${A_UNPARSED_ARGUMENTS} ${A_LEGACY} "${FTCAL_WIRE_SCHEMA_PY}"
    COMMENT "wire schemas: ${function}"
    VERBATIM)
endfunction()
ftcal_wire_schemas(FtcalSchemas "${PROJECT_BINARY_DIR}/wire_schemas.cc" ${FTCAL_LCM_FILES}
  LEGACY ${FTCAL_LEGACY_LCM_FILES})
# The rule lives in this directory; services/common compiles the file (CMP0118) after this.
add_custom_target(ftcal_wire_schemas_gen DEPENDS "${PROJECT_BINARY_DIR}/wire_schemas.cc")
# The legacy versions' own schemas, for ftcal-log-upgrade to check each old message before its
# decoder runs.
ftcal_wire_schemas(LegacySchemas "${PROJECT_BINARY_DIR}/legacy_wire_schemas.cc"
  ${FTCAL_LEGACY_LCM_FILES})
add_custom_target(ftcal_legacy_schemas_gen DEPENDS "${PROJECT_BINARY_DIR}/legacy_wire_schemas.cc")
