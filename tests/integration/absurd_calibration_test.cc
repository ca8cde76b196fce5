// Issue 36, finding 6: validly signed calibrations with finite but absurd values went into use
// (offsets of +1e9 N, a leg weight of -1e6 N, a total mass of 1e9 kg, p~' of 1000 km, a mass of
// 1e-300 kg). The real ftcal-corrector refuses each, as a file at start (exit 2) and as a signed
// CALIBRATION (counted, the calibration in use kept), naming the parameter, its value and limit;
// the twin's true calibration passes both ways.
#include <signal.h>

#include <chrono>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "common/envelope.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "ftcal/service_status_t.hpp"
#include "signed_commander.h"
#include "sim/twin.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::Encode;
using testing::NowUs;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";

struct Absurd {
  std::string name;
  std::function<void(calibration::Calibration*)> make;
  std::string says;  // in the refusal
};

std::vector<Absurd> AbsurdCalibrations() {
  return {
      {"offset 1e9 N",
       [](calibration::Calibration* c) { c->mutable_leg(2)->mutable_force_offset_n()->set_z(1e9); },
       "leg[2] (FL).force_offset_n.z = 1000000000, outside the transducer's rated range +-400"},
      {"leg weight -1e6 N",
       [](calibration::Calibration* c) {
         c->mutable_leg(0)->mutable_leg_weight_n()->set_value(-1e6);
       },
       "leg[0] (HL).leg_weight_n = -1000000, outside [0, "},
      {"total mass 1e9 kg", [](calibration::Calibration* c) { c->set_total_mass_kg(1e9); },
       "total_mass_kg = 1000000000, outside the config's robot.total_mass_kg"},
      {"p~' 1000 km",
       [](calibration::Calibration* c) {
         c->mutable_leg(4)->mutable_mounting()->mutable_p_tilde_prime_m()->set_y(1e6);
       },
       "leg[4] (MR).mounting.p_tilde_prime_m[1] = 1000000, outside +-"},
      {"total mass 1e-300 kg", [](calibration::Calibration* c) { c->set_total_mass_kg(1e-300); },
       "total_mass_kg = 1e-300, outside the config's robot.total_mass_kg"},
      {"g0 98 m/s^2", [](calibration::Calibration* c) { c->set_g0_m_s2(98.0); },
       "g0_m_s2 = 98, outside the config's robot.g0_m_s2"},
      {"leg CoM 50 m",
       [](calibration::Calibration* c) {
         c->mutable_leg(1)->mutable_com()->mutable_y_m()->set_value(50.0);
       },
       "leg[1] (ML).com.y_m = 50, outside +-"},
  };
}

class AbsurdCalibrationTest : public testing::NetnsDirTest {
 protected:
  void SetUp() override {
    NetnsDirTest::SetUp();
    std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    text = testing::TrustKey(text, "calibrator", auth::ToHex(calibrator_.public_key().data(), 32),
                             {"CALIBRATION"});
    config_path_ = Path("config.pbtxt");
    std::ofstream(config_path_) << text;
    config_ = LoadConfigFile(config_path_);
    truth_ = BigAntTwin(config_, TwinOptions{}).TruthProto();
    truth_.set_version(1);
  }
  auth::Signer calibrator_ = testing::NewSigner();
  std::string config_path_;
  config::Config config_;
  calibration::Calibration truth_;
};

TEST_F(AbsurdCalibrationTest, TheCorrectorRefusesEachAsAFileAtStartNamingIt) {
  {
    SCOPED_TRACE("the truth");
    WriteCalibrationFile(truth_, Path("truth.pbtxt"));
    // The truth passes the same checks in the library, independently of the process.
    EXPECT_NO_THROW(
        CheckCalibrationPlausible(CalibrationFromProto(truth_, config_.robot()), config_));
  }
  for (const Absurd& a : AbsurdCalibrations()) {
    SCOPED_TRACE(a.name);
    calibration::Calibration c = truth_;
    a.make(&c);
    const std::string file = Path("absurd.pbtxt");
    WriteCalibrationFile(c, file);
    Child corrector(
        {FTCAL_CORRECTOR, "--config", config_path_, "--lcm-url", kUrl, "--calibration", file},
        Path("corrector.out"), Path("corrector.err"));
    const auto rc = corrector.Wait(30);
    ASSERT_TRUE(rc) << "it ran on with the calibration";
    EXPECT_EQ(testing::DescribeWaitStatus(*rc), "exit 2");
    const std::string log =
        testing::ReadFile(Path("corrector.out")) + testing::ReadFile(Path("corrector.err"));
    EXPECT_NE(log.find(a.says), std::string::npos) << log;
    EXPECT_NE(log.find("--calibration " + file), std::string::npos) << log;
  }
}

TEST_F(AbsurdCalibrationTest, TheCorrectorRefusesEachSignedMessageAndKeepsTheOneInUse) {
  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  WriteCalibrationFile(truth_, Path("truth.pbtxt"));
  Child corrector({FTCAL_CORRECTOR, "--config", config_path_, "--lcm-url", kUrl, "--calibration",
                   Path("truth.pbtxt")},
                  Path("corrector.out"), Path("corrector.err"));
  auto log = [&] {
    return testing::ReadFile(Path("corrector.out")) + testing::ReadFile(Path("corrector.err"));
  };
  ASSERT_EQ(testing::AwaitHeartbeats(lcm, {corrector.pid()}, 30).size(), 1u) << log();
  const std::vector<Absurd> absurd = AbsurdCalibrations();
  int64_t version = 1;
  for (const Absurd& a : absurd) {
    calibration::Calibration c = truth_;
    a.make(&c);
    c.set_version(static_cast<uint64_t>(++version));
    std::string bytes;
    c.SerializeToString(&bytes);
    calibration_t msg{};
    msg.utime = NowUs();
    msg.version = version;
    msg.content_sha256 = Sha256Hex(bytes);
    msg.data.assign(bytes.begin(), bytes.end());
    msg.size = static_cast<int32_t>(msg.data.size());
    const auto env = Encode(calibrator_.Seal("CALIBRATION", msg, NowUs()));
    ASSERT_EQ(lcm.publish("CALIBRATION", env.data(), static_cast<unsigned>(env.size())), 0);
  }
  // Every one refused (each with its parameter in the log), and version 1 still in use.
  const auto deadline = Clock::now() + std::chrono::seconds(30);
  service_status_t last{};
  auto counter = [&](const std::string& name) -> int64_t {
    for (int i = 0; i < last.num_counters; ++i) {
      if (last.counter_name[i] == name) return last.counter_value[i];
    }
    return -1;
  };
  while (Clock::now() < deadline) {
    const auto heard = testing::AwaitHeartbeats(lcm, {corrector.pid()}, 5);
    if (heard.empty()) continue;
    last = heard.begin()->second;
    if (counter("calibrations_refused") >= static_cast<int64_t>(absurd.size())) break;
  }
  EXPECT_EQ(counter("calibrations_refused"), static_cast<int64_t>(absurd.size())) << log();
  EXPECT_EQ(counter("calibration_version"), 1) << log();
  for (const Absurd& a : absurd) EXPECT_NE(log().find(a.says), std::string::npos) << a.name;
  corrector.Signal(SIGTERM);
  EXPECT_TRUE(corrector.Wait(15));
}

}  // namespace
}  // namespace ftcal
