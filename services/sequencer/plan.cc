#include "sequencer/plan.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "ftcal/config.h"
#include "ftcal/latency.h"
#include "ftcal/experiment_marker_t.hpp"

namespace ftcal::sequencer {
namespace {

constexpr double kDeg = M_PI / 180.0;
// A smooth move s(u) = (1 - cos(pi u)) / 2 peaks at pi/2 times the mean speed.
constexpr double kBlendPeakFactor = M_PI / 2.0;
// Shortest move the planner schedules: the servos' own profile needs a few cycles.
constexpr double kMinMoveS = 0.3;
// Tripod stances: both tripods stand this long before one lifts.
constexpr double kAllSixS = 1.0;

std::string Num(double v) {
  std::ostringstream s;
  s.precision(6);
  s << v;
  return s.str();
}

double Blend(double u) { return 0.5 * (1.0 - std::cos(M_PI * std::clamp(u, 0.0, 1.0))); }

// Buehler clock (the report's gait, as the twin walks it): slow stance through
// [-sweep/2, sweep/2] for the first `duty` of each cycle, fast swing over the rest of the turn.
double Buehler(double clock, double duty, double sweep) {
  const double cycle = std::floor(clock);
  const double psi = clock - cycle;
  const double in_cycle = psi < duty
                              ? -0.5 * sweep + sweep * psi / duty
                              : 0.5 * sweep + (2.0 * M_PI - sweep) * (psi - duty) / (1.0 - duty);
  return 2.0 * M_PI * cycle + in_cycle;
}

class Builder {
 public:
  Builder(const config::Config& config, const config::ExperimentPlan& plan)
      : plan_(plan), seq_(config.sequencer()) {
    const auto& legs = config.robot().leg();
    for (int k = 0; k < kNumLegs; ++k) {
      const config::Servo& s = legs[k].servo();
      lo_[k] = s.min_angle_rad() + seq_.joint_limit_margin_rad();
      hi_[k] = s.max_angle_rad() - seq_.joint_limit_margin_rad();
      // A module turned about z (the right side) moves its foot the other way for the same
      // shaft angle: the gait turns it the other way so that every stance pushes backward.
      right_[k] = NominalTransducerPoses(config.robot())[k].R(0, 0) < 0.0;
    }
    x_b_ft0_ = NominalTransducerPoses(config.robot())[0].R;
    schedule_.plan_name = plan.name();
  }

  Schedule Build() {
    for (int i = 0; i < plan_.phase_size(); ++i) AddPhase(i, plan_.phase(i));
    // Back to the neutral pose at the end, outside every marker.
    Angles zero{};
    Move(plan_.phase_size() - 1, 0, zero);
    for (const Step& s : schedule_.steps) schedule_.duration_s += s.duration_s;
    return std::move(schedule_);
  }

 private:
  [[noreturn]] void Fail(int phase, const std::string& what) const {
    throw std::invalid_argument("plan '" + plan_.name() + "' phase " + std::to_string(phase) +
                                " (" + schedule_.phase_names[phase] + "): " + what);
  }

  void CheckLimits(int phase, const Angles& a) const {
    for (int k = 0; k < kNumLegs; ++k) {
      if (a[k] < lo_[k] || a[k] > hi_[k]) {
        Fail(phase, "leg " + std::string(kLegNames[k]) + " goal " + Num(a[k]) +
                        " rad is outside its limits [" + Num(lo_[k]) + ", " + Num(hi_[k]) +
                        "] rad (robot.leg[" + std::to_string(k) +
                        "].servo min/max_angle_rad minus sequencer.joint_limit_margin_rad)");
      }
    }
  }

  void Push(Step s) { schedule_.steps.push_back(std::move(s)); }

  Step Base(int phase, int8_t marker, StepKind kind) const {
    Step s;
    s.kind = kind;
    s.phase = phase;
    s.marker = marker;
    s.from = s.to = current_;
    return s;
  }

  // A smooth move to `to`, timed so that no shaft's peak speed exceeds the limit.
  void Move(int phase, int8_t marker, const Angles& to, int unit = -1, bool resume = false) {
    CheckLimits(phase, to);
    if (to == current_ && !resume) return;
    Step s = Base(phase, marker, StepKind::kMove);
    s.to = to;
    s.duration_s = MoveDurationS(current_, to, seq_.max_velocity_rad_s());
    s.unit = unit;
    s.resume_point = resume;
    Push(s);
    current_ = to;
  }

