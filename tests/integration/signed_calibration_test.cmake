# The corrector and signed CALIBRATION on memq:// (no network): a forged one is not applied.
ftcal_add_gtest(signed_calibration_test integration TIMEOUT 60
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/signed_calibration_test.cc"
  LIBS ftcal_corrector_stage ftcal_twin)
target_compile_definitions(signed_calibration_test PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
