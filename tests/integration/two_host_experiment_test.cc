// Two hosts, tested here (issue 12): an experiment plan run live across two network
// namespaces, "robot" and "workstation", joined by a veth pair (LCM at ttl=1 across the link),
// the process group brought up by `ftcal-launch up` on one supervisord per host, and one
// process killed with -9 on each side in the middle of the run.
//
//   robot:       ftcal-record (SCHED_FIFO, as scripts/record runs it), the twin as the robot
//                (ftcal-sim live --scenario commanded --control FIFO), the ATI, Dynamixel and
//                mocap bridges;
//   workstation: the pose segmenter, the live calibrator, the corrector and the sequencer with
//                config/sim.pbtxt's plan "experiment" (tare, four hanging series, 46 standing
//                poses); this test, ftcal-launch and ftcal-status. The test is the operator, as
//                scripts/experiment is: at each of the sequencer's prompts it hangs, lifts or
//                sets down the twin through the twin's FIFO and sends a signed CONFIRM
//                (ftcal-sequencer-control).
//
// In the standing phase it kills the robot's recorder and the workstation's segmenter, and
// checks against what does not come from the processes it judges:
//   1. each host's supervisord spawned a new child for each (read from /proc) within
//      kRestartBoundS, and supervisorctl, ftcal-launch status, ftcal-status and the listeners'
//      PROCESS_STATE show the restart with the new pid;
//   2. the recording lost nothing outside the logger's outage: the two files of `ftcal-record -i`
//      counted by each FT_<LEG> channel's rdt_sequence (the twin's, one per record): every gap
//      lies inside the outage, between the killed logger's last event and the restarted
//      logger's first;
//   3. the live calibration, with a segmenter that had to pick the standing phase up again from
//      the sequencer's repeated start marker, recovers the twin's truth (truth.pbtxt) within the
//      bounds experiment_live_test holds the same plan to.
// The long tier runs it on the plan "experiment"; the main tier on kRestartPlan (the tare and
// the standing grid, two minutes), which checks 1 and 2 and that the restarted segmenter picked
// the phase up again, while experiment_live_test checks the live calibration of a whole plan.
// The figures are printed on lines starting with FIGURE.
#include <fcntl.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <map>
#include <optional>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "calibration_errors.h"
#include "child_process.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/process_state_t.hpp"
#include "launch_helpers.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

using namespace launch_testing;      // NOLINT: launch_helpers.h
using namespace calibration_errors;  // NOLINT: calibration_errors.h

constexpr double kAtiRateHz = 200;     // the twin's --ati-rate, as scripts/experiment runs it
constexpr int kKillAfterPoses = 10;    // STEADY_POSE heard: well inside the 46-pose standing phase
constexpr double kPlanTimeoutS = 900;  // the plan "experiment" takes about five minutes
// The main tier's plan: the tare and 31 standing poses (every 24th of the grid) of 2.5 s, about
// two minutes: the kills after kKillAfterPoses, then poses enough for the restarted segmenter to
// show that it picked the phase up again.
constexpr char kRestartPlan[] = R"(
plan {
  name: "restart"
  phase { kind: PHASE_TARE tare_s: 2 }
  phase { kind: PHASE_STANDING_GRID confirm: true pose_stride: 24 dwell_s: 2.5 }
}
)";

std::string Replaced(std::string text, const std::regex& what, const std::string& with,
                     const std::string& name) {
  EXPECT_TRUE(std::regex_search(text, what)) << "config/sim.pbtxt has no " << name;
  return std::regex_replace(text, what, with);
}

// config/sim.pbtxt as scripts/experiment edits it (there with sed): `key` trusted for the
// channels that act, unsigned messages refused; inputs allowed a second of age, servo replies
// 100 ms, the bridge's dead-man, the servos' Bus Watchdog and the SERVO_CMD window a second
// (two cores shared by the twin, which emulates every device, and everything else: with a
// build beside it the bridge went 0.5 s without a cycle once, and the watchdog stopped the
// legs, as it should on a robot).
std::string ExperimentConfig(const std::string& public_key) {
  std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  text = Replaced(text, std::regex("max_input_age_s: [0-9.]+"), "max_input_age_s: 1.0",
                  "max_input_age_s");
  text = Replaced(
      text, std::regex("reply_timeout_s: [0-9.]+"),
      "reply_timeout_s: 0.1\n  deadman_s: 1.0\n  bus_watchdog_s: 1.0\n  start_quiet_s: 1.5",
      "reply_timeout_s");
  text = Replaced(text, std::regex("\n  allow_unsigned: true"),
                  "\n  allow_unsigned: false\n  servo_cmd_window_s: 1.0\n"
                  "  trusted_key { name: \"experiment\" public_key_hex: \"" +
                      public_key +
                      "\" channel: \"SERVO_CMD\" channel: \"EXPERIMENT\" channel: "
                      "\"SEQUENCER_CONTROL\" channel: \"CALIBRATION\" }",
                  "allow_unsigned");
  // The segmenter's kill costs the poses of its outage, and marker dropouts cost more: the
  // short plan's 46 grid poses gave 28-41 steady ones after a mid-phase kill, against the
  // shipped margin of 30. What this test claims about the calibration is held against the
  // truth itself (the bounds experiment_live_test uses), so the margin comes down to 20.
  text = Replaced(text, std::regex("min_poses: [0-9]+"), "min_poses: 20", "min_poses");
  return text;
}

