# Corrector throughput, engine and stage (label bench). Run by hand: <build>/tests/bench/corrector_bench
add_executable(corrector_bench "${CMAKE_CURRENT_LIST_DIR}/corrector_bench.cc")
target_link_libraries(corrector_bench PRIVATE ftcal_corrector_stage ftcal_twin benchmark::benchmark Threads::Threads)
target_compile_definitions(corrector_bench PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
add_test(NAME corrector_bench COMMAND corrector_bench --benchmark_min_time=1)
set_tests_properties(corrector_bench PROPERTIES LABELS bench TIMEOUT 300)
