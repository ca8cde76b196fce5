// The table ftcal-status shows: the latest heartbeat of every process on the bus.
//
// A process is keyed by (host, pid, name), so a restarted process appears as a new row and the
// old one goes LOST. A row whose last heartbeat is older than `lost_after_s` is shown as LOST,
// or STOPPED when that last heartbeat said STOPPING (it said goodbye). Ages are measured on this
// host's clock from when each heartbeat was received, so clock skew between hosts does not
// matter.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <tuple>
#include <vector>

#include "ftcal/service_status_t.hpp"

namespace ftcal {

class StatusBoard {
 public:
  explicit StatusBoard(double lost_after_s = 3.0);

  void Update(const service_status_t& status, int64_t received_utime);

  struct Row {
    service_status_t status;
    int64_t received_utime;
    double age_s;
    std::string shown_state;  // RUNNING, ..., or LOST / STOPPED when silent
  };
  // Rows sorted by name, host, pid, as of `now_utime`.
  std::vector<Row> Rows(int64_t now_utime) const;
  // The table as text, one line per process under a header line.
  std::string Render(int64_t now_utime) const;
  size_t size() const { return latest_.size(); }

 private:
  using Key = std::tuple<std::string, std::string, int64_t>;  // name, host, pid
  struct Entry {
    service_status_t status;
    int64_t received_utime;
  };
  double lost_after_s_;
  std::map<Key, Entry> latest_;
};

}  // namespace ftcal
