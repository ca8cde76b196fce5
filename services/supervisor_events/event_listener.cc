#include "supervisor_events/event_listener.h"

#include <sstream>

namespace ftcal::supervisor {

std::map<std::string, std::string> ParseTokens(const std::string& text) {
  std::map<std::string, std::string> out;
  std::istringstream in(text);
  for (std::string token; in >> token;) {
    const auto colon = token.find(':');
    if (colon == std::string::npos) continue;
    out[token.substr(0, colon)] = token.substr(colon + 1);
  }
  return out;
}

std::optional<process_state_t> EventTranslator::Translate(const std::string& header,
                                                          const std::string& payload,
                                                          int64_t utime) {
  const auto h = ParseTokens(header);
  const auto name_it = h.find("eventname");
  static const std::string kPrefix = "PROCESS_STATE_";
  if (name_it == h.end() || name_it->second.rfind(kPrefix, 0) != 0) return std::nullopt;
  // The payload's first line holds the tokens (PROCESS_STATE events have no body after it).
  const auto p = ParseTokens(payload.substr(0, payload.find('\n')));
  const auto get = [&p](const char* key) {
    const auto it = p.find(key);
    return it == p.end() ? std::string() : it->second;
  };
  process_state_t m{};
  m.utime = utime;
  m.host = host_;
  m.group = get("groupname");
  m.name = get("processname");
  if (!group_.empty() && m.group != group_) return std::nullopt;
  m.from_state = get("from_state");
  m.to_state = name_it->second.substr(kPrefix.size());
  const auto number = [&](const char* key) -> int64_t {
    const std::string v = get(key);
    try {
      return v.empty() ? 0 : std::stoll(v);
    } catch (const std::exception&) {
      return 0;
    }
  };
  m.pid = number("pid");
  m.tries = static_cast<int32_t>(number("tries"));
  m.expected = get("expected") == "1";
  History& hist = history_[m.group + ":" + m.name];
  if (m.to_state == "EXITED" || m.to_state == "BACKOFF") hist.unplanned = true;
  if (m.to_state == "STOPPED" || m.to_state == "STOPPING") hist.unplanned = false;
  if (m.to_state == "RUNNING") {
    if (hist.ran && hist.unplanned) ++hist.restarts;
    hist.ran = true;
    hist.unplanned = false;
  }
  m.restarts = hist.restarts;
  return m;
}

}  // namespace ftcal::supervisor
