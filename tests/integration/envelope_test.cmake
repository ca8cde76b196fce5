# Signed channels (services/common/envelope) on memq://, ftcal-keygen and ftcal-envelopes
# (no network).
ftcal_add_gtest(envelope_test integration TIMEOUT 60 TIER fast
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/envelope_test.cc"
  LIBS ftcal_common ftcal_child_process)
target_compile_definitions(envelope_test PRIVATE FTCAL_KEYGEN="$<TARGET_FILE:ftcal-keygen>"
  FTCAL_ENVELOPES="$<TARGET_FILE:ftcal-envelopes>" FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
add_dependencies(envelope_test ftcal-keygen ftcal-envelopes)
