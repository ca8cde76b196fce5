# ftcal-log-upgrade on logs written with the older message versions' own encoders
# (lcmtypes/legacy/): the conversions field for field, the other events byte for byte, damaged
# events refused, and the wire guard's refusal naming the command. No network: logs only.
ftcal_add_gtest(log_upgrade_test integration TIMEOUT 60 TIER fast
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/log_upgrade_test.cc"
  LIBS ftcal_log_upgrade)
target_compile_definitions(log_upgrade_test PRIVATE
  FTCAL_LOG_UPGRADE="$<TARGET_FILE:ftcal-log-upgrade>")
add_dependencies(log_upgrade_test ftcal-log-upgrade)
