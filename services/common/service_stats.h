// What a process counts about itself; its heartbeat (service_status_t) publishes these.
//
// Bad input and errors are counted per *kind* (a short stable label such as
// "undecodable ftcal.ft_batch_t on FT_HL") and logged the first time each kind occurs, then at
// most once per repeat_log_period with the count since the last line, so a 100 Hz stream of bad
// packets costs one log line a minute, not a hundred a second; LogSummary() prints the totals
// per kind at exit. last_error() is the latest error text, cleared when the process says it
// is healthy again.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include <spdlog/logger.h>

namespace ftcal {

class ServiceStats {
 public:
  explicit ServiceStats(
      std::shared_ptr<spdlog::logger> log,
      std::chrono::steady_clock::duration repeat_log_period = std::chrono::seconds(60));

  void CountIn() { ++msgs_in_; }
  void CountOut() { ++msgs_out_; }
  // An input dropped (malformed, duplicate, stale, ...).
  void Drop(const std::string& kind, const std::string& reason);
  // Something went wrong that is not a single bad input (a handler failure, an I/O error).
  void Error(const std::string& kind, const std::string& reason);
  // An error that ends the process: counted and carried in the status as Error() does, and
  // logged at once, critical, whatever was logged of its kind before: the line that says why
  // the process stopped is never held back as a repeat.
  void Fatal(const std::string& kind, const std::string& reason);
  // A process-specific counter, created at zero on first use; published by name.
  int64_t& Counter(const std::string& name) { return counters_[name]; }

  int64_t msgs_in() const { return msgs_in_; }
  int64_t msgs_out() const { return msgs_out_; }
  int64_t drops() const { return drops_; }
  int64_t errors() const { return errors_; }
  const std::string& last_error() const { return last_error_; }
  // For errors a process tracks itself (a device's state): the text the status carries.
  void SetLastError(std::string text) { last_error_ = std::move(text); }
  void ClearLastError() { last_error_.clear(); }
  const std::map<std::string, int64_t>& counters() const { return counters_; }
  // Occurrences per drop/error kind.
  const std::map<std::string, int64_t>& kinds() const { return kinds_; }
  spdlog::logger& log() const { return *log_; }

  // One line with the totals, then one per kind seen.
  void LogSummary() const;

 private:
  // Counts `kind`; returns the number of occurrences the caller should report in a log line
  // now (1 the first time, the count since the last line once repeat_log_period has passed),
  // or 0 to stay quiet.
  std::int64_t CountKind(const std::string& kind);

  struct KindLog {
    std::chrono::steady_clock::time_point last_logged{};
    std::int64_t unlogged = 0;
  };

  std::shared_ptr<spdlog::logger> log_;
  int64_t msgs_in_ = 0;
  int64_t msgs_out_ = 0;
  int64_t drops_ = 0;
  int64_t errors_ = 0;
  std::string last_error_;
  std::map<std::string, int64_t> counters_;
  std::map<std::string, int64_t> kinds_;
  std::chrono::steady_clock::duration repeat_log_period_;
  std::map<std::string, KindLog> kind_logs_;
};

}  // namespace ftcal
