#include "ftcal/config.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <regex>
#include <string>
#include <vector>

#include <unistd.h>

namespace ftcal {
namespace {

namespace fs = std::filesystem;

const fs::path kSourceDir = FTCAL_SOURCE_DIR;
const fs::path kBadDir = kSourceDir / "tests/unit/testdata/config";

// The message of the ConfigError that loading `path` throws ("" if it loads).
std::string LoadError(const fs::path& path) {
  try {
    LoadConfigFile(path.string());
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "";
}

std::string TextError(const std::string& text) {
  try {
    LoadConfigText(text, "inline.pbtxt");
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "";
}

std::string ReadFile(const fs::path& path) {
  std::ifstream in(path);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// Replaces the single occurrence of `from` in `text` (fails the test if not exactly one).
std::string Replace(std::string text, const std::string& from, const std::string& to) {
  const size_t at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  EXPECT_EQ(text.find(from, at + 1), std::string::npos) << from;
  if (at != std::string::npos) text.replace(at, from.size(), to);
  return text;
}

#define EXPECT_CONTAINS(haystack, needle) \
  EXPECT_NE(std::string(haystack).find(needle), std::string::npos) << "in: " << (haystack)

TEST(Config, EveryShippedConfigLoadsAndValidates) {
  std::vector<fs::path> files;
  for (const auto& entry : fs::directory_iterator(kSourceDir / "config")) {
    if (entry.path().extension() == ".pbtxt") files.push_back(entry.path());
  }
  ASSERT_GE(files.size(), 2u) << "expected at least bigant.pbtxt and sim.pbtxt";
  for (const fs::path& f : files) {
    SCOPED_TRACE(f.string());
    config::Config config;
    ASSERT_NO_THROW(config = LoadConfigFile(f.string())) << LoadError(f);
    const std::array<Pose3, kNumLegs> poses = NominalTransducerPoses(config.robot());
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_EQ(config.robot().leg(k).name(), kLegNames[k]);
      EXPECT_LT(OrthonormalityError(poses[k].R), 1e-12);
    }
  }
}

// The shipped robot: hips where the brief puts them, left transducers along the body axes and
// right ones turned 180 deg about z, so the mirrored legs see gravity with the opposite sign.
TEST(Config, ShippedRobotGeometry) {
  for (const char* name : {"bigant.pbtxt", "sim.pbtxt"}) {
    SCOPED_TRACE(name);
    const config::Config config = LoadConfigFile((kSourceDir / "config" / name).string());
    EXPECT_DOUBLE_EQ(config.robot().total_mass_kg(), 8.18);
    const std::array<Pose3, kNumLegs> X_B_ft = NominalTransducerPoses(config.robot());
    const double hip_x[kNumLegs] = {-0.2, 0.0, 0.2, -0.2, 0.0, 0.2};
    for (int k = 0; k < kNumLegs; ++k) {
      const bool left = k < 3;
      EXPECT_NEAR((X_B_ft[k].p - Vec3(hip_x[k], left ? 0.15 : -0.15, -0.03)).norm(), 0.0, 1e-12);
      // Body +x in transducer axes: +x on the left, -x on the mirrored right side.
      const Vec3 g_ft = X_B_ft[k].R.transpose() * Vec3(1, 0, 0);
      EXPECT_NEAR(g_ft.x(), left ? 1.0 : -1.0, 1e-12);
      EXPECT_NEAR(X_B_ft[k].R(2, 2), 1.0, 1e-12);
    }
  }
  const config::Config sim = LoadConfigFile((kSourceDir / "config/sim.pbtxt").string());
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_EQ(sim.robot().leg(k).ati().address(), "127.0.1." + std::to_string(k + 1));
    EXPECT_EQ(sim.robot().leg(k).servo().id(), static_cast<uint32_t>(k + 1));
  }
  EXPECT_EQ(sim.mocap().server_address(), "127.0.0.1");
}

TEST(Config, MinimalGoodFileLoadsWithDefaults) {
  const config::Config config = LoadConfigFile((kBadDir / "good_minimal.pbtxt").string());
  EXPECT_DOUBLE_EQ(config.robot().g0_m_s2(), 9.80665);
  EXPECT_EQ(config.segmenter().savgol_window(), 41u);
  const Vec6 k = KWeights(config.calibrator());
  EXPECT_EQ(k, (Vec6() << 1, 1, 1, 10, 10, 10).finished());
  // rpy_deg { z: 180 } on the right legs is the same rotation as diag(-1, -1, 1).
  const std::array<Pose3, kNumLegs> poses = NominalTransducerPoses(config.robot());
  EXPECT_NEAR((poses[4].R - Eigen::Vector3d(-1, -1, 1).asDiagonal().toDenseMatrix()).norm(), 0.0,
              1e-12);
}

TEST(Config, MissingFieldPointsAtEnclosingMessage) {
  const std::string e = LoadError(kBadDir / "missing_field.pbtxt");
  EXPECT_CONTAINS(e, "missing_field.pbtxt:7:3: robot.leg[2].x_b_ft: required field is missing");
}

TEST(Config, MissingRobotPointsAtLineOne) {
  const std::string e = LoadError(kBadDir / "missing_robot.pbtxt");
  EXPECT_CONTAINS(e, "missing_robot.pbtxt:1:1: robot: required field is missing");
}

TEST(Config, UnknownFieldIsAParseError) {
  const std::string e = LoadError(kBadDir / "unknown_field.pbtxt");
  EXPECT_CONTAINS(e, "unknown_field.pbtxt:4:");
  EXPECT_CONTAINS(e, "total_mass_lb");
}

TEST(Config, BadRotationNamesLineAndField) {
  const std::string e = LoadError(kBadDir / "bad_rotation.pbtxt");
  EXPECT_CONTAINS(e, "bad_rotation.pbtxt:9:");
  EXPECT_CONTAINS(e,
                  "robot.leg[4].x_b_ft.rotation_row_major: not a rotation matrix (|R^T R - I| = ");
}

TEST(Config, ReflectionIsNotARotation) {
  const std::string e = LoadError(kBadDir / "reflection.pbtxt");
  EXPECT_CONTAINS(e, "reflection.pbtxt:6:");
  EXPECT_CONTAINS(e, "robot.leg[1].x_b_ft.rotation_row_major: not a rotation matrix (det R = -1");
}

TEST(Config, DuplicateLegNamesBothPlacesAndTheMissingOne) {
  const std::string e = LoadError(kBadDir / "duplicate_leg.pbtxt");
  EXPECT_CONTAINS(e, "duplicate_leg.pbtxt:6:");
  EXPECT_CONTAINS(e, "robot.leg[1].name: duplicate leg 'HL' (already given as robot.leg[0])");
  EXPECT_CONTAINS(e, "duplicate_leg.pbtxt:2:1: robot: missing leg(s) ML");
}

TEST(Config, WrongTypeIsAParseError) {
  const std::string e = LoadError(kBadDir / "wrong_type.pbtxt");
  EXPECT_CONTAINS(e, "wrong_type.pbtxt:4:");
  EXPECT_CONTAINS(e, "total_mass_kg");
}

TEST(Config, NegativeMassRefused) {
  const std::string e = LoadError(kBadDir / "negative_mass.pbtxt");
  EXPECT_CONTAINS(e, "negative_mass.pbtxt:4:3: robot.total_mass_kg: must be > 0, got -8.18");
}

TEST(Config, WrongLegOrderRefused) {
  const std::string e = LoadError(kBadDir / "wrong_leg_order.pbtxt");
  EXPECT_CONTAINS(e, "wrong_leg_order.pbtxt:5:");
  EXPECT_CONTAINS(e, "robot.leg[0].name: leg 'ML' listed at position 0");
  EXPECT_CONTAINS(e, "in the order HL ML FL HR MR FR");
}

TEST(Config, UnknownLegNamed) {
  const std::string e = LoadError(kBadDir / "unknown_leg.pbtxt");
  EXPECT_CONTAINS(e, "unknown_leg.pbtxt:10:");
  EXPECT_CONTAINS(e, "robot.leg[5].name: unknown leg 'XR'");
  EXPECT_CONTAINS(e, "missing leg(s) FR");
}

TEST(Config, MissingLegNamed) {
  const std::string e = LoadError(kBadDir / "missing_leg.pbtxt");
  EXPECT_CONTAINS(e, "missing_leg.pbtxt:2:1: robot: missing leg(s) FR");
}

TEST(Config, DuplicateServoIdNamed) {
  const std::string e = LoadError(kBadDir / "duplicate_servo.pbtxt");
  EXPECT_CONTAINS(e, "duplicate_servo.pbtxt:10:");
  EXPECT_CONTAINS(e, "robot.leg[5].servo.id: servo id 5 already used by robot.leg[4]");
}

TEST(Config, EvenSavgolWindowRefused) {
  const std::string e = LoadError(kBadDir / "bad_segmenter.pbtxt");
  EXPECT_CONTAINS(e, "bad_segmenter.pbtxt:13:3: segmenter.savgol_window: must be odd, got 40");
}

TEST(Config, UnreadableFileNamed) {
  const std::string e = LoadError(kBadDir / "no_such_file.pbtxt");
  EXPECT_CONTAINS(e, "no_such_file.pbtxt");
  EXPECT_CONTAINS(e, "No such file or directory");
}

// Extended Position mode takes +-256 turns around the zero count (docs/device-protocols.md
// §2.7): a servo limit beyond them could never be commanded, so it is refused by name.
TEST(Config, ExtendedPositionModeLimitsStayWithinTheServosTurns) {
  std::string text = ReadFile(kBadDir / "good_minimal.pbtxt");
  text = std::regex_replace(text, std::regex("servo \\{ id: 6 \\}"),
                            "servo { id: 6 max_angle_rad: 2000 }");
  EXPECT_EQ(TextError(text), "") << "position mode: the limit is the config's business";
  text += "dynamixel { device: \"/dev/null\" operating_mode: EXTENDED_POSITION_MODE }\n";
  const std::string error = TextError(text);
  EXPECT_NE(error.find("robot.leg[5].servo.max_angle_rad: is encoder count"), std::string::npos)
      << error;
  EXPECT_NE(error.find("outside the +-1048575 of Extended Position mode"), std::string::npos)
      << error;
  // 256 turns less a little: accepted.
  text = std::regex_replace(text, std::regex("max_angle_rad: 2000"), "max_angle_rad: 1600");
  EXPECT_EQ(TextError(text), "");
}

// Range checks on the minimal file, one edit each: the message names field and value.
TEST(Config, RangeChecks) {
  const std::string good = ReadFile(kBadDir / "good_minimal.pbtxt");
  ASSERT_EQ(TextError(good), "");
  struct Case {
    std::string from, to, expect;
  };
  const std::vector<Case> cases = {
      {"servo { id: 6 }", "servo { id: 253 }",
       "robot.leg[5].servo.id: Dynamixel id must be in 0..252"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" sign: 0 }",
       "robot.leg[5].ati.sign: must be +1 or -1, got 0"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" rdt_port: 70000 }",
       "robot.leg[5].ati.rdt_port: port must be in 1..65535"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" rated_range: [1, 2, 3, 4, 5] }",
       "robot.leg[5].ati.rated_range: needs 0 or 6 entries"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" rated_range: [1, 2, 3, 4, 5, -6] }",
       "robot.leg[5].ati.rated_range[5]: must be > 0"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" counts_per_force: 0 }",
       "robot.leg[5].ati.counts_per_force: must be > 0"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" records_per_datagram: 0 }",
       "robot.leg[5].ati.records_per_datagram: must be in 1..40 (1: real-time mode; else the "
       "box's RDT buffer size), got 0"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" records_per_datagram: 41 }",
       "robot.leg[5].ati.records_per_datagram: must be in 1..40"},
      {"\"127.0.1.6\"", "\"127.0.1\"", "robot.leg[5].ati.address: not an IPv4 address"},
      {"total_mass_kg: 8.18", "total_mass_kg: nan", "robot.total_mass_kg: must be a finite number"},
      {"total_mass_kg: 8.18", "total_mass_kg: 8.18 g0_m_s2: 1.62",
       "robot.g0_m_s2: must be in (9.7, 9.9)"},
      {"x: 0.2 y: -0.15", "x: inf y: -0.15",
       "robot.leg[5].x_b_ft.translation_m.x: must be a finite number"},
      {"rpy_deg { z: 180 } } ati { address: \"127.0.1.6\"",
       "rpy_deg { z: 180 } rotation_row_major: [1, 0, 0, 0, 1, 0, 0, 0, 1] } ati { address: "
       "\"127.0.1.6\"",
       "robot.leg[5].x_b_ft.rpy_deg: give the rotation either as rotation_row_major or as rpy_deg, "
       "not both"},
      {"rpy_deg { z: 180 } } ati { address: \"127.0.1.6\"", "} ati { address: \"127.0.1.6\"",
       "robot.leg[5].x_b_ft: missing rotation"},
      {"x: -0.2 y: 0.15 z: -0.03 } rotation_row_major: [1, 0, 0, 0, 1, 0, 0, 0, 1]",
       "x: -0.2 y: 0.15 z: -0.03 } rotation_row_major: [1, 0, 0, 0, 1, 0, 0, 0]",
       "robot.leg[0].x_b_ft.rotation_row_major: needs 9 numbers"},
      {"\n}\n", "\n}\nsegmenter { savgol_window: 3 savgol_order: 3 }\n",
       "segmenter.savgol_window: must be greater than savgol_order"},
      {"\n}\n", "\n}\nsegmenter { savgol_order: 0 }\n", "segmenter.savgol_order: must be >= 1"},
      {"\n}\n", "\n}\nsegmenter { max_force_rate_n_s: 0 }\n",
       "segmenter.max_force_rate_n_s: must be > 0"},
      {"\n}\n", "\n}\ncalibrator { k_weights: [1, 1, 1, 10, 10] }\n",
       "calibrator.k_weights: needs 0 or 6 entries"},
      {"\n}\n", "\n}\ncalibrator { k_weights: [1, 1, 1, 10, 0, 10] }\n",
       "calibrator.k_weights[4]: must be > 0"},
      {"\n}\n", "\n}\ncalibrator { cv_folds: 1 }\n", "calibrator.cv_folds: must be >= 2"},
      {"\n}\n", "\n}\ncalibrator { phase_bins: 7 }\n", "calibrator.phase_bins: must be >= 8"},
      {"\n}\n", "\n}\ncalibrator { unloaded_leg_min_angle_deg: 180 }\n",
       "calibrator.unloaded_leg_min_angle_deg: must be in (0, 180), got 180"},
      {"\n}\n", "\n}\ncorrector { max_ft_age_s: -1 }\n", "corrector.max_ft_age_s: must be > 0"},
      {"\n}\n", "\n}\ndrift { max_foot_force_n: 0 }\n", "drift.max_foot_force_n: must be > 0"},
      {"\n}\n", "\n}\ndrift { process_noise_torque_nm: -1e-4 }\n",
       "drift.process_noise_torque_nm: must be >= 0, got -0.0001"},
      {"\n}\n", "\n}\ndrift { min_window_s: 2 max_window_s: 1 }\n",
       "drift.max_window_s: must be >= min_window_s (2), got 1"},
      {"\n}\n", "\n}\ndrift { apply_factor: 0 }\n", "drift.apply_factor: must be > 0"},
      {"\n}\n", "\n}\ndrift { apply_min_interval_s: -5 }\n",
       "drift.apply_min_interval_s: must be > 0, got -5"},
      {"\n}\n", "\n}\nmocap { server_address: \"127.0.0.1\" port: 0 }\n",
       "mocap.port: port must be in 1..65535"},
      {"\n}\n", "\n}\nmocap { port: 22223 }\n", "mocap.server_address: required field is missing"},
      {"\n}\n", "\n}\ndynamixel { baud: 1000000 }\n",
       "dynamixel.device: required field is missing"},

      {"\n}\n", "\n}\nchannels { status: \"\" }\n",
       "channels.status: channel name must not be empty"},
      {"\n}\n", "\n}\nlcm_url: \"\"\n", "lcm_url: must not be empty"},
      // Absurd values a typo makes (issue 14): refused with the field named.
      {"total_mass_kg: 8.18", "total_mass_kg: 8180",
       "robot.total_mass_kg: must be at most 1000 kg"},
      {"x: 0.2 y: -0.15", "x: 2000 y: -0.15", "robot.leg[5].x_b_ft.translation_m: is 2000"},
      {"\"127.0.1.6\" }", "\"127.0.1.6\" rated_range: [130, 130, 400, 10, 10, 1e-300] }",
       "robot.leg[5].ati.rated_range[5]: must be in [0.001, 1000000] N or N*m, got 1e-300"},
      {"\n}\n", "\n}\nsegmenter { savgol_window: 100001 }\n",
       "segmenter.savgol_window: spans 1000.01 s at sample_rate_hz 100; at most 60 s, got 100001"},
      {"\n}\n", "\n}\nchannels { contact_wrench: \"SYNC_SAMPLE\" }\n",
       "channels.contact_wrench: channel 'SYNC_SAMPLE' is also channels.sync_sample"},
      {"\n}\n", "\n}\nchannels { ft_prefix: \"SERVO_\" servo_state: \"SERVO_HL\" }\n",
       "channels.servo_state: channel 'SERVO_HL' is also channels.ft_prefix (SERVO_HL)"},
      {"\n}\n",
       "\n}\nauth { trusted_key { name: \"op\" public_key_hex: \"abc\" channel: \"SERVO_CMD\" } "
       "}\n",
       "auth.trusted_key[0].public_key_hex: must be 64 hex digits"},
      {"\n}\n",
       "\n}\nauth { trusted_key { name: \"op\" public_key_hex: "
       "\"00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\" channel: \"FT_HL\" } "
       "}\n",
       "auth.trusted_key[0].channel: 'FT_HL' is not a signed channel"},
      {"\n}\n",
       "\n}\nauth { trusted_key { name: \"a\" public_key_hex: "
       "\"00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\" channel: "
       "\"SERVO_CMD\" } trusted_key { name: \"b\" public_key_hex: "
       "\"10112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\" channel: "
       "\"SERVO_CMD\" } trusted_key { name: \"c\" public_key_hex: "
       "\"20112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\" channel: "
       "\"SERVO_CMD\" } }\n",
       "auth.trusted_key[2].channel: more than two trusted keys for 'SERVO_CMD'"},
      {"\n}\n",
       "\n}\nauth { trusted_key { name: \"a\" public_key_hex: "
       "\"00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\" channel: "
       "\"SERVO_CMD\" } trusted_key { name: \"a\" public_key_hex: "
       "\"10112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\" channel: "
       "\"EXPERIMENT\" } }\n",
       "auth.trusted_key[1].name: duplicate trusted key name 'a'"},
      {"\n}\n", "\n}\nauth { servo_cmd_window_s: 0 }\n",
       "auth.servo_cmd_window_s: must be in (0, 10] s"},
      // Issue 36, finding 5: the bridge forgets its commands on restart and ignores new ones for
      // start_quiet_s, which is safe only while that outlasts the window.
      {"\n}\n",
       "\n}\nauth { servo_cmd_window_s: 1.5 }\ndynamixel { device: \"/dev/x\" start_quiet_s: 1 "
       "}\n",
       "auth.servo_cmd_window_s: must be below dynamixel.start_quiet_s (1 s)"},
      {"\n}\n",
       "\n}\nauth { servo_cmd_window_s: 1 }\ndynamixel { device: \"/dev/x\" start_quiet_s: 1 "
       "}\n",
       "auth.servo_cmd_window_s: must be below dynamixel.start_quiet_s (1 s)"},
      {"\n}\n", "\n}\nhealth { max_drop_share: 0 }\n",
       "health.max_drop_share: must be in (0, 1], got 0"},
      {"\n}\n", "\n}\nhealth { min_inputs: 0 }\n", "health.min_inputs: must be >= 1, got 0"},
      {"\n}\n", "\n}\nauth { control_window_s: 0 }\n",
       "auth.control_window_s: must be in (0, 60] s"},
      {"\n}\n", "\n}\nauth { calibration_window_s: 1e9 }\n",
       "auth.calibration_window_s: must be in (0, 3600] s"},
      {"\n}\n", "\n}\nauth { max_clock_ahead_s: -1 }\n",
       "auth.max_clock_ahead_s: must be in (0, 60] s"},
      {"\n}\n", "\n}\ndynamixel { device: \"/dev/x\" deadman_s: 0 }\n",
       "dynamixel.deadman_s: must be > 0"},
      {"\n}\n", "\n}\ndynamixel { device: \"/dev/x\" max_velocity_rad_s: 0.02 }\n",
       "dynamixel.max_velocity_rad_s: must be at least one unit of the servos' Velocity Limit "
       "(0.229 rpm = "},
      {"\n}\n", "\n}\ndynamixel { device: \"/dev/x\" max_acceleration_rad_s2: 0.3 }\n",
       "dynamixel.max_acceleration_rad_s2: must be at least one unit of the servos' Acceleration "
       "Limit"},
      {"\n}\n", "\n}\ndynamixel { device: \"/dev/x\" bus_watchdog_s: 0.05 }\n",
       "dynamixel.bus_watchdog_s: must be a multiple of 0.02 s within 0.02-2.54 s"},
      {"\n}\n", "\n}\ndynamixel { device: \"/dev/x\" bus_watchdog_s: 2.56 }\n",
       "dynamixel.bus_watchdog_s: must be a multiple of 0.02 s within 0.02-2.54 s"},
      {"\n}\n", "\n}\ndynamixel { device: \"/dev/x\" bus_watchdog_s: 0.04 }\n",
       "dynamixel.bus_watchdog_s: must span at least five bridge cycles (5 / rate_hz = 0.05 s)"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.to);
    EXPECT_CONTAINS(TextError(Replace(good, c.from, c.to)), "inline.pbtxt:");
    EXPECT_CONTAINS(TextError(Replace(good, c.from, c.to)), c.expect);
  }
}

TEST(Config, ToPose3FromRollPitchYawDegrees) {
  config::Pose pose;
  pose.mutable_translation_m()->set_x(1.0);
  pose.mutable_rpy_deg()->set_x(90.0);  // roll: y -> z
  const Pose3 X = ToPose3(pose);
  EXPECT_NEAR((X.R * Vec3::UnitY() - Vec3::UnitZ()).norm(), 0.0, 1e-12);
  EXPECT_NEAR((X.p - Vec3(1, 0, 0)).norm(), 0.0, 0.0);
  pose.add_rotation_row_major(1.0);
  EXPECT_THROW(ToPose3(pose), ConfigError);  // both forms given
}

TEST(Config, ToPose3ProjectsANearlyOrthonormalMatrix) {
  config::Pose pose;
  pose.mutable_translation_m();
  // 30 deg about z, typed to 7 decimals: orthonormal to ~1e-7, not to 1e-12.
  for (double v : {0.8660254, -0.5, 0.0, 0.5, 0.8660254, 0.0, 0.0, 0.0, 1.0}) {
    pose.add_rotation_row_major(v);
  }
  const Pose3 X = ToPose3(pose);
  EXPECT_LT(OrthonormalityError(X.R), 1e-14);
  EXPECT_NEAR(X.R(1, 0), 0.5, 1e-7);
}

TEST(Config, KWeightsChecked) {
  config::Calibrator c;
  for (double w : {2.0, 2.0, 2.0, 5.0, 5.0, 5.0}) c.add_k_weights(w);
  EXPECT_EQ(KWeights(c), (Vec6() << 2, 2, 2, 5, 5, 5).finished());
  c.set_k_weights(3, -1.0);
  EXPECT_THROW(KWeights(c), ConfigError);
}

// FIPS 180-2 test vectors.
TEST(Config, Sha256KnownVectors) {
  EXPECT_EQ(Sha256Hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  EXPECT_EQ(Sha256Hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  const fs::path path = fs::temp_directory_path() / ("ftcal_sha_" + std::to_string(::getpid()));
  {
    // 1,000,000 'a': crosses the streaming buffer many times.
    std::ofstream out(path, std::ios::binary);
    out << std::string(1000000, 'a');
  }
  EXPECT_EQ(Sha256File(path.string()),
            "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0");
  fs::remove(path);
  try {
    Sha256File(path.string());
    FAIL() << "expected an error for a missing file";
  } catch (const std::runtime_error& e) {
    EXPECT_CONTAINS(e.what(), path.string());
  }
}

}  // namespace
}  // namespace ftcal

namespace ftcal {
namespace {

// The launch section: errors name the field path of the offending process or gate.
TEST(ConfigLaunch, UnknownHostCycleAndBadGateAreRefusedByPath) {
  const std::string sim = ReadFile(kSourceDir / "config/sim.pbtxt");
  EXPECT_CONTAINS(TextError(Replace(sim, R"(name: "corrector" host: "local")",
                                    R"(name: "corrector" host: "robot")")),
                  "launch.group[0].process[7].host: no host 'robot' in launch.host");
  EXPECT_CONTAINS(
      TextError(Replace(sim, R"(name: "twin" host: "local" command: "ftcal-sim")",
                        R"(name: "twin" host: "local" command: "ftcal-sim" after: "corrector")")),
      "the dependencies form a cycle");
  EXPECT_CONTAINS(TextError(Replace(sim, R"("${run_dir}/calibration.pbtxt"]
      after: ["segmenter"])",
                                    R"("${run_dir}/calibration.pbtxt"]
      after: ["segmenter", "sequencer"])")),
                  "launch.group[0].process[6].after[1]: no process 'sequencer' in group 'sim'");
  EXPECT_CONTAINS(
      TextError(Replace(sim, R"(channel: "FT_*" rate_hz: 500)", R"(channel: "FT_*" rate_hz: -5)")),
      "launch.group[0].process[2].gate[1].rate_hz: must be in (0, 1e5] Hz, got -5");
  EXPECT_CONTAINS(
      TextError(Replace(sim, R"(channel: "FT_*" rate_hz: 500)", R"(channel: "F*T_" rate_hz: 500)")),
      "'*' may only end a prefix");
  EXPECT_CONTAINS(TextError(Replace(sim, R"(restart { startsecs_s: 2 })",
                                    R"(restart { startsecs_s: 2 stopsignal: "STOP" })")),
                  "launch.group[0].process[1].restart.stopsignal: must be one of TERM");
  EXPECT_CONTAINS(TextError(Replace(sim, R"(name: "segmenter" host: "local")",
                                    R"(name: "segmenter" host: "local" env: "1X=2")")),
                  "launch.group[0].process[5].env[0]: must be NAME=VALUE");
}

}  // namespace
}  // namespace ftcal
