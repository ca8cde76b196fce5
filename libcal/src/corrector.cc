#include "ftcal/corrector.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace ftcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

void CheckAge(double s, const char* what) {
  if (!(s > 0) || !std::isfinite(s)) {
    throw std::invalid_argument(std::string("Corrector: ") + what + " must be > 0 s, got " +
                                std::to_string(s));
  }
}

std::string LegLabel(int k) { return "leg " + std::string(kLegNames[k]); }

}  // namespace

Corrector::Corrector(const CorrectorOptions& options) : options_(options) {
  CheckAge(options.max_ft_age_s, "max_ft_age_s");
  CheckAge(options.max_servo_age_s, "max_servo_age_s");
  CheckAge(options.max_mocap_age_s, "max_mocap_age_s");
}

void Corrector::SetCalibration(const RobotCalibration& cal, int64_t version) {
  std::array<LegConst, kNumLegs> leg;
  for (int k = 0; k < kNumLegs; ++k) {
    const Pose3 X = cal.X_C_ft(k);
    if (!X.R.allFinite() || !X.p.allFinite() || OrthonormalityError(X.R) > 1e-6) {
      throw std::invalid_argument("Corrector: " + LegLabel(k) +
                                  ": X_C_ft is not a finite rigid transform");
    }
    const LegCalibration& l = cal.leg[k];
    const LegComModel& c = l.com;
    if (!l.offset.allFinite() || !std::isfinite(l.weight_n) ||
        !std::isfinite(c.x.a + c.x.c + c.x.d + c.y + c.z.a + c.z.c + c.z.d)) {
      throw std::invalid_argument("Corrector: " + LegLabel(k) +
                                  ": offset, weight or CoM curve not finite");
    }
    leg[k] = {X.R, X.p, l.offset, l.weight_n, l.com};
  }
  if (!(cal.TotalWeightN() > 0) || !std::isfinite(cal.TotalWeightN())) {
    throw std::invalid_argument("Corrector: total weight must be finite and > 0, got " +
                                std::to_string(cal.TotalWeightN()) + " N");
  }
  leg_ = leg;
  weight_total_n_ = cal.TotalWeightN();
  version_ = version;
  has_calibration_ = true;
  // Wrenches corrected with the previous calibration must not be summed with new ones.
  for (LegState& s : state_) s.seen = false;
}

bool Corrector::AddServo(const ServoInput& in) {
  if (!AcceptServo(in, &servo_, &counters_)) return false;
  return true;
}

bool Corrector::AddMocap(const MocapInput& in) { return AcceptMocap(in, &mocap_, &counters_); }

// Eq. 3 with the precomputed X_C_ft: f^C = R (f_m - f_o), tau^C = R (tau_m - tau_o) + p x f^C,
// minus the leg's gravity wrench about the CoM, then both rotated by R_WC.
Vec6 Corrector::CorrectLeg(int k, const Vec6& w_m, double angle_rad, const Mat3& R_WC) const {
  const LegConst& l = leg_[k];
  const Vec6 d = w_m - l.offset;
  const Vec3 f_C = l.R_C_ft * d.head<3>();
  const Vec3 tau_C = l.R_C_ft * d.tail<3>() + l.p_C_ft.cross(f_C);
  // g^C = R_WC^T (0, 0, -1) per unit weight: minus W's z axis seen in C.
  const Vec3 mg_C = -l.weight_n * R_WC.row(2).transpose();
  const Vec3 r_C = l.R_C_ft * l.com.At(LegPhase(angle_rad)) + l.p_C_ft;
  Vec6 w_W;
  w_W.head<3>() = R_WC * (f_C - mg_C);
  w_W.tail<3>() = R_WC * (tau_C - r_C.cross(mg_C));
  return w_W;
}

std::optional<ContactWrenches> Corrector::AddFt(const FtInput& in, bool saturated) {
  ContactWrenches out;
  if (!AddFt(in, saturated, &out)) return std::nullopt;
  return out;
}

bool Corrector::AddFt(const FtInput& in, bool saturated, ContactWrenches* out) {
  if (in.leg < 0 || in.leg >= kNumLegs) {
    throw std::invalid_argument("Corrector::AddFt: leg index " + std::to_string(in.leg) +
                                " outside [0, " + std::to_string(kNumLegs) + ")");
  }
  ++counters_.ft_in;
  if (!in.wrench.allFinite()) {
    ++counters_.non_finite;
    return false;
  }
  LegState& st = state_[in.leg];
  if (st.seen && in.utime <= st.utime) {
    ++counters_.out_of_order;
    return false;
  }
  if (!has_calibration_) {
    ++counters_.no_calibration;
    return false;
  }
  const int64_t t = in.utime;
  int32_t flags = 0;

  // Attitude: the latest frame if fresh and tracked, else level.
  Mat3 R_WC = Mat3::Identity();
  out->mocap_age_s = -1.0;
  if (mocap_) {
    out->mocap_age_s = 1e-6 * static_cast<double>(t - mocap_->utime);
    if (mocap_->tracked && std::abs(out->mocap_age_s) <= options_.max_mocap_age_s) {
      R_WC = mocap_->R_WC;
    } else {
      flags |= kFlagStaleMocap;
    }
  } else {
    flags |= kFlagStaleMocap;
  }

  double angle = kNaN;
  out->servo_age_s = -1.0;
  if (const auto look = servo_.At(t)) {
    angle = look->angle_rad[in.leg];
    out->servo_age_s = look->age_s;
    if (look->age_s > options_.max_servo_age_s) flags |= kFlagStaleServo;
  } else {
    ++counters_.no_servo;  // no phase: the leg's wrench is NaN, flagged
    flags |= kFlagStaleServo;
  }

  st.seen = true;
  st.utime = t;
  st.saturated = saturated;
  st.wrench_W = std::isnan(angle) ? Vec6::Constant(kNaN) : CorrectLeg(in.leg, in.wrench, angle, R_WC);

  out->utime = t;
  out->updated_leg = in.leg;
  out->calibration_version = version_;
  out->total_W.setZero();
  for (int k = 0; k < kNumLegs; ++k) {
    const LegState& s = state_[k];
    if (!s.seen) {
      out->wrench_W[k].setConstant(kNaN);
      out->ft_age_s[k] = -1.0;
      flags |= kFlagStaleFt;
    } else {
      out->wrench_W[k] = s.wrench_W;
      out->ft_age_s[k] = 1e-6 * static_cast<double>(t - s.utime);
      if (std::abs(out->ft_age_s[k]) > options_.max_ft_age_s) flags |= kFlagStaleFt;
      if (s.saturated) flags |= kFlagSaturated;
    }
    out->total_W += out->wrench_W[k];
  }
  out->residual_W = out->total_W;
  out->residual_W[2] -= weight_total_n_;
  out->flags = flags;
  ++counters_.corrected;
  return true;
}

}  // namespace ftcal
