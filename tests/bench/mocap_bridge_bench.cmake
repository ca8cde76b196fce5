# ftcal-mocap-bridge's class against the QTM emulator at 100 and 1000 frames/s (label bench;
# scripts/test leaves it out). By hand: scripts/netns-exec <build>/tests/bench/mocap_bridge_bench 5
if(TARGET ftcal_mocap_bridge AND TARGET ftcal_qtm_emulator)
  add_executable(mocap_bridge_bench "${CMAKE_CURRENT_LIST_DIR}/mocap_bridge_bench.cc")
  target_link_libraries(mocap_bridge_bench PRIVATE ftcal_mocap_bridge ftcal_qtm_emulator Threads::Threads)
  add_test(NAME mocap_bridge_bench
    COMMAND "${PROJECT_SOURCE_DIR}/scripts/netns-exec" $<TARGET_FILE:mocap_bridge_bench> 10)
  set_tests_properties(mocap_bridge_bench PROPERTIES LABELS bench TIMEOUT 120)
endif()
