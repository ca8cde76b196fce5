// ftcal-sim: the BigAnt twin as a program.
//
//   ftcal-sim log --out SESSION.lcmlog [--truth truth.pbtxt] [--seed N] [--poses 729] ...
// writes a whole experiment (hanging series, standing poses, tripod stances, walk) straight
// into an LCM log as the bridges would publish it (services/sim/log_writer.h), and the truth
// it was made from as a calibration file. No network: nothing is published.
//
//   ftcal-sim live --pty-link PATH [--scenario walk] [--seed N] [--duration S] [faults...]
// runs the twin's devices in real time on this machine (services/sim/live.h): six ATI Net F/T
// boxes (RDT and calibration page) at the config's addresses, the Dynamixel bus on a
// pseudo-terminal linked at PATH, the QTM RT server (or with --mocap natnet OptiTrack Motive's
// NatNet server, --natnet-version, --natnet-transport) at the config's address; the bridges run
// against it unchanged. With --scenario commanded the servos follow the goals a bridge writes
// (first-order, --servo-tau) and the twin's legs follow the servos; --control PATH is then the
// operator's FIFO (hang, lift, stand: services/sim/operator_fifo.h). At the end (SIGINT, SIGTERM or
// --duration) the truth series of every device, with the faults injected, goes to --truth-dir.
#include <signal.h>

#include <chrono>
#include <csignal>
#include <thread>
#include <cmath>
#include <cstdio>
#include <exception>
#include <limits>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "common/service.h"
#include "ftcal/config.h"
#include "ftcal/calibration_io.h"
#include "ftcal/legs.h"
#include "sim/live.h"
#include "sim/live_flags.h"
#include "sim/operator_fifo.h"
#include "sim/log_writer.h"
#include "sim/offset_drift.h"
#include "sim/twin.h"

namespace {

// DIR/NAME.EXT -> DIR/NAME<suffix>: a file that goes with `path`, in the same directory.
std::string BesidePath(const std::string& path, const std::string& suffix) {
  const auto slash = path.rfind('/');
  const auto dot = path.rfind('.');
  const bool has_ext = dot != std::string::npos && (slash == std::string::npos || dot > slash + 1);
  return (has_ext ? path.substr(0, dot) : path) + suffix;
}

// SESSION.lcmlog -> SESSION.truth.pbtxt.
std::string DefaultTruthPath(const std::string& log_path) {
  return BesidePath(log_path, ".truth.pbtxt");
}

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

using ftcal::sim::LiveFlags;

int RunLive(const ftcal::config::Config& config, LiveFlags flags) {
  ftcal::sim::ResolveLiveFlags(&flags);
  struct sigaction sa {};
  sa.sa_handler = OnSignal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);

