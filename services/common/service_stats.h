// What a process counts about itself; its heartbeat (service_status_t) publishes these.
//
// Bad input and errors are counted per *kind* (a short stable label such as
// "undecodable ftcal.ft_sample_t on FT_HL") and logged the first time each kind occurs, so a
// 100 Hz stream of bad packets costs one log line, not a hundred a second; LogSummary() prints
// the totals per kind at exit.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include <spdlog/logger.h>

namespace ftcal {

class ServiceStats {
 public:
  explicit ServiceStats(std::shared_ptr<spdlog::logger> log);

  void CountIn() { ++msgs_in_; }
  void CountOut() { ++msgs_out_; }
  // An input dropped (malformed, duplicate, stale, ...).
  void Drop(const std::string& kind, const std::string& reason);
  // Something went wrong that is not a single bad input (a handler failure, an I/O error).
  void Error(const std::string& kind, const std::string& reason);
  // A process-specific counter, created at zero on first use; published by name.
  int64_t& Counter(const std::string& name) { return counters_[name]; }

  int64_t msgs_in() const { return msgs_in_; }
  int64_t msgs_out() const { return msgs_out_; }
  int64_t drops() const { return drops_; }
  int64_t errors() const { return errors_; }
  const std::string& last_error() const { return last_error_; }
  const std::map<std::string, int64_t>& counters() const { return counters_; }
  // Occurrences per drop/error kind.
  const std::map<std::string, int64_t>& kinds() const { return kinds_; }
  spdlog::logger& log() const { return *log_; }

  // One line with the totals, then one per kind seen.
  void LogSummary() const;

 private:
  // Returns true the first time `kind` is seen.
  bool CountKind(const std::string& kind);

  std::shared_ptr<spdlog::logger> log_;
  int64_t msgs_in_ = 0;
  int64_t msgs_out_ = 0;
  int64_t drops_ = 0;
  int64_t errors_ = 0;
  std::string last_error_;
  std::map<std::string, int64_t> counters_;
  std::map<std::string, int64_t> kinds_;
};

}  // namespace ftcal
