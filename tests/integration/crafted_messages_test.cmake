# The crafted messages of issue 12 sent at a live ftcal-pose-segmenter over multicast, in its
# own network namespace: refused and counted, memory bounded, the process keeps its heartbeat.
add_executable(crafted_messages_test "${CMAKE_CURRENT_LIST_DIR}/crafted_messages_test.cc")
target_link_libraries(crafted_messages_test PRIVATE
  ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
target_compile_definitions(crafted_messages_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>")
add_dependencies(crafted_messages_test ftcal-pose-segmenter)
set_target_properties(crafted_messages_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
ftcal_gtest_discover(crafted_messages_test KIND integration
  PROPERTIES TIMEOUT 120
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
