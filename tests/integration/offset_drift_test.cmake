# Offset drift (docs/method.md): ftcal-sim log writes a drift session, ftcal-calibrator
# --reestimate-offsets re-estimates the offsets (both real processes; logs only, no network);
# checked against the twin's drifted truth rebuilt in the test.
ftcal_add_gtest(offset_drift_test integration TIMEOUT 300
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/offset_drift_test.cc"
  LIBS ftcal_twin libcal ftcal_child_process)
target_compile_definitions(offset_drift_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>")
add_dependencies(offset_drift_test ftcal-sim ftcal-calibrator)
