#include "common/atomic_log.h"

#include <dirent.h>
#include <fcntl.h>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>

namespace ftcal {
namespace {

std::pair<std::string, std::string> SplitPath(const std::string& path) {
  const auto slash = path.rfind('/');
  if (slash == std::string::npos) return {".", path};
  return {slash == 0 ? "/" : path.substr(0, slash), path.substr(slash + 1)};
}

}  // namespace

std::string AtomicLogFile::TempPrefix(const std::string& path) {
  const auto [dir, base] = SplitPath(path);
  return "." + base + ".tmp.";
}

int AtomicLogFile::RemoveLeftovers(const std::string& path) {
  const auto [dir, base] = SplitPath(path);
  const std::string prefix = TempPrefix(path);
  DIR* d = ::opendir(dir.c_str());
  if (d == nullptr) return 0;
  int removed = 0;
  while (const dirent* e = ::readdir(d)) {
    const std::string name = e->d_name;
    if (name.compare(0, prefix.size(), prefix) != 0) continue;
    // .<base>.tmp.<pid>.<random>: the pid of the run that wrote it.
    char* end = nullptr;
    const long pid = std::strtol(name.c_str() + prefix.size(), &end, 10);
    if (pid <= 0 || end == nullptr || *end != '.') continue;
    if (::kill(static_cast<pid_t>(pid), 0) == 0 || errno != ESRCH) continue;  // still running
    if (::unlinkat(::dirfd(d), name.c_str(), 0) == 0) ++removed;
  }
  ::closedir(d);
  return removed;
}

AtomicLogFile::AtomicLogFile(const std::string& path, const std::string& what)
    : path_(path), what_(what) {
  const auto [dir, base] = SplitPath(path);
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode)) {
    throw std::runtime_error(what_ + " '" + path_ + "' is a directory");
  }
  // A run killed with SIGKILL (or a power cut) cannot clean up after itself: the next run of
  // the same output does.
  RemoveLeftovers(path);
  // Beside the target, so that the rename is atomic; a name no one can predict, opened
  // exclusively (mkostemp: O_CREAT | O_EXCL, which never follows a symlink planted there).
  // Created before any work, so an unwritable output is known at once.
  tmp_path_ = dir + "/" + TempPrefix(path) + std::to_string(::getpid()) + ".XXXXXX";
  fd_ = ::mkostemp(tmp_path_.data(), O_CLOEXEC);
  if (fd_ < 0) {
    throw std::runtime_error(what_ + " '" + path_ + "': cannot create a file in '" + dir +
                             "': " + std::strerror(errno));
  }
  ::fchmod(fd_, 0644);  // mkostemp makes it 0600; logs are for everyone to read
  fill_.resize(kBufferBytes + 4096);
  try {
    writer_ = std::thread([this] { WriterLoop(); });
  } catch (...) {
    ::close(fd_);
    ::unlink(tmp_path_.c_str());
    throw;
  }
}

AtomicLogFile::~AtomicLogFile() {
  StopWriter();
  if (fd_ >= 0) ::close(fd_);
  if (!committed_) ::unlink(tmp_path_.c_str());
}

void AtomicLogFile::StopWriter() {
  if (!writer_.joinable()) return;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  writer_.join();
}

void AtomicLogFile::WriterLoop() {
  std::unique_lock<std::mutex> lock(mutex_);
  for (;;) {
    cv_.wait(lock, [this] { return !queue_.empty() || stop_; });
    if (queue_.empty()) return;  // stopped with nothing left
    Full full = std::move(queue_.front());
    queue_.pop_front();
    writing_ = true;
    const bool failed = !error_.empty();
    lock.unlock();
    std::string error;
    const char* p = full.data.data();
    size_t left = failed ? 0 : full.bytes;  // after a failure, the rest is only drained
    while (left > 0) {
      const ssize_t n = ::write(fd_, p, left);
      if (n < 0) {
        if (errno == EINTR) continue;
        error = errno == ENOSPC || errno == EDQUOT
                    ? std::string("the disk is full (") + std::strerror(errno) +
                          "): free space and run again; nothing was written under the final name"
                    : std::strerror(errno);
        break;
      }
      p += n;
      left -= static_cast<size_t>(n);
    }
    if (error.empty() && !failed) {
      if (tap_) {
        try {
          tap_(full.data.data(), full.bytes);
        } catch (...) {
          tap_ = nullptr;  // the tap has not seen every byte: its owner gets no status
          tap_failed_ = true;
        }
      }
      // Starts the disk on what was just written without waiting, so that the fdatasync below
      // finds it under way. (Best effort: where the filesystem does not support it, the
      // fdatasync does it all.)
      ::sync_file_range(fd_, static_cast<off_t>(written_), static_cast<off_t>(full.bytes),
                        SYNC_FILE_RANGE_WRITE);
      written_ += static_cast<int64_t>(full.bytes);
      unsynced_ += static_cast<int64_t>(full.bytes);
    }
    lock.lock();
    if (!error.empty() && error_.empty()) error_ = error;
    spare_.push_back(std::move(full.data));
    const bool sync = error_.empty() && unsynced_ >= kSyncBytes;
    if (sync) {
      // The buffer is back and the queue has room: the caller goes on while this waits.
      cv_.notify_all();
      lock.unlock();
      const int synced = ::fdatasync(fd_) == 0 ? 0 : errno;
      unsynced_ = 0;
      lock.lock();
      if (synced != 0 && synced != EINVAL && error_.empty()) {
        error_ = std::string("fdatasync: ") + std::strerror(synced);
      }
    }
    writing_ = false;
    cv_.notify_all();
  }
}

