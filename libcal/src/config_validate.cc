// The run in the config: the stages (segmenter, calibrator, corrector), channels, experiment
// plans, the sequencer, authentication, launch groups; and Validate, which walks every section
// of a parsed file and the rules between sections.
#include <arpa/inet.h>

#include <cctype>
#include <cmath>
#include <cstring>
#include <map>
#include <regex>
#include <set>
#include <tuple>
#include <string>
#include <vector>

#include "config_internal.h"

namespace ftcal::config_detail {

void ValidateSegmenter(const Node& node, const config::Segmenter& s) {
  node.Positive("sample_rate_hz", s.sample_rate_hz());
  if (s.savgol_order() < 1) {
    node.Error("savgol_order", "must be >= 1, got " + std::to_string(s.savgol_order()));
  }
  if (s.savgol_window() % 2 == 0) {
    node.Error("savgol_window", "must be odd, got " + std::to_string(s.savgol_window()));
  } else if (s.savgol_window() <= s.savgol_order()) {
    node.Error("savgol_window", "must be greater than savgol_order (" +
                                    std::to_string(s.savgol_order()) + "), got " +
                                    std::to_string(s.savgol_window()));
  }
  if (std::isfinite(s.sample_rate_hz()) && s.sample_rate_hz() > 0 &&
      s.savgol_window() / s.sample_rate_hz() > kMaxSavgolWindowS) {
    node.Error("savgol_window", "spans " + FormatNumber(s.savgol_window() / s.sample_rate_hz()) +
                                    " s at sample_rate_hz " + FormatNumber(s.sample_rate_hz()) +
                                    "; at most " + FormatNumber(kMaxSavgolWindowS) + " s, got " +
                                    std::to_string(s.savgol_window()));
  }
  node.Positive("max_force_rate_n_s", s.max_force_rate_n_s());
  node.Positive("min_steady_s", s.min_steady_s());
}

void ValidateCalibrator(const Node& node, const config::Calibrator& c) {
  if (c.phase_bins() < 8) {
    node.Error("phase_bins", "must be >= 8, got " + std::to_string(c.phase_bins()));
  }
  node.Positive("smoother_transition_var", c.smoother_transition_var());
  node.Positive("smoother_observation_var", c.smoother_observation_var());
  if (c.k_weights_size() != 0 && c.k_weights_size() != 6) {
    node.Error("k_weights", "needs 0 or 6 entries [fx fy fz tx ty tz], got " +
                                std::to_string(c.k_weights_size()));
  } else {
    for (int i = 0; i < c.k_weights_size(); ++i) {
      if (node.Finite("k_weights", c.k_weights(i), i) && !(c.k_weights(i) > 0.0)) {
        node.Error("k_weights", "must be > 0, got " + FormatNumber(c.k_weights(i)), i);
      }
    }
  }
  if (c.solver() == config::STEP2_SOLVER_UNSPECIFIED) {
    node.Error("solver", "must be JOINT or ALTERNATING");
  }
  node.Positive("alternating_tolerance", c.alternating_tolerance());
  if (c.robust_loss() == config::ROBUST_LOSS_UNSPECIFIED) {
    node.Error("robust_loss", "must be NONE, HUBER or CAUCHY");
  }
  node.Positive("robust_loss_scale", c.robust_loss_scale());
  if (c.cv_folds() < 2) {
    node.Error("cv_folds", "must be >= 2, got " + std::to_string(c.cv_folds()));
  }
  node.Positive("mass_check_sigmas", c.mass_check_sigmas());
  if (node.Finite("mass_tolerance_kg", c.mass_tolerance_kg()) && c.mass_tolerance_kg() < 0.0) {
    node.Error("mass_tolerance_kg", "must be >= 0, got " + FormatNumber(c.mass_tolerance_kg()));
  }
  node.Positive("residual_floor_warn_factor", c.residual_floor_warn_factor());
  if (node.Finite("max_gap_share", c.max_gap_share()) &&
      (c.max_gap_share() < 0.0 || c.max_gap_share() > 1.0)) {
    node.Error("max_gap_share",
               "must be a share in [0, 1], got " + FormatNumber(c.max_gap_share()));
  }
  if (c.profile() == config::CALIBRATION_PROFILE_UNSPECIFIED) {
    node.Error("profile", "must be FTCAL or REPORT");
  }
  if (c.com_model() == config::ROBOT_COM_MODEL_UNSPECIFIED) {
    node.Error("com_model", "must be COM_BY_DATA, COM_FIXED or COM_LEG_AWARE");
  }
  if (c.min_poses() < 1) {
    node.Error("min_poses", "must be >= 1, got " + std::to_string(c.min_poses()));
  }
  if (node.Finite("unloaded_leg_min_angle_deg", c.unloaded_leg_min_angle_deg()) &&
      !(c.unloaded_leg_min_angle_deg() > 0.0 && c.unloaded_leg_min_angle_deg() < 180.0)) {
    node.Error("unloaded_leg_min_angle_deg",
               "must be in (0, 180), got " + FormatNumber(c.unloaded_leg_min_angle_deg()));
  }
}

void ValidateCorrector(const Node& node, const config::Corrector& c) {
  node.Positive("max_servo_age_s", c.max_servo_age_s());
  node.Positive("max_mocap_age_s", c.max_mocap_age_s());
  node.Positive("max_ft_age_s", c.max_ft_age_s());
}

void ValidateChannels(const Node& node, const config::Channels& c) {
  const pb::Descriptor* d = c.GetDescriptor();
  const pb::Reflection* r = c.GetReflection();
  // Every field is a channel name; reflection keeps this in step with the schema. Two
  // purposes on one channel make a process read its own output (the corrector once ate its
  // CONTACT_WRENCH): every name, and every FT_<LEG> the prefix makes, must be distinct.
  std::vector<std::pair<std::string, std::string>> names;  // channel, field
  for (int i = 0; i < d->field_count(); ++i) {
    const pb::FieldDescriptor* f = d->field(i);
    if (f->type() != pb::FieldDescriptor::TYPE_STRING) continue;
    const std::string value = r->GetString(c, f);
    if (value.empty()) {
      node.Error(f->name(), "channel name must not be empty");
      continue;
    }
    if (f->name() == "ft_prefix") {
      for (std::string_view leg : kLegNames) {
        names.emplace_back(value + std::string(leg),
                           "ft_prefix (" + value + std::string(leg) + ")");
      }
    } else {
      names.emplace_back(value, f->name());
    }
  }
  for (std::size_t i = 0; i < names.size(); ++i) {
    for (std::size_t j = 0; j < i; ++j) {
      if (names[i].first == names[j].first) {
        const std::string field = names[i].second.substr(0, names[i].second.find(' '));
        node.Error(field, "channel '" + names[i].first + "' is also channels." + names[j].second +
                              ": each channel carries one thing");
      }
    }
  }
}

// A number that must lie in [lo, hi] (inclusive), with both named in the message.
void InRange(const Node& node, std::string_view name, double v, double lo, double hi,
             std::string_view unit = "") {
  if (node.Finite(name, v) && !(v >= lo && v <= hi)) {
    node.Error(name, "must be in [" + FormatNumber(lo) + ", " + FormatNumber(hi) + "]" +
                         std::string(unit) + ", got " + FormatNumber(v));
  }
}

void ValidatePlanPhase(const Node& node, const config::PlanPhase& p) {
  switch (p.kind()) {
    case config::PHASE_TARE:
      InRange(node, "tare_s", p.tare_s(), 0.1, 600.0, " s");
      break;
    case config::PHASE_HANG:
      if (p.orientation() == config::HANG_ORIENTATION_UNSPECIFIED) {
        node.Error("orientation",
                   "a hanging phase needs HANG_X_POS, HANG_X_NEG, HANG_Z_POS or "
                   "HANG_Z_NEG");
      }
      if (p.cycles() < 1 || p.cycles() > 1000) {
        node.Error("cycles", "must be in [1, 1000], got " + std::to_string(p.cycles()));
      }
      InRange(node, "cycle_s", p.cycle_s(), 1.0, 3600.0, " s");
      break;
    case config::PHASE_STANDING_GRID:
      if (p.grid_angles_deg_size() > 5) {
        node.Error("grid_angles_deg",
                   "at most 5 angles (5^6 poses), got " + std::to_string(p.grid_angles_deg_size()));
      }
      for (int i = 0; i < p.grid_angles_deg_size(); ++i) {
        if (node.Finite("grid_angles_deg", p.grid_angles_deg(i), i) &&
            std::abs(p.grid_angles_deg(i)) > 90.0) {
          node.Error("grid_angles_deg",
                     "a standing angle must be within +-90 deg of straight down, got " +
                         FormatNumber(p.grid_angles_deg(i)),
                     i);
        }
      }
      if (p.pose_stride() < 1) node.Error("pose_stride", "must be >= 1");
      InRange(node, "dwell_s", p.dwell_s(), 0.5, 600.0, " s");
      break;
    case config::PHASE_TRIPOD_STANCES:
      if (p.stances() < 1 || p.stances() > 1000) {
        node.Error("stances", "must be in [1, 1000], got " + std::to_string(p.stances()));
      }
      InRange(node, "lift_angle_deg", p.lift_angle_deg(), 90.0, 180.0, " deg");
      InRange(node, "dwell_s", p.dwell_s(), 0.5, 600.0, " s");
      break;
    case config::PHASE_TRIPOD_WALK:
      InRange(node, "clock_hz", p.clock_hz(), 0.001, 2.0, " Hz");
      if (node.Finite("duty", p.duty()) && !(p.duty() > 0.0 && p.duty() < 1.0)) {
        node.Error("duty", "must be in (0, 1), got " + FormatNumber(p.duty()));
      }
      InRange(node, "sweep_deg", p.sweep_deg(), 1.0, 180.0, " deg");
      InRange(node, "turn_sweep_delta_deg", p.turn_sweep_delta_deg(), -90.0, 90.0, " deg");
      InRange(node, "walk_s", p.walk_s(), 1.0, 36000.0, " s");
      break;
    default:
      node.Error("kind",
                 "must be PHASE_TARE, PHASE_HANG, PHASE_STANDING_GRID, "
                 "PHASE_TRIPOD_STANCES or PHASE_TRIPOD_WALK");
  }
}

// The port of a udpm URL ("udpm://GROUP:PORT?opts"), or -1.
int UdpmPort(const std::string& url) {
  const std::regex udpm("udpm://[^:/?]+:([0-9]+)([?].*)?");
  std::smatch m;
  return std::regex_match(url, m, udpm) ? std::stoi(m[1]) : -1;
}

void ValidateRoutes(const Node& root, const config::Config& config) {
  std::set<int> ports;
  const int main_port = UdpmPort(config.lcm_url());
  if (main_port >= 0) ports.insert(main_port);
  for (int i = 0; i < config.lcm_route_size(); ++i) {
    const config::LcmRoute& r = config.lcm_route(i);
    const Node node = root.Child("lcm_route", i, r);
    if (r.channels().empty()) {
      node.Error("channels", "must name the channels the route carries (a regular expression)");
    } else {
      try {
        std::regex check(r.channels());
      } catch (const std::regex_error& e) {
        node.Error("channels", "'" + r.channels() + "' is not a regular expression: " + e.what());
      }
    }
    const int port = UdpmPort(r.url());
    if (port < 0 || main_port < 0) {
      node.Error("url", "'" + r.url() + "' with lcm_url '" + config.lcm_url() +
                            "': routes need udpm:// URLs of the form udpm://GROUP:PORT[?...]");
    } else if (!ports.insert(port).second) {
      // Linux delivers a multicast datagram to every socket bound to its port that joined any
      // group (IP_MULTICAST_ALL): a port shared is a route that filters nothing.
      node.Error("url", "'" + r.url() + "' uses port " + std::to_string(port) +
                            ", as lcm_url or another route does: each route needs a port of its "
                            "own, or the kernel delivers both to every reader");
    }
  }
}

void ValidatePlans(const Node& root, const config::Config& config) {
  for (int i = 0; i < config.plan_size(); ++i) {
    const config::ExperimentPlan& plan = config.plan(i);
    const Node node = root.Child("plan", i, plan);
    if (plan.name().empty()) node.Missing("name");
    for (int j = 0; j < i; ++j) {
      if (config.plan(j).name() == plan.name() && !plan.name().empty()) {
        node.Error("name", "duplicate plan name '" + plan.name() + "' (already " +
                               root.FieldPath("plan", j) + ")");
      }
    }
    if (plan.phase_size() == 0) node.SelfError("a plan needs at least one phase");
    for (int k = 0; k < plan.phase_size(); ++k) {
      ValidatePlanPhase(node.Child("phase", k, plan.phase(k)), plan.phase(k));
    }
  }
}

void ValidateSequencer(const Node& node, const config::Sequencer& s) {
  InRange(node, "command_rate_hz", s.command_rate_hz(), 1.0, 1000.0, " Hz");
  InRange(node, "max_velocity_rad_s", s.max_velocity_rad_s(), 0.01, 20.0, " rad/s");
  InRange(node, "joint_limit_margin_rad", s.joint_limit_margin_rad(), 0.0, 1.0, " rad");
  InRange(node, "max_input_age_s", s.max_input_age_s(), 0.01, 10.0, " s");
  InRange(node, "airborne_max_support_n", s.airborne_max_support_n(), 0.1, 1000.0, " N");
  InRange(node, "standing_min_weight_share", s.standing_min_weight_share(), 0.0, 2.0);
  InRange(node, "standing_max_weight_share", s.standing_max_weight_share(), 0.0, 5.0);
  if (std::isfinite(s.standing_min_weight_share()) &&
      std::isfinite(s.standing_max_weight_share()) &&
      !(s.standing_min_weight_share() < s.standing_max_weight_share())) {
    node.Error("standing_max_weight_share", "must be greater than standing_min_weight_share (" +
                                                FormatNumber(s.standing_min_weight_share()) +
                                                "), got " +
                                                FormatNumber(s.standing_max_weight_share()));
  }
  InRange(node, "max_tilt_deg", s.max_tilt_deg(), 0.1, 90.0, " deg");
  InRange(node, "arrival_tolerance_rad", s.arrival_tolerance_rad(), 0.001, 1.0, " rad");
  InRange(node, "arrival_timeout_s", s.arrival_timeout_s(), 0.1, 600.0, " s");
  if (s.safe_action() == config::SAFE_ACTION_UNSPECIFIED) {
    node.Error("safe_action", "must be SAFE_HOLD or SAFE_TORQUE_OFF");
  }
}

void ValidateAuth(const Node& node, const config::Auth& auth, const config::Channels& channels) {
  const std::set<std::string> signed_channels = {channels.servo_cmd(), channels.experiment(),
                                                 channels.calibration(),
                                                 channels.sequencer_control()};
  std::map<std::string, int> keys_per_channel;
  std::set<std::string> names, keys;
  for (int i = 0; i < auth.trusted_key_size(); ++i) {
    const config::TrustedKey& key = auth.trusted_key(i);
    const Node key_node = node.Child("trusted_key", i, key);
    if (key.name().empty()) key_node.Missing("name");
    if (!names.insert(key.name()).second) {
      key_node.Error("name", "duplicate trusted key name '" + key.name() + "'");
    }
    const std::string& hex = key.public_key_hex();
    if (hex.size() != 64 || hex.find_first_not_of("0123456789abcdefABCDEF") != std::string::npos) {
      key_node.Error("public_key_hex",
                     "must be 64 hex digits (an Ed25519 public key, as ftcal-keygen prints it)");
    } else if (!keys.insert(hex).second) {
      key_node.Error("public_key_hex", "the same key is listed twice");
    }
    if (key.channel_size() == 0) key_node.Error("channel", "name at least one signed channel");
    for (const std::string& channel : key.channel()) {
      if (signed_channels.count(channel) == 0) {
        key_node.Error("channel", "'" + channel + "' is not a signed channel (" +
                                      channels.servo_cmd() + ", " + channels.experiment() + ", " +
                                      channels.calibration() + ", " + channels.sequencer_control() +
                                      ")");
      } else if (++keys_per_channel[channel] == 3) {
        key_node.Error("channel", "more than two trusted keys for '" + channel +
                                      "' (two at once, for rotation)");
      }
    }
  }
  if (node.Finite("servo_cmd_window_s", auth.servo_cmd_window_s()) &&
      !(auth.servo_cmd_window_s() > 0 && auth.servo_cmd_window_s() <= 10)) {
    node.Error("servo_cmd_window_s",
               "must be in (0, 10] s, got " + FormatNumber(auth.servo_cmd_window_s()));
  }
  for (const auto& [name, value, max] :
       {std::tuple<const char*, double, double>{"control_window_s", auth.control_window_s(), 60},
        {"experiment_window_s", auth.experiment_window_s(), 60},
        {"calibration_window_s", auth.calibration_window_s(), 3600},
        {"max_clock_ahead_s", auth.max_clock_ahead_s(), 60}}) {
    if (node.Finite(name, value) && !(value > 0 && value <= max)) {
      node.Error(name, "must be in (0, " + FormatNumber(max) + "] s, got " + FormatNumber(value));
    }
  }
}

// ---- Launch groups ----

bool IsProgramName(const std::string& name) {
  // supervisor's section names and systemd unit names both accept these; ':' would split a
  // supervisor "group:name".
  if (name.empty() || name.size() > 64) return false;
  return name.find_first_not_of("abcdefghijklmnopqrstuvwxyz0123456789_-") == std::string::npos;
}

void ValidateRestart(const Node& node, const config::RestartPolicy& r) {
  if (node.Finite("startsecs_s", r.startsecs_s()) &&
      !(r.startsecs_s() == 0 || (r.startsecs_s() >= 2 && r.startsecs_s() <= 3600))) {
    // supervisord may notice an exit a second late: below 2 s a process that dies at once can
    // pass as started, and is then restarted forever instead of ending FATAL.
    node.Error("startsecs_s",
               "must be 0 (no start check) or in 2..3600 s, got " + FormatNumber(r.startsecs_s()));
  }
  if (r.startretries() > 100) {
    node.Error("startretries",
               "must be at most 100 (a process that keeps dying should end "
               "FATAL), got " +
                   std::to_string(r.startretries()));
  }
  static const std::set<std::string> kSignals = {"TERM", "INT",  "QUIT", "KILL",
                                                 "HUP",  "USR1", "USR2"};
  if (kSignals.count(r.stopsignal()) == 0) {
    node.Error("stopsignal",
               "must be one of TERM INT QUIT KILL HUP USR1 USR2, got '" + r.stopsignal() + "'");
  }
  if (node.Finite("stopwaitsecs_s", r.stopwaitsecs_s()) &&
      !(r.stopwaitsecs_s() > 0 && r.stopwaitsecs_s() <= 3600)) {
    node.Error("stopwaitsecs_s", "must be in (0, 3600] s, got " + FormatNumber(r.stopwaitsecs_s()));
  }
  if (node.Finite("watchdog_s", r.watchdog_s()) &&
      !(r.watchdog_s() == 0 || (r.watchdog_s() >= 2 && r.watchdog_s() <= 3600))) {
    // The heartbeat pings the watchdog once a second: below 2 s one late tick kills it.
    node.Error("watchdog_s", "must be 0 (none) or in 2..3600 s (the heartbeat is 1 Hz), got " +
                                 FormatNumber(r.watchdog_s()));
  }
}

void ValidateGate(const Node& node, const config::HealthGate& g) {
  if (g.kind() == config::HealthGate::KIND_UNSPECIFIED) {
    node.Missing("kind");
    return;
  }
  if (g.kind() == config::HealthGate::RATE || g.kind() == config::HealthGate::FRESH) {
    const std::string& ch = g.channel();
    if (ch.empty() || ch == "*") {
      node.Error("channel", "name a channel (or a prefix ending in '*')");
    } else if (ch.find('*') != std::string::npos && ch.find('*') != ch.size() - 1) {
      node.Error("channel", "'*' may only end a prefix, got '" + ch + "'");
    }
  } else if (g.has_channel()) {
    node.Error("channel", "a STATUS_RUNNING gate reads the process's own heartbeat: no channel");
  }
  if (g.kind() == config::HealthGate::RATE) {
    if (!g.has_rate_hz()) {
      node.Missing("rate_hz");
    } else if (node.Finite("rate_hz", g.rate_hz()) && !(g.rate_hz() > 0 && g.rate_hz() <= 1e5)) {
      node.Error("rate_hz", "must be in (0, 1e5] Hz, got " + FormatNumber(g.rate_hz()));
    }
    if (node.Finite("min_fraction", g.min_fraction()) &&
        !(g.min_fraction() > 0 && g.min_fraction() <= 1)) {
      node.Error("min_fraction", "must be in (0, 1], got " + FormatNumber(g.min_fraction()));
    }
    if (node.Finite("window_s", g.window_s()) && !(g.window_s() >= 0.1 && g.window_s() <= 60)) {
      node.Error("window_s", "must be in 0.1..60 s, got " + FormatNumber(g.window_s()));
    }
  }
  if (g.kind() == config::HealthGate::FRESH && node.Finite("max_age_s", g.max_age_s()) &&
      !(g.max_age_s() > 0 && g.max_age_s() <= 60)) {
    node.Error("max_age_s", "must be in (0, 60] s, got " + FormatNumber(g.max_age_s()));
  }
  if (node.Finite("within_s", g.within_s()) && !(g.within_s() > 0 && g.within_s() <= 600)) {
    node.Error("within_s", "must be in (0, 600] s, got " + FormatNumber(g.within_s()));
  }
  if (g.kind() == config::HealthGate::RATE && g.window_s() > g.within_s()) {
    node.Error("window_s", "the rate window (" + FormatNumber(g.window_s()) +
                               " s) must fit in within_s (" + FormatNumber(g.within_s()) + " s)");
  }
}

void ValidateLaunch(const Node& node, const config::Launch& launch) {
  std::set<std::string> hosts;
  for (int h = 0; h < launch.host_size(); ++h) {
    const config::LaunchHost& host = launch.host(h);
    const Node host_node = node.Child("host", h, host);
    if (!IsProgramName(host.name())) {
      host_node.Error("name", "must be 1..64 of [a-z0-9_-], got '" + host.name() + "'");
    } else if (!hosts.insert(host.name()).second) {
      host_node.Error("name", "duplicate host '" + host.name() + "'");
    }
    if (host.address().empty()) host_node.Missing("address");
    for (int i = 0; i < host.shell_size(); ++i) {
      if (host.shell(i).empty()) host_node.Error("shell", "an empty word", i);
    }
  }
  std::set<std::string> groups;
  for (int gi = 0; gi < launch.group_size(); ++gi) {
    const config::LaunchGroup& group = launch.group(gi);
    const Node group_node = node.Child("group", gi, group);
    if (!IsProgramName(group.name())) {
      group_node.Error("name", "must be 1..64 of [a-z0-9_-], got '" + group.name() + "'");
    } else if (!groups.insert(group.name()).second) {
      group_node.Error("name", "duplicate group '" + group.name() + "'");
    }
    if (group.process_size() == 0) group_node.Error("process", "a group needs a process");
    std::map<std::string, int> index;
    for (int p = 0; p < group.process_size(); ++p) {
      const config::LaunchProcess& proc = group.process(p);
      const Node proc_node = group_node.Child("process", p, proc);
      if (!IsProgramName(proc.name())) {
        proc_node.Error("name", "must be 1..64 of [a-z0-9_-], got '" + proc.name() + "'");
      } else if (!index.emplace(proc.name(), p).second) {
        proc_node.Error("name",
                        "duplicate process '" + proc.name() + "' in group '" + group.name() + "'");
      }
      if (proc.host().empty()) {
        proc_node.Missing("host");
      } else if (hosts.count(proc.host()) == 0) {
        proc_node.Error("host", "no host '" + proc.host() + "' in launch.host");
      }
      if (proc.command().empty()) proc_node.Missing("command");
      for (int i = 0; i < proc.env_size(); ++i) {
        const std::string& e = proc.env(i);
        const auto eq = e.find('=');
        if (eq == 0 || eq == std::string::npos || std::isdigit(static_cast<unsigned char>(e[0])) ||
            e.substr(0, eq).find_first_not_of("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"
                                              "0123456789_") != std::string::npos) {
          proc_node.Error("env", "must be NAME=VALUE, got '" + e + "'", i);
        }
      }
      ValidateRestart(proc_node.Child("restart", proc.restart()), proc.restart());
      for (int k = 0; k < proc.gate_size(); ++k) {
        ValidateGate(proc_node.Child("gate", k, proc.gate(k)), proc.gate(k));
      }
    }
    // Dependencies name processes of the group, and admit an order (no cycle).
    for (int p = 0; p < group.process_size(); ++p) {
      const config::LaunchProcess& proc = group.process(p);
      const Node proc_node = group_node.Child("process", p, proc);
      for (int i = 0; i < proc.after_size(); ++i) {
        if (index.count(proc.after(i)) == 0) {
          proc_node.Error("after",
                          "no process '" + proc.after(i) + "' in group '" + group.name() + "'", i);
        } else if (proc.after(i) == proc.name()) {
          proc_node.Error("after", "a process cannot wait for itself", i);
        }
      }
    }
    std::vector<int> state(group.process_size(), 0);  // 0 new, 1 on the path, 2 done
    std::function<bool(int)> acyclic = [&](int p) {
      if (state[p] == 1) return false;
      if (state[p] == 2) return true;
      state[p] = 1;
      for (const std::string& dep : group.process(p).after()) {
        const auto it = index.find(dep);
        if (it != index.end() && it->second != p && !acyclic(it->second)) return false;
      }
      state[p] = 2;
      return true;
    };
    for (int p = 0; p < group.process_size(); ++p) {
      if (!acyclic(p)) {
        group_node.Child("process", p, group.process(p))
            .Error("after",
                   "the dependencies form a cycle through '" + group.process(p).name() + "'");
        break;
      }
    }
  }
  if (launch.process_state_channel().empty())
    node.Error("process_state_channel", "must not be empty");
}

void Validate(const config::Config& config, const ParseInfoTree* tree, const std::string& source,
              std::vector<std::string>* errors) {
  const Node root(config, tree, "", Location{1, 1}, &source, errors);
  if (!config.has_robot()) {
    root.Missing("robot");
  } else {
    ValidateRobot(root.Child("robot", config.robot()), config.robot());
  }
  if (config.has_mocap()) ValidateMocap(root.Child("mocap", config.mocap()), config.mocap());
  if (config.has_dynamixel()) {
    ValidateDynamixel(root.Child("dynamixel", config.dynamixel()), config.dynamixel());
  }
  // Sections with only defaults are validated too: the defaults are values we run with.
  ValidateSegmenter(root.Child("segmenter", config.segmenter()), config.segmenter());
  ValidateCalibrator(root.Child("calibrator", config.calibrator()), config.calibrator());
  ValidateCorrector(root.Child("corrector", config.corrector()), config.corrector());
  ValidateDrift(root.Child("drift", config.drift()), config.drift());
  ValidateChannels(root.Child("channels", config.channels()), config.channels());
  if (config.lcm_url().empty()) root.Error("lcm_url", "must not be empty");
  ValidateRoutes(root, config);
  ValidatePlans(root, config);
  ValidateSequencer(root.Child("sequencer", config.sequencer()), config.sequencer());
  if (config.has_dynamixel() &&
      config.sequencer().max_velocity_rad_s() > config.dynamixel().max_velocity_rad_s()) {
    // The bridge rate-limits every goal: a plan timed faster would lag and be called stuck.
    root.Child("sequencer", config.sequencer())
        .Error("max_velocity_rad_s", "must not exceed dynamixel.max_velocity_rad_s (" +
                                         FormatNumber(config.dynamixel().max_velocity_rad_s()) +
                                         " rad/s, the bridge's own limit), got " +
                                         FormatNumber(config.sequencer().max_velocity_rad_s()));
  }
  ValidateAuth(root.Child("auth", config.auth()), config.auth(), config.channels());
  {
    const Node health = root.Child("health", config.health());
    const double share = config.health().max_drop_share();
    if (health.Finite("max_drop_share", share) && !(share > 0.0 && share <= 1.0)) {
      health.Error("max_drop_share", "must be in (0, 1], got " + FormatNumber(share));
    }
    if (config.health().min_inputs() < 1) {
      health.Error("min_inputs",
                   "must be >= 1, got " + std::to_string(config.health().min_inputs()));
    }
  }
  // The bridge remembers no SERVO_CMD across a restart; it ignores commands for start_quiet_s
  // instead, and that is only enough while every command it took before the restart is stale by
  // then, i.e. older than the window.
  if (config.has_dynamixel() && std::isfinite(config.auth().servo_cmd_window_s()) &&
      std::isfinite(config.dynamixel().start_quiet_s()) &&
      !(config.auth().servo_cmd_window_s() < config.dynamixel().start_quiet_s())) {
    root.Child("auth", config.auth())
        .Error("servo_cmd_window_s",
               "must be below dynamixel.start_quiet_s (" +
                   FormatNumber(config.dynamixel().start_quiet_s()) +
                   " s): a command taken before a bridge restart would still be fresh when the "
                   "restarted bridge starts listening, got " +
                   FormatNumber(config.auth().servo_cmd_window_s()));
  }
  if (config.has_launch()) ValidateLaunch(root.Child("launch", config.launch()), config.launch());
  if (config.has_dynamixel() && config.has_robot() &&
      config.dynamixel().operating_mode() == config::EXTENDED_POSITION_MODE) {
    // Extended Position mode takes goals within +-1,048,575 counts (+-256 turns,
    // docs/device-protocols.md §2.7): a limit beyond them could not be commanded.
    constexpr double kMaxExtendedCount = 1048575.0;
    const Node robot = root.Child("robot", config.robot());
    for (int i = 0; i < config.robot().leg_size(); ++i) {
      const config::Servo& servo = config.robot().leg(i).servo();
      const Node node = robot.Child("leg", i, config.robot().leg(i)).Child("servo", servo);
      for (const auto& [name, angle] :
           {std::pair<const char*, double>{"min_angle_rad", servo.min_angle_rad()},
            {"max_angle_rad", servo.max_angle_rad()}}) {
        const double count = servo.zero_count() + servo.direction() * angle * 4096.0 / (2 * M_PI);
        if (std::isfinite(count) && std::abs(count) > kMaxExtendedCount) {
          node.Error(name, "is encoder count " + FormatNumber(count) +
                               ", outside the +-1048575 of Extended Position mode (dynamixel."
                               "operating_mode), got " +
                               FormatNumber(angle));
        }
      }
    }
  }
}

}  // namespace ftcal::config_detail
