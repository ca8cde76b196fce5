# ftcal-dynamixel-bridge against ftcal-emulate-dynamixel (the twin's MX-106 bus on a pty): the
# emulator alone, the bridge class in-process, and the processes over LCM. The whole binary runs
# in its own network namespace (scripts/netns-exec as the CROSSCOMPILING_EMULATOR). Included
# from tests/integration/CMakeLists.txt.
if(TARGET ftcal-emulate-dynamixel AND TARGET ftcal-dynamixel-bridge)
  add_executable(dynamixel_bridge_test "${CMAKE_CURRENT_LIST_DIR}/dynamixel_bridge_test.cc")
  target_link_libraries(dynamixel_bridge_test PRIVATE
    ftcal_dynamixel_bridge ftcal_dxl_emulator ftcal_lcmtypes ftcal_child_process
    GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(dynamixel_bridge_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_EMULATE_DYNAMIXEL="$<TARGET_FILE:ftcal-emulate-dynamixel>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>")
  add_dependencies(dynamixel_bridge_test ftcal-emulate-dynamixel ftcal-dynamixel-bridge)
  set_target_properties(dynamixel_bridge_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(dynamixel_bridge_test KIND integration
    # the emulator and the bridge on a pty in process, and the bridge failing at start: fast
    FAST "DynamixelEmulator.*:DynamixelBridgePty.*:DynamixelBridgeFailures.*"
    PROPERTIES TIMEOUT 60
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
