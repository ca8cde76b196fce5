#include "ftcal/calibration_io.h"

#include <gtest/gtest.h>

#include <csignal>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include <sys/resource.h>
#include <sys/stat.h>
#include <unistd.h>

#include <google/protobuf/util/message_differencer.h>

#include "ftcal/config.h"

namespace ftcal {
namespace {

namespace fs = std::filesystem;

#define EXPECT_CONTAINS(haystack, needle) \
  EXPECT_NE(std::string(haystack).find(needle), std::string::npos) << "in: " << (haystack)

config::Robot SimRobot() {
  return LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt").robot();
}

RobotCalibration RandomCalibration(std::mt19937& rng, const config::Robot& robot) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  // -> Vec3: returning the Eigen expression would refer to a temporary that is gone.
  auto vec = [&](double scale) -> Vec3 { return Vec3(u(rng), u(rng), u(rng)) * scale; };
  RobotCalibration cal;
  cal.X_B_ft = NominalTransducerPoses(robot);
  cal.g0 = 9.80665 + 0.01 * u(rng);
  cal.total_mass_kg = 8.0 + u(rng);
  cal.p_C_B = vec(0.02);
  for (LegCalibration& l : cal.leg) {
    l.offset << vec(5.0), vec(0.3);
    l.weight_n = 4.0 + u(rng);
    l.com.x = {0.01 * u(rng), M_PI * u(rng), 0.02 * u(rng)};
    l.com.y = 0.01 * u(rng);
    l.com.z = {0.01 * u(rng), M_PI * u(rng), -0.05 + 0.01 * u(rng)};
    // Mounting tilts of a few degrees, and one large one to exercise the quaternion sign.
    l.R_tilde = ExpSO3(vec(0.1));
    l.p_tilde_prime = vec(0.02);
  }
  cal.leg[3].R_tilde = ExpSO3(Vec3(0.3, -0.2, 0.9).normalized() * 3.0);
  return cal;
}

void ExpectSameCalibration(const RobotCalibration& a, const RobotCalibration& b, double tol) {
  EXPECT_NEAR(a.g0, b.g0, tol);
  EXPECT_NEAR(a.total_mass_kg, b.total_mass_kg, tol);
  EXPECT_NEAR((a.p_C_B - b.p_C_B).norm(), 0.0, tol);
  for (int k = 0; k < kNumLegs; ++k) {
    SCOPED_TRACE(kLegNames[k]);
    const LegCalibration& x = a.leg[k];
    const LegCalibration& y = b.leg[k];
    EXPECT_NEAR((x.offset - y.offset).norm(), 0.0, tol);
    EXPECT_NEAR(x.weight_n, y.weight_n, tol);
    EXPECT_NEAR(x.com.x.a, y.com.x.a, tol);
    EXPECT_NEAR(x.com.x.c, y.com.x.c, tol);
    EXPECT_NEAR(x.com.x.d, y.com.x.d, tol);
    EXPECT_NEAR(x.com.y, y.com.y, tol);
    EXPECT_NEAR(x.com.z.a, y.com.z.a, tol);
    EXPECT_NEAR(x.com.z.c, y.com.z.c, tol);
    EXPECT_NEAR(x.com.z.d, y.com.z.d, tol);
    EXPECT_NEAR((x.R_tilde - y.R_tilde).norm(), 0.0, tol);
    EXPECT_NEAR((x.p_tilde_prime - y.p_tilde_prime).norm(), 0.0, tol);
    EXPECT_NEAR((a.X_B_ft[k].Matrix() - b.X_B_ft[k].Matrix()).norm(), 0.0, tol);
  }
}

class TempDir {
 public:
  TempDir() {
    std::string templ = (fs::temp_directory_path() / "ftcal_calio_XXXXXX").string();
    std::vector<char> buf(templ.begin(), templ.end());
    buf.push_back('\0');
    if (::mkdtemp(buf.data()) == nullptr) throw std::runtime_error("mkdtemp failed");
    path_ = buf.data();
  }
  ~TempDir() {
    std::error_code ec;
    fs::permissions(path_, fs::perms::owner_all, fs::perm_options::add, ec);
    fs::remove_all(path_, ec);
  }
  const fs::path& path() const { return path_; }
  std::vector<std::string> Entries() const {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(path_)) names.push_back(e.path().filename());
    return names;
  }

 private:
  fs::path path_;
};

std::string ReadFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

std::string ErrorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

