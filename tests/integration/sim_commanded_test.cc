// ftcal-sim live --scenario commanded with the real ATI and Dynamixel bridges and lcm-logger, as
// real processes over UDP, a pseudo-terminal and LCM multicast inside a private network
// namespace (ctest runs this binary through scripts/netns-exec). The test publishes SERVO_CMD
// (signed: arm, then torque on and two poses in turn, with heartbeats) and checks the loop the twin
// closes:
//   - SERVO_STATE: each servo leaves its start only after the command, approaches the goal as a
//     first-order response (log-linear fit of the remaining error against the servos' own
//     Realtime Tick: the time constant given to ftcal-sim, a third of the way left one time
//     constant after the start) and sits within one encoder count of the goal after ten;
//   - FT_<LEG>: the mean of each transducer's wrenches once settled is the twin's noise-free
//     reading at those shaft angles (BigAntTwin::Driven, rebuilt here from the same config and
//     seed) within a few standard errors of the noise, and the second pose changes the loads
//     by far more than the noise.
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <regex>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "test_helpers.h"
#include "signed_commander.h"
#include "ftcal/config.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/servo_command_t.hpp"
#include "ftcal/signed_envelope_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "protocol2.h"
#include "sim/live.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::Decode;
using testing::Terminate;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
constexpr char kLoggerUrl[] = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=8388608";
constexpr double kOneCountRad = 2.0 * M_PI / 4096.0;
constexpr std::uint64_t kSeed = 11;
constexpr int kAtiRateHz = 500;
constexpr double kTauS = 0.5;   // --servo-tau
constexpr double kHoldS = 6.5;  // per pose: ten time constants, then the averaging window
constexpr double kSettledS = 10 * kTauS;
constexpr double kForceSigmaN = 0.05, kTorqueSigmaNm = 0.002;  // TwinOptions' defaults
constexpr double kTwinRateHz = 100.0;  // a new twin frame (a new noise draw) every 10 ms

// Goals (rad, legs HL ML FL HR MR FR): the start is every shaft at 0.
constexpr std::array<double, kNumLegs> kPoseA = {0.5, -0.3, 0.4, -0.5, 0.3, -0.4};
constexpr std::array<double, kNumLegs> kPoseB = {-0.4, 0.5, -0.3, 0.4, -0.5, 0.2};

using testing::SleepS;

// The sim config with the Dynamixel device at `device` and the reply timeout longer than the
// config's 10 ms, so that a loaded test machine does not turn a reply into a late one.
std::string TestConfigText(const std::string& device) {
  std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  text = std::regex_replace(text, std::regex("device: \"[^\"]*\""), "device: \"" + device + "\"");
  // A goal is a step, as the first-order fit below assumes: no velocity limit to speak of.
  text = std::regex_replace(text, std::regex("reply_timeout_s: [0-9.]+"),
                            "reply_timeout_s: 0.05\n  max_velocity_rad_s: 1000");
  return text;
}

// The recorded log, decoded; times are the logger's (s).
struct Recorded {
  // One FT record. A message carries a datagram's records: its last one has the message's
  // logged time, an earlier one that much before it as its sample time is before the last's.
  struct Ft {
    double t_s;
    int leg;
    Vec6 w;
  };
  struct Servo {
    double t_s;
    servo_state_t m;
  };
  struct Command {
    double t_s;
    servo_command_t m;
  };
  std::vector<Ft> ft;
  std::vector<Servo> servo;
  std::vector<Command> cmd;
  int undecodable = 0;
};
Recorded ReadLog(const std::string& path) {
  Recorded r;
  testing::ForEachLogEvent(path, [&r](const lcm::LogEvent* e) {
    const std::string& ch = e->channel;
    const double t = static_cast<double>(e->timestamp) * 1e-6;
    if (ch.rfind("FT_", 0) == 0) {
      ft_batch_t m;
      if (!Decode(e, &m) || m.n < 1) {
        ++r.undecodable;
        return;
      }
      const auto k = LegIndex(m.leg);
      if (!k) {
        ++r.undecodable;
        return;
      }
      for (int j = 0; j < m.n; ++j) {
        Vec6 w;
        for (int i = 0; i < 6; ++i) w[i] = m.wrench[j][i];
        const double before_last =
            static_cast<double>(m.sample_utime[m.n - 1] - m.sample_utime[j]) * 1e-6;
        r.ft.push_back({t - before_last, *k, w});
      }
    } else if (ch == "SERVO_STATE") {
      servo_state_t m;
      if (!Decode(e, &m))
        ++r.undecodable;
      else
        r.servo.push_back({t, m});
    } else if (ch == "SERVO_CMD") {  // signed envelopes; the goals are in the MOVEs
      signed_envelope_t envelope;
      servo_command_t m;
      if (!Decode(e, &envelope) ||
          m.decode(envelope.payload.data(), 0, envelope.size) != envelope.size) {
        ++r.undecodable;
      } else if (m.action == servo_command_t::MOVE) {
        r.cmd.push_back({t, m});
      }
    }
  });
  return r;
}

