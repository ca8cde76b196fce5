# ftcal-sim live (the twin's six ATI boxes, Dynamixel bus and QTM server in one process) with the
# three real bridges and lcm-logger, inside its own network namespace (scripts/netns-exec as the
# CROSSCOMPILING_EMULATOR): the recorded log against the twin's truth series.
if(TARGET ftcal-sim AND TARGET ftcal-ati-bridge AND TARGET ftcal-dynamixel-bridge
   AND TARGET ftcal-mocap-bridge)
  add_executable(sim_live_test "${CMAKE_CURRENT_LIST_DIR}/sim_live_test.cc")
  target_link_libraries(sim_live_test PRIVATE
    ftcal_sim_live ftcal_lcmtypes ftcal_child_process libcal
    GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(sim_live_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>"
    FTCAL_MOCAP_BRIDGE="$<TARGET_FILE:ftcal-mocap-bridge>"
    FTCAL_LCM_LOGGER="${LCM_LOGGER}")
  add_dependencies(sim_live_test ftcal-sim ftcal-ati-bridge ftcal-dynamixel-bridge
    ftcal-mocap-bridge)
  set_target_properties(sim_live_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  # The lock of the WHOLE_GROUP tests (tests/CMakeLists.txt): a twin and its bridges, never
  # beside another group; beside the single-process tests, as it always ran.
  ftcal_gtest_discover(sim_live_test KIND integration
    PROPERTIES TIMEOUT 120 RESOURCE_LOCK ftcal_whole_group
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
