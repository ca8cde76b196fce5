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

bool IsHangPhase(int phase) { return HangSeriesOfPhase(phase).has_value(); }

HangSeries SeriesOfPhase(int phase) { return *HangSeriesOfPhase(phase); }

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

CalibrationCollector::CalibrationCollector(const config::Config& config)
    : config_(config),
      inputs_(config),
      segmenter_options_(SegmenterOptionsFromConfig(config.segmenter())),
      aligner_(AlignerOptionsFromConfig(config), [this](const AlignedSample& a) { OnAligned(a); }) {
  PoseSegmenter check(segmenter_options_, nullptr);  // refuse unusable options at start
  hang_gaps_index_.fill(-1);
}

void CalibrationCollector::Attach(Bus& bus) {
  const auto& ch = config_.channels();
  // Each input log's signers count their sequences afresh: logs may be given in any order.
  verifier_ = auth::Verifier::FromConfig(config_);
  bus.SubscribeRaw(".*", [this](const MessageInfo& info, const void*, int) {
    LegOfChannel(info.channel);
  });
  // Every FT_* channel, not just the config's: a log from a robot with other legs must be told
  // apart from one whose legs are silent.
  bus.SubscribeRaw(ch.ft_prefix() + ".*", [this](const MessageInfo& info, const void* data,
                                                 int size) { OnFtRaw(info, data, size); });
  inputs_.Subscribe(bus, {nullptr, [this](const ServoInput& in) { aligner_.AddServo(in); },
                          [this](const MocapInput& in) { aligner_.AddMocap(in); }});
  // No time window: markers replayed from a recording (lcm-logplayer) are old by design; the
  // signature and the rising sequence still hold.
  bus.SubscribeSigned<experiment_marker_t>(
      ch.experiment(), &verifier_, /*window_us=*/0, config_.auth().allow_unsigned(),
      [this](const MessageInfo&, const experiment_marker_t& m) { OnExperiment(m); });
  bus.Subscribe<steady_pose_t>(ch.steady_pose(), [this](const MessageInfo&, const steady_pose_t& m) {
    OnSteadyPose(m);
  });
}

int CalibrationCollector::LegOfChannel(const std::string& channel) {
  const auto it = channel_leg_.find(channel);
  if (it != channel_leg_.end()) return it->second;
  // First event on this channel.
  channels_seen_.insert(channel);
  if (std::regex_match(channel, ft_pattern_)) ft_channels_seen_.insert(channel);
  int leg = -1;
  for (int k = 0; k < kNumLegs; ++k) {
    if (channel == inputs_.FtChannel(k)) leg = k;
  }
  channel_leg_.emplace(channel, leg);
  return leg;
}

void CalibrationCollector::OnFtRaw(const MessageInfo& info, const void* data, int size) {
  const int k = LegOfChannel(info.channel);
  if (k < 0) return;
  ft_sample_t& msg = ft_scratch_;  // decoded into again: no allocation per sample
  if (auto refused = wire::Decode(data, size, &msg)) {
    throw BadInput("undecodable ft_sample_t on " + info.channel + ": " + refused->kind,
                   refused->detail);
  }
  if (phase_ >= 0) CountRecord(k, msg.rdt_sequence);
  aligner_.AddFt(inputs_.FromFt(k, msg));
}

// Records arriving a little out of order (two sockets, a busy receiver) are not lost: a number
// up to this far below the highest seen fills a gap counted before.
constexpr int64_t kReorderWindow = 64;

void CalibrationCollector::CountRecord(int k, int64_t sequence) {
  int64_t& last = last_sequence_[k];
  if (last == 0) {
    ++current_gaps_.received[k];
  } else if (sequence > last) {
    ++current_gaps_.received[k];
    current_gaps_.lost[k] += sequence - last - 1;
  } else if (sequence == last) {
    return;  // the same record twice (a replayed log): not data, not a gap
  } else if (last - sequence <= kReorderWindow && current_gaps_.lost[k] > 0) {
    ++current_gaps_.received[k];
    --current_gaps_.lost[k];
    return;
  } else {
    ++current_gaps_.received[k];
    ++current_gaps_.restarts[k];
  }
  last = sequence;
}

