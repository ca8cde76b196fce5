// An LCM event log written atomically: events go to a temporary file beside the target, and
// Commit() fsyncs it, renames it onto the final name and syncs the directory. Destroyed without
// Commit() (an error, an interrupted run), it removes the temporary file, so a partial log never
// appears under the final name.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <lcm/lcm-cpp.hpp>

namespace ftcal {

class AtomicLogFile {
 public:
  // `what` names the file in error messages, e.g. "replay output". Throws std::runtime_error
  // naming the path when the temporary file cannot be created.
  AtomicLogFile(const std::string& path, const std::string& what);
  ~AtomicLogFile();
  AtomicLogFile(const AtomicLogFile&) = delete;
  AtomicLogFile& operator=(const AtomicLogFile&) = delete;

  // Appends one event (numbered in write order). Throws std::runtime_error on I/O failure,
  // std::invalid_argument for a channel longer than LCM allows (255 bytes here) or a negative
  // size, and std::logic_error after Commit().
  void Write(int64_t utime, const std::string& channel, const void* data, int size);
  // Idempotent. Throws std::runtime_error on I/O failure (the temporary file then stays until
  // destruction removes it).
  void Commit();
  bool committed() const { return committed_; }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
  std::string tmp_path_;
  std::string what_;
  static constexpr size_t kBufferBytes = 1 << 20;
  static constexpr size_t kMaxChannelBytes = 255;  // LCM's own limit is 63
  std::vector<char> buffer_;  // the stream's buffer: declared before log_, so it outlives it
  std::unique_ptr<lcm::LogFile> log_;
  int64_t event_number_ = 0;
  bool committed_ = false;
};

}  // namespace ftcal