void AtomicLogFile::ThrowWriteError(const std::string& error) const {
  throw std::runtime_error(what_ + " '" + tmp_path_ + "': write failed: " + error);
}

void AtomicLogFile::HandOff() {
  std::unique_lock<std::mutex> lock(mutex_);
  cv_.wait(lock, [this] { return queue_.size() < kMaxQueued || !error_.empty(); });
  if (!error_.empty()) ThrowWriteError(error_);
  queue_.push_back(Full{std::move(fill_), fill_bytes_});
  if (spare_.empty()) {
    fill_ = std::vector<char>(kBufferBytes + 4096);
  } else {
    fill_ = std::move(spare_.back());
    spare_.pop_back();
  }
  fill_bytes_ = 0;
  cv_.notify_all();
}

void AtomicLogFile::Drain() {
  if (fill_bytes_ > 0) HandOff();
  std::unique_lock<std::mutex> lock(mutex_);
  cv_.wait(lock, [this] { return (queue_.empty() && !writing_) || !error_.empty(); });
  if (!error_.empty()) ThrowWriteError(error_);
}

void AtomicLogFile::Write(int64_t utime, const std::string& channel, const void* data, int size) {
  if (committed_) throw std::logic_error(what_ + " '" + path_ + "': write after Commit()");
  // LCM's log format: sync word, event number, timestamp, channel length, data length
  // (big-endian), channel, data. Written here rather than with lcm_eventlog_write_event(),
  // which makes seven locked stdio calls per event and cannot overlap the disk.
  if (channel.size() > kMaxChannelBytes || size < 0) {
    throw std::invalid_argument(what_ + " '" + path_ + "': event on '" + channel +
                                "' with a channel of " + std::to_string(channel.size()) +
                                " bytes or " + std::to_string(size) + " data bytes");
  }
  const size_t head_bytes = kLcmEventHeaderBytes + channel.size();
  const size_t at = fill_bytes_;
  const size_t end = at + head_bytes + static_cast<size_t>(size);
  if (fill_.size() < end) fill_.resize(end);  // an event larger than the slack
  fill_bytes_ = end;
  char* head = fill_.data() + at;
  EncodeLcmEventHeader(head, event_number_, utime, static_cast<uint32_t>(channel.size()),
                       static_cast<uint32_t>(size));
  // An LCM event's channel is length-prefixed, not NUL-terminated.
  // NOLINTNEXTLINE(bugprone-not-null-terminated-result)
  std::memcpy(head + kLcmEventHeaderBytes, channel.data(), channel.size());
  if (size > 0) std::memcpy(head + head_bytes, data, static_cast<size_t>(size));
  ++event_number_;
  if (fill_bytes_ >= kBufferBytes) HandOff();
}

void AtomicLogFile::SetTap(std::function<void(const char* data, size_t size)> tap) {
  if (event_number_ > 0) {
    throw std::logic_error(what_ + " '" + path_ + "': tap set after the first event");
  }
  std::lock_guard<std::mutex> lock(mutex_);
  tap_ = std::move(tap);
}

void AtomicLogFile::Commit() {
  if (committed_) return;
  Drain();
  StopWriter();
  struct stat written {};
  const int synced = ::fsync(fd_) == 0 ? 0 : errno;
  if (::fstat(fd_, &written) != 0) written = {};
  const int closed = ::close(fd_) == 0 ? 0 : errno;
  fd_ = -1;
  if (synced != 0 || closed != 0) {
    throw std::runtime_error(what_ + " '" + tmp_path_ +
                             "': " + std::strerror(synced != 0 ? synced : closed));
  }
  if (std::rename(tmp_path_.c_str(), path_.c_str()) != 0) {
    throw std::runtime_error(what_ + ": cannot rename '" + tmp_path_ + "' to '" + path_ +
                             "': " + std::strerror(errno));
  }
  committed_ = true;
  // Taken after the rename, which changes the file's ctime, and kept only when the name still
  // holds this file as written (another run's output may have been renamed onto it, or the
  // file written to, meanwhile).
  struct stat now {};
  if (!tap_failed_ && ::stat(path_.c_str(), &now) == 0 && written.st_ino != 0 &&
      now.st_ino == written.st_ino && now.st_dev == written.st_dev &&
      now.st_size == written.st_size && now.st_mtim.tv_sec == written.st_mtim.tv_sec &&
      now.st_mtim.tv_nsec == written.st_mtim.tv_nsec) {
    committed_stat_ = now;
  }
  // The rename itself is durable only once the directory is synced.
  const auto slash = path_.rfind('/');
  const std::string dir = slash == std::string::npos ? "." : path_.substr(0, slash + 1);
  const int dir_fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir_fd >= 0) {
    ::fsync(dir_fd);
    ::close(dir_fd);
  }
}

}  // namespace ftcal