void CalibrationCollector::OnExperiment(const experiment_marker_t& msg) {
  ++counters_.markers;
  const bool same = phase_ == msg.phase && phase_session_ == msg.session_id;
  if (msg.start) {
    if (same) return;  // a repeated start marker (the sequencer repeats them)
    if (phase_ >= 0) {
      spdlog::warn("EXPERIMENT: {} started while {} had no stop marker; {} discarded",
                   PhaseName(msg.phase), PhaseName(phase_), PhaseName(phase_));
      EndPhase(false);
    }
    phase_ = msg.phase;
    phase_session_ = msg.session_id;
    current_gaps_ = PhaseGaps();
    current_gaps_.phase = phase_;
    current_gaps_.session = phase_session_;
    last_sequence_.fill(0);
    if (IsHangPhase(phase_)) {
      current_hang_ = HangingRecording();
      current_hang_.series = SeriesOfPhase(phase_);
      current_hang_.gravity_b = Vec3(msg.gravity_b[0], msg.gravity_b[1], msg.gravity_b[2]);
    } else if (phase_ == experiment_marker_t::STANDING) {
      current_poses_.clear();
      segmenter_ = std::make_unique<PoseSegmenter>(
          segmenter_options_, [this](const SteadyPoseOut& p) {
            if (!p.markers_ok) return;
            current_poses_.push_back(p.pose);
            ++counters_.segmented_poses;
          });
    } else if (phase_ == experiment_marker_t::TARE) {
      for (Vec6& w : tare_sum_) w.setZero();
      tare_count_ = 0;
    } else if (phase_ == experiment_marker_t::TRIPOD) {
      current_unloaded_.clear();
      segmenter_ = std::make_unique<PoseSegmenter>(
          segmenter_options_, [this](const SteadyPoseOut& p) { OnTripodStance(p); });
    }
    spdlog::info("EXPERIMENT: {} started (session '{}')", PhaseName(phase_), phase_session_);
    return;
  }
  if (!same) {
    spdlog::warn("EXPERIMENT: stop marker of {} (session '{}') without its start; ignored",
                 PhaseName(msg.phase), msg.session_id);
    return;
  }
  const bool standing = phase_ == experiment_marker_t::STANDING;
  EndPhase(true);
  if (standing && on_standing_stop_) on_standing_stop_();
}

void CalibrationCollector::EndPhase(bool completed) {
  // A STANDING or TRIPOD phase's segmenter hands over the pose in progress first.
  SegmenterCounters segmented;
  if (segmenter_) {
    segmenter_->Flush();
    segmented = segmenter_->counters();
    segmenter_.reset();
  }
  if (completed) phase_gaps_.push_back(current_gaps_);
  if (IsHangPhase(phase_)) {
    if (completed) {
      const int s = static_cast<int>(current_hang_.series);
      if (hang_gaps_index_[s] >= 0) phase_gaps_[hang_gaps_index_[s]].superseded = true;
      hang_gaps_index_[s] = static_cast<int>(phase_gaps_.size()) - 1;
      if (hang_[s]) {
        spdlog::warn("{} recorded again: the later recording replaces the earlier one",
                     HangSeriesName(current_hang_.series));
      }
      spdlog::info("{} complete: {} samples per leg, {} attitude samples",
                   HangSeriesName(current_hang_.series), current_hang_.legs[0].t_s.size(),
                   current_hang_.attitude.size());
      hang_[s] = std::move(current_hang_);
    }
    current_hang_ = HangingRecording();
  } else if (phase_ == experiment_marker_t::STANDING) {
    if (completed) {
      spdlog::info("STANDING complete (session '{}'): {} steady poses segmented",
                   phase_session_, current_poses_.size());
      segmented_poses_.insert(segmented_poses_.end(), current_poses_.begin(),
                              current_poses_.end());
      standing_session_ = phase_session_;
    }
    current_poses_.clear();
  } else if (phase_ == experiment_marker_t::TARE) {
    if (completed && tare_count_ > 0) {
      std::array<Vec6, kNumLegs> mean;
      for (int k = 0; k < kNumLegs; ++k) mean[k] = tare_sum_[k] / static_cast<double>(tare_count_);
      tare_ = mean;
      spdlog::info("TARE complete (session '{}'): naive tare from {} samples", phase_session_,
                   tare_count_);
    }
  } else if (phase_ == experiment_marker_t::TRIPOD) {
    if (completed) {
      spdlog::info("TRIPOD complete (session '{}'): {} steady stances with a leg lifted; left "
                   "out: {} steady runs shorter than {} s, {} with a marker untracked, {} (so far) "
                   "with no leg lifted",
                   phase_session_, current_unloaded_.size(), segmented.dropped_short,
                   segmenter_options_.min_steady_s, segmented.dropped_markers,
                   counters_.tripod_stances_dropped);
      unloaded_.insert(unloaded_.end(), current_unloaded_.begin(), current_unloaded_.end());
    }
    current_unloaded_.clear();
  } else if (phase_ == experiment_marker_t::WALKING) {
    if (completed && walking_.empty() && !current_walk_.empty()) {
      spdlog::info("WALKING complete (session '{}'): {} aligned samples kept for the report",
                   phase_session_, current_walk_.size());
      walking_ = std::move(current_walk_);
    }
    current_walk_.clear();
  }
  phase_ = -1;
  phase_session_.clear();
}