// The warnings and errors a process logged (spdlog's "[warning]" and "[error]" lines).
std::string WarningsAndErrors(const std::string& err_path) {
  std::istringstream in(testing::ReadFile(err_path));
  std::string out, line;
  while (std::getline(in, line)) {
    if (line.find("] [warning] ") != std::string::npos ||
        line.find("] [error] ") != std::string::npos) {
      out += line + "\n";
    }
  }
  return out;
}

// One servo's fresh samples: logger time, Realtime Tick (s) and angle.
struct ServoSample {
  double t_s, tick_s, angle;
  bool torque_off;
};

TEST(SimCommanded, LegsFollowTheServosAndTheLoadsFollowTheLegs) {
  testing::AheadOfTheMachine();
  ASSERT_TRUE(testing::InNetns());
  ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) not found at configure time";
  const auto test_started = Clock::now();
  const std::string dir = testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  const std::string link = path("tty");
  const std::string config_path = path("config.pbtxt");
  testing::SignedCommander commander(kUrl);
  ASSERT_TRUE(commander.good());
  std::ofstream(config_path) << commander.Trusted(TestConfigText(link));
  const config::Config config = LoadConfigFile(config_path);
  std::array<int, kNumLegs> id{}, zero{}, direction{};
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& s = config.robot().leg(k).servo();
    id[k] = static_cast<int>(s.id());
    zero[k] = s.zero_count();
    direction[k] = s.direction();
  }
  // A goal as the servo holds it: the bridge rounds it to a whole count.
  auto held = [&](double goal, int k) {
    return direction[k] * (dxl::RadToPosition(goal, zero[k], direction[k]) - zero[k]) *
           kOneCountRad;
  };

  Child sim({FTCAL_SIM, "live", "--config", config_path, "--pty-link", link, "--truth-dir", dir,
             "--ready", path("ready"), "--scenario", "commanded", "--seed", std::to_string(kSeed),
             "--ati-rate", std::to_string(kAtiRateHz), "--servo-tau", std::to_string(kTauS)},
            path("sim.out"), path("sim.err"));
  const auto deadline = Clock::now() + std::chrono::seconds(30);
  while (::access(path("ready").c_str(), F_OK) != 0) {
    ASSERT_FALSE(sim.Wait(0.02).has_value())
        << "ftcal-sim ended: " << testing::ReadFile(path("sim.err"));
    ASSERT_LT(Clock::now(), deadline)
        << "ftcal-sim not ready: " << testing::ReadFile(path("sim.err"));
  }
  Child logger({FTCAL_LCM_LOGGER, "--lcm-url", kLoggerUrl, "-f", path("run.lcmlog")},
               path("logger.out"), path("logger.err"));
  SleepS(0.3);
  // A long silence timeout: a loaded machine must not make the bridge restart the stream.
  Child ati(
      {FTCAL_ATI_BRIDGE, "--config", config_path, "--lcm-url", kUrl, "--silence-timeout", "1.0"},
      path("ati.out"), path("ati.err"));
  Child dxl({FTCAL_DYNAMIXEL_BRIDGE, "--config", config_path, "--lcm-url", kUrl}, path("dxl.out"),
            path("dxl.err"));
  // A machine too loaded for the loop shows in the bridge's log first (replies late, servos
  // lost, commands refused): on any failure, that log tells the loop's fault from the
  // machine's.
  struct ExplainFailure {
    std::string err_path;
    ~ExplainFailure() {
      if (!::testing::Test::HasFailure()) return;
      const std::string logged = WarningsAndErrors(err_path);
      std::cout << "ftcal-dynamixel-bridge's warnings and errors:\n"
                << (logged.empty() ? "(none)\n" : logged);
    }
  } explain{path("dxl.err")};
  SleepS(2.5);  // the bridges start; the last second of it is the start pose's window

  std::vector<int> ids(id.begin(), id.end());
  auto command = [&](const std::array<double, kNumLegs>& goal) {
    ASSERT_EQ(commander.Move(ids, std::vector<double>(goal.begin(), goal.end())), 0);
  };
  ASSERT_EQ(commander.Arm(), 0);
  commander.StartHeartbeat(0.05);  // the bridge's dead-man
  SleepS(0.05);
  command(kPoseA);
  SleepS(kHoldS);
  command(kPoseB);
  SleepS(kHoldS);
  commander.StopHeartbeat();
  sim.Signal(SIGTERM);
  SleepS(0.3);
  Terminate(ati, "ftcal-ati-bridge", path("ati.err"));
  Terminate(dxl, "ftcal-dynamixel-bridge", path("dxl.err"));
  Terminate(sim, "ftcal-sim live", path("sim.err"));
  SleepS(0.3);
  logger.Signal(SIGINT);
  ASSERT_TRUE(logger.Wait(10).has_value());
  std::cout << testing::ReadFile(path("sim.out"));

  const Recorded rec = ReadLog(path("run.lcmlog"));
  EXPECT_EQ(rec.undecodable, 0);
  ASSERT_EQ(rec.cmd.size(), 2u) << "the logger did not hear both commands";
  const double t_a = rec.cmd[0].t_s, t_b = rec.cmd[1].t_s;

  // Each servo's fresh samples in time order.
  std::array<std::vector<ServoSample>, kNumLegs> servo;
  // Per servo, logger time - its Realtime Tick (the smallest is the least latency): each servo
  // keeps its own clock, booted at its own moment (the twin's lab clocks, as real servos).
  std::array<double, kNumLegs> tick_offset;
  tick_offset.fill(INFINITY);
  for (const auto& s : rec.servo) {
    for (int j = 0; j < 6; ++j) {
      if (s.m.flags[j] & servo_state_t::FLAG_STALE) continue;
      const auto k = LegIndex(s.m.leg[j]);
      ASSERT_TRUE(k.has_value()) << s.m.leg[j];
      const double tick_s = static_cast<double>(s.m.device_tick_ms[j]) * 1e-3;
      servo[*k].push_back(
          {s.t_s, tick_s, s.m.angle_rad[j], (s.m.flags[j] & servo_state_t::FLAG_TORQUE_OFF) != 0});
      tick_offset[*k] = std::min(tick_offset[*k], s.t_s - tick_s);
    }
  }

  // ---- SERVO_STATE: at rest, the steps, settled ----
  struct Window {
    const char* name;
    double from_s, to_s;
    std::array<double, kNumLegs> goal;
    bool torque_on;
  };
  const std::array<double, kNumLegs> start{};
  const Window windows[] = {{"start", t_a - 1.2, t_a - 0.05, start, false},
                            {"pose A", t_a + kSettledS, t_b - 0.05, kPoseA, true},
                            {"pose B", t_b + kSettledS, t_b + kHoldS - 0.05, kPoseB, true}};
  double worst_settled_counts = 0;
  for (const Window& w : windows) {
    SCOPED_TRACE(w.name);
    for (int k = 0; k < kNumLegs; ++k) {
      // One verdict per leg and window, on its worst sample: a servo that left its goal does so
      // for many samples, and each would repeat the same failure.
      int n = 0, off_goal = 0, wrong_torque = 0;
      double worst = 0, worst_at = 0;
      for (const ServoSample& s : servo[k]) {
        if (s.t_s < w.from_s || s.t_s > w.to_s) continue;
        ++n;
        const double counts = std::abs(s.angle - w.goal[k]) / kOneCountRad;
        off_goal += counts > 1.0;
        wrong_torque += s.torque_off == w.torque_on;
        if (counts > worst) worst = counts, worst_at = s.t_s - t_a;
      }
      EXPECT_LE(worst, 1.0) << kLegNames[k] << ": " << off_goal << " of " << n
                            << " samples off the goal, the worst at " << worst_at
                            << " s after the first command";
      EXPECT_EQ(wrong_torque, 0) << kLegNames[k] << ": torque " << (w.torque_on ? "off" : "on")
                                 << " in " << wrong_torque << " of " << n << " samples";
      worst_settled_counts = std::max(worst_settled_counts, worst);
      // SERVO_STATE at 100 Hz; at least half of it fresh and heard.
      EXPECT_GT(n, 50 * (w.to_s - w.from_s)) << kLegNames[k];
    }
  }
  std::cout << "servos: worst |angle - goal| once settled " << worst_settled_counts << " counts\n";

  struct Step {
    const char* name;
    double t_cmd;
    std::array<double, kNumLegs> from, to;
  };
  const Step steps[] = {{"start -> A", t_a, start, kPoseA}, {"A -> B", t_b, kPoseA, kPoseB}};
  for (const Step& st : steps) {
    SCOPED_TRACE(st.name);
    double tau_lo = INFINITY, tau_hi = 0, worst_fit = 0, frac_lo = INFINITY, frac_hi = 0;
    double start_lo = INFINITY, start_hi = -INFINITY;
    for (int k = 0; k < kNumLegs; ++k) {
      const double cmd_tick = st.t_cmd - tick_offset[k];  // the command on this servo's clock
      const double from = held(st.from[k], k), to = held(st.to[k], k), step = to - from;
      ASSERT_GT(std::abs(step), 100 * kOneCountRad);
      // Log-linear least squares of the remaining fraction, between 90 % and 10 % of the step.
      std::vector<const ServoSample*> used;
      double sx = 0, sy = 0, sxx = 0, sxy = 0;
      for (const ServoSample& s : servo[k]) {
        if (s.t_s < st.t_cmd - 0.5 || s.t_s > st.t_cmd + kSettledS) continue;
        const double left = (to - s.angle) / step;
        if (left > 0.9 || left < 0.1) continue;
        const double x = s.tick_s - cmd_tick, y = std::log(left);
        used.push_back(&s);
        sx += x, sy += y, sxx += x * x, sxy += x * y;
      }
      const double n = static_cast<double>(used.size());
      ASSERT_GE(n, 0.5 * 100 * kTauS * std::log(9.0))
          << kLegNames[k] << ": too few samples on the way";
      const double slope = (n * sxy - sx * sy) / (n * sxx - sx * sx);
      const double intercept = (sy - slope * sx) / n;
      const double tau = -1.0 / slope;
      const double t0 = -intercept / slope;  // where the fit leaves the start, after the command
      double fit = 0;
      for (const ServoSample* s : used) {
        fit = std::max(fit, std::abs(std::log((to - s->angle) / step) -
                                     (intercept + slope * (s->tick_s - cmd_tick))));
      }
      EXPECT_NEAR(tau, kTauS, 0.05 * kTauS) << kLegNames[k];
      EXPECT_LT(fit, 0.1) << kLegNames[k] << ": not a first-order response";
      // The motion starts once the bridge has written the goal: its next cycle at 100 Hz, a
      // little later on a loaded machine; never before the command.
      EXPECT_GT(t0, -0.01) << kLegNames[k];
      EXPECT_LT(t0, 0.1) << kLegNames[k];
      // Before it, the servo is where it was; one time constant after it, a third of the step
      // is left (exp(-1)), read off the samples on either side.
      const ServoSample* before = nullptr;
      const ServoSample* after = nullptr;
      for (const ServoSample& s : servo[k]) {
        if (s.t_s < st.t_cmd - 0.5 || s.t_s > st.t_cmd + kSettledS) continue;
        const double x = s.tick_s - cmd_tick;
        if (x < t0 - 0.005) {
          EXPECT_LE(std::abs(s.angle - from), kOneCountRad)
              << kLegNames[k] << " moved before the command";
        }
        if (x <= t0 + kTauS) before = &s;
        if (x > t0 + kTauS && after == nullptr) after = &s;
      }
      ASSERT_TRUE(before != nullptr && after != nullptr) << kLegNames[k];
      const double xb = before->tick_s - cmd_tick, xa = after->tick_s - cmd_tick;
      ASSERT_LT(xa - xb, 0.1) << kLegNames[k] << ": no samples around one time constant";
      const double left_b = (to - before->angle) / step, left_a = (to - after->angle) / step;
      const double left = left_b + (left_a - left_b) * (t0 + kTauS - xb) / (xa - xb);
      EXPECT_NEAR(left, std::exp(-1.0), 0.03) << kLegNames[k];
      tau_lo = std::min(tau_lo, tau), tau_hi = std::max(tau_hi, tau);
      worst_fit = std::max(worst_fit, fit);
      frac_lo = std::min(frac_lo, left), frac_hi = std::max(frac_hi, left);
      start_lo = std::min(start_lo, t0), start_hi = std::max(start_hi, t0);
    }
    std::cout << "servos " << st.name << ": fitted time constant " << tau_lo << " .. " << tau_hi
              << " s (given " << kTauS << "), worst |ln residual| " << worst_fit << ", start "
              << start_lo * 1e3 << " .. " << start_hi * 1e3
              << " ms after the command, left after one time constant " << frac_lo << " .. "
              << frac_hi << " (exp(-1) = " << std::exp(-1.0) << ")\n";
  }

  // ---- FT_<LEG>: the twin's readings at the settled angles ----
  TwinOptions quiet;
  quiet.seed = kSeed;
  quiet.force_noise_n = 0.0;
  quiet.torque_noise_nm = 0.0;
  const BigAntTwin twin(config, quiet);
  std::array<std::array<Vec6, kNumLegs>, 3> measured{}, expected{};
  for (std::size_t i = 0; i < std::size(windows); ++i) {
    const Window& w = windows[i];
    SCOPED_TRACE(w.name);
    std::array<double, kNumLegs> angle;
    for (int k = 0; k < kNumLegs; ++k) angle[k] = held(w.goal[k], k);
    BigAntTwin::Driven driven(twin);
    const TwinFrame& f = driven.Frame(0.0, angle);
    std::array<int, kNumLegs> n{};
    std::array<Vec6, kNumLegs> sum{};
    for (auto& s : sum) s.setZero();
    for (const auto& s : rec.ft) {
      if (s.t_s < w.from_s || s.t_s > w.to_s) continue;
      sum[s.leg] += s.w;
      ++n[s.leg];
    }
    const double duration = w.to_s - w.from_s;
    // Each twin frame draws its own noise; the transducers repeat a frame until the next.
    const double frames = kTwinRateHz * duration;
    double worst_force = 0, worst_torque = 0;
    for (int k = 0; k < kNumLegs; ++k) {
      ASSERT_GT(n[k], 0.7 * kAtiRateHz * duration) << kLegNames[k];
      measured[i][k] = sum[k] / n[k];
      expected[i][k] = f.reading[k];
      for (int j = 0; j < 6; ++j) {
        const double se = (j < 3 ? kForceSigmaN : kTorqueSigmaNm) / std::sqrt(frames);
        const double miss = std::abs(measured[i][k][j] - expected[i][k][j]);
        EXPECT_LT(miss, 5.0 * se + 1e-5) << kLegNames[k] << " axis " << j << ": measured "
                                         << measured[i][k][j] << ", twin " << expected[i][k][j];
        (j < 3 ? worst_force : worst_torque) =
            std::max(j < 3 ? worst_force : worst_torque, miss / se);
      }
    }
    std::cout << "wrenches " << w.name << ": " << n[0] << ".. samples per transducer over "
              << duration << " s, worst |mean - twin| " << worst_force << " (force) / "
              << worst_torque << " (torque) standard errors (force se "
              << kForceSigmaN / std::sqrt(frames) << " N, torque se "
              << kTorqueSigmaNm / std::sqrt(frames) << " N*m)\n";
  }
  // A new pose moves the load between the feet by far more than the noise.
  for (std::size_t i = 1; i < std::size(windows); ++i) {
    double largest = 0, largest_expected = 0, worst_change_miss = 0;
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 change = measured[i][k] - measured[i - 1][k];
      const Vec6 change_expected = expected[i][k] - expected[i - 1][k];
      largest = std::max(largest, change.head<3>().norm());
      largest_expected = std::max(largest_expected, change_expected.head<3>().norm());
      worst_change_miss = std::max(worst_change_miss, (change - change_expected).head<3>().norm());
    }
    EXPECT_GT(largest, 20 * kForceSigmaN) << windows[i - 1].name << " -> " << windows[i].name;
    std::cout << "wrenches " << windows[i - 1].name << " -> " << windows[i].name
              << ": largest force change " << largest << " N (twin " << largest_expected
              << " N, one sample's noise " << kForceSigmaN << " N), worst |change - twin's| "
              << worst_change_miss << " N\n";
  }
  std::cout << "test ran " << std::chrono::duration<double>(Clock::now() - test_started).count()
            << " s\n";

  if (!HasFailure()) {
    testing::RemoveTree(dir);
  } else {
    std::cerr << "logs kept in " << dir << "\n";
  }
}

}  // namespace
}  // namespace ftcal
