#include "common/service_stats.h"

#include <utility>

namespace ftcal {

ServiceStats::ServiceStats(std::shared_ptr<spdlog::logger> log,
                           std::chrono::steady_clock::duration repeat_log_period)
    : log_(std::move(log)), repeat_log_period_(repeat_log_period) {}

std::int64_t ServiceStats::CountKind(const std::string& kind) {
  const auto now = std::chrono::steady_clock::now();
  KindLog& k = kind_logs_[kind];
  ++k.unlogged;
  if (++kinds_[kind] == 1 || now - k.last_logged >= repeat_log_period_) {
    k.last_logged = now;
    return std::exchange(k.unlogged, 0);
  }
  return 0;
}

void ServiceStats::Drop(const std::string& kind, const std::string& reason) {
  ++drops_;
  const std::int64_t n = CountKind(kind);
  if (n == 0) return;
  if (kinds_[kind] == 1) {
    log_->warn("dropped input: {}: {} (repeats are counted and logged at most once a minute)", kind,
               reason);
  } else {
    log_->warn("dropped input: {}: {} more since the last line ({} in all); latest: {}", kind, n,
               kinds_[kind], reason);
  }
}

void ServiceStats::Error(const std::string& kind, const std::string& reason) {
  ++errors_;
  last_error_ = kind + ": " + reason;
  const std::int64_t n = CountKind(kind);
  if (n == 0) return;
  if (kinds_[kind] == 1) {
    log_->error("{}: {} (repeats are counted and logged at most once a minute)", kind, reason);
  } else {
    log_->error("{}: {} more since the last line ({} in all); latest: {}", kind, n, kinds_[kind],
                reason);
  }
}

void ServiceStats::Fatal(const std::string& kind, const std::string& reason) {
  ++errors_;
  ++kinds_[kind];
  last_error_ = kind + ": " + reason;
  log_->critical("{}: {}", kind, reason);
}

void ServiceStats::LogSummary() const {
  log_->info("in {} out {} drops {} errors {}", msgs_in_, msgs_out_, drops_, errors_);
  for (const auto& [kind, count] : kinds_) {
    log_->info("  {} x {}", count, kind);
  }
}

}  // namespace ftcal