TEST(CalibrationIo, ProtoRoundTripOfRandomCalibrations) {
  const config::Robot robot = SimRobot();
  std::mt19937 rng(20261122);
  for (int trial = 0; trial < 50; ++trial) {
    const RobotCalibration cal = RandomCalibration(rng, robot);
    calibration::Calibration proto;
    FillCalibrationValues(cal, &proto);
    ASSERT_EQ(proto.leg_size(), kNumLegs);
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_EQ(proto.leg(k).name(), kLegNames[k]);
      // p~ is stored too; it must be eq. R~ p~' - p^C_B (independent of the reader).
      const auto& pt = proto.leg(k).mounting().p_tilde_m();
      const Vec3 expected = cal.leg[k].R_tilde * cal.leg[k].p_tilde_prime - cal.p_C_B;
      EXPECT_NEAR((Vec3(pt.x(), pt.y(), pt.z()) - expected).norm(), 0.0, 1e-15);
    }
    ExpectSameCalibration(cal, CalibrationFromProto(proto, robot), 1e-12);
  }
}

TEST(CalibrationIo, FillKeepsSigmasOfMatchingLegs) {
  const config::Robot robot = SimRobot();
  std::mt19937 rng(7);
  calibration::Calibration proto;
  FillCalibrationValues(RandomCalibration(rng, robot), &proto);
  proto.mutable_leg(2)->mutable_force_offset_n()->set_sigma_x(0.125);
  const RobotCalibration second = RandomCalibration(rng, robot);
  FillCalibrationValues(second, &proto);
  EXPECT_EQ(proto.leg(2).force_offset_n().sigma_x(), 0.125);
  EXPECT_EQ(proto.leg(2).force_offset_n().x(), second.leg[2].offset[0]);
}

TEST(CalibrationIo, FileRoundTripIsExact) {
  const config::Robot robot = SimRobot();
  std::mt19937 rng(99);
  TempDir dir;
  const fs::path file = dir.path() / "cal.pbtxt";
  for (int trial = 0; trial < 10; ++trial) {
    const RobotCalibration cal = RandomCalibration(rng, robot);
    calibration::Calibration proto;
    proto.set_robot_name("bigant-sim");
    proto.set_model(calibration::FULL);
    proto.mutable_provenance()->set_config_sha256(Sha256Hex("config"));
    FillCalibrationValues(cal, &proto);
    WriteCalibrationFile(proto, file.string());
    const calibration::Calibration read = ReadCalibrationFile(file.string());
    // Text format prints doubles with round-trip precision: the read-back is identical.
    EXPECT_TRUE(google::protobuf::util::MessageDifferencer::Equals(proto, read));
    ExpectSameCalibration(cal, CalibrationFromProto(read, robot), 1e-12);
  }
}

TEST(CalibrationIo, AtomicWriteLeavesOnlyTheTarget) {
  TempDir dir;
  const fs::path file = dir.path() / "out.txt";
  WriteFileAtomic(file.string(), "first");
  WriteFileAtomic(file.string(), "second, longer");
  EXPECT_EQ(ReadFile(file), "second, longer");
  EXPECT_EQ(dir.Entries(), std::vector<std::string>{"out.txt"});
  struct stat st {};
  ASSERT_EQ(::stat(file.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0644u);
}

TEST(CalibrationIo, WriteIntoMissingDirectoryThrowsNamingPath) {
  TempDir dir;
  const fs::path file = dir.path() / "no_such_dir" / "cal.pbtxt";
  const std::string e = ErrorOf([&] { WriteFileAtomic(file.string(), "x"); });
  EXPECT_CONTAINS(e, file.string());
  EXPECT_CONTAINS(e, "No such file or directory");
  EXPECT_FALSE(fs::exists(file));
  // A parent that is a regular file.
  WriteFileAtomic((dir.path() / "plain").string(), "x");
  const std::string e2 =
      ErrorOf([&] { WriteFileAtomic((dir.path() / "plain" / "cal.pbtxt").string(), "x"); });
  EXPECT_CONTAINS(e2, "Not a directory");
}

// A write that fails half-way (here: the file-size limit, EFBIG) must leave the old file as it
// was and no temporary file behind. This works for root too, unlike a read-only directory.
TEST(CalibrationIo, FailedWriteKeepsOldFileAndRemovesTemp) {
  TempDir dir;
  const fs::path file = dir.path() / "cal.pbtxt";
  WriteFileAtomic(file.string(), "old contents");

  rlimit old_limit{};
  ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &old_limit), 0);
  rlimit small = old_limit;
  small.rlim_cur = 4096;
  // Without this the kernel ends the process with SIGXFSZ instead of failing the write.
  const auto old_handler = std::signal(SIGXFSZ, SIG_IGN);
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &small), 0);
  const std::string e = ErrorOf([&] { WriteFileAtomic(file.string(), std::string(1 << 20, 'n')); });
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &old_limit), 0);
  std::signal(SIGXFSZ, old_handler);

  EXPECT_CONTAINS(e, file.string());
  EXPECT_CONTAINS(e, "write: File too large");
  EXPECT_EQ(ReadFile(file), "old contents");
  EXPECT_EQ(dir.Entries(), std::vector<std::string>{"cal.pbtxt"});
}

