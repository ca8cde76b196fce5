// A log's SHA-256 taken as its writer writes it, handed to the digest cache (libcal's
// DigestCache) once the log is complete: the first calibration of a new log then takes its
// provenance digest from the cache instead of hashing the whole file, which was half of that
// run's CPU at report scale. Used by the writers of calibrator inputs: ftcal-sim log, the
// segmenter's poses log (ServiceSpec::digest_replay_output) and ftcal-record.
#pragma once

#include <sys/stat.h>

#include <cstddef>
#include <functional>
#include <memory>
#include <string>

namespace ftcal {

class Sha256;

class WrittenDigest {
 public:
  // Hashes only when the digest cache (DigestCache::FromEnvironment()) is on.
  WrittenDigest();
  ~WrittenDigest();
  WrittenDigest(const WrittenDigest&) = delete;
  WrittenDigest& operator=(const WrittenDigest&) = delete;

  // The tap for an AtomicLogFile (SetTap) or a replay's output (LogReplayBus::TapOutput): it
  // hashes every byte written, on the writer thread. Empty when the cache is off.
  std::function<void(const char* data, size_t size)> Tap();
  // For a writer that writes the bytes itself: every byte of the file, in order.
  void Update(const void* data, size_t size);
  // Ends the digest and stores it for `path` when the file still has `written`, its status
  // after the writer's last change (an all-zero status: nothing stored). Returns the digest
  // when it was stored, else an empty string. Call once.
  std::string HandOver(const std::string& path, const struct stat& written);

 private:
  std::unique_ptr<Sha256> sha_;  // none when the digest cache is off
};

}  // namespace ftcal
