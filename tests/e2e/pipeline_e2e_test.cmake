# Issue #5 end to end on the twin: ftcal-sim log -> ftcal-calibrator --log -> ftcal-corrector
# --replay, against the twin regenerated in process (pipeline_e2e_test.cc). No network: every
# program reads and writes logs. One ctest test for the whole binary (not gtest_discover_tests):
# its TESTs share one run of the pipeline (~1 GB of logs, about a minute), which one process per
# TEST would repeat.
add_executable(pipeline_e2e_test "${CMAKE_CURRENT_LIST_DIR}/pipeline_e2e_test.cc")
target_include_directories(pipeline_e2e_test PRIVATE "${CMAKE_CURRENT_LIST_DIR}"
  "${CMAKE_CURRENT_LIST_DIR}/../integration")
target_link_libraries(pipeline_e2e_test PRIVATE
  ftcal_sim_log ftcal_twin ftcal_lcmtypes ftcal_messages ftcal_child_process
  GTest::gtest GTest::gtest_main Threads::Threads)
target_compile_definitions(pipeline_e2e_test PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>")
add_dependencies(pipeline_e2e_test ftcal-sim ftcal-calibrator ftcal-corrector)
add_test(NAME pipeline_e2e_test COMMAND pipeline_e2e_test)
set_tests_properties(pipeline_e2e_test PROPERTIES LABELS e2e.main TIMEOUT 600)
