# LogReplayBus's own log reader and AtomicLogFile's writer against LCM's (no network).
ftcal_add_gtest(replay_bus_test integration TIMEOUT 60 TIER fast
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/replay_bus_test.cc"
  LIBS ftcal_common)
