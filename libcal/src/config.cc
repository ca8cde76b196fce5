#include "ftcal/config.h"

#include <arpa/inet.h>
#include <openssl/evp.h>

#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <set>
#include <memory>
#include <sstream>
#include <string_view>
#include <vector>

#include <google/protobuf/io/tokenizer.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>
#include <google/protobuf/text_format.h>

namespace ftcal {
namespace {

namespace pb = google::protobuf;
using ParseInfoTree = pb::TextFormat::ParseInfoTree;

constexpr double kRotationTolerance = 1e-6;

std::string FormatNumber(double v) {
  std::ostringstream s;
  s.precision(10);
  s << v;
  return s.str();
}

// TextFormat reports 0-based positions; every message we print is 1-based. Its messages name
// the token, not the field ("Expected double, got: ..."), so the offending source line is
// quoted under the message with a caret, as compilers do.
class CollectingErrorCollector : public pb::io::ErrorCollector {
 public:
  CollectingErrorCollector(std::string source, const std::string& text)
      : source_(std::move(source)), text_(text) {}

  void AddError(int line, pb::io::ColumnNumber column, const std::string& message) override {
    std::string e = source_ + ":" + std::to_string(line + 1) + ":" + std::to_string(column + 1) +
                    ": " + message;
    const std::string quoted = Line(line);
    if (!quoted.empty()) {
      e += "\n    " + quoted + "\n    " + std::string(std::max(column, 0), ' ') + "^";
    }
    errors_.push_back(std::move(e));
  }

  const std::vector<std::string>& errors() const { return errors_; }

 private:
  std::string Line(int line) const {
    size_t begin = 0;
    for (int i = 0; i < line; ++i) {
      begin = text_.find('\n', begin);
      if (begin == std::string::npos) return {};
      ++begin;
    }
    const size_t end = text_.find('\n', begin);
    return text_.substr(begin, end == std::string::npos ? std::string::npos : end - begin);
  }

  std::string source_;
  const std::string& text_;
  std::vector<std::string> errors_;
};

struct Location {
  int line = 1;    // 1-based
  int column = 1;  // 1-based
};

// A message being validated: where it sits in the file (its field path and location) and the
// parser's location tree for its own fields, so an error can name the exact line of a field.
// A missing field has no location of its own and points at this enclosing message.
class Node {
 public:
  Node(const pb::Message& message, const ParseInfoTree* tree, std::string path, Location location,
       const std::string* source, std::vector<std::string>* errors)
      : message_(message),
        tree_(tree),
        path_(std::move(path)),
        location_(location),
        source_(source),
        errors_(errors) {}

  const std::string& path() const { return path_; }

  // Path and location of field `name` (element `index` of a repeated field).
  std::string FieldPath(std::string_view name, int index = -1) const {
    std::string p = path_.empty() ? std::string(name) : path_ + "." + std::string(name);
    if (index >= 0) p += "[" + std::to_string(index) + "]";
    return p;
  }

  Location FieldLocation(std::string_view name, int index = -1) const {
    const pb::FieldDescriptor* field = Field(name);
    if (tree_ == nullptr) return location_;
    // Repeated scalars written in list syntax ("f: [1, 2, 3]") record one location for the
    // whole list, so an element without its own location falls back to the first.
    int i = field->is_repeated() ? std::max(index, 0) : -1;
    pb::TextFormat::ParseLocation loc = tree_->GetLocation(field, i);
    if (loc.line < 0 && field->is_repeated()) loc = tree_->GetLocation(field, 0);
    if (loc.line < 0) return location_;
    return Location{loc.line + 1, loc.column + 1};
  }

  // The node of a singular message field (which must be present).
  Node Child(std::string_view name, const pb::Message& child) const {
    const pb::FieldDescriptor* field = Field(name);
    const ParseInfoTree* nested = tree_ ? tree_->GetTreeForNested(field, -1) : nullptr;
    return Node(child, nested, FieldPath(name), FieldLocation(name), source_, errors_);
  }

  // The node of element `index` of a repeated message field.
  Node Child(std::string_view name, int index, const pb::Message& child) const {
    const pb::FieldDescriptor* field = Field(name);
    const ParseInfoTree* nested = tree_ ? tree_->GetTreeForNested(field, index) : nullptr;
    return Node(child, nested, FieldPath(name, index), FieldLocation(name, index), source_,
                errors_);
  }

  void Error(std::string_view name, const std::string& what, int index = -1) const {
    ErrorAt(FieldLocation(name, index), FieldPath(name, index), what);
  }

  // An error about the message itself (e.g. a field missing from it).
  void SelfError(const std::string& what) const {
    ErrorAt(location_, path_.empty() ? std::string("<config>") : path_, what);
  }

  void Missing(std::string_view name) const {
    ErrorAt(location_, FieldPath(name), "required field is missing");
  }

  // Checks for finite numbers, with the value and the bound in the message.
  bool Finite(std::string_view name, double v, int index = -1) const {
    if (std::isfinite(v)) return true;
    Error(name, "must be a finite number, got " + FormatNumber(v), index);
    return false;
  }
  void Positive(std::string_view name, double v) const {
    if (Finite(name, v) && !(v > 0.0)) Error(name, "must be > 0, got " + FormatNumber(v));
  }

