// Issue 36, findings 1, 2 and 8: a signature says who wrote a message, not when or for which run,
// and the receivers forgot what they had seen when they restarted. Here the real processes
// (ftcal-sequencer, ftcal-corrector, ftcal-calibrator live) take a signed message, are
// restarted as `ftcal-launch restart` would (same config, same files, same state directory),
// and are sent the captured message again: it must be refused, for the reason the fix gives
// (the high-water mark kept on disk; for a calibration also its version), and so must a
// freshly signed message of an earlier prompt or version and one signed too long ago.
//
// Each channel's window is widened in the test config where the replay must fall inside it,
// so that what refuses the replay is the mark kept across the restart, not the clock.
#include <signal.h>
#include <sys/wait.h>

#include <chrono>
#include <fstream>
#include <functional>
#include <map>
#include <optional>
#include <tuple>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "common/envelope.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/sequencer_control_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "signed_commander.h"
#include "sim/twin.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::Encode;
using testing::NowUs;
using testing::StatusCounter;
using testing::StatusWatch;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
constexpr double kTimeoutS = 30.0;

class RestartReplayTest : public testing::NetnsDirTest {
 protected:
  void SetUp() override {
    NetnsDirTest::SetUp();
    ASSERT_TRUE(lcm_.good());
    state_env_ = std::make_unique<testing::ScopedEnv>("FTCAL_STATE_DIR", Path("state"));
  }
  void TearDown() override {
    state_env_.reset();
    NetnsDirTest::TearDown();
  }
  // A config from sim.pbtxt with unsigned messages refused, `extra_auth` in its auth section and
  // `keys` trusted ({name, public key, channels}).
  std::string WriteConfig(
      const std::string& extra_auth,
      const std::vector<std::tuple<std::string, std::string, std::vector<std::string>>>& keys,
      const std::string& extra = "") {
    std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    const std::string from = "\n  allow_unsigned: true";
    const size_t at = text.find(from);
    EXPECT_NE(at, std::string::npos) << "sim.pbtxt allows unsigned messages no more";
    text.replace(at, from.size(), "\n  allow_unsigned: false\n" + extra_auth);
    for (const auto& [name, key, channels] : keys) {
      text = testing::TrustKey(text, name, key, channels);
    }
    text += extra;
    const std::string path = Path("config.pbtxt");
    std::ofstream(path) << text;
    return path;
  }
  std::unique_ptr<Child> Start(const std::string& name, const std::vector<std::string>& argv) {
    ++starts_[name];
    const std::string base = Path(name + "." + std::to_string(starts_[name]));
    return std::make_unique<Child>(argv, base + ".out", base + ".err");
  }
  // The log of the `n`th start of `name` (stdout and stderr).
  std::string Log(const std::string& name, int n) {
    const std::string base = Path(name + "." + std::to_string(n));
    return testing::ReadFile(base + ".out") + testing::ReadFile(base + ".err");
  }
  // Waits until the log of the latest start of `name` says `what`.
  bool AwaitLog(const std::string& name, const std::string& what, double timeout_s = kTimeoutS) {
    const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (Clock::now() < deadline) {
      if (Log(name, starts_[name]).find(what) != std::string::npos) return true;
      lcm_.handleTimeout(50);
    }
    return false;
  }
  void Send(const std::string& channel, const std::vector<uint8_t>& bytes) {
    ASSERT_EQ(lcm_.publish(channel, bytes.data(), static_cast<unsigned>(bytes.size())), 0);
  }
  void Stop(std::unique_ptr<Child>& child) {
    child->Signal(SIGTERM);
    ASSERT_TRUE(child->Wait(15).has_value()) << "did not stop on SIGTERM";
  }

  lcm::LCM lcm_{kUrl};
  std::unique_ptr<testing::ScopedEnv> state_env_;
  std::map<std::string, int> starts_;
};

