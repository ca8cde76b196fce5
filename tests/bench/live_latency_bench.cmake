# The live pipeline with real processes at 6 x 7 kHz (issue 11, "Speed"): the twin's devices,
# the ATI bridges, the Dynamixel and mocap bridges, the corrector with the true calibration and
# a subscriber; end-to-end latency and loss, and SERVO_CMD -> goal written on the bus (label
# bench; scripts/test leaves it out). It sends multicast: scripts/netns-exec as the
# CROSSCOMPILING_EMULATOR. By hand: scripts/netns-exec <build>/tests/bench/live_latency_bench
if(TARGET ftcal-sim AND TARGET ftcal-ati-bridge AND TARGET ftcal-dynamixel-bridge
   AND TARGET ftcal-mocap-bridge AND TARGET ftcal-corrector)
  add_executable(live_latency_bench "${CMAKE_CURRENT_LIST_DIR}/live_latency_bench.cc")
  target_include_directories(live_latency_bench PRIVATE "${PROJECT_SOURCE_DIR}/tests/integration")
  target_link_libraries(live_latency_bench PRIVATE
    ftcal_sim_live ftcal_twin ftcal_lcmtypes ftcal_child_process ftcal_common libcal
    CLI11::CLI11 Threads::Threads)
  target_compile_definitions(live_latency_bench PRIVATE
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FTCAL_SIM="$<TARGET_FILE:ftcal-sim>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_DYNAMIXEL_BRIDGE="$<TARGET_FILE:ftcal-dynamixel-bridge>"
    FTCAL_MOCAP_BRIDGE="$<TARGET_FILE:ftcal-mocap-bridge>"
    FTCAL_CORRECTOR="$<TARGET_FILE:ftcal-corrector>")
  add_dependencies(live_latency_bench ftcal-sim ftcal-ati-bridge ftcal-dynamixel-bridge
    ftcal-mocap-bridge ftcal-corrector)
  set_target_properties(live_latency_bench PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  add_test(NAME live_latency_bench COMMAND live_latency_bench)
  set_tests_properties(live_latency_bench PROPERTIES LABELS bench TIMEOUT 180)
endif()
