# Issue 36, finding 4: what a 250 MB message costs the real Dynamixel bridge (run --realtime, as
# shipped) against the bus emulator; over multicast in the binary's own network namespace.
add_executable(big_message_test "${CMAKE_CURRENT_LIST_DIR}/big_message_test.cc")
target_link_libraries(big_message_test PRIVATE
  ftcal_common ftcal_lcmtypes ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
target_compile_definitions(big_message_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_EMULATE_DYNAMIXEL="$<TARGET_FILE:ftcal-emulate-dynamixel>"
  FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>")
add_dependencies(big_message_test ftcal-emulate-dynamixel ftcal-dynamixel-bridge)
set_target_properties(big_message_test PROPERTIES
  CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
ftcal_gtest_discover(big_message_test KIND integration
  PROPERTIES TIMEOUT 120
  DISCOVERY_TIMEOUT 60
  DISCOVERY_MODE PRE_TEST)
