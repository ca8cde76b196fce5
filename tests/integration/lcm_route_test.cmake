# Channel routes (config lcm_route): a routed channel reaches only the sockets of its port, and
# ftcal-relay copies them onto one URL for lcm-spy;
# over multicast in the binary's own network namespace.
add_executable(lcm_route_test "${CMAKE_CURRENT_LIST_DIR}/lcm_route_test.cc")
target_link_libraries(lcm_route_test PRIVATE
  ftcal_common ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
target_compile_definitions(lcm_route_test PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_RELAY="$<TARGET_FILE:ftcal-relay>")
add_dependencies(lcm_route_test ftcal-relay)
set_target_properties(lcm_route_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
ftcal_gtest_discover(lcm_route_test KIND integration TIER fast
  PROPERTIES TIMEOUT 60
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
