# ftcal-mocap-bridge against the twin's QTM emulator: in-process over loopback TCP, then the real
# processes over multicast LCM, all inside its own network namespace.
if(TARGET ftcal-mocap-bridge AND TARGET ftcal-emulate-qtm)
  add_executable(mocap_bridge_test "${CMAKE_CURRENT_LIST_DIR}/mocap_bridge_test.cc")
  target_link_libraries(mocap_bridge_test PRIVATE ftcal_mocap_bridge ftcal_qtm_emulator
    ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(mocap_bridge_test PRIVATE
    FTCAL_MOCAP_BRIDGE="$<TARGET_FILE:ftcal-mocap-bridge>"
    FTCAL_EMULATE_QTM="$<TARGET_FILE:ftcal-emulate-qtm>")
  add_dependencies(mocap_bridge_test ftcal-mocap-bridge ftcal-emulate-qtm)
  set_target_properties(mocap_bridge_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(mocap_bridge_test KIND integration
    # the emulator alone: fast
    FAST "QtmEmulatorTest.*"
    PROPERTIES TIMEOUT 120
    DISCOVERY_TIMEOUT 60)
endif()
