# scripts/experiment end to end on the twin through the real processes. Main tier: the plan
# "quick" of config/sim.pbtxt through QTM (four minutes of motion), and a bridge that dies as the
# plan starts. Long tier: the plan "experiment" twice at once, once with QTM and
# ftcal-mocap-bridge, once with OptiTrack (NatNet) and ftcal-natnet-bridge; each live
# calibration against the twin's truth and against the offline calibration of its recording, and
# the two against each other (about six minutes). Multicast: this test in its own network
# namespace (scripts/netns-exec as the CROSSCOMPILING_EMULATOR), each run in one of its own
# inside it. WHOLE_GROUP: a whole process group on the twin in real time; two at once on two
# cores stalled the twin's boxes past the bridges' limits.
if(TARGET ftcal-sim AND TARGET ftcal-sequencer AND TARGET ftcal-sequencer-control AND
   TARGET ftcal-calibrator AND TARGET ftcal-natnet-bridge AND LCM_LOGGER)
  add_executable(experiment_live_test "${CMAKE_CURRENT_LIST_DIR}/experiment_live_test.cc")
  target_link_libraries(experiment_live_test PRIVATE
    ftcal_lcmtypes ftcal_child_process libcal GTest::gtest GTest::gtest_main)
  target_compile_definitions(experiment_live_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_BUILD_DIR="${PROJECT_BINARY_DIR}")
  add_dependencies(experiment_live_test ftcal-sim ftcal-keygen ftcal-ati-bridge
    ftcal-dynamixel-bridge ftcal-mocap-bridge ftcal-natnet-bridge ftcal-pose-segmenter ftcal-calibrator
    ftcal-corrector ftcal-drift ftcal-sequencer ftcal-sequencer-control)
  set_target_properties(experiment_live_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(experiment_live_test KIND integration
    LONG "ExperimentLive.TheShortPlanCalibratesLiveAsTheTruthThroughQtmAndThroughNatNetAlike"
    WHOLE_GROUP PROPERTIES TIMEOUT 1200
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
