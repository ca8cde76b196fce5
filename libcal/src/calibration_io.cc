#include "ftcal/calibration_io.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <vector>

#include <google/protobuf/io/tokenizer.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>
#include <google/protobuf/text_format.h>

#include "ftcal/config.h"

namespace ftcal {
namespace {

namespace pb = google::protobuf;

constexpr double kQuaternionNormTolerance = 1e-6;
// The file carries R~ twice (quaternion and rotation vector); a hand edit of one of them
// must not go unnoticed.
constexpr double kRotationAgreementDeg = 1e-6;

std::string Num(double v) {
  std::ostringstream s;
  s.precision(10);
  s << v;
  return s.str();
}

void SetVec3(const Vec3& v, calibration::Vec3Estimate* out) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

void SetSinusoid(const SinusoidFit& fit, calibration::SinusoidFit* out) {
  out->set_a_m(fit.a);
  out->set_c_rad(fit.c);
  out->set_d_m(fit.d);
}

// Reads from a calibration proto with every missing or non-finite value refused by name.
class Reader {
 public:
  [[noreturn]] static void Fail(const std::string& path, const std::string& what) {
    throw std::runtime_error("calibration: " + path + ": " + what);
  }

  static double Scalar(const std::string& path, bool has, double v) {
    if (!has) Fail(path, "missing");
    if (!std::isfinite(v)) Fail(path, "not a finite number (" + Num(v) + ")");
    return v;
  }

  static Vec3 Vector(const std::string& path, bool has, const calibration::Vec3Estimate& e) {
    if (!has) Fail(path, "missing");
    return Vec3(Scalar(path + ".x", e.has_x(), e.x()), Scalar(path + ".y", e.has_y(), e.y()),
                Scalar(path + ".z", e.has_z(), e.z()));
  }

  static SinusoidFit Sinusoid(const std::string& path, bool has,
                              const calibration::SinusoidFit& e) {
    if (!has) Fail(path, "missing");
    SinusoidFit fit;
    fit.a = Scalar(path + ".a_m", e.has_a_m(), e.a_m());
    fit.c = Scalar(path + ".c_rad", e.has_c_rad(), e.c_rad());
    fit.d = Scalar(path + ".d_m", e.has_d_m(), e.d_m());
    return fit;
  }
};

class ErrorCollector : public pb::io::ErrorCollector {
 public:
  explicit ErrorCollector(std::string source) : source_(std::move(source)) {}
  // 0-based from the tokenizer; printed 1-based.
  void AddError(int line, pb::io::ColumnNumber column, const std::string& message) override {
    if (!errors_.empty()) errors_ += "\n";
    errors_ += source_ + ":" + std::to_string(line + 1) + ":" + std::to_string(column + 1) + ": " +
               message;
  }
  const std::string& errors() const { return errors_; }

 private:
  std::string source_;
  std::string errors_;
};

[[noreturn]] void ThrowErrno(const std::string& path, const std::string& step, int err) {
  throw std::runtime_error("cannot write '" + path + "': " + step + ": " + std::strerror(err));
}

}  // namespace

void FillCalibrationValues(const RobotCalibration& cal, calibration::Calibration* out) {
  // Keep existing legs (and the sigmas the method put there) when they are the right ones.
  bool legs_match = out->leg_size() == kNumLegs;
  for (int k = 0; legs_match && k < kNumLegs; ++k) {
    legs_match = out->leg(k).name() == kLegNames[k];
  }
  if (!legs_match) {
    out->clear_leg();
    for (int k = 0; k < kNumLegs; ++k) out->add_leg()->set_name(std::string(kLegNames[k]));
  }
  out->set_g0_m_s2(cal.g0);
  out->set_total_mass_kg(cal.total_mass_kg);
  SetVec3(cal.p_C_B, out->mutable_p_c_b_m());
  // Only a delay that is applied is written: a file without one reads as no delay.
  if (cal.servo_delay_s != 0.0 || out->has_latencies()) {
    out->mutable_latencies()->set_applied_servo_delay_s(cal.servo_delay_s);
  }
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& l = cal.leg[k];
    calibration::LegCalibration* leg = out->mutable_leg(k);
    SetVec3(l.offset.head<3>(), leg->mutable_force_offset_n());
    SetVec3(l.offset.tail<3>(), leg->mutable_torque_offset_nm());
    leg->mutable_leg_weight_n()->set_value(l.weight_n);
    SetSinusoid(l.com.x, leg->mutable_com()->mutable_x());
    leg->mutable_com()->mutable_y_m()->set_value(l.com.y);
    SetSinusoid(l.com.z, leg->mutable_com()->mutable_z());
    calibration::Mounting* m = leg->mutable_mounting();
    m->clear_quaternion_wxyz();
    const Eigen::Vector4d q = RotationToQuaternion(l.R_tilde);
    for (int i = 0; i < 4; ++i) m->add_quaternion_wxyz(q[i]);
    SetVec3(LogSO3(l.R_tilde) * (180.0 / M_PI), m->mutable_rotation_vector_deg());
    SetVec3(l.p_tilde_prime, m->mutable_p_tilde_prime_m());
    SetVec3(cal.PTilde(k), m->mutable_p_tilde_m());
  }
}

