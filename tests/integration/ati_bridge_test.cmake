# ftcal-ati-bridge against ftcal-emulate-ati (the twin's Net F/T boxes), each test in its own
# network namespace (scripts/netns-exec as the CROSSCOMPILING_EMULATOR, as for the heartbeat
# test). Included from tests/integration/CMakeLists.txt.
if(TARGET ftcal-emulate-ati AND TARGET ftcal-ati-bridge)
  add_executable(ati_bridge_test "${CMAKE_CURRENT_LIST_DIR}/ati_bridge_test.cc")
  target_link_libraries(ati_bridge_test PRIVATE
    ftcal_ati_bridge ftcal_ati_emulator libcal ftcal_lcmtypes ftcal_child_process
    PkgConfig::HTTPLIB GTest::gtest GTest::gtest_main Threads::Threads)
  target_compile_definitions(ati_bridge_test PRIVATE
    FTCAL_EMULATE_ATI="$<TARGET_FILE:ftcal-emulate-ati>"
    FTCAL_ATI_BRIDGE="$<TARGET_FILE:ftcal-ati-bridge>"
    FTCAL_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  add_dependencies(ati_bridge_test ftcal-emulate-ati ftcal-ati-bridge)
  set_target_properties(ati_bridge_test PROPERTIES
    CROSSCOMPILING_EMULATOR "${PROJECT_SOURCE_DIR}/scripts/netns-exec")
  ftcal_gtest_discover(ati_bridge_test KIND integration
    # the in-process ones (no network): fast
    FAST "AtiEmulatorInProcess.*:AtiBridgeInProcess.*"
    PROPERTIES TIMEOUT 60
    DISCOVERY_TIMEOUT 60)
endif()
