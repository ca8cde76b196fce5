#include "corrector/corrector_stage.h"

#include <stdexcept>

#include "ftcal/calibration_io.h"
#include "ftcal/config.h"

namespace ftcal {

CorrectorOptions CorrectorOptionsFromConfig(const config::Corrector& c) {
  CorrectorOptions o;
  o.max_ft_age_s = c.max_ft_age_s();
  o.max_servo_age_s = c.max_servo_age_s();
  o.max_mocap_age_s = c.max_mocap_age_s();
  return o;
}

CorrectorStage::CorrectorStage(const config::Config& config, Bus& bus, StateSink set_state)
    : config_(config),
      bus_(bus),
      set_state_(std::move(set_state)),
      inputs_(config),
      corrector_(CorrectorOptionsFromConfig(config.corrector())) {
  ServiceStats& st = bus.stats();
  counters_ = {&st.Counter("corrected"),         &st.Counter("before_calibration"),
               &st.Counter("calibrations"),      &st.Counter("calibrations_refused"),
               &st.Counter("drop_out_of_order"), &st.Counter("drop_non_finite"),
               &st.Counter("stale_outputs"),     &st.Counter("calibration_version")};
  const auto& ch = config.channels();
  inputs_.Subscribe(bus, {[this](const FtBatch& batch) { OnFt(batch); },
                          [this](const ServoInput& in) { OnServo(in); },
                          [this](const MocapInput& in) { OnMocap(in); }});
  // A sample that waited in the receive queue longer than max_ft_age_s would only give a stale
  // wrench. Live, when the process falls behind (6 x 7 kHz on two busy cores did), it sheds
  // those instead of correcting its way through a standing queue: measured before, the wrenches
  // came out 3.6 s late at p50. The queue delay is on this host's clock alone (LCM's receive
  // stamp to the handler), so clock offsets between hosts do not enter.
  if (!bus.IsReplay()) {
    const auto max_queue_us = static_cast<int64_t>(1e6 * config.corrector().max_ft_age_s());
    for (int k = 0; k < kNumLegs; ++k) bus.ShedLate(inputs_.FtChannel(k), max_queue_us);
  }
  // Signed, fresh (a calibration is published once, when it is made) and of a version above
  // the last one this corrector used from its signer (OnCalibration).
  bus.SubscribeSigned<calibration_t>(
      ch.calibration(), &verifier_,
      static_cast<int64_t>(config_.auth().calibration_window_s() * 1e6),
      config_.auth().allow_unsigned(),
      [this](const MessageInfo& i, const calibration_t& m) { OnCalibration(i, m); });
  set_state_(service_status_t::DEGRADED);
  UpdateCounters();
}

void CorrectorStage::ReportWaitingForCalibration() {
  if (has_calibration()) return;
  bus_.stats().Error("no calibration", "nothing is published until a calibration arrives on " +
                                           config_.channels().calibration() +
                                           " (or start with --calibration FILE)");
  UpdateCounters();
}

void CorrectorStage::UseCalibration(const calibration::Calibration& proto, int64_t version,
                                    const std::string& sha256) {
  if (!calibration_sha256_.empty() && sha256 == calibration_sha256_) return;  // a repeat
  const RobotCalibration cal = CalibrationFromProto(proto, config_.robot());
  CheckCalibrationPlausible(cal, config_);
  corrector_.SetCalibration(cal, version);
  calibration_sha256_ = sha256;
  ++calibrations_;
  bus_.stats().log().info("calibration version {} ({}) in use", version, sha256.substr(0, 12));
  set_state_(service_status_t::RUNNING);
  UpdateCounters();
}

void CorrectorStage::OnCalibration(const MessageInfo& info, const calibration_t& msg) {
  const std::string& channel = config_.channels().calibration();
  // An unsigned calibration (auth.allow_unsigned, the loopback twin) is anyone's: its version
  // binds nothing, and none is kept.
  const bool keep = info.signer != nullptr;
  const std::string signer = keep ? *info.signer : std::string("unsigned");
  try {
    int64_t unsigned_last = 0;
    int64_t& last = keep ? last_version_[signer] : unsigned_last;
    if (const auto& store = bus_.seen_store(); store && keep) {
      last = std::max(last, store->Version(channel, signer));
    }
    if (msg.version <= last) {
      throw std::runtime_error("version " + std::to_string(msg.version) + " from " + signer +
                               " is not above " + std::to_string(last) +
                               ", the last this corrector used from it (an old calibration "
                               "sent again?)");
    }
    const CalibrationMessage cal = FromLcm(msg);
    UseCalibration(cal.proto, cal.version, cal.sha256);
    last = msg.version;
    if (const auto& store = bus_.seen_store(); store && keep) {
      store->RaiseVersion(channel, signer, msg.version);
    }
  } catch (const std::exception& e) {
    ++refused_;
    UpdateCounters();
    // Every refusal is logged (rare, and the operator must see it); the old calibration stays.
    bus_.stats().log().error(
        "calibration version {} refused: {}; {}", msg.version, e.what(),
        corrector_.has_calibration()
            ? "keeping version " + std::to_string(corrector_.calibration_version())
            : std::string("still none in use"));
    bus_.stats().Error("refused calibration",
                       "version " + std::to_string(msg.version) + ": " + e.what());
  }
}

void CorrectorStage::OnServo(const ServoInput& in) {
  const CorrectorCounters before = corrector_.counters();
  if (!corrector_.AddServo(in)) {
    bus_.stats().Drop(corrector_.counters().non_finite > before.non_finite
                          ? "non-finite servo state"
                          : "out-of-order servo state",
                      "utime " + std::to_string(in.utime));
  }
  UpdateCounters();
}

void CorrectorStage::OnMocap(const MocapInput& in) {
  const CorrectorCounters before = corrector_.counters();
  if (!corrector_.AddMocap(in)) {
    bus_.stats().Drop(corrector_.counters().non_finite > before.non_finite
                          ? "non-finite mocap frame"
                          : "out-of-order mocap frame",
                      "utime " + std::to_string(in.utime));
  }
  UpdateCounters();
}

void CorrectorStage::OnFt(const FtBatch& batch) {
  const int leg = batch.leg;
  ClearLcm(leg, batch.receipt_utime, &wrench_msg_);
  ClearLcm(corrector_.calibration_version(), &sum_msg_);
  WrenchSum sum;
  for (const FtRecord& r : batch) {
    const FtInput& in = r.in;
    const CorrectorCounters before = corrector_.counters();
    const bool saturated = (in.flags & ft_batch_t::FLAG_SATURATED) != 0;
    if (!corrector_.AddFt(in, saturated, &out_)) {
      const CorrectorCounters& now = corrector_.counters();
      if (now.non_finite > before.non_finite) {
        bus_.stats().Drop("non-finite " + inputs_.FtChannel(leg),
                          "utime " + std::to_string(in.utime));
      } else if (now.out_of_order > before.out_of_order) {
        bus_.stats().Drop("out-of-order " + inputs_.FtChannel(leg),
                          "utime " + std::to_string(in.utime));
      }
      continue;
    }
    if (out_.flags & (kFlagStaleFt | kFlagStaleServo | kFlagStaleMocap)) ++stale_;
    AppendLcm(LegWrenchOf(out_), &wrench_msg_);
    ++leg_samples_;
    while (corrector_.NextSum(&sum)) AppendSum(sum);
  }
  // One CONTACT_WRENCH per FT message (its samples, corrected), then the sums it completed.
  if (wrench_msg_.n > 0) bus_.Publish(config_.channels().contact_wrench(), wrench_msg_, buffer_);
  if (sum_msg_.n > 0) bus_.Publish(config_.channels().contact_wrench_sum(), sum_msg_, buffer_);
  UpdateCounters();
}

void CorrectorStage::FinishSums() {
  ClearLcm(corrector_.calibration_version(), &sum_msg_);
  WrenchSum sum;
  while (corrector_.NextSum(&sum, /*input_ended=*/true)) AppendSum(sum);
  if (sum_msg_.n > 0) bus_.Publish(config_.channels().contact_wrench_sum(), sum_msg_, buffer_);
  UpdateCounters();
}

void CorrectorStage::AppendSum(const WrenchSum& sum) {
  if (sum_msg_.n == contact_wrench_sum_t::MAX_N) {
    bus_.Publish(config_.channels().contact_wrench_sum(), sum_msg_, buffer_);
    ClearLcm(corrector_.calibration_version(), &sum_msg_);
  }
  AppendLcm(sum, &sum_msg_);
  ++sums_;
}

void CorrectorStage::UpdateCounters() {
  const CorrectorCounters& c = corrector_.counters();
  *counters_.corrected = c.corrected;
  *counters_.no_calibration = c.no_calibration;
  *counters_.calibrations = calibrations_;
  *counters_.calibrations_refused = refused_;
  *counters_.drop_out_of_order = c.out_of_order;
  *counters_.drop_non_finite = c.non_finite;
  *counters_.stale = stale_;
  *counters_.version = corrector_.has_calibration() ? corrector_.calibration_version() : 0;
}

}  // namespace ftcal
