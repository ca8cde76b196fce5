#include "status/group_board.h"

#include <algorithm>
#include <cstdio>

#include "common/heartbeat.h"
#include "status/table_text.h"

namespace ftcal {
namespace {

std::string StatusNameOf(const config::LaunchProcess& p) {
  if (p.status_name() == "-") return "";
  if (!p.status_name().empty()) return p.status_name();
  const auto slash = p.command().rfind('/');
  return slash == std::string::npos ? p.command() : p.command().substr(slash + 1);
}

}  // namespace

GroupBoard::GroupBoard(const config::Launch& launch, double lost_after_s)
    : launch_(launch), lost_after_s_(lost_after_s) {}

void GroupBoard::Update(const process_state_t& state, int64_t /*received_utime*/) {
  states_[{state.host, state.group, state.name}] = state;
}

void GroupBoard::Update(const service_status_t& status, int64_t received_utime) {
  Beat& b = beats_[{status.name, status.pid}];
  if (b.received_utime > 0 && status.utime > b.status.utime) {
    b.out_per_s = static_cast<double>(status.msgs_out - b.status.msgs_out) /
                  (static_cast<double>(status.utime - b.status.utime) * 1e-6);
  }
  b.status = status;
  b.received_utime = received_utime;
}

const GroupBoard::Beat* GroupBoard::BeatFor(const config::LaunchProcess& p, int64_t pid) const {
  const std::string name = StatusNameOf(p);
  if (pid > 0) {
    const auto it = beats_.find({name, pid});
    return it == beats_.end() ? nullptr : &it->second;
  }
  int launched_with_name = 0;
  for (const auto& g : launch_.group()) {
    for (const auto& q : g.process()) launched_with_name += StatusNameOf(q) == name;
  }
  if (launched_with_name != 1) return nullptr;
  const Beat* newest = nullptr;
  for (const auto& [key, beat] : beats_) {
    if (key.first == name && (!newest || beat.received_utime > newest->received_utime))
      newest = &beat;
  }
  return newest;
}

std::vector<GroupBoard::Row> GroupBoard::Rows(int64_t now_utime) const {
  std::vector<Row> rows;
  for (const auto& g : launch_.group()) {
    for (const auto& p : g.process()) {
      Row r;
      r.host = p.host();
      r.group = g.name();
      r.name = p.name();
      const auto st = states_.find({p.host(), g.name(), p.name()});
      r.supervisor_state = st == states_.end() ? "?" : st->second.to_state;
      if (st != states_.end()) {
        r.restarts = st->second.restarts;
        if (st->second.to_state == "RUNNING") r.pid = st->second.pid;
      }
      if (StatusNameOf(p).empty()) {
        r.heartbeat = "-";
      } else if (const Beat* b = BeatFor(p, r.pid)) {
        const double age_s = static_cast<double>(now_utime - b->received_utime) * 1e-6;
        r.heartbeat = age_s > lost_after_s_ ? "SILENT" : ServiceStateName(b->status.state);
        if (r.pid == 0) r.pid = b->status.pid;
        r.out_per_s = b->out_per_s;
        r.last_error = Printable(b->status.last_error);
      } else {
        r.heartbeat = "SILENT";
      }
      rows.push_back(r);
    }
  }
  return rows;
}

std::string GroupBoard::Render(int64_t now_utime) const {
  std::vector<std::vector<std::string>> cells = {
      {"HOST", "PROCESS", "SUPERVISOR", "PID", "RESTARTS", "HEARTBEAT", "OUT/S", "LAST ERROR"}};
  for (const Row& r : Rows(now_utime)) {
    char rate[32] = "?";
    if (r.out_per_s >= 0) std::snprintf(rate, sizeof(rate), "%.0f", r.out_per_s);
    cells.push_back({r.host, r.group + ":" + r.name, r.supervisor_state,
                     r.pid > 0 ? std::to_string(r.pid) : "-", std::to_string(r.restarts),
                     r.heartbeat == "SILENT" ? "SILENT!" : r.heartbeat, rate, r.last_error});
  }
  return AlignColumns(cells);
}

}  // namespace ftcal
