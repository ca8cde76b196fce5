// One file over 600 lines: one physics model, whose helpers and seeded draws every scenario shares.
#include "sim/twin.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>
#include <sstream>
#include <stdexcept>

#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/segmenter.h"

namespace ftcal {
namespace {

constexpr double kDeg = M_PI / 180.0;

// The report's Table II (legs in the order HL ML FL HR MR FR): the true parameters are drawn
// around these so the twin's numbers look like the lab robot's.
constexpr double kTableForceOffsetN[kNumLegs][3] = {{1.47, -1.30, -5.61},   {1.419, -4.884, -0.406},
                                                    {0.57, 3.71, -2.039},   {-8.49, -1.448, -2.43},
                                                    {-0.06, -0.123, -0.07}, {-0.93, 0.653, -2.183}};
constexpr double kTableTorqueOffsetNm[kNumLegs][3] = {
    {0.2457, 0.002, 0.034},   {-0.0136, 0.0808, 0.0144}, {0.2176, 0.0921, -0.0177},
    {-0.3159, 0.3449, 0.001}, {-0.2392, -0.0982, 0.004}, {-0.3611, -0.153, 0.0222}};
constexpr double kTableWeightN[kNumLegs] = {6.2, 6.2, 6.2, 6.1, 6.2, 6.4};

// Tripods: {HL, FL, MR} and {ML, HR, FR}.
constexpr std::array<int, kNumLegs> kTripod = {0, 1, 0, 1, 0, 1};

// SplitMix64 finaliser: decorrelates the per-scenario seeds derived from one user seed.
uint64_t MixSeed(uint64_t seed, uint64_t tag) {
  uint64_t z = seed + 0x9E3779B97F4A7C15ull * (tag + 1);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

enum ScenarioTag : uint64_t {
  kTagTruth = 1,
  kTagPoseOrder = 2,
  kTagHanging = 10,  // + series
  kTagStanding = 20,
  kTagTripod = 21,
  kTagWalk = 22,
  kTagDriven = 23,
  kTagDrivenInternal = 24,
  kTagTare = 25,
};

class Random {
 public:
  explicit Random(uint64_t seed) : engine_(seed) {}
  double Uniform(double lo, double hi) {
    return std::uniform_real_distribution<double>(lo, hi)(engine_);
  }
  double Normal() { return normal_(engine_); }
  double Exponential(double rate) { return std::exponential_distribution<double>(rate)(engine_); }
  Vec3 UnitVector() {
    Vec3 v;
    do {
      v = Vec3(Normal(), Normal(), Normal());
    } while (v.norm() < 1e-6);
    return v.normalized();
  }
  std::mt19937_64& Engine() { return engine_; }

 private:
  std::mt19937_64 engine_;
  std::normal_distribution<double> normal_{0.0, 1.0};
};

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("BigAntTwin: " + what);
}

void ValidateOptions(const TwinOptions& o) {
  auto non_negative = [](double v, const char* name) {
    Require(std::isfinite(v) && v >= 0.0, std::string("TwinOptions.") + name +
                                              " must be finite and >= 0, got " + std::to_string(v));
  };
  auto positive = [](double v, const char* name) {
    Require(std::isfinite(v) && v > 0.0, std::string("TwinOptions.") + name +
                                             " must be finite and > 0, got " + std::to_string(v));
  };
  auto range = [](double lo, double hi, const char* name) {
    Require(std::isfinite(lo) && std::isfinite(hi) && 0.0 <= lo && lo <= hi,
            std::string("TwinOptions.") + name + ": need 0 <= min <= max, got [" +
                std::to_string(lo) + ", " + std::to_string(hi) + "]");
  };
  non_negative(o.force_noise_n, "force_noise_n");
  non_negative(o.torque_noise_nm, "torque_noise_nm");
  non_negative(o.attitude_noise_deg, "attitude_noise_deg");
  non_negative(o.marker_noise_m, "marker_noise_m");
  non_negative(o.marker_dropout_rate_hz, "marker_dropout_rate_hz");
  positive(o.marker_dropout_mean_s, "marker_dropout_mean_s");
  positive(o.counts_per_force, "counts_per_force");
  positive(o.counts_per_torque, "counts_per_torque");
  positive(o.sample_rate_hz, "sample_rate_hz");
  non_negative(o.offset_force_spread_n, "offset_force_spread_n");
  non_negative(o.offset_torque_spread_nm, "offset_torque_spread_nm");
  non_negative(o.weight_spread_n, "weight_spread_n");
  range(o.tilt_min_deg, o.tilt_max_deg, "tilt_{min,max}_deg");
  range(o.shift_min_m, o.shift_max_m, "shift_{min,max}_m");
  range(o.p_C_B_min_m, o.p_C_B_max_m, "p_C_B_{min,max}_m");
  range(o.hang_tilt_min_deg, o.hang_tilt_max_deg, "hang_tilt_{min,max}_deg");
  non_negative(o.drift_force_n, "drift_force_n");
  non_negative(o.drift_torque_nm, "drift_torque_nm");
  positive(o.foot_drop_m, "foot_drop_m");
  non_negative(o.foot_rx_m, "foot_rx_m");
  non_negative(o.foot_rz_m, "foot_rz_m");
  positive(o.foot_flatten, "foot_flatten");
  positive(o.foot_stiffness_vertical_n_m, "foot_stiffness_vertical_n_m");
  positive(o.foot_stiffness_horizontal_n_m, "foot_stiffness_horizontal_n_m");
  non_negative(o.internal_force_n, "internal_force_n");
  positive(o.hang_cycle_s, "hang_cycle_s");
  Require(o.hang_cycles > 0,
          "TwinOptions.hang_cycles must be > 0, got " + std::to_string(o.hang_cycles));
  non_negative(o.stance_angle_deg, "stance_angle_deg");
  positive(o.pose_move_s, "pose_move_s");
  positive(o.pose_dwell_s, "pose_dwell_s");
  positive(o.settle_tau_s, "settle_tau_s");
  non_negative(o.settle_freq_hz, "settle_freq_hz");
  non_negative(o.settle_height_m, "settle_height_m");
  non_negative(o.settle_tilt_deg, "settle_tilt_deg");
  non_negative(o.settle_cutoff_s, "settle_cutoff_s");
  non_negative(o.lift_spread_rad, "lift_spread_rad");
  positive(o.walk_clock_hz, "walk_clock_hz");
  Require(std::isfinite(o.walk_turn_deg_per_cycle),
          "TwinOptions.walk_turn_deg_per_cycle must be finite");
  Require(o.walk_duty > 0.5 && o.walk_duty < 1.0,
          "TwinOptions.walk_duty must be in (0.5, 1) so a tripod always stands, got " +
              std::to_string(o.walk_duty));
  Require(o.walk_sweep_deg > 0.0 && o.walk_sweep_deg < 360.0,
          "TwinOptions.walk_sweep_deg must be in (0, 360)");
}

// Smooth servo motion between two goals: s in [0, 1] -> [0, 1] with zero end velocities.
double Blend(double s) { return 0.5 * (1.0 - std::cos(M_PI * std::clamp(s, 0.0, 1.0))); }

int32_t ToCounts(double value, double counts_per_unit) {
  const double c = std::round(value * counts_per_unit);
  constexpr double kMax = std::numeric_limits<int32_t>::max();
  return static_cast<int32_t>(std::clamp(c, -kMax, kMax));
}

// J_k = [I, -[a]]: the displacement of foot point a under a small chassis motion [dp; dw].
Eigen::Matrix<double, 3, 6> FootJacobian(const Vec3& a) {
  Eigen::Matrix<double, 3, 6> J;
  J << Mat3::Identity(), -Skew(a);
  return J;
}

template <typename T>
double Median(std::vector<T>* v) {
  const size_t mid = v->size() / 2;
  std::nth_element(v->begin(), v->begin() + mid, v->end());
  double m = (*v)[mid];
  if (v->size() % 2 == 0) {
    m = 0.5 * (m + *std::max_element(v->begin(), v->begin() + mid));
  }
  return m;
}

}  // namespace

// Per-scenario device emulation: noise, quantization, mocap markers with dropouts. Holds its
// own random stream and reuses one frame, so emitting a frame allocates nothing.
class BigAntTwin::Generator {
 public:
  Generator(const BigAntTwin& twin, const RunOptions& run, const FrameSink& sink, uint64_t tag)
      : twin_(twin), run_(run), sink_(sink), rng_(MixSeed(twin.options_.seed, tag)) {
    Require(std::isfinite(run.t0_s), "RunOptions.t0_s must be finite");
    Require(!std::isnan(run.drift_from_s), "RunOptions.drift_from_s must not be NaN");
    Require(static_cast<bool>(sink), "a frame sink is required");
    const TwinOptions& o = twin.options_;
    for (int m = 0; m < kNumChassisMarkers; ++m) {
      drop_start_[m] = NextDropout(run.t0_s);
      drop_end_[m] = drop_start_[m] + rng_.Exponential(1.0 / o.marker_dropout_mean_s);
    }
  }