// Finding 1: a CONFIRM captured off the bus, replayed to a sequencer resumed on its progress
// file, armed the bridge and moved the legs; a replayed STOP stopped later runs.
TEST_F(RestartReplayTest, ASequencerRestartedOnItsProgressRefusesACapturedConfirm) {
  const std::string seq_pub = testing::WriteKeyFile(Path("sequencer.key"));
  const std::string op_pub = testing::WriteKeyFile(Path("operator.key"));
  // The replay comes within the window: what refuses it must be the sequence kept on disk.
  const std::string config = WriteConfig(
      "  control_window_s: 30\n",
      {{"sequencer", seq_pub, {"SERVO_CMD", "EXPERIMENT"}},
       {"operator", op_pub, {"SEQUENCER_CONTROL"}}},
      "plan { name: \"grid\" phase { kind: PHASE_STANDING_GRID confirm: true pose_stride: 100 "
      "dwell_s: 1.5 } }\n");
  auth::Signer op = auth::Signer::FromSeedFile(Path("operator.key"));
  StatusWatch watch(lcm_);
  const std::vector<std::string> argv = {FTCAL_SEQUENCER,
                                         "--config",
                                         config,
                                         "--lcm-url",
                                         kUrl,
                                         "--plan",
                                         "grid",
                                         "--progress",
                                         Path("run.progress"),
                                         "--signing-key",
                                         Path("sequencer.key")};

  auto seq = Start("sequencer", argv);
  auto prompt = watch.Await(
      seq->pid(), [](const service_status_t& s) { return StatusCounter(s, "confirm_nonce") > 0; });
  ASSERT_TRUE(prompt) << Log("sequencer", 1);
  sequencer_control_t confirm{};
  confirm.utime = NowUs();
  confirm.action = sequencer_control_t::CONFIRM;
  confirm.step = -1;
  confirm.nonce = StatusCounter(*prompt, "confirm_nonce");
  const std::vector<uint8_t> captured = Encode(op.Seal("SEQUENCER_CONTROL", confirm, NowUs()));
  Send("SEQUENCER_CONTROL", captured);
  ASSERT_TRUE(watch.AwaitCounter(seq->pid(), "confirms", 1)) << Log("sequencer", 1);
  // No robot here: the standing pre-check fails once its inputs stay missing, and the operator
  // is asked again, with a new nonce. Stopped there, the plan resumes at that prompt.
  ASSERT_TRUE(watch.Await(seq->pid(), [&](const service_status_t& s) {
    const int64_t n = StatusCounter(s, "confirm_nonce");
    return n > 0 && n != confirm.nonce;
  })) << Log("sequencer", 1);
  Stop(seq);

  seq = Start("sequencer", argv);
  auto resumed = watch.Await(
      seq->pid(), [](const service_status_t& s) { return StatusCounter(s, "confirm_nonce") > 0; });
  ASSERT_TRUE(resumed) << Log("sequencer", 2);
  EXPECT_NE(StatusCounter(*resumed, "confirm_nonce"), confirm.nonce);

  Send("SEQUENCER_CONTROL", captured);  // the capture, seconds later
  EXPECT_TRUE(AwaitLog("sequencer", "replayed from operator on SEQUENCER_CONTROL"))
      << Log("sequencer", 2);
  // Signed afresh, but for the prompt before the restart.
  confirm.utime = NowUs();
  Send("SEQUENCER_CONTROL", Encode(op.Seal("SEQUENCER_CONTROL", confirm, NowUs())));
  EXPECT_TRUE(AwaitLog("sequencer", "confirm of another prompt")) << Log("sequencer", 2);
  // A STOP signed a minute ago (outside the window) stops nothing.
  sequencer_control_t stop{};
  stop.utime = NowUs() - 60'000'000;
  stop.action = sequencer_control_t::STOP;
  stop.step = -1;
  Send("SEQUENCER_CONTROL", Encode(op.Seal("SEQUENCER_CONTROL", stop, stop.utime)));
  EXPECT_TRUE(AwaitLog("sequencer", "stale from operator on SEQUENCER_CONTROL"))
      << Log("sequencer", 2);
  auto after = watch.Await(seq->pid(), [](const service_status_t&) { return true; });
  ASSERT_TRUE(after);
  // No confirmation and no stop taken (a counter appears with its first count).
  EXPECT_LE(StatusCounter(*after, "confirms"), 0) << Log("sequencer", 2);
  EXPECT_LE(StatusCounter(*after, "stops"), 0) << Log("sequencer", 2);
  EXPECT_TRUE(seq->running());

  // The operator's tool reads the prompt's nonce and its CONFIRM is taken.
  Child tool({FTCAL_SEQUENCER_CONTROL, "--config", config, "--lcm-url", kUrl, "--signing-key",
              Path("operator.key"), "confirm"},
             Path("control.out"), Path("control.err"));
  const auto rc = tool.Wait(kTimeoutS);
  ASSERT_TRUE(rc);
  EXPECT_EQ(testing::DescribeWaitStatus(*rc), "exit 0") << testing::ReadFile(Path("control.err"));
  EXPECT_TRUE(watch.AwaitCounter(seq->pid(), "confirms", 1)) << Log("sequencer", 2);
  Stop(seq);
}

