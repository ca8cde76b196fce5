# Issue 36: a flood of garbage at the real corrector shows in its heartbeat (DEGRADED, the drops
# named), over multicast in the binary's own network namespace.
add_executable(flood_status_test "${CMAKE_CURRENT_LIST_DIR}/flood_status_test.cc")
target_link_libraries(flood_status_test PRIVATE
  ftcal_twin ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
target_compile_definitions(flood_status_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>")
add_dependencies(flood_status_test ftcal-corrector)
set_target_properties(flood_status_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
ftcal_gtest_discover(flood_status_test KIND integration
  PROPERTIES TIMEOUT 90
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
