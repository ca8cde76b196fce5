# ftcal-drift live: lcm-logplayer plays a walk whose offsets step on one leg into a private
# network namespace (multicast: scripts/netns-exec) while ftcal-drift runs on live LCM; the test
# hears DRIFT and the heartbeat.
if(LCM_LOGPLAYER)
  add_executable(drift_live_test "${CMAKE_CURRENT_LIST_DIR}/drift_live_test.cc")
  target_link_libraries(drift_live_test PRIVATE
    libcal ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(drift_live_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_DRIFT="$<TARGET_FILE:ftcal-drift>"
    FTCAL_LCM_LOGPLAYER="${LCM_LOGPLAYER}")
  add_dependencies(drift_live_test ftcal-sim ftcal-drift)
  set_target_properties(drift_live_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(drift_live_test KIND integration
    PROPERTIES TIMEOUT 90
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
