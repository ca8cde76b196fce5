// The robot and its devices in the config: ports, poses, ATI transducers, servos, the leg
// table, motion capture (QTM, NatNet) and the Dynamixel bus. Each check names the field, its
// file position and the value (config_internal.h's Node).
#include <arpa/inet.h>

#include <cctype>
#include <cmath>
#include <cstring>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "config_internal.h"

namespace ftcal::config_detail {

void ValidatePort(const Node& node, std::string_view name, uint32_t port) {
  if (port < 1 || port > 65535) {
    node.Error(name, "port must be in 1..65535, got " + std::to_string(port));
  }
}

void ValidateVec3(const Node& node, const config::Vec3& v) {
  node.Finite("x", v.x());
  node.Finite("y", v.y());
  node.Finite("z", v.z());
}

// Why a row-major 3x3 is not in SO(3), or empty when it is (to kRotationTolerance).
std::string RotationProblem(const Mat3& R) {
  const double ortho = (R.transpose() * R - Mat3::Identity()).cwiseAbs().maxCoeff();
  if (ortho > kRotationTolerance) {
    return "not a rotation matrix (|R^T R - I| = " + FormatNumber(ortho) + ")";
  }
  const double det = R.determinant();
  if (std::abs(det - 1.0) > kRotationTolerance) {
    return "not a rotation matrix (det R = " + FormatNumber(det) + ", a reflection)";
  }
  return {};
}

Mat3 RowMajor(const config::Pose& pose) {
  Mat3 R;
  for (int i = 0; i < 9; ++i) R(i / 3, i % 3) = pose.rotation_row_major(i);
  return R;
}

void ValidatePose(const Node& node, const config::Pose& pose) {
  if (!pose.has_translation_m()) {
    node.Missing("translation_m");
  } else {
    ValidateVec3(node.Child("translation_m", pose.translation_m()), pose.translation_m());
  }
  const bool has_matrix = pose.rotation_row_major_size() > 0;
  if (has_matrix && pose.has_rpy_deg()) {
    node.Error("rpy_deg", "give the rotation either as rotation_row_major or as rpy_deg, not both");
    return;
  }
  if (!has_matrix && !pose.has_rpy_deg()) {
    node.SelfError("missing rotation: give rotation_row_major (9 numbers) or rpy_deg");
    return;
  }
  if (pose.has_rpy_deg()) {
    ValidateVec3(node.Child("rpy_deg", pose.rpy_deg()), pose.rpy_deg());
    return;
  }
  if (pose.rotation_row_major_size() != 9) {
    node.Error("rotation_row_major", "needs 9 numbers (row-major 3x3), got " +
                                         std::to_string(pose.rotation_row_major_size()));
    return;
  }
  bool finite = true;
  for (int i = 0; i < 9; ++i) {
    finite = node.Finite("rotation_row_major", pose.rotation_row_major(i), i) && finite;
  }
  if (!finite) return;
  const std::string problem = RotationProblem(RowMajor(pose));
  if (!problem.empty()) node.Error("rotation_row_major", problem);
}

void ValidateAti(const Node& node, const config::AtiTransducer& ati) {
  if (!ati.has_address()) {
    node.Missing("address");
  } else {
    in_addr addr{};
    if (inet_pton(AF_INET, ati.address().c_str(), &addr) != 1) {
      node.Error("address", "not an IPv4 address: '" + ati.address() + "'");
    }
  }
  ValidatePort(node, "rdt_port", ati.rdt_port());
  ValidatePort(node, "http_port", ati.http_port());
  if (ati.sign() != 1 && ati.sign() != -1) {
    node.Error("sign", "must be +1 or -1, got " + std::to_string(ati.sign()));
  }
  if (ati.has_counts_per_force()) node.Positive("counts_per_force", ati.counts_per_force());
  if (ati.has_counts_per_torque()) node.Positive("counts_per_torque", ati.counts_per_torque());
  // The Net F/T's RDT buffer size (comrdtbsiz) ranges over 1..40 (docs/device-protocols.md §1.3).
  if (ati.has_records_per_datagram() &&
      (ati.records_per_datagram() < 1 || ati.records_per_datagram() > 40)) {
    node.Error("records_per_datagram",
               "must be in 1..40 (1: real-time mode; else the box's RDT buffer size), got " +
                   std::to_string(ati.records_per_datagram()));
  }
  if (ati.rated_range_size() != 0 && ati.rated_range_size() != 6) {
    node.Error("rated_range", "needs 0 or 6 entries [Fx Fy Fz Tx Ty Tz], got " +
                                  std::to_string(ati.rated_range_size()));
  } else {
    for (int i = 0; i < ati.rated_range_size(); ++i) {
      const double v = ati.rated_range(i);
      if (node.Finite("rated_range", v, i) && !(v > 0.0)) {
        node.Error("rated_range", "must be > 0, got " + FormatNumber(v), i);
      } else if (std::isfinite(v) && !(v >= kMinRatedRange && v <= kMaxRatedRange)) {
        // ATI's smallest transducer (Nano17) is rated 0.12 N*m, its largest (Omega250) 16 kN.
        node.Error("rated_range",
                   "must be in [" + FormatNumber(kMinRatedRange) + ", " +
                       FormatNumber(kMaxRatedRange) + "] N or N*m, got " + FormatNumber(v),
                   i);
      }
    }
  }
}

// A transducer more than this from the body origin is a typo (a hip 2 km away), not a robot.
void ValidateTransducerOffset(const Node& node, const config::Pose& pose) {
  if (!pose.has_translation_m()) return;
  const auto& t = pose.translation_m();
  const double d = std::sqrt(t.x() * t.x() + t.y() * t.y() + t.z() * t.z());
  if (std::isfinite(d) && d > kMaxTransducerDistanceM) {
    node.Error("translation_m", "is " + FormatNumber(d) + " m from the body origin; more than " +
                                    FormatNumber(kMaxTransducerDistanceM) +
                                    " m is not a leg of this robot (units are metres)");
  }
}

void ValidateServo(const Node& node, const config::Servo& servo) {
  if (!servo.has_id()) {
    node.Missing("id");
  } else if (servo.id() > 252) {
    // Dynamixel protocol 2.0: 253 is reserved and 254 is the broadcast id.
    node.Error("id", "Dynamixel id must be in 0..252, got " + std::to_string(servo.id()));
  }
  if (servo.direction() != 1 && servo.direction() != -1) {
    node.Error("direction", "must be +1 or -1, got " + std::to_string(servo.direction()));
  }
  if (servo.zero_count() < 0) {
    node.Error("zero_count", "must be >= 0, got " + std::to_string(servo.zero_count()));
  }
  const bool min_finite = node.Finite("min_angle_rad", servo.min_angle_rad());
  const bool max_finite = node.Finite("max_angle_rad", servo.max_angle_rad());
  const bool finite = min_finite && max_finite;
  if (finite && !(servo.min_angle_rad() < servo.max_angle_rad())) {
    node.Error("max_angle_rad", "must be greater than min_angle_rad (" +
                                    FormatNumber(servo.min_angle_rad()) + "), got " +
                                    FormatNumber(servo.max_angle_rad()));
  }
}

std::string LegOrder() {
  std::string s;
  for (std::string_view n : kLegNames) s += (s.empty() ? "" : " ") + std::string(n);
  return s;
}

void ValidateRobot(const Node& node, const config::Robot& robot) {
  if (!robot.has_total_mass_kg()) {
    node.Missing("total_mass_kg");
  } else {
    node.Positive("total_mass_kg", robot.total_mass_kg());
    if (robot.total_mass_kg() > kMaxRobotMassKg) {
      node.Error("total_mass_kg", "must be at most " + FormatNumber(kMaxRobotMassKg) +
                                      " kg (units are kg), got " +
                                      FormatNumber(robot.total_mass_kg()));
    }
  }
  if (node.Finite("g0_m_s2", robot.g0_m_s2()) &&
      !(robot.g0_m_s2() > 9.7 && robot.g0_m_s2() < 9.9)) {
    node.Error("g0_m_s2", "must be in (9.7, 9.9) m/s^2 (Earth's surface), got " +
                              FormatNumber(robot.g0_m_s2()));
  }
  if (robot.chassis_marker_count() < 3) {
    node.Error("chassis_marker_count", "a rigid body needs at least 3 markers, got " +
                                           std::to_string(robot.chassis_marker_count()));
  }

  std::array<int, kNumLegs> seen_at;
  seen_at.fill(-1);
  std::vector<std::pair<uint32_t, int>> servo_ids;  // id, leg index
  for (int i = 0; i < robot.leg_size(); ++i) {
    const config::Leg& leg = robot.leg(i);
    const Node leg_node = node.Child("leg", i, leg);
    if (!leg.has_name()) {
      leg_node.Missing("name");
    } else {
      const std::optional<int> k = LegIndex(leg.name());
      if (!k) {
        leg_node.Error("name", "unknown leg '" + leg.name() + "' (legs are " + LegOrder() + ")");
      } else if (seen_at[*k] >= 0) {
        leg_node.Error("name", "duplicate leg '" + leg.name() + "' (already given as " +
                                   node.FieldPath("leg", seen_at[*k]) + ")");
      } else {
        seen_at[*k] = i;
        if (*k != i) {
          leg_node.Error("name", "leg '" + leg.name() + "' listed at position " +
                                     std::to_string(i) + ": legs must be listed in the order " +
                                     LegOrder());
        }
      }
    }
    if (!leg.has_servo()) {
      leg_node.Missing("servo");
    } else {
      const Node servo_node = leg_node.Child("servo", leg.servo());
      ValidateServo(servo_node, leg.servo());
      if (leg.servo().has_id()) {
        for (const auto& [id, other] : servo_ids) {
          if (id == leg.servo().id()) {
            servo_node.Error("id", "servo id " + std::to_string(id) + " already used by " +
                                       node.FieldPath("leg", other));
          }
        }
        servo_ids.emplace_back(leg.servo().id(), i);
      }
    }
    if (!leg.has_x_b_ft()) {
      leg_node.Missing("x_b_ft");
    } else {
      ValidatePose(leg_node.Child("x_b_ft", leg.x_b_ft()), leg.x_b_ft());
      ValidateTransducerOffset(leg_node.Child("x_b_ft", leg.x_b_ft()), leg.x_b_ft());
    }
    if (!leg.has_ati()) {
      leg_node.Missing("ati");
    } else {
      ValidateAti(leg_node.Child("ati", leg.ati()), leg.ati());
    }
  }
  std::string missing;
  for (int k = 0; k < kNumLegs; ++k) {
    if (seen_at[k] < 0) missing += (missing.empty() ? "" : " ") + std::string(kLegNames[k]);
  }
  if (!missing.empty()) {
    node.SelfError("missing leg(s) " + missing + " (expected exactly the legs " + LegOrder() +
                   ", in that order)");
  } else if (robot.leg_size() != kNumLegs) {
    node.SelfError("expected exactly " + std::to_string(kNumLegs) + " legs, got " +
                   std::to_string(robot.leg_size()));
  }
}

void ValidateNatNet(const Node& node, const config::NatNet& n) {
  if (n.server_address().empty()) node.Missing("server_address");
  ValidatePort(node, "command_port", n.command_port());
  ValidatePort(node, "data_port", n.data_port());
  if (n.up_axis() != "Y" && n.up_axis() != "Z") {
    node.Error("up_axis", "must be \"Y\" or \"Z\", got \"" + n.up_axis() + "\"");
  }
  const std::string& v = n.bitstream_version();
  if (!v.empty() && !(v.size() >= 3 && (v[0] == '3' || v[0] == '4') && v[1] == '.' &&
                      v.find_first_not_of("0123456789.") == std::string::npos)) {
    node.Error("bitstream_version",
               "must be a NatNet 3.x or 4.x version such as \"4.1\", got \"" + v + "\"");
  }
  if (!v.empty() && n.multicast()) {
    node.Error("bitstream_version", "only a unicast client can choose the bitstream (multicast)");
  }
  if (node.Finite("keepalive_s", n.keepalive_s()) && !(n.keepalive_s() > 0)) {
    node.Error("keepalive_s", "must be positive");
  }
  if (node.Finite("silence_s", n.silence_s()) && !(n.silence_s() > 0)) {
    node.Error("silence_s", "must be positive");
  }
  if (n.has_x_pivot_chassis()) {
    ValidatePose(node.Child("x_pivot_chassis", n.x_pivot_chassis()), n.x_pivot_chassis());
  }
}

void ValidateMocap(const Node& node, const config::Mocap& mocap) {
  if (!mocap.has_server_address() || mocap.server_address().empty()) {
    node.Missing("server_address");
  }
  ValidatePort(node, "port", mocap.port());
  if (mocap.body_name().empty()) node.Error("body_name", "must not be empty");
  if (node.Finite("hang_axis_tolerance_deg", mocap.hang_axis_tolerance_deg()) &&
      !(mocap.hang_axis_tolerance_deg() > 0.0 && mocap.hang_axis_tolerance_deg() < 90.0)) {
    node.Error("hang_axis_tolerance_deg",
               "must be in (0, 90), got " + FormatNumber(mocap.hang_axis_tolerance_deg()));
  }
  if (mocap.system() == config::OPTITRACK && !mocap.has_natnet()) node.Missing("natnet");
  if (mocap.has_natnet()) ValidateNatNet(node.Child("natnet", mocap.natnet()), mocap.natnet());
}

void ValidateDynamixel(const Node& node, const config::DynamixelBus& bus) {
  if (!bus.has_device() || bus.device().empty()) node.Missing("device");
  if (bus.baud() == 0) node.Error("baud", "must be > 0");
  node.Positive("rate_hz", bus.rate_hz());
  node.Positive("reply_timeout_s", bus.reply_timeout_s());
  if (node.Finite("start_quiet_s", bus.start_quiet_s()) && bus.start_quiet_s() < 0) {
    node.Error("start_quiet_s", "must be >= 0, got " + FormatNumber(bus.start_quiet_s()));
  }
  node.Positive("deadman_s", bus.deadman_s());
  if (node.Finite("limit_margin_rad", bus.limit_margin_rad()) && bus.limit_margin_rad() < 0) {
    node.Error("limit_margin_rad", "must be >= 0, got " + FormatNumber(bus.limit_margin_rad()));
  }
  // Each limit goes into a servo register (docs/device-protocols.md §2.7) whose 0 means "no
  // limit": a value under one unit would switch the limit off. Above the register's range
  // (1023 and 32767 units, five times the MX-106's no-load speed and more) the register holds
  // its maximum and the bridge's own ramp is the limit.
  constexpr double kVelocityUnitRadS = 0.229 * 2 * M_PI / 60;           // Velocity Limit (44)
  constexpr double kAccelerationUnitRadS2 = 214.577 * 2 * M_PI / 3600;  // Acceleration Limit (40)
  node.Positive("max_velocity_rad_s", bus.max_velocity_rad_s());
  if (std::isfinite(bus.max_velocity_rad_s()) && bus.max_velocity_rad_s() > 0 &&
      bus.max_velocity_rad_s() < kVelocityUnitRadS) {
    node.Error("max_velocity_rad_s",
               "must be at least one unit of the servos' Velocity Limit "
               "(0.229 rpm = " +
                   FormatNumber(kVelocityUnitRadS) + " rad/s), got " +
                   FormatNumber(bus.max_velocity_rad_s()));
  }
  node.Positive("max_acceleration_rad_s2", bus.max_acceleration_rad_s2());
  if (std::isfinite(bus.max_acceleration_rad_s2()) && bus.max_acceleration_rad_s2() > 0 &&
      bus.max_acceleration_rad_s2() < kAccelerationUnitRadS2) {
    node.Error("max_acceleration_rad_s2",
               "must be at least one unit of the servos' Acceleration Limit (214.577 rev/min^2 = " +
                   FormatNumber(kAccelerationUnitRadS2) + " rad/s^2), got " +
                   FormatNumber(bus.max_acceleration_rad_s2()));
  }
  node.Positive("bus_watchdog_s", bus.bus_watchdog_s());
  if (std::isfinite(bus.bus_watchdog_s()) && bus.bus_watchdog_s() > 0) {
    const double units = bus.bus_watchdog_s() / 0.02;
    if (!(units >= 1 - 1e-9 && units <= 127 + 1e-9) || std::abs(units - std::round(units)) > 1e-6) {
      node.Error("bus_watchdog_s",
                 "must be a multiple of 0.02 s within 0.02-2.54 s (the Bus "
                 "Watchdog's 20 ms units, 1-127), got " +
                     FormatNumber(bus.bus_watchdog_s()));
    } else if (std::isfinite(bus.rate_hz()) && bus.rate_hz() > 0 &&
               bus.bus_watchdog_s() * bus.rate_hz() < 5) {
      node.Error("bus_watchdog_s", "must span at least five bridge cycles (5 / rate_hz = " +
                                       FormatNumber(5 / bus.rate_hz()) +
                                       " s): the bridge's own reads feed it; got " +
                                       FormatNumber(bus.bus_watchdog_s()));
    }
  }
}

}  // namespace ftcal::config_detail
