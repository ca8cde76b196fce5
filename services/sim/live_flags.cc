#include "sim/live_flags.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <iterator>
#include <stdexcept>

#include "ftcal/legs.h"

namespace ftcal::sim {
namespace {

// "START_S:DURATION_S" -> ticks at `rate_hz`.
ftcal::sim::TickWindow TickWindowFlag(const std::string& text, double rate_hz,
                                      const std::string& flag) {
  const auto parts = ftcal::sim::SplitFlag(text, ':');
  if (parts.size() != 2)
    throw std::invalid_argument(flag + " '" + text + "': want START_S:DURATION_S");
  const double start = ftcal::sim::ParseFlagNumber(parts[0], flag);
  const double duration = ftcal::sim::ParseFlagNumber(parts[1], flag);
  if (start < 0 || duration <= 0)
    throw std::invalid_argument(flag + " '" + text + "': out of range");
  return {std::llround(start * rate_hz), std::max<int64_t>(1, std::llround(duration * rate_hz))};
}

}  // namespace

void AddLiveFlags(CLI::App* live, LiveFlags* f) {
  ftcal::sim::LiveOptions& o = f->options;
  std::vector<std::string> scenarios(std::begin(ftcal::sim::kLiveScenarios),
                                     std::end(ftcal::sim::kLiveScenarios));
  live->add_option("--scenario", o.scenario,
                   "twin scenario, looped; commanded: the legs follow the servos, which follow "
                   "the goals a bridge writes")
      ->check(CLI::IsMember(scenarios))
      ->capture_default_str();
  live->add_option("--seed", o.seed, "twin and fault seed")->capture_default_str();
  live->add_option("--com", f->com,
                   "the twin's robot CoM: fixed (the report's assumption) or leg-aware (moves "
                   "with the legs)")
      ->check(CLI::IsMember({"fixed", "leg-aware"}))
      ->capture_default_str();
  live->add_option("--loop-s", o.loop_s, "scenario length before it repeats, s")
      ->check(CLI::Range(1.0, 3600.0))
      ->capture_default_str();
  live->add_flag_callback(
      "--ideal-clocks", [&o] { o.clocks = ftcal::SimClocks::Ideal(); },
      "every device clock exact (default: a lab's, tens of ppm off, services/sim/sim_clocks.h)");
  live->add_option("--duration", f->duration_s, "seconds to run (default: until SIGINT/SIGTERM)")
      ->check(CLI::NonNegativeNumber);
  live->add_option("--truth-dir", f->truth_dir,
                   "directory for the twin's truth.pbtxt (its calibration parameters, at "
                   "start) and the truth series at exit: ati.csv, dynamixel.csv, qtm.csv or "
                   "natnet.csv")
      ->check(CLI::ExistingDirectory);
  live->add_option("--ready", f->ready_path, "file written once every device is up");
  live->add_option("--control", f->control_path,
                   "commanded: the operator's hands, a FIFO created at this path taking lines "
                   "'hang HANG_X_POS|HANG_X_NEG|HANG_Z_POS|HANG_Z_NEG', 'lift' (upright, feet in "
                   "the air) and 'stand'; each applied line is acknowledged in PATH.state as "
                   "'<lines applied> <support>'");
  live->add_option("--pty-link", o.pty_link,
                   "symlink to the Dynamixel bus' pseudo-terminal (the bridge's config device)")
      ->required();
  // ATI.
  live->add_option("--ati-rate", o.ati_rate_hz, "RDT output rate of every box, records/s")
      ->check(CLI::Range(1, 7000))
      ->capture_default_str();
  live->add_option("--ati-http-port", o.ati_http_port,
                   "calibration page port of every box (default: the config's)")
      ->check(CLI::Range(1, 65535));
  live->add_flag("--ati-no-http", f->no_http, "serve no calibration page");
  live->add_option("--ati-drop", f->ati_drop,
                   "probability a datagram (a record in real-time mode) is not sent")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--ati-duplicate", f->ati_duplicate, "probability a datagram is sent twice")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--ati-reorder", f->ati_reorder,
                   "probability a datagram is sent after the next one")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--ati-corrupt", f->ati_corrupt,
                   "probability a datagram is sent with a wrong length")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--ati-silence", f->ati_silence,
                   "LEG:AT_S:DURATION_S  LEG's network down a while (repeatable)");
  live->add_option("--ati-reboot", f->ati_reboot, "LEG:AT_S  LEG's box reboots (repeatable)");
  // Dynamixel.
  live->add_option("--dxl-drop", o.dxl_rates.drop_reply, "probability a reply is dropped")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--dxl-corrupt", o.dxl_rates.corrupt_crc,
                   "probability a reply's CRC is corrupted")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--dxl-noise", o.dxl_rates.noise, "probability of noise bytes before a reply")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--dxl-missing", f->dxl_missing, "ID:START_S:END_S  servo ID does not answer");
  live->add_option("--dxl-silent", f->dxl_silent, "START_S:END_S  no servo answers");
  live->add_option("--dxl-hw-error", f->dxl_hw_error,
                   "ID:T_S[:BITS]  servo ID raises hardware error BITS (default 32, overload)");
  live->add_option("--dxl-disconnect", f->dxl_disconnect,
                   "START_S:END_S  the port vanishes and comes back as a new pty");
  live->add_option("--servo-tau", o.servo_time_constant_s,
                   "commanded: the servos' first-order time constant toward their goal, s")
      ->check(CLI::Range(0.001, 60.0))
      ->capture_default_str();
  live->add_option("--start-angles", f->start_angles,
                   "commanded: A:B:C:D:E:F  shaft angles at the start (legs HL ML FL HR MR FR), "
                   "rad (default: all 0)");
  // QTM.
  live->add_option("--qtm-port", o.qtm_port, "TCP port (default: the config's; 0: any)")
      ->check(CLI::Range(0, 65535));
  live->add_option("--qtm-gap", o.qtm_faults.gap_probability,
                   "probability per frame of skipped frame numbers")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--qtm-corrupt", o.qtm_faults.corrupt_probability,
                   "probability per frame of a corrupt data packet")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--qtm-marker-dropout", o.qtm_faults.marker_dropout_probability,
                   "probability per frame and marker of an extra dropout")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--qtm-untracked", f->qtm_untracked, "START_S:DURATION_S  body not tracked");
  live->add_option("--qtm-silent", f->qtm_silent, "START_S:DURATION_S  nothing sent");
  live->add_option("--qtm-no-more-data", f->qtm_no_more_data,
                   "START_S:DURATION_S  measurement stopped; frames restart at 1 after");
  live->add_option("--qtm-disconnect", f->qtm_disconnect,
                   "START_S:DURATION_S  QTM shuts down: clients closed, refused meanwhile");
  live->add_option("--qtm-settings-changed", f->qtm_settings_changed,
                   "T_S  Camera Settings Changed event");
  // Motion capture: QTM, or OptiTrack Motive (NatNet) from the config's mocap.natnet section.
  live->add_option("--mocap", o.mocap, "motion capture to serve: qtm or natnet")
      ->check(CLI::IsMember({"qtm", "natnet"}))
      ->capture_default_str();
  live->add_option("--natnet-version", f->natnet_version, "Motive's NatNet bitstream")
      ->check(CLI::IsMember({"3.0", "3.1", "4.0", "4.1", "4.2"}))
      ->capture_default_str();
  live->add_option("--natnet-transport", f->natnet_transport,
                   "multicast or unicast (default: the config's mocap.natnet.multicast)")
      ->check(CLI::IsMember({"multicast", "unicast"}));
  live->add_option("--natnet-rate", o.natnet_rate_hz, "Motive's frame rate, Hz")
      ->check(CLI::Range(1.0, 2000.0))
      ->capture_default_str();
  live->add_option("--natnet-gap", o.natnet_faults.gap_probability,
                   "probability per frame of skipped frame numbers")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--natnet-duplicate", o.natnet_faults.duplicate_probability,
                   "probability per frame that it is sent twice")
      ->check(CLI::Range(0.0, 1.0));
  live->add_option("--natnet-corrupt", o.natnet_faults.corrupt_probability,
                   "probability per frame of a corrupt frame (framing intact)")
      ->check(CLI::Range(0.0, 1.0));
  live->add_flag("--natnet-mid-exposure-zero", o.natnet_faults.mid_exposure_zero,
                 "send mid-exposure ticks 0 (USB cameras, playback)");
  live->add_option("--natnet-untracked", f->natnet_untracked,
                   "START_S:DURATION_S  body not tracked");
  live->add_option("--natnet-silent", f->natnet_silent,
                   "START_S:DURATION_S  Motive up and answering, no frames");
  live->add_option("--natnet-edit-mode", f->natnet_edit_mode,
                   "START_S:DURATION_S  frames flagged edit mode (4.0+)");
  live->add_option(
      "--natnet-down", f->natnet_down,
      "START_S:DURATION_S  Motive gone; restarts afterwards (frames, clock, ids anew)");
  live->add_option("--natnet-model-change", f->natnet_model_change,
                   "T_S  model list changed: the rigid bodies swap order and ids");
}

