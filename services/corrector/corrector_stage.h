// ftcal-corrector's work, transport-agnostic through the Bus (docs/method.md, "Correction"):
// every FT_<LEG> message becomes one CONTACT_WRENCH with its samples' ground-contact wrenches
// in W about the CoM (libcal's Corrector), using SERVO_STATE for the leg phase and MOCAP_BODY
// for R_WC; the six legs' sums at the pace leg's sample instants (Corrector::NextSum) that the
// message completed go out together on one CONTACT_WRENCH_SUM.
//
// Calibration: from --calibration FILE at start and/or any CALIBRATION message, picked up
// without a restart. A message is checked (its SHA-256, the protobuf, CalibrationFromProto
// against the config, the corrector's own checks); a bad one is refused with its reason
// logged and kept as last_error, and the calibration in use stays. A message with the hash of
// the calibration in use is a repeat and changes nothing. A message is taken only fresh
// (auth.calibration_window_s) and with a version above the last one this corrector used from
// the same signer, remembered across restarts: a captured old calibration cannot come back. Until a
// calibration is in use nothing is published and the state is DEGRADED with last_error saying why.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <string>

#include "common/bus.h"
#include "common/messages.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/corrector.h"
#include "ftcal/service_status_t.hpp"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

CorrectorOptions CorrectorOptionsFromConfig(const config::Corrector& corrector);

class CorrectorStage {
 public:
  using StateSink = std::function<void(int8_t service_state)>;
  // Subscribes its handlers on `bus`; reports RUNNING/DEGRADED through `set_state`.
  CorrectorStage(const config::Config& config, Bus& bus, StateSink set_state);

  // Validates and adopts a calibration; throws std::runtime_error with the reason (nothing
  // changes then). `sha256` identifies it (repeats are ignored); `version` is published.
  void UseCalibration(const calibration::Calibration& proto, int64_t version,
                      const std::string& sha256);
  bool has_calibration() const { return corrector_.has_calibration(); }
  // Leg-samples published on CONTACT_WRENCH, and sums on CONTACT_WRENCH_SUM.
  int64_t leg_samples() const { return leg_samples_; }
  int64_t sums() const { return sums_; }
  // At the end of the input (ServiceApp::AtInputEnd): the sums still waiting for a leg's next
  // sample, which will not come, from the samples there are (Corrector::NextSum).
  void FinishSums();
  // Says in the status (last error, DEGRADED) why nothing is published yet. Called once the
  // start-up calibration, if any, has been applied, so a --calibration start reports no error.
  void ReportWaitingForCalibration();

 private:
  void OnFt(const FtBatch& batch);
  void OnServo(const ServoInput& in);
  void OnMocap(const MocapInput& in);
  void OnCalibration(const MessageInfo& info, const calibration_t& msg);
  void UpdateCounters();
  // Adds a sum to sum_msg_, publishing it first when full (contact_wrench_sum_t::MAX_N).
  void AppendSum(const WrenchSum& sum);

  const config::Config& config_;
  // CALIBRATION is a signed channel (common/envelope.h).
  auth::Verifier verifier_ = auth::Verifier::FromConfig(config_);
  Bus& bus_;
  StateSink set_state_;
  DeviceInputs inputs_;
  Corrector corrector_;
  std::string calibration_sha256_;
  // Per signer (the trusted key's name), the last calibration version put in use; also on disk
  // in a live process (Bus::seen_store), so a restart refuses what it used before.
  std::map<std::string, int64_t> last_version_;
  ContactWrenches out_;
  contact_wrench_t wrench_msg_;   // reused: its vectors keep their capacity
  contact_wrench_sum_t sum_msg_;  // reused too
  // What the outputs are encoded into (Bus::Publish with a buffer): the hot path allocates
  // nothing.
  std::vector<uint8_t> buffer_;
  struct Counters {
    int64_t *corrected, *no_calibration, *calibrations, *calibrations_refused, *drop_out_of_order,
        *drop_non_finite, *stale, *version;
  } counters_{};
  int64_t calibrations_ = 0, refused_ = 0, stale_ = 0, leg_samples_ = 0, sums_ = 0;
};

}  // namespace ftcal