  flags.options.physical_com = flags.com == "leg-aware";
  ftcal::sim::LiveSim sim(config, flags.options);
  // The parameters a calibration of this run must recover, at once (the devices' series follow
  // at the end).
  if (!flags.truth_dir.empty()) sim.twin().WriteTruthFile(flags.truth_dir + "/truth.pbtxt");
  std::unique_ptr<ftcal::sim::OperatorFifo> control;
  if (!flags.control_path.empty()) {
    if (!sim.commanded()) {
      throw std::invalid_argument(
          "--control needs --scenario commanded (the recorded scenarios "
          "play their own supports)");
    }
    control = std::make_unique<ftcal::sim::OperatorFifo>(flags.control_path);
    control->WriteState(0, "STANDING");
  }
  if (!flags.ready_path.empty()) ftcal::WriteFileAtomic(flags.ready_path, "ready\n");
  const std::string mocap = sim.natnet_command_port() != 0
                                ? "Motive NatNet " + flags.options.natnet_version.ToString() +
                                      " on port " + std::to_string(sim.natnet_command_port())
                                : "QTM on port " + std::to_string(sim.qtm_port());
  std::printf(
      "ftcal-sim live: scenario %s (seed %llu): %d ATI boxes at %d records/s, "
      "Dynamixel bus on %s (linked at %s), %s\n",
      flags.options.scenario.c_str(), static_cast<unsigned long long>(flags.options.seed),
      sim.ati_boxes(), flags.options.ati_rate_hz, sim.pty_path().c_str(),
      flags.options.pty_link.c_str(), mocap.c_str());
  std::fflush(stdout);
  std::int64_t requested = 0, acknowledged = 0;
  std::string support = "STANDING";
  while (g_stop == 0 && !(flags.duration_s > 0 && sim.Now() >= flags.duration_s)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    if (!control) continue;
    for (const std::string& line : control->ReadLines()) {
      std::string why;
      const auto cmd = ftcal::sim::ParseOperatorLine(line, &why);
      if (!cmd) {
        std::fprintf(stderr, "ftcal-sim live: --control %s: %s; ignored\n", control->path().c_str(),
                     why.c_str());
        continue;
      }
      sim.SetSupport(cmd->support, cmd->series);
      ++requested;
      support = ftcal::sim::SupportName(*cmd);
      std::printf("ftcal-sim live: t=%.2f s the operator: %s\n", sim.Now(), support.c_str());
      std::fflush(stdout);
    }
    // Acknowledged once the devices report frames made after it.
    if (requested != acknowledged && sim.supports_applied() >= requested) {
      acknowledged = requested;
      control->WriteState(acknowledged, support);
    }
  }
  const double ran_s = sim.Now();
  sim.Stop();
  if (!flags.truth_dir.empty()) sim.WriteTruth(flags.truth_dir);

  const ftcal::sim::LiveCounts c = sim.Counts();
  std::printf("ftcal-sim live: stopped after %.1f s\n", ran_s);
  for (int k = 0; k < ftcal::kNumLegs; ++k) {
    const auto& a = c.ati[k];
    std::printf(
        "  ati %s: records %llu datagrams %llu starts %llu drop %llu duplicate %llu "
        "reorder %llu corrupt %llu silent %llu reboots %llu http %llu\n",
        std::string(ftcal::kLegNames[k]).c_str(), (unsigned long long)a.records,
        (unsigned long long)a.datagrams, (unsigned long long)a.starts,
        (unsigned long long)a.faults[1], (unsigned long long)a.faults[2],
        (unsigned long long)a.faults[3], (unsigned long long)a.faults[4],
        (unsigned long long)a.faults[5], (unsigned long long)a.reboots,
        (unsigned long long)a.http_requests);
  }
  std::printf(
      "  dynamixel: replies %lld dropped %lld corrupted %lld noise bursts %lld missing "
      "%lld silent %lld hardware errors %lld reopens %lld\n",
      (long long)c.dxl_replies, (long long)c.dxl.dropped, (long long)c.dxl.corrupted,
      (long long)c.dxl.noise_bursts, (long long)c.dxl.missing, (long long)c.dxl.silent,
      (long long)c.dxl.hardware_errors, (long long)c.dxl_reopens);
  std::printf(
      "  qtm: ticks %lld frames_sent %lld corrupt %lld untracked %lld gaps %lld skipped "
      "%lld connections %lld disconnects %lld events %lld\n",
      (long long)c.qtm.ticks, (long long)c.qtm.frames_sent, (long long)c.qtm.frames_corrupt,
      (long long)c.qtm.frames_untracked, (long long)c.qtm.gaps, (long long)c.qtm.frames_skipped,
      (long long)c.qtm.connections, (long long)c.qtm.disconnects, (long long)c.qtm.events_sent);
  if (flags.options.mocap == "natnet") {
    const auto& n = c.natnet;
    std::printf(
        "  natnet: ticks %lld frames_sent %lld corrupt %lld duplicated %lld untracked %lld "
        "gaps %lld skipped %lld connects %lld keepalives %lld descriptions %lld restarts "
        "%lld model_changes %lld expired %lld\n",
        (long long)n.ticks, (long long)n.frames_sent, (long long)n.frames_corrupt,
        (long long)n.frames_duplicated, (long long)n.frames_untracked, (long long)n.gaps,
        (long long)n.frames_skipped, (long long)n.connects, (long long)n.keepalives,
        (long long)n.descriptions_sent, (long long)n.restarts, (long long)n.model_changes,
        (long long)n.clients_expired);
  }
  std::fflush(stdout);
  return 0;
}

}  // namespace

