#include "drift/drift_stage.h"

#include <algorithm>
#include <filesystem>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <limits>
#include <stdexcept>

#include "common/calibration_offsets.h"
#include "common/calibration_publish.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"

namespace ftcal {
namespace {

constexpr const char* kAxes[6] = {"fx", "fy", "fz", "tx", "ty", "tz"};

Vec6 Pair(double force, double torque) {
  return (Vec6() << force, force, force, torque, torque, torque).finished();
}

double SigmaOf(const calibration::Vec3Estimate& v, int axis) {
  const double s = axis == 0 ? v.sigma_x() : axis == 1 ? v.sigma_y() : v.sigma_z();
  return std::isfinite(s) && s > 0.0 ? s : 0.0;
}

void SetInputFile(const std::string& path, calibration::InputFile* in) {
  in->set_path(std::filesystem::absolute(path).string());
  in->set_sha256(Sha256File(path));
  in->set_bytes(std::filesystem::file_size(path));
}

std::string UtcNow() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

}  // namespace

OffsetTrackerOptions OffsetTrackerOptionsFromConfig(const config::Config& config) {
  const config::Drift& d = config.drift();
  OffsetTrackerOptions o;
  o.bin_s = d.bin_s();
  o.max_foot_force_n = d.max_foot_force_n();
  o.max_shaft_accel_rad_s2 = d.max_shaft_accel_rad_s2();
  o.max_shaft_speed_rad_s = d.max_shaft_speed_rad_s();
  o.accel_baseline_s = d.accel_baseline_s();
  o.min_window_s = d.min_window_s();
  o.max_window_s = d.max_window_s();
  o.edge_trim_s = d.edge_trim_s();
  // Every stage calls an input stale at the same age (the corrector's).
  o.max_servo_age_s = config.corrector().max_servo_age_s();
  o.max_mocap_age_s = config.corrector().max_mocap_age_s();
  o.process_noise = Pair(d.process_noise_force_n(), d.process_noise_torque_nm());
  o.initial_sigma = Pair(d.initial_sigma_force_n(), d.initial_sigma_torque_nm());
  o.window_floor = Pair(d.window_floor_force_n(), d.window_floor_torque_nm());
  return o;
}

std::array<Vec6, kNumLegs> OffsetSigmas(const calibration::Calibration& proto) {
  std::array<Vec6, kNumLegs> out{};
  for (int k = 0; k < kNumLegs && k < proto.leg_size(); ++k) {
    for (int i = 0; i < 6; ++i) {
      const auto& v = i < 3 ? proto.leg(k).force_offset_n() : proto.leg(k).torque_offset_nm();
      out[k][i] = SigmaOf(v, i % 3);
    }
  }
  return out;
}

DriftStage::DriftStage(const config::Config& config, Bus& bus, StateSink set_state)
    : config_(config),
      bus_(bus),
      set_state_(std::move(set_state)),
      inputs_(config),
      options_(OffsetTrackerOptionsFromConfig(config)) {
  const config::Drift& d = config.drift();
  apply_policy_.factor = d.apply_factor();
  apply_policy_.min_change = Pair(d.warn_min_force_n(), d.warn_min_torque_nm());
  apply_policy_.min_interval_s = d.apply_min_interval_s();
  // Refuse at start, not at the first calibration, options the tracker refuses.
  (void)OffsetTracker(options_, RobotCalibration{});
  ServiceStats& st = bus.stats();
  counters_ = {&st.Counter("windows"),
               &st.Counter("bins_air"),
               &st.Counter("bins_loaded"),
               &st.Counter("bins_moving"),
               &st.Counter("bins_no_servo"),
               &st.Counter("bins_no_attitude"),
               &st.Counter("drift_warn"),
               &st.Counter("calibration_version"),
               &st.Counter("calibrations_applied")};
  const auto& ch = config.channels();
  inputs_.Subscribe(bus, {[this](const FtBatch& batch) { OnFt(batch); },
                          [this](const ServoInput& in) { OnServo(in); },
                          [this](const MocapInput& in) { OnMocap(in); }});
  bus.SubscribeSigned<experiment_marker_t>(
      ch.experiment(), &verifier_, static_cast<int64_t>(config_.auth().experiment_window_s() * 1e6),
      config_.auth().allow_unsigned(),
      [this](const MessageInfo&, const experiment_marker_t& m) { OnExperiment(m); });
  bus.SubscribeSigned<calibration_t>(
      ch.calibration(), &verifier_,
      static_cast<int64_t>(config_.auth().calibration_window_s() * 1e6),
      config_.auth().allow_unsigned(),
      [this](const MessageInfo& i, const calibration_t& m) { OnCalibration(i, m); });
  csv_ =
      "utime,leg,status,d_fx_n,d_fy_n,d_fz_n,d_tx_nm,d_ty_nm,d_tz_nm,"
      "sigma_fx_n,sigma_fy_n,sigma_fz_n,sigma_tx_nm,sigma_ty_nm,sigma_tz_nm,warn_mask,windows,"
      "balance_samples,balance_force_rms_n,balance_force_rms_tracked_n,balance_torque_rms_nm,"
      "balance_torque_rms_tracked_nm\n";
  set_state_(service_status_t::DEGRADED);
  UpdateCounters();
}

void DriftStage::ReportWaitingForCalibration() {
  if (has_calibration()) return;
  bus_.stats().Error("no calibration", "nothing is tracked until a calibration arrives on " +
                                           config_.channels().calibration() +
                                           " (or start with --calibration FILE)");
}

void DriftStage::UseCalibration(const calibration::Calibration& proto, int64_t version,
                                const std::string& sha256) {
  if (!sha256_.empty() && sha256 == sha256_) return;  // a repeat
  const RobotCalibration cal = CalibrationFromProto(proto, config_.robot());
  CheckCalibrationPlausible(cal, config_);
  auto tracker = std::make_unique<OffsetTracker>(options_, cal);
  tracker->SetPhase(phase_);
  tracker_ = std::move(tracker);
  proto_ = proto;
  calibration_sigma_ = OffsetSigmas(proto);
  version_ = version;
  sha256_ = sha256;
  ++calibrations_;
  warned_.clear();
  bus_.stats().ClearLastError();
  bus_.stats().log().info("calibration version {} ({}) in use: offsets tracked from now on",
                          version, sha256.substr(0, 12));
  set_state_(service_status_t::RUNNING);
  UpdateCounters();
}

void DriftStage::OnCalibration(const MessageInfo& info, const calibration_t& msg) {
  const bool keep = info.signer != nullptr;
  const std::string signer = keep ? *info.signer : std::string("unsigned");
  try {
    int64_t unsigned_last = 0;
    int64_t& last = keep ? last_version_[signer] : unsigned_last;
    if (msg.version <= last) {
      throw std::runtime_error("version " + std::to_string(msg.version) + " from " + signer +
                               " is not above " + std::to_string(last) +
                               ", the last this tracker used from it");
    }
    const CalibrationMessage cal = FromLcm(msg);
    UseCalibration(cal.proto, cal.version, cal.sha256);
    last = msg.version;
  } catch (const std::exception& e) {
    ++refused_;
    bus_.stats().Error("refused calibration",
                       "version " + std::to_string(msg.version) + ": " + e.what());
  }
}

void DriftStage::OnExperiment(const experiment_marker_t& msg) {
  phase_ = msg.start ? static_cast<ExperimentPhase>(msg.phase) : ExperimentPhase::kIdle;
  if (tracker_) tracker_->SetPhase(phase_);
}

void DriftStage::EnableApply(auth::Signer* signer) {
  apply_ = true;
  signer_ = signer;
}

void DriftStage::OnFt(const FtBatch& batch) {
  if (!tracker_) return;
  for (const FtRecord& r : batch) {
    if (!tracker_->AddFt(r.in)) {
      bus_.stats().Drop("out-of-order or non-finite " + inputs_.FtChannel(batch.leg),
                        "utime " + std::to_string(r.in.utime));
    }
  }
}

void DriftStage::OnServo(const ServoInput& in) {
  if (tracker_ && !tracker_->AddServo(in)) {
    bus_.stats().Drop("out-of-order or non-finite servo state",
                      "utime " + std::to_string(in.utime));
  }
}

void DriftStage::OnMocap(const MocapInput& in) {
  if (tracker_ && !tracker_->AddMocap(in)) {
    bus_.stats().Drop("out-of-order or non-finite mocap frame",
                      "utime " + std::to_string(in.utime));
  }
}

void DriftStage::Finish() {
  if (tracker_) tracker_->Finish();
  PublishDrift();
}

void DriftStage::PublishDrift() {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  msg_ = drift_t{};
  // The estimates are given at the newest input the tracker has seen (its clock), the bus's
  // time when it has seen none.
  msg_.utime =
      tracker_ && tracker_->newest_utime() > 0 ? tracker_->newest_utime() : bus_.NowUtime();
  msg_.calibration_version = tracker_ ? version_ : 0;
  msg_.status = tracker_ ? drift_t::OK : drift_t::NO_CALIBRATION;
  const BalanceStats balance = tracker_ ? tracker_->TakeBalance() : BalanceStats{};
  msg_.balance_samples = static_cast<int32_t>(balance.count);
  for (int i = 0; i < 2; ++i) {
    msg_.balance_force_rms_n[i] = balance.count > 0 ? balance.ForceRmsN(i) : nan;
    msg_.balance_torque_rms_nm[i] = balance.count > 0 ? balance.TorqueRmsNm(i) : nan;
  }
  const config::Drift& c = config_.drift();
  const Vec6 min_change = Pair(c.warn_min_force_n(), c.warn_min_torque_nm());
  std::string warn_text;
  std::array<LegDrift, kNumLegs> drift{};
  for (int k = 0; k < kNumLegs; ++k) {
    LegDrift& d = drift[k];
    if (tracker_) {
      d = tracker_->Drift(k, msg_.utime);
      const int mask =
          DriftBeyondCalibration(d, calibration_sigma_[k], c.warn_factor(), min_change);
      msg_.warn_mask[k] = mask;
      for (int i = 0; i < 6; ++i) {
        if ((mask >> i & 1) == 0) continue;
        char text[160];
        std::snprintf(text, sizeof text, "%s%s %s %+.4g +- %.2g (calibration sigma %.2g)",
                      warn_text.empty() ? "" : "; ", std::string(kLegNames[k]).c_str(), kAxes[i],
                      d.change[i], d.sigma[i], calibration_sigma_[k][i]);
        warn_text += text;
      }
    }
    for (int i = 0; i < 6; ++i) {
      msg_.offset_change[k][i] = d.change[i];
      msg_.sigma[k][i] = tracker_ ? d.sigma[i] : nan;
    }
    msg_.windows[k] = static_cast<int32_t>(d.windows);
    msg_.window_s[k] = static_cast<float>(d.window_seconds);
    msg_.last_window_utime[k] = d.last_window_utime;
  }
  if (!warn_text.empty()) msg_.status = drift_t::WARN;
  if (tracker_) {
    // WARN is a transducer that moved beyond its calibration: the operator is to act (README,
    // "Offset drift"), so it shows in the status and the log, once per change of what is beyond.
    const std::string summary = warn_text.empty() ? "" : "offset drift beyond the calibration: ";
    std::string mask_key;
    for (int k = 0; k < kNumLegs; ++k) mask_key += std::to_string(msg_.warn_mask[k]) + ",";
    if (mask_key != warned_) {
      if (!warn_text.empty()) {
        bus_.stats().log().warn("{}{}", summary, warn_text);
      } else if (!warned_.empty()) {
        bus_.stats().log().info("offset drift back within the calibration's sigma");
      }
      warned_ = warn_text.empty() ? "" : mask_key;
    }
    if (warn_text.empty()) {
      bus_.stats().ClearLastError();
      set_state_(service_status_t::RUNNING);
    } else {
      bus_.stats().SetLastError(summary + warn_text);
      set_state_(service_status_t::DEGRADED);
    }
  }
  bus_.Publish(config_.channels().drift(), msg_);
  ++published_;
  char row[1024];
  for (int k = 0; k < kNumLegs; ++k) {
    int n = std::snprintf(row, sizeof row, "%lld,%s,%d", static_cast<long long>(msg_.utime),
                          std::string(kLegNames[k]).c_str(), msg_.status);
    for (int i = 0; i < 6; ++i)
      n += std::snprintf(row + n, sizeof row - n, ",%.9g", msg_.offset_change[k][i]);
    for (int i = 0; i < 6; ++i)
      n += std::snprintf(row + n, sizeof row - n, ",%.9g", msg_.sigma[k][i]);
    n += std::snprintf(row + n, sizeof row - n, ",%d,%d,%d,%.9g,%.9g,%.9g,%.9g\n",
                       msg_.warn_mask[k], msg_.windows[k], msg_.balance_samples,
                       msg_.balance_force_rms_n[0], msg_.balance_force_rms_n[1],
                       msg_.balance_torque_rms_nm[0], msg_.balance_torque_rms_nm[1]);
    csv_.append(row, static_cast<size_t>(n));
  }
  UpdateCounters();
  if (apply_ && tracker_) {
    const int legs =
        LegsToApply(drift, calibration_sigma_, apply_policy_, msg_.utime, last_apply_utime_);
    if (legs != 0) Apply(legs, drift);
  }
}

void DriftStage::Apply(int legs, const std::array<LegDrift, kNumLegs>& drift) {
  calibration::Calibration out;
  const int64_t utime = msg_.utime;
  WithTrackedOffsets(legs, utime, &out);
  calibration::OffsetReestimation* r = out.mutable_offset_reestimation();
  r->set_created_utc(UtcNow());
  r->set_command_line("ftcal-drift --apply");
  // The provenance: per applied leg, the windows its offsets come from and the change.
  std::string text = "offsets applied by ftcal-drift --apply at utime " + std::to_string(utime) +
                     " over version " + std::to_string(version_) + ":";
  for (int k = 0; k < kNumLegs; ++k) {
    if ((legs >> k & 1) == 0) continue;
    const LegDrift& d = drift[k];
    char row[320];
    std::snprintf(row, sizeof row,
                  " %s from %lld windows (%.1f s of data, the last at utime %lld), change "
                  "[%+.4g %+.4g %+.4g] N [%+.4g %+.4g %+.4g] N*m;",
                  std::string(kLegNames[k]).c_str(), static_cast<long long>(d.windows),
                  d.window_seconds, static_cast<long long>(d.last_window_utime), d.change[0],
                  d.change[1], d.change[2], d.change[3], d.change[4], d.change[5]);
    text += row;
  }
  text.pop_back();
  out.add_warning(text);
  // Above the version in use and above every one published here before: a receiver takes
  // only a version above the last it used from this signer, and a calibrator's calibration in
  // between may have a lower number than ours (versions are per signer).
  const int64_t version = std::max(version_, last_applied_version_) + 1;
  out.set_version(static_cast<uint64_t>(version));
  last_apply_utime_ = utime;  // a refusal below waits the interval too
  // In use here first (checked as any calibration is; the tracking restarts relative to it),
  // then published; when this process hears its own message, its hash makes it a repeat.
  std::string bytes;
  out.SerializeToString(&bytes);
  try {
    UseCalibration(out, version, Sha256Hex(bytes));
  } catch (const std::exception& e) {
    bus_.stats().Error("apply refused", std::string("the tracked offsets: ") + e.what());
    return;
  }
  PublishCalibration(bus_, config_.channels().calibration(), out, version, signer_);
  last_applied_version_ = version;
  ++applied_;
  UpdateCounters();
  bus_.stats().log().info("published calibration version {} on {}: {}", version,
                          config_.channels().calibration(), text);
}

int64_t DriftStage::WithTrackedOffsets(int legs, int64_t utime,
                                       calibration::Calibration* out) const {
  *out = proto_;
  calibration::OffsetReestimation* r = out->mutable_offset_reestimation();
  r->Clear();
  const RobotCalibration base = CalibrationFromProto(proto_, config_.robot());
  int determined = 0;
  int64_t windows = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegDrift d = tracker_->Drift(k, utime);
    const bool use = (legs >> k & 1) != 0 && d.windows > 0;
    if (use) windows += d.windows;
    for (int i = 0; i < 6; ++i) {
      r->add_previous_offset(base.leg[k].offset[i]);
      if (!use) {
        // Not applied, or no window of this leg (the data say nothing): the offsets stay.
        r->add_undetermined(std::string(kLegNames[k]) + " " + kAxes[i]);
        continue;
      }
      SetOffsetComponent(i, base.leg[k].offset[i] + d.change[i], d.sigma[i], out->mutable_leg(k));
      ++determined;
    }
  }
  r->set_base_version(proto_.version());
  r->set_standing_poses(0);
  r->set_unloaded_leg_samples(static_cast<uint32_t>(windows));
  r->set_rank(static_cast<uint32_t>(determined));
  return windows;
}

