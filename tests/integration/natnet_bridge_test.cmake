# ftcal-natnet-bridge against the twin's Motive (NatNet) emulator, both bitstreams (3.1, 4.1)
# and both transports (unicast, multicast), inside its own network namespace.
if(TARGET ftcal-natnet-bridge AND TARGET ftcal_natnet_emulator)
  add_executable(natnet_bridge_test "${CMAKE_CURRENT_LIST_DIR}/natnet_bridge_test.cc")
  target_link_libraries(natnet_bridge_test PRIVATE ftcal_natnet_bridge ftcal_natnet_emulator
    ftcal_child_process GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(natnet_bridge_test PRIVATE
    FTCAL_NATNET_BRIDGE="$<TARGET_FILE:ftcal-natnet-bridge>"
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  add_dependencies(natnet_bridge_test ftcal-natnet-bridge)
  set_target_properties(natnet_bridge_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(natnet_bridge_test KIND integration
    PROPERTIES TIMEOUT 120
    DISCOVERY_TIMEOUT 60)
endif()
