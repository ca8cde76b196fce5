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
               &st.Counter("stale_outputs")};
  msg_.num_legs = kNumLegs;
  msg_.leg.assign(kLegNames.begin(), kLegNames.end());
  msg_.wrench_w.assign(kNumLegs, std::vector<double>(6));
  msg_.ft_age_s.assign(kNumLegs, 0.0);

  const auto& ch = config.channels();
  for (int k = 0; k < kNumLegs; ++k) {
    bus.Subscribe<ft_sample_t>(inputs_.FtChannel(k),
                               [this, k](const MessageInfo&, const ft_sample_t& m) { OnFt(k, m); });
  }
  bus.Subscribe<servo_state_t>(ch.servo_state(),
                               [this](const MessageInfo&, const servo_state_t& m) { OnServo(m); });
  bus.Subscribe<mocap_body_t>(ch.mocap_body(),
                              [this](const MessageInfo&, const mocap_body_t& m) { OnMocap(m); });
  // Signed; no time window, so a calibration replayed from a recording still applies.
  bus.SubscribeSigned<calibration_t>(
      ch.calibration(), &verifier_, /*window_us=*/0, config_.auth().allow_unsigned(),
      [this](const MessageInfo&, const calibration_t& m) { OnCalibration(m); });
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
  corrector_.SetCalibration(cal, version);
  calibration_sha256_ = sha256;
  ++calibrations_;
  bus_.stats().log().info("calibration version {} ({}) in use", version, sha256.substr(0, 12));
  set_state_(service_status_t::RUNNING);
  UpdateCounters();
}

void CorrectorStage::OnCalibration(const calibration_t& msg) {
  try {
    if (msg.size != static_cast<int32_t>(msg.data.size())) {
      throw std::runtime_error("size field " + std::to_string(msg.size) + " but " +
                               std::to_string(msg.data.size()) + " bytes");
    }
    const std::string bytes(msg.data.begin(), msg.data.end());
    const std::string sha = Sha256Hex(bytes);
    if (sha != msg.content_sha256) {
      throw std::runtime_error("content_sha256 " + msg.content_sha256 +
                               " does not match the data's " + sha);
    }
    calibration::Calibration proto;
    if (!proto.ParseFromString(bytes)) {
      throw std::runtime_error("data is not a binary ftcal.calibration.Calibration");
    }
    UseCalibration(proto, msg.version, sha);
  } catch (const std::exception& e) {
    ++refused_;
    UpdateCounters();
    // Every refusal is logged (rare, and the operator must see it); the old calibration stays.
    bus_.stats().log().error("calibration version {} refused: {}; {}", msg.version, e.what(),
                             corrector_.has_calibration()
                                 ? "keeping version " + std::to_string(corrector_.calibration_version())
                                 : std::string("still none in use"));
    bus_.stats().Error("refused calibration", "version " + std::to_string(msg.version) + ": " +
                                                  e.what());
  }
}

void CorrectorStage::OnServo(const servo_state_t& msg) {
  const CorrectorCounters before = corrector_.counters();
  if (!corrector_.AddServo(inputs_.FromServo(msg))) {
    bus_.stats().Drop(corrector_.counters().non_finite > before.non_finite
                          ? "non-finite servo state"
                          : "out-of-order servo state",
                      "utime " + std::to_string(msg.utime));
  }
  UpdateCounters();
}

void CorrectorStage::OnMocap(const mocap_body_t& msg) {
  const auto in = inputs_.FromMocap(msg);
  if (!in) return;
  const CorrectorCounters before = corrector_.counters();
  if (!corrector_.AddMocap(*in)) {
    bus_.stats().Drop(corrector_.counters().non_finite > before.non_finite
                          ? "non-finite mocap frame"
                          : "out-of-order mocap frame",
                      "utime " + std::to_string(msg.utime));
  }
  UpdateCounters();
}

void CorrectorStage::OnFt(int leg, const ft_sample_t& msg) {
  const FtInput in = inputs_.FromFt(leg, msg);
  const CorrectorCounters before = corrector_.counters();
  const bool saturated = (msg.flags & ft_sample_t::FLAG_SATURATED) != 0;
  if (!corrector_.AddFt(in, saturated, &out_)) {
    const CorrectorCounters& now = corrector_.counters();
    if (now.non_finite > before.non_finite) {
      bus_.stats().Drop("non-finite " + inputs_.FtChannel(leg), "utime " + std::to_string(msg.utime));
    } else if (now.out_of_order > before.out_of_order) {
      bus_.stats().Drop("out-of-order " + inputs_.FtChannel(leg), "utime " + std::to_string(msg.utime));
    }
    UpdateCounters();
    return;
  }
  msg_.utime = out_.utime;
  msg_.updated_leg = out_.updated_leg;
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) msg_.wrench_w[k][i] = out_.wrench_W[k][i];
    msg_.ft_age_s[k] = out_.ft_age_s[k];
  }
  for (int i = 0; i < 6; ++i) {
    msg_.total_w[i] = out_.total_W[i];
    msg_.residual_w[i] = out_.residual_W[i];
  }
  msg_.calibration_version = out_.calibration_version;
  msg_.servo_age_s = out_.servo_age_s;
  msg_.mocap_age_s = out_.mocap_age_s;
  msg_.flags = out_.flags;
  if (out_.flags & (kFlagStaleFt | kFlagStaleServo | kFlagStaleMocap)) ++stale_;
  // Encode into a reused buffer (Bus::Publish would allocate one per message).
  const int size = msg_.getEncodedSize();
  if (buffer_.size() < static_cast<size_t>(size)) buffer_.resize(static_cast<size_t>(size));
  if (msg_.encode(buffer_.data(), 0, size) != size) {
    bus_.stats().Error("encode contact_wrench_t", "message did not encode");
  } else {
    bus_.PublishRaw(config_.channels().contact_wrench(), buffer_.data(), size);
  }
  UpdateCounters();
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
}

}  // namespace ftcal
