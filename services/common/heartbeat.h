// The 1 Hz FTCAL_STATUS heartbeat every process publishes (lcmtypes/service_status_t.lcm).
#pragma once

#include <cstdint>
#include <string>

#include "common/service_stats.h"
#include "ftcal/service_status_t.hpp"

namespace ftcal {

struct ProcessIdentity {
  std::string name;
  std::string host;
  int64_t pid = 0;
};

// This process: `name`, gethostname(), getpid().
ProcessIdentity ThisProcess(const std::string& name);

// The heartbeat message for the given identity, state and counters at `utime`.
service_status_t MakeServiceStatus(const ProcessIdentity& identity, int8_t state, double uptime_s,
                                   const ServiceStats& stats, int64_t utime);

// "STARTING", "RUNNING", ... or "STATE(<n>)" for a value the type does not define.
std::string ServiceStateName(int8_t state);

}  // namespace ftcal
