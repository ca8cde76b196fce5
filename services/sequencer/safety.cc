#include "sequencer/safety.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

#include "ftcal/config.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/service_status_t.hpp"

namespace ftcal::sequencer {
namespace {

constexpr double kDeg = M_PI / 180.0;
constexpr const char* kAxes[6] = {"Fx", "Fy", "Fz", "Tx", "Ty", "Tz"};

std::string Num(double v, int precision = 4) {
  std::ostringstream s;
  s.precision(precision);
  s << v;
  return s.str();
}

}  // namespace

int64_t OwnStalls::Awake(int64_t now_utime) {
  int64_t stalled = 0;
  if (last_utime_ > 0 && now_utime - last_utime_ > kStallUs) {
    stalled = now_utime - last_utime_;
    stalls_.push_back({last_utime_, now_utime});
  }
  last_utime_ = std::max(last_utime_, now_utime);
  while (!stalls_.empty() && stalls_.front().to < now_utime - kMemoryUs) stalls_.pop_front();
  return stalled;
}

int64_t OwnStalls::StalledUs(int64_t since_utime, int64_t now_utime) const {
  int64_t sum = 0;
  for (const Span& s : stalls_) {
    const int64_t from = std::max(s.from, since_utime), to = std::min(s.to, now_utime);
    if (to > from) sum += to - from;
  }
  return sum;
}

Safety::Safety(const config::Config& config) : config_(config), seq_(config.sequencer()) {
  const auto poses = NominalTransducerPoses(config.robot());
  for (int k = 0; k < kNumLegs; ++k) {
    R_B_ft_[k] = poses[k].R;
    rated_[k].setConstant(std::numeric_limits<double>::infinity());
    const config::AtiTransducer& ati = config.robot().leg(k).ati();
    for (int i = 0; i < std::min(6, ati.rated_range_size()); ++i) rated_[k][i] = ati.rated_range(i);
  }
  weight_n_ = config.robot().total_mass_kg() * config.robot().g0_m_s2();
}

std::set<std::string> WatchedStatusNames(const config::Config& config) {
  auto status_name = [](const config::LaunchProcess& p) -> std::string {
    if (p.status_name() == "-") return "";
    if (!p.status_name().empty()) return p.status_name();
    const auto slash = p.command().rfind('/');
    return slash == std::string::npos ? p.command() : p.command().substr(slash + 1);
  };
  auto is_bridge = [](const std::string& name) {
    static const std::string kSuffix = "-bridge";
    return name.size() > kSuffix.size() &&
           name.compare(name.size() - kSuffix.size(), kSuffix.size(), kSuffix) == 0;
  };
  std::set<std::string> names;
  for (const config::LaunchGroup& g : config.launch().group()) {
    bool ours = false;
    for (const auto& p : g.process()) ours = ours || status_name(p) == "ftcal-sequencer";
    if (!ours) continue;
    for (const auto& p : g.process()) {
      if (is_bridge(status_name(p))) names.insert(status_name(p));
    }
  }
  // The bridges whose data the sequencer reads, launched by a group or not.
  names.insert({"ftcal-ati-bridge", "ftcal-dynamixel-bridge",
                config.mocap().system() == config::OPTITRACK ? "ftcal-natnet-bridge"
                                                             : "ftcal-mocap-bridge"});
  return names;
}

std::optional<std::string> Safety::Stale(const Inputs& in, int64_t now_utime, bool need_mocap,
                                         const OwnStalls& own) const {
  const double limit = seq_.max_input_age_s();
  auto old = [&](const std::string& what, int64_t utime) -> std::optional<std::string> {
    const int64_t stalled = own.StalledUs(utime, now_utime);
    const double age = (now_utime - utime - stalled) * 1e-6;
    if (age > limit) {
      return what + " is " + Num(age, 3) + " s old, above sequencer.max_input_age_s " + Num(limit) +
             (stalled > 0 ? " (not counting " + Num(stalled * 1e-6, 3) +
                                " s in which the sequencer itself did not run)"
                          : std::string());
    }
    return std::nullopt;
  };
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string what = "FT_" + std::string(kLegNames[k]);
    if (!in.ft[k]) return "no " + what + " sample yet";
    if (auto e = old(what, in.ft[k]->utime)) return e;
  }
  if (!in.servo) return std::string("no SERVO_STATE yet");
  if (auto e = old("SERVO_STATE", in.servo->utime)) return e;
  if (need_mocap) {
    if (!in.mocap) return std::string("no MOCAP_BODY yet");
    if (auto e = old("MOCAP_BODY", in.mocap->utime)) return e;
  }
  for (const auto& [name, st] : in.status) {
    if ((now_utime - st.utime) * 1e-6 > kStatusExpiryS) continue;
    if (st.state != service_status_t::RUNNING && st.state != service_status_t::STARTING) {
      return name + " reports state " + std::to_string(st.state) +
             (st.last_error.empty() ? std::string() : " (" + st.last_error + ")") +
             " in FTCAL_STATUS, not RUNNING";
    }
  }
  return std::nullopt;
}

