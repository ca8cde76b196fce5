// What ftcal-launch writes for supervisord and systemd, from the shipped configs.
#include "launcher/launch_plan.h"

#include <sys/stat.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "ftcal/config.h"
#include "launcher/supervisor.h"

namespace ftcal::launch {
namespace {

config::Config Shipped(const std::string& name) {
  return LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/" + name);
}

std::vector<std::string> Names(const config::LaunchGroup& g, const std::vector<int>& order) {
  std::vector<std::string> out;
  for (int i : order) out.push_back(g.process(i).name());
  return out;
}

TEST(LaunchPlan, StartOrderPutsEveryProcessAfterWhatItWaitsFor) {
  for (const char* file : {"sim.pbtxt", "bigant.pbtxt"}) {
    const auto config = Shipped(file);
    for (const auto& g : config.launch().group()) {
      const auto names = Names(g, StartOrder(g));
      ASSERT_EQ(names.size(), static_cast<size_t>(g.process_size()));
      for (const auto& p : g.process()) {
        const auto at = std::find(names.begin(), names.end(), p.name());
        for (const auto& dep : p.after()) {
          EXPECT_LT(std::find(names.begin(), names.end(), dep), at) << file << ": " << p.name();
        }
      }
    }
  }
  // Hand-checked: the config's order among the free ones.
  const auto sim = Shipped("sim.pbtxt");
  EXPECT_EQ(
      Names(sim.launch().group(0), StartOrder(sim.launch().group(0))),
      (std::vector<std::string>{"recorder", "twin", "ati-bridge", "dynamixel-bridge",
                                "mocap-bridge", "segmenter", "calibrator", "corrector", "drift"}));
}

TEST(LaunchPlan, GroupConfHasEveryProgramOfTheHostWithItsPolicyAndNoHttpServer) {
  const auto config = Shipped("bigant.pbtxt");
  const auto& g = FindGroup(config.launch(), "lab");
  Placeholders v{"/r/config.pbtxt", "/r", config.lcm_url()};
  const std::string robot = GroupConf(config, g, "robot", v, {"ftcal-supervisor-events"});
  EXPECT_NE(
      robot.find(
          "[program:ati-bridge]\ncommand=ftcal-ati-bridge --config /r/config.pbtxt --realtime\n"),
      std::string::npos)
      << robot;
  EXPECT_NE(robot.find("autostart=false\nautorestart=true\nstartsecs=2\nstartretries=3\n"),
            std::string::npos)
      << robot;
  EXPECT_EQ(robot.find("[program:segmenter]"), std::string::npos)
      << "segmenter is the workstation's";
  EXPECT_NE(robot.find("programs=recorder,ati-bridge,dynamixel-bridge,mocap-bridge\n"),
            std::string::npos)
      << robot;
  // The LCM URL goes into shlex as one word, and '%' would be supervisor's expansion.
  EXPECT_NE(robot.find("'udpm://239.255.76.67:7667?ttl=1'"), std::string::npos) << robot;
  const std::string sup = SupervisordConf("robot", "/r");
  EXPECT_NE(sup.find("[unix_http_server]\nfile=/r/supervisor.sock\nchmod=0700\n"),
            std::string::npos);
  EXPECT_EQ(sup.find("\n[inet_http_server]"), std::string::npos) << "no HTTP control server";
}

TEST(LaunchPlan, ExpandRefusesAnUnknownPlaceholderNamingWhere) {
  Placeholders v{"/c", "/r", "udpm://x"};
  EXPECT_EQ(Expand("${run_dir}/a-${config}", v, "here"), "/r/a-/c");
  try {
    Expand("${home}/x", v, "launch.group[sim].process[twin].args[1]");
    FAIL();
  } catch (const LaunchError& e) {
    EXPECT_NE(std::string(e.what()).find("launch.group[sim].process[twin].args[1]: '${home}/x': "
                                         "unknown ${home}"),
              std::string::npos)
        << e.what();
  }
}

TEST(LaunchPlan, SystemdUnitCarriesRestartWatchdogAndMemory) {
  const auto config = Shipped("bigant.pbtxt");
  const auto& g = FindGroup(config.launch(), "lab");
  Placeholders v{"/etc/ftcal/lab.pbtxt", "%t/ftcal", config.lcm_url()};
  const std::string unit = SystemdUnit(config, g, *FindProcess(g, "ati-bridge"), v);
  for (const char* line :
       {"Type=notify\n", "Restart=always\n", "WatchdogSec=5\n", "MemoryMax=256M\n",
        "StartLimitBurst=4\n", "KillSignal=SIGTERM\n",
        "ExecStart=ftcal-ati-bridge --config /etc/ftcal/lab.pbtxt --realtime\n"}) {
    EXPECT_NE(unit.find(line), std::string::npos) << line << " in\n" << unit;
  }
  // ftcal-record is a ServiceApp: READY=1 and the watchdog fed by its heartbeat (Type=notify),
  // where lcm-logger was Type=simple with no watchdog.
  const std::string recorder = SystemdUnit(config, g, *FindProcess(g, "recorder"), v);
  EXPECT_NE(recorder.find("Type=notify\n"), std::string::npos) << recorder;
  EXPECT_NE(recorder.find("WatchdogSec="), std::string::npos) << recorder;
  const std::string seq = SystemdUnit(config, g, *FindProcess(g, "sequencer"), v);
  EXPECT_NE(seq.find("Restart=no\n"), std::string::npos) << seq;
}

// Issue 36, finding 10: the exported units ran as root, and /run/ftcal was 0755.
TEST(LaunchPlan, SystemdUnitRunsAsADedicatedUserWithPrivateDirectories) {
  const auto config = Shipped("bigant.pbtxt");
  const auto& g = FindGroup(config.launch(), "lab");
  Placeholders v{"/etc/ftcal/lab.pbtxt", "%t/ftcal", config.lcm_url()};
  for (const auto& p : g.process()) {
    const std::string unit = SystemdUnit(config, g, p, v);
    for (const char* line : {"\nUser=ftcal\n", "\nGroup=ftcal\n", "\nRuntimeDirectory=ftcal\n",
                             "\nRuntimeDirectoryMode=0700\n", "\nStateDirectory=ftcal\n",
                             "\nStateDirectoryMode=0700\n"}) {
      EXPECT_NE(unit.find(line), std::string::npos) << p.name() << ": " << line << " in\n" << unit;
    }
    EXPECT_EQ(unit.find("User=root"), std::string::npos) << unit;
  }
  const auto& p = *FindProcess(g, "corrector");
  EXPECT_NE(SystemdUnit(config, g, p, v, "ftcal-lab").find("\nUser=ftcal-lab\n"),
            std::string::npos);
  for (const char* bad : {"root", "", "Ftcal", "a b", "x;rm"}) {
    EXPECT_THROW(SystemdUnit(config, g, p, v, bad), LaunchError) << bad;
  }
}

}  // namespace
}  // namespace ftcal::launch

