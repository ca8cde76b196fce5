# ftcal-natnet-bridge's class against the Motive emulator at 240 and 1000 frames/s, unicast and
# multicast (label bench; scripts/test leaves it out).
# By hand: scripts/netns-exec <build>/tests/bench/natnet_bridge_bench 5
if(TARGET ftcal_natnet_bridge AND TARGET ftcal_natnet_emulator)
  add_executable(natnet_bridge_bench "${CMAKE_CURRENT_LIST_DIR}/natnet_bridge_bench.cc")
  target_link_libraries(natnet_bridge_bench PRIVATE ftcal_natnet_bridge ftcal_natnet_emulator Threads::Threads)
  add_test(NAME natnet_bridge_bench
    COMMAND "${PROJECT_SOURCE_DIR}/scripts/netns-exec" $<TARGET_FILE:natnet_bridge_bench> 10)
  set_tests_properties(natnet_bridge_bench PROPERTIES LABELS bench TIMEOUT 180)
endif()
