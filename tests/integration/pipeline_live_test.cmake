# The whole chain live (lcm-logplayer -> ftcal-pose-segmenter, ftcal-calibrator, ftcal-corrector
# -> lcm-logger) against --replay/--log, and ftcal-corrector killed and restarted mid-play:
# multicast, so the binary runs in its own network namespace (scripts/netns-exec), listed when
# ctest runs (PRE_TEST).
add_executable(pipeline_live_test "${CMAKE_CURRENT_LIST_DIR}/pipeline_live_test.cc")
target_link_libraries(pipeline_live_test PRIVATE
  ftcal_twin ftcal_calibrator ftcal_pose_segmenter_stage ftcal_common ftcal_lcmtypes ftcal_child_process GTest::gtest
  GTest::gtest_main Threads::Threads)
target_compile_definitions(pipeline_live_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>"
  FTCAL_LCM_LOGGER="${LCM_LOGGER}"
  FTCAL_LCM_LOGPLAYER="${LCM_LOGPLAYER}")
add_dependencies(pipeline_live_test ftcal-pose-segmenter ftcal-calibrator ftcal-corrector)
set_target_properties(pipeline_live_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
# WHOLE_GROUP: the live chain keeps pace with lcm-logplayer only if the machine is its own; in
# CI's sanitizer run, beside other tests on two cores, it failed (it passes alone).
ftcal_gtest_discover(pipeline_live_test KIND integration
  WHOLE_GROUP PROPERTIES TIMEOUT 180
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