  void Hold(int phase, int8_t marker, double duration_s, int unit = -1) {
    Step s = Base(phase, marker, StepKind::kHold);
    s.duration_s = duration_s;
    s.unit = unit;
    Push(s);
  }

  void Open(int phase, int8_t marker, bool confirm, const std::string& prompt, Precheck check,
            const Angles& start) {
    if (confirm) {
      Step c = Base(phase, marker, StepKind::kConfirm);
      c.prompt = prompt;
      Push(c);
    }
    Step p = Base(phase, marker, StepKind::kPrecheck);
    p.precheck = check;
    Push(p);
    Move(phase, marker, start);
    Push(Base(phase, marker, StepKind::kMarkerStart));
  }

  void Close(int phase, int8_t marker) { Push(Base(phase, marker, StepKind::kMarkerStop)); }

  std::array<double, 3> StatedGravityB(config::HangOrientation o) const {
    Vec3 e = (o == config::HANG_X_POS)   ? Vec3::UnitX()
             : (o == config::HANG_X_NEG) ? Vec3(-Vec3::UnitX())
             : (o == config::HANG_Z_POS) ? Vec3::UnitZ()
                                         : Vec3(-Vec3::UnitZ());
    const Vec3 v = x_b_ft0_ * e;
    int axis = 0;
    v.cwiseAbs().maxCoeff(&axis);
    std::array<double, 3> g{0.0, 0.0, 0.0};
    g[axis] = v[axis] > 0 ? 1.0 : -1.0;
    return g;
  }

