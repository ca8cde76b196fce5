# The Dynamixel bridge's command gate (arming, dead-man, limits) with a hand-made clock.
ftcal_add_gtest(command_gate_test unit TIMEOUT 60
  SOURCES "${CMAKE_CURRENT_LIST_DIR}/command_gate_test.cc"
  LIBS ftcal_dynamixel_bridge)
target_compile_definitions(command_gate_test PRIVATE FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