int main(int argc, char** argv) try {
  CLI::App cli{"ftcal-sim: the BigAnt twin (truth model) as a program."};
  cli.require_subcommand(1);
  // --config may come before or after the subcommand.
  cli.fallthrough();
  std::string config_path;
  cli.add_option("--config", config_path, "config file (default: the embedded config/sim.pbtxt)");

  CLI::App* log = cli.add_subcommand(
      "log",
      "Write a whole experiment into an LCM log as the bridges would publish it: FT_<LEG>, "
      "SERVO_STATE, MOCAP_BODY at 100 Hz with per-device timestamp jitter, EXPERIMENT markers "
      "around each scenario (hanging ones with the stated gravity_b); and the truth file.");
  std::string out_path, truth_path, drifted_truth_path, session_id;
  uint64_t seed = 1;
  ftcal::ExperimentPlan plan;
  double noise_scale = 1.0;
  bool physical_com = false, no_mounting_errors = false;
  std::vector<std::string> scenarios = {"tare", "hang", "stand", "tripod", "walk"};
  int hang_cycles = -1;
  log->add_option("--out", out_path, "output LCM log (written atomically)")->required();
  log->add_option("--truth", truth_path,
                  "truth calibration file (default: next to the log, <log stem>.truth.pbtxt)");
  log->add_option("--seed", seed, "twin seed (truth, noise, jitter)")->capture_default_str();
  log->add_option("--session-id", session_id, "EXPERIMENT session id (default: sim-<seed>)");
  log->add_option("--poses", plan.poses, "standing poses (at most 729)")
      ->capture_default_str()
      ->check(CLI::Range(1, 729));
  log->add_option("--tripod-stances", plan.tripod_stances, "tripod stances")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  log->add_option("--hang-cycles", hang_cycles, "leg cycles per hanging series (twin default 10)")
      ->check(CLI::Range(1, 1000));
  log->add_option("--noise-scale", noise_scale, "multiplies every noise sigma of the twin")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1000.0));
  std::string com = "fixed";
  log->add_option("--com", com,
                  "the robot's CoM: fixed (at C, the report's assumption; a rig whose CoM does "
                  "not move) or leg-aware (moves with the legs, which carry nearly half the mass)")
      ->check(CLI::IsMember({"fixed", "leg-aware"}))
      ->capture_default_str();
  log->add_flag("--physical-com", physical_com, "the same as --com leg-aware");
  log->add_flag("--no-mounting-errors", no_mounting_errors, "true mounting equals the nominal");
  log->add_option("--scenarios", scenarios, "comma-separated subset of tare,hang,stand,tripod,walk")
      ->delimiter(',')
      ->check(CLI::IsMember({"tare", "hang", "stand", "tripod", "walk"}))
      ->capture_default_str();
  log->add_option("--drifted-truth", drifted_truth_path,
                  "with --drift-at-s: the truth with the drifted offsets (default: next to the "
                  "truth file, <truth stem>.drifted.pbtxt)");
  log->add_option("--drift-at-s", plan.drift_at_s,
                  "twin time (s from the first frame) from which the transducer offsets drift");
  std::vector<std::string> drift_steps, drift_ramps, drift_warmups;
  std::string drift_csv_path;
  double drift_csv_period_s = 1.0;
  log->add_option("--drift-step", drift_steps,
                  "offsets that jump during the session (a leg knocks something), repeatable: "
                  "LEG:AT_S:fx,fy,fz,tx,ty,tz (N, N*m; LEG a leg name or all; twin time)");
  log->add_option("--drift-ramp", drift_ramps,
                  "offsets that creep linearly, repeatable: LEG:FROM_S:UNTIL_S:fx,fy,fz,tx,ty,tz "
                  "(the whole change, held after UNTIL_S)");
  log->add_option("--drift-warmup", drift_warmups,
                  "offsets that settle after power-up, repeatable: "
                  "LEG:FROM_S:TAU_S:fx,fy,fz,tx,ty,tz (change * (1 - exp(-(t - FROM_S)/TAU_S)))");
  log->add_option("--drift-truth-csv", drift_csv_path,
                  "with --drift-*: the drifted offsets over time, per leg and axis (default: next "
                  "to the log, <log stem>.drift.csv)");
  log->add_option("--drift-truth-period-s", drift_csv_period_s,
                  "row spacing of --drift-truth-csv in twin time (steps get rows at both sides)")
      ->capture_default_str()
      ->check(CLI::Range(0.001, 3600.0));
  log->add_option("--walk-s", plan.walk_s, "walking duration, s")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  log->add_option("--gap-s", plan.gap_s, "silence between scenarios, s")
      ->capture_default_str()
      ->check(CLI::Range(0.05, 3600.0));
  const ftcal::SimClocks lab_clocks = ftcal::SimClocks::Lab();
  bool ideal_clocks = false;
  double clock_ppm_scale = 1.0, stall_every_s = lab_clocks.stall_every_s,
         stall_max_ms = 1e3 * lab_clocks.stall_max_s;
  log->add_flag("--ideal-clocks", ideal_clocks,
                "every device clock exact and no host stalls (the twin before its lab clocks)");
  log->add_option("--clock-ppm-scale", clock_ppm_scale,
                  "multiplies every device clock's rate error (a lab's: tens of ppm, each "
                  "device its own; services/sim/sim_clocks.h)")
      ->capture_default_str()
      ->check(CLI::Range(-10.0, 10.0));
  log->add_option("--stall-every-s", stall_every_s,
                  "mean interval between host stalls, s (0: none)")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1e6));
  log->add_option("--stall-max-ms", stall_max_ms, "longest host stall, ms")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1e3 * ftcal::kMaxStallS));

  CLI::App* live = cli.add_subcommand(
      "live",
      "Run the twin's devices in real time on this machine: six ATI Net F/T boxes (RDT and "
      "calibration page) at the config's addresses, the Dynamixel bus on a pseudo-terminal, the "
      "QTM RT server; faults by flag. The truth series go to --truth-dir at exit.");
  LiveFlags live_flags;
  ftcal::sim::AddLiveFlags(live, &live_flags);

  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e);
  }

  if (live->parsed()) {
    try {
      return RunLive(ftcal::LoadConfigOrDefault(config_path), live_flags);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "ftcal-sim live: %s\n", ftcal::UserText(e, "running the twin").c_str());
      return 1;
    }
  }

  try {
    const ftcal::config::Config config = ftcal::LoadConfigOrDefault(config_path);
    ftcal::TwinOptions twin_options;
    twin_options.seed = seed;
    twin_options.physical_com = physical_com || com == "leg-aware";
    twin_options.mounting_errors = !no_mounting_errors;
    twin_options.force_noise_n *= noise_scale;
    twin_options.torque_noise_nm *= noise_scale;
    twin_options.attitude_noise_deg *= noise_scale;
    twin_options.marker_noise_m *= noise_scale;
    if (hang_cycles > 0) twin_options.hang_cycles = hang_cycles;
    const ftcal::BigAntTwin twin(config, twin_options);

    plan.tare = plan.hanging = plan.standing = plan.tripod = plan.walking = false;
    for (const std::string& s : scenarios) {
      if (s == "tare") plan.tare = true;
      if (s == "hang") plan.hanging = true;
      if (s == "stand") plan.standing = true;
      if (s == "tripod") plan.tripod = true;
      if (s == "walk") plan.walking = true;
    }
    ftcal::SimLogOptions log_options;
    log_options.seed = seed;
    log_options.session_id = session_id.empty() ? "sim-" + std::to_string(seed) : session_id;
    log_options.mocap_residual_m = twin_options.marker_noise_m;
    if (ideal_clocks) {
      log_options.clocks = ftcal::SimClocks::Ideal();
    } else {
      for (auto& c : log_options.clocks.ft) c.rate_ppm *= clock_ppm_scale;
      for (auto& c : log_options.clocks.servo) c.rate_ppm *= clock_ppm_scale;
      log_options.clocks.mocap.rate_ppm *= clock_ppm_scale;
      log_options.clocks.stall_every_s = stall_every_s;
      log_options.clocks.stall_max_s = 1e-3 * stall_max_ms;
    }
    if (truth_path.empty()) truth_path = DefaultTruthPath(out_path);
    const bool drift = std::isfinite(plan.drift_at_s);
    if (!drifted_truth_path.empty() && !drift) {
      throw std::invalid_argument(
          "--drifted-truth needs --drift-at-s (no drift, no drifted truth)");
    }
    // TRUTH.pbtxt -> TRUTH.drifted.pbtxt.
    if (drift && drifted_truth_path.empty()) {
      drifted_truth_path = BesidePath(truth_path, ".drifted.pbtxt");
    }

    ftcal::OffsetDrift moving;
    for (const std::string& v : drift_steps)
      moving.AddFlag(ftcal::OffsetDriftTerm::Shape::kStep, v, "--drift-step");
    for (const std::string& v : drift_ramps)
      moving.AddFlag(ftcal::OffsetDriftTerm::Shape::kRamp, v, "--drift-ramp");
    for (const std::string& v : drift_warmups)
      moving.AddFlag(ftcal::OffsetDriftTerm::Shape::kWarmup, v, "--drift-warmup");
    if (!drift_csv_path.empty() && moving.empty()) {
      throw std::invalid_argument(
          "--drift-truth-csv needs --drift-step, --drift-ramp or "
          "--drift-warmup (no moving offsets, nothing to write)");
    }
    if (!moving.empty()) {
      plan.offset_change = [&moving](int k, double t) { return moving.OffsetChange(k, t); };
      if (drift_csv_path.empty()) drift_csv_path = BesidePath(out_path, ".drift.csv");
    }

    const auto started = std::chrono::steady_clock::now();
    ftcal::SimLogWriter writer(config, out_path, log_options);
    const double end_s = ftcal::WriteExperiment(twin, plan, &writer);
    twin.WriteTruthFile(truth_path);
    if (drift) twin.WriteTruthFile(drifted_truth_path, /*drifted=*/true);
    if (!moving.empty()) {
      const double drift_at = plan.drift_at_s;
      ftcal::WriteFileAtomic(
          drift_csv_path,
          ftcal::DriftTruthCsv(
              moving, twin.Truth(),
              [&twin, drift_at](double t) -> const ftcal::RobotCalibration& {
                return t >= drift_at ? twin.DriftedTruth() : twin.Truth();
              },
              [&writer](double t) { return writer.Utime(t); }, end_s, drift_csv_period_s));
    }
    const std::string digest = writer.Commit();
    const double wall_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    const ftcal::SimLogCounts& c = writer.counts();
    std::printf(
        "ftcal-sim log: %s (session %s): %.1f s of robot time, %lld events (%lld FT per leg, "
        "%lld servo, %lld mocap, %lld markers) in %.2f s; truth %s\n",
        out_path.c_str(), log_options.session_id.c_str(), end_s, static_cast<long long>(c.Total()),
        static_cast<long long>(c.ft[0]), static_cast<long long>(c.servo),
        static_cast<long long>(c.mocap), static_cast<long long>(c.markers), wall_s,
        truth_path.c_str());
    if (!digest.empty()) {
      std::printf("ftcal-sim log: SHA-256 %s handed to the digest cache\n", digest.c_str());
    }
    if (drift)
      std::printf("ftcal-sim log: offsets drift from %.1f s; drifted truth %s\n", plan.drift_at_s,
                  drifted_truth_path.c_str());
    if (!moving.empty())
      std::printf("ftcal-sim log: %zu moving offset terms; the drifted truth over time %s\n",
                  moving.terms().size(), drift_csv_path.c_str());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ftcal-sim log: %s\n",
                 ftcal::UserText(e, "writing the twin's log").c_str());
    return 1;
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-sim");
}
