# Pose segmenter x real time: the --replay path over a log, and the logic alone (label bench).
# Run by hand: <build>/tests/bench/segmenter_bench
add_executable(segmenter_bench "${CMAKE_CURRENT_LIST_DIR}/segmenter_bench.cc")
target_link_libraries(segmenter_bench PRIVATE ftcal_pose_segmenter_stage ftcal_sim_log ftcal_twin benchmark::benchmark Threads::Threads)
target_compile_definitions(segmenter_bench PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
add_test(NAME segmenter_bench COMMAND segmenter_bench --benchmark_min_time=1)
set_tests_properties(segmenter_bench PROPERTIES LABELS bench TIMEOUT 300)