RobotCalibration CalibrationFromProto(const calibration::Calibration& proto,
                                      const config::Robot& robot) {
  using R = Reader;
  if (proto.leg_size() != kNumLegs) {
    R::Fail("leg", "expected " + std::to_string(kNumLegs) + " legs, got " +
                       std::to_string(proto.leg_size()));
  }
  RobotCalibration cal;
  try {
    cal.X_B_ft = NominalTransducerPoses(robot);
  } catch (const ConfigError& e) {
    throw std::runtime_error(std::string("calibration: the config does not describe the robot: ") +
                             e.what());
  }
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string path = "leg[" + std::to_string(k) + "]";
    const calibration::LegCalibration& leg = proto.leg(k);
    if (leg.name() != robot.leg(k).name()) {
      R::Fail(path + ".name", "leg '" + leg.name() + "' where the config has '" +
                                  robot.leg(k).name() + "' (legs must be in config order)");
    }
    LegCalibration& l = cal.leg[k];
    l.offset.head<3>() =
        R::Vector(path + ".force_offset_n", leg.has_force_offset_n(), leg.force_offset_n());
    l.offset.tail<3>() =
        R::Vector(path + ".torque_offset_nm", leg.has_torque_offset_nm(), leg.torque_offset_nm());
    if (!leg.has_leg_weight_n()) R::Fail(path + ".leg_weight_n", "missing");
    l.weight_n = R::Scalar(path + ".leg_weight_n.value", leg.leg_weight_n().has_value(),
                           leg.leg_weight_n().value());
    if (!leg.has_com()) R::Fail(path + ".com", "missing");
    const calibration::LegCom& com = leg.com();
    l.com.x = R::Sinusoid(path + ".com.x", com.has_x(), com.x());
    if (!com.has_y_m()) R::Fail(path + ".com.y_m", "missing");
    l.com.y = R::Scalar(path + ".com.y_m.value", com.y_m().has_value(), com.y_m().value());
    l.com.z = R::Sinusoid(path + ".com.z", com.has_z(), com.z());

    if (!leg.has_mounting()) R::Fail(path + ".mounting", "missing");
    const calibration::Mounting& m = leg.mounting();
    const std::string qpath = path + ".mounting.quaternion_wxyz";
    if (m.quaternion_wxyz_size() != 4) {
      R::Fail(qpath,
              "needs 4 numbers (w, x, y, z), got " + std::to_string(m.quaternion_wxyz_size()));
    }
    Eigen::Vector4d q;
    for (int i = 0; i < 4; ++i) {
      q[i] = R::Scalar(qpath + "[" + std::to_string(i) + "]", true, m.quaternion_wxyz(i));
    }
    if (std::abs(q.norm() - 1.0) > kQuaternionNormTolerance) {
      R::Fail(qpath, "not a unit quaternion (norm " + Num(q.norm()) + ")");
    }
    l.R_tilde = QuaternionToRotation(q);
    if (m.has_rotation_vector_deg()) {
      const Vec3 rv_deg =
          R::Vector(path + ".mounting.rotation_vector_deg", true, m.rotation_vector_deg());
      const double disagreement_deg =
          LogSO3(l.R_tilde.transpose() * ExpSO3(rv_deg * (M_PI / 180.0))).norm() * 180.0 / M_PI;
      if (disagreement_deg > kRotationAgreementDeg) {
        R::Fail(path + ".mounting.rotation_vector_deg",
                "disagrees with quaternion_wxyz by " + Num(disagreement_deg) + " deg");
      }
    }
    l.p_tilde_prime =
        R::Vector(path + ".mounting.p_tilde_prime_m", m.has_p_tilde_prime_m(), m.p_tilde_prime_m());
  }
  // Models 1 and 3 do not estimate p^C_B; it is then zero (informational for correction).
  if (proto.has_p_c_b_m()) cal.p_C_B = R::Vector("p_c_b_m", true, proto.p_c_b_m());
  // The file's g0 and mass are the ones the parameters were estimated with; the config's
  // stand in only when the file lacks them.
  cal.g0 = proto.has_g0_m_s2() ? R::Scalar("g0_m_s2", true, proto.g0_m_s2()) : robot.g0_m_s2();
  cal.total_mass_kg = proto.has_total_mass_kg()
                          ? R::Scalar("total_mass_kg", true, proto.total_mass_kg())
                          : robot.total_mass_kg();
  if (proto.has_latencies() && proto.latencies().has_applied_servo_delay_s()) {
    cal.servo_delay_s = R::Scalar("latencies.applied_servo_delay_s", true,
                                  proto.latencies().applied_servo_delay_s());
    // Beyond the aligner's wait for a servo state (50 ms by default) no pairing could use it;
    // a second is no servo bus's latency but a unit error.
    if (!(std::abs(cal.servo_delay_s) <= kMaxServoDelayS)) {
      R::Fail("latencies.applied_servo_delay_s",
              "|" + Num(cal.servo_delay_s) + "| s is beyond " + Num(kMaxServoDelayS) + " s");
    }
  }
  if (!(cal.g0 > 0.0)) R::Fail("g0_m_s2", "must be > 0, got " + Num(cal.g0));
  if (!(cal.total_mass_kg > 0.0)) {
    R::Fail("total_mass_kg", "must be > 0, got " + Num(cal.total_mass_kg));
  }
  return cal;
}