namespace ftcal::launch {
namespace {

TEST(LaunchPlan, WavesStartTogetherWhatWaitsForNothingInEachOther) {
  const auto sim = Shipped("sim.pbtxt");
  const auto& g = sim.launch().group(0);
  std::vector<std::vector<std::string>> names;
  for (const auto& wave : StartWaves(g)) names.push_back(Names(g, wave));
  EXPECT_EQ(names, (std::vector<std::vector<std::string>>{
                       {"recorder", "twin"},
                       {"ati-bridge", "dynamixel-bridge", "mocap-bridge"},
                       {"segmenter"},
                       {"calibrator", "corrector", "drift"}}));
}

}  // namespace
}  // namespace ftcal::launch

// ---- issue 36, finding 3: the run dir ----

namespace ftcal::launch {
namespace {

class RunDirTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char tmpl[] = "/tmp/ftcal_rundir_test.XXXXXX";
    ASSERT_NE(::mkdtemp(tmpl), nullptr);
    base_ = tmpl;
  }
  void TearDown() override { std::filesystem::remove_all(base_); }
  // What HostSupervisor::run_dir() says of `spec` on this host (sh -c): the directory, or the
  // refusal.
  std::string RunDir(const std::string& spec, bool* refused) {
    HostSupervisor hs("local", {}, spec);
    try {
      *refused = false;
      return hs.run_dir();
    } catch (const LaunchError& e) {
      *refused = true;
      return e.what();
    }
  }
  std::string base_;
};

TEST_F(RunDirTest, ItIsMadeWithMode0700) {
  bool refused = true;
  const std::string dir = RunDir(base_ + "/a/run", &refused);
  ASSERT_FALSE(refused) << dir;
  EXPECT_EQ(dir, base_ + "/a/run");
  struct stat st {};
  ASSERT_EQ(::stat(dir.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 07777, 0700u);
  EXPECT_EQ(st.st_uid, ::geteuid());
  // Made before by this user in the same way: used again.
  EXPECT_EQ(RunDir(base_ + "/a/run", &refused), dir);
  EXPECT_FALSE(refused);
}

TEST_F(RunDirTest, OneOpenToOthersIsRefusedNamingPathOwnerAndMode) {
  const std::string dir = base_ + "/open";
  ASSERT_EQ(::mkdir(dir.c_str(), 0700), 0);
  ASSERT_EQ(::chmod(dir.c_str(), 0755), 0);
  bool refused = false;
  const std::string what = RunDir(dir, &refused);
  ASSERT_TRUE(refused) << what;
  EXPECT_NE(what.find("run dir '" + dir + "' is owned by uid " + std::to_string(::geteuid())),
            std::string::npos)
      << what;
  EXPECT_NE(what.find("with mode 755"), std::string::npos) << what;
}

TEST_F(RunDirTest, OneOfAnotherUserIsRefusedNamingTheOwner) {
  // The fallback /tmp/ftcal-launch-UID made first by someone else. As root, a directory given to
  // nobody; otherwise one that root owns.
  std::string dir = "/";
  uid_t owner = 0;
  if (::geteuid() == 0) {
    dir = base_ + "/theirs";
    owner = 65534;
    ASSERT_EQ(::mkdir(dir.c_str(), 0700), 0);
    ASSERT_EQ(::chown(dir.c_str(), owner, owner), 0);
  }
  bool refused = false;
  const std::string what = RunDir(dir, &refused);
  ASSERT_TRUE(refused) << what;
  EXPECT_NE(what.find("run dir '" + dir + "' is owned by uid " + std::to_string(owner)),
            std::string::npos)
      << what;
  EXPECT_NE(what.find("with mode "), std::string::npos) << what;
}

TEST_F(RunDirTest, ASymbolicLinkIsRefused) {
  const std::string dir = base_ + "/real";
  ASSERT_EQ(::mkdir(dir.c_str(), 0700), 0);
  ASSERT_EQ(::symlink(dir.c_str(), (base_ + "/link").c_str()), 0);
  bool refused = false;
  const std::string what = RunDir(base_ + "/link", &refused);
  ASSERT_TRUE(refused) << what;
  EXPECT_NE(what.find("is not a directory of its own"), std::string::npos) << what;
}

}  // namespace
}  // namespace ftcal::launch
