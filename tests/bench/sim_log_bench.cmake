# ftcal-sim log: the whole report-scale experiment into an LCM log (label bench).
# Run by hand: <build>/tests/bench/sim_log_bench
add_executable(sim_log_bench "${CMAKE_CURRENT_LIST_DIR}/sim_log_bench.cc")
target_link_libraries(sim_log_bench PRIVATE ftcal_sim_log benchmark::benchmark Threads::Threads)
target_compile_definitions(sim_log_bench PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
add_test(NAME sim_log_bench COMMAND sim_log_bench)
set_tests_properties(sim_log_bench PROPERTIES LABELS bench TIMEOUT 300)
