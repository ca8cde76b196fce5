// Step 1 into the calibration: the parameters of eq. 3 (ApplyHangingResult) and the calibration
// file's hanging fields (WriteHangingToCalibration), apart from the step itself so that the
// step's file reads as the method.
#include "ftcal/hanging.h"

#include <string>

namespace ftcal {

void ApplyHangingResult(const HangingResult& result, RobotCalibration* cal) {
  for (int k = 0; k < kNumLegs; ++k) {
    cal->leg[k].offset = result.leg[k].with_s.Offset();
    cal->leg[k].weight_n = result.leg[k].with_s.weight_n.value;
    cal->leg[k].com = result.leg[k].com.model;
  }
}

namespace {

void SetVec3(const Vec3Sigma& v, calibration::Vec3Estimate* out) {
  out->set_x(v.value.x());
  out->set_y(v.value.y());
  out->set_z(v.value.z());
  out->set_sigma_x(v.sigma.x());
  out->set_sigma_y(v.sigma.y());
  out->set_sigma_z(v.sigma.z());
}

void SetScalar(const ScalarSigma& v, calibration::ScalarEstimate* out) {
  out->set_value(v.value);
  out->set_sigma(v.sigma);
}

void SetSinusoid(const SinusoidFit& fit, const Vec3& sigma, calibration::SinusoidFit* out) {
  out->set_a_m(fit.a);
  out->set_c_rad(fit.c);
  out->set_d_m(fit.d);
  out->set_sigma_a_m(sigma(0));
  out->set_sigma_c_rad(sigma(1));
  out->set_sigma_d_m(sigma(2));
}

void SetStats(const WrenchResidualStats& s, calibration::ResidualStats* out) {
  out->set_label(s.label);
  out->set_count(static_cast<uint32_t>(s.count));
  for (int k = 0; k < 6; ++k) {
    out->add_mean(s.mean(k));
    out->add_std(s.std(k));
    out->add_rms(s.rms(k));
    out->add_p05(s.p05(k));
    out->add_p95(s.p95(k));
  }
}

}  // namespace

void WriteHangingToCalibration(const HangingResult& result, calibration::Calibration* out) {
  out->set_hanging_uncertainty(calibration::CYCLE_SPREAD);
  out->mutable_solver()->set_exact_hanging_rotations(result.exact_rotations);
  out->clear_hanging_residual();
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string name(kLegNames[k]);
    calibration::LegCalibration* leg = nullptr;
    for (auto& l : *out->mutable_leg()) {
      if (l.name() == name) leg = &l;
    }
    if (leg == nullptr) {
      leg = out->add_leg();
      leg->set_name(name);
    }
    const LegHangingResult& r = result.leg[k];
    SetVec3(r.with_s.force_offset_n, leg->mutable_force_offset_n());
    SetVec3(r.with_s.torque_offset_nm, leg->mutable_torque_offset_nm());
    SetScalar(r.with_s.weight_n, leg->mutable_leg_weight_n());
    calibration::LegCom* com = leg->mutable_com();
    com->Clear();
    SetSinusoid(r.com.model.x, r.com.sigma_x, com->mutable_x());
    SetSinusoid(r.com.model.z, r.com.sigma_z, com->mutable_z());
    SetScalar({r.com.model.y, r.com.sigma_y_m}, com->mutable_y_m());
    for (size_t b = 0; b < r.com_bins.phase.size(); ++b) {
      com->add_bin_phase(r.com_bins.phase[b]);
      com->add_bin_x_m(r.com_bins.median_m[b].x());
      com->add_bin_y_m(r.com_bins.median_m[b].y());
      com->add_bin_z_m(r.com_bins.median_m[b].z());
      com->add_bin_sigma_x_m(r.com_bins.sigma_m[b].x());
      com->add_bin_sigma_y_m(r.com_bins.sigma_m[b].y());
      com->add_bin_sigma_z_m(r.com_bins.sigma_m[b].z());
    }
    leg->clear_hanging();
    for (const HangingPairResult& p : r.with_s.pair) {
      calibration::HangingPair* hp = leg->add_hanging();
      hp->set_axis(std::string(1, p.axis));
      SetVec3(p.s_plus_rad, hp->mutable_s_plus_rad());
      SetVec3(p.s_minus_rad, hp->mutable_s_minus_rad());
      SetScalar(p.weight_n, hp->mutable_leg_weight_n());
      SetVec3(p.force_offset_n, hp->mutable_force_offset_n());
      SetVec3(p.torque_offset_nm, hp->mutable_torque_offset_nm());
      hp->set_matched_samples(static_cast<uint32_t>(p.matched_samples));
    }
    leg->clear_naive_offset();
    for (int i = 0; i < 6; ++i) leg->add_naive_offset(r.naive_offset(i));
  }
  for (int k = 0; k < kNumLegs; ++k) {
    SetStats(result.leg[k].with_s.residual, out->add_hanging_residual());
    SetStats(result.leg[k].without_s.residual, out->add_hanging_residual());
    SetStats(result.leg[k].naive_residual, out->add_hanging_residual());
  }
}

}  // namespace ftcal
