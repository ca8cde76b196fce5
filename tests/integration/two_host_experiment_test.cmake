# Two hosts, tested here (issue 12): the short experiment plan live across two network
# namespaces joined by a veth pair, the group brought up by ftcal-launch on one supervisord per
# host, the recorder (robot) and the segmenter (workstation) killed with -9 mid-run; the restarts
# against /proc, the recording against the transducers' sequence numbers, the live calibration
# against the twin's truth. About six minutes of real time, root only (two namespaces of its
# own; the test skips otherwise), inside scripts/netns-exec like the other multicast tests.
find_program(FTCAL_SUPERVISORD supervisord)
if(FTCAL_SUPERVISORD AND TARGET ftcal-launch AND TARGET ftcal-sim AND TARGET ftcal-sequencer AND TARGET ftcal-record AND
   TARGET ftcal-sequencer-control AND TARGET ftcal-keygen AND LCM_LOGGER)
  add_executable(two_host_experiment_test "${CMAKE_CURRENT_LIST_DIR}/two_host_experiment_test.cc")
  target_link_libraries(two_host_experiment_test PRIVATE
    ftcal_launcher ftcal_lcmtypes ftcal_child_process libcal GTest::gtest GTest::gtest_main
    Threads::Threads)
  target_compile_definitions(two_host_experiment_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_LAUNCH="$<TARGET_FILE:ftcal-launch>"
    FTCAL_EVENTS="$<TARGET_FILE:ftcal-supervisor-events>"
    FTCAL_STATUS_EXE="$<TARGET_FILE:ftcal-status>"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>"
    FTCAL_MOCAP_BRIDGE="$<TARGET_FILE:ftcal-mocap-bridge>"
    FTCAL_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
    FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
    FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>"
    FTCAL_DRIFT="$<TARGET_FILE:ftcal-drift>"
    FTCAL_SEQUENCER="$<TARGET_FILE:ftcal-sequencer>"
    FTCAL_SEQUENCER_CONTROL="$<TARGET_FILE:ftcal-sequencer-control>"
    FTCAL_KEYGEN="$<TARGET_FILE:ftcal-keygen>"
    FTCAL_RECORD="$<TARGET_FILE:ftcal-record>"
    FTCAL_LCM_LOGGER="${LCM_LOGGER}")
  add_dependencies(two_host_experiment_test ftcal-launch ftcal-supervisor-events ftcal-status
    ftcal-sim ftcal-ati-bridge ftcal-dynamixel-bridge ftcal-mocap-bridge ftcal-pose-segmenter
    ftcal-calibrator ftcal-corrector ftcal-drift ftcal-sequencer ftcal-sequencer-control ftcal-keygen
    ftcal-record)
  set_target_properties(two_host_experiment_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  # WHOLE_GROUP: timing-sensitive (restart bounds, a recording that must lose nothing outside the
  # outage) and it runs a dozen processes on its own.
  ftcal_gtest_discover(two_host_experiment_test KIND integration
    LONG "TwoHostExperiment.ShortPlanLiveAcrossAVethPairLoggerAndSegmenterKilledMidRun"
    WHOLE_GROUP PROPERTIES TIMEOUT 1200
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
