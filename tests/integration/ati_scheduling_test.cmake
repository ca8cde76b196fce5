# ftcal::ApplyScheduling (the ATI bridge's --realtime and --slice-us) against the kernel's own
# account of the thread's policy. No network: no namespace needed.
if(TARGET ftcal_ati_bridge)
  add_executable(ati_scheduling_test "${CMAKE_CURRENT_LIST_DIR}/ati_scheduling_test.cc")
  target_link_libraries(ati_scheduling_test PRIVATE
    ftcal_ati_bridge GTest::gtest GTest::gtest_main Threads::Threads)
  gtest_discover_tests(ati_scheduling_test
    PROPERTIES LABELS integration TIMEOUT 30
    DISCOVERY_TIMEOUT 60 DISCOVERY_MODE PRE_TEST)
endif()
