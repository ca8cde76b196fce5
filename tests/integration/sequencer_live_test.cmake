# ftcal-sequencer driving the twin (ftcal-sim live --scenario commanded) through the real ATI,
# Dynamixel and mocap bridges, with the pose segmenter and lcm-logger: a standing grid, the ATI
# bridge killed mid-grid (stop, marker closed), and the resume. Multicast: its own network
# namespace (scripts/netns-exec as the CROSSCOMPILING_EMULATOR).
if(TARGET ftcal-sim AND TARGET ftcal-ati-bridge AND TARGET ftcal-dynamixel-bridge AND
   TARGET ftcal-mocap-bridge AND TARGET ftcal-sequencer)
  add_executable(sequencer_live_test "${CMAKE_CURRENT_LIST_DIR}/sequencer_live_test.cc")
  target_link_libraries(sequencer_live_test PRIVATE
    ftcal_sequencer ftcal_lcmtypes ftcal_child_process libcal
    GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(sequencer_live_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>"
    FTCAL_MOCAP_BRIDGE="$<TARGET_FILE:ftcal-mocap-bridge>"
    FTCAL_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
    FTCAL_SEQUENCER="$<TARGET_FILE:ftcal-sequencer>"
    FTCAL_LCM_LOGGER="${LCM_LOGGER}"
    FTCAL_RECORD="$<TARGET_FILE:ftcal-record>")
  add_dependencies(sequencer_live_test ftcal-record ftcal-sim ftcal-ati-bridge ftcal-dynamixel-bridge
    ftcal-mocap-bridge ftcal-pose-segmenter ftcal-sequencer)
  set_target_properties(sequencer_live_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  # WHOLE_GROUP: the twin follows real time and the segmenter needs each grid pose's dwell to be
  # steady; beside the other live tests on two cores, a clean-clone run found no steady window
  # for three of the poses (it passes alone and passed in the runs before).
  ftcal_gtest_discover(sequencer_live_test KIND integration
    WHOLE_GROUP PROPERTIES TIMEOUT 240
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
