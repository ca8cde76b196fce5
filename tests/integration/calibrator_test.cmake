# ftcal-calibrator over logs the test writes from the twin (no network: the logs are read with
# LogReplayBus), its refusals, and the HTML report (scripts/report, Debian's python3).
ftcal_add_gtest(calibrator_test integration TIMEOUT 300
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/calibrator_test.cc"
  LIBS ftcal_twin ftcal_calibrator ftcal_child_process ftcal_legacy_lcmtypes)
target_compile_definitions(calibrator_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
  FTCAL_LOG_UPGRADE="$<TARGET_FILE:ftcal-log-upgrade>"
  FTCAL_PYTHON_DIR="${PROJECT_BINARY_DIR}/python")
add_dependencies(calibrator_test ftcal-calibrator ftcal-pose-segmenter ftcal-log-upgrade)