 private:
  const pb::FieldDescriptor* Field(std::string_view name) const {
    const pb::FieldDescriptor* field = message_.GetDescriptor()->FindFieldByName(std::string(name));
    if (field == nullptr) {
      // A misspelt name in this file, not bad input: stop loudly.
      throw std::logic_error("config.cc: no field '" + std::string(name) + "' in " +
                             message_.GetDescriptor()->full_name());
    }
    return field;
  }

  void ErrorAt(Location loc, const std::string& path, const std::string& what) const {
    errors_->push_back(*source_ + ":" + std::to_string(loc.line) + ":" +
                       std::to_string(loc.column) + ": " + path + ": " + what);
  }

  const pb::Message& message_;
  const ParseInfoTree* tree_;
  std::string path_;
  Location location_;
  const std::string* source_;
  std::vector<std::string>* errors_;
};

// Bounds of plausibility: far beyond any hexapod this project calibrates, close enough to
// catch a unit typed wrong (grams for kg, mm for m).
constexpr double kMaxRobotMassKg = 1000.0;
constexpr double kMaxTransducerDistanceM = 10.0;
constexpr double kMinRatedRange = 1e-3;
constexpr double kMaxRatedRange = 1e6;
constexpr double kMaxSavgolWindowS = 60.0;

std::string JoinErrors(const std::vector<std::string>& errors) {
  std::string out;
  for (const std::string& e : errors) {
    if (!out.empty()) out += "\n";
    out += e;
  }
  return out;
}

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

void ValidateSegmenter(const Node& node, const config::Segmenter& s) {
  node.Positive("sample_rate_hz", s.sample_rate_hz());
  if (s.savgol_order() < 1) {
    node.Error("savgol_order", "must be >= 1, got " + std::to_string(s.savgol_order()));
  }
  if (s.savgol_window() % 2 == 0) {
    node.Error("savgol_window", "must be odd, got " + std::to_string(s.savgol_window()));
  } else if (s.savgol_window() <= s.savgol_order()) {
    node.Error("savgol_window", "must be greater than savgol_order (" +
                                    std::to_string(s.savgol_order()) + "), got " +
                                    std::to_string(s.savgol_window()));
  }
  if (std::isfinite(s.sample_rate_hz()) && s.sample_rate_hz() > 0 &&
      s.savgol_window() / s.sample_rate_hz() > kMaxSavgolWindowS) {
    node.Error("savgol_window", "spans " + FormatNumber(s.savgol_window() / s.sample_rate_hz()) +
                                    " s at sample_rate_hz " + FormatNumber(s.sample_rate_hz()) +
                                    "; at most " + FormatNumber(kMaxSavgolWindowS) + " s, got " +
                                    std::to_string(s.savgol_window()));
  }
  node.Positive("max_force_rate_n_s", s.max_force_rate_n_s());
  node.Positive("min_steady_s", s.min_steady_s());
}

void ValidateCalibrator(const Node& node, const config::Calibrator& c) {
  if (c.phase_bins() < 8) {
    node.Error("phase_bins", "must be >= 8, got " + std::to_string(c.phase_bins()));
  }
  node.Positive("smoother_transition_var", c.smoother_transition_var());
  node.Positive("smoother_observation_var", c.smoother_observation_var());
  if (c.k_weights_size() != 0 && c.k_weights_size() != 6) {
    node.Error("k_weights", "needs 0 or 6 entries [fx fy fz tx ty tz], got " +
                                std::to_string(c.k_weights_size()));
  } else {
    for (int i = 0; i < c.k_weights_size(); ++i) {
      if (node.Finite("k_weights", c.k_weights(i), i) && !(c.k_weights(i) > 0.0)) {
        node.Error("k_weights", "must be > 0, got " + FormatNumber(c.k_weights(i)), i);
      }
    }
  }
  if (c.solver() == config::STEP2_SOLVER_UNSPECIFIED) {
    node.Error("solver", "must be JOINT or ALTERNATING");
  }
  node.Positive("alternating_tolerance", c.alternating_tolerance());
  if (c.robust_loss() == config::ROBUST_LOSS_UNSPECIFIED) {
    node.Error("robust_loss", "must be NONE, HUBER or CAUCHY");
  }
  node.Positive("robust_loss_scale", c.robust_loss_scale());
  if (c.cv_folds() < 2) {
    node.Error("cv_folds", "must be >= 2, got " + std::to_string(c.cv_folds()));
  }
  node.Positive("mass_check_sigmas", c.mass_check_sigmas());
  if (node.Finite("mass_tolerance_kg", c.mass_tolerance_kg()) && c.mass_tolerance_kg() < 0.0) {
    node.Error("mass_tolerance_kg", "must be >= 0, got " + FormatNumber(c.mass_tolerance_kg()));
  }
  node.Positive("residual_floor_warn_factor", c.residual_floor_warn_factor());
  if (node.Finite("max_gap_share", c.max_gap_share()) &&
      (c.max_gap_share() < 0.0 || c.max_gap_share() > 1.0)) {
    node.Error("max_gap_share",
               "must be a share in [0, 1], got " + FormatNumber(c.max_gap_share()));
  }
  if (c.profile() == config::CALIBRATION_PROFILE_UNSPECIFIED) {
    node.Error("profile", "must be FTCAL or REPORT");
  }
  if (c.com_model() == config::ROBOT_COM_MODEL_UNSPECIFIED) {
    node.Error("com_model", "must be COM_BY_DATA, COM_FIXED or COM_LEG_AWARE");
  }
  if (c.min_poses() < 1) {
    node.Error("min_poses", "must be >= 1, got " + std::to_string(c.min_poses()));
  }
  if (node.Finite("unloaded_leg_min_angle_deg", c.unloaded_leg_min_angle_deg()) &&
      !(c.unloaded_leg_min_angle_deg() > 0.0 && c.unloaded_leg_min_angle_deg() < 180.0)) {
    node.Error("unloaded_leg_min_angle_deg",
               "must be in (0, 180), got " + FormatNumber(c.unloaded_leg_min_angle_deg()));
  }
}

void ValidateCorrector(const Node& node, const config::Corrector& c) {
  node.Positive("max_servo_age_s", c.max_servo_age_s());
  node.Positive("max_mocap_age_s", c.max_mocap_age_s());
  node.Positive("max_ft_age_s", c.max_ft_age_s());
}

void ValidateChannels(const Node& node, const config::Channels& c) {
  const pb::Descriptor* d = c.GetDescriptor();
  const pb::Reflection* r = c.GetReflection();
  // Every field is a channel name; reflection keeps this in step with the schema. Two
  // purposes on one channel make a process read its own output (the corrector once ate its
  // CONTACT_WRENCH): every name, and every FT_<LEG> the prefix makes, must be distinct.
  std::vector<std::pair<std::string, std::string>> names;  // channel, field
  for (int i = 0; i < d->field_count(); ++i) {
    const pb::FieldDescriptor* f = d->field(i);
    if (f->type() != pb::FieldDescriptor::TYPE_STRING) continue;
    const std::string value = r->GetString(c, f);
    if (value.empty()) {
      node.Error(f->name(), "channel name must not be empty");
      continue;
    }
    if (f->name() == "ft_prefix") {
      for (std::string_view leg : kLegNames) {
        names.emplace_back(value + std::string(leg),
                           "ft_prefix (" + value + std::string(leg) + ")");
      }
    } else {
      names.emplace_back(value, f->name());
    }
  }
  for (std::size_t i = 0; i < names.size(); ++i) {
    for (std::size_t j = 0; j < i; ++j) {
      if (names[i].first == names[j].first) {
        const std::string field = names[i].second.substr(0, names[i].second.find(' '));
        node.Error(field, "channel '" + names[i].first + "' is also channels." + names[j].second +
                              ": each channel carries one thing");
      }
    }
  }
}

// A number that must lie in [lo, hi] (inclusive), with both named in the message.
void InRange(const Node& node, std::string_view name, double v, double lo, double hi,
             std::string_view unit = "") {
  if (node.Finite(name, v) && !(v >= lo && v <= hi)) {
    node.Error(name, "must be in [" + FormatNumber(lo) + ", " + FormatNumber(hi) + "]" +
                         std::string(unit) + ", got " + FormatNumber(v));
  }
}

void ValidatePlanPhase(const Node& node, const config::PlanPhase& p) {
  switch (p.kind()) {
    case config::PHASE_TARE:
      InRange(node, "tare_s", p.tare_s(), 0.1, 600.0, " s");
      break;
    case config::PHASE_HANG:
      if (p.orientation() == config::HANG_ORIENTATION_UNSPECIFIED) {
        node.Error("orientation",
                   "a hanging phase needs HANG_X_POS, HANG_X_NEG, HANG_Z_POS or "
                   "HANG_Z_NEG");
      }
      if (p.cycles() < 1 || p.cycles() > 1000) {
        node.Error("cycles", "must be in [1, 1000], got " + std::to_string(p.cycles()));
      }
      InRange(node, "cycle_s", p.cycle_s(), 1.0, 3600.0, " s");
      break;
    case config::PHASE_STANDING_GRID:
      if (p.grid_angles_deg_size() > 5) {
        node.Error("grid_angles_deg",
                   "at most 5 angles (5^6 poses), got " + std::to_string(p.grid_angles_deg_size()));
      }
      for (int i = 0; i < p.grid_angles_deg_size(); ++i) {
        if (node.Finite("grid_angles_deg", p.grid_angles_deg(i), i) &&
            std::abs(p.grid_angles_deg(i)) > 90.0) {
          node.Error("grid_angles_deg",
                     "a standing angle must be within +-90 deg of straight down, got " +
                         FormatNumber(p.grid_angles_deg(i)),
                     i);
        }
      }
      if (p.pose_stride() < 1) node.Error("pose_stride", "must be >= 1");
      InRange(node, "dwell_s", p.dwell_s(), 0.5, 600.0, " s");
      break;
    case config::PHASE_TRIPOD_STANCES:
      if (p.stances() < 1 || p.stances() > 1000) {
        node.Error("stances", "must be in [1, 1000], got " + std::to_string(p.stances()));
      }
      InRange(node, "lift_angle_deg", p.lift_angle_deg(), 90.0, 180.0, " deg");
      InRange(node, "dwell_s", p.dwell_s(), 0.5, 600.0, " s");
      break;
    case config::PHASE_TRIPOD_WALK:
      InRange(node, "clock_hz", p.clock_hz(), 0.001, 2.0, " Hz");
      if (node.Finite("duty", p.duty()) && !(p.duty() > 0.0 && p.duty() < 1.0)) {
        node.Error("duty", "must be in (0, 1), got " + FormatNumber(p.duty()));
      }
      InRange(node, "sweep_deg", p.sweep_deg(), 1.0, 180.0, " deg");
      InRange(node, "turn_sweep_delta_deg", p.turn_sweep_delta_deg(), -90.0, 90.0, " deg");
      InRange(node, "walk_s", p.walk_s(), 1.0, 36000.0, " s");
      break;
    default:
      node.Error("kind",
                 "must be PHASE_TARE, PHASE_HANG, PHASE_STANDING_GRID, "
                 "PHASE_TRIPOD_STANCES or PHASE_TRIPOD_WALK");
  }
}

void ValidatePlans(const Node& root, const config::Config& config) {
  for (int i = 0; i < config.plan_size(); ++i) {
    const config::ExperimentPlan& plan = config.plan(i);
    const Node node = root.Child("plan", i, plan);
    if (plan.name().empty()) node.Missing("name");
    for (int j = 0; j < i; ++j) {
      if (config.plan(j).name() == plan.name() && !plan.name().empty()) {
        node.Error("name", "duplicate plan name '" + plan.name() + "' (already " +
                               root.FieldPath("plan", j) + ")");
      }
    }
    if (plan.phase_size() == 0) node.SelfError("a plan needs at least one phase");
    for (int k = 0; k < plan.phase_size(); ++k) {
      ValidatePlanPhase(node.Child("phase", k, plan.phase(k)), plan.phase(k));
    }
  }
}

void ValidateSequencer(const Node& node, const config::Sequencer& s) {
  InRange(node, "command_rate_hz", s.command_rate_hz(), 1.0, 1000.0, " Hz");
  InRange(node, "max_velocity_rad_s", s.max_velocity_rad_s(), 0.01, 20.0, " rad/s");
  InRange(node, "joint_limit_margin_rad", s.joint_limit_margin_rad(), 0.0, 1.0, " rad");
  InRange(node, "max_input_age_s", s.max_input_age_s(), 0.01, 10.0, " s");
  InRange(node, "airborne_max_support_n", s.airborne_max_support_n(), 0.1, 1000.0, " N");
  InRange(node, "standing_min_weight_share", s.standing_min_weight_share(), 0.0, 2.0);
  InRange(node, "standing_max_weight_share", s.standing_max_weight_share(), 0.0, 5.0);
  if (std::isfinite(s.standing_min_weight_share()) &&
      std::isfinite(s.standing_max_weight_share()) &&
      !(s.standing_min_weight_share() < s.standing_max_weight_share())) {
    node.Error("standing_max_weight_share", "must be greater than standing_min_weight_share (" +
                                                FormatNumber(s.standing_min_weight_share()) +
                                                "), got " +
                                                FormatNumber(s.standing_max_weight_share()));
  }
  InRange(node, "max_tilt_deg", s.max_tilt_deg(), 0.1, 90.0, " deg");
  InRange(node, "arrival_tolerance_rad", s.arrival_tolerance_rad(), 0.001, 1.0, " rad");
  InRange(node, "arrival_timeout_s", s.arrival_timeout_s(), 0.1, 600.0, " s");
  if (s.safe_action() == config::SAFE_ACTION_UNSPECIFIED) {
    node.Error("safe_action", "must be SAFE_HOLD or SAFE_TORQUE_OFF");
  }
}

void ValidateAuth(const Node& node, const config::Auth& auth, const config::Channels& channels) {
  const std::set<std::string> signed_channels = {channels.servo_cmd(), channels.experiment(),
                                                 channels.calibration(),
                                                 channels.sequencer_control()};
  std::map<std::string, int> keys_per_channel;
  std::set<std::string> names, keys;
  for (int i = 0; i < auth.trusted_key_size(); ++i) {
    const config::TrustedKey& key = auth.trusted_key(i);
    const Node key_node = node.Child("trusted_key", i, key);
    if (key.name().empty()) key_node.Missing("name");
    if (!names.insert(key.name()).second) {
      key_node.Error("name", "duplicate trusted key name '" + key.name() + "'");
    }
    const std::string& hex = key.public_key_hex();
    if (hex.size() != 64 || hex.find_first_not_of("0123456789abcdefABCDEF") != std::string::npos) {
      key_node.Error("public_key_hex",
                     "must be 64 hex digits (an Ed25519 public key, as ftcal-keygen prints it)");
    } else if (!keys.insert(hex).second) {
      key_node.Error("public_key_hex", "the same key is listed twice");
    }
    if (key.channel_size() == 0) key_node.Error("channel", "name at least one signed channel");
    for (const std::string& channel : key.channel()) {
      if (signed_channels.count(channel) == 0) {
        key_node.Error("channel", "'" + channel + "' is not a signed channel (" +
                                      channels.servo_cmd() + ", " + channels.experiment() + ", " +
                                      channels.calibration() + ", " + channels.sequencer_control() +
                                      ")");
      } else if (++keys_per_channel[channel] == 3) {
        key_node.Error("channel", "more than two trusted keys for '" + channel +
                                      "' (two at once, for rotation)");
      }
    }
  }
  if (node.Finite("servo_cmd_window_s", auth.servo_cmd_window_s()) &&
      !(auth.servo_cmd_window_s() > 0 && auth.servo_cmd_window_s() <= 10)) {
    node.Error("servo_cmd_window_s",
               "must be in (0, 10] s, got " + FormatNumber(auth.servo_cmd_window_s()));
  }
}

// ---- Launch groups ----

bool IsProgramName(const std::string& name) {
  // supervisor's section names and systemd unit names both accept these; ':' would split a
  // supervisor "group:name".
  if (name.empty() || name.size() > 64) return false;
  return name.find_first_not_of("abcdefghijklmnopqrstuvwxyz0123456789_-") == std::string::npos;
}

void ValidateRestart(const Node& node, const config::RestartPolicy& r) {
  if (node.Finite("startsecs_s", r.startsecs_s()) &&
      !(r.startsecs_s() == 0 || (r.startsecs_s() >= 2 && r.startsecs_s() <= 3600))) {
    // supervisord may notice an exit a second late: below 2 s a process that dies at once can
    // pass as started, and is then restarted forever instead of ending FATAL.
    node.Error("startsecs_s",
               "must be 0 (no start check) or in 2..3600 s, got " + FormatNumber(r.startsecs_s()));
  }
  if (r.startretries() > 100) {
    node.Error("startretries",
               "must be at most 100 (a process that keeps dying should end "
               "FATAL), got " +
                   std::to_string(r.startretries()));
  }
  static const std::set<std::string> kSignals = {"TERM", "INT",  "QUIT", "KILL",
                                                 "HUP",  "USR1", "USR2"};
  if (kSignals.count(r.stopsignal()) == 0) {
    node.Error("stopsignal",
               "must be one of TERM INT QUIT KILL HUP USR1 USR2, got '" + r.stopsignal() + "'");
  }
  if (node.Finite("stopwaitsecs_s", r.stopwaitsecs_s()) &&
      !(r.stopwaitsecs_s() > 0 && r.stopwaitsecs_s() <= 3600)) {
    node.Error("stopwaitsecs_s", "must be in (0, 3600] s, got " + FormatNumber(r.stopwaitsecs_s()));
  }
  if (node.Finite("watchdog_s", r.watchdog_s()) &&
      !(r.watchdog_s() == 0 || (r.watchdog_s() >= 2 && r.watchdog_s() <= 3600))) {
    // The heartbeat pings the watchdog once a second: below 2 s one late tick kills it.
    node.Error("watchdog_s", "must be 0 (none) or in 2..3600 s (the heartbeat is 1 Hz), got " +
                                 FormatNumber(r.watchdog_s()));
  }
}

void ValidateGate(const Node& node, const config::HealthGate& g) {
  if (g.kind() == config::HealthGate::KIND_UNSPECIFIED) {
    node.Missing("kind");
    return;
  }
  if (g.kind() == config::HealthGate::RATE || g.kind() == config::HealthGate::FRESH) {
    const std::string& ch = g.channel();
    if (ch.empty() || ch == "*") {
      node.Error("channel", "name a channel (or a prefix ending in '*')");
    } else if (ch.find('*') != std::string::npos && ch.find('*') != ch.size() - 1) {
      node.Error("channel", "'*' may only end a prefix, got '" + ch + "'");
    }
  } else if (g.has_channel()) {
    node.Error("channel", "a STATUS_RUNNING gate reads the process's own heartbeat: no channel");
  }
  if (g.kind() == config::HealthGate::RATE) {
    if (!g.has_rate_hz()) {
      node.Missing("rate_hz");
    } else if (node.Finite("rate_hz", g.rate_hz()) && !(g.rate_hz() > 0 && g.rate_hz() <= 1e5)) {
      node.Error("rate_hz", "must be in (0, 1e5] Hz, got " + FormatNumber(g.rate_hz()));
    }
    if (node.Finite("min_fraction", g.min_fraction()) &&
        !(g.min_fraction() > 0 && g.min_fraction() <= 1)) {
      node.Error("min_fraction", "must be in (0, 1], got " + FormatNumber(g.min_fraction()));
    }
    if (node.Finite("window_s", g.window_s()) && !(g.window_s() >= 0.1 && g.window_s() <= 60)) {
      node.Error("window_s", "must be in 0.1..60 s, got " + FormatNumber(g.window_s()));
    }
  }
  if (g.kind() == config::HealthGate::FRESH && node.Finite("max_age_s", g.max_age_s()) &&
      !(g.max_age_s() > 0 && g.max_age_s() <= 60)) {
    node.Error("max_age_s", "must be in (0, 60] s, got " + FormatNumber(g.max_age_s()));
  }
  if (node.Finite("within_s", g.within_s()) && !(g.within_s() > 0 && g.within_s() <= 600)) {
    node.Error("within_s", "must be in (0, 600] s, got " + FormatNumber(g.within_s()));
  }
  if (g.kind() == config::HealthGate::RATE && g.window_s() > g.within_s()) {
    node.Error("window_s", "the rate window (" + FormatNumber(g.window_s()) +
                               " s) must fit in within_s (" + FormatNumber(g.within_s()) + " s)");
  }
}

void ValidateLaunch(const Node& node, const config::Launch& launch) {
  std::set<std::string> hosts;
  for (int h = 0; h < launch.host_size(); ++h) {
    const config::LaunchHost& host = launch.host(h);
    const Node host_node = node.Child("host", h, host);
    if (!IsProgramName(host.name())) {
      host_node.Error("name", "must be 1..64 of [a-z0-9_-], got '" + host.name() + "'");
    } else if (!hosts.insert(host.name()).second) {
      host_node.Error("name", "duplicate host '" + host.name() + "'");
    }
    if (host.address().empty()) host_node.Missing("address");
    for (int i = 0; i < host.shell_size(); ++i) {
      if (host.shell(i).empty()) host_node.Error("shell", "an empty word", i);
    }
  }
  std::set<std::string> groups;
  for (int gi = 0; gi < launch.group_size(); ++gi) {
    const config::LaunchGroup& group = launch.group(gi);
    const Node group_node = node.Child("group", gi, group);
    if (!IsProgramName(group.name())) {
      group_node.Error("name", "must be 1..64 of [a-z0-9_-], got '" + group.name() + "'");
    } else if (!groups.insert(group.name()).second) {
      group_node.Error("name", "duplicate group '" + group.name() + "'");
    }
    if (group.process_size() == 0) group_node.Error("process", "a group needs a process");
    std::map<std::string, int> index;
    for (int p = 0; p < group.process_size(); ++p) {
      const config::LaunchProcess& proc = group.process(p);
      const Node proc_node = group_node.Child("process", p, proc);
      if (!IsProgramName(proc.name())) {
        proc_node.Error("name", "must be 1..64 of [a-z0-9_-], got '" + proc.name() + "'");
      } else if (!index.emplace(proc.name(), p).second) {
        proc_node.Error("name",
                        "duplicate process '" + proc.name() + "' in group '" + group.name() + "'");
      }
      if (proc.host().empty()) {
        proc_node.Missing("host");
      } else if (hosts.count(proc.host()) == 0) {
        proc_node.Error("host", "no host '" + proc.host() + "' in launch.host");
      }
      if (proc.command().empty()) proc_node.Missing("command");
      for (int i = 0; i < proc.env_size(); ++i) {
        const std::string& e = proc.env(i);
        const auto eq = e.find('=');
        if (eq == 0 || eq == std::string::npos || std::isdigit(static_cast<unsigned char>(e[0])) ||
            e.substr(0, eq).find_first_not_of("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"
                                              "0123456789_") != std::string::npos) {
          proc_node.Error("env", "must be NAME=VALUE, got '" + e + "'", i);
        }
      }
      ValidateRestart(proc_node.Child("restart", proc.restart()), proc.restart());
      for (int k = 0; k < proc.gate_size(); ++k) {
        ValidateGate(proc_node.Child("gate", k, proc.gate(k)), proc.gate(k));
      }
    }
    // Dependencies name processes of the group, and admit an order (no cycle).
    for (int p = 0; p < group.process_size(); ++p) {
      const config::LaunchProcess& proc = group.process(p);
      const Node proc_node = group_node.Child("process", p, proc);
      for (int i = 0; i < proc.after_size(); ++i) {
        if (index.count(proc.after(i)) == 0) {
          proc_node.Error("after",
                          "no process '" + proc.after(i) + "' in group '" + group.name() + "'", i);
        } else if (proc.after(i) == proc.name()) {
          proc_node.Error("after", "a process cannot wait for itself", i);
        }
      }
    }
    std::vector<int> state(group.process_size(), 0);  // 0 new, 1 on the path, 2 done
    std::function<bool(int)> acyclic = [&](int p) {
      if (state[p] == 1) return false;
      if (state[p] == 2) return true;
      state[p] = 1;
      for (const std::string& dep : group.process(p).after()) {
        const auto it = index.find(dep);
        if (it != index.end() && it->second != p && !acyclic(it->second)) return false;
      }
      state[p] = 2;
      return true;
    };
    for (int p = 0; p < group.process_size(); ++p) {
      if (!acyclic(p)) {
        group_node.Child("process", p, group.process(p))
            .Error("after",
                   "the dependencies form a cycle through '" + group.process(p).name() + "'");
        break;
      }
    }
  }
  if (launch.process_state_channel().empty())
    node.Error("process_state_channel", "must not be empty");
}

void Validate(const config::Config& config, const ParseInfoTree* tree, const std::string& source,
              std::vector<std::string>* errors) {
  const Node root(config, tree, "", Location{1, 1}, &source, errors);
  if (!config.has_robot()) {
    root.Missing("robot");
  } else {
    ValidateRobot(root.Child("robot", config.robot()), config.robot());
  }
  if (config.has_mocap()) ValidateMocap(root.Child("mocap", config.mocap()), config.mocap());
  if (config.has_dynamixel()) {
    ValidateDynamixel(root.Child("dynamixel", config.dynamixel()), config.dynamixel());
  }
  // Sections with only defaults are validated too: the defaults are values we run with.
  ValidateSegmenter(root.Child("segmenter", config.segmenter()), config.segmenter());
  ValidateCalibrator(root.Child("calibrator", config.calibrator()), config.calibrator());
  ValidateCorrector(root.Child("corrector", config.corrector()), config.corrector());
  ValidateChannels(root.Child("channels", config.channels()), config.channels());
  if (config.lcm_url().empty()) root.Error("lcm_url", "must not be empty");
  ValidatePlans(root, config);
  ValidateSequencer(root.Child("sequencer", config.sequencer()), config.sequencer());
  if (config.has_dynamixel() &&
      config.sequencer().max_velocity_rad_s() > config.dynamixel().max_velocity_rad_s()) {
    // The bridge rate-limits every goal: a plan timed faster would lag and be called stuck.
    root.Child("sequencer", config.sequencer())
        .Error("max_velocity_rad_s", "must not exceed dynamixel.max_velocity_rad_s (" +
                                         FormatNumber(config.dynamixel().max_velocity_rad_s()) +
                                         " rad/s, the bridge's own limit), got " +
                                         FormatNumber(config.sequencer().max_velocity_rad_s()));
  }
  ValidateAuth(root.Child("auth", config.auth()), config.auth(), config.channels());
  if (config.has_launch()) ValidateLaunch(root.Child("launch", config.launch()), config.launch());
  if (config.has_dynamixel() && config.has_robot() &&
      config.dynamixel().operating_mode() == config::EXTENDED_POSITION_MODE) {
    // Extended Position mode takes goals within +-1,048,575 counts (+-256 turns,
    // docs/device-protocols.md §2.7): a limit beyond them could not be commanded.
    constexpr double kMaxExtendedCount = 1048575.0;
    const Node robot = root.Child("robot", config.robot());
    for (int i = 0; i < config.robot().leg_size(); ++i) {
      const config::Servo& servo = config.robot().leg(i).servo();
      const Node node = robot.Child("leg", i, config.robot().leg(i)).Child("servo", servo);
      for (const auto& [name, angle] :
           {std::pair<const char*, double>{"min_angle_rad", servo.min_angle_rad()},
            {"max_angle_rad", servo.max_angle_rad()}}) {
        const double count = servo.zero_count() + servo.direction() * angle * 4096.0 / (2 * M_PI);
        if (std::isfinite(count) && std::abs(count) > kMaxExtendedCount) {
          node.Error(name, "is encoder count " + FormatNumber(count) +
                               ", outside the +-1048575 of Extended Position mode (dynamixel."
                               "operating_mode), got " +
                               FormatNumber(angle));
        }
      }
    }
  }
}

std::string ReadWholeFile(const std::string& path, const char* what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw ConfigError(std::string("cannot open ") + what + " '" + path +
                      "': " + std::strerror(errno));
  }
  std::ostringstream s;
  s << in.rdbuf();
  if (in.bad()) {
    throw ConfigError(std::string("cannot read ") + what + " '" + path +
                      "': " + std::strerror(errno));
  }
  return s.str();
}

std::string ToHex(const unsigned char* digest, unsigned int length) {
  static constexpr char kHex[] = "0123456789abcdef";
  std::string hex;
  hex.reserve(2 * length);
  for (unsigned int i = 0; i < length; ++i) {
    hex += kHex[digest[i] >> 4];
    hex += kHex[digest[i] & 0xf];
  }
  return hex;
}

}  // namespace

