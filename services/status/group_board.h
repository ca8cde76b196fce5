// The process-group table ftcal-status shows beside the heartbeats: every process of the
// config's launch groups, with its host's supervisor state and restart count (from the event
// listeners' PROCESS_STATE), its heartbeat state, output rate and last error (FTCAL_STATUS), and
// SILENT when a process the config launches sends no heartbeat.
//
// A heartbeat belongs to a launched process by pid when a PROCESS_STATE said which pid runs
// it; before that (ftcal-status started after the group), by heartbeat name when exactly one
// process of the config has that name.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <tuple>
#include <vector>

#include "ftcal/process_state_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "proto/config.pb.h"

namespace ftcal {

class GroupBoard {
 public:
  GroupBoard(const config::Launch& launch, double lost_after_s);

  void Update(const process_state_t& state, int64_t received_utime);
  void Update(const service_status_t& status, int64_t received_utime);

  struct Row {
    std::string host, group, name;
    std::string supervisor_state;  // "?" when no event heard yet
    int64_t pid = 0;
    int32_t restarts = 0;
    std::string heartbeat;  // RUNNING ... or SILENT, "-" for a process that sends none
    double out_per_s = -1;  // from the last two heartbeats; -1 unknown
    std::string last_error;
  };
  std::vector<Row> Rows(int64_t now_utime) const;
  std::string Render(int64_t now_utime) const;

 private:
  struct Beat {
    service_status_t status;
    int64_t received_utime;
    double out_per_s = -1;
  };
  const Beat* BeatFor(const config::LaunchProcess& p, int64_t pid) const;

  config::Launch launch_;
  double lost_after_s_;
  std::map<std::tuple<std::string, std::string, std::string>, process_state_t>
      states_;                                             // host, group, name
  std::map<std::pair<std::string, int64_t>, Beat> beats_;  // name, pid
};

}  // namespace ftcal
