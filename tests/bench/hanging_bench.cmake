# Step 1 (hanging) at the report's scale (label bench; scripts/test leaves it out).
# Run by hand: <build>/tests/bench/hanging_bench
add_executable(hanging_bench "${CMAKE_CURRENT_LIST_DIR}/hanging_bench.cc")
target_include_directories(hanging_bench PRIVATE "${PROJECT_SOURCE_DIR}/tests/unit")
target_link_libraries(hanging_bench PRIVATE libcal benchmark::benchmark Threads::Threads)
add_test(NAME hanging_bench COMMAND hanging_bench --benchmark_min_time=1)
set_tests_properties(hanging_bench PROPERTIES LABELS bench TIMEOUT 300)