void CalibrationCollector::Flush() {
  if (phase_ >= 0) {
    spdlog::warn("input ended inside {} (no stop marker): that phase is discarded",
                 PhaseName(phase_));
    EndPhase(false);
  }
}

void CalibrationCollector::OnSteadyPose(const steady_pose_t& msg) {
  ++counters_.logged_poses;
  const SteadyPoseOut p = FromLcm(msg);
  if (!p.markers_ok) {
    ++counters_.poses_dropped_markers;
    return;
  }
  logged_poses_.push_back(p.pose);
  if (on_steady_pose_) on_steady_pose_();
}

void CalibrationCollector::OnAligned(const AlignedSample& a) {
  ++counters_.aligned_samples;
  const SyncSample& s = a.sample;
  if (IsHangPhase(phase_)) {
    ++counters_.hanging_samples;
    const double t_s = 1e-6 * static_cast<double>(s.utime);
    for (int k = 0; k < kNumLegs; ++k) {
      LegSamples& leg = current_hang_.legs[k];
      leg.t_s.push_back(t_s);
      leg.angle_rad.push_back(s.angle_rad[k]);
      leg.wrench.push_back(s.wrench[k]);
    }
    if (s.attitude_ok) current_hang_.attitude.push_back(s.R_WC);
  } else if (phase_ == experiment_marker_t::STANDING && segmenter_) {
    ++counters_.standing_samples;
    segmenter_->Add(s);
  } else if (phase_ == experiment_marker_t::TRIPOD && segmenter_) {
    ++counters_.tripod_samples;
    segmenter_->Add(s);
  } else if (phase_ == experiment_marker_t::TARE) {
    for (int k = 0; k < kNumLegs; ++k) tare_sum_[k] += s.wrench[k];
    ++tare_count_;
  } else if (phase_ == experiment_marker_t::WALKING) {
    ++counters_.walking_samples;
    if (walking_.empty() && current_walk_.size() < kMaxWalkingSamples) current_walk_.push_back(s);
  }
}

// The shaft angle, not the reading, says which legs are off the ground: the reading is what
// the offsets are being re-estimated from, and a drifted offset can be as large as a light load.
void CalibrationCollector::OnTripodStance(const SteadyPoseOut& p) {
  const double min_rad = config_.calibrator().unloaded_leg_min_angle_deg() * M_PI / 180.0;
  LoadSample sample;
  sample.wrench = p.pose.wrench;
  sample.angle_rad = p.pose.angle_rad;
  sample.R_WC = p.pose.R_WC;
  bool any = false;
  for (int k = 0; k < kNumLegs; ++k) {
    sample.unloaded[k] = std::abs(std::remainder(p.pose.angle_rad[k], 2.0 * M_PI)) > min_rad;
    any = any || sample.unloaded[k];
  }
  if (!p.markers_ok || !any) {
    ++counters_.tripod_stances_dropped;
    return;
  }
  ++counters_.tripod_stances;
  current_unloaded_.push_back(sample);
}

std::vector<HangingRecording> CalibrationCollector::HangingRecordings() const {
  std::vector<HangingRecording> out;
  std::string missing;
  for (int s = 0; s < kNumHangSeries; ++s) {
    if (hang_[s]) {
      out.push_back(*hang_[s]);
    } else {
      missing += (missing.empty() ? "" : ", ") + HangSeriesName(static_cast<HangSeries>(s));
    }
  }
  if (!missing.empty()) {
    throw CalibratorInputError("missing hanging series: " + missing +
                               " (no EXPERIMENT start..stop marker pair with samples)");
  }
  for (const HangingRecording& r : out) {
    if (r.legs[0].t_s.empty()) {
      throw CalibratorInputError("hanging series " + HangSeriesName(r.series) +
                                 " has markers but no aligned samples (FT_*/SERVO_STATE "
                                 "missing in that span)");
    }
  }
  return out;
}

