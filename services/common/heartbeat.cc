#include "common/heartbeat.h"

#include <unistd.h>

#include <climits>

namespace ftcal {

ProcessIdentity ThisProcess(const std::string& name) {
  char host[HOST_NAME_MAX + 1] = {};
  if (::gethostname(host, sizeof(host) - 1) != 0) host[0] = '\0';
  return {name, host, static_cast<int64_t>(::getpid())};
}

service_status_t MakeServiceStatus(const ProcessIdentity& identity, int8_t state, double uptime_s,
                                   const ServiceStats& stats, int64_t utime) {
  service_status_t msg;
  msg.utime = utime;
  msg.name = identity.name;
  msg.host = identity.host;
  msg.pid = identity.pid;
  msg.state = state;
  msg.uptime_s = uptime_s;
  msg.msgs_in = stats.msgs_in();
  msg.msgs_out = stats.msgs_out();
  msg.drops = stats.drops();
  msg.errors = stats.errors();
  msg.last_error = stats.last_error();
  msg.num_counters = static_cast<int32_t>(stats.counters().size());
  for (const auto& [name, value] : stats.counters()) {
    msg.counter_name.push_back(name);
    msg.counter_value.push_back(value);
  }
  return msg;
}

std::string ServiceStateName(int8_t state) {
  switch (state) {
    case service_status_t::STARTING:
      return "STARTING";
    case service_status_t::RUNNING:
      return "RUNNING";
    case service_status_t::DEGRADED:
      return "DEGRADED";
    case service_status_t::STOPPING:
      return "STOPPING";
    case service_status_t::FAILED:
      return "FAILED";
    default:
      return "STATE(" + std::to_string(static_cast<int>(state)) + ")";
  }
}

}  // namespace ftcal
