# The wire guard (services/common/wire_guard) against crafted messages, on memq:// (no network).
# Its own message type (lcmtypes/crafted_t.lcm) has the shapes the ftcal types lack.
set(_crafted_lcm "${CMAKE_CURRENT_LIST_DIR}/lcmtypes/crafted_t.lcm")
set(_crafted_dir "${CMAKE_CURRENT_BINARY_DIR}/crafted_lcmtypes")
add_custom_command(
  OUTPUT "${_crafted_dir}/ftcal_test/crafted_t.hpp"
  COMMAND ${LCM_GEN} --cpp --cpp-hpath "${_crafted_dir}" "${_crafted_lcm}"
  DEPENDS "${_crafted_lcm}"
  COMMENT "lcm-gen: wire_guard_test's crafted_t"
  VERBATIM)
ftcal_wire_schemas(CraftedSchemas "${_crafted_dir}/crafted_schemas.cc" "${_crafted_lcm}")
ftcal_add_gtest(wire_guard_test integration TIMEOUT 60 TIER fast
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/wire_guard_test.cc"
          "${_crafted_dir}/ftcal_test/crafted_t.hpp"
          "${_crafted_dir}/crafted_schemas.cc"
  LIBS ftcal_common)
target_include_directories(wire_guard_test PRIVATE "${_crafted_dir}")
