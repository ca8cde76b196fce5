// ftcal-log-upgrade (services/log_upgrade): a log written with the older message versions'
// own encoders (lcmtypes/legacy/, generated beside the current types) is rewritten into the
// current types, field for field against hand-written values; every other event is kept byte
// for byte, in order, with its timestamp; a damaged older event is refused naming its event
// and channel, with nothing left under NEW; and the wire guard's refusal of an older version
// names the command. No network: logs only.
#include <sys/wait.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "common/wire_guard.h"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/signed_envelope_t.hpp"
#include "log_upgrade/upgrade.h"

namespace ftcal::log_upgrade {
namespace {

namespace fs = std::filesystem;

struct Event {
  int64_t utime;
  std::string channel;
  std::vector<uint8_t> data;
};

template <class Msg>
std::vector<uint8_t> Bytes(const Msg& msg) {
  std::vector<uint8_t> out(static_cast<size_t>(msg.getEncodedSize()));
  EXPECT_EQ(msg.encode(out.data(), 0, static_cast<int>(out.size())), static_cast<int>(out.size()));
  return out;
}

void WriteLog(const std::string& path, const std::vector<Event>& events) {
  lcm::LogFile log(path, "w");
  ASSERT_TRUE(log.good()) << path;
  for (const Event& e : events) {
    lcm::LogEvent le{};
    le.timestamp = e.utime;
    le.channel = e.channel;
    le.datalen = static_cast<int32_t>(e.data.size());
    le.data = const_cast<uint8_t*>(e.data.data());
    ASSERT_EQ(log.writeEvent(&le), 0);
  }
}

std::vector<Event> ReadLog(const std::string& path) {
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  std::vector<Event> events;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    const auto* d = static_cast<const uint8_t*>(e->data);
    events.push_back({e->timestamp, e->channel, std::vector<uint8_t>(d, d + e->datalen)});
  }
  return events;
}

template <class Msg>
Msg DecodeCurrent(const Event& e) {
  Msg msg;
  const auto refused = wire::Decode(e.data.data(), static_cast<int>(e.data.size()), &msg);
  EXPECT_FALSE(refused) << e.channel << ": " << refused->kind << ": " << refused->detail;
  return msg;
}

class LogUpgradeTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("log_upgrade_test." + std::to_string(::getpid()) + "." +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    old_ = (dir_ / "old.lcmlog").string();
    new_ = (dir_ / "new.lcmlog").string();
  }
  void TearDown() override { fs::remove_all(dir_); }

  fs::path dir_;
  std::string old_;
  std::string new_;
};

// The older versions written with their own encoders, hand-chosen values.
ftcal_pre_batch::ft_sample_t OldFt() {
  ftcal_pre_batch::ft_sample_t m{};
  m.utime = 1'700'000'000'000'123;
  m.leg = "ML";
  m.rdt_sequence = 4'000'000'001;
  m.ft_sequence = 77;
  m.status = 0x20000;
  for (int k = 0; k < 6; ++k) {
    m.counts[k] = -1000 * (k + 1);
    m.wrench[k] = 0.5 * k - 1.25;
  }
  m.gap = 3;
  m.flags = ftcal_pre_batch::ft_sample_t::FLAG_GAP | ftcal_pre_batch::ft_sample_t::FLAG_SATURATED;
  return m;
}

ftcal_pre_batch::contact_wrench_t OldWrench() {
  ftcal_pre_batch::contact_wrench_t m{};
  m.utime = 1'700'000'000'000'500;
  m.leg = 4;
  for (int k = 0; k < 6; ++k) m.wrench_w[k] = 10.0 + k;
  m.wrench_w[2] = std::nan("");
  m.servo_age_s = 0.0125f;
  m.mocap_age_s = -1.0f;
  m.flags = ftcal_pre_batch::contact_wrench_t::FLAG_STALE_MOCAP;
  return m;
}

ftcal_pre_batch::contact_wrench_sum_t OldSum() {
  ftcal_pre_batch::contact_wrench_sum_t m{};
  m.utime = 1'700'000'000'000'600;
  for (int k = 0; k < 6; ++k) {
    m.total_w[k] = 100.0 - k;
    m.residual_w[k] = -0.25 * k;
  }
  m.calibration_version = 42;
  m.oldest_ft_age_s = 0.004f;
  m.flags = 1 | 8;
  return m;
}