  Random& Rng() { return rng_; }
  double Dt() const { return 1.0 / twin_.options_.sample_rate_hz; }

  void Emit(double t_s, ExperimentPhase phase, int segment, bool steady,
            const std::array<double, kNumLegs>& angle_rad, const StanceState& state,
            const Vec3& p_GC_m, double yaw_rad) {
    const TwinOptions& o = twin_.options_;
    TwinFrame& f = frame_;
    f.t_s = t_s;
    f.phase = phase;
    f.segment = segment;
    f.steady = steady;
    f.drifted = t_s >= run_.drift_from_s;
    const RobotCalibration& cal = f.drifted ? twin_.drifted_ : twin_.truth_;
    f.angle_rad = angle_rad;
    f.R_WC = state.R_WC;
    f.in_contact = state.contact;
    f.ground_w_C = state.ground_w_C;
    f.com_shift_C = state.com_shift_C;
    for (int k = 0; k < kNumLegs; ++k) {
      Vec6 w = TransducerReading(cal, k, state.ground_w_C[k], angle_rad[k], state.R_WC);
      f.offset_change[k] = run_.offset_change ? run_.offset_change(k, t_s) : Vec6::Zero();
      w += f.offset_change[k];
      for (int i = 0; i < 6; ++i) {
        const bool force = i < 3;
        w[i] += (force ? o.force_noise_n : o.torque_noise_nm) * rng_.Normal();
        const double cpu = force ? o.counts_per_force : o.counts_per_torque;
        f.counts[k][i] = ToCounts(w[i], cpu);
        if (o.quantize) w[i] = f.counts[k][i] / cpu;
      }
      f.reading[k] = w;
    }
    // Motion capture: the chassis body's pose and markers in the global frame G.
    const Mat3 R_GC = Eigen::AngleAxisd(yaw_rad, Vec3::UnitZ()).toRotationMatrix() * state.R_WC;
    const Vec3 attitude_noise(rng_.Normal(), rng_.Normal(), rng_.Normal());
    f.R_GC = R_GC * ExpSO3(o.attitude_noise_deg * kDeg * attitude_noise);
    const Vec3& p_C_B = twin_.truth_.p_C_B;
    f.p_GB_m = p_GC_m + R_GC * p_C_B;
    for (int m = 0; m < kNumChassisMarkers; ++m) {
      while (t_s >= drop_end_[m]) {
        drop_start_[m] = NextDropout(drop_end_[m]);
        drop_end_[m] = drop_start_[m] + rng_.Exponential(1.0 / o.marker_dropout_mean_s);
      }
      const Vec3 noise(rng_.Normal(), rng_.Normal(), rng_.Normal());
      f.marker_tracked[m] = t_s < drop_start_[m];
      f.marker_G_m[m] =
          f.marker_tracked[m]
              ? Vec3(p_GC_m + R_GC * (twin_.markers_B_[m] + p_C_B) + o.marker_noise_m * noise)
              : Vec3::Constant(std::numeric_limits<double>::quiet_NaN());
    }
    sink_(f);
  }