std::vector<StandingPose> CalibrationCollector::StandingPoses() const {
  // Poses a segmenter already published are what the operator saw; when the log has none, the
  // same segmenter logic over the STANDING spans gives them.
  if (logged_poses_.empty()) return segmented_poses_;
  // A STEADY_POSE message carries medians only; the within-pose scatter (the noise floor,
  // docs/method.md) comes from this collector's own segmentation of the same span, matched by
  // time (the same logic on the same samples finds the same runs) and shaft angles.
  std::vector<StandingPose> out = logged_poses_;
  std::vector<const StandingPose*> by_time;
  for (const StandingPose& p : segmented_poses_) by_time.push_back(&p);
  std::sort(by_time.begin(), by_time.end(),
            [](const StandingPose* a, const StandingPose* b) { return a->t_s < b->t_s; });
  for (StandingPose& pose : out) {
    auto it = std::lower_bound(by_time.begin(), by_time.end(), pose.t_s,
                               [](const StandingPose* p, double t) { return p->t_s < t; });
    for (auto c : {it, it == by_time.begin() ? it : it - 1}) {
      if (c == by_time.end()) continue;
      const StandingPose& seg = **c;
      bool same = std::abs(seg.t_s - pose.t_s) < 0.5;
      for (int k = 0; k < kNumLegs && same; ++k) {
        same = std::abs(seg.angle_rad[k] - pose.angle_rad[k]) < 1e-3;
      }
      if (!same) continue;
      pose.samples = seg.samples;
      pose.wrench_sem = seg.wrench_sem;
      pose.attitude_sem_rad = seg.attitude_sem_rad;
      break;
    }
  }
  return out;
}

void CalibrationCollector::CheckMarkersAndLegs(const std::string& phases) const {
  if (counters_.markers == 0) {
    throw CalibratorInputError("no EXPERIMENT markers (channel '" + config_.channels().experiment() +
                               "') in the input: cannot tell " + phases);
  }
  std::string unknown, silent;
  std::set<std::string> expected;
  for (int k = 0; k < kNumLegs; ++k) expected.insert(inputs_.FtChannel(k));
  for (const std::string& c : ft_channels_seen_) {
    if (!expected.count(c)) unknown += (unknown.empty() ? "" : ", ") + c;
  }
  for (const std::string& c : expected) {
    if (!ft_channels_seen_.count(c)) silent += (silent.empty() ? "" : ", ") + c;
  }
  if (!unknown.empty() || !silent.empty()) {
    std::string msg = "the config's legs do not match the log's FT channels:";
    if (!unknown.empty()) msg += " channels for legs the config does not have: " + unknown + ";";
    if (!silent.empty()) msg += " config legs with no channel in the log: " + silent + ";";
    std::string all;
    for (const std::string& c : channels_seen_) all += (all.empty() ? "" : ", ") + c;
    msg += " the log's channels: " + (all.empty() ? std::string("none") : all);
    throw CalibratorInputError(msg);
  }
}

void WriteCalibrationOutputs(const CalibrationRun& run, const std::string& out_path) {
  WriteCalibrationFile(run.proto, out_path);
  WriteFileAtomic(ResidualsPathFor(out_path), ResidualsCsv(run.standing));
}

LiveCalibrator::LiveCalibrator(const config::Config& config, Bus& bus, std::string out_path,
                               CalibratorOptions options, Callback on_calibrated)
    : config_(config),
      bus_(bus),
      out_path_(std::move(out_path)),
      options_(std::move(options)),
      on_calibrated_(std::move(on_calibrated)),
      collector_(config) {
  collector_.Attach(bus);
  collector_.SetOnStandingStop([this] { OnStandingStop(); });
  collector_.SetOnSteadyPose([this] {
    if (waiting_since_utime_ >= 0 && collector_.logged_pose_count() >= collector_.segmented_pose_count()) {
      waiting_since_utime_ = -1;
      CalibrateNow();
    }
  });
}