const char* const kLegs[6] = {"HL", "ML", "FL", "HR", "MR", "FR"};
// The fingerprints servo_state_t and mocap_body_t had before sample_utime (lcmtypes/legacy/
// README.md): the files as they were at the commit before, hashed by lcm-gen.
constexpr uint64_t kServoStateBeforeSampleTime = 0xe11119ff83534062u;
constexpr uint64_t kMocapBodyBeforeSampleTime = 0x362ada9bc864c030u;

ftcal_pre_fixed6::servo_state_t OldServo(int32_t num_servos = 6) {
  ftcal_pre_fixed6::servo_state_t m{};
  m.utime = 1'700'000'000'000'200;
  m.num_servos = num_servos;
  for (int i = 0; i < num_servos; ++i) {
    m.leg.push_back(kLegs[i % 6]);
    m.id.push_back(11 + i);
    m.angle_rad.push_back(0.1 * i - 0.2);
    m.velocity_rad_s.push_back(-0.5 * i);
    m.current_a.push_back(0.01 * i);
    m.hardware_error.push_back(i == 2 ? 4 : 0);
    m.device_tick_ms.push_back(9'000'000'000LL + i);
    m.flags.push_back(i == 5 ? 8 | 1 : 0);
  }
  return m;
}

ftcal_pre_fixed6::sync_sample_t OldSync() {
  ftcal_pre_fixed6::sync_sample_t m{};
  m.utime = 1'700'000'000'000'300;
  m.num_legs = 6;
  for (int i = 0; i < 6; ++i) {
    m.leg.push_back(kLegs[i]);
    std::vector<double> w;
    for (int k = 0; k < 6; ++k) w.push_back(i * 10 + k + 0.5);
    m.wrench.push_back(w);
    m.angle_rad.push_back(-0.3 * i);
  }
  const double q[4] = {0.5, -0.5, 0.5, 0.5};
  for (int k = 0; k < 4; ++k) m.q_wc[k] = q[k];
  m.attitude_ok = 1;
  m.markers_ok = 0;
  m.flags = 4;
  return m;
}

ftcal_pre_fixed6::steady_pose_t OldPoseCounted() {
  ftcal_pre_fixed6::steady_pose_t m{};
  m.utime = 1'700'000'000'000'400;
  m.session_id = "s-counted";
  m.pose_index = 7;
  m.start_utime = 1'699'999'999'000'000;
  m.end_utime = 1'700'000'000'000'000;
  m.num_samples = 700;
  m.num_legs = 6;
  for (int i = 0; i < 6; ++i) {
    m.leg.push_back(kLegs[i]);
    std::vector<double> w;
    for (int k = 0; k < 6; ++k) w.push_back(-i * 10.0 - k);
    m.wrench.push_back(w);
    m.angle_rad.push_back(0.25 * i);
  }
  m.q_wc[0] = 1.0;
  m.markers_ok = 1;
  return m;
}

ftcal_pre_scatter::steady_pose_t OldPoseFixed() {
  ftcal_pre_scatter::steady_pose_t m{};
  m.utime = 1'700'000'000'000'450;
  m.session_id = "s-fixed";
  m.pose_index = 8;
  m.start_utime = 1'700'000'000'000'001;
  m.end_utime = 1'700'000'000'000'449;
  m.num_samples = 12;
  for (int i = 0; i < 6; ++i) {
    m.leg[i] = kLegs[5 - i];
    for (int k = 0; k < 6; ++k) m.wrench[i][k] = 1.0 / (1 + i + k);
    m.angle_rad[i] = -0.125 * i;
  }
  m.q_wc[0] = 0.0;
  m.q_wc[3] = 1.0;
  m.markers_ok = 0;
  return m;
}

ftcal_pre_nonce::sequencer_control_t OldControl() {
  ftcal_pre_nonce::sequencer_control_t m{};
  m.utime = 1'700'000'000'000'700;
  m.action = 2;  // STOP
  m.step = -1;
  m.note = "operator stop";
  return m;
}

// Before the mapped sample times (ftcal_pre_sample_time).
ftcal_pre_sample_time::servo_state_t OldServoNoSampleTime() {
  ftcal_pre_sample_time::servo_state_t m{};
  m.utime = 1'700'000'000'000'800;
  for (int i = 0; i < 6; ++i) {
    m.leg[i] = kLegs[5 - i];
    m.id[i] = 21 + i;
    m.angle_rad[i] = -0.05 * i;
    m.velocity_rad_s[i] = 0.25 * i;
    m.current_a[i] = -0.02 * i;
    m.hardware_error[i] = i == 1 ? 32 : 0;
    m.device_tick_ms[i] = 123'456 + 3 * i;
    m.flags[i] = i == 4 ? 1 : 0;
  }
  return m;
}

ftcal_pre_sample_time::mocap_body_t OldMocapNoSampleTime() {
  ftcal_pre_sample_time::mocap_body_t m{};
  m.utime = 1'700'000'000'000'900;
  m.frame_number = 4321;
  m.device_utime = 43'210'000;
  m.body = "chassis";
  m.tracked = true;
  for (int i = 0; i < 4; ++i) m.q_wc[i] = m.q_gc[i] = i == 2 ? 1.0 : 0.0;
  m.position_m[0] = 0.5;
  m.position_m[1] = -0.25;
  m.position_m[2] = 1.125;
  m.yaw_rad = 0.75;
  m.residual_m = 0.0004;
  m.num_markers = 2;
  m.marker_m = {{0.1, 0.2, 0.3}, {-0.1, -0.2, -0.3}};
  m.marker_tracked = {true, false};
  return m;
}

// A current message, a bare non-ftcal payload and an envelope: copied as they are.
std::vector<uint8_t> CurrentMocap() {
  ftcal::mocap_body_t m{};
  m.utime = 1'700'000'000'000'050;
  m.num_markers = 0;
  return Bytes(m);
}

std::vector<Event> OldLog() {
  return {
      {1000, "MOCAP_BODY", CurrentMocap()},
      {1001, "FT_ML", Bytes(OldFt())},
      {1002, "SERVO_STATE", Bytes(OldServo())},
      {1002, "SOMEONE_ELSE", {1, 2, 3, 4, 5, 6, 7, 8, 9, 10}},
      {1003, "SYNC_SAMPLE", Bytes(OldSync())},
      {1004, "STEADY_POSE", Bytes(OldPoseCounted())},
      {1004, "STEADY_POSE", Bytes(OldPoseFixed())},
      {1005, "CONTACT_WRENCH", Bytes(OldWrench())},
      {1006, "CONTACT_WRENCH_SUM", Bytes(OldSum())},
      {1007, "SEQUENCER_CONTROL", Bytes(OldControl())},
      {999, "EMPTY", {}},  // a timestamp out of order, and no data: kept as they are
      {1008, "SERVO_STATE", Bytes(OldServoNoSampleTime())},
      {1009, "MOCAP_BODY", Bytes(OldMocapNoSampleTime())},
  };
}

TEST_F(LogUpgradeTest, LegacyVersionsKeepTheirFingerprints) {
  // The fingerprints the types had in the commits before each change (lcm-gen's hash of the
  // files at d2866c5^, d2866c5, 27d4812^ and 1faf3aa^): the package does not enter it.
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_batch::ft_sample_t::getHash()), 0x5f4243aab0dd6ae0u);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_batch::contact_wrench_t::getHash()),
            0x583de87b42d4afe3u);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_batch::contact_wrench_sum_t::getHash()),
            0xa52d4535c7b5b8ecu);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_fixed6::servo_state_t::getHash()), 0xc2eb415f7e1dad57u);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_fixed6::sync_sample_t::getHash()), 0x164ced0cb4c0360eu);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_fixed6::steady_pose_t::getHash()), 0x174a56f0bf25af7eu);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_scatter::steady_pose_t::getHash()),
            0xa6ac1ac62db8933du);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_nonce::sequencer_control_t::getHash()),
            0x083817326c7ba930u);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_sample_time::servo_state_t::getHash()),
            kServoStateBeforeSampleTime);
  EXPECT_EQ(static_cast<uint64_t>(ftcal_pre_sample_time::mocap_body_t::getHash()),
            kMocapBodyBeforeSampleTime);
  // And the guard's table (generated by cmake/lcm_wire_schema.py) has each, and no current one.
  EXPECT_EQ(wire::FtcalSchemasLegacy().size(), 10u);
  for (const wire::LegacyVersion& v : wire::FtcalSchemasLegacy()) {
    EXPECT_EQ(wire::FindSchema(v.fingerprint), nullptr) << v.name << " " << v.what;
  }
}

