# The scripts a newcomer runs first, as a newcomer on a text terminal would. Included from
# tests/integration/CMakeLists.txt.

# scripts/spy without a display says so in one line (it once died in a Java stack trace).
add_test(NAME scripts_spy_without_a_display_names_the_reason
  COMMAND env -u DISPLAY -u WAYLAND_DISPLAY "${PROJECT_SOURCE_DIR}/scripts/spy")
set_tests_properties(scripts_spy_without_a_display_names_the_reason PROPERTIES
  LABELS integration TIMEOUT 30
  PASS_REGULAR_EXPRESSION "spy: no display \\(DISPLAY and WAYLAND_DISPLAY are unset\\)")