 private:
  double NextDropout(double after_s) {
    const double rate = twin_.options_.marker_dropout_rate_hz;
    return rate > 0.0 ? after_s + rng_.Exponential(rate) : std::numeric_limits<double>::infinity();
  }

  const BigAntTwin& twin_;
  const RunOptions& run_;
  const FrameSink& sink_;
  Random rng_;
  TwinFrame frame_;
  std::array<double, kNumChassisMarkers> drop_start_{};
  std::array<double, kNumChassisMarkers> drop_end_{};
};

namespace {

// A damped oscillation of the chassis after a change of pose or support: the small extra
// displacement osc = [dp; dw] squeezes the springs (the sum of ground forces then balances
// the chassis' acceleration, not gravity alone) and tilts the chassis.
void ApplySettling(const Vec6& osc, double kh, double kz, StanceState* st) {
  if (osc.isZero(0.0)) return;
  const Vec3 K(kh, kh, kz);
  const Mat3 R_new = ExpSO3(osc.tail<3>()) * st->R_WC;
  for (int k = 0; k < kNumLegs; ++k) {
    if (!st->contact[k]) continue;
    const Vec3 a_W = st->R_WC * st->foot_C[k];
    st->force_W[k] -= K.asDiagonal() * (FootJacobian(a_W) * osc);
    const Vec3 f_C = R_new.transpose() * st->force_W[k];
    st->ground_w_C[k] << f_C, st->foot_C[k].cross(f_C);
  }
  st->R_WC = R_new;
}

}  // namespace

BigAntTwin::BigAntTwin(const config::Config& config, const TwinOptions& options)
    : options_(options) {
  ValidateOptions(options_);
  const config::Robot& robot = config.robot();
  Require(config.has_robot(), "config: robot is missing");
  Require(robot.total_mass_kg() > 0.0 && std::isfinite(robot.total_mass_kg()),
          "config: robot.total_mass_kg must be > 0");
  Require(robot.chassis_marker_count() == kNumChassisMarkers,
          "config: robot.chassis_marker_count must be " + std::to_string(kNumChassisMarkers) +
              " for the twin, got " + std::to_string(robot.chassis_marker_count()));
  robot_name_ = robot.name();

  RobotCalibration& cal = truth_;
  cal.X_B_ft = NominalTransducerPoses(robot);
  cal.g0 = robot.g0_m_s2();
  cal.total_mass_kg = robot.total_mass_kg();

  // The stated hanging axes: the reference (first) leg's transducer axis, in B.
  for (int s = 0; s < kNumHangSeries; ++s) (void)StatedGravityB(static_cast<HangSeries>(s));

  Random rng(MixSeed(options_.seed, kTagTruth));
  const TwinOptions& o = options_;
  cal.p_C_B = rng.UnitVector() * rng.Uniform(o.p_C_B_min_m, o.p_C_B_max_m);
  for (int k = 0; k < kNumLegs; ++k) {
    LegCalibration& leg = cal.leg[k];
    for (int i = 0; i < 3; ++i) {
      leg.offset[i] = kTableForceOffsetN[k][i] + rng.Uniform(-1.0, 1.0) * o.offset_force_spread_n;
      leg.offset[3 + i] =
          kTableTorqueOffsetNm[k][i] + rng.Uniform(-1.0, 1.0) * o.offset_torque_spread_nm;
    }
    leg.weight_n = kTableWeightN[k] + rng.Uniform(-1.0, 1.0) * o.weight_spread_n;
    // Leg CoM in the module frame ft_k (report Fig. 4/7): below the transducer, a little
    // outboard (+y of the module on both sides), x and z sinusoidal in phase with 1-2 cm
    // amplitude, following the foot (x ~ -sin, z ~ -cos) with a few tenths of a radian of lag.
    leg.com.x.a = rng.Uniform(0.01, 0.02);
    leg.com.x.c = M_PI + rng.Uniform(-0.3, 0.3);
    leg.com.x.d = rng.Uniform(-0.01, 0.01);
    leg.com.y = 0.02 + rng.Uniform(-0.005, 0.005);
    leg.com.z.a = rng.Uniform(0.01, 0.02);
    leg.com.z.c = -0.5 * M_PI + rng.Uniform(-0.3, 0.3);
    leg.com.z.d = -0.05 + rng.Uniform(-0.005, 0.005);
    // Mounting error: tilt about the transducer's own origin plus a shift d; T~ acts about the
    // body origin, so p~ = d + (I - R~) p^B_ft (docs/method.md).
    const Vec3 tilt_axis = rng.UnitVector();
    const double tilt = rng.Uniform(o.tilt_min_deg, o.tilt_max_deg) * kDeg;
    const Vec3 shift = rng.UnitVector() * rng.Uniform(o.shift_min_m, o.shift_max_m);
    Vec3 p_tilde = Vec3::Zero();
    if (o.mounting_errors) {
      leg.R_tilde = ExpSO3(tilt * tilt_axis);
      p_tilde = shift + (Mat3::Identity() - leg.R_tilde) * cal.X_B_ft[k].p;
    }
    leg.p_tilde_prime = leg.R_tilde.transpose() * (p_tilde + cal.p_C_B);
  }
  drifted_ = truth_;
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 3; ++i) {
      drifted_.leg[k].offset[i] += rng.Uniform(-1.0, 1.0) * o.drift_force_n;
      drifted_.leg[k].offset[3 + i] += rng.Uniform(-1.0, 1.0) * o.drift_torque_nm;
    }
  }
  // Each hanging series: the stated axis tilted by 1-3 deg about an axis across it.
  for (int s = 0; s < kNumHangSeries; ++s) {
    const Vec3 g_b = StatedGravityB(static_cast<HangSeries>(s));
    Vec3 axis = rng.UnitVector();
    axis = (axis - g_b * g_b.dot(axis));
    if (axis.norm() < 1e-6) axis = g_b.unitOrthogonal();
    axis.normalize();
    const double tilt = rng.Uniform(o.hang_tilt_min_deg, o.hang_tilt_max_deg) * kDeg;
    const Vec3 u_C = ExpSO3(tilt * axis) * g_b;  // actual gravity direction in C
    // g^C = R_WC^T (0, 0, -g0) = g0 u_C  <=>  R_CW e_z = -u_C.
    const Mat3 R_CW = Quat::FromTwoVectors(Vec3::UnitZ(), -u_C).toRotationMatrix();
    hang_R_WC_[s] = R_CW.transpose();
  }
  yaw0_rad_ = rng.Uniform(-M_PI, M_PI);
  origin_G_m_ = Vec3(rng.Uniform(-1.0, 1.0), rng.Uniform(-1.0, 1.0), 0.0);

  // Twelve chassis markers on the top plate and on short posts, asymmetric so the body is
  // unambiguous.
  markers_B_ = {Vec3(0.25, 0.14, 0.03),   Vec3(0.25, -0.14, 0.03), Vec3(-0.25, 0.14, 0.03),
                Vec3(-0.25, -0.14, 0.03), Vec3(0.0, 0.14, 0.03),   Vec3(0.0, -0.14, 0.03),
                Vec3(0.25, 0.0, 0.03),    Vec3(-0.25, 0.0, 0.03),  Vec3(0.10, 0.05, 0.08),
                Vec3(-0.12, 0.06, 0.07),  Vec3(0.05, -0.07, 0.09), Vec3(-0.08, -0.04, 0.06)};

  Random order_rng(MixSeed(options_.seed, kTagPoseOrder));
  std::iota(pose_order_.begin(), pose_order_.end(), 0);
  std::shuffle(pose_order_.begin(), pose_order_.end(), order_rng.Engine());
}

