// The span index of a session log made by a process that reads the log before the calibrator
// does: ftcal-pose-segmenter's --replay, on a thread of its own beside the replay. The first
// calibration of a new session log then skips what only a later one could (the STANDING
// phase's records, counted, not read: most of a report-scale log, docs/performance.md), instead
// of reading it to make the index itself.
//
// The index is the calibrator's own (CalibrationCollector::SetIndexOnly, the same counting
// rules and the same rules string), stored beside the log's digest in the digest cache under
// the file key the log had before it was read; the calibrator uses it only while the file
// still has that key and its digest is cached, and checks the counts at each span's start.
#pragma once

#include <memory>
#include <string>

#include <spdlog/logger.h>

#include "ftcal/digest_cache.h"
#include "session/collector.h"
#include "proto/config.pb.h"

namespace ftcal {

struct SpanIndexPass {
  bool stored = false;
  int spans = 0;
  int64_t span_bytes = 0;  // bytes of the log inside the spans
  std::string why_not;     // when not stored: the reason, for the log
};

// Reads the session log at `path` with a collector in index-only mode and stores the spans it
// found in `cache`. Constructed on the thread that owns `config`, run on any one thread: the
// constructor makes the collector, which reads the config's channel names. (protobuf builds a
// string field's explicit default on its first read, behind a lock inside libprotobuf, which
// ThreadSanitizer cannot see; so the owner's thread reads them first.)
class SessionIndexer {
 public:
  SessionIndexer(const config::Config& config, std::string path, DigestCache cache);
  ~SessionIndexer();
  SessionIndexer(const SessionIndexer&) = delete;
  SessionIndexer& operator=(const SessionIndexer&) = delete;

  // Does nothing (why_not says so) when the cache is off or has no digest of the file: a
  // calibrator that must hash the file reads it whole anyway. Never throws: a log this pass
  // cannot read is refused by the calibrator when it reads it. Call once.
  SpanIndexPass Run();

 private:
  std::string path_;
  DigestCache cache_;
  std::shared_ptr<spdlog::logger> quiet_;
  std::unique_ptr<CalibrationCollector> collector_;
  std::string refused_;  // why the collector could not be made
};

}  // namespace ftcal
