// Writing one offset component into a calibration file's leg: shared by the calibrator's
// offset re-estimation and ftcal-drift's --out-calibration, which both replace offsets only.
#pragma once

#include "proto/calibration.pb.h"

namespace ftcal {

// Component i (0..5 = [f; tau]) of a leg's offset, with its sigma.
inline void SetOffsetComponent(int i, double value, double sigma,
                               calibration::LegCalibration* leg) {
  calibration::Vec3Estimate* v =
      i < 3 ? leg->mutable_force_offset_n() : leg->mutable_torque_offset_nm();
  switch (i % 3) {
    case 0:
      v->set_x(value);
      v->set_sigma_x(sigma);
      break;
    case 1:
      v->set_y(value);
      v->set_sigma_y(sigma);
      break;
    default:
      v->set_z(value);
      v->set_sigma_z(sigma);
      break;
  }
}

}  // namespace ftcal