calibration::Calibration DriftStage::TrackedCalibrationProto(
    const std::string& base_path, const std::vector<std::string>& inputs,
    const std::string& command_line) const {
  if (!tracker_) throw std::logic_error("no calibration in use: nothing was tracked");
  calibration::Calibration out;
  const int64_t windows = WithTrackedOffsets((1 << kNumLegs) - 1, tracker_->newest_utime(), &out);
  calibration::OffsetReestimation* r = out.mutable_offset_reestimation();
  if (!base_path.empty()) SetInputFile(base_path, r->mutable_base_calibration());
  for (const std::string& path : inputs) SetInputFile(path, r->add_input());
  r->set_created_utc(UtcNow());
  r->set_command_line(command_line);
  out.add_warning("offsets tracked by ftcal-drift at the end of its input: " +
                  std::to_string(windows) + " windows with a leg in the air and quasi-static" +
                  (r->rank() < 6 * kNumLegs ? "; legs without a window keep their offsets" : ""));
  out.set_version(proto_.version() + 1);
  return out;
}

void DriftStage::UpdateCounters() {
  if (tracker_) {
    const OffsetTrackerCounters& c = tracker_->counters();
    *counters_.windows = c.windows_used;
    *counters_.bins_air = c.bins_air;
    *counters_.bins_loaded = c.bins_loaded;
    *counters_.bins_moving = c.bins_moving;
    *counters_.bins_no_servo = c.bins_no_servo;
    *counters_.bins_no_attitude = c.bins_no_attitude;
  }
  *counters_.warn = msg_.status == drift_t::WARN ? 1 : 0;
  *counters_.version = tracker_ ? version_ : 0;
  *counters_.applied = applied_;
}

}  // namespace ftcal
