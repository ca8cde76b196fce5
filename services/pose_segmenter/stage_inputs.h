// The boundary between the device messages (lcmtypes) and libcal's transport-free inputs,
// shared by ftcal-pose-segmenter and ftcal-corrector. Validation happens here: a message from
// an unknown leg, on the wrong channel, without every leg, or with a quaternion that is not
// one is refused with a BadInput naming what was wrong; non-finite numbers are passed on for
// the aligner/corrector to count (they own the drop rule).
#pragma once

#include <array>
#include <optional>
#include <string>

#include "common/bus.h"
#include "ftcal/aligner.h"
#include "ftcal/ft_sample_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "proto/config.pb.h"

namespace ftcal {

class StageInputs {
 public:
  // Throws std::invalid_argument when the config's legs are not kLegNames in order.
  explicit StageInputs(const config::Config& config);

  // FT_<LEG> channel name of leg k.
  const std::string& FtChannel(int k) const { return ft_channel_[k]; }
  // `leg` is the channel's leg; the message must name the same one.
  FtInput FromFt(int leg, const ft_sample_t& msg) const;
  ServoInput FromServo(const servo_state_t& msg) const;
  // nullopt for another rigid body than the config's chassis body.
  std::optional<MocapInput> FromMocap(const mocap_body_t& msg) const;

 private:
  std::array<std::string, kNumLegs> ft_channel_;
  std::string body_name_;
  int chassis_markers_;
};

// R as the (w, x, y, z) quaternion the lcmtypes carry.
void RotationToQuaternionArray(const Mat3& R, double q_wxyz[4]);

}  // namespace ftcal
