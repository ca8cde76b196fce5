# ftcal-sim live --scenario commanded (the twin's legs follow its servos, which follow the goals
# the bridge writes) with the real ATI and Dynamixel bridges and lcm-logger, SERVO_CMD published
# by the test, inside its own network namespace (scripts/netns-exec as the
# CROSSCOMPILING_EMULATOR).
if(TARGET ftcal-sim AND TARGET ftcal-ati-bridge AND TARGET ftcal-dynamixel-bridge)
  add_executable(sim_commanded_test "${CMAKE_CURRENT_LIST_DIR}/sim_commanded_test.cc")
  target_link_libraries(sim_commanded_test PRIVATE
    ftcal_sim_live ftcal_lcmtypes ftcal_child_process libcal ftcal_common
    GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(sim_commanded_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>"
    FTCAL_LCM_LOGGER="${LCM_LOGGER}")
  add_dependencies(sim_commanded_test ftcal-sim ftcal-ati-bridge ftcal-dynamixel-bridge)
  set_target_properties(sim_commanded_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  # WHOLE_GROUP: the servo loop is real time (10 ms cycles, a servo lost after five replies
  # missed): beside another test under the sanitizers, with the machine also busy, the
  # emulator answered too late, the bridge lost every servo and refused the commands.
  ftcal_gtest_discover(sim_commanded_test KIND integration
    WHOLE_GROUP PROPERTIES TIMEOUT 120
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
