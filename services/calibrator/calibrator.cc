#include "calibrator/calibrator.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <functional>
#include <iterator>

#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

#include "common/calibration_offsets.h"
#include "common/calibration_publish.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "ftcal/hanging.h"
#include "ftcal/sensing_model.h"
#include "ftcal/standing.h"

#ifndef FTCAL_SOFTWARE_VERSION
#define FTCAL_SOFTWARE_VERSION "unknown"
#endif

namespace ftcal {

namespace {

std::string UtcNowIso8601() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

void SetInputFile(const std::string& path, calibration::InputFile* in,
                  const std::function<std::string(const std::string&)>& sha256 = nullptr) {
  in->set_path(std::filesystem::absolute(path).string());
  in->set_sha256(sha256 ? sha256(path) : Sha256File(path));
  in->set_bytes(std::filesystem::file_size(path));
}

std::string HostName() {
  char buf[256] = {};
  if (::gethostname(buf, sizeof buf - 1) != 0) return "unknown";
  return buf;
}

}  // namespace

LiveCalibrator::LiveCalibrator(const config::Config& config, Bus& bus, std::string out_path,
                               CalibratorOptions options, Callback on_calibrated)
    : config_(config),
      bus_(bus),
      out_path_(std::move(out_path)),
      options_(std::move(options)),
      on_calibrated_(std::move(on_calibrated)),
      collector_(config) {
  // A restarted calibrator continues above the version it wrote last, which the correctors have
  // used and now refuse to go back to. (An unreadable file is overwritten by the next
  // calibration, as before; its version is then unknown and the count starts at 1.)
  std::error_code ec;
  if (std::filesystem::exists(out_path_, ec)) {
    try {
      version_ = static_cast<int64_t>(ReadCalibrationFile(out_path_).version());
      spdlog::info("{} holds calibration version {}: the next one is {}", out_path_, version_,
                   version_ + 1);
    } catch (const std::exception& e) {
      spdlog::warn("{}: {}; versions start at 1", out_path_, e.what());
    }
  }
  collector_.Attach(bus);
  collector_.SetOnStandingStop([this] { OnStandingStop(); });
  collector_.SetOnSteadyPose([this] {
    if (waiting_since_utime_ >= 0 &&
        collector_.logged_pose_count() >= collector_.segmented_pose_count()) {
      waiting_since_utime_ = -1;
      CalibrateNow();
    }
  });
}

void LiveCalibrator::OnStandingStop() {
  const size_t logged = collector_.logged_pose_count(), found = collector_.segmented_pose_count();
  if (logged > 0 && logged < found) {
    spdlog::info(
        "STANDING stopped: {} STEADY_POSE events, {} poses found here; waiting up to "
        "{} s for the segmenter's last",
        logged, found, kLatePoseWaitS);
    waiting_since_utime_ = bus_.NowUtime();
    return;
  }
  CalibrateNow();
}

void LiveCalibrator::Tick() {
  if (waiting_since_utime_ < 0 ||
      bus_.NowUtime() - waiting_since_utime_ < static_cast<int64_t>(kLatePoseWaitS * 1e6)) {
    return;
  }
  waiting_since_utime_ = -1;
  spdlog::warn("calibrating with {} STEADY_POSE events of the {} poses found here",
               collector_.logged_pose_count(), collector_.segmented_pose_count());
  CalibrateNow();
}

void LiveCalibrator::CalibrateNow() {
  CalibrationRun run;
  try {
    run = RunCalibration(collector_, config_, options_);
  } catch (const CalibratorInputError& e) {
    ++refused_;
    last_refusal_ = e.what();
    spdlog::error("calibration refused: {}", e.what());
    return;
  }
  run.proto.set_version(static_cast<uint64_t>(version_ + 1));
  WriteCalibrationOutputs(run, out_path_);  // the file first: a published version exists on disk
  ++version_;
  ++made_;
  PublishCalibration(bus_, config_.channels().calibration(), run.proto, version_, signer_);
  spdlog::info("wrote {}; published calibration version {} on {}", out_path_, version_,
               config_.channels().calibration());
  if (on_calibrated_) on_calibrated_(run);
}

std::string SoftwareVersion() { return FTCAL_SOFTWARE_VERSION; }

std::vector<calibration::RecordingGaps> CheckRecordingGaps(const CalibrationCollector& collector,
                                                           const config::Config& config,
                                                           const std::set<int>& used,
                                                           bool allow_gaps,
                                                           std::vector<std::string>* warnings) {
  const double limit = config.calibrator().max_gap_share();
  std::vector<calibration::RecordingGaps> out;
  std::vector<std::string> over;
  for (const PhaseGaps& g : collector.phase_gaps()) {
    const bool is_used = used.count(g.phase) > 0 && !g.superseded;
    std::string lossy;
    for (int k = 0; k < kNumLegs; ++k) {
      calibration::RecordingGaps& r = out.emplace_back();
      r.set_phase(PhaseName(g.phase));
      r.set_session_id(g.session);
      r.set_channel(collector.ft_channel(k));
      r.set_received(static_cast<uint64_t>(g.received[k]));
      r.set_lost(static_cast<uint64_t>(g.lost[k]));
      r.set_restarts(static_cast<uint32_t>(g.restarts[k]));
      r.set_lost_share(g.LostShare(k));
      r.set_used(is_used);
      if (g.lost[k] > 0 || g.restarts[k] > 0) {
        lossy += fmt::format("{}{} {} of {} lost ({:.2f}%){}", lossy.empty() ? "" : ", ",
                             collector.ft_channel(k), g.lost[k], g.received[k] + g.lost[k],
                             100.0 * g.LostShare(k),
                             g.restarts[k] > 0 ? fmt::format(", {} restarts", g.restarts[k]) : "");
      }
      if (is_used && g.LostShare(k) > limit) {
        over.push_back(fmt::format("{} (session '{}') {}: {} of {} records lost ({:.2f}%)",
                                   PhaseName(g.phase), g.session, collector.ft_channel(k),
                                   g.lost[k], g.received[k] + g.lost[k], 100.0 * g.LostShare(k)));
      }
    }
    if (!lossy.empty()) {
      spdlog::warn("{} (session '{}'{}): transducer records missing by sequence number: {}",
                   PhaseName(g.phase), g.session, is_used ? "" : ", not used", lossy);
    }
  }
  if (over.empty()) return out;
  std::string list;
  for (const std::string& o : over) list += (list.empty() ? "" : "; ") + o;
  const std::string what = fmt::format(
      "the recording lost more than calibrator.max_gap_share ({:.2f}%) of a transducer's "
      "records in a phase the calibration uses: {}",
      100.0 * limit, list);
  if (!allow_gaps) {
    throw CalibratorInputError(what +
                               ". Look at the recording path (receive buffers, a bridge "
                               "restarting); --allow-gaps calibrates anyway");
  }
  warnings->push_back(what + " (calibrated anyway: --allow-gaps)");
  return out;
}

namespace {

CalibrateOptions CalibrateOptionsOf(const CalibrationCollector& collector,
                                    const CalibratorOptions& options) {
  CalibrateOptions co;
  co.accept_mass_mismatch = options.accept_mass_mismatch;
  co.accept_leg_map_mismatch = options.accept_leg_map_mismatch;
  if (collector.tare()) {
    co.has_naive_tare = true;
    co.naive_tare = *collector.tare();
  }
  return co;
}

}  // namespace

EarlyCalibration::EarlyCalibration(CalibrationCollector& collector, const config::Config& config,
                                   const CalibratorOptions& options)
    : collector_(collector), config_(config), options_(options) {
  collector_.SetCalibrationInputHooks([this] { Start(); }, [this] { Discard(); });
}

EarlyCalibration::~EarlyCalibration() {
  collector_.SetCalibrationInputHooks(nullptr, nullptr);
  if (job_.valid()) job_.wait();
}

void EarlyCalibration::Start() {
  if (valid_) return;  // one is running on these very inputs
  if (job_.valid()) job_.wait();
  // The job refers to the collector's hanging series, which Discard() waits for before they
  // change; the poses and options are its own copies.
  const std::vector<HangingRecording>* hanging = nullptr;
  std::vector<StandingPose> poses;
  try {
    hanging = &collector_.HangingRecordings();  // all four there
    poses = collector_.StandingPoses();
  } catch (const CalibratorInputError&) {
    return;  // not complete yet: RunCalibration() says what is missing
  }
  if (poses.empty()) return;
  job_ = std::async(std::launch::async, [this, hanging, poses = std::move(poses),
                                         co = CalibrateOptionsOf(collector_, options_)] {
    return Calibrate(*hanging, poses, config_, co);
  });
  started_ = valid_ = true;
  spdlog::info("calibrating on another thread while the rest of the session is read");
}

void EarlyCalibration::Discard() {
  if (!job_.valid()) return;
  job_.wait();
  valid_ = false;
}

std::optional<CalibrationRun> EarlyCalibration::Take() {
  if (!job_.valid()) return std::nullopt;
  const bool valid = valid_;
  valid_ = false;
  try {
    CalibrationRun run = job_.get();
    if (valid) return run;
  } catch (const std::exception&) {
    // Refused or failed: the caller's own run on the same inputs says why, in its own words.
  }
  return std::nullopt;
}

CalibrationRun RunCalibration(const CalibrationCollector& collector, const config::Config& config,
                              const CalibratorOptions& options, EarlyCalibration* early) {
  collector.CheckMarkersAndLegs("hanging series from standing");
  std::vector<std::string> gap_warnings;
  const std::vector<calibration::RecordingGaps> gaps =
      CheckRecordingGaps(collector, config,
                         {experiment_marker_t::HANG_X_POS, experiment_marker_t::HANG_X_NEG,
                          experiment_marker_t::HANG_Z_POS, experiment_marker_t::HANG_Z_NEG,
                          experiment_marker_t::STANDING},
                         options.allow_gaps, &gap_warnings);
  const std::vector<HangingRecording>& hanging = collector.HangingRecordings();
  const std::vector<StandingPose> poses = collector.StandingPoses();
  if (poses.empty()) {
    throw CalibratorInputError(
        "no steady standing poses: no STEADY_POSE events and no completed STANDING phase with "
        "a steady pose");
  }
  spdlog::info("calibrating: 4 hanging series, {} standing poses ({})", poses.size(),
               collector.counters().logged_poses > 0 ? "from STEADY_POSE events"
                                                     : "segmented from the STANDING spans");
  CalibrationRun run;
  if (std::optional<CalibrationRun> taken = early ? early->Take() : std::nullopt) {
    run = std::move(*taken);
  } else {
    try {
      run = Calibrate(hanging, poses, config, CalibrateOptionsOf(collector, options));
    } catch (const CalibrationStageError& e) {
      throw CalibratorInputError(e.what());
    }
  }
  spdlog::info("calibration done: {} candidates, model {}", run.standing.fits.size(),
               StandingModelName(run.standing.selected));
  // The configured total mass is checked against the data's inside Calibrate() (a
  // MassMismatchError unless accepted): a config for another robot is refused there.
  for (const std::string& w : gap_warnings) {
    run.warnings.push_back(w);
    run.proto.add_warning(w);
  }
  for (const calibration::RecordingGaps& g : gaps) *run.proto.add_recording_gaps() = g;
  for (const std::string& w : run.warnings) spdlog::warn("{}", w);
  AddResultRmse({}, nullptr, &run);  // the standing poses; offline adds the walk

  calibration::Provenance* p = run.proto.mutable_provenance();
  for (const std::string& path : options.log_paths) {
    SetInputFile(path, p->add_input(), options.sha256);
  }
  if (!options.config_path.empty()) {
    p->set_config_path(std::filesystem::absolute(options.config_path).string());
    p->set_config_sha256(Sha256File(options.config_path));
  }
  p->set_software_version(SoftwareVersion());
  p->set_created_utc(UtcNowIso8601());
  p->set_host(HostName());
  p->set_command_line(options.command_line);
  return run;
}

namespace {}  // namespace

OffsetReestimationRun RunOffsetReestimation(const CalibrationCollector& collector,
                                            const config::Config& config,
                                            const std::string& base_path, bool allow_partial,
                                            const CalibratorOptions& options) {
  collector.CheckMarkersAndLegs("standing poses or tripod stances");
  std::vector<std::string> gap_warnings;
  CheckRecordingGaps(collector, config,
                     {experiment_marker_t::STANDING, experiment_marker_t::TRIPOD},
                     options.allow_gaps, &gap_warnings);
  OffsetReestimationRun run;
  try {
    run.proto = ReadCalibrationFile(base_path);
    run.before = CalibrationFromProto(run.proto, config.robot());
    CheckCalibrationPlausible(run.before, config);
  } catch (const std::exception& e) {
    throw CalibratorInputError("--reestimate-offsets '" + base_path + "': " + e.what());
  }
  if (run.proto.robot_name() != config.robot().name()) {
    throw CalibratorInputError("--reestimate-offsets '" + base_path + "' is a calibration of '" +
                               run.proto.robot_name() + "', the config's robot is '" +
                               config.robot().name() + "'");
  }
  const std::vector<StandingPose> poses = collector.StandingPoses();
  const std::vector<LoadSample>& unloaded = collector.unloaded_samples();
  if (poses.empty() && unloaded.empty()) {
    throw CalibratorInputError(
        "no steady standing poses and no steady tripod stances with a leg lifted (completed "
        "STANDING or TRIPOD phases): nothing to re-estimate the offsets from");
  }
  OffsetReestimationOptions o;
  o.k_weights = KWeights(config.calibrator());
  // The same target as the base calibration's step 2 was fitted to.
  o.leg_aware_com = run.proto.solver().leg_aware_com();
  o.require_all = !allow_partial;
  spdlog::info("re-estimating the offsets: {} standing poses, {} tripod stances with a leg lifted",
               poses.size(), unloaded.size());
  try {
    run.estimate = ReestimateOffsets(run.before, poses, unloaded, o);
  } catch (const std::invalid_argument& e) {
    throw CalibratorInputError(std::string(e.what()) +
                               (allow_partial ? "" : " (or --partial to keep their old values)"));
  }
  run.after = ApplyOffsetReestimate(run.before, run.estimate);

  calibration::OffsetReestimation* r = run.proto.mutable_offset_reestimation();
  r->Clear();
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      r->add_previous_offset(run.before.leg[k].offset[i]);
      if (run.estimate.determined[k][i]) {
        SetOffsetComponent(i, run.estimate.offset[k][i], run.estimate.sigma[k][i],
                           run.proto.mutable_leg(k));
      }
    }
  }
  SetInputFile(base_path, r->mutable_base_calibration());
  r->set_base_version(run.proto.version());
  for (const std::string& path : options.log_paths) {
    SetInputFile(path, r->add_input(), options.sha256);
  }
  r->set_created_utc(UtcNowIso8601());
  r->set_command_line(options.command_line);
  r->set_standing_poses(static_cast<uint32_t>(poses.size()));
  r->set_unloaded_leg_samples(static_cast<uint32_t>(run.estimate.unloaded_rows / 6));
  r->set_rank(static_cast<uint32_t>(run.estimate.rank));
  for (const std::string& u : run.estimate.undetermined) r->add_undetermined(u);
  r->set_residual_rms(run.estimate.residual_rms);
  for (const std::string& w : gap_warnings) {
    spdlog::warn("{}", w);
    run.proto.add_warning(w);
  }
  run.proto.set_version(run.proto.version() + 1);
  return run;
}

}  // namespace ftcal
