// supervisor's event listener protocol (supervisor docs, "Events"): the listener writes READY,
// supervisord sends a header line ("ver:3.0 ... eventname:PROCESS_STATE_RUNNING len:54") and
// `len` bytes of payload ("processname:x groupname:g from_state:STARTING pid:12"), the
// listener answers "RESULT 2\nOK" and is READY again. Parsing and the restart count live here,
// apart from stdin/stdout, so a test feeds it supervisor's own bytes.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>

#include "ftcal/process_state_t.hpp"

namespace ftcal::supervisor {

// "k1:v1 k2:v2" into a map (supervisor's token format for headers and payloads).
std::map<std::string, std::string> ParseTokens(const std::string& text);

class EventTranslator {
 public:
  EventTranslator(std::string host, std::string group)
      : host_(std::move(host)), group_(std::move(group)) {}

  // The message for one event, or nullopt for an event of another group or kind.
  std::optional<process_state_t> Translate(const std::string& header, const std::string& payload,
                                           int64_t utime);

 private:
  struct History {
    bool ran = false;        // has been RUNNING
    bool unplanned = false;  // ended without being asked (EXITED, BACKOFF) since
    int32_t restarts = 0;
  };
  std::string host_;
  std::string group_;  // empty: every group
  std::map<std::string, History> history_;
};

}  // namespace ftcal::supervisor
