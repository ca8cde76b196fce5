// The offset tracker's section of the config (drift, ftcal-drift): every number is one the
// tracker divides by or compares with, so each must be finite and of its sign.
#include <cmath>
#include <string>
#include <utility>

#include "config_internal.h"

namespace ftcal::config_detail {

void ValidateDrift(const Node& node, const config::Drift& d) {
  for (const auto& [name, v] : {std::pair<const char*, double>{"bin_s", d.bin_s()},
                                {"max_foot_force_n", d.max_foot_force_n()},
                                {"max_shaft_accel_rad_s2", d.max_shaft_accel_rad_s2()},
                                {"accel_baseline_s", d.accel_baseline_s()},
                                {"min_window_s", d.min_window_s()},
                                {"max_window_s", d.max_window_s()},
                                {"initial_sigma_force_n", d.initial_sigma_force_n()},
                                {"initial_sigma_torque_nm", d.initial_sigma_torque_nm()},
                                {"warn_factor", d.warn_factor()},
                                {"publish_period_s", d.publish_period_s()},
                                {"apply_factor", d.apply_factor()},
                                {"apply_min_interval_s", d.apply_min_interval_s()}}) {
    node.Positive(name, v);
  }
  for (const auto& [name, v] :
       {std::pair<const char*, double>{"max_shaft_speed_rad_s", d.max_shaft_speed_rad_s()},
        {"edge_trim_s", d.edge_trim_s()},
        {"process_noise_force_n", d.process_noise_force_n()},
        {"process_noise_torque_nm", d.process_noise_torque_nm()},
        {"window_floor_force_n", d.window_floor_force_n()},
        {"window_floor_torque_nm", d.window_floor_torque_nm()},
        {"warn_min_force_n", d.warn_min_force_n()},
        {"warn_min_torque_nm", d.warn_min_torque_nm()}}) {
    if (node.Finite(name, v) && !(v >= 0.0)) {
      node.Error(name, "must be >= 0, got " + FormatNumber(v));
    }
  }
  if (std::isfinite(d.min_window_s()) && std::isfinite(d.max_window_s()) &&
      d.max_window_s() < d.min_window_s()) {
    node.Error("max_window_s", "must be >= min_window_s (" + FormatNumber(d.min_window_s()) +
                                   "), got " + FormatNumber(d.max_window_s()));
  }
}

}  // namespace ftcal::config_detail