calibration::Calibration BigAntTwin::TruthProto(bool drifted) const {
  calibration::Calibration proto;
  FillCalibrationValues(drifted ? drifted_ : truth_, &proto);
  proto.set_robot_name(robot_name_);
  proto.set_g0_m_s2(truth_.g0);
  proto.set_total_mass_kg(truth_.total_mass_kg);
  proto.set_model(options_.mounting_errors ? calibration::FULL : calibration::ONE_TRANSLATION);
  proto.set_hanging_uncertainty(calibration::TRUTH);
  proto.set_standing_uncertainty(calibration::TRUTH);
  std::ostringstream what;
  what << "BigAntTwin truth: seed=" << options_.seed << " physical_com=" << options_.physical_com
       << " mounting_errors=" << options_.mounting_errors << (drifted ? " offsets=drifted" : "");
  proto.mutable_provenance()->set_software_version("ftcal-twin");
  proto.mutable_provenance()->set_command_line(what.str());
  return proto;
}

void BigAntTwin::WriteTruthFile(const std::string& path, bool drifted) const {
  WriteCalibrationFile(TruthProto(drifted), path);
}

Vec3 BigAntTwin::StatedGravityB(HangSeries series) const {
  const int s = static_cast<int>(series);
  Require(s >= 0 && s < kNumHangSeries, "unknown hanging series " + std::to_string(s));
  const Vec3 e_ft = (series == HangSeries::kXPos)   ? Vec3::UnitX()
                    : (series == HangSeries::kXNeg) ? Vec3(-Vec3::UnitX())
                    : (series == HangSeries::kZPos) ? Vec3::UnitZ()
                                                    : Vec3(-Vec3::UnitZ());
  const Vec3 v = truth_.X_B_ft[0].R * e_ft;
  int axis = 0;
  v.cwiseAbs().maxCoeff(&axis);
  // The operator can only hang the robot along a body axis: the reference leg's transducer
  // axes must be body axes (within 10 deg).
  Require(std::abs(v[axis]) > std::cos(10.0 * kDeg),
          "config: robot.leg[0].x_b_ft: the transducer axes must lie along body axes for hanging");
  Vec3 g_b = Vec3::Zero();
  g_b[axis] = v[axis] > 0 ? 1.0 : -1.0;
  return g_b;
}

Vec3 BigAntTwin::FootC(int k, double angle_rad) const {
  const TwinOptions& o = options_;
  const double c = std::cos(angle_rad);
  const double bottom = (c >= 0 ? 1.0 : -1.0) * std::pow(std::abs(c), o.foot_flatten);
  const Vec3 foot_ft(-o.foot_rx_m * std::sin(angle_rad), 0.0,
                     -o.foot_drop_m - o.foot_rz_m * bottom);
  return truth_.X_C_ft(k) * foot_ft;
}

std::array<double, kNumLegs> BigAntTwin::StandingPoseAngles(int index) const {
  Require(index >= 0 && index < static_cast<int>(pose_order_.size()),
          "standing pose index " + std::to_string(index) + " outside [0, 729)");
  int code = pose_order_[index];
  std::array<double, kNumLegs> angle{};
  for (int k = 0; k < kNumLegs; ++k) {
    angle[k] = (code % 3 - 1) * options_.stance_angle_deg * kDeg;
    code /= 3;
  }
  return angle;
}