// The group: the robot records and runs the devices and bridges (--realtime, as the lab's),
// the workstation the stages and the sequencer (config/bigant.pbtxt's `lab`, with the twin as
// the robot's devices).
std::string ExperimentGroup(const std::string& key, const std::string& plan) {
  return R"(  group {
    name: "two"
    # scripts/record's recorder: ftcal-record (lcm-logger's 30-message queue lost records
    # here), SCHED_FIFO and a large socket buffer; -i: a restarted recorder writes the next file
    # (session.lcmlog.01) instead of refusing the first.
    process { name: "recorder" host: "robot" command: "chrt"
              args: ["-f", "10", "ftcal-record", "--config", "${config}",
                     "--lcm-url", "${lcm_url}&recv_buf_size=8388608",
                     "-i", "${run_dir}/session.lcmlog"]
              sd_notify: false status_name: "-" }
    process { name: "twin" host: "robot" command: "ftcal-sim"
              args: ["live", "--config", "${config}", "--scenario", "commanded", "--seed", "3",
                     "--com", "leg-aware", "--pty-link", "${run_dir}/dynamixel",
                     "--control", "${run_dir}/operator.fifo", "--truth-dir", "${run_dir}",
                     "--ati-rate", "200", "--servo-tau", "0.05", "--mocap", "qtm"]
              sd_notify: false status_name: "-" restart { startsecs_s: 2 } }
    # A second of silence before the bridge restarts a stream (0.1 s by default): the twin
    # descheduled for a tenth of a second on a loaded machine restarted every stream mid-plan
    # (the sequence numbers going back), which a box on a robot does not do.
    process { name: "ati-bridge" host: "robot" command: "ftcal-ati-bridge"
              args: ["--config", "${config}", "--realtime", "--silence-timeout", "1.0"]
              after: ["twin"]
              gate { kind: STATUS_RUNNING within_s: 5 }
              gate { kind: RATE channel: "FT_*" rate_hz: 200 min_channels: 6 window_s: 2 within_s: 10 } }
    process { name: "dynamixel-bridge" host: "robot" command: "ftcal-dynamixel-bridge"
              args: ["--config", "${config}", "--device", "${run_dir}/dynamixel", "--realtime"]
              after: ["twin"]
              gate { kind: FRESH channel: "SERVO_STATE" max_age_s: 0.5 within_s: 5 } }
    process { name: "mocap-bridge" host: "robot" command: "ftcal-mocap-bridge"
              args: ["--config", "${config}", "--realtime"] after: ["twin"]
              gate { kind: FRESH channel: "MOCAP_BODY" max_age_s: 0.5 within_s: 5 } }
    process { name: "segmenter" host: "workstation" command: "ftcal-pose-segmenter"
              args: ["--config", "${config}"]
              after: ["ati-bridge", "dynamixel-bridge", "mocap-bridge"]
              gate { kind: STATUS_RUNNING accept_degraded: true within_s: 5 } }
    process { name: "calibrator" host: "workstation" command: "ftcal-calibrator"
              args: ["--config", "${config}", "--lcm-url", "${lcm_url}&recv_buf_size=8388608",
                     "--signing-key", ")" +
         key + R"(", "--out", "${run_dir}/calibration.pbtxt"]
              after: ["segmenter"] sd_notify: false
              gate { kind: STATUS_RUNNING accept_degraded: true within_s: 5 } }
    process { name: "corrector" host: "workstation" command: "ftcal-corrector"
              args: ["--config", "${config}"] after: ["segmenter"]
              gate { kind: STATUS_RUNNING accept_degraded: true within_s: 5 } }
    # Moves the robot: last, and never restarted by supervisor (config/bigant.pbtxt's lab).
    process { name: "sequencer" host: "workstation" command: "ftcal-sequencer"
              args: ["--config", "${config}", "--plan", ")" +
         plan + R"(",
                     "--progress", "${run_dir}/run.progress", "--session", "two-host-3",
                     "--signing-key", ")" +
         key + R"("]
              after: ["segmenter", "calibrator", "corrector"]
              restart { autorestart: NEVER }
              gate { kind: STATUS_RUNNING within_s: 10 } }
  }
)";
}

