# Step 2 (standing) and offset re-estimation at the report's scale (label bench; scripts/test
# leaves it out). Run by hand: <build>/tests/bench/standing_bench
add_executable(standing_bench "${CMAKE_CURRENT_LIST_DIR}/standing_bench.cc")
target_include_directories(standing_bench PRIVATE "${PROJECT_SOURCE_DIR}/tests/unit")
target_link_libraries(standing_bench PRIVATE libcal benchmark::benchmark Threads::Threads)
add_test(NAME standing_bench COMMAND standing_bench --benchmark_min_time=1)
set_tests_properties(standing_bench PROPERTIES LABELS bench TIMEOUT 300)
