# The scripts a newcomer runs first, as a newcomer on a text terminal would. Included from
# tests/integration/CMakeLists.txt.

# scripts/spy without a display says so in one line (it once died in a Java stack trace).
add_test(NAME scripts_spy_without_a_display_names_the_reason
  COMMAND env -u DISPLAY -u WAYLAND_DISPLAY "${PROJECT_SOURCE_DIR}/scripts/spy")
set_tests_properties(scripts_spy_without_a_display_names_the_reason PROPERTIES
  LABELS integration.fast TIMEOUT 30
  PASS_REGULAR_EXPRESSION "spy: no display \\(DISPLAY and WAYLAND_DISPLAY are unset\\)")

# The README's by-hand package list is scripts/setup's (they had drifted apart).
add_test(NAME scripts_readme_package_list_matches_setup
  COMMAND bash "${CMAKE_CURRENT_LIST_DIR}/readme_packages_test.sh" "${PROJECT_SOURCE_DIR}")
set_tests_properties(scripts_readme_package_list_matches_setup PROPERTIES LABELS integration.fast TIMEOUT 30)

# The C++ is formatted as .clang-format says (issue 15, house rules): scripts/format fixes it.
add_test(NAME clang_format_check COMMAND "${PROJECT_SOURCE_DIR}/scripts/format" --check)
set_tests_properties(clang_format_check PROPERTIES LABELS unit.fast TIMEOUT 120)

# scripts/setup beside a held dpkg lock (unattended upgrades at boot): waits and says so,
# installs once it is released, gives up after FTCAL_DPKG_LOCK_WAIT_S. A lock file and stubs
# of its own: the machine's apt is never touched.
add_test(NAME scripts_setup_waits_for_a_held_dpkg_lock
  COMMAND bash "${CMAKE_CURRENT_LIST_DIR}/setup_lock_test.sh" "${PROJECT_SOURCE_DIR}")
set_tests_properties(scripts_setup_waits_for_a_held_dpkg_lock PROPERTIES
  LABELS integration.fast TIMEOUT 60)

# scripts/compare_calibration.py (what scripts/experiment judges live against offline with)
# against cases computed by hand; needs the generated calibration schema (ftcal_proto_py).
add_test(NAME scripts_compare_calibration_cases
  COMMAND bash "${CMAKE_CURRENT_LIST_DIR}/compare_calibration_test.sh" "${PROJECT_SOURCE_DIR}"
          "${PROJECT_BINARY_DIR}")
set_tests_properties(scripts_compare_calibration_cases PROPERTIES LABELS integration.fast TIMEOUT 60)