// Quasi-static equilibrium on compliant feet.
// Model: the ground pushes foot k with f_k = K (s_k - J_k delta), s_k the springs' compression
//   at the undisplaced chassis, delta = [dp; dw] the chassis' small displacement, J_k = [I,
//   -[a_k]].
// Residual: sum_k J_k^T f_k - target = 0 (J_k^T f = [f; a x f], the wrench about C in W).
// Unknowns: delta (6). Null spaces: none with three non-collinear feet (H = sum J^T K J > 0);
//   the vertical offset of the floor is absorbed in dz, the heading in the W convention.
// Two solves: the first finds the tilt; the second, at the tilted attitude with the actual lever
//   arms, makes the sum exact (its correction is second order). Self-balancing forces are then
//   added in the null space of the map f -> sum J^T f.
StanceState BigAntTwin::Equilibrium(const std::array<double, kNumLegs>& angle_rad,
                                    const std::array<bool, kNumLegs>& contact,
                                    const std::array<Vec3, kNumLegs>& internal_h) const {
  const TwinOptions& o = options_;
  StanceState st;
  st.contact = contact;
  int num_contacts = 0;
  double z_mean = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    st.foot_C[k] = FootC(k, angle_rad[k]);
    st.force_W[k].setZero();
    st.ground_w_C[k].setZero();
    if (contact[k]) {
      ++num_contacts;
      z_mean += st.foot_C[k].z();
    }
  }
  Require(num_contacts >= 3, "equilibrium needs at least three feet on the ground, got " +
                                 std::to_string(num_contacts));
  z_mean /= num_contacts;
  st.com_shift_C = o.physical_com ? ComShiftC(truth_, angle_rad) : Vec3::Zero();
  const double weight = truth_.TotalWeightN();
  auto target = [&](const Mat3& R_WC) {
    const Vec3 up(0.0, 0.0, weight);
    Vec6 t;
    t << up, (R_WC * st.com_shift_C).cross(up);
    return t;
  };
  const Vec3 K(o.foot_stiffness_horizontal_n_m, o.foot_stiffness_horizontal_n_m,
               o.foot_stiffness_vertical_n_m);

  // Pass 1: level chassis.
  Mat6 H = Mat6::Zero();
  Vec6 rhs = -target(Mat3::Identity());
  std::array<Vec3, kNumLegs> f1;
  for (int k = 0; k < kNumLegs; ++k) {
    if (!contact[k]) continue;
    const Eigen::Matrix<double, 3, 6> J = FootJacobian(st.foot_C[k]);
    const Vec3 s(0.0, 0.0, z_mean - st.foot_C[k].z());
    H += J.transpose() * K.asDiagonal() * J;
    rhs += J.transpose() * (K.asDiagonal() * s);
  }
  Eigen::LDLT<Mat6> ldlt(H);
  Require(ldlt.info() == Eigen::Success && ldlt.isPositive() && ldlt.rcond() > 1e-12,
          "the feet on the ground cannot carry the robot (collinear support)");
  const Vec6 delta = ldlt.solve(rhs);
  for (int k = 0; k < kNumLegs; ++k) {
    if (!contact[k]) continue;
    const Vec3 s(0.0, 0.0, z_mean - st.foot_C[k].z());
    f1[k] = K.asDiagonal() * (s - FootJacobian(st.foot_C[k]) * delta);
  }
  st.R_WC = RemoveHeading(ExpSO3(delta.tail<3>()));

  // Pass 2: tilted chassis, exact lever arms.
  Mat6 H2 = Mat6::Zero();
  Mat6 N = Mat6::Zero();  // A A^T for the null-space projection
  Vec6 r2 = -target(st.R_WC);
  Vec6 y = Vec6::Zero();
  std::array<Eigen::Matrix<double, 3, 6>, kNumLegs> J2;
  for (int k = 0; k < kNumLegs; ++k) {
    if (!contact[k]) continue;
    J2[k] = FootJacobian(st.R_WC * st.foot_C[k]);
    H2 += J2[k].transpose() * K.asDiagonal() * J2[k];
    N += J2[k].transpose() * J2[k];
    r2 += J2[k].transpose() * f1[k];
    y += J2[k].transpose() * Vec3(internal_h[k].x(), internal_h[k].y(), 0.0);
  }
  const Vec6 delta2 = H2.ldlt().solve(r2);
  const Vec6 lambda = N.ldlt().solve(y);
  double height = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    if (!contact[k]) continue;
    const Vec3 u(internal_h[k].x(), internal_h[k].y(), 0.0);
    st.force_W[k] = f1[k] - K.asDiagonal() * (J2[k] * delta2) + (u - J2[k] * lambda);
    const Vec3 f_C = st.R_WC.transpose() * st.force_W[k];
    st.ground_w_C[k] << f_C, st.foot_C[k].cross(f_C);
    // Foot k sinks f_z / kz into the floor: C is that far above the floor less its own z.
    height += -st.force_W[k].z() / K.z() - (st.R_WC * st.foot_C[k]).z();
  }
  st.height_m = height / num_contacts;
  st.target_W = target(st.R_WC);
  return st;
}

StanceState BigAntTwin::HangingState(HangSeries series,
                                     const std::array<double, kNumLegs>& angle_rad) const {
  const int s = static_cast<int>(series);
  Require(s >= 0 && s < kNumHangSeries, "unknown hanging series " + std::to_string(s));
  StanceState st = LiftedState(angle_rad);
  st.R_WC = hang_R_WC_[s];
  return st;
}

StanceState BigAntTwin::LiftedState(const std::array<double, kNumLegs>& angle_rad) const {
  StanceState st;
  st.R_WC = Mat3::Identity();
  st.contact.fill(false);
  for (int k = 0; k < kNumLegs; ++k) {
    st.ground_w_C[k].setZero();
    st.foot_C[k] = FootC(k, angle_rad[k]);
    st.force_W[k].setZero();
  }
  if (options_.physical_com) st.com_shift_C = ComShiftC(truth_, angle_rad);
  return st;
}

Vec3 BigAntTwin::HangingPositionG() const { return origin_G_m_ + Vec3(0.0, 0.0, 1.2); }

double BigAntTwin::Hanging(HangSeries series, const RunOptions& run, const FrameSink& sink) const {
  const int s = static_cast<int>(series);
  Require(s >= 0 && s < kNumHangSeries, "unknown hanging series " + std::to_string(s));
  Generator gen(*this, run, sink, kTagHanging + s);
  const TwinOptions& o = options_;
  const long n = std::lround(o.hang_cycles * o.hang_cycle_s * o.sample_rate_hz);
  const ExperimentPhase phase =
      static_cast<ExperimentPhase>(static_cast<int>(ExperimentPhase::kHangXPos) + s);
  std::array<double, kNumLegs> angle{};
  for (long i = 0; i < n; ++i) {
    const double tau = i * gen.Dt();
    angle.fill(2.0 * M_PI * tau / o.hang_cycle_s);
    gen.Emit(run.t0_s + tau, phase, s, true, angle, HangingState(series, angle), HangingPositionG(),
             yaw0_rad_);
  }
  return run.t0_s + n * gen.Dt();
}

