// The span index of a session log made by a process that reads the log before the calibrator
// does: ftcal-pose-segmenter's --replay, on a thread of its own beside the replay. The first
// calibration of a new session log then skips what only a later one could (the STANDING
// phase's records, counted, not read: three quarters of a report-scale log), instead of
// reading it to make the index itself.
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
#include "proto/config.pb.h"

namespace ftcal {

struct SpanIndexPass {
  bool stored = false;
  int spans = 0;
  int64_t span_bytes = 0;  // bytes of the log inside the spans
  std::string why_not;     // when not stored: the reason, for the log
};

// Reads the session log at `path` with a collector in index-only mode and stores the spans it
// found in `cache`. Does nothing (why_not says so) when the cache is off or has no digest of
// the file: a calibrator that must hash the file reads it whole anyway. Never throws: a log
// this pass cannot read is refused by the calibrator when it reads it.
SpanIndexPass IndexSessionLog(const config::Config& config, const std::string& path,
                              const DigestCache& cache);

}  // namespace ftcal
