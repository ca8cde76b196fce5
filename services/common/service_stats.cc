#include "common/service_stats.h"

#include <utility>

namespace ftcal {

ServiceStats::ServiceStats(std::shared_ptr<spdlog::logger> log) : log_(std::move(log)) {}

bool ServiceStats::CountKind(const std::string& kind) { return ++kinds_[kind] == 1; }

void ServiceStats::Drop(const std::string& kind, const std::string& reason) {
  ++drops_;
  if (CountKind(kind)) {
    log_->warn("dropped input: {}: {} (further drops of this kind are counted, not logged)",
               kind, reason);
  }
}

void ServiceStats::Error(const std::string& kind, const std::string& reason) {
  ++errors_;
  last_error_ = kind + ": " + reason;
  if (CountKind(kind)) {
    log_->error("{}: {} (further errors of this kind are counted, not logged)", kind, reason);
  }
}

void ServiceStats::LogSummary() const {
  log_->info("in {} out {} drops {} errors {}", msgs_in_, msgs_out_, drops_, errors_);
  for (const auto& [kind, count] : kinds_) {
    log_->info("  {} x {}", count, kind);
  }
}

}  // namespace ftcal