// Finding 2: an old signed CALIBRATION replayed to a restarted corrector replaced the
// calibration it was started with.
TEST_F(RestartReplayTest, ACorrectorRestartedRefusesACalibrationItUsedBeforeAndOlderVersions) {
  auth::Signer calibrator = testing::NewSigner();
  const std::string config = WriteConfig(
      "", {{"calibrator", auth::ToHex(calibrator.public_key().data(), 32), {"CALIBRATION"}}});
  const config::Config parsed = LoadConfigFile(config);
  calibration::Calibration truth = BigAntTwin(parsed, TwinOptions{}).TruthProto();
  truth.set_version(1);
  WriteCalibrationFile(truth, Path("start.pbtxt"));
  // A CALIBRATION of `version`, signed at `signed_utime`.
  auto message = [&](int64_t version, int64_t signed_utime) {
    calibration::Calibration c = truth;
    c.set_version(static_cast<uint64_t>(version));  // other bytes, another hash
    std::string bytes;
    c.SerializeToString(&bytes);
    calibration_t msg{};
    msg.utime = signed_utime;
    msg.version = version;
    msg.content_sha256 = Sha256Hex(bytes);
    msg.data.assign(bytes.begin(), bytes.end());
    msg.size = static_cast<int32_t>(msg.data.size());
    return Encode(calibrator.Seal("CALIBRATION", msg, signed_utime));
  };
  StatusWatch watch(lcm_);
  const std::vector<std::string> argv = {
      FTCAL_CORRECTOR, "--config", config, "--lcm-url", kUrl, "--calibration", Path("start.pbtxt")};

  auto corrector = Start("corrector", argv);
  ASSERT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 1))
      << Log("corrector", 1);
  const auto v2 = message(2, NowUs());
  Send("CALIBRATION", v2);
  ASSERT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 2))
      << Log("corrector", 1);
  Send("CALIBRATION", message(3, NowUs()));
  ASSERT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 3))
      << Log("corrector", 1);
  Stop(corrector);

  corrector = Start("corrector", argv);
  ASSERT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 1))
      << Log("corrector", 2);
  Send("CALIBRATION", v2);  // the capture, inside calibration_window_s
  EXPECT_TRUE(AwaitLog("corrector", "replayed from calibrator on CALIBRATION"))
      << Log("corrector", 2);
  Send("CALIBRATION", message(2, NowUs()));  // version 2 signed afresh
  EXPECT_TRUE(AwaitLog("corrector", "version 2 from calibrator is not above 3"))
      << Log("corrector", 2);
  const int64_t window_us = static_cast<int64_t>(parsed.auth().calibration_window_s() * 1e6);
  Send("CALIBRATION", message(9, NowUs() - 2 * window_us));  // never seen, but old
  EXPECT_TRUE(AwaitLog("corrector", "stale from calibrator on CALIBRATION")) << Log("corrector", 2);
  auto status = watch.Await(corrector->pid(), [](const service_status_t&) { return true; });
  ASSERT_TRUE(status);
  EXPECT_EQ(StatusCounter(*status, "calibration_version"), 1) << Log("corrector", 2);
  // A new one is taken.
  Send("CALIBRATION", message(4, NowUs()));
  EXPECT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 4))
      << Log("corrector", 2);
  Stop(corrector);
}

// Finding 2: a restarted live calibrator accepted an old session's HANG_X_POS start marker.
TEST_F(RestartReplayTest, ALiveCalibratorRestartedRefusesMarkersItTookBeforeAndOldOnes) {
  auth::Signer sequencer = testing::NewSigner();
  const std::string config =
      WriteConfig("  experiment_window_s: 30\n",
                  {{"sequencer", auth::ToHex(sequencer.public_key().data(), 32), {"EXPERIMENT"}}});
  auto marker = [&](const std::string& session, int64_t signed_utime) {
    experiment_marker_t m{};
    m.utime = signed_utime;
    m.session_id = session;
    m.phase = experiment_marker_t::HANG_X_POS;
    m.start = true;
    m.gravity_b[0] = 1.0;
    return Encode(sequencer.Seal("EXPERIMENT", m, signed_utime));
  };
  StatusWatch watch(lcm_);
  const std::vector<std::string> argv = {
      FTCAL_CALIBRATOR, "--config", config, "--lcm-url", kUrl, "--out", Path("calibration.pbtxt")};
  auto cal = Start("calibrator", argv);
  ASSERT_TRUE(watch.AwaitCounter(cal->pid(), "markers", 0)) << Log("calibrator", 1);
  const auto captured = marker("old-session", NowUs());
  Send("EXPERIMENT", captured);
  ASSERT_TRUE(watch.AwaitCounter(cal->pid(), "markers", 1)) << Log("calibrator", 1);
  Stop(cal);

  cal = Start("calibrator", argv);
  ASSERT_TRUE(watch.AwaitCounter(cal->pid(), "markers", 0)) << Log("calibrator", 2);
  Send("EXPERIMENT", captured);
  EXPECT_TRUE(AwaitLog("calibrator", "replayed from sequencer on EXPERIMENT"))
      << Log("calibrator", 2);
  Send("EXPERIMENT", marker("older-session", NowUs() - 60'000'000));
  EXPECT_TRUE(AwaitLog("calibrator", "stale from sequencer on EXPERIMENT")) << Log("calibrator", 2);
  auto status = watch.Await(cal->pid(), [](const service_status_t&) { return true; });
  ASSERT_TRUE(status);
  EXPECT_EQ(StatusCounter(*status, "markers"), 0) << Log("calibrator", 2);
  Send("EXPERIMENT", marker("this-session", NowUs()));
  EXPECT_TRUE(watch.AwaitCounter(cal->pid(), "markers", 1)) << Log("calibrator", 2);
  Stop(cal);
}