  void AddPhase(int i, const config::PlanPhase& p) {
    const int8_t marker = MarkerOf(p);
    schedule_.phase_names.push_back(config::PlanPhaseKind_Name(p.kind()) +
                                    (p.kind() == config::PHASE_HANG
                                         ? " " + config::HangOrientation_Name(p.orientation())
                                         : std::string()));
    schedule_.phase_gravity_b.push_back({0.0, 0.0, 0.0});
    schedule_.phase_marker.push_back(marker);
    const Angles zero{};
    switch (p.kind()) {
      case config::PHASE_TARE: {
        Open(i, marker, p.has_confirm() ? p.confirm() : true,
             "Tare: lift the robot upright with every foot in the air, then confirm.",
             Precheck::kAirborne, zero);
        Step h = Base(i, marker, StepKind::kHold);
        h.duration_s = p.tare_s();
        h.resume_point = true;
        Push(h);
        Close(i, marker);
        break;
      }
      case config::PHASE_HANG: {
        schedule_.phase_gravity_b[i] = StatedGravityB(p.orientation());
        const auto& g = schedule_.phase_gravity_b[i];
        Open(i, marker, p.has_confirm() ? p.confirm() : true,
             "Hang the robot with gravity along body axis (" + Num(g[0]) + ", " + Num(g[1]) + ", " +
                 Num(g[2]) + ") (" + config::HangOrientation_Name(p.orientation()) +
                 " of the transducers), then confirm.",
             Precheck::kAirborne, zero);
        // The sweep's speed varies (HangSweepAngle, docs/method.md "Latencies"): its peak
        // is what the servos must reach.
        const double rate = HangSweepPeakRate(p.cycle_s());
        if (rate > seq_.max_velocity_rad_s()) {
          Fail(i, "cycle_s " + Num(p.cycle_s()) + " s turns the shafts at up to " + Num(rate) +
                      " rad/s, above sequencer.max_velocity_rad_s " +
                      Num(seq_.max_velocity_rad_s()));
        }
        Step t = Base(i, marker, StepKind::kTurn);
        t.cycle_s = p.cycle_s();
        t.direction.fill(1.0);
        t.duration_s = p.cycles() * p.cycle_s();
        t.resume_point = true;
        for (int k = 0; k < kNumLegs; ++k) t.to[k] = current_[k] + 2.0 * M_PI * p.cycles();
        CheckLimits(i, t.to);
        Push(t);
        current_ = t.to;
        Close(i, marker);
        // Unwind to straight down outside the marker (the servos count whole turns).
        Move(i, 0, zero);
        break;
      }
      case config::PHASE_STANDING_GRID: {
        std::vector<double> grid;
        for (double d : p.grid_angles_deg()) grid.push_back(d * kDeg);
        if (grid.empty()) grid = {-36.0 * kDeg, 0.0, 36.0 * kDeg};
        const std::vector<Angles> all = GrayGrid(grid);
        std::vector<Angles> poses;
        for (size_t j = 0; j < all.size(); j += p.pose_stride()) poses.push_back(all[j]);
        Open(i, marker, p.has_confirm() && p.confirm(),
             "Set the robot down on its feet, upright, then confirm.", Precheck::kStanding,
             poses.front());
        for (size_t j = 0; j < poses.size(); ++j) {
          Move(i, marker, poses[j], static_cast<int>(j), /*resume=*/true);
          Hold(i, marker, p.dwell_s(), static_cast<int>(j));
        }
        Close(i, marker);
        break;
      }
      case config::PHASE_TRIPOD_STANCES: {
        Open(i, marker, p.has_confirm() && p.confirm(),
             "Set the robot down on its feet, upright, then confirm.", Precheck::kStanding, zero);
        const double lift = p.lift_angle_deg() * kDeg;
        for (uint32_t j = 0; j < p.stances(); ++j) {
          const int lifted = static_cast<int>(j % 2);
          // Every leg down (the tripod lifted last lands) and all six stand a moment...
          Move(i, marker, zero, static_cast<int>(j), /*resume=*/true);
          Hold(i, marker, kAllSixS, static_cast<int>(j));
          // ... then one tripod lifts and the robot stands on the other.
          Angles up = zero;
          for (int k = 0; k < kNumLegs; ++k) {
            if (kTripodOf[k] == lifted) up[k] = lift;
          }
          Move(i, marker, up, static_cast<int>(j));
          Hold(i, marker, p.dwell_s(), static_cast<int>(j));
        }
        Move(i, marker, zero);
        Close(i, marker);
        break;
      }
      case config::PHASE_TRIPOD_WALK: {
        Step w = Base(i, marker, StepKind::kWalk);
        w.clock_hz = p.clock_hz();
        w.duty = p.duty();
        w.duration_s = p.walk_s();
        w.resume_point = true;
        Angles start{};
        double fastest = 0.0;
        for (int k = 0; k < kNumLegs; ++k) {
          const double delta = (right_[k] ? -0.5 : 0.5) * p.turn_sweep_delta_deg();
          w.sweep_rad[k] = (p.sweep_deg() + delta) * kDeg;
          w.direction[k] = right_[k] ? -1.0 : 1.0;
          if (!(w.sweep_rad[k] > 0.0 && w.sweep_rad[k] < 2.0 * M_PI)) {
            Fail(i, "leg " + std::string(kLegNames[k]) + " sweep " + Num(w.sweep_rad[k] / kDeg) +
                        " deg is outside (0, 360)");
          }
          const double swing = (2.0 * M_PI - w.sweep_rad[k]) * w.clock_hz / (1.0 - w.duty);
          const double stance = w.sweep_rad[k] * w.clock_hz / w.duty;
          fastest = std::max({fastest, swing, stance});
        }
        if (fastest > seq_.max_velocity_rad_s()) {
          Fail(i, "the gait turns a shaft at " + Num(fastest) +
                      " rad/s, above sequencer.max_velocity_rad_s " +
                      Num(seq_.max_velocity_rad_s()));
        }
        start = GoalAt(w, 0.0);
        Open(i, marker, p.has_confirm() && p.confirm(),
             "Set the robot down on its feet with room to walk, then confirm.", Precheck::kStanding,
             start);
        w.from = start;
        w.to = GoalAt(w, w.duration_s);
        CheckLimits(i, w.to);
        Push(w);
        current_ = w.to;
        Close(i, marker);
        // Unwind outside the marker.
        Move(i, 0, zero);
        break;
      }
      default:
        Fail(i, "unknown phase kind " + std::to_string(p.kind()));
    }
  }

