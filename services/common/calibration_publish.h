// Publishing a calibration on CALIBRATION: shared by the live calibrator and ftcal-drift
// --apply, the two publishers of the channel (docs/architecture.md, "Who publishes
// CALIBRATION"). Signed with the publisher's key when it has one (README, "Signed channels");
// without one it goes out bare, which receivers refuse unless auth.allow_unsigned.
#pragma once

#include <cstdint>
#include <string>

#include "common/bus.h"
#include "common/envelope.h"
#include "common/messages.h"
#include "ftcal/calibration_t.hpp"
#include "proto/calibration.pb.h"

namespace ftcal {

// Publishes `proto` as version `version`, stamped and signed at the bus's now; returns the
// message (its content_sha256 is the calibration's identity, what a receiver compares).
inline calibration_t PublishCalibration(Bus& bus, const std::string& channel,
                                        const calibration::Calibration& proto, int64_t version,
                                        auth::Signer* signer) {
  const calibration_t msg = ToLcm(proto, version, bus.NowUtime());
  if (signer != nullptr) {
    bus.PublishSigned(channel, msg, *signer);
  } else {
    bus.Publish(channel, msg);
  }
  return msg;
}

}  // namespace ftcal
