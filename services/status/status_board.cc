#include "status/status_board.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "common/heartbeat.h"
#include "status/table_text.h"

namespace ftcal {
namespace {

std::string Printf(const char* format, double value) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), format, value);
  return buf;
}

std::string FormatDuration(double s) {
  if (!std::isfinite(s) || s < 0) return "?";
  if (s < 60) return Printf("%.1fs", s);
  const auto total = static_cast<int64_t>(s);
  const auto two_digits = [](int64_t v) { return (v < 10 ? "0" : "") + std::to_string(v); };
  if (s < 3600) return std::to_string(total / 60) + "m" + two_digits(total % 60) + "s";
  return std::to_string(total / 3600) + "h" + two_digits(total % 3600 / 60) + "m";
}

std::string Counters(const service_status_t& status) {
  std::string out;
  const size_t n = std::min<size_t>({static_cast<size_t>(std::max(status.num_counters, 0)),
                                     status.counter_name.size(), status.counter_value.size()});
  for (size_t i = 0; i < n; ++i) {
    if (!out.empty()) out += ' ';
    out += Printable(status.counter_name[i]) + "=" + std::to_string(status.counter_value[i]);
  }
  return out;
}

}  // namespace

StatusBoard::StatusBoard(double lost_after_s) : lost_after_s_(lost_after_s) {
  if (!(lost_after_s > 0)) throw std::invalid_argument("lost_after_s must be > 0");
}

void StatusBoard::Update(const service_status_t& status, int64_t received_utime) {
  latest_[Key{status.name, status.host, status.pid}] = Entry{status, received_utime};
}

std::vector<StatusBoard::Row> StatusBoard::Rows(int64_t now_utime) const {
  std::vector<Row> rows;
  rows.reserve(latest_.size());
  for (const auto& [key, entry] : latest_) {
    const double age_s = static_cast<double>(now_utime - entry.received_utime) * 1e-6;
    std::string shown = ServiceStateName(entry.status.state);
    if (age_s > lost_after_s_) {
      shown = entry.status.state == service_status_t::STOPPING ? "STOPPED" : "LOST";
    }
    rows.push_back({entry.status, entry.received_utime, age_s, shown});
  }
  return rows;  // std::map keeps them sorted by name, host, pid
}

std::string StatusBoard::Render(int64_t now_utime) const {
  // COUNTERS last: a bridge's run to a few hundred characters, and a column that wide before
  // another pads every row to it.
  const std::vector<std::string> header = {"NAME",   "HOST", "PID",        "STATE",
                                           "UPTIME", "IN",   "OUT",        "DROPS",
                                           "ERRORS", "AGE",  "LAST ERROR", "COUNTERS"};
  std::vector<std::vector<std::string>> cells = {header};
  for (const Row& row : Rows(now_utime)) {
    const service_status_t& s = row.status;
    cells.push_back({Printable(s.name), Printable(s.host), std::to_string(s.pid), row.shown_state,
                     FormatDuration(s.uptime_s), std::to_string(s.msgs_in),
                     std::to_string(s.msgs_out), std::to_string(s.drops), std::to_string(s.errors),
                     FormatDuration(row.age_s), Printable(s.last_error), Counters(s)});
  }
  std::string out = AlignColumns(cells);
  if (latest_.empty()) out += "(no heartbeats yet)\n";
  return out;
}

}  // namespace ftcal
