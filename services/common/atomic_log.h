// An LCM event log written atomically: events go to a temporary file beside the target
// (.<name>.tmp.<pid>.<random>, created exclusively), and Commit() fsyncs it, renames it onto the
// final name and syncs the directory. Destroyed without Commit() (an error, an interrupted run,
// SIGINT/SIGTERM through the services' shutdown), it removes the temporary file, so a partial
// log never appears under the final name; the leftovers of a run killed outright are removed
// by the next run writing the same output.
//
// Writing overlaps the caller's work: events are encoded into one 1 MiB buffer while a writer
// thread hands the previous one to the kernel. A replay's output is several times its input
// (a CONTACT_WRENCH per transducer sample), and copying it into the page cache took two thirds
// of ftcal-corrector --replay; on two cores that copy now runs beside the correction. A write
// error on the writer thread is reported by the next Write() or by Commit().
#pragma once

#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace ftcal {

class AtomicLogFile {
 public:
  // `what` names the file in error messages, e.g. "replay output". Throws std::runtime_error
  // naming the path when the temporary file cannot be created (the directory is missing or
  // not writable) or `path` is a directory.
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
  const std::string& temp_path() const { return tmp_path_; }
  // Removes the temporary files of `path` left by runs no longer alive; returns how many.
  static int RemoveLeftovers(const std::string& path);
  static std::string TempPrefix(const std::string& path);
  const std::string& path() const { return path_; }

 private:
  // Waits until the writer has taken the previous buffer, then passes it `fill_`.
  void HandOff();
  // Waits until everything handed off is written; throws the writer's error if it had one.
  void Drain();
  void WriterLoop();
  void StopWriter();
  [[noreturn]] void ThrowWriteError(const std::string& error) const;

  std::string path_;
  std::string tmp_path_;
  std::string what_;
  static constexpr size_t kBufferBytes = 1 << 20;
  static constexpr size_t kMaxChannelBytes = 255;  // LCM's own limit is 63
  int fd_ = -1;
  // Both buffers only grow (to a little over kBufferBytes) and hold `*_bytes_` valid bytes:
  // resizing a vector per event zero-filled every byte before it was overwritten.
  std::vector<char> fill_;  // the caller encodes into this one
  size_t fill_bytes_ = 0;
  std::vector<char> pending_;  // the writer writes this one (guarded by mutex_ while handed off)
  size_t pending_bytes_ = 0;
  int64_t written_ = 0;  // bytes the writer has written: where the next sync_file_range starts
  std::mutex mutex_;
  std::condition_variable cv_;
  bool has_pending_ = false;
  bool stop_ = false;
  std::string error_;  // the writer's first failure
  std::thread writer_;
  int64_t event_number_ = 0;
  bool committed_ = false;
};

}  // namespace ftcal
