# ftcal-record over real LCM multicast, inside scripts/netns-exec's private namespace.
if(TARGET ftcal-record)
  add_executable(recorder_test "${CMAKE_CURRENT_LIST_DIR}/recorder_test.cc")
  target_link_libraries(recorder_test PRIVATE
    ftcal_lcmtypes ftcal_child_process libcal GTest::gtest GTest::gtest_main Threads::Threads lcm::lcm)
  target_compile_definitions(recorder_test PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_RECORD="$<TARGET_FILE:ftcal-record>")
  add_dependencies(recorder_test ftcal-record)
  set_target_properties(recorder_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(recorder_test KIND integration
    PROPERTIES TIMEOUT 60
    DISCOVERY_TIMEOUT 60
    DISCOVERY_MODE PRE_TEST)
endif()
