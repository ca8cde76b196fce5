# The Dynamixel bridge's read-write cycle on the emulated bus (label bench; scripts/test leaves
# it out). By hand: <build>/tests/bench/dynamixel_bridge_bench --duration 5
if(TARGET ftcal_dynamixel_bridge AND TARGET ftcal_dxl_emulator)
  add_executable(dynamixel_bridge_bench "${CMAKE_CURRENT_LIST_DIR}/dynamixel_bridge_bench.cc")
  target_link_libraries(dynamixel_bridge_bench PRIVATE
    ftcal_dynamixel_bridge ftcal_dxl_emulator CLI11::CLI11 Threads::Threads)
  target_compile_definitions(dynamixel_bridge_bench PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  add_test(NAME dynamixel_bridge_bench COMMAND $<TARGET_FILE:dynamixel_bridge_bench> --duration 10)
  set_tests_properties(dynamixel_bridge_bench PROPERTIES LABELS bench TIMEOUT 120)
endif()
