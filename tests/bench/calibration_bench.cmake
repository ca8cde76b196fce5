# The whole method (Calibrate) at the report's scale on the twin: per-stage times, total, peak
# memory (label bench; scripts/test leaves it out). Run by hand: <build>/tests/bench/calibration_bench
add_executable(calibration_bench "${CMAKE_CURRENT_LIST_DIR}/calibration_bench.cc")
target_link_libraries(calibration_bench PRIVATE ftcal_twin Threads::Threads)
target_compile_definitions(calibration_bench PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
add_test(NAME calibration_bench COMMAND calibration_bench)
set_tests_properties(calibration_bench PROPERTIES LABELS bench TIMEOUT 300)