TEST(CalibrationIo, UnwritableDirectoryThrowsAndKeepsOldFile) {
  if (::geteuid() == 0) GTEST_SKIP() << "root ignores directory permissions";
  TempDir dir;
  const fs::path file = dir.path() / "cal.pbtxt";
  WriteFileAtomic(file.string(), "old contents");
  fs::permissions(dir.path(), fs::perms::owner_read | fs::perms::owner_exec);
  const std::string e = ErrorOf([&] { WriteFileAtomic(file.string(), "new"); });
  fs::permissions(dir.path(), fs::perms::owner_all);
  EXPECT_CONTAINS(e, file.string());
  EXPECT_CONTAINS(e, "Permission denied");
  EXPECT_EQ(ReadFile(file), "old contents");
  EXPECT_EQ(dir.Entries(), std::vector<std::string>{"cal.pbtxt"});
}

TEST(CalibrationIo, MismatchedLegNamesRefused) {
  const config::Robot robot = SimRobot();
  std::mt19937 rng(3);
  calibration::Calibration proto;
  FillCalibrationValues(RandomCalibration(rng, robot), &proto);
  proto.mutable_leg(0)->set_name("ML");
  proto.mutable_leg(1)->set_name("HL");
  const std::string e = ErrorOf([&] { CalibrationFromProto(proto, robot); });
  EXPECT_CONTAINS(e, "leg[0].name: leg 'ML' where the config has 'HL'");

  proto.mutable_leg()->RemoveLast();
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(proto, robot); }), "expected 6 legs, got 5");
}

TEST(CalibrationIo, BadValuesNamed) {
  const config::Robot robot = SimRobot();
  std::mt19937 rng(5);
  calibration::Calibration good;
  FillCalibrationValues(RandomCalibration(rng, robot), &good);
  ASSERT_EQ(ErrorOf([&] { CalibrationFromProto(good, robot); }), "");

  calibration::Calibration p = good;
  p.mutable_leg(2)->mutable_mounting()->set_quaternion_wxyz(0, 0.5);
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(p, robot); }),
                  "leg[2].mounting.quaternion_wxyz: not a unit quaternion");

  p = good;
  p.mutable_leg(4)->mutable_torque_offset_nm()->set_y(std::nan(""));
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(p, robot); }),
                  "leg[4].torque_offset_nm.y: not a finite number");

  p = good;
  p.mutable_leg(1)->mutable_com()->mutable_z()->clear_d_m();
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(p, robot); }), "leg[1].com.z.d_m: missing");

  p = good;
  p.mutable_leg(5)->clear_mounting();
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(p, robot); }), "leg[5].mounting: missing");

  p = good;
  p.mutable_leg(0)->mutable_mounting()->mutable_rotation_vector_deg()->set_x(
      p.leg(0).mounting().rotation_vector_deg().x() + 0.5);
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(p, robot); }),
                  "leg[0].mounting.rotation_vector_deg: disagrees with quaternion_wxyz");
}

TEST(CalibrationIo, ReadErrorsHaveLineAndColumn) {
  TempDir dir;
  const fs::path file = dir.path() / "bad.pbtxt";
  WriteFileAtomic(file.string(), "robot_name: \"x\"\nleg {\n  name: \"HL\"\n  weight: 3\n}\n");
  const std::string e = ErrorOf([&] { ReadCalibrationFile(file.string()); });
  EXPECT_CONTAINS(e, file.string() + ":4:");
  EXPECT_CONTAINS(e, "weight");
  EXPECT_CONTAINS(ErrorOf([&] { ReadCalibrationFile((dir.path() / "none").string()); }),
                  "No such file or directory");
}

}  // namespace
}  // namespace ftcal

namespace ftcal {
namespace {

// The servo delay (calibration.proto Latencies): written when applied, read back; a file
// without it (every file before it existed) applies none; an absurd one is refused by name.
TEST(CalibrationIo, ServoDelayRoundTripsAndIsZeroWhenAbsent) {
  const config::Robot robot = SimRobot();
  std::mt19937 rng(8);
  RobotCalibration cal = RandomCalibration(rng, robot);
  calibration::Calibration proto;
  FillCalibrationValues(cal, &proto);
  EXPECT_FALSE(proto.has_latencies()) << "no delay, no field: the file reads as before";
  EXPECT_EQ(CalibrationFromProto(proto, robot).servo_delay_s, 0.0);

  cal.servo_delay_s = 0.0157;
  FillCalibrationValues(cal, &proto);
  EXPECT_EQ(proto.latencies().applied_servo_delay_s(), 0.0157);
  EXPECT_EQ(CalibrationFromProto(proto, robot).servo_delay_s, 0.0157);

  proto.mutable_latencies()->set_applied_servo_delay_s(16.0);  // ms taken for s
  EXPECT_CONTAINS(ErrorOf([&] { CalibrationFromProto(proto, robot); }),
                  "latencies.applied_servo_delay_s");
}

}  // namespace
}  // namespace ftcal