double BigAntTwin::Tare(const RunOptions& run, const FrameSink& sink) const {
  // The naive tare as an operator records it: the robot hangs upright and level (no ground
  // contact), every shaft at 0, for tare_s.
  Generator gen(*this, run, sink, kTagTare);
  const long n = std::lround(options_.tare_s * options_.sample_rate_hz);
  const std::array<double, kNumLegs> angle{};
  const StanceState st = LiftedState(angle);
  for (long i = 0; i < n; ++i) {
    gen.Emit(run.t0_s + i * gen.Dt(), ExperimentPhase::kTare, 0, true, angle, st,
             HangingPositionG(), yaw0_rad_);
  }
  return run.t0_s + n * gen.Dt();
}

namespace {

// Random self-balancing horizontal forces (before projection) for a new contact epoch.
std::array<Vec3, kNumLegs> DrawInternal(Random* rng, double rms_n) {
  std::array<Vec3, kNumLegs> h;
  for (Vec3& v : h) v = Vec3(rms_n * rng->Normal(), rms_n * rng->Normal(), 0.0);
  return h;
}

Vec6 DrawSettling(Random* rng, const TwinOptions& o) {
  Vec6 a = Vec6::Zero();
  a[2] = o.settle_height_m * rng->Normal();
  a[3] = o.settle_tilt_deg * kDeg * rng->Normal();
  a[4] = o.settle_tilt_deg * kDeg * rng->Normal();
  return a;
}

// Settling displacement tau_s after a change: zero at the change, exactly zero after the cutoff.
Vec6 Settling(const Vec6& amplitude, double tau_s, const TwinOptions& o) {
  if (tau_s < 0.0 || tau_s >= o.settle_cutoff_s) return Vec6::Zero();
  return amplitude * std::exp(-tau_s / o.settle_tau_s) *
         std::sin(2.0 * M_PI * o.settle_freq_hz * tau_s);
}

}  // namespace

double BigAntTwin::Standing(int num_poses, const RunOptions& run, const FrameSink& sink) const {
  Require(num_poses >= 1 && num_poses <= 729,
          "Standing: num_poses must be in [1, 729], got " + std::to_string(num_poses));
  Generator gen(*this, run, sink, kTagStanding);
  const TwinOptions& o = options_;
  const double dt = gen.Dt();
  const long n_move = std::lround(o.pose_move_s * o.sample_rate_hz);
  const long n_dwell = std::lround(o.pose_dwell_s * o.sample_rate_hz);
  std::array<bool, kNumLegs> all;
  all.fill(true);
  std::array<double, kNumLegs> prev{};
  double t = run.t0_s;
  for (int p = 0; p < num_poses; ++p) {
    const std::array<double, kNumLegs> next = StandingPoseAngles(p);
    const std::array<Vec3, kNumLegs> internal = DrawInternal(&gen.Rng(), o.internal_force_n);
    const Vec6 settle = DrawSettling(&gen.Rng(), o);
    for (long i = 0; i < n_move; ++i, t += dt) {
      std::array<double, kNumLegs> angle;
      const double b = Blend(static_cast<double>(i) / n_move);
      for (int k = 0; k < kNumLegs; ++k) angle[k] = prev[k] + (next[k] - prev[k]) * b;
      const StanceState st = Equilibrium(angle, all, internal);
      gen.Emit(t, ExperimentPhase::kStanding, p, false, angle, st,
               origin_G_m_ + Vec3(0.0, 0.0, st.height_m), yaw0_rad_);
    }
    const StanceState rest = Equilibrium(next, all, internal);
    for (long i = 0; i < n_dwell; ++i, t += dt) {
      StanceState st = rest;
      const double since = i * dt;
      ApplySettling(Settling(settle, since, o), o.foot_stiffness_horizontal_n_m,
                    o.foot_stiffness_vertical_n_m, &st);
      gen.Emit(t, ExperimentPhase::kStanding, p, since >= o.settle_cutoff_s, next, st,
               origin_G_m_ + Vec3(0.0, 0.0, st.height_m), yaw0_rad_);
    }
    prev = next;
  }
  return t;
}

