# ftcal-pose-segmenter and ftcal-corrector over a log written from the twin (--replay), and the
# segmenter live with lcm-logplayer/lcm-logger: multicast, so the whole binary runs in its own
# network namespace (scripts/netns-exec), listed when ctest runs (PRE_TEST).
add_executable(stages_test "${CMAKE_CURRENT_LIST_DIR}/stages_test.cc")
target_link_libraries(stages_test PRIVATE
  ftcal_twin ftcal_messages ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
target_compile_definitions(stages_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>"
  FTCAL_LCM_LOGGER="${LCM_LOGGER}"
  FTCAL_LCM_LOGPLAYER="${LCM_LOGPLAYER}")
add_dependencies(stages_test ftcal-pose-segmenter ftcal-corrector)
set_target_properties(stages_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
ftcal_gtest_discover(stages_test KIND integration
  PROPERTIES TIMEOUT 180
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
