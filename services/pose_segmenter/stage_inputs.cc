#include "pose_segmenter/stage_inputs.h"

#include <cmath>
#include <stdexcept>

namespace ftcal {

StageInputs::StageInputs(const config::Config& config)
    : body_name_(config.mocap().body_name()),
      chassis_markers_(static_cast<int>(config.robot().chassis_marker_count())) {
  if (config.robot().leg_size() != kNumLegs) {
    throw std::invalid_argument("config: robot.leg: " + std::to_string(kNumLegs) +
                                " legs expected, got " +
                                std::to_string(config.robot().leg_size()));
  }
  for (int k = 0; k < kNumLegs; ++k) {
    if (config.robot().leg(k).name() != kLegNames[k]) {
      throw std::invalid_argument("config: robot.leg[" + std::to_string(k) + "].name: '" +
                                  config.robot().leg(k).name() + "', expected '" +
                                  std::string(kLegNames[k]) + "'");
    }
    ft_channel_[k] = config.channels().ft_prefix() + std::string(kLegNames[k]);
  }
}

FtInput StageInputs::FromFt(int leg, const ft_sample_t& msg) const {
  if (msg.leg != kLegNames[leg]) {
    throw BadInput("leg name not the channel's on " + ft_channel_[leg],
                   "message names leg '" + msg.leg + "'");
  }
  FtInput in;
  in.utime = msg.utime;
  in.leg = leg;
  for (int i = 0; i < 6; ++i) in.wrench[i] = msg.wrench[i];
  in.flags = msg.flags;
  return in;
}

ServoInput StageInputs::FromServo(const servo_state_t& msg) const {
  ServoInput in;
  in.utime = msg.utime;
  std::array<bool, kNumLegs> seen{};
  for (int i = 0; i < msg.num_servos; ++i) {
    const auto k = LegIndex(msg.leg[i]);
    if (!k) {
      throw BadInput("unknown leg in servo state", "servo " + std::to_string(i) + " (id " +
                                                       std::to_string(msg.id[i]) +
                                                       ") names leg '" + msg.leg[i] + "'");
    }
    if (seen[*k]) {
      throw BadInput("duplicate leg in servo state", "leg " + msg.leg[i] + " twice");
    }
    seen[*k] = true;
    in.angle_rad[*k] = msg.angle_rad[i];
  }
  for (int k = 0; k < kNumLegs; ++k) {
    if (!seen[k]) {
      throw BadInput("servo state without every leg",
                     "no servo for leg " + std::string(kLegNames[k]));
    }
  }
  return in;
}

std::optional<MocapInput> StageInputs::FromMocap(const mocap_body_t& msg) const {
  if (msg.body != body_name_) return std::nullopt;
  MocapInput in;
  in.utime = msg.utime;
  in.tracked = msg.tracked;
  if (msg.tracked) {
    const Eigen::Vector4d q(msg.q_wc[0], msg.q_wc[1], msg.q_wc[2], msg.q_wc[3]);
    if (q.allFinite() && std::abs(q.norm() - 1.0) > 1e-3) {
      throw BadInput("mocap q_wc not a unit quaternion",
                     "|q_wc| = " + std::to_string(q.norm()) + " at utime " +
                         std::to_string(msg.utime));
    }
    // A non-finite quaternion stays non-finite: the aligner/corrector count and drop it.
    in.R_WC = q.allFinite() ? QuaternionToRotation(q) : Mat3::Constant(std::nan(""));
  }
  bool all = msg.tracked && msg.num_markers >= chassis_markers_;
  for (int i = 0; all && i < msg.num_markers; ++i) all = msg.marker_tracked[i];
  in.markers_ok = all;
  return in;
}

void RotationToQuaternionArray(const Mat3& R, double q_wxyz[4]) {
  const Eigen::Vector4d q = RotationToQuaternion(R);
  for (int i = 0; i < 4; ++i) q_wxyz[i] = q[i];
}

}  // namespace ftcal