config::Config LoadConfigText(const std::string& text, const std::string& source_name) {
  config::Config config;
  CollectingErrorCollector collector(source_name, text);
  ParseInfoTree tree;
  pb::TextFormat::Parser parser;
  parser.RecordErrorsTo(&collector);
  parser.WriteLocationsTo(&tree);
  pb::io::ArrayInputStream input(text.data(), static_cast<int>(text.size()));
  if (!parser.Parse(&input, &config)) {
    if (collector.errors().empty()) {
      throw ConfigError(source_name + ":1:1: could not parse the config");
    }
    throw ConfigError(JoinErrors(collector.errors()));
  }
  std::vector<std::string> errors;
  Validate(config, &tree, source_name, &errors);
  if (!errors.empty()) throw ConfigError(JoinErrors(errors));
  return config;
}

config::Config LoadConfigFile(const std::string& path) {
  return LoadConfigText(ReadWholeFile(path, "config file"), path);
}

Pose3 ToPose3(const config::Pose& pose) {
  if (!pose.has_translation_m()) throw ConfigError("pose: translation_m is missing");
  const config::Vec3& t = pose.translation_m();
  const Vec3 p(t.x(), t.y(), t.z());
  if (!p.allFinite()) throw ConfigError("pose: translation_m is not finite");
  const bool has_matrix = pose.rotation_row_major_size() > 0;
  if (has_matrix == pose.has_rpy_deg()) {
    throw ConfigError("pose: give exactly one of rotation_row_major and rpy_deg");
  }
  if (pose.has_rpy_deg()) {
    const config::Vec3& a = pose.rpy_deg();
    const Vec3 rpy_rad = Vec3(a.x(), a.y(), a.z()) * (M_PI / 180.0);
    if (!rpy_rad.allFinite()) throw ConfigError("pose: rpy_deg is not finite");
    return Pose3(RotationFromRollPitchYaw(rpy_rad.x(), rpy_rad.y(), rpy_rad.z()), p);
  }
  if (pose.rotation_row_major_size() != 9) {
    throw ConfigError("pose: rotation_row_major needs 9 numbers, got " +
                      std::to_string(pose.rotation_row_major_size()));
  }
  const Mat3 R = RowMajor(pose);
  if (!R.allFinite()) throw ConfigError("pose: rotation_row_major is not finite");
  const std::string problem = RotationProblem(R);
  if (!problem.empty()) throw ConfigError("pose: rotation_row_major: " + problem);
  // A matrix typed with a few decimals is only orthonormal to ~1e-6; project it so that
  // everything downstream works with an exact rotation.
  return Pose3(ProjectToSO3(R), p);
}