void CheckCalibrationPlausible(const RobotCalibration& cal, const config::Config& config) {
  const config::Robot& robot = config.robot();
  auto refuse = [](const std::string& parameter, double value, const std::string& limit) {
    throw std::runtime_error("implausible calibration: " + parameter + " = " + Num(value) +
                             ", outside " + limit);
  };
  const double tolerance_kg = config.calibrator().mass_tolerance_kg();
  if (!(std::abs(cal.total_mass_kg - robot.total_mass_kg()) <= tolerance_kg)) {
    refuse("total_mass_kg", cal.total_mass_kg,
           "the config's robot.total_mass_kg " + Num(robot.total_mass_kg()) + " +- " +
               Num(tolerance_kg) + " kg (calibrator.mass_tolerance_kg)");
  }
  if (!(std::abs(cal.g0 - robot.g0_m_s2()) <= kG0ToleranceMs2)) {
    refuse("g0_m_s2", cal.g0,
           "the config's robot.g0_m_s2 " + Num(robot.g0_m_s2()) + " +- " + Num(kG0ToleranceMs2) +
               " m/s^2");
  }
  double size_m = 0.0;
  for (const Pose3& X : NominalTransducerPoses(robot)) size_m = std::max(size_m, X.p.norm());
  size_m = std::max(2.0 * size_m, kMinRobotSizeM);
  const std::string size_limit =
      "+-" + Num(size_m) +
      " m (the robot's size: twice its farthest transducer from the body "
      "origin)";
  const double robot_weight_n = robot.total_mass_kg() * robot.g0_m_s2();
  double legs_n = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& l = cal.leg[k];
    const std::string leg = "leg[" + std::to_string(k) + "] (" + robot.leg(k).name() + ")";
    // 0 is a tare-only calibration (no leg gravity model): the naive-tare baseline the report
    // and pipeline_e2e_test compare against. Below it, no leg weighs that.
    if (!(l.weight_n >= 0.0 && l.weight_n < robot_weight_n)) {
      refuse(leg + ".leg_weight_n", l.weight_n,
             "[0, " + Num(robot_weight_n) + ") N (the robot's weight, robot.total_mass_kg g0)");
    }
    legs_n += l.weight_n;
    const config::AtiTransducer& ati = robot.leg(k).ati();
    if (ati.rated_range_size() == 6) {
      static const char* const kAxes[] = {"force_offset_n.x",   "force_offset_n.y",
                                          "force_offset_n.z",   "torque_offset_nm.x",
                                          "torque_offset_nm.y", "torque_offset_nm.z"};
      for (int i = 0; i < 6; ++i) {
        if (!(std::abs(l.offset[i]) <= ati.rated_range(i))) {
          refuse(leg + "." + kAxes[i], l.offset[i],
                 "the transducer's rated range +-" + Num(ati.rated_range(i)) + " (robot.leg[" +
                     std::to_string(k) + "].ati.rated_range[" + std::to_string(i) + "])");
        }
      }
    }
    for (int i = 0; i < 3; ++i) {
      if (!(std::abs(l.p_tilde_prime[i]) <= size_m)) {
        refuse(leg + ".mounting.p_tilde_prime_m[" + std::to_string(i) + "]", l.p_tilde_prime[i],
               size_limit);
      }
    }
    // The CoM curve a sin(2 pi phi + c) + d reaches |a| + |d|.
    const double com_x = std::abs(l.com.x.a) + std::abs(l.com.x.d);
    const double com_z = std::abs(l.com.z.a) + std::abs(l.com.z.d);
    if (!(com_x <= size_m)) refuse(leg + ".com.x (largest |r_x|)", com_x, size_limit);
    if (!(std::abs(l.com.y) <= size_m)) refuse(leg + ".com.y_m", l.com.y, size_limit);
    if (!(com_z <= size_m)) refuse(leg + ".com.z (largest |r_z|)", com_z, size_limit);
  }
  if (!(legs_n < robot_weight_n)) {
    refuse("the sum of the leg weights (N)", legs_n,
           "(0, " + Num(robot_weight_n) + ") N (the legs are part of the robot's weight)");
  }
  for (int i = 0; i < 3; ++i) {
    if (!(std::abs(cal.p_C_B[i]) <= size_m)) {
      refuse("p_c_b_m[" + std::to_string(i) + "]", cal.p_C_B[i], size_limit);
    }
  }
}

