# The pipeline's processes over the full report-scale experiment (ftcal-sim log, then
# ftcal-pose-segmenter, ftcal-calibrator and ftcal-corrector over it), each timed whole
# (label bench; writes ~3 GB under /tmp and removes it). Run by hand:
#   <build>/tests/bench/pipeline_bench [--poses N] [--dir DIR] [--keep]
add_executable(pipeline_bench "${CMAKE_CURRENT_LIST_DIR}/pipeline_bench.cc")
target_compile_definitions(pipeline_bench PRIVATE
  FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
  FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
  FTCAL_POSE_SEGMENTER="$<TARGET_FILE:ftcal-pose-segmenter>"
  FTCAL_CALIBRATOR="$<TARGET_FILE:ftcal-calibrator>"
  FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>")
add_dependencies(pipeline_bench ftcal-sim ftcal-pose-segmenter ftcal-calibrator ftcal-corrector)
add_test(NAME pipeline_bench COMMAND pipeline_bench)
set_tests_properties(pipeline_bench PROPERTIES LABELS bench TIMEOUT 600)