void LiveCalibrator::OnStandingStop() {
  const size_t logged = collector_.logged_pose_count(), found = collector_.segmented_pose_count();
  if (logged > 0 && logged < found) {
    spdlog::info("STANDING stopped: {} STEADY_POSE events, {} poses found here; waiting up to "
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
  const calibration_t msg = ToLcm(run.proto, version_, bus_.NowUtime());
  if (signer_ != nullptr) {
    bus_.PublishSigned(config_.channels().calibration(), msg, *signer_);
  } else {
    bus_.Publish(config_.channels().calibration(), msg);
  }
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

CalibrationRun RunCalibration(const CalibrationCollector& collector, const config::Config& config,
                              const CalibratorOptions& options) {
  collector.CheckMarkersAndLegs("hanging series from standing");
  std::vector<std::string> gap_warnings;
  const std::vector<calibration::RecordingGaps> gaps = CheckRecordingGaps(
      collector, config,
      {experiment_marker_t::HANG_X_POS, experiment_marker_t::HANG_X_NEG,
       experiment_marker_t::HANG_Z_POS, experiment_marker_t::HANG_Z_NEG,
       experiment_marker_t::STANDING},
      options.allow_gaps, &gap_warnings);
  const std::vector<HangingRecording> hanging = collector.HangingRecordings();
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
  try {
    CalibrateOptions co;
    co.accept_mass_mismatch = options.accept_mass_mismatch;
    co.accept_leg_map_mismatch = options.accept_leg_map_mismatch;
    if (collector.tare()) {
      co.has_naive_tare = true;
      co.naive_tare = *collector.tare();
    }
    run = Calibrate(hanging, poses, config, co);
  } catch (const CalibrationStageError& e) {
    throw CalibratorInputError(e.what());
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

namespace {

constexpr const char* kComponents[6] = {"fx N", "fy N", "fz N", "tx Nm", "ty Nm", "tz Nm"};

// Component i (0..5 = [f; tau]) of a leg's offset in the calibration file.
void SetOffsetComponent(int i, double value, double sigma, calibration::LegCalibration* leg) {
  calibration::Vec3Estimate* v =
      i < 3 ? leg->mutable_force_offset_n() : leg->mutable_torque_offset_nm();
  switch (i % 3) {
    case 0: v->set_x(value); v->set_sigma_x(sigma); break;
    case 1: v->set_y(value); v->set_sigma_y(sigma); break;
    default: v->set_z(value); v->set_sigma_z(sigma); break;
  }
}

}  // namespace

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
  for (const std::string& path : options.log_paths) SetInputFile(path, r->add_input());
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

std::string OffsetSummaryTable(const OffsetReestimationRun& run) {
  const calibration::OffsetReestimation& r = run.proto.offset_reestimation();
  std::string o = fmt::format(
      "Offsets of {} re-estimated (docs/method.md \"Offset drift\"): {} standing poses, {} "
      "unloaded-leg samples; rank {} of 36; K-weighted rms residual {:.4f}\n",
      run.proto.robot_name(), r.standing_poses(), r.unloaded_leg_samples(), r.rank(),
      r.residual_rms());
  o += fmt::format("{:<10}", "leg");
  for (const char* c : kComponents) o += fmt::format(" {:>9}", c);
  o += "\n";
  for (int k = 0; k < kNumLegs; ++k) {
    const char* rows[3] = {"new", "drift", "+-"};
    for (int row = 0; row < 3; ++row) {
      o += fmt::format("{:<4}{:<6}", row == 0 ? kLegNames[k] : "", rows[row]);
      for (int i = 0; i < 6; ++i) {
        if (!run.estimate.determined[k][i]) {
          o += fmt::format(" {:>9}", row == 0 ? "kept" : "-");
          continue;
        }
        const double v = row == 0   ? run.after.leg[k].offset[i]
                         : row == 1 ? run.after.leg[k].offset[i] - run.before.leg[k].offset[i]
                                    : run.estimate.sigma[k][i];
        o += fmt::format(" {:>9.4f}", v);
      }
      o += "\n";
    }
  }
  if (r.undetermined_size() > 0) {
    std::string list;
    for (const std::string& u : r.undetermined()) list += (list.empty() ? "" : ", ") + u;
    o += "not determined by this session, base values kept: " + list + "\n";
  }
  return o;
}

std::string SummaryTable(const CalibrationRun& run) {
  const calibration::Calibration& c = run.proto;
  std::string o;
  o += fmt::format("Calibration of {} ({} standing poses, model {})\n", c.robot_name(),
                   c.standing_poses(), calibration::StandingModel_Name(c.model()));
  const calibration::SolverInfo& m = c.solver();
  o += fmt::format("Method: profile {}; step-2 solver {}; hanging rotations {}; hanging gravity "
                   "prior {}; robot CoM {} ({})\n",
                   m.profile(), m.solver(),
                   m.exact_hanging_rotations() ? "exact" : "first-order (report)",
                   m.hanging_gravity_prior() ? "on" : "off",
                   m.leg_aware_com() ? "leg-aware" : "fixed (report)", m.com_model_source());
  if (c.has_mass_check()) {
    const calibration::MassCheck& mc = c.mass_check();
    o += fmt::format("Total mass: configured {:.4f} kg, implied by the data {:.4f} +- {:.4f} kg "
                     "(allowed difference {:.4f} kg): {}\n",
                     mc.configured_kg(), mc.implied_kg(), mc.sigma_kg(), mc.allowed_kg(),
                     mc.consistent() ? "consistent" : "MISMATCH (accepted)");
  }
  if (c.has_noise_floor() && c.noise_floor().has_residual_to_floor()) {
    o += fmt::format("Standing residual: {:.2f} times the noise floor of the poses (warn above "
                     "{:g})\n",
                     c.noise_floor().residual_to_floor(), c.noise_floor().warn_factor());
  }
  for (const std::string& w : c.warning()) o += "WARNING: " + w + "\n";
  o += fmt::format("{:<4} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9}\n",
                   "leg", "fo_x N", "fo_y N", "fo_z N", "to_x Nm", "to_y Nm", "to_z Nm", "mg N",
                   "+-", "rx deg", "ry deg", "rz deg", "p~'x mm", "p~'y mm");
  for (const auto& leg : c.leg()) {
    const auto& f = leg.force_offset_n();
    const auto& t = leg.torque_offset_nm();
    const auto& r = leg.mounting().rotation_vector_deg();
    const auto& p = leg.mounting().p_tilde_prime_m();
    o += fmt::format(
        "{:<4} {:>8.3f} {:>8.3f} {:>8.3f} {:>8.4f} {:>8.4f} {:>8.4f} {:>9.3f} {:>8.4f} {:>8.3f} "
        "{:>8.3f} {:>9.3f} {:>9.2f} {:>9.2f}  p~'z {:.2f} mm\n",
        leg.name(), f.x(), f.y(), f.z(), t.x(), t.y(), t.z(), leg.leg_weight_n().value(),
        leg.leg_weight_n().sigma(), r.x(), r.y(), r.z(), 1e3 * p.x(), 1e3 * p.y(), 1e3 * p.z());
  }
  if (c.has_p_c_b_m()) {
    o += fmt::format("p^C_B = ({:.2f}, {:.2f}, {:.2f}) mm\n", 1e3 * c.p_c_b_m().x(),
                     1e3 * c.p_c_b_m().y(), 1e3 * c.p_c_b_m().z());
  }
  o += fmt::format("\nModel selection (lowest BIC selected; solver {}):\n", m.solver());
  o += fmt::format("  {:<26} {:<10} {:>4} {:>12} {:>12} {:>12} {:>10}\n", "model", "robot CoM",
                   "DOF", "CV MSE", "RSS", "BIC", "dBIC");
  for (const auto& row : c.model_selection()) {
    o += fmt::format("{} {:<26} {:<10} {:>4} {:>12.5g} {:>12.5g} {:>12.5g} {:>10.1f}\n",
                     row.selected() ? "*" : " ", calibration::StandingModel_Name(row.model()),
                     row.leg_aware_com() ? "leg-aware" : "fixed", row.dof(), row.cv_mse(),
                     row.rss(), row.bic(), row.delta_bic());
  }
  if (m.has_bic_margin()) {
    o += fmt::format("  selected by a BIC margin of {:.1f} over {}", m.bic_margin(), m.runner_up());
    if (m.has_com_bic_margin()) {
      o += fmt::format("; {:.1f} over the best {} robot-CoM candidate", m.com_bic_margin(),
                       m.leg_aware_com() ? "fixed" : "leg-aware");
    }
    o += "\n";
  }
  if (c.result_rmse_size() > 0) {
    o += "\nGround-contact RMSE, naive tare -> calibrated (the journal's terms):\n";
    o += fmt::format("  {:<15} {:<6} {:<15} {:>7} {:>20} {:>22}\n", "samples", "wrench",
                     "against", "count", "force N", "torque N*m");
    for (const auto& r : c.result_rmse()) {
      auto pct = [](double a, double b) { return a > 0 ? 100.0 * (b - a) / a : 0.0; };
      o += fmt::format("  {:<15} {:<6} {:<15} {:>7} {:>7.3f} -> {:<6.3f}{:>+5.0f}% {:>7.4f} -> "
                       "{:<6.4f}{:>+5.0f}%\n",
                       r.samples(), r.wrench(), r.reference(), r.count(), r.force_naive_n(),
                       r.force_calibrated_n(), pct(r.force_naive_n(), r.force_calibrated_n()),
                       r.torque_naive_nm(), r.torque_calibrated_nm(),
                       pct(r.torque_naive_nm(), r.torque_calibrated_nm()));
    }
  }
  o += "\nResidual of the total wrench at the CoM in W (rms per component):\n";
  o += fmt::format("  {:<18} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}\n", "variant", "fx N", "fy N",
                   "fz N", "tx Nm", "ty Nm", "tz Nm");
  for (const auto& r : c.standing_residual()) {
    o += fmt::format("  {:<18}", r.label());
    for (int i = 0; i < r.rms_size(); ++i) o += fmt::format(" {:>8.4f}", r.rms(i));
    o += "\n";
  }
  return o;
}

namespace {

RobotCalibration NaiveTareCalibration(const CalibrationRun& run) {
  RobotCalibration naive = run.step1;
  for (int k = 0; k < kNumLegs; ++k) {
    naive.leg[k].offset = run.hanging.leg[k].naive_offset;
    naive.leg[k].weight_n = 0.0;
  }
  naive.p_C_B = Vec3::Zero();
  return naive;
}

struct RmsAccumulator {
  double f2 = 0.0, t2 = 0.0;
  uint32_t n = 0;
  void Add(const Vec6& d) {
    f2 += d.head<3>().squaredNorm();
    t2 += d.tail<3>().squaredNorm();
    ++n;
  }
  double F() const { return n ? std::sqrt(f2 / n) : 0.0; }
  double T() const { return n ? std::sqrt(t2 / n) : 0.0; }
};

void AddRow(const std::string& samples, const std::string& wrench, const std::string& reference,
            const RmsAccumulator& naive, const RmsAccumulator& cal, calibration::Calibration* out) {
  calibration::ResultRmse* r = out->add_result_rmse();
  r->set_samples(samples);
  r->set_wrench(wrench);
  r->set_reference(reference);
  r->set_count(cal.n);
  r->set_force_naive_n(naive.F());
  r->set_force_calibrated_n(cal.F());
  r->set_torque_naive_nm(naive.T());
  r->set_torque_calibrated_nm(cal.T());
}

}  // namespace

void AddResultRmse(const std::vector<SyncSample>& walk, const RobotCalibration* truth,
                   CalibrationRun* run) {
  calibration::Calibration& out = run->proto;
  out.clear_result_rmse();
  {
    RmsAccumulator naive, cal;
    for (const Vec6& r : run->standing.residual_naive) naive.Add(r);
    for (const Vec6& r : run->standing.residual_full) cal.Add(r);
    AddRow("standing poses", "total", "balance target", naive, cal, &out);
  }
  if (walk.empty()) return;
  const RobotCalibration naive_cal = NaiveTareCalibration(*run);
  const bool leg_aware = run->standing.selected_leg_aware_com;
  const double G = run->calibration.TotalWeightN();
  RmsAccumulator total_naive, total_cal;
  std::array<RmsAccumulator, kNumLegs> leg_naive, leg_cal;
  for (const SyncSample& s : walk) {
    if (!s.attitude_ok) continue;
    Vec6 target;
    target << 0, 0, G, 0, 0, 0;
    if (leg_aware) {
      target.tail<3>() = (s.R_WC * ComShiftC(run->calibration, s.angle_rad)).cross(Vec3(0, 0, G));
    }
    Vec6 sum_naive = Vec6::Zero(), sum_cal = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 wn = GroundWrenchW(naive_cal, k, s.wrench[k], s.angle_rad[k], s.R_WC);
      const Vec6 wc = GroundWrenchW(run->calibration, k, s.wrench[k], s.angle_rad[k], s.R_WC);
      sum_naive += wn;
      sum_cal += wc;
      if (truth != nullptr) {
        const Vec6 wt = GroundWrenchW(*truth, k, s.wrench[k], s.angle_rad[k], s.R_WC);
        leg_naive[k].Add(wn - wt);
        leg_cal[k].Add(wc - wt);
      }
    }
    total_naive.Add(sum_naive - target);
    total_cal.Add(sum_cal - target);
  }
  AddRow("walk", "total", "balance target", total_naive, total_cal, &out);
  if (truth != nullptr) {
    for (int k = 0; k < kNumLegs; ++k) {
      AddRow("walk", std::string(kLegNames[k]), "true parameters", leg_naive[k], leg_cal[k], &out);
    }
  }
}

// fmt's "{:.Ng}" is printf's %.Ng, which is what an ostream with precision(N) writes: the same
// bytes as before, without the stream's locale and virtual calls (the walking file is ~2 M
// numbers).
std::string ResidualsCsv(const StandingResult& standing) {
  fmt::memory_buffer out;
  auto put = std::back_inserter(out);
  fmt::format_to(put, "pose,variant,fx_n,fy_n,fz_n,tx_nm,ty_nm,tz_nm\n");
  const std::pair<const char*, const std::vector<Vec6>*> variants[] = {
      {"naive tare", &standing.residual_naive},
      {"without T~", &standing.residual_without},
      {"full calibration", &standing.residual_full}};
  for (const auto& [label, rows] : variants) {
    for (size_t p = 0; p < rows->size(); ++p) {
      const Vec6& r = (*rows)[p];
      fmt::format_to(put, "{},{},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g}\n", p, label,
                     r[0], r[1], r[2], r[3], r[4], r[5]);
    }
  }
  return fmt::to_string(out);
}

namespace {
std::string PathBeside(const std::string& calibration_path, const std::string& suffix) {
  std::string base = calibration_path;
  const auto slash = base.rfind('/');
  const auto dot = base.rfind('.');
  if (dot != std::string::npos && (slash == std::string::npos || dot > slash)) base.resize(dot);
  return base + suffix;
}
}  // namespace

std::string ResidualsPathFor(const std::string& calibration_path) {
  return PathBeside(calibration_path, ".residuals.csv");
}

std::string WalkingPathFor(const std::string& calibration_path) {
  return PathBeside(calibration_path, ".walking.csv");
}

std::string WalkingCsv(const std::vector<SyncSample>& samples, const CalibrationRun& run,
                       const RobotCalibration* truth, double period_s) {
  if (samples.empty()) throw std::invalid_argument("WalkingCsv: no walking samples");
  // The naive-tare baseline as the corrector would apply it (standing.h's NaiveTareResiduals).
  RobotCalibration naive = run.step1;
  for (int k = 0; k < kNumLegs; ++k) {
    naive.leg[k].offset = run.hanging.leg[k].naive_offset;
    naive.leg[k].weight_n = 0.0;
  }
  naive.p_C_B = Vec3::Zero();
  std::vector<std::pair<const char*, const RobotCalibration*>> variants = {
      {"full calibration", &run.calibration}, {"naive tare", &naive}};
  if (truth != nullptr) variants.emplace_back("truth", truth);

  fmt::memory_buffer out;
  auto put = std::back_inserter(out);
  fmt::format_to(put, "t_s,variant");
  const char* comp[] = {"fx_n", "fy_n", "fz_n", "tx_nm", "ty_nm", "tz_nm"};
  for (int k = 0; k <= kNumLegs; ++k) {
    for (const char* c : comp) {
      fmt::format_to(put, ",{}_{}", k < kNumLegs ? kLegNames[k] : "total", c);
    }
  }
  fmt::format_to(put, "\n");
  const int64_t step_us = static_cast<int64_t>(std::llround(period_s * 1e6));
  const int64_t t0 = samples.front().utime;
  int64_t next = t0;
  for (const SyncSample& s : samples) {
    if (!s.attitude_ok || s.utime < next) continue;
    next = s.utime + step_us;
    for (const auto& [label, cal] : variants) {
      fmt::format_to(put, "{:.7g},{}", 1e-6 * static_cast<double>(s.utime - t0), label);
      Vec6 total = Vec6::Zero();
      for (int k = 0; k < kNumLegs; ++k) {
        const Vec6 w = GroundWrenchW(*cal, k, s.wrench[k], s.angle_rad[k], s.R_WC);
        total += w;
        for (int i = 0; i < 6; ++i) fmt::format_to(put, ",{:.7g}", w[i]);
      }
      for (int i = 0; i < 6; ++i) fmt::format_to(put, ",{:.7g}", total[i]);
      fmt::format_to(put, "\n");
    }
  }
  return fmt::to_string(out);
}

}  // namespace ftcal
