// ftcal-calibrator: the whole method (steps 1 and 2) on recorded logs or live, the calibration
// file (atomically, with provenance), a summary table and optionally the HTML report.
// Exit codes: 0 done, 2 input refused (message names what), 1 I/O or other failure.
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <exception>
#include <filesystem>
#include <future>
#include <map>
#include <iostream>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <spdlog/cfg/env.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <google/protobuf/text_format.h>
#include <spdlog/spdlog.h>

#include "calibrator/calibrator.h"
#include "common/batch_memory.h"
#include "common/lcm_bus.h"
#include "common/log_replay_bus.h"
#include "common/default_config.h"
#include "common/exit_codes.h"
#include "common/heartbeat.h"
#include "common/service.h"
#include "common/service_stats.h"
#include "common/shutdown.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "ftcal/digest_cache.h"

#ifndef FTCAL_PYTHON_DIR
#define FTCAL_PYTHON_DIR "build/python"
#endif
#ifndef FTCAL_REPORT_SCRIPT
#define FTCAL_REPORT_SCRIPT "scripts/report"
#endif

namespace {

using ftcal::CalibratorInputError;

struct Args {
  std::vector<std::string> logs;
  std::string out;
  std::string report_dir;
  std::string truth;
  std::string reestimate_base;
  bool partial = false;
  std::string config_path;
  std::string lcm_url;
  std::string log_level;
  std::string profile;
  bool accept_mass_mismatch = false;
  bool accept_leg_map_mismatch = false;
  bool allow_gaps = false;
  std::string command_line;
  std::string signing_key;
};

// Runs scripts/report; returns its exit status (its messages go to our stderr).
int RunReport(const std::string& cal, const std::string& residuals, const std::string& walking,
              const Args& args) {
  std::vector<std::string> argv = {FTCAL_REPORT_SCRIPT, cal, residuals, args.report_dir};
  if (!args.truth.empty()) {
    argv.push_back("--truth");
    argv.push_back(args.truth);
  }
  if (!walking.empty()) {
    argv.push_back("--walking");
    argv.push_back(walking);
  }
  std::vector<char*> cargv;
  cargv.reserve(argv.size() + 1);
  for (auto& a : argv) cargv.push_back(a.data());
  cargv.push_back(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) return 1;
  if (pid == 0) {
    // The schemas of this build, unless the caller chose others.
    ::setenv("FTCAL_PYTHON_DIR", FTCAL_PYTHON_DIR, /*overwrite=*/0);
    ::execv(cargv[0], cargv.data());
    std::perror(cargv[0]);
    ::_exit(127);
  }
  int status = 0;
  if (::waitpid(pid, &status, 0) < 0) return 1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 1;
}

// Prints the summary and runs the report (the files are written).
int Report(const ftcal::CalibrationRun& run, const Args& args, const std::string& walking = "") {
  std::cout << ftcal::SummaryTable(run) << std::flush;
  if (args.report_dir.empty()) return 0;
  spdlog::info("writing the report into {}", args.report_dir);
  const int rc = RunReport(args.out, ftcal::ResidualsPathFor(args.out), walking, args);
  if (rc != 0) {
    spdlog::error("report failed (exit {}); the calibration file is written", rc);
    return ftcal::kExitDeviceIo;
  }
  return 0;
}

// The order in which to read the --logs: those with no transducer sample among their first
// events (the segmenter's poses log: SYNC_SAMPLE and STEADY_POSE) first, then the rest, each
// group in the order given. A poses log read before its session spares the collector aligning
// and segmenting the STANDING phase again (its STEADY_POSE events carry the within-pose
// scatter), and the calibration does not depend on the order; so the user need not know that.
std::vector<std::string> ReadingOrder(const std::vector<std::string>& logs,
                                      const std::string& ft_prefix) {
  // A session log's transducers publish hundreds of samples a second from the start; a poses
  // log has none at all.
  constexpr int kEventsLooked = 256;
  std::vector<std::string> first, rest;
  for (const std::string& path : logs) {
    bool samples = false;
    for (const std::string& channel : ftcal::LogChannelsAtStart(path, kEventsLooked)) {
      samples = samples || channel.compare(0, ft_prefix.size(), ft_prefix) == 0;
    }
    (samples ? rest : first).push_back(path);
  }
  std::vector<std::string> order = first;
  order.insert(order.end(), rest.begin(), rest.end());
  if (order != logs) {
    spdlog::info(
        "reading {} before {}: no {} samples at its start (a poses log), so the "
        "STANDING phase need not be segmented again",
        first.back(), rest.front(), ft_prefix);
  }
  return order;
}

// Reads every --log into the collector, in ReadingOrder(). Returns false when reading was
// interrupted (a signal); throws CalibratorInputError for a missing, damaged or truncated log.
// Each log's SHA-256 (provenance) goes into *sha256 by path: from `cache` when the file is
// unchanged since it was hashed, else from the bytes read, on the read-ahead thread (and then
// into the cache).
bool ReadLogs(ftcal::CalibrationCollector& collector, const ftcal::config::Config& config,
              const Args& args, const ftcal::DigestCache& cache,
              std::map<std::string, std::string>* sha256) {
  auto log = spdlog::default_logger();
  const std::string scratch = (std::filesystem::temp_directory_path() /
                               ("ftcal-calibrator-" + std::to_string(::getpid()) + ".lcmlog"))
                                  .string();
  // Every input before any work: a typo in the last of several logs is refused at once, and
  // so is an output directory that does not exist (found only after minutes of reading).
  {
    const std::filesystem::path parent = std::filesystem::path(args.out).parent_path();
    std::error_code ec;
    if (!parent.empty() && !std::filesystem::is_directory(parent, ec)) {
      throw CalibratorInputError("--out '" + args.out + "': directory '" + parent.string() +
                                 "' does not exist");
    }
  }
  for (const std::string& path : args.logs) {
    std::error_code ec;
    if (!std::filesystem::is_regular_file(path, ec)) {
      throw CalibratorInputError("input log '" + path + "' does not exist or is not a file");
    }
  }
  for (const std::string& path : ReadingOrder(args.logs, config.channels().ft_prefix())) {
    ftcal::ServiceStats stats(log);
    // Nothing is published: the replay output stays uncommitted and is removed.
    ftcal::LogReplayBus bus(path, scratch, stats);
    const std::optional<ftcal::FileKey> key = ftcal::FileKeyOf(path);
    const std::optional<std::string> cached = cache.Lookup(path);
    ftcal::Sha256 sha;
    if (cached) {
      (*sha256)[path] = *cached;
      spdlog::info("{}: SHA-256 from the digest cache in {} (the file is unchanged since)", path,
                   cache.dir());
    } else {
      bus.ConsumeInput([&sha](const uint8_t* data, size_t size) { sha.Update(data, size); });
    }
    // The spans a whole reading of this file found it need not read again: only while the
    // file is the one its digest is cached for (no hash to feed), under the same rules.
    std::optional<ftcal::logindex::LogIndex> index;
    if (cached) {
      if (const std::optional<std::string> text = cache.LookupNote("spans", path)) {
        index.emplace();
        if (!google::protobuf::TextFormat::ParseFromString(*text, &*index) ||
            index->rules() != collector.SpanIndexRules()) {
          index.reset();
        }
      }
    }
    collector.SetSpanIndex(index ? &*index : nullptr);
    collector.Attach(bus);
    int64_t first_utime = -1;
    bus.Run(
        [&] {
          if (first_utime < 0) first_utime = bus.NowUtime();
          spdlog::info("{}: {:.0f} s of log read, {} events", path,
                       1e-6 * static_cast<double>(bus.NowUtime() - first_utime), bus.events_read());
        },
        60'000'000);
    if (!bus.finished()) {
      spdlog::error("{}: reading interrupted; no calibration written", path);
      return false;
    }
    // A damaged log may have lost any part of a series: refuse rather than calibrate on the
    // rest. Each kind names the byte span or the message skipped.
    int64_t undecodable = 0;
    std::string kinds;
    for (const auto& [kind, n] : stats.kinds()) {
      kinds += "; " + kind + " x" + std::to_string(n);
      if (kind.rfind("undecodable", 0) == 0) undecodable += n;
    }
    if (stats.errors() > 0 || undecodable > 0) {
      throw CalibratorInputError(
          "log '" + path + "' is damaged or truncated: " + std::to_string(stats.errors()) +
          " unreadable spans, " + std::to_string(undecodable) + " undecodable messages, " +
          std::to_string(bus.events_read()) + " events read (" + stats.last_error() + kinds + ")");
    }
    if (stats.drops() > 0) {
      spdlog::warn("{}: {} inputs dropped{}", path, stats.drops(), kinds);
    }
    spdlog::info("{}: {} events", path, bus.events_read());
    collector.SetSpanIndex(nullptr);
    if (!cached && bus.InputConsumedWhole()) {
      const std::string hex = sha.HexDigest();
      (*sha256)[path] = hex;
      if (key) cache.Store(path, *key, hex);
    }
    // Read whole: what it found to skip another time goes beside the digest.
    const ftcal::logindex::LogIndex found = collector.TakeSpanIndex();
    if (key && bus.skipped_bytes() == 0 && found.span_size() > 0) {
      std::string text;
      if (google::protobuf::TextFormat::PrintToString(found, &text) &&
          cache.StoreNote("spans", path, *key, text)) {
        spdlog::debug("{}: span index stored in the digest cache", path);
      }
    }
  }
  collector.Flush();
  return true;
}

ftcal::CalibratorOptions OptionsOf(const Args& args,
                                   const std::map<std::string, std::string>& hashes = {}) {
  ftcal::CalibratorOptions options;
  options.log_paths = args.logs;
  // A log the reading did not hash whole (none, as a rule) is hashed from its file.
  options.sha256 = [hashes](const std::string& path) {
    const auto it = hashes.find(path);
    return it != hashes.end() ? it->second : ftcal::Sha256File(path);
  };
  options.config_path = args.config_path;
  options.command_line = args.command_line;
  options.accept_mass_mismatch = args.accept_mass_mismatch;
  options.accept_leg_map_mismatch = args.accept_leg_map_mismatch;
  options.allow_gaps = args.allow_gaps;
  return options;
}

int Offline(const ftcal::config::Config& config, const Args& args) {
  ftcal::CalibrationCollector collector(config);
  collector.SetSkipSegmentingLoggedSessions(true);
  collector.SetCollectTripodStances(false);  // they serve --reestimate-offsets only
  std::map<std::string, std::string> hashes;
  ftcal::CalibratorOptions options = OptionsOf(args);
  ftcal::EarlyCalibration early(collector, config, options);
  if (!ReadLogs(collector, config, args, ftcal::DigestCache::FromEnvironment(), &hashes)) {
    return ftcal::kExitDeviceIo;
  }
  options = OptionsOf(args, hashes);  // the same Calibrate() options, with the digests read
  ftcal::CalibrationRun run = ftcal::RunCalibration(collector, config, options, &early);
  std::optional<ftcal::RobotCalibration> truth;
  if (!args.truth.empty()) {
    try {
      truth = ftcal::CalibrationFromProto(ftcal::ReadCalibrationFile(args.truth), config.robot());
    } catch (const std::exception& e) {
      throw CalibratorInputError("--truth '" + args.truth +
                                 "': " + ftcal::UserText(e, "reading the truth file"));
    }
  }
  // The walking file (2 M numbers for the report's walk) is formatted on its own thread while
  // the calibration file and the residuals are: it reads the calibration, the rest writes only
  // the calibration proto. It is written after them, so that a calibration that could not be
  // written leaves no walking file beside it.
  std::future<std::string> walking_csv;
  if (!collector.walking_samples().empty()) {
    walking_csv = std::async(std::launch::async, [&] {
      return ftcal::WalkingCsv(collector.walking_samples(), run, truth ? &*truth : nullptr);
    });
  }
  ftcal::AddResultRmse(collector.walking_samples(), truth ? &*truth : nullptr, &run);
  ftcal::WriteCalibrationOutputs(run, args.out);
  spdlog::info("wrote {} and {}", args.out, ftcal::ResidualsPathFor(args.out));
  std::string walking;
  if (walking_csv.valid()) {
    walking = ftcal::WalkingPathFor(args.out);
    ftcal::WriteFileAtomic(walking, walking_csv.get());
    spdlog::info("wrote {} (the walking session corrected, for the report)", walking);
  }
  return Report(run, args, walking);
}

// Offset drift: the base calibration's offsets re-estimated from the logs, all else kept.
int ReestimateOffsets(const ftcal::config::Config& config, const Args& args) {
  ftcal::CalibrationCollector collector(config);
  collector.SetSkipSegmentingLoggedSessions(true);
  std::map<std::string, std::string> hashes;
  if (!ReadLogs(collector, config, args, ftcal::DigestCache::FromEnvironment(), &hashes)) {
    return ftcal::kExitDeviceIo;
  }
  const ftcal::OffsetReestimationRun run = ftcal::RunOffsetReestimation(
      collector, config, args.reestimate_base, args.partial, OptionsOf(args, hashes));
  ftcal::WriteCalibrationFile(run.proto, args.out);
  spdlog::info("wrote {} (version {})", args.out, run.proto.version());
  std::cout << ftcal::OffsetSummaryTable(run) << std::flush;
  return 0;
}

// Live: collect by markers; calibrate when a STANDING phase stops (LiveCalibrator).
int Live(const ftcal::config::Config& config, const Args& args) {
  ftcal::ServiceStats stats(spdlog::default_logger());
  const std::string url = args.lcm_url.empty() ? config.lcm_url() : args.lcm_url;
  ftcal::LcmBus bus(url, stats);
  // What it accepted on EXPERIMENT, kept across restarts (common/seen_store.h): a restarted
  // calibrator refuses the markers it took before.
  if (const std::string dir = ftcal::auth::SeenStore::DefaultDir(); !dir.empty()) {
    try {
      bus.SetSeenStore(std::make_shared<ftcal::auth::SeenStore>(dir + "/ftcal-calibrator.seen"));
    } catch (const std::exception& e) {
      spdlog::critical("{}", ftcal::UserText(e, "reading the state file"));
      return ftcal::kExitDeviceIo;
    }
  } else {
    spdlog::warn(
        "no state directory (FTCAL_STATE_DIR, HOME unset): what this process accepts "
        "on EXPERIMENT is forgotten when it restarts");
  }
  ftcal::CalibratorOptions options = OptionsOf(args);
  int rc = 0;
  ftcal::LiveCalibrator live(config, bus, args.out, options,
                             [&](const ftcal::CalibrationRun& run) { rc = Report(run, args); });
  // CALIBRATION is a signed channel: without a key, receivers refuse what this publishes
  // unless their config allows unsigned (the loopback twin's does).
  std::optional<ftcal::auth::Signer> signer;
  if (!args.signing_key.empty()) {
    try {
      signer.emplace(ftcal::auth::Signer::FromSeedFile(args.signing_key));
    } catch (const std::exception& e) {
      spdlog::critical("--signing-key: {}", ftcal::UserText(e, "reading the signing key"));
      return ftcal::kExitConfig;
    }
    live.SetSigner(&*signer);
  } else {
    spdlog::warn("no --signing-key: {} goes out unsigned (refused unless auth.allow_unsigned)",
                 config.channels().calibration());
  }
  ftcal::InstallShutdownHandlers();
  spdlog::info("listening on {} for EXPERIMENT markers", url);
  // The 1 Hz FTCAL_STATUS every process publishes (ServiceApp's, which this mode does not use:
  // its --out is required and it has no --replay). A refused calibration is its last error.
  const ftcal::ProcessIdentity identity = ftcal::ThisProcess("ftcal-calibrator");
  const auto started = std::chrono::steady_clock::now();
  int64_t next_status_utime = 0, refusals_reported = 0;
  auto publish_status = [&](int8_t state) {
    if (live.refused() > refusals_reported) {
      refusals_reported = live.refused();
      stats.Error("calibration refused", live.last_refusal());
    }
    stats.Counter("calibrations") = live.made();
    stats.Counter("version") = live.version();
    stats.Counter("markers") = live.markers();
    stats.Counter("refused") = live.refused();
    const double uptime_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    bus.Publish(config.channels().status(),
                ftcal::MakeServiceStatus(identity, state, uptime_s, stats, bus.NowUtime()),
                /*count=*/false);
  };
  bus.Run(
      [&] {
        live.Tick();
        if (bus.NowUtime() >= next_status_utime) {
          publish_status(ftcal::service_status_t::RUNNING);
          next_status_utime = bus.NowUtime() + 1'000'000;
        }
      },
      100'000);
  publish_status(ftcal::service_status_t::STOPPING);
  if (const auto& store = bus.seen_store()) {
    const std::string error = store->Flush();
    if (!error.empty()) spdlog::error("state not saved: {}", error);
  }
  return rc;
}

}  // namespace

int main(int argc, char** argv) try {
  Args args;
  for (int i = 0; i < argc; ++i) args.command_line += (i ? " " : "") + std::string(argv[i]);
  CLI::App cli(
      "Calibrates the six transducers (docs/method.md steps 1 and 2). Offline (--log): reads the "
      "logs in order, collects the four hanging series (EXPERIMENT HANG_* start..stop) and the "
      "steady standing poses (STEADY_POSE events, else segmented over STANDING), runs the "
      "method and writes --out atomically with provenance, plus <out>.residuals.csv. Live (no "
      "--log): collects the same on LCM, calibrates when STANDING stops, publishes CALIBRATION "
      "(calibration_t) and writes --out. Exit 2 when the input is refused.",
      "ftcal-calibrator");
  cli.add_option("--log", args.logs, "input log(s) (lcm-logger format), read in the order given");
  cli.add_option("--out", args.out, "calibration file to write (text format)")->required();
  cli.add_option("--report", args.report_dir, "also write the HTML report into this directory");
  cli.add_option("--truth", args.truth, "a truth calibration file (the twin's) for the report")
      ->check(CLI::ExistingFile);
  cli.add_option("--reestimate-offsets", args.reestimate_base,
                 "offset drift (docs/method.md): re-estimate only the offsets of this calibration "
                 "from --log (standing poses and tripod stances), everything else kept; refused "
                 "when the data leaves an offset component undetermined")
      ->check(CLI::ExistingFile);
  cli.add_flag("--partial", args.partial,
               "with --reestimate-offsets: keep the old value of the components the data does "
               "not determine (listed) instead of refusing");
  cli.add_option(
      "--config", args.config_path,
      "configuration file; default: the " + std::string(ftcal::kDefaultConfigName) + " built in");
  cli.add_option("--lcm-url", args.lcm_url, "live: LCM URL; overrides the config's lcm_url");
  ftcal::AddLogLevelOption(cli, &args.log_level);
  cli.add_option("--profile", args.profile,
                 "ftcal (the model the data supports) or report (the report's procedure: "
                 "first-order hanging rotations, fixed CoM, no gravity prior); overrides the "
                 "config's calibrator.profile")
      ->check(CLI::IsMember({"ftcal", "report"}));
  cli.add_flag("--accept-mass-mismatch", args.accept_mass_mismatch,
               "calibrate even when the configured total mass disagrees with the mass the data "
               "implies (recorded in the calibration file as a warning); refused otherwise");
  cli.add_flag("--accept-leg-map-mismatch", args.accept_leg_map_mismatch,
               "calibrate even when a transducer's standing data follows another leg's shaft "
               "far better than its own (two legs' servo ids or transducer addresses swapped in "
               "the config; recorded in the calibration file as a warning); refused otherwise");
  cli.add_flag("--allow-gaps", args.allow_gaps,
               "calibrate even when a phase the calibration uses lost more than "
               "calibrator.max_gap_share of a transducer's records (by RDT sequence number; "
               "recorded in the calibration file as a warning); refused otherwise");
  cli.add_option("--signing-key", args.signing_key,
                 "live: sign CALIBRATION with the Ed25519 seed in this file (owner-only; "
                 "ftcal-keygen makes one)");
  cli.footer(ftcal::ExitCodeTable());
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;

  // Offline, the calibrator is a batch run: read, calibrate, write, exit (common/batch_memory.h).
  // Live, it keeps malloc's defaults.
  ftcal::BatchMemory::Granted memory;
  if (!args.logs.empty()) memory = ftcal::BatchMemory::UseForProcess();
  spdlog::set_default_logger(spdlog::stderr_color_mt("ftcal-calibrator"));
  spdlog::cfg::load_env_levels();
  if (!args.log_level.empty()) spdlog::set_level(spdlog::level::from_str(args.log_level));
  if (!args.logs.empty()) {
    spdlog::debug("batch memory: malloc thresholds {}, {} MiB of heap for huge pages",
                  memory.thresholds ? "set" : "refused", memory.huge_bytes >> 20);
  }
  ftcal::config::Config config;
  try {
    config = ftcal::LoadConfigOrDefault(args.config_path);
  } catch (const ftcal::ConfigError& e) {
    spdlog::critical("{}", e.what());
    return ftcal::kExitConfig;
  }
  if (!args.profile.empty()) {
    config.mutable_calibrator()->set_profile(args.profile == "report" ? ftcal::config::REPORT
                                                                      : ftcal::config::FTCAL);
  }
  if (!args.reestimate_base.empty() && (args.logs.empty() || !args.report_dir.empty())) {
    spdlog::critical("--reestimate-offsets needs --log (the drift session) and takes no --report");
    return ftcal::kExitUsage;
  }
  if (args.partial && args.reestimate_base.empty()) {
    spdlog::critical("--partial goes with --reestimate-offsets");
    return ftcal::kExitUsage;
  }
  try {
    if (!args.reestimate_base.empty()) return ReestimateOffsets(config, args);
    return args.logs.empty() ? Live(config, args) : Offline(config, args);
  } catch (const CalibratorInputError& e) {
    spdlog::critical("refused: {}", e.what());
    return ftcal::kExitRefused;
  } catch (const std::invalid_argument& e) {
    spdlog::critical("refused: {}", e.what());
    return ftcal::kExitRefused;
  } catch (const std::exception& e) {
    // What is left is a file that cannot be read or written (the calibration, its CSVs), or
    // an internal failure (out of memory, a bug), which is named as such.
    spdlog::critical("{}", ftcal::UserText(e, "calibrating"));
    return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-calibrator");
}