calibration::Calibration ReadCalibrationFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw std::runtime_error("cannot open calibration file '" + path +
                             "': " + std::strerror(errno));
  }
  std::ostringstream s;
  s << in.rdbuf();
  if (in.bad()) {
    throw std::runtime_error("cannot read calibration file '" + path +
                             "': " + std::strerror(errno));
  }
  const std::string text = s.str();
  calibration::Calibration cal;
  ErrorCollector collector(path);
  pb::TextFormat::Parser parser;
  parser.RecordErrorsTo(&collector);
  pb::io::ArrayInputStream input(text.data(), static_cast<int>(text.size()));
  if (!parser.Parse(&input, &cal)) {
    throw std::runtime_error(collector.errors().empty() ? path + ":1:1: could not parse"
                                                        : collector.errors());
  }
  return cal;
}

void WriteCalibrationFile(const calibration::Calibration& cal, const std::string& path) {
  std::string text;
  if (!pb::TextFormat::PrintToString(cal, &text)) {
    throw std::runtime_error("cannot write '" + path + "': text format printing failed");
  }
  WriteFileAtomic(path, text);
}

void WriteFileAtomic(const std::string& path, const std::string& bytes) {
  const size_t slash = path.rfind('/');
  const std::string dir =
      slash == std::string::npos ? "." : (slash == 0 ? "/" : path.substr(0, slash));
  const std::string base = slash == std::string::npos ? path : path.substr(slash + 1);
  if (base.empty()) ThrowErrno(path, "not a file name", EINVAL);

  // The temporary file lives beside the target so that rename() is atomic (same filesystem).
  std::string tmp = dir + "/." + base + ".tmp.XXXXXX";
  std::vector<char> tmp_buf(tmp.begin(), tmp.end());
  tmp_buf.push_back('\0');
  const int fd = ::mkostemp(tmp_buf.data(), O_CLOEXEC);
  if (fd < 0) ThrowErrno(path, "creating a temporary file in '" + dir + "'", errno);
  tmp.assign(tmp_buf.data());

  auto fail = [&](const std::string& step, int err, bool close_fd) {
    if (close_fd) ::close(fd);
    ::unlink(tmp.c_str());
    ThrowErrno(path, step, err);
  };

  // mkstemp makes the file 0600; results are for everyone to read.
  if (::fchmod(fd, 0644) != 0) fail("fchmod", errno, true);
  size_t written = 0;
  while (written < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + written, bytes.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      fail("write", errno, true);
    }
    written += static_cast<size_t>(n);
  }
  if (::fsync(fd) != 0) fail("fsync", errno, true);
  if (::close(fd) != 0) fail("close", errno, false);
  if (::rename(tmp.c_str(), path.c_str()) != 0) fail("rename", errno, false);

  // The rename itself is durable only once the directory is synced.
  const int dir_fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir_fd < 0) ThrowErrno(path, "opening directory '" + dir + "' to fsync it", errno);
  const int sync_result = ::fsync(dir_fd);
  const int sync_errno = errno;
  ::close(dir_fd);
  if (sync_result != 0) ThrowErrno(path, "fsync of directory '" + dir + "'", sync_errno);
}

}  // namespace ftcal