std::array<Pose3, kNumLegs> NominalTransducerPoses(const config::Robot& robot) {
  if (robot.leg_size() != kNumLegs) {
    throw ConfigError("robot: expected " + std::to_string(kNumLegs) + " legs, got " +
                      std::to_string(robot.leg_size()));
  }
  std::array<Pose3, kNumLegs> poses;
  for (int k = 0; k < kNumLegs; ++k) {
    const config::Leg& leg = robot.leg(k);
    if (leg.name() != kLegNames[k]) {
      throw ConfigError("robot.leg[" + std::to_string(k) + "]: expected leg '" +
                        std::string(kLegNames[k]) + "', got '" + leg.name() + "'");
    }
    if (!leg.has_x_b_ft()) {
      throw ConfigError("robot.leg[" + std::to_string(k) + "].x_b_ft is missing");
    }
    try {
      poses[k] = ToPose3(leg.x_b_ft());
    } catch (const ConfigError& e) {
      throw ConfigError("robot.leg[" + std::to_string(k) + "].x_b_ft: " + e.what());
    }
  }
  return poses;
}

Vec6 KWeights(const config::Calibrator& calibrator) {
  if (calibrator.k_weights_size() == 0) {
    Vec6 k;
    k << 1, 1, 1, 10, 10, 10;  // docs/method.md eq. 8: torques weighted 10x (N vs N*m scales)
    return k;
  }
  if (calibrator.k_weights_size() != 6) {
    throw ConfigError("calibrator.k_weights: needs 0 or 6 entries, got " +
                      std::to_string(calibrator.k_weights_size()));
  }
  Vec6 k;
  for (int i = 0; i < 6; ++i) {
    k[i] = calibrator.k_weights(i);
    if (!std::isfinite(k[i]) || !(k[i] > 0.0)) {
      throw ConfigError("calibrator.k_weights[" + std::to_string(i) + "]: must be > 0, got " +
                        FormatNumber(k[i]));
    }
  }
  return k;
}

