#include "session/span_index.h"

#include <time.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <thread>

#include <google/protobuf/text_format.h>

#include "common/log_replay_bus.h"
#include "common/service_stats.h"
#include "common/user_errors.h"

namespace ftcal {

namespace {

int64_t RealtimeNs() {
  timespec now{};
  ::clock_gettime(CLOCK_REALTIME, &now);
  return static_cast<int64_t>(now.tv_sec) * 1'000'000'000 + now.tv_nsec;
}

// Longer than the kernel's coarse clock tick, which stamps ctime: a write after the key is
// taken then always moves the ctime on, whatever tick the last one fell in.
constexpr int64_t kSettleNs = 100'000'000;

}  // namespace

SessionIndexer::SessionIndexer(const config::Config& config, std::string path, DigestCache cache)
    : path_(std::move(path)),
      cache_(std::move(cache)),
      // The collector's lines would repeat the segmenter's own; its drops are counted in Run().
      quiet_(std::make_shared<spdlog::logger>("ftcal-span-index")) {
  try {
    collector_ = std::make_unique<CalibrationCollector>(config);
    collector_->SetIndexOnly();
    collector_->SetLogger(quiet_);
    collector_->SpanIndexRules();  // every channel name it reads, read here
  } catch (const std::exception& e) {
    refused_ = UserText(e, "making the span index");
  }
}

SessionIndexer::~SessionIndexer() = default;

SpanIndexPass SessionIndexer::Run() {
  SpanIndexPass out;
  if (!collector_) {
    out.why_not = refused_;
    return out;
  }
  if (!cache_.enabled()) {
    out.why_not = "no digest cache";
    return out;
  }
  if (!cache_.Lookup(path_)) {
    out.why_not =
        "its digest is not in the cache (a calibrator hashes the log, reading it whole anyway)";
    return out;
  }
  // The key the index is stored under, taken once the ctime has settled (kSettleNs): the log's
  // writer may have finished a moment ago.
  std::optional<FileKey> key = FileKeyOf(path_);
  if (key) {
    const int64_t wait_ns = key->ctime_ns + kSettleNs - RealtimeNs();
    if (wait_ns > 0) {
      std::this_thread::sleep_for(std::chrono::nanoseconds(std::min(wait_ns, kSettleNs)));
    }
    key = FileKeyOf(path_);
  }
  const int64_t key_taken_ns = RealtimeNs();
  if (!key || key_taken_ns - key->ctime_ns < kSettleNs) {
    out.why_not = "the file is being written";
    return out;
  }
  ServiceStats stats(quiet_);
  const std::string scratch = (std::filesystem::temp_directory_path() /
                               ("ftcal-span-index-" + std::to_string(::getpid()) + ".lcmlog"))
                                  .string();
  try {
    CalibrationCollector& collector = *collector_;
    // Nothing is published: the replay's output stays uncommitted and is removed.
    LogReplayBus bus(path_, scratch, stats);
    collector.Attach(bus);
    bus.Run([] {}, 60'000'000);
    if (!bus.finished()) {
      out.why_not = "interrupted";
      return out;
    }
    collector.Flush();
    if (stats.errors() > 0 || stats.drops() > 0) {
      // The calibrator refuses or warns about such a log when it reads it; it reads it whole.
      out.why_not = "the log has unreadable spans or messages dropped (" + stats.last_error() + ")";
      return out;
    }
    const logindex::LogIndex index = collector.TakeSpanIndex();
    for (const logindex::SkippableSpan& s : index.span()) {
      ++out.spans;
      out.span_bytes += s.to_offset() - s.from_offset();
    }
    if (out.spans == 0) {
      out.why_not = "no span to skip (no STANDING or TRIPOD phase long enough)";
      return out;
    }
    std::string text;
    if (!google::protobuf::TextFormat::PrintToString(index, &text)) {
      out.why_not = "the index could not be printed";
      return out;
    }
    // Settled as of when the key was taken (above), whatever the reading took since.
    const double settled_s = 1e-9 * static_cast<double>(RealtimeNs() - key_taken_ns + kSettleNs);
    out.stored = cache_.StoreNote("spans", path_, *key, text, settled_s);
    if (!out.stored) {
      out.why_not = "the file changed while it was read, or the cache is not writable";
    }
  } catch (const std::exception& e) {
    out.why_not = UserText(e, "indexing " + path_);
  }
  return out;
}

}  // namespace ftcal
