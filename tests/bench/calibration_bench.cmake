# Step 2 (standing) and offset re-estimation at the report's scale (label bench; scripts/test
# leaves it out). Run by hand: <build>/tests/bench/calibration_bench
add_executable(calibration_bench "${CMAKE_CURRENT_LIST_DIR}/calibration_bench.cc")
target_include_directories(calibration_bench PRIVATE "${PROJECT_SOURCE_DIR}/tests/unit")
target_link_libraries(calibration_bench PRIVATE libcal benchmark::benchmark Threads::Threads)
add_test(NAME calibration_bench COMMAND calibration_bench --benchmark_min_time=1)
set_tests_properties(calibration_bench PROPERTIES LABELS bench TIMEOUT 300)