double BigAntTwin::TripodStances(int num_stances, const RunOptions& run,
                                 const FrameSink& sink) const {
  Require(num_stances >= 1,
          "TripodStances: num_stances must be >= 1, got " + std::to_string(num_stances));
  Generator gen(*this, run, sink, kTagTripod);
  const TwinOptions& o = options_;
  const double dt = gen.Dt();
  const double a = o.stance_angle_deg * kDeg;
  const long n_move = std::lround(o.pose_move_s * o.sample_rate_hz);
  const long n_land = std::lround(1.0 * o.sample_rate_hz);
  const long n_dwell = std::lround(o.pose_dwell_s * o.sample_rate_hz);
  std::array<double, kNumLegs> angle{};
  std::array<bool, kNumLegs> contact;
  contact.fill(true);
  double t = run.t0_s;
  // Moves the legs in `moving` from `from` to `to` over n frames, then holds for n_hold frames,
  // with the settling oscillation from the end of the motion.
  auto segment = [&](int stance, const std::array<bool, kNumLegs>& moving,
                     const std::array<double, kNumLegs>& to, long n, long n_hold,
                     const std::array<bool, kNumLegs>& contact_moving,
                     const std::array<bool, kNumLegs>& contact_hold) {
    const std::array<double, kNumLegs> from = angle;
    std::array<Vec3, kNumLegs> internal = DrawInternal(&gen.Rng(), o.internal_force_n);
    for (long i = 0; i < n; ++i, t += dt) {
      const double b = Blend(static_cast<double>(i) / n);
      for (int k = 0; k < kNumLegs; ++k)
        angle[k] = moving[k] ? from[k] + (to[k] - from[k]) * b : from[k];
      const StanceState st = Equilibrium(angle, contact_moving, internal);
      gen.Emit(t, ExperimentPhase::kTripod, stance, false, angle, st,
               origin_G_m_ + Vec3(0.0, 0.0, st.height_m), yaw0_rad_);
    }
    for (int k = 0; k < kNumLegs; ++k) angle[k] = moving[k] ? to[k] : from[k];
    if (contact_hold != contact_moving) internal = DrawInternal(&gen.Rng(), o.internal_force_n);
    const StanceState rest = Equilibrium(angle, contact_hold, internal);
    const Vec6 settle = DrawSettling(&gen.Rng(), o);
    for (long i = 0; i < n_hold; ++i, t += dt) {
      StanceState st = rest;
      const double since = i * dt;
      ApplySettling(Settling(settle, since, o), o.foot_stiffness_horizontal_n_m,
                    o.foot_stiffness_vertical_n_m, &st);
      gen.Emit(t, ExperimentPhase::kTripod, stance, since >= o.settle_cutoff_s, angle, st,
               origin_G_m_ + Vec3(0.0, 0.0, st.height_m), yaw0_rad_);
    }
    contact = contact_hold;
  };
  for (int i = 0; i < num_stances; ++i) {
    const int lifted = i % 2;
    std::array<double, kNumLegs> to = angle;
    std::array<bool, kNumLegs> support, all, landing, lifting;
    all.fill(true);
    for (int k = 0; k < kNumLegs; ++k) {
      support[k] = kTripod[k] != lifted;
      // Support legs take a stance angle; the legs of the tripod lifted last time land there.
      if (support[k]) to[k] = (static_cast<int>(gen.Rng().Uniform(0.0, 3.0)) - 1) * a;
      landing[k] = support[k];
      lifting[k] = !support[k];
    }
    // 1. Support legs go to their stance angles (the ones in the air land at the end), then all
    //    six stand for a second.
    std::array<bool, kNumLegs> during = contact;
    segment(i, landing, to, n_move, n_land, during, all);
    // 2. The other tripod lifts (off the ground as soon as it starts to move) and the robot
    //    stands on three feet.
    for (int k = 0; k < kNumLegs; ++k) {
      if (lifting[k]) to[k] = M_PI + gen.Rng().Uniform(-1.0, 1.0) * o.lift_spread_rad;
    }
    segment(i, lifting, to, n_move, n_dwell, support, support);
  }
  return t;
}

double BigAntTwin::TripodWalk(double duration_s, const RunOptions& run,
                              const FrameSink& sink) const {
  Require(std::isfinite(duration_s) && duration_s > 0.0,
          "TripodWalk: duration_s must be > 0, got " + std::to_string(duration_s));
  Generator gen(*this, run, sink, kTagWalk);
  const TwinOptions& o = options_;
  const double dt = gen.Dt();
  const double sweep = o.walk_sweep_deg * kDeg;
  const double d = o.walk_duty;
  // Buehler clock: slow stance through [-sweep/2, sweep/2], fast swing over the rest of the turn.
  auto buehler = [&](double clock) {
    const double cycle = std::floor(clock);
    const double psi = clock - cycle;
    const double in_cycle = psi < d ? -0.5 * sweep + sweep * psi / d
                                    : 0.5 * sweep + (2.0 * M_PI - sweep) * (psi - d) / (1.0 - d);
    return 2.0 * M_PI * cycle + in_cycle;
  };
  const long n = std::lround(duration_s * o.sample_rate_hz);
  const double stride_m = 2.0 * o.foot_rx_m * std::sin(0.5 * sweep);
  const double speed_m_s = stride_m / (d / o.walk_clock_hz);  // body moves while a tripod stands
  Vec3 p = origin_G_m_;
  std::array<bool, kNumLegs> last_contact{};
  std::array<Vec3, kNumLegs> internal{};
  std::array<double, kNumLegs> angle{};
  std::array<bool, kNumLegs> contact{};
  for (long i = 0; i < n; ++i) {
    const double tau = i * dt;
    const double clock = o.walk_clock_hz * tau;
    for (int k = 0; k < kNumLegs; ++k) {
      const double leg_clock = clock + 0.5 * kTripod[k];
      const double psi = leg_clock - std::floor(leg_clock);
      // In stance the foot must move backward in B: d(foot_B.x)/dtheta = -rx R_B_ft(0, 0) at
      // theta = 0, so a module turned about z (the right side in the config) turns the other way.
      const bool right = truth_.X_B_ft[k].R(0, 0) < 0.0;
      angle[k] = (right ? -1.0 : 1.0) * buehler(leg_clock);
      contact[k] = psi < d;
    }
    if (i == 0 || contact != last_contact) internal = DrawInternal(&gen.Rng(), o.internal_force_n);
    last_contact = contact;
    const StanceState st = Equilibrium(angle, contact, internal);
    const double yaw = yaw0_rad_ + o.walk_turn_deg_per_cycle * kDeg * clock;
    p += speed_m_s * dt * Vec3(std::cos(yaw), std::sin(yaw), 0.0);
    gen.Emit(run.t0_s + tau, ExperimentPhase::kWalking, static_cast<int>(std::floor(clock)), true,
             angle, st, Vec3(p.x(), p.y(), st.height_m), yaw);
  }
  return run.t0_s + n * dt;
}

BigAntTwin::Driven::Driven(const BigAntTwin& twin, const RunOptions& run)
    : twin_(twin), run_(run), sink_([this](const TwinFrame& f) { frame_ = f; }) {
  // The forces come from their own stream, so that they are the same whatever the noise
  // options (a noise-free twin gives the expected readings of a noisy one).
  Random rng(MixSeed(twin.options_.seed, kTagDrivenInternal));
  internal_ = DrawInternal(&rng, twin.options_.internal_force_n);
  gen_ = std::make_unique<Generator>(twin_, run_, sink_, kTagDriven);
}

BigAntTwin::Driven::~Driven() = default;

