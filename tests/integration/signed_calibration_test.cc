// The attack of issue 12 on the corrector: a CALIBRATION from anyone on the network. With the
// config trusting only the calibrator's key on CALIBRATION (and not allowing unsigned), a bare
// message, one signed by another key, and one the calibrator signed for another channel are
// refused and change nothing; the calibrator's own is applied; replaying it is refused.
#include <sodium.h>

#include <chrono>

#include <gtest/gtest.h>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/lcm_bus.h"
#include "common/envelope.h"
#include "signed_commander.h"
#include "corrector/corrector_stage.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

using testing::Encode;
using testing::NewSigner;
using testing::NowUs;

TEST(SignedCalibration, AForgedCalibrationIsNotAppliedAndTheCalibratorsIs) {
  auth::Signer calibrator = NewSigner(), intruder = NewSigner();
  config::Config config = LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  config.mutable_auth()->set_allow_unsigned(false);
  auto* key = config.mutable_auth()->add_trusted_key();
  key->set_name("calibrator");
  key->set_public_key_hex(auth::ToHex(calibrator.public_key().data(), 32));
  key->add_channel("CALIBRATION");

  ServiceStats stats(
      std::make_shared<spdlog::logger>("test", std::make_shared<spdlog::sinks::null_sink_mt>()));
  LcmBus bus("memq://", stats);
  CorrectorStage stage(config, bus, [](int8_t) {});

  const calibration::Calibration truth = BigAntTwin(config, TwinOptions{}).TruthProto();
  std::string bytes;
  truth.SerializeToString(&bytes);
  calibration_t cal{};
  cal.utime = NowUs();
  cal.version = 1;
  cal.content_sha256 = Sha256Hex(bytes);
  cal.data.assign(bytes.begin(), bytes.end());
  cal.size = static_cast<int32_t>(cal.data.size());

  auto send = [&](const std::vector<uint8_t>& b) {
    bus.PublishRaw("CALIBRATION", b.data(), static_cast<int>(b.size()));
    while (bus.HandleOnce(0) > 0) {
    }
  };
  auto kind = [&](const std::string& k) {
    const auto it = stats.kinds().find(k);
    return it == stats.kinds().end() ? 0 : it->second;
  };

  send(Encode(cal));                                          // bare
  send(Encode(intruder.Seal("CALIBRATION", cal, NowUs())));   // another key
  send(Encode(calibrator.Seal("EXPERIMENT", cal, NowUs())));  // moved between channels
  EXPECT_FALSE(stage.has_calibration());
  EXPECT_EQ(kind("unsigned on CALIBRATION"), 1);
  EXPECT_EQ(kind("untrusted signer on CALIBRATION"), 1);
  EXPECT_EQ(kind("bad signature from calibrator on CALIBRATION"), 1);

  const auto good = Encode(calibrator.Seal("CALIBRATION", cal, NowUs()));
  send(good);
  EXPECT_TRUE(stage.has_calibration());
  send(good);
  EXPECT_EQ(kind("replayed from calibrator on CALIBRATION"), 1);
  EXPECT_EQ(stats.drops(), 4);
}

}  // namespace
}  // namespace ftcal