// Finding 8: one accepted envelope with a far-future sequence locked its key out at that
// receiver until restart. The real corrector refuses it, and still takes its signer's next one.
TEST_F(RestartReplayTest, ACorrectorRefusesAFarFutureSequenceAndStillHearsItsSigner) {
  const std::string pub = testing::WriteKeyFile(Path("calibrator.key"));
  const std::string config = WriteConfig("", {{"calibrator", pub, {"CALIBRATION"}}});
  const config::Config parsed = LoadConfigFile(config);
  calibration::Calibration truth = BigAntTwin(parsed, TwinOptions{}).TruthProto();
  truth.set_version(1);
  WriteCalibrationFile(truth, Path("start.pbtxt"));
  auto message = [&](auth::Signer& signer, int64_t version) {
    calibration::Calibration c = truth;
    c.set_version(static_cast<uint64_t>(version));
    std::string bytes;
    c.SerializeToString(&bytes);
    calibration_t msg{};
    msg.utime = NowUs();
    msg.version = version;
    msg.content_sha256 = Sha256Hex(bytes);
    msg.data.assign(bytes.begin(), bytes.end());
    msg.size = static_cast<int32_t>(msg.data.size());
    return Encode(signer.Seal("CALIBRATION", msg, NowUs()));
  };
  StatusWatch watch(lcm_);
  auto corrector = Start("corrector", {FTCAL_CORRECTOR, "--config", config, "--lcm-url", kUrl,
                                       "--calibration", Path("start.pbtxt")});
  ASSERT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 1))
      << Log("corrector", 1);
  // The key's holder with its clock a year ahead once: its sequence counts on from there.
  auth::Signer ahead = auth::Signer::FromSeedFile(Path("calibrator.key"));
  ahead.Seal("CALIBRATION", calibration_t{}, NowUs() + 365LL * 86'400'000'000);
  Send("CALIBRATION", message(ahead, 2));
  EXPECT_TRUE(AwaitLog("corrector", "ahead of time from calibrator on CALIBRATION"))
      << Log("corrector", 1);
  // The same key from a process with a right clock: heard, not locked out.
  auth::Signer honest = auth::Signer::FromSeedFile(Path("calibrator.key"));
  Send("CALIBRATION", message(honest, 3));
  EXPECT_TRUE(watch.AwaitCounter(corrector->pid(), "calibration_version", 3))
      << Log("corrector", 1);
  Stop(corrector);
}

// Finding 5: the Dynamixel bridge keeps no SERVO_CMD mark across a restart and relies on
// ignoring commands for dynamixel.start_quiet_s; a window as long would let a command taken
// before the restart act after it. The real bridge refuses such a config at start.
TEST_F(RestartReplayTest, TheDynamixelBridgeRefusesAWindowThatOutlastsItsStartQuiet) {
  std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  const std::string from = "\n  allow_unsigned: true";
  ASSERT_NE(text.find(from), std::string::npos);
  text.replace(text.find(from), from.size(), from + "\n  servo_cmd_window_s: 1.5");
  std::ofstream(Path("long_window.pbtxt")) << text;
  Child bridge({FTCAL_DYNAMIXEL_BRIDGE, "--config", Path("long_window.pbtxt"), "--lcm-url", kUrl},
               Path("dxl.out"), Path("dxl.err"));
  const auto rc = bridge.Wait(30);
  ASSERT_TRUE(rc) << "it started";
  EXPECT_EQ(testing::DescribeWaitStatus(*rc), "exit 3");
  const std::string log = testing::ReadFile(Path("dxl.out")) + testing::ReadFile(Path("dxl.err"));
  EXPECT_NE(log.find("auth.servo_cmd_window_s: must be below dynamixel.start_quiet_s (1 s)"),
            std::string::npos)
      << log;
}

}  // namespace
}  // namespace ftcal
