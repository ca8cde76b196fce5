# ftcal-drift --apply live: lcm-logplayer plays a walk whose offsets step on one leg into a
# private network namespace (multicast: scripts/netns-exec) while ftcal-drift --apply (signed)
# and ftcal-corrector run on live LCM; the test hears CALIBRATION, DRIFT and CONTACT_WRENCH_SUM.
if(LCM_LOGPLAYER)
  add_executable(drift_apply_live_test "${CMAKE_CURRENT_LIST_DIR}/drift_apply_live_test.cc")
  target_link_libraries(drift_apply_live_test PRIVATE
    libcal ftcal_messages ftcal_common ftcal_lcmtypes ftcal_child_process GTest::gtest
    GTest::gtest_main Threads::Threads)
  target_compile_definitions(drift_apply_live_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_DRIFT="$<TARGET_FILE:ftcal-drift>"
    FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>"
    FTCAL_LCM_LOGPLAYER="${LCM_LOGPLAYER}")
  add_dependencies(drift_apply_live_test ftcal-sim ftcal-drift ftcal-corrector)
  set_target_properties(drift_apply_live_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(drift_apply_live_test KIND integration
    PROPERTIES TIMEOUT 120
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
