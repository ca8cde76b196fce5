// What ftcal-launch writes for supervisord and systemd, from the shipped configs.
#include "launcher/launch_plan.h"

#include <gtest/gtest.h>

#include <fstream>
#include <sstream>

#include "ftcal/config.h"

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
  EXPECT_EQ(Names(sim.launch().group(0), StartOrder(sim.launch().group(0))),
            (std::vector<std::string>{"recorder", "twin", "ati-bridge", "dynamixel-bridge",
                                      "mocap-bridge", "segmenter", "calibrator", "corrector"}));
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
                       {"calibrator", "corrector"}}));
}

}  // namespace
}  // namespace ftcal::launch
