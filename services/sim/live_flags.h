// The flags of `ftcal-sim live` (sim_main.cc): declared on its subcommand, and turned into the
// emulators' fault options.
#pragma once

#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "sim/live.h"

namespace ftcal::sim {

// The flags of `ftcal-sim live`, as given.
struct LiveFlags {
  LiveOptions options;
  std::string truth_dir, ready_path, control_path;
  std::string com = "fixed";
  double duration_s = 0;
  bool no_http = false;
  double ati_drop = 0, ati_duplicate = 0, ati_reorder = 0, ati_corrupt = 0;
  std::vector<std::string> ati_silence, ati_reboot;
  std::vector<std::string> dxl_missing, dxl_silent, dxl_hw_error, dxl_disconnect;
  std::vector<std::string> qtm_untracked, qtm_silent, qtm_no_more_data, qtm_disconnect;
  std::vector<double> qtm_settings_changed;
  std::string start_angles;
  std::string natnet_version = "4.1", natnet_transport;
  std::vector<std::string> natnet_untracked, natnet_silent, natnet_edit_mode, natnet_down;
  std::vector<double> natnet_model_change;
};

void AddLiveFlags(CLI::App* live, LiveFlags* f);
// Turns the flags' text into the emulators' fault options. Throws std::invalid_argument naming
// the flag.
void ResolveLiveFlags(LiveFlags* f);

}  // namespace ftcal::sim