// Turns the flags' text into the emulators' fault options.
void ResolveLiveFlags(LiveFlags* f) {
  using ftcal::sim::ParseFlagNumber;
  using ftcal::sim::SplitFlag;
  ftcal::sim::LiveOptions& o = f->options;
  if (f->no_http) o.ati_http_port = 0;
  for (int k = 0; k < ftcal::kNumLegs; ++k) {
    auto& a = o.ati_faults[k];
    a.seed = o.seed * 1000 + static_cast<std::uint64_t>(k);
    a.drop = f->ati_drop;
    a.duplicate = f->ati_duplicate;
    a.reorder = f->ati_reorder;
    a.corrupt = f->ati_corrupt;
  }
  if (f->ati_drop + f->ati_duplicate + f->ati_reorder + f->ati_corrupt > 1.0) {
    throw std::invalid_argument("--ati-drop + --ati-duplicate + --ati-reorder + --ati-corrupt > 1");
  }
  for (const std::string& s : f->ati_silence) {
    const auto p = SplitFlag(s, ':');
    const auto k = p.size() == 3 ? ftcal::LegIndex(p[0]) : std::nullopt;
    if (!k) throw std::invalid_argument("--ati-silence '" + s + "': want LEG:AT_S:DURATION_S");
    o.ati_faults[*k].events.push_back({ftcal::sim::AtiScheduledEvent::Kind::kSilence,
                                       ParseFlagNumber(p[1], "--ati-silence"),
                                       ParseFlagNumber(p[2], "--ati-silence")});
  }
  for (const std::string& s : f->ati_reboot) {
    const auto p = SplitFlag(s, ':');
    const auto k = p.size() == 2 ? ftcal::LegIndex(p[0]) : std::nullopt;
    if (!k) throw std::invalid_argument("--ati-reboot '" + s + "': want LEG:AT_S");
    o.ati_faults[*k].events.push_back(
        {ftcal::sim::AtiScheduledEvent::Kind::kReboot, ParseFlagNumber(p[1], "--ati-reboot"), 0});
  }
  o.dxl_rates.seed = o.seed;
  auto servo_id = [](const std::string& text, const std::string& flag) {
    const double id = ParseFlagNumber(text, flag);
    if (id < 0 || id > 252 || id != std::floor(id)) {
      throw std::invalid_argument(flag + ": servo id '" + text + "' is not 0-252");
    }
    return static_cast<std::uint8_t>(id);
  };
  for (const std::string& s : f->dxl_missing) {
    const auto p = SplitFlag(s, ':');
    if (p.size() != 3)
      throw std::invalid_argument("--dxl-missing '" + s + "': want ID:START_S:END_S");
    o.dxl_events.push_back(
        {ftcal::sim::DxlFaultKind::kMissingServo, ParseFlagNumber(p[1], "--dxl-missing"),
         ParseFlagNumber(p[2], "--dxl-missing"), servo_id(p[0], "--dxl-missing"), 0});
  }
  for (const std::string& s : f->dxl_silent) {
    const auto p = SplitFlag(s, ':');
    if (p.size() != 2) throw std::invalid_argument("--dxl-silent '" + s + "': want START_S:END_S");
    o.dxl_events.push_back({ftcal::sim::DxlFaultKind::kSilent,
                            ParseFlagNumber(p[0], "--dxl-silent"),
                            ParseFlagNumber(p[1], "--dxl-silent"), 0, 0});
  }
  for (const std::string& s : f->dxl_hw_error) {
    const auto p = SplitFlag(s, ':');
    if (p.size() != 2 && p.size() != 3) {
      throw std::invalid_argument("--dxl-hw-error '" + s + "': want ID:T_S[:BITS]");
    }
    const double bits = p.size() == 3 ? ParseFlagNumber(p[2], "--dxl-hw-error") : 32;
    if (bits < 1 || bits > 255)
      throw std::invalid_argument("--dxl-hw-error '" + s + "': BITS 1-255");
    o.dxl_events.push_back({ftcal::sim::DxlFaultKind::kHardwareError,
                            ParseFlagNumber(p[1], "--dxl-hw-error"), 0,
                            servo_id(p[0], "--dxl-hw-error"), static_cast<std::uint8_t>(bits)});
  }
  for (const std::string& s : f->dxl_disconnect) {
    const auto p = SplitFlag(s, ':');
    if (p.size() != 2)
      throw std::invalid_argument("--dxl-disconnect '" + s + "': want START_S:END_S");
    o.dxl_disconnects.push_back(
        {ParseFlagNumber(p[0], "--dxl-disconnect"), ParseFlagNumber(p[1], "--dxl-disconnect")});
  }
  if (!f->start_angles.empty()) {
    if (o.scenario != ftcal::sim::kCommandedScenario) {
      throw std::invalid_argument("--start-angles needs --scenario commanded");
    }
    const auto p = SplitFlag(f->start_angles, ':');
    if (p.size() != 6)
      throw std::invalid_argument("--start-angles '" + f->start_angles +
                                  "': want six angles A:B:C:D:E:F");
    for (int k = 0; k < ftcal::kNumLegs; ++k)
      o.commanded_start_rad[k] = ParseFlagNumber(p[k], "--start-angles");
  }
  auto& q = o.qtm_faults;
  q.seed = o.seed;
  const double r = o.qtm_rate_hz;
  for (const auto& w : f->qtm_untracked)
    q.untracked.push_back(TickWindowFlag(w, r, "--qtm-untracked"));
  for (const auto& w : f->qtm_silent) q.silent.push_back(TickWindowFlag(w, r, "--qtm-silent"));
  for (const auto& w : f->qtm_no_more_data) {
    q.no_more_data.push_back(TickWindowFlag(w, r, "--qtm-no-more-data"));
  }
  for (const auto& w : f->qtm_disconnect) {
    q.disconnected.push_back(TickWindowFlag(w, r, "--qtm-disconnect"));
  }
  for (double t : f->qtm_settings_changed) {
    if (!(t >= 0)) throw std::invalid_argument("--qtm-settings-changed: negative time");
    q.settings_changed.push_back(std::llround(t * r));
  }
  const auto v = ftcal::natnet::ParseVersion(f->natnet_version);
  if (!v) throw std::invalid_argument("--natnet-version '" + f->natnet_version + "'");
  o.natnet_version = *v;
  if (!f->natnet_transport.empty()) o.natnet_multicast = f->natnet_transport == "multicast";
  auto& n = o.natnet_faults;
  n.seed = o.seed;
  const double nr = o.natnet_rate_hz;
  auto window = [nr](const std::string& w, const char* flag) {
    const auto t = TickWindowFlag(w, nr, flag);
    return ftcal::sim::NatNetWindow{t.first_tick, t.num_ticks};
  };
  for (const auto& w : f->natnet_untracked) n.untracked.push_back(window(w, "--natnet-untracked"));
  for (const auto& w : f->natnet_silent) n.silent.push_back(window(w, "--natnet-silent"));
  for (const auto& w : f->natnet_edit_mode) n.edit_mode.push_back(window(w, "--natnet-edit-mode"));
  for (const auto& w : f->natnet_down) n.down.push_back(window(w, "--natnet-down"));
  for (double t : f->natnet_model_change) {
    if (!(t >= 0)) throw std::invalid_argument("--natnet-model-change: negative time");
    n.model_changes.push_back(std::llround(t * nr));
  }
}

}  // namespace ftcal::sim
