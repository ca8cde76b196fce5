# The whole method (Calibrate) at the report's scale on the twin: per-stage times, total, peak
# memory (label bench; scripts/test leaves it out). Run by hand: <build>/tests/bench/calibrate_bench
add_executable(calibrate_bench "${CMAKE_CURRENT_LIST_DIR}/calibrate_bench.cc")
target_link_libraries(calibrate_bench PRIVATE ftcal_twin Threads::Threads)
target_compile_definitions(calibrate_bench PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
add_test(NAME calibrate_bench COMMAND calibrate_bench)
set_tests_properties(calibrate_bench PROPERTIES LABELS bench TIMEOUT 300)
