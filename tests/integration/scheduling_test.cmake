# ftcal::ApplyScheduling (every bridge's --realtime and --slice-us, services/common) against the
# kernel's own account of the thread's policy. No network: no namespace needed.
add_executable(scheduling_test "${CMAKE_CURRENT_LIST_DIR}/scheduling_test.cc")
target_link_libraries(scheduling_test PRIVATE
  ftcal_common GTest::gtest GTest::gtest_main Threads::Threads)
ftcal_gtest_discover(scheduling_test KIND integration
  PROPERTIES TIMEOUT 30
  DISCOVERY_TIMEOUT 60 DISCOVERY_MODE PRE_TEST)