TEST_F(LogUpgradeTest, OlderVersionsBecomeTheCurrentTypesFieldForField) {
  WriteLog(old_, OldLog());
  const Summary summary = UpgradeLog(old_, new_);
  EXPECT_EQ(summary.events, 13);
  EXPECT_EQ(summary.converted, 10);
  const auto out = ReadLog(new_);
  ASSERT_EQ(out.size(), 13u);

  const auto ft = DecodeCurrent<ftcal::ft_batch_t>(out[1]);
  EXPECT_EQ(ft.receipt_utime, 1'700'000'000'000'123);
  EXPECT_EQ(ft.leg, "ML");
  ASSERT_EQ(ft.n, 1);
  EXPECT_EQ(ft.sample_utime[0], 1'700'000'000'000'123);
  EXPECT_EQ(ft.rdt_sequence[0], 4'000'000'001);
  EXPECT_EQ(ft.ft_sequence[0], 77);
  EXPECT_EQ(ft.status[0], 0x20000);
  for (int k = 0; k < 6; ++k) {
    EXPECT_EQ(ft.counts[0][k], -1000 * (k + 1));
    EXPECT_EQ(ft.wrench[0][k], 0.5 * k - 1.25);
  }
  EXPECT_EQ(ft.gap[0], 3);
  EXPECT_EQ(ft.flags[0], ftcal::ft_batch_t::FLAG_GAP | ftcal::ft_batch_t::FLAG_SATURATED);

  const auto servo = DecodeCurrent<ftcal::servo_state_t>(out[2]);
  EXPECT_EQ(servo.utime, 1'700'000'000'000'200);
  EXPECT_EQ(servo.sample_utime, 1'700'000'000'000'200);  // what readers aligned by then
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(servo.leg[i], kLegs[i]);
    EXPECT_EQ(servo.id[i], 11 + i);
    EXPECT_EQ(servo.angle_rad[i], 0.1 * i - 0.2);
    EXPECT_EQ(servo.velocity_rad_s[i], -0.5 * i);
    EXPECT_EQ(servo.current_a[i], 0.01 * i);
    EXPECT_EQ(servo.hardware_error[i], i == 2 ? 4 : 0);
    EXPECT_EQ(servo.device_tick_ms[i], 9'000'000'000LL + i);
    EXPECT_EQ(servo.flags[i], i == 5 ? 9 : 0);
  }

  const auto sync = DecodeCurrent<ftcal::sync_sample_t>(out[4]);
  EXPECT_EQ(sync.utime, 1'700'000'000'000'300);
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(sync.leg[i], kLegs[i]);
    for (int k = 0; k < 6; ++k) EXPECT_EQ(sync.wrench[i][k], i * 10 + k + 0.5);
    EXPECT_EQ(sync.angle_rad[i], -0.3 * i);
  }
  EXPECT_EQ(sync.q_wc[0], 0.5);
  EXPECT_EQ(sync.q_wc[1], -0.5);
  EXPECT_EQ(sync.q_wc[2], 0.5);
  EXPECT_EQ(sync.q_wc[3], 0.5);
  EXPECT_EQ(sync.attitude_ok, 1);
  EXPECT_EQ(sync.markers_ok, 0);
  EXPECT_EQ(sync.flags, 4);

  const auto counted = DecodeCurrent<ftcal::steady_pose_t>(out[5]);
  EXPECT_EQ(counted.utime, 1'700'000'000'000'400);
  EXPECT_EQ(counted.session_id, "s-counted");
  EXPECT_EQ(counted.pose_index, 7);
  EXPECT_EQ(counted.start_utime, 1'699'999'999'000'000);
  EXPECT_EQ(counted.end_utime, 1'700'000'000'000'000);
  EXPECT_EQ(counted.num_samples, 700);
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(counted.leg[i], kLegs[i]);
    for (int k = 0; k < 6; ++k) {
      EXPECT_EQ(counted.wrench[i][k], -i * 10.0 - k);
      EXPECT_TRUE(std::isnan(counted.wrench_sem[i][k]));  // not computed
    }
    EXPECT_EQ(counted.angle_rad[i], 0.25 * i);
  }
  EXPECT_EQ(counted.q_wc[0], 1.0);
  EXPECT_EQ(counted.q_wc[1], 0.0);
  EXPECT_EQ(counted.markers_ok, 1);
  for (double v : counted.attitude_sem_rad) EXPECT_TRUE(std::isnan(v));

  const auto fixed = DecodeCurrent<ftcal::steady_pose_t>(out[6]);
  EXPECT_EQ(fixed.utime, 1'700'000'000'000'450);
  EXPECT_EQ(fixed.session_id, "s-fixed");
  EXPECT_EQ(fixed.pose_index, 8);
  EXPECT_EQ(fixed.start_utime, 1'700'000'000'000'001);
  EXPECT_EQ(fixed.end_utime, 1'700'000'000'000'449);
  EXPECT_EQ(fixed.num_samples, 12);
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(fixed.leg[i], kLegs[5 - i]);
    for (int k = 0; k < 6; ++k) {
      EXPECT_EQ(fixed.wrench[i][k], 1.0 / (1 + i + k));
      EXPECT_TRUE(std::isnan(fixed.wrench_sem[i][k]));
    }
    EXPECT_EQ(fixed.angle_rad[i], -0.125 * i);
  }
  EXPECT_EQ(fixed.q_wc[3], 1.0);
  EXPECT_EQ(fixed.markers_ok, 0);
  for (double v : fixed.attitude_sem_rad) EXPECT_TRUE(std::isnan(v));

  const auto wrench = DecodeCurrent<ftcal::contact_wrench_t>(out[7]);
  EXPECT_EQ(wrench.receipt_utime, 1'700'000'000'000'500);
  EXPECT_EQ(wrench.leg, 4);
  ASSERT_EQ(wrench.n, 1);
  EXPECT_EQ(wrench.utime[0], 1'700'000'000'000'500);
  for (int k = 0; k < 6; ++k) {
    if (k == 2) {
      EXPECT_TRUE(std::isnan(wrench.wrench_w[0][k]));
    } else {
      EXPECT_EQ(wrench.wrench_w[0][k], 10.0 + k);
    }
  }
  EXPECT_EQ(wrench.servo_age_s[0], 0.0125f);
  EXPECT_EQ(wrench.mocap_age_s[0], -1.0f);
  EXPECT_EQ(wrench.flags[0], +ftcal::contact_wrench_t::FLAG_STALE_MOCAP);

  const auto sum = DecodeCurrent<ftcal::contact_wrench_sum_t>(out[8]);
  EXPECT_EQ(sum.calibration_version, 42);
  ASSERT_EQ(sum.n, 1);
  EXPECT_EQ(sum.utime[0], 1'700'000'000'000'600);
  for (int k = 0; k < 6; ++k) {
    EXPECT_EQ(sum.total_w[0][k], 100.0 - k);
    EXPECT_EQ(sum.residual_w[0][k], -0.25 * k);
  }
  EXPECT_EQ(sum.oldest_ft_age_s[0], 0.004f);
  EXPECT_EQ(sum.flags[0], 9);

  const auto control = DecodeCurrent<ftcal::sequencer_control_t>(out[9]);
  EXPECT_EQ(control.utime, 1'700'000'000'000'700);
  EXPECT_EQ(control.action, +ftcal::sequencer_control_t::STOP);
  EXPECT_EQ(control.step, -1);
  EXPECT_EQ(control.nonce, 0);
  EXPECT_EQ(control.note, "operator stop");

  // Before the sample times: sample_utime = the old utime (the completion, the receipt), every
  // other field as it was.
  const auto timed_servo = DecodeCurrent<ftcal::servo_state_t>(out[11]);
  const auto old_servo = OldServoNoSampleTime();
  EXPECT_EQ(timed_servo.utime, old_servo.utime);
  EXPECT_EQ(timed_servo.sample_utime, old_servo.utime);
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(timed_servo.leg[i], old_servo.leg[i]);
    EXPECT_EQ(timed_servo.id[i], old_servo.id[i]);
    EXPECT_EQ(timed_servo.angle_rad[i], old_servo.angle_rad[i]);
    EXPECT_EQ(timed_servo.velocity_rad_s[i], old_servo.velocity_rad_s[i]);
    EXPECT_EQ(timed_servo.current_a[i], old_servo.current_a[i]);
    EXPECT_EQ(timed_servo.hardware_error[i], old_servo.hardware_error[i]);
    EXPECT_EQ(timed_servo.device_tick_ms[i], old_servo.device_tick_ms[i]);
    EXPECT_EQ(timed_servo.flags[i], old_servo.flags[i]);
  }
  const auto mocap = DecodeCurrent<ftcal::mocap_body_t>(out[12]);
  const auto old_mocap = OldMocapNoSampleTime();
  EXPECT_EQ(mocap.utime, old_mocap.utime);
  EXPECT_EQ(mocap.sample_utime, old_mocap.utime);
  EXPECT_EQ(mocap.frame_number, old_mocap.frame_number);
  EXPECT_EQ(mocap.device_utime, old_mocap.device_utime);
  EXPECT_EQ(mocap.body, old_mocap.body);
  EXPECT_EQ(mocap.tracked, old_mocap.tracked);
  for (int i = 0; i < 4; ++i) {
    EXPECT_EQ(mocap.q_wc[i], old_mocap.q_wc[i]);
    EXPECT_EQ(mocap.q_gc[i], old_mocap.q_gc[i]);
  }
  for (int i = 0; i < 3; ++i) EXPECT_EQ(mocap.position_m[i], old_mocap.position_m[i]);
  EXPECT_EQ(mocap.yaw_rad, old_mocap.yaw_rad);
  EXPECT_EQ(mocap.residual_m, old_mocap.residual_m);
  EXPECT_EQ(mocap.num_markers, 2);
  EXPECT_EQ(mocap.marker_m, old_mocap.marker_m);
  EXPECT_EQ(mocap.marker_tracked, old_mocap.marker_tracked);

  EXPECT_EQ(summary.channels.at("FT_ML").converted, 1);
  EXPECT_EQ(summary.channels.at("STEADY_POSE").converted, 2);
  EXPECT_EQ(summary.channels.at("MOCAP_BODY").copied, 1);
  EXPECT_EQ(summary.channels.at("MOCAP_BODY").converted, 1);
  const std::string text = Render(summary, old_, new_);
  EXPECT_NE(text.find("10 of 13 events converted"), std::string::npos) << text;
  EXPECT_NE(text.find("ftcal.ft_sample_t (one record a message"), std::string::npos) << text;
}

TEST_F(LogUpgradeTest, EveryOtherEventIsCopiedByteForByteInItsPlace) {
  const auto in = OldLog();
  WriteLog(old_, in);
  UpgradeLog(old_, new_);
  const auto out = ReadLog(new_);
  ASSERT_EQ(out.size(), in.size());
  for (size_t i = 0; i < in.size(); ++i) {
    EXPECT_EQ(out[i].channel, in[i].channel) << i;
    EXPECT_EQ(out[i].utime, in[i].utime) << i;
  }
  for (size_t i : {0u, 3u, 10u}) EXPECT_EQ(out[i].data, in[i].data) << in[i].channel;
}

TEST_F(LogUpgradeTest, ACurrentLogIsCopiedAndSaidSo) {
  const auto once = OldLog();
  WriteLog(old_, once);
  UpgradeLog(old_, new_);
  const std::string twice = (dir_ / "twice.lcmlog").string();
  const Summary summary = UpgradeLog(new_, twice);
  EXPECT_EQ(summary.converted, 0);
  const auto a = ReadLog(new_);
  const auto b = ReadLog(twice);
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    EXPECT_EQ(a[i].channel, b[i].channel);
    EXPECT_EQ(a[i].utime, b[i].utime);
    EXPECT_EQ(a[i].data, b[i].data);
  }
  EXPECT_NE(Render(summary, new_, twice).find("already current: nothing to convert"),
            std::string::npos);
}

TEST_F(LogUpgradeTest, ADamagedOlderEventIsRefusedNamingItAndNothingIsWritten) {
  auto events = OldLog();
  // The leg name's length (after utime) claims more bytes than the message has.
  std::vector<uint8_t>& ft = events[1].data;
  ft[16] = 0x7f;
  WriteLog(old_, events);
  try {
    UpgradeLog(old_, new_);
    FAIL() << "a damaged ft_sample_t was converted";
  } catch (const RefusedEvent& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("event 1 on FT_ML"), std::string::npos) << what;
    EXPECT_NE(what.find("ftcal.ft_sample_t"), std::string::npos) << what;
    EXPECT_NE(what.find("string past the end"), std::string::npos) << what;
  }
  EXPECT_FALSE(fs::exists(new_));
  EXPECT_EQ(std::distance(fs::directory_iterator(dir_), fs::directory_iterator()), 1)
      << "a temporary file was left";
}

TEST_F(LogUpgradeTest, AServoStateOfFiveServosHasNoCurrentFormAndIsRefused) {
  WriteLog(old_, {{5, "SERVO_STATE", Bytes(OldServo(5))}});
  try {
    UpgradeLog(old_, new_);
    FAIL() << "five servos converted into six";
  } catch (const RefusedEvent& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("event 0 on SERVO_STATE"), std::string::npos) << what;
    EXPECT_NE(what.find("num_servos is 5"), std::string::npos) << what;
  }
  EXPECT_FALSE(fs::exists(new_));
}

TEST_F(LogUpgradeTest, TheProgramExitsTwoOnARefusalAndZeroWhenDone) {
  auto events = OldLog();
  events[2].data.resize(events[2].data.size() - 3);  // SERVO_STATE cut short
  WriteLog(old_, events);
  const std::string cmd = std::string(FTCAL_LOG_UPGRADE) + " '" + old_ + "' '" + new_ + "' 2>'" +
                          (dir_ / "err").string() + "' >/dev/null";
  int status = std::system(cmd.c_str());
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 2);
  std::ifstream err(dir_ / "err");
  const std::string text((std::istreambuf_iterator<char>(err)), std::istreambuf_iterator<char>());
  EXPECT_NE(text.find("event 2 on SERVO_STATE"), std::string::npos) << text;
  EXPECT_FALSE(fs::exists(new_));

  WriteLog(old_, OldLog());
  status = std::system(
      (std::string(FTCAL_LOG_UPGRADE) + " '" + old_ + "' '" + new_ + "' >/dev/null").c_str());
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  EXPECT_TRUE(fs::exists(new_));
}

TEST_F(LogUpgradeTest, AnEnvelopeWithAnOlderInnerMessageIsKeptAsSigned) {
  // Re-encoding the inside would break the signature: the envelope is copied and counted.
  const auto inner = Bytes(OldControl());
  ftcal::signed_envelope_t envelope{};
  envelope.sequence = 7;
  envelope.inner_fingerprint = ftcal_pre_nonce::sequencer_control_t::getHash();
  envelope.size = static_cast<int32_t>(inner.size());
  envelope.payload = inner;
  const Event in{77, "SEQUENCER_CONTROL", Bytes(envelope)};
  WriteLog(old_, {in});
  const Summary summary = UpgradeLog(old_, new_);
  EXPECT_EQ(summary.converted, 0);
  EXPECT_EQ(summary.old_signed, 1);
  EXPECT_EQ(summary.channels.at("SEQUENCER_CONTROL").old_signed, 1);
  const auto out = ReadLog(new_);
  ASSERT_EQ(out.size(), 1u);
  EXPECT_EQ(out[0].data, in.data);
  EXPECT_EQ(out[0].utime, 77);
  EXPECT_NE(Render(summary, old_, new_).find("kept 1 signed envelope"), std::string::npos);
}

TEST_F(LogUpgradeTest, TheGuardsRefusalOfAnOldFtSampleNamesTheCommand) {
  const auto old = Bytes(OldFt());
  const wire::Schema* current =
      wire::FindSchema(static_cast<uint64_t>(ftcal::ft_batch_t::getHash()));
  ASSERT_NE(current, nullptr);
  const auto refused = wire::Check(*current, old.data(), static_cast<int>(old.size()));
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "wrong fingerprint");
  EXPECT_NE(refused->detail.find("ftcal.ft_sample_t"), std::string::npos) << refused->detail;
  EXPECT_NE(refused->detail.find("convert the log with ftcal-log-upgrade OLD NEW"),
            std::string::npos)
      << refused->detail;
  // A fingerprint that is no older version of ftcal's keeps the plain refusal.
  auto other = old;
  other[0] ^= 0xff;
  const auto plain = wire::Check(*current, other.data(), static_cast<int>(other.size()));
  ASSERT_TRUE(plain);
  EXPECT_EQ(plain->detail.find("ftcal-log-upgrade"), std::string::npos) << plain->detail;
}

}  // namespace
}  // namespace ftcal::log_upgrade