// The operator, as scripts/experiment is: each prompt of the sequencer (its stdout, which
// supervisord writes into the workstation's logs/two-sequencer.out) names what the hands must
// do; the twin's FIFO does it, the twin's PATH.state says when its devices report it, and then
// a signed CONFIRM goes out (ftcal-sequencer-control).
class Operator {
 public:
  Operator(std::string prompts, std::string fifo, std::string config, std::string key)
      : prompts_(std::move(prompts)),
        fifo_(std::move(fifo)),
        config_(std::move(config)),
        key_(std::move(key)) {}

  // Answers every prompt printed since the last call; false on one it does not know.
  bool Serve() {
    std::ifstream in(prompts_, std::ios::binary);
    if (!in) return true;  // not written yet
    in.seekg(static_cast<std::streamoff>(offset_));
    std::string chunk((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::size_t start = 0;
    for (std::size_t nl; (nl = chunk.find('\n', start)) != std::string::npos; start = nl + 1) {
      if (!Answer(chunk.substr(start, nl - start))) return false;
    }
    offset_ += start;  // a line not yet complete is read again next time
    return true;
  }
  int answered() const { return applied_; }

 private:
  // The prompts of services/sequencer/plan.cc, mapped as scripts/experiment maps them.
  static std::optional<std::string> Hands(const std::string& line) {
    for (const char* series : {"HANG_X_POS", "HANG_X_NEG", "HANG_Z_POS", "HANG_Z_NEG"}) {
      if (line.find("(" + std::string(series) + " ") != std::string::npos) {
        return "hang " + std::string(series);
      }
    }
    if (line.rfind("Tare: lift", 0) == 0) return "lift";
    if (line.rfind("Set the robot down", 0) == 0) return "stand";
    return std::nullopt;
  }

  bool Answer(const std::string& line) {
    std::cout << "sequencer: " << line << "\n";
    if (line.find("[press Enter]") == std::string::npos) return true;
    const auto hands = Hands(line);
    if (!hands) {
      ADD_FAILURE() << "a prompt this operator does not know: " << line;
      return false;
    }
    std::cout << "operator: " << *hands << std::endl;
    const int fd = ::open(fifo_.c_str(), O_WRONLY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) {
      ADD_FAILURE() << "the twin's FIFO " << fifo_ << ": " << std::strerror(errno);
      return false;
    }
    const std::string text = *hands + "\n";
    const bool written = ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size());
    ::close(fd);
    EXPECT_TRUE(written) << fifo_;
    ++applied_;
    // The twin acknowledges once its devices report the new support; the bridges then need a
    // moment to carry it to the sequencer's pre-check (which asks again if it is not there yet).
    const auto t0 = Clock::now();
    while (Since(t0) < 5.0) {
      std::ifstream state(fifo_ + ".state");
      int n = 0;
      if (state >> n && n >= applied_) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    const auto r =
        RunShell({},
                 ShellQuote(FTCAL_SEQUENCER_CONTROL) + " --config " + ShellQuote(config_) +
                     " --signing-key " + ShellQuote(key_) + " confirm --note " + ShellQuote(*hands),
                 "", 30);
    EXPECT_EQ(r.exit_code, 0) << "the CONFIRM could not be sent: " << r.output;
    return true;
  }

  std::string prompts_, fifo_, config_, key_;
  std::size_t offset_ = 0;
  int applied_ = 0;
};

int64_t WallUtime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// The recording as ftcal-record wrote it: every file of `-i` (session.lcmlog.00, .01, ...), the
// first and last event time of each, and each FT_<LEG> channel's records in log order (a
// message's records one by one).
struct Recording {
  struct Ft {
    // utime: the record's logged time. A message's last record has the message's (the logger's
    // receipt); an earlier record of a buffered datagram that much before it as its sample time
    // is before the last record's (sample_utime, one host's clock), as if it had come alone.
    int64_t seq, utime;
    int file;
    int32_t bridge_gap;  // what the bridge itself saw missing before this record
  };
  std::vector<std::string> files;
  std::vector<std::pair<int64_t, int64_t>> span;
  std::map<std::string, std::vector<Ft>> ft;
  std::vector<process_state_t> states;
  int64_t first_marker = -1;  // the first EXPERIMENT event: the plan's first phase
};

Recording ReadRecording(const std::string& dir) {
  Recording rec;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("session.lcmlog.", 0) == 0) rec.files.push_back(entry.path().string());
  }
  std::sort(rec.files.begin(), rec.files.end());
  auto is_ft = [](const std::string& ch) {  // FT_<LEG>
    return ch.size() > 3 && ch.compare(0, 3, "FT_") == 0 &&
           std::all_of(ch.begin() + 3, ch.end(), [](char c) { return c >= 'A' && c <= 'Z'; });
  };
  for (int f = 0; f < static_cast<int>(rec.files.size()); ++f) {
    lcm::LogFile log(rec.files[f], "r");
    EXPECT_TRUE(log.good()) << rec.files[f];
    std::pair<int64_t, int64_t> span{-1, -1};
    // A log cut by kill -9 ends in a partial event: the reader stops before it.
    while (const lcm::LogEvent* e = log.readNextEvent()) {
      if (span.first < 0) span.first = e->timestamp;
      span.second = e->timestamp;
      if (is_ft(e->channel)) {
        ft_batch_t m;
        if (m.decode(e->data, 0, e->datalen) != e->datalen) continue;
        for (int i = 0; i < m.n; ++i) {
          const int64_t before_last = m.sample_utime[m.n - 1] - m.sample_utime[i];
          rec.ft[e->channel].push_back(
              {m.rdt_sequence[i], e->timestamp - before_last, f, m.gap[i]});
        }
      } else if (e->channel == "EXPERIMENT") {
        if (rec.first_marker < 0) rec.first_marker = e->timestamp;
      } else if (e->channel == "PROCESS_STATE") {
        process_state_t m;
        if (m.decode(e->data, 0, e->datalen) == e->datalen) rec.states.push_back(m);
      }
    }
    rec.span.push_back(span);
  }
  return rec;
}