const TwinFrame& BigAntTwin::Driven::Frame(double t_s,
                                           const std::array<double, kNumLegs>& angle_rad) {
  Require(std::isfinite(t_s), "Driven::Frame: time must be finite");
  for (int k = 0; k < kNumLegs; ++k) {
    Require(std::isfinite(angle_rad[k]),
            "Driven::Frame: shaft angle of leg " + std::to_string(k) + " is not finite");
  }
  const bool steady = first_ || angle_rad == last_angle_;
  first_ = false;
  last_angle_ = angle_rad;
  switch (support_) {
    case Support::kHanging: {
      const int s = static_cast<int>(series_);
      gen_->Emit(t_s,
                 static_cast<ExperimentPhase>(static_cast<int>(ExperimentPhase::kHangXPos) + s), s,
                 steady, angle_rad, twin_.HangingState(series_, angle_rad),
                 twin_.HangingPositionG(), twin_.yaw0_rad_);
      break;
    }
    case Support::kLifted:
      gen_->Emit(t_s, ExperimentPhase::kTare, 0, steady, angle_rad, twin_.LiftedState(angle_rad),
                 twin_.HangingPositionG(), twin_.yaw0_rad_);
      break;
    case Support::kStanding: {
      std::array<bool, kNumLegs> all;
      all.fill(true);
      const StanceState st = twin_.Equilibrium(angle_rad, all, internal_);
      gen_->Emit(t_s, ExperimentPhase::kStanding, -1, steady, angle_rad, st,
                 twin_.origin_G_m_ + Vec3(0.0, 0.0, st.height_m), twin_.yaw0_rad_);
      break;
    }
  }
  return frame_;
}

void BigAntTwin::Driven::SetSupport(Support support, HangSeries series) {
  const int s = static_cast<int>(series);
  Require(s >= 0 && s < kNumHangSeries, "unknown hanging series " + std::to_string(s));
  support_ = support;
  series_ = series;
}

HangingRecording BigAntTwin::MakeHangingRecording(HangSeries series) const {
  HangingRecording rec;
  rec.series = series;
  rec.gravity_b = StatedGravityB(series);
  Hanging(series, RunOptions{}, [&rec](const TwinFrame& f) {
    for (int k = 0; k < kNumLegs; ++k) {
      rec.legs[k].t_s.push_back(f.t_s);
      rec.legs[k].angle_rad.push_back(f.angle_rad[k]);
      rec.legs[k].wrench.push_back(f.reading[k]);
    }
    rec.attitude.push_back(f.R_GC);
  });
  return rec;
}

namespace {

// Medians of the steady frames of one segment, as the pose segmenter reports them.
struct SteadyAccumulator {
  std::array<std::vector<double>, kNumLegs * 6> wrench;
  std::array<std::vector<double>, kNumLegs> angle;
  std::array<std::vector<double>, 9> attitude;
  std::vector<double> t;
  std::vector<SyncSample> samples;  // for the within-pose scatter
  std::array<bool, kNumLegs> contact{};
  bool markers_ok = true;

  void Add(const TwinFrame& f) {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 6; ++i) wrench[k * 6 + i].push_back(f.reading[k][i]);
      angle[k].push_back(f.angle_rad[k]);
    }
    const Mat3 R_WC = RemoveHeading(f.R_GC);
    for (int i = 0; i < 9; ++i) attitude[i].push_back(R_WC(i / 3, i % 3));
    t.push_back(f.t_s);
    SyncSample sample;
    sample.wrench = f.reading;
    sample.angle_rad = f.angle_rad;
    sample.R_WC = R_WC;
    samples.push_back(sample);
    contact = f.in_contact;
    for (bool tracked : f.marker_tracked) markers_ok = markers_ok && tracked;
  }
  bool Empty() const { return t.empty(); }
  void Clear() { *this = SteadyAccumulator(); }
  void Fill(std::array<Vec6, kNumLegs>* w, std::array<double, kNumLegs>* a, Mat3* R) {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 6; ++i) (*w)[k][i] = Median(&wrench[k * 6 + i]);
      (*a)[k] = Median(&angle[k]);
    }
    Mat3 m;
    for (int i = 0; i < 9; ++i) m(i / 3, i % 3) = Median(&attitude[i]);
    *R = ProjectToSO3(m);
  }
};

}  // namespace

std::vector<StandingPose> BigAntTwin::MakeSteadyPoses(int num_poses) const {
  std::vector<StandingPose> poses;
  SteadyAccumulator acc;
  int current = -1;
  auto flush = [&]() {
    if (!acc.Empty() && acc.markers_ok) {
      StandingPose pose;
      pose.t_s = Median(&acc.t);
      acc.Fill(&pose.wrench, &pose.angle_rad, &pose.R_WC);
      SetWithinPoseScatter(acc.samples, &pose);
      poses.push_back(pose);
    }
    acc.Clear();
  };
  Standing(num_poses, RunOptions{}, [&](const TwinFrame& f) {
    if (f.segment != current) {
      flush();
      current = f.segment;
    }
    if (f.steady) acc.Add(f);
  });
  flush();
  return poses;
}

std::vector<LoadSample> BigAntTwin::MakeTripodLoadSamples(int num_stances, bool drifted) const {
  std::vector<LoadSample> samples;
  SteadyAccumulator acc;
  int current = -1;
  auto flush = [&]() {
    if (!acc.Empty() && acc.markers_ok) {
      LoadSample s;
      acc.Fill(&s.wrench, &s.angle_rad, &s.R_WC);
      for (int k = 0; k < kNumLegs; ++k) s.unloaded[k] = !acc.contact[k];
      samples.push_back(s);
    }
    acc.Clear();
  };
  RunOptions run;
  if (drifted) run.drift_from_s = -std::numeric_limits<double>::infinity();
  TripodStances(num_stances, run, [&](const TwinFrame& f) {
    if (f.segment != current) {
      flush();
      current = f.segment;
    }
    if (f.steady) acc.Add(f);
  });
  flush();
  return samples;
}

}  // namespace ftcal
