#include "launcher/gates.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

namespace ftcal::launch {
namespace {

constexpr int64_t kKeepUs = 60'000'000;

std::string Number(double v, int precision = 3) {
  std::ostringstream s;
  s.precision(precision);
  s << v;
  return s.str();
}

bool Matches(const std::string& pattern, const std::string& channel) {
  if (!pattern.empty() && pattern.back() == '*') {
    return channel.compare(0, pattern.size() - 1, pattern, 0, pattern.size() - 1) == 0;
  }
  return channel == pattern;
}

std::shared_ptr<spdlog::logger> Logger() {
  if (auto l = spdlog::get("ftcal-launch")) return l;
  return spdlog::stderr_color_mt("ftcal-launch");
}

}  // namespace

GateWatcher::GateWatcher(const std::string& lcm_url, const std::string& status_channel,
                         const std::vector<LcmBus::Route>& routes)
    : stats_(std::make_unique<ServiceStats>(Logger())),
      bus_(std::make_unique<LcmBus>(lcm_url, *stats_, routes)) {
  bus_->SubscribeRaw(".*", [this](const MessageInfo& info, const void*, int) {
    auto& a = channels_[info.channel].utimes;
    a.push_back(info.recv_utime);
    while (!a.empty() && a.front() < info.recv_utime - kKeepUs) a.pop_front();
  });
  bus_->Subscribe<service_status_t>(status_channel,
                                    [this](const MessageInfo& info, const service_status_t& s) {
                                      heartbeats_[{s.name, s.pid}] = {s, info.recv_utime};
                                    });
}

int64_t GateWatcher::Now() const { return bus_->NowUtime(); }

void GateWatcher::Pump(double seconds, const std::function<bool()>& done) {
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (!(done && done())) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          end - std::chrono::steady_clock::now())
                          .count();
    if (left <= 0) break;
    bus_->HandleOnce(static_cast<int>(std::min<long long>(left, 50)));
  }
}

std::optional<service_status_t> GateWatcher::Heartbeat(const std::string& name, int64_t pid) const {
  const auto it = heartbeats_.find({name, pid});
  if (it == heartbeats_.end()) return std::nullopt;
  return it->second.first;
}

GateVerdict GateWatcher::Judge(const config::HealthGate& gate, int64_t pid,
                               const std::string& status_name, int64_t since_utime) const {
  const int64_t now = Now();
  GateVerdict v;
  switch (gate.kind()) {
    case config::HealthGate::STATUS_RUNNING: {
      const auto it = heartbeats_.find({status_name, pid});
      if (it == heartbeats_.end() || it->second.second < since_utime) {
        v.figure = "no FTCAL_STATUS heartbeat from " + status_name + " pid " + std::to_string(pid);
        return v;
      }
      const auto& s = it->second.first;
      static const char* kNames[] = {"STARTING", "RUNNING", "DEGRADED", "STOPPING", "FAILED"};
      const std::string state =
          s.state >= 0 && s.state <= 4 ? kNames[s.state] : "state " + std::to_string(s.state);
      v.passed = s.state == service_status_t::RUNNING ||
                 (gate.accept_degraded() && s.state == service_status_t::DEGRADED);
      v.figure = "heartbeat says " + state +
                 (s.last_error.empty() ? "" : " (last error: " + s.last_error + ")");
      return v;
    }
    case config::HealthGate::FRESH: {
      int64_t newest = -1;
      std::string which;
      for (const auto& [channel, a] : channels_) {
        if (!Matches(gate.channel(), channel) || a.utimes.empty()) continue;
        if (a.utimes.back() > newest) {
          newest = a.utimes.back();
          which = channel;
        }
      }
      if (newest < since_utime) {
        v.figure = "nothing heard on " + gate.channel() + " since the start";
        return v;
      }
      const double age_s = (now - newest) * 1e-6;
      v.passed = age_s <= gate.max_age_s();
      v.figure = which + " last heard " + Number(age_s) + " s ago";
      return v;
    }
    case config::HealthGate::RATE: {
      // The window must lie after the start: a rate measured over the time before it would
      // count the process as slow for having not existed yet.
      const int64_t window_us = static_cast<int64_t>(gate.window_s() * 1e6);
      const int64_t from = now - window_us;
      if (from < since_utime) {
        v.figure = "not yet " + Number(gate.window_s()) + " s since the start";
        return v;
      }
      const double need = gate.min_fraction() * gate.rate_hz();
      int channels = 0;
      double worst = -1;
      std::string worst_channel;
      for (const auto& [channel, a] : channels_) {
        if (!Matches(gate.channel(), channel)) continue;
        const auto n = std::count_if(a.utimes.begin(), a.utimes.end(),
                                     [&](int64_t t) { return t > from && t <= now; });
        ++channels;
        const double rate = n / gate.window_s();
        if (worst < 0 || rate < worst) {
          worst = rate;
          worst_channel = channel;
        }
      }
      const int min_channels = std::max<int>(1, static_cast<int>(gate.min_channels()));
      if (channels == 0) {
        v.figure = "no channel matching " + gate.channel() + " heard";
        return v;
      }
      std::ostringstream f;
      f << worst_channel << " at " << Number(worst, 4) << " Hz ("
        << Number(100.0 * worst / gate.rate_hz(), 3) << "% of " << Number(gate.rate_hz()) << " Hz)";
      if (channels < min_channels || gate.min_channels() > 0) {
        f << "; " << channels << " of " << min_channels << " channels heard";
      }
      v.figure = f.str();
      v.passed = worst >= need && channels >= min_channels;
      return v;
    }
    default:
      v.figure = "unknown gate kind";
      return v;
  }
}

GateVerdict GateWatcher::Await(const config::HealthGate& gate, int64_t pid,
                               const std::string& status_name, int64_t since_utime,
                               const std::function<bool(std::string*)>& alive) {
  const int64_t deadline = since_utime + static_cast<int64_t>(gate.within_s() * 1e6);
  int64_t next_alive_check = Now() + 1'000'000;
  GateVerdict v;
  while (true) {
    Pump(0.1);
    v = Judge(gate, pid, status_name, since_utime);
    if (v.passed) return v;
    if (Now() >= next_alive_check) {
      std::string why;
      if (!alive(&why)) {
        v.figure += "; " + why;
        return v;
      }
      next_alive_check = Now() + 1'000'000;
    }
    if (Now() >= deadline) return v;
  }
}

}  // namespace ftcal::launch
