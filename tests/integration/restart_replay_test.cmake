# Issue 36: the real sequencer, corrector and live calibrator are restarted and sent what they
# took before (a replay after restart), and the corrector is given absurd calibrations; over
# multicast in the binary's own network namespace.
add_executable(restart_replay_test "${CMAKE_CURRENT_LIST_DIR}/restart_replay_test.cc"
  "${CMAKE_CURRENT_LIST_DIR}/absurd_calibration_test.cc")
target_link_libraries(restart_replay_test PRIVATE
  ftcal_twin ftcal_common ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main
  Threads::Threads)
target_compile_definitions(restart_replay_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_SEQUENCER="$<TARGET_FILE:ftcal-sequencer>"
  FTCAL_SEQUENCER_CONTROL="$<TARGET_FILE:ftcal-sequencer-control>"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>")
add_dependencies(restart_replay_test ftcal-sequencer ftcal-sequencer-control ftcal-corrector
  ftcal-calibrator ftcal-dynamixel-bridge)
set_target_properties(restart_replay_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
ftcal_gtest_discover(restart_replay_test KIND integration
  PROPERTIES TIMEOUT 120
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