class TwoHostExperiment : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_STREQ(std::getenv("FTCAL_NETNS"), "1")
        << "multicast tests run only inside scripts/netns-exec";
    dir_ = testing::MakeTempDir();
  }
  void TearDown() override {
    if (HasFailure()) {
      std::cout << "kept " << dir_ << "\n"
                << RunShell({}, "tail -n 8 " + dir_ + "/robot/logs/*.err " + dir_ +
                                    "/workstation/logs/*.err " + dir_ + "/robot/supervisord.log " +
                                    dir_ + "/workstation/supervisord.log 2>/dev/null")
                       .output;
    } else {
      testing::RemoveTree(dir_);
    }
  }
  // The whole test on the plan `plan` (config/sim.pbtxt's, or kRestartPlan), the live
  // calibration held to the whole experiment's recovery bounds times `truth_scale`; with
  // truth_scale 0 (a plan without the hanging series) there is no calibration to check.
  void RunPlan(const std::string& plan, double truth_scale);
  std::string dir_;
};

void TwoHostExperiment::RunPlan(const std::string& plan, double truth_scale) {
  if (::geteuid() != 0) GTEST_SKIP() << "two network namespaces need root (CI runs as root)";
  // Ahead of whatever else the machine runs (CI, builds): this test and everything it starts,
  // supervisord and the group included, inherit it.
  testing::AheadOfTheMachine();
  PutProgramsOnPath();
  PutOnPath({FTCAL_SEQUENCER, FTCAL_RECORD});

  // Its own key for the four channels that act (scripts/experiment's step 1).
  const std::string keys = dir_ + "/keys";
  std::filesystem::create_directories(keys);
  std::filesystem::permissions(keys, std::filesystem::perms::owner_all);
  const std::string key = keys + "/experiment.key";
  const auto keygen = RunShell({}, ShellQuote(FTCAL_KEYGEN) + " --out " + ShellQuote(key), "", 30);
  ASSERT_EQ(keygen.exit_code, 0) << keygen.output;
  std::smatch hex;
  ASSERT_TRUE(std::regex_search(keygen.output, hex, std::regex("[0-9a-f]{64}"))) << keygen.output;

  TwoNamespaces ns;
  const std::string robot_run = dir_ + "/robot", ws_run = dir_ + "/workstation";
  SupervisordGuard guard;
  guard.run_dirs = {robot_run, ws_run};
  const std::string config = dir_ + "/two.pbtxt";
  // kRestartPlan beside the shipped plans (the launch block, which comes last, is replaced).
  const std::string with_plan = Replaced(ExperimentConfig(hex.str()), std::regex("\nauth \\{"),
                                         std::string(kRestartPlan) + "\nauth {", "auth");
  WriteText(config,
            TwoHostLaunchConfig(with_plan, ns, robot_run, ws_run, ExperimentGroup(key, plan)));
  const std::vector<std::string> robot_shell = {"ip", "netns", "exec", ns.robot, "sh", "-c"};
  ns.Enter(ns.workstation);  // the test, the launcher, ftcal-status and the operator
  // A socket buffer of its own size: it must not miss a heartbeat or a PROCESS_STATE among the
  // transducers' datagrams while the test is busy in supervisorctl.
  Ear ear("udpm://239.255.76.67:7667?ttl=1&recv_buf_size=4194304", "STEADY_POSE");

  const Ran up = Launch({"--config", config, "up", "two"}, 300);
  ASSERT_EQ(up.rc, 0) << up.out;
  std::cout << up.out << "FIGURE ftcal-launch up two (2 hosts, 9 processes): " << up.seconds
            << " s\n";

  // The plan, with this test as the operator; the kills once the standing phase is well under way.
  Operator op(ws_run + "/logs/two-sequencer.out", robot_run + "/operator.fifo", config, key);
  const auto t_plan = Clock::now();
  auto sequencer_ended = [&] {
    for (const auto& m : ear.states()) {
      if (m.host == "workstation" && m.name == "sequencer" &&
          (m.to_state == "EXITED" || m.to_state == "FATAL")) {
        return true;
      }
    }
    return false;
  };
  bool killed = false;
  pid_t old_logger = 0, old_segmenter = 0, new_logger = 0;
  std::optional<std::pair<int64_t, double>> segmenter_back;
  int64_t t_kill_us = 0, poses_at_kill = 0;
  Clock::time_point t_kill;
  std::map<std::string, launch::ProgramStatus> robot_before, ws_before;
  auto last_poll = Clock::now();
  while (true) {
    ASSERT_LT(Since(t_plan), kPlanTimeoutS) << "the plan did not end";
    ASSERT_TRUE(op.Serve());
    if (!killed && ear.count("STEADY_POSE") >= kKillAfterPoses) {
      killed = true;
      robot_before = SupervisorStatus(robot_run, robot_shell);
      ws_before = SupervisorStatus(ws_run);
      old_logger = static_cast<pid_t>(robot_before["two:recorder"].pid);
      old_segmenter = static_cast<pid_t>(ws_before["two:segmenter"].pid);
      ASSERT_GT(old_logger, 0);
      ASSERT_GT(old_segmenter, 0);
      // ftcal-status listens through the kills, as an operator's would.
      testing::Child status_view({FTCAL_STATUS_EXE, "--config", config, "--once-after", "8"},
                                 dir_ + "/status.out", dir_ + "/status.err");
      ear.Pump(0.5);
      const std::size_t from = ear.beat_count();
      poses_at_kill = ear.count("STEADY_POSE");
      Respawn logger{SupervisordPid(robot_run), "ftcal-record", old_logger},
          segmenter{SupervisordPid(ws_run), "ftcal-pose-segmenter", old_segmenter};
      t_kill = Clock::now();
      t_kill_us = WallUtime();
      const double kill_boot_s = BootS();
      ASSERT_EQ(::kill(old_logger, SIGKILL), 0);
      ASSERT_EQ(::kill(old_segmenter, SIGKILL), 0);
      // The restarts as the kernel sees them: each supervisord's new child, both watched at once.
      WatchRespawns(kill_boot_s, {&logger, &segmenter}, 5);
      new_logger = logger.pid;
      std::cout << "FIGURE kill -9 -> supervisord's new child: robot/recorder " << logger.Describe()
                << ", workstation/segmenter " << segmenter.Describe() << " (after " << poses_at_kill
                << " steady poses, " << Since(t_plan) << " s into the plan)\n";
      EXPECT_GT(logger.pid, 0) << "the logger was not restarted within 5 s";
      EXPECT_LT(logger.net_s(), kRestartBoundS) << logger.Describe();
      EXPECT_GT(segmenter.pid, 0) << "the segmenter was not restarted within 5 s";
      EXPECT_LT(segmenter.net_s(), kRestartBoundS) << segmenter.Describe();
      ASSERT_GT(new_logger, 0);
      // The restarted logger runs as the first did: SCHED_FIFO (policy 1, /proc/PID/stat field 41).
      {
        std::ifstream stat("/proc/" + std::to_string(new_logger) + "/stat");
        std::string line;
        std::getline(stat, line);
        std::istringstream rest(line.substr(line.rfind(')') + 2));
        std::vector<std::string> fields;
        for (std::string f; rest >> f;) fields.push_back(f);
        // fields[0] is field 3 (state): field 41 (policy) is fields[38].
        const std::string policy = fields.size() > 38 ? fields[38] : "?";
        std::cout << "restarted recorder pid " << new_logger << ": scheduling policy " << policy
                  << " (1: SCHED_FIFO)\n";
        EXPECT_EQ(policy, "1");
      }
      ear.PumpUntil(
          [&] {
            segmenter_back = Restarted(ear, from, "ftcal-pose-segmenter", old_segmenter, t_kill);
            return segmenter_back.has_value();
          },
          5.0);
      ASSERT_TRUE(segmenter_back) << "no heartbeat from a restarted segmenter within 5 s";
      std::cout << "FIGURE kill -9 -> new pid's first heartbeat: workstation/segmenter "
                << segmenter_back->second << " s\n";
      EXPECT_LT(segmenter_back->second, 2.0);

      // supervisor calls them RUNNING once they stayed up startsecs (2 s), with the new pids;
      // nothing else was restarted.
      auto robot_after = SupervisorStatus(robot_run, robot_shell);
      auto ws_after = SupervisorStatus(ws_run);
      EXPECT_TRUE(ear.PumpUntil(
          [&] {
            robot_after = SupervisorStatus(robot_run, robot_shell);
            ws_after = SupervisorStatus(ws_run);
            return robot_after["two:recorder"].state == "RUNNING" &&
                   ws_after["two:segmenter"].state == "RUNNING";
          },
          8.0));
      EXPECT_EQ(robot_after["two:recorder"].pid, new_logger);
      EXPECT_EQ(ws_after["two:segmenter"].pid, segmenter_back->first);
      for (const char* p : {"twin", "ati-bridge", "dynamixel-bridge", "mocap-bridge"}) {
        EXPECT_EQ(robot_after["two:" + std::string(p)].pid,
                  robot_before["two:" + std::string(p)].pid)
            << p;
      }
      for (const char* p : {"calibrator", "corrector", "sequencer"}) {
        EXPECT_EQ(ws_after["two:" + std::string(p)].pid, ws_before["two:" + std::string(p)].pid)
            << p;
      }
      const Ran launch_status = Launch({"--config", config, "status", "two"});
      EXPECT_EQ(launch_status.rc, 0) << launch_status.out;
      EXPECT_TRUE(std::regex_search(launch_status.out, std::regex("two:recorder +RUNNING +pid " +
                                                                  std::to_string(new_logger))))
          << launch_status.out;
      EXPECT_TRUE(std::regex_search(
          launch_status.out,
          std::regex("two:segmenter +RUNNING +pid " + std::to_string(segmenter_back->first))))
          << launch_status.out;

      // ftcal-status, on the workstation, shows both restarts with their hosts.
      const auto status_rc = status_view.Wait(15);
      EXPECT_TRUE(status_rc.has_value()) << "ftcal-status --once-after 8 did not exit";
      const std::string table = testing::ReadFile(dir_ + "/status.out");
      {  // its counter column is wide: the head of each row is what this test checks
        std::istringstream rows(table);
        for (std::string row; std::getline(rows, row);) std::cout << row.substr(0, 120) << "\n";
      }
      const auto logger_row = GroupRow(table, "two:recorder");
      const auto segmenter_row = GroupRow(table, "two:segmenter");
      EXPECT_FALSE(logger_row.empty()) << table;
      EXPECT_FALSE(segmenter_row.empty()) << table;
      if (!logger_row.empty()) {
        EXPECT_EQ(logger_row[0], "robot") << table;
        EXPECT_EQ(logger_row[2], "RUNNING") << table;
        EXPECT_EQ(logger_row[3], std::to_string(new_logger)) << table;
        EXPECT_EQ(logger_row[4], "1") << table << " (restarts)";
        EXPECT_EQ(logger_row[5], "-")
            << table << " (status_name " - ": not matched to a heartbeat)";
      }
      if (!segmenter_row.empty()) {
        EXPECT_EQ(segmenter_row[0], "workstation") << table;
        EXPECT_EQ(segmenter_row[2], "RUNNING") << table;
        EXPECT_EQ(segmenter_row[3], std::to_string(segmenter_back->first)) << table;
        EXPECT_EQ(segmenter_row[4], "1") << table << " (restarts)";
        EXPECT_TRUE(segmenter_row[5] == "RUNNING" || segmenter_row[5] == "DEGRADED") << table;
      }
      // The listeners published the restarts, one from each host.
      int restarts_heard = 0;
      for (const auto& m : ear.states()) {
        if (m.to_state != "RUNNING" || m.restarts != 1) continue;
        restarts_heard +=
            (m.host == "robot" && m.name == "recorder" && m.pid == new_logger) ||
            (m.host == "workstation" && m.name == "segmenter" && m.pid == segmenter_back->first);
      }
      EXPECT_EQ(restarts_heard, 2);
    }
    if (Since(last_poll) > 10) {  // the listener's EXITED may be lost on the way: ask supervisor
      last_poll = Clock::now();
      const auto st = SupervisorStatus(ws_run)["two:sequencer"].state;
      if (st != "RUNNING" && st != "STARTING") break;
    }
    if (sequencer_ended()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  const double plan_s = Since(t_plan);
  op.Serve();  // its last lines
  ASSERT_TRUE(killed) << "the plan ended before " << kKillAfterPoses << " steady poses were heard ("
                      << ear.count("STEADY_POSE") << ")";
  // The sequencer ran the plan to its end: exit 0 (supervisord's own log says).
  const std::string ws_log = testing::ReadFile(ws_run + "/supervisord.log");
  std::smatch exited;
  ASSERT_TRUE(std::regex_search(ws_log, exited, std::regex("exited: sequencer \\(([^)]*)\\)")))
      << ws_log;
  ASSERT_EQ(exited[1].str(), "exit status 0; expected")
      << "the plan stopped before its end:\n"
      << RunShell({}, "tail -n 30 " + ws_run + "/logs/two-sequencer.err").output;
  std::cout << "FIGURE plan '" << plan << "' ran to its end in " << plan_s << " s, "
            << op.answered() << " prompts answered\n";

  // The restarted segmenter picked the standing phase up again: steady poses after the kill,
  // counted by the new pid itself.
  const int64_t poses_after = ear.count("STEADY_POSE") - poses_at_kill;
  int64_t new_segmenter_poses = -1;
  for (const auto& b : ear.beats()) {
    if (b.status.name != "ftcal-pose-segmenter" || b.status.pid != segmenter_back->first) continue;
    for (int i = 0; i < b.status.num_counters; ++i) {
      if (b.status.counter_name[i] == "poses") new_segmenter_poses = b.status.counter_value[i];
    }
  }
  std::cout << "FIGURE steady poses: " << poses_at_kill << " before the kill, " << poses_after
            << " after it (the restarted segmenter counts " << new_segmenter_poses << ")\n";
  EXPECT_GE(new_segmenter_poses, 10) << "the restarted segmenter did not pick up STANDING";
  EXPECT_GE(poses_after, 10);

  // The live calibration: the calibrator solves when STANDING ends.
  const std::string calibration_path = ws_run + "/calibration.pbtxt";
  const std::string calibrator_err = ws_run + "/logs/two-calibrator.err";
  const auto t_end = Clock::now();
  while (truth_scale > 0 && Since(t_end) < 300 &&
         !(std::filesystem::exists(calibration_path) &&
           std::filesystem::file_size(calibration_path) > 0)) {
    if (testing::ReadFile(calibrator_err).find("calibration refused") != std::string::npos) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }
  std::cout << "FIGURE live calibration written " << Since(t_end) << " s after the plan's end\n";

  // Where a datagram the robot's logger did not get was lost, should one be: the kernel's UDP
  // counters of the robot's namespace (RcvbufErrors: a full socket buffer).
  const std::string robot_udp = RunShell(robot_shell, "grep ^Udp: /proc/net/snmp", "", 30).output;
  const Ran down = Launch({"--config", config, "down", "two"}, 120);
  EXPECT_EQ(down.rc, 0) << down.out;

  // 2. The recording: two files, one gap per FT channel, inside the outage.
  const Recording rec = ReadRecording(robot_run);
  ASSERT_EQ(rec.files.size(), 2u) << "ftcal-record -i: one file before the kill, one after";
  const int64_t outage_from = rec.span[0].second, outage_to = rec.span[1].first;
  std::cout << "FIGURE outage of the recording: the killed logger's last event "
            << (t_kill_us - outage_from) / 1e3 << " ms before the kill, the restarted logger's "
            << "first " << (outage_to - t_kill_us) / 1e3 << " ms after it\n";
  // What a logger killed with -9 loses of what it had received: its unwritten buffer (a few kB,
  // milliseconds here) and its socket's queue.
  EXPECT_LE(outage_from, t_kill_us + 5000);
  EXPECT_LT(t_kill_us - outage_from, 250000) << "the killed logger had stopped recording earlier";
  EXPECT_LT(outage_to - t_kill_us, 2000000);
  const int64_t period_us = static_cast<int64_t>(1e6 / kAtiRateHz);
  // A record's logged time is its receipt by the logger: a transducer's records come up to a
  // few milliseconds from their nominal spacing (the bridge and the link in between).
  const int64_t jitter_us = 25000;
  int64_t lost_outside = 0, lost_outside_at_bridge = 0, backwards = 0;
  // The experiment is what the recording is for: from the plan's first marker on. Before it,
  // while the group starts, a twin descheduled for 100 ms makes the ATI bridge restart the
  // streams (rdt_sequence from 1 again); that is counted and printed, not held against it.
  ASSERT_GT(rec.first_marker, 0) << "no EXPERIMENT marker in the recording";
  int64_t lost_before_plan = 0, restarts_before_plan = 0;
  int losses_printed = 0;
  ASSERT_EQ(rec.ft.size(), 6u) << "FT_<LEG> channels in the recording";
  std::ostringstream gaps;
  for (const auto& [channel, records] : rec.ft) {
    int inside_gaps = 0;
    for (std::size_t i = 1; i < records.size(); ++i) {
      const auto& a = records[i - 1];
      const auto& b = records[i];
      if (a.utime < rec.first_marker) {
        restarts_before_plan += b.seq <= a.seq;
        lost_before_plan += b.seq > a.seq ? b.seq - a.seq - 1 : 0;
        continue;
      }
      if (b.seq <= a.seq) {
        ++backwards;
        continue;
      }
      const int64_t missing = b.seq - a.seq - 1;
      if (missing == 0) continue;
      // The lost records' times, from the records either side and the twin's rate.
      const int64_t first_lost = a.utime + period_us, last_lost = b.utime - period_us;
      const bool inside = a.file + 1 == b.file && first_lost >= outage_from - jitter_us &&
                          last_lost <= outage_to + jitter_us;
      if (inside) {
        ++inside_gaps;
        gaps << " " << channel << " " << missing << " records = " << missing * period_us / 1e3
             << " ms (neighbours " << (b.utime - a.utime) / 1e3 << " ms apart);";
      } else {
        lost_outside += missing;
        lost_outside_at_bridge += std::min<int64_t>(b.bridge_gap, missing);
        if (++losses_printed > 24) continue;  // the first ones say when; the sum says how many
        std::cout << channel << ": " << missing << " records lost outside the outage, "
                  << (a.utime - t_kill_us) / 1e3 << " ms from the kill, "
                  << (a.utime - rec.first_marker) / 1e6 << " s into the plan (files " << a.file
                  << "/" << b.file << ", the bridge saw " << b.bridge_gap << " of them missing)\n";
      }
    }
    EXPECT_EQ(inside_gaps, 1) << channel << ": the outage shows once in every channel";
  }
  std::cout << "FIGURE recording gaps inside the outage:" << gaps.str() << "\n";
  std::cout << "FIGURE records lost outside the outage: " << lost_outside << " (of them lost "
            << "before the bridge: " << lost_outside_at_bridge << "); before the plan's first "
            << "marker: " << lost_before_plan << " lost, " << restarts_before_plan
            << " stream restarts\n"
            << "robot's UDP counters at the end:\n"
            << robot_udp;
  EXPECT_EQ(lost_outside, 0);
  EXPECT_EQ(backwards, 0) << "a transducer's sequence went back: its stream restarted";
  // The recording holds both restarts beside the data: the new processes' RUNNING (their
  // EXITED went out while the logger was down: both were killed at once).
  bool segmenter_recorded = false, logger_recorded = false;
  for (const auto& m : rec.states) {
    if (m.to_state != "RUNNING" || m.restarts != 1) continue;
    segmenter_recorded |=
        m.host == "workstation" && m.name == "segmenter" && m.pid == segmenter_back->first;
    logger_recorded |= m.host == "robot" && m.name == "recorder" && m.pid == new_logger;
  }
  EXPECT_TRUE(segmenter_recorded)
      << "no PROCESS_STATE RUNNING of the new segmenter in the recording";
  EXPECT_TRUE(logger_recorded) << "no PROCESS_STATE RUNNING of the new logger in the recording";

  if (truth_scale <= 0) return;
  // 3. The live calibration against the twin's truth, with experiment_live_test's bounds for
  // this plan: the whole experiment's times three, p~' each component within four of its sigma.
  // Its precision bound is 1.5 mm, not 1: the segmenter's outage and restart cost poses (22 of
  // 46 kept in a CI run, horizontal sigmas 1.03-1.24 mm; 33 in others).
  ASSERT_TRUE(std::filesystem::exists(calibration_path))
      << "no live calibration:\n"
      << RunShell({}, "tail -n 20 " + calibrator_err).output;
  const config::Config cfg = LoadConfigFile(config);
  const calibration::Calibration live_proto = ReadCalibrationFile(calibration_path);
  const RobotCalibration live = CalibrationFromProto(live_proto, cfg.robot());
  const RobotCalibration truth =
      CalibrationFromProto(ReadCalibrationFile(robot_run + "/truth.pbtxt"), cfg.robot());
  const Errors e = Compare(live, truth);
  ExpectWithinBounds(e, truth_scale, "live vs truth");
  const double p_sigmas = ExpectPTildeWithinSigmas(live_proto, live, truth, 4, 1.5e-3);
  std::cout << "FIGURE live calibration vs truth (" << live_proto.standing_poses()
            << " standing poses): " << Describe(e) << "; p~' worst component " << p_sigmas
            << " sigmas\n";
}

// The main tier's: kRestartPlan, the restarts and the recording checked as on the whole plan;
// the live calibration on a whole plan is experiment_live_test's (plan "quick") in this tier.
TEST_F(TwoHostExperiment, StandingPlanLiveAcrossAVethPairLoggerAndSegmenterKilledMidRun) {
  RunPlan("restart", 0);
}

// The long tier's: the plan "experiment" (about five minutes).
TEST_F(TwoHostExperiment, ShortPlanLiveAcrossAVethPairLoggerAndSegmenterKilledMidRun) {
  RunPlan("experiment", 3);
}

}  // namespace
}  // namespace ftcal
