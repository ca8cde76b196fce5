# ftcal-ati-bridge at full load (label bench; scripts/test leaves it out). Run it by hand with a
# shorter duration: scripts/netns-exec <build>/tests/bench/ati_bridge_bench --duration 5
if(TARGET ftcal-emulate-ati AND TARGET ftcal-ati-bridge)
  add_executable(ati_bridge_bench "${CMAKE_CURRENT_LIST_DIR}/ati_bridge_bench.cc")
  target_link_libraries(ati_bridge_bench PRIVATE ftcal_lcmtypes CLI11::CLI11 Threads::Threads)
  target_compile_definitions(ati_bridge_bench PRIVATE
    FTCAL_EMULATE_ATI="$<TARGET_FILE:ftcal-emulate-ati>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>")
  add_dependencies(ati_bridge_bench ftcal-emulate-ati ftcal-ati-bridge)
  add_test(NAME ati_bridge_bench
    COMMAND "${PROJECT_SOURCE_DIR}/scripts/netns-exec" $<TARGET_FILE:ati_bridge_bench> --duration 60 --wake-probe 5)
  set_tests_properties(ati_bridge_bench PROPERTIES LABELS bench TIMEOUT 180)
endif()
