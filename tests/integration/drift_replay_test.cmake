# ftcal-drift over logs ftcal-sim writes with the twin's offsets drifting (both real processes;
# logs only, no network): DRIFT and --out-calibration against the drifted truth the twin wrote
# beside the log, the demo's drift session against its drifted truth, and --apply's calibrations
# (only significant changes, at most once per interval).
ftcal_add_gtest(drift_replay_test integration TIMEOUT 120 TIER fast
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/drift_replay_test.cc"
  LIBS libcal ftcal_messages ftcal_common ftcal_child_process)
target_compile_definitions(drift_replay_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
  FTCAL_DRIFT="$<TARGET_FILE:ftcal-drift>")
add_dependencies(drift_replay_test ftcal-sim ftcal-drift)
