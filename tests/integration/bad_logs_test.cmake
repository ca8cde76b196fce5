# Damaged logs (a corrupt payload, a broken sync word, a wrong type on an FT channel) and inputs
# from another robot into ftcal-pose-segmenter/ftcal-corrector --replay and ftcal-calibrator
# --log: counted or refused, never a wrong output. No network: logs only.
ftcal_add_gtest(bad_logs_test integration TIMEOUT 180
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/bad_logs_test.cc"
  LIBS ftcal_twin ftcal_messages ftcal_lcmtypes ftcal_child_process)
target_compile_definitions(bad_logs_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>")
add_dependencies(bad_logs_test ftcal-pose-segmenter ftcal-calibrator ftcal-corrector)
