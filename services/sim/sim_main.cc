// ftcal-sim: the BigAnt twin as a program.
//
//   ftcal-sim log --out SESSION.lcmlog [--truth truth.pbtxt] [--seed N] [--poses 729] ...
// writes a whole experiment (hanging series, standing poses, tripod stances, walk) straight
// into an LCM log as the bridges would publish it (services/sim/log_writer.h), and the truth
// it was made from as a calibration file. No network: nothing is published.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/service.h"
#include "ftcal/config.h"
#include "sim/log_writer.h"
#include "sim/twin.h"

namespace {

// SESSION.lcmlog -> SESSION.truth.pbtxt, in the same directory.
std::string DefaultTruthPath(const std::string& log_path) {
  const auto slash = log_path.rfind('/');
  const auto dot = log_path.rfind('.');
  const bool has_ext = dot != std::string::npos && (slash == std::string::npos || dot > slash + 1);
  return (has_ext ? log_path.substr(0, dot) : log_path) + ".truth.pbtxt";
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App cli{"ftcal-sim: the BigAnt twin (truth model) as a program."};
  cli.require_subcommand(1);
  // --config may come before or after the subcommand.
  cli.fallthrough();
  std::string config_path;
  cli.add_option("--config", config_path,
                 "config file (default: the embedded config/sim.pbtxt)");

  CLI::App* log = cli.add_subcommand(
      "log",
      "Write a whole experiment into an LCM log as the bridges would publish it: FT_<LEG>, "
      "SERVO_STATE, MOCAP_BODY at 100 Hz with per-device timestamp jitter, EXPERIMENT markers "
      "around each scenario (hanging ones with the stated gravity_b); and the truth file.");
  std::string out_path, truth_path, session_id;
  uint64_t seed = 1;
  ftcal::ExperimentPlan plan;
  double noise_scale = 1.0;
  bool physical_com = false, no_mounting_errors = false;
  std::vector<std::string> scenarios = {"hang", "stand", "tripod", "walk"};
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
  log->add_flag("--physical-com", physical_com, "the CoM moves with the legs");
  log->add_flag("--no-mounting-errors", no_mounting_errors, "true mounting equals the nominal");
  log->add_option("--scenarios", scenarios, "comma-separated subset of hang,stand,tripod,walk")
      ->delimiter(',')
      ->check(CLI::IsMember({"hang", "stand", "tripod", "walk"}))
      ->capture_default_str();
  log->add_option("--drift-at-s", plan.drift_at_s,
                  "twin time (s from the first frame) from which the transducer offsets drift");
  log->add_option("--walk-s", plan.walk_s, "walking duration, s")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  log->add_option("--gap-s", plan.gap_s, "silence between scenarios, s")
      ->capture_default_str()
      ->check(CLI::Range(0.05, 3600.0));

  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e);
  }

  try {
    if (config_path.empty()) config_path = ftcal::ServiceApp::DefaultConfigPath();
    const ftcal::config::Config config = ftcal::LoadConfigFile(config_path);
    ftcal::TwinOptions twin_options;
    twin_options.seed = seed;
    twin_options.physical_com = physical_com;
    twin_options.mounting_errors = !no_mounting_errors;
    twin_options.force_noise_n *= noise_scale;
    twin_options.torque_noise_nm *= noise_scale;
    twin_options.attitude_noise_deg *= noise_scale;
    twin_options.marker_noise_m *= noise_scale;
    if (hang_cycles > 0) twin_options.hang_cycles = hang_cycles;
    const ftcal::BigAntTwin twin(config, twin_options);

    plan.hanging = plan.standing = plan.tripod = plan.walking = false;
    for (const std::string& s : scenarios) {
      if (s == "hang") plan.hanging = true;
      if (s == "stand") plan.standing = true;
      if (s == "tripod") plan.tripod = true;
      if (s == "walk") plan.walking = true;
    }
    ftcal::SimLogOptions log_options;
    log_options.seed = seed;
    log_options.session_id = session_id.empty() ? "sim-" + std::to_string(seed) : session_id;
    log_options.mocap_residual_m = twin_options.marker_noise_m;
    if (truth_path.empty()) truth_path = DefaultTruthPath(out_path);

    const auto started = std::chrono::steady_clock::now();
    ftcal::SimLogWriter writer(config, out_path, log_options);
    const double end_s = ftcal::WriteExperiment(twin, plan, &writer);
    twin.WriteTruthFile(truth_path);
    writer.Commit();
    const double wall_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    const ftcal::SimLogCounts& c = writer.counts();
    std::printf(
        "ftcal-sim log: %s (session %s): %.1f s of robot time, %lld events (%lld FT per leg, "
        "%lld servo, %lld mocap, %lld markers) in %.2f s; truth %s\n",
        out_path.c_str(), log_options.session_id.c_str(), end_s,
        static_cast<long long>(c.Total()), static_cast<long long>(c.ft[0]),
        static_cast<long long>(c.servo), static_cast<long long>(c.mocap),
        static_cast<long long>(c.markers), wall_s, truth_path.c_str());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ftcal-sim log: %s\n", e.what());
    return 1;
  }
}