std::string Sha256Hex(const std::string& bytes) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  if (EVP_Digest(bytes.data(), bytes.size(), digest, &length, EVP_sha256(), nullptr) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL EVP_Digest failed");
  }
  return ToHex(digest, length);
}

std::string Sha256File(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw std::runtime_error("SHA-256: cannot open '" + path + "': " + std::strerror(errno));
  }
  // Streamed: logs can be far larger than memory would like.
  std::unique_ptr<EVP_MD_CTX, decltype(&EVP_MD_CTX_free)> ctx(EVP_MD_CTX_new(), EVP_MD_CTX_free);
  if (!ctx || EVP_DigestInit_ex(ctx.get(), EVP_sha256(), nullptr) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL digest init failed");
  }
  std::vector<char> buffer(1 << 16);
  while (in) {
    in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    const std::streamsize n = in.gcount();
    if (n > 0 && EVP_DigestUpdate(ctx.get(), buffer.data(), static_cast<size_t>(n)) != 1) {
      throw std::runtime_error("SHA-256: OpenSSL digest update failed");
    }
  }
  if (in.bad()) {
    throw std::runtime_error("SHA-256: cannot read '" + path + "': " + std::strerror(errno));
  }
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  if (EVP_DigestFinal_ex(ctx.get(), digest, &length) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL digest final failed");
  }
  return ToHex(digest, length);
}

}  // namespace ftcal