std::optional<std::string> Safety::OverRange(const Inputs& in) const {
  for (int k = 0; k < kNumLegs; ++k) {
    if (!in.ft[k]) continue;
    const FtInput& r = *in.ft[k];
    for (int i = 0; i < 6; ++i) {
      if (!(std::abs(r.wrench[i]) <= rated_[k][i])) {
        return "FT_" + std::string(kLegNames[k]) + " " + kAxes[i] + " = " + Num(r.wrench[i]) +
               " is beyond the rated range " + Num(rated_[k][i]) + " (robot.leg[" +
               std::to_string(k) + "].ati.rated_range)";
      }
    }
    if (r.flags & ft_batch_t::FLAG_SATURATED)
      return "FT_" + std::string(kLegNames[k]) + " is flagged saturated";
  }
  return std::nullopt;
}

double Safety::TiltDeg(const Mat3& R_WC) {
  // The angle between the body's z axis and the vertical.
  const double c = std::clamp(R_WC(2, 2), -1.0, 1.0);
  return std::acos(c) / kDeg;
}

std::optional<std::string> Safety::Tilted(const Inputs& in) const {
  if (!in.mocap) return std::string("no MOCAP_BODY to see the body's tilt");
  if (!in.mocap->tracked) return std::string("MOCAP_BODY: the body is not tracked");
  const double tilt = TiltDeg(in.mocap->R_WC);
  if (tilt > seq_.max_tilt_deg()) {
    return "the body is tilted " + Num(tilt, 3) + " deg, above sequencer.max_tilt_deg " +
           Num(seq_.max_tilt_deg());
  }
  return std::nullopt;
}

std::optional<std::string> Safety::Airborne(const Inputs& in, const Vec3& stated_gravity_b) const {
  // Gravity in B as the operator states it (upright for the tare).
  const Vec3 g_b = stated_gravity_b.norm() > 0.0 ? stated_gravity_b.normalized() : Vec3(0, 0, -1);
  Vec3 sum = Vec3::Zero();
  for (int k = 0; k < kNumLegs; ++k) {
    if (!in.ft[k]) return "no FT_" + std::string(kLegNames[k]) + " sample yet";
    sum += R_B_ft_[k] * in.ft[k]->wrench.head<3>();
  }
  // In the air the legs hang from the chassis and pull it along gravity with their weight;
  // whatever else the sum holds (a push against gravity, or across it) is support from outside.
  const double support = (sum - std::max(0.0, sum.dot(g_b)) * g_b).norm();
  if (support > seq_.airborne_max_support_n()) {
    return "the robot is not in the air: the transducers' summed force has " + Num(support) +
           " N that is not the legs hanging along gravity (" + Num(g_b.x()) + ", " + Num(g_b.y()) +
           ", " + Num(g_b.z()) + "), above sequencer.airborne_max_support_n " +
           Num(seq_.airborne_max_support_n());
  }
  if (!in.mocap)
    return std::nullopt;  // motion capture is optional for hanging (the report had none)
  if (!in.mocap->tracked) return std::string("MOCAP_BODY: the body is not tracked");
  if (stated_gravity_b.norm() == 0.0) return Tilted(in);
  const Vec3 g_C = in.mocap->R_WC.transpose() * Vec3(0.0, 0.0, -1.0);
  const double angle =
      std::acos(std::clamp(g_C.dot(stated_gravity_b.normalized()), -1.0, 1.0)) / kDeg;
  const double tol = config_.mocap().hang_axis_tolerance_deg();
  if (angle > tol) {
    return "motion capture sees gravity " + Num(angle, 3) + " deg from the stated body axis (" +
           Num(stated_gravity_b.x()) + ", " + Num(stated_gravity_b.y()) + ", " +
           Num(stated_gravity_b.z()) + "), above mocap.hang_axis_tolerance_deg " + Num(tol);
  }
  return std::nullopt;
}

std::optional<std::string> Safety::Standing(const Inputs& in) const {
  if (auto e = Tilted(in)) return e;
  double up = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    if (!in.ft[k]) return "no FT_" + std::string(kLegNames[k]) + " sample yet";
    // The wrench the leg exerts on the chassis: standing, the legs push the chassis up.
    up += (R_B_ft_[k] * in.ft[k]->wrench.head<3>()).z();
  }
  const double lo = seq_.standing_min_weight_share() * weight_n_;
  const double hi = seq_.standing_max_weight_share() * weight_n_;
  if (!(up >= lo && up <= hi)) {
    return "the robot is not standing: the transducers carry " + Num(up) + " N upward, outside [" +
           Num(lo) + ", " + Num(hi) +
           "] N (sequencer.standing_{min,max}_weight_share of m g = " + Num(weight_n_) + " N)";
  }
  return std::nullopt;
}

}  // namespace ftcal::sequencer