  const config::ExperimentPlan& plan_;
  const config::Sequencer& seq_;
  Angles lo_{}, hi_{};
  std::array<bool, kNumLegs> right_{};
  Mat3 x_b_ft0_ = Mat3::Identity();
  Angles current_{};
  Schedule schedule_;
};

}  // namespace

int8_t MarkerOf(const config::PlanPhase& phase) {
  switch (phase.kind()) {
    case config::PHASE_TARE:
      return experiment_marker_t::TARE;
    case config::PHASE_HANG:
      switch (phase.orientation()) {
        case config::HANG_X_POS:
          return experiment_marker_t::HANG_X_POS;
        case config::HANG_X_NEG:
          return experiment_marker_t::HANG_X_NEG;
        case config::HANG_Z_POS:
          return experiment_marker_t::HANG_Z_POS;
        case config::HANG_Z_NEG:
          return experiment_marker_t::HANG_Z_NEG;
        default:
          return experiment_marker_t::IDLE;
      }
    case config::PHASE_STANDING_GRID:
      return experiment_marker_t::STANDING;
    case config::PHASE_TRIPOD_STANCES:
      return experiment_marker_t::TRIPOD;
    case config::PHASE_TRIPOD_WALK:
      return experiment_marker_t::WALKING;
    default:
      return experiment_marker_t::IDLE;
  }
}

std::vector<Angles> GrayGrid(const std::vector<double>& angles_rad) {
  const int n = static_cast<int>(angles_rad.size());
  if (n < 1) throw std::invalid_argument("GrayGrid: no angles");
  int total = 1;
  for (int k = 0; k < kNumLegs; ++k) total *= n;
  std::vector<Angles> poses;
  poses.reserve(total);
  // Reflected n-ary Gray code: digit k runs up and down in turn, reversing each time the
  // digits above it step, so exactly one digit changes by one between neighbours.
  for (int i = 0; i < total; ++i) {
    Angles a{};
    int rest = i;
    int above = 0;  // the number formed by the digits above k, which sets k's direction
    int div = total;
    for (int k = 0; k < kNumLegs; ++k) {
      div /= n;
      const int raw = rest / div;
      rest %= div;
      const int digit = (above % 2 == 0) ? raw : n - 1 - raw;
      a[k] = angles_rad[digit];
      above = above * n + raw;
    }
    poses.push_back(a);
  }
  return poses;
}

double MoveDurationS(const Angles& from, const Angles& to, double max_velocity_rad_s) {
  double longest = 0.0;
  for (int k = 0; k < kNumLegs; ++k) longest = std::max(longest, std::abs(to[k] - from[k]));
  return std::max(kMinMoveS, kBlendPeakFactor * longest / max_velocity_rad_s);
}

Angles GoalAt(const Step& step, double t) {
  const double d = step.duration_s;
  const double tc = std::clamp(t, 0.0, d);
  Angles a = step.to;
  switch (step.kind) {
    case StepKind::kMove: {
      if (tc >= d) break;  // exactly `to` at the end, not to + rounding
      const double b = Blend(tc / d);
      for (int k = 0; k < kNumLegs; ++k) a[k] = step.from[k] + (step.to[k] - step.from[k]) * b;
      break;
    }
    case StepKind::kTurn: {
      const int cycles = static_cast<int>(std::lround(d / step.cycle_s));
      const double turned = HangSweepAngle(tc, step.cycle_s, cycles);
      for (int k = 0; k < kNumLegs; ++k) a[k] = step.from[k] + step.direction[k] * turned;
      break;
    }
    case StepKind::kWalk:
      for (int k = 0; k < kNumLegs; ++k) {
        const double leg_clock = step.clock_hz * tc + 0.5 * kTripodOf[k];
        a[k] = step.direction[k] * Buehler(leg_clock, step.duty, step.sweep_rad[k]);
      }
      break;
    default:
      break;
  }
  return a;
}

Schedule Expand(const config::Config& config, const std::string& plan_name) {
  if (config.plan_size() == 0) {
    throw std::invalid_argument("the config has no experiment plan (config field `plan`)");
  }
  const config::ExperimentPlan* plan = nullptr;
  std::string names;
  for (const config::ExperimentPlan& p : config.plan()) {
    names += (names.empty() ? "" : ", ") + p.name();
    if (plan_name.empty() || p.name() == plan_name) {
      plan = &p;
      break;
    }
  }
  if (plan == nullptr) {
    throw std::invalid_argument("no experiment plan named '" + plan_name + "' (the config has " +
                                names + ")");
  }
  return Builder(config, *plan).Build();
}

}  // namespace ftcal::sequencer
