# The same twin session through QTM + ftcal-mocap-bridge and through Motive (NatNet) +
# ftcal-natnet-bridge, each recorded and segmented: the same steady poses. Real processes over
# multicast LCM, inside its own network namespace.
if(TARGET ftcal-sim AND TARGET ftcal-natnet-bridge AND TARGET ftcal-mocap-bridge
   AND TARGET ftcal-ati-bridge AND TARGET ftcal-dynamixel-bridge AND TARGET ftcal-pose-segmenter)
  add_executable(natnet_swap_test "${CMAKE_CURRENT_LIST_DIR}/natnet_swap_test.cc")
  target_link_libraries(natnet_swap_test PRIVATE
    ftcal_lcmtypes ftcal_child_process libcal GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(natnet_swap_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>"
    FTCAL_MOCAP_BRIDGE="$<TARGET_FILE:ftcal-mocap-bridge>"
    FTCAL_NATNET_BRIDGE="$<TARGET_FILE:ftcal-natnet-bridge>"
    FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
    FTCAL_LCM_LOGGER="${LCM_LOGGER}")
  add_dependencies(natnet_swap_test ftcal-sim ftcal-ati-bridge ftcal-dynamixel-bridge
    ftcal-mocap-bridge ftcal-natnet-bridge ftcal-pose-segmenter)
  set_target_properties(natnet_swap_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  # The lock of the WHOLE_GROUP tests (tests/CMakeLists.txt): a twin and its bridges, never
  # beside another group; beside the single-process tests, as it always ran.
  ftcal_gtest_discover(natnet_swap_test KIND integration
    PROPERTIES TIMEOUT 240 RESOURCE_LOCK ftcal_whole_group
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
