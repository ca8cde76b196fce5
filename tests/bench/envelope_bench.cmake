# Cost of the signed channels and the wire guard per message (label bench). Run by hand:
# <build>/tests/bench/envelope_bench
add_executable(envelope_bench "${CMAKE_CURRENT_LIST_DIR}/envelope_bench.cc")
target_link_libraries(envelope_bench PRIVATE ftcal_common benchmark::benchmark Threads::Threads)
add_test(NAME envelope_bench COMMAND envelope_bench --benchmark_min_time=1)
set_tests_properties(envelope_bench PROPERTIES LABELS bench TIMEOUT 300)
