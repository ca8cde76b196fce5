#include "ftcal/corrector.h"

#include <algorithm>
#include <cmath>
#include <cstring>
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

LegWrench LegWrenchOf(const ContactWrenches& c) {
  LegWrench w;
  w.utime = c.utime;
  w.leg = c.updated_leg;
  w.wrench_W = c.wrench_W[c.updated_leg];
  w.servo_age_s = c.servo_age_s;
  w.mocap_age_s = c.mocap_age_s;
  w.flags = c.leg_flags;
  return w;
}

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
  if (!(std::abs(cal.servo_delay_s) < options_.max_servo_age_s)) {
    throw std::invalid_argument("Corrector: servo delay " + std::to_string(cal.servo_delay_s) +
                                " s: its magnitude must be below max_servo_age_s " +
                                std::to_string(options_.max_servo_age_s) + " s");
  }
  if (!(cal.TotalWeightN() > 0) || !std::isfinite(cal.TotalWeightN())) {
    throw std::invalid_argument("Corrector: total weight must be finite and > 0, got " +
                                std::to_string(cal.TotalWeightN()) + " N");
  }
  leg_ = leg;
  weight_total_n_ = cal.TotalWeightN();
  const int64_t delay_us = std::llround(cal.servo_delay_s * 1e6);
  // The states held were shifted by the old delay: mixed with new ones they could run backwards.
  if (delay_us != servo_delay_us_) servo_ = ServoHistory();
  servo_delay_us_ = delay_us;
  version_ = version;
  has_calibration_ = true;
  // Wrenches corrected with the previous calibration must not be summed with new ones.
  for (LegState& s : state_) s.seen = false;
  for (History& h : history_) h.count = 0;
  for (ComMemo& m : com_memo_) m.valid = false;  // computed with the old CoM curve
  newest_utime_ = 0;
  first_utime_ = 0;
  last_sum_utime_ = -1;
}

bool Corrector::AddServo(const ServoInput& in) {
  // On the transducers' time base (docs/method.md "Latencies"): the state describes the shaft
  // servo_delay_s before its stamp.
  ServoInput shifted = in;
  shifted.utime -= servo_delay_us_;
  if (!AcceptServo(shifted, &servo_, &counters_)) return false;
  return true;
}

bool Corrector::AddMocap(const MocapInput& in) { return AcceptMocap(in, &mocap_, &counters_); }

const Vec3& Corrector::ComInC(int k, double angle_rad) {
  ComMemo& m = com_memo_[k];
  uint64_t bits;
  std::memcpy(&bits, &angle_rad, sizeof bits);
  if (!m.valid || m.angle_bits != bits) {
    const LegConst& l = leg_[k];
    m.r_C = l.R_C_ft * l.com.At(LegPhase(angle_rad)) + l.p_C_ft;
    m.angle_bits = bits;
    m.valid = true;
  }
  return m.r_C;
}

// Eq. 3 with the precomputed X_C_ft: f^C = R (f_m - f_o), tau^C = R (tau_m - tau_o) + p x f^C,
// minus the leg's gravity wrench about the CoM (at r_C), then both rotated by R_WC.
Vec6 Corrector::CorrectLeg(int k, const Vec6& w_m, const Vec3& r_C, const Mat3& R_WC) const {
  const LegConst& l = leg_[k];
  const Vec6 d = w_m - l.offset;
  const Vec3 f_C = l.R_C_ft * d.head<3>();
  const Vec3 tau_C = l.R_C_ft * d.tail<3>() + l.p_C_ft.cross(f_C);
  // g^C = R_WC^T (0, 0, -1) per unit weight: minus W's z axis seen in C.
  const Vec3 mg_C = -l.weight_n * R_WC.row(2).transpose();
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

  if (saturated) flags |= kFlagSaturated;
  st.seen = true;
  st.utime = t;
  st.flags = flags;
  st.wrench_W = std::isnan(angle) ? Vec6::Constant(kNaN)
                                  : CorrectLeg(in.leg, in.wrench, ComInC(in.leg, angle), R_WC);

  History& h = history_[in.leg];
  Past& past = h.ring[static_cast<size_t>(h.count % kHistory)];
  past.utime = t;
  past.flags = flags;
  past.wrench_W = st.wrench_W;
  ++h.count;
  if (newest_utime_ == 0) first_utime_ = t;
  newest_utime_ = std::max(newest_utime_, t);

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
      flags |= s.flags & kFlagSaturated;
    }
    out->total_W += out->wrench_W[k];
  }
  out->residual_W = out->total_W;
  out->residual_W[2] -= weight_total_n_;
  out->flags = flags;
  out->leg_flags = st.flags;
  ++counters_.corrected;
  return true;
}

bool Corrector::NextSum(WrenchSum* out, bool input_ended) {
  if (!has_calibration_) return false;
  const auto max_age_us = static_cast<int64_t>(options_.max_ft_age_s * 1e6);
  // A leg never seen is waited for as long as a seen one: max_ft_age_s from the first sample.
  auto silent = [&](int k) {
    return (state_[k].seen ? state_[k].utime : first_utime_) < newest_utime_ - max_age_us;
  };
  int pace = -1;
  for (int k = 0; k < kNumLegs && pace < 0; ++k) {
    if (!silent(k)) pace = k;
  }
  if (pace < 0) return false;  // no leg seen yet
  // The pace leg's oldest sample after the last sum (still in its history).
  const History& ph = history_[pace];
  const int64_t first = std::max<int64_t>(0, ph.count - kHistory);
  int64_t i = ph.count - 1;
  if (i < first || ph.At(i).utime <= last_sum_utime_) return false;
  while (i > first && ph.At(i - 1).utime > last_sum_utime_) --i;
  const int64_t t = ph.At(i).utime;
  for (int k = 0; k < kNumLegs && !input_ended; ++k) {
    // Wait for its sample at or after t.
    if (!silent(k) && (!state_[k].seen || state_[k].utime < t)) return false;
  }
  out->utime = t;
  out->calibration_version = version_;
  out->total_W.setZero();
  out->oldest_ft_age_s = 0.0;
  int32_t flags = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const History& hk = history_[k];
    if (hk.count == 0) {
      out->total_W += Vec6::Constant(kNaN);
      out->oldest_ft_age_s = -1.0;
      flags |= kFlagStaleFt;
      continue;
    }
    // The sample nearest t: from the latest back while the one before is no farther.
    const int64_t oldest = std::max<int64_t>(0, hk.count - kHistory);
    int64_t j = hk.count - 1;
    auto distance = [&](int64_t at) { return std::abs(hk.At(at).utime - t); };
    while (j > oldest && distance(j - 1) <= distance(j)) --j;
    const Past& p = hk.At(j);
    out->total_W += p.wrench_W;
    const double age_s = 1e-6 * static_cast<double>(distance(j));
    if (out->oldest_ft_age_s >= 0) out->oldest_ft_age_s = std::max(out->oldest_ft_age_s, age_s);
    if (age_s > options_.max_ft_age_s) flags |= kFlagStaleFt;
    flags |= p.flags;
  }
  out->residual_W = out->total_W;
  out->residual_W[2] -= weight_total_n_;
  out->flags = flags;
  last_sum_utime_ = t;
  return true;
}

}  // namespace ftcal
