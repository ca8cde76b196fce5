// An LCM event log written atomically: events go to a temporary file beside the target
// (.<name>.tmp.<pid>.<random>, created exclusively), and Commit() fsyncs it, renames it onto the
// final name and syncs the directory. Destroyed without Commit() (an error, an interrupted run,
// SIGINT/SIGTERM through the services' shutdown), it removes the temporary file, so a partial
// log never appears under the final name; the leftovers of a run killed outright are removed
// by the next run writing the same output.
//
// Writing overlaps the caller's work: events are encoded into a 1 MiB buffer while a writer
// thread hands the full ones to the kernel. A replay's output is several times its input
// (a CONTACT_WRENCH per transducer sample), and copying it into the page cache took two thirds
// of ftcal-corrector --replay; on two cores that copy now runs beside the correction.
// The writer also makes the data durable as it goes (fdatasync every kSyncBytes), so that
// Commit()'s fsync has only the last few MiB left: a single fsync at the end waited for the
// whole output (21 ms of a 79 ms replay of 32 MB here, on a virtio disk, even with
// sync_file_range started after every write: the device's cache flush is what costs). Up to
// kMaxQueued buffers wait for the writer, so the caller is not held up while it syncs.
// A write or sync error on the writer thread is reported by the next Write() or by Commit().
#pragma once

#include <sys/stat.h>

#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <deque>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace ftcal {

// LCM's event-log header, as lcm_eventlog_write_event() writes it: sync word, event number,
// timestamp, channel length, data length, all big-endian; the channel and the data follow.
// One store per field (a byte loop here was a twentieth of a replay's time).
constexpr size_t kLcmEventHeaderBytes = 28;
inline void EncodeLcmEventHeader(char* head, int64_t event_number, int64_t utime,
                                 uint32_t channel_bytes, uint32_t data_bytes) {
  auto put32 = [head](int offset, uint32_t v) {
    v = __builtin_bswap32(v);
    std::memcpy(head + offset, &v, 4);
  };
  auto put64 = [head](int offset, uint64_t v) {
    v = __builtin_bswap64(v);
    std::memcpy(head + offset, &v, 8);
  };
  put32(0, 0xEDA1DA01u);
  put64(4, static_cast<uint64_t>(event_number));
  put64(12, static_cast<uint64_t>(utime));
  put32(20, channel_bytes);
  put32(24, data_bytes);
}

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
  // Gives `tap` every byte of the file, in order, as the writer thread writes it: a digest of
  // the output taken on the way (the SHA-256 the calibrator would otherwise read the file
  // again for). Set it before the first Write(); it runs on the writer thread.
  void SetTap(std::function<void(const char* data, size_t size)> tap);
  // The committed file's status, taken after the rename; all zero (st_ino 0) before Commit(),
  // when the name no longer held this file as written by then, or when the tap threw (it
  // then saw only part of the file, and is called no more).
  const struct stat& committed_stat() const { return committed_stat_; }
  bool committed() const { return committed_; }
  const std::string& temp_path() const { return tmp_path_; }
  // Removes the temporary files of `path` left by runs no longer alive; returns how many.
  static int RemoveLeftovers(const std::string& path);
  static std::string TempPrefix(const std::string& path);
  const std::string& path() const { return path_; }

 private:
  // Queues `fill_` for the writer (waiting while kMaxQueued buffers are queued already) and
  // takes an empty buffer in its place.
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
  static constexpr size_t kMaxQueued = 8;
  static constexpr int64_t kSyncBytes = 4 << 20;
  static constexpr size_t kMaxChannelBytes = 255;  // LCM's own limit is 63
  int fd_ = -1;
  // Buffers only grow (to a little over kBufferBytes) and are reused: resizing a vector per
  // event zero-filled every byte before it was overwritten.
  std::vector<char> fill_;  // the caller encodes into this one; `fill_bytes_` of it are valid
  size_t fill_bytes_ = 0;
  struct Full {
    std::vector<char> data;
    size_t bytes;
  };
  // Guarded by mutex_: full buffers for the writer, in order; empty ones back from it.
  std::deque<Full> queue_;
  std::vector<std::vector<char>> spare_;
  bool writing_ = false;  // the writer holds a buffer taken from queue_
  // The writer's own: bytes written, and bytes written since its last fdatasync.
  int64_t written_ = 0;
  int64_t unsynced_ = 0;
  std::mutex mutex_;
  std::condition_variable cv_;
  bool stop_ = false;
  std::string error_;  // the writer's first failure
  std::thread writer_;
  int64_t event_number_ = 0;
  bool committed_ = false;
  std::function<void(const char*, size_t)> tap_;  // the writer thread's once writing began
  bool tap_failed_ = false;
  struct stat committed_stat_ {};
};

}  // namespace ftcal
