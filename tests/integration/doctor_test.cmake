# ftcal-doctor on twin recordings with known faults (a gap, a stall, a missing phase, a skewed
# clock): its text and exit code. No network: logs only.
ftcal_add_gtest(doctor_test integration TIMEOUT 120
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/doctor_test.cc"
  LIBS ftcal_twin ftcal_messages ftcal_lcmtypes ftcal_child_process)
target_compile_definitions(doctor_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_BUILD_DIR="${PROJECT_BINARY_DIR}"
  FTCAL_DOCTOR="$<TARGET_FILE:ftcal-doctor>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>")
add_dependencies(doctor_test ftcal-doctor ftcal-calibrator ftcal-pose-segmenter)
