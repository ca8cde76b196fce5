#include "common/atomic_log.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <stdexcept>

namespace ftcal {

AtomicLogFile::AtomicLogFile(const std::string& path, const std::string& what)
    : path_(path), tmp_path_(path + ".tmp." + std::to_string(::getpid())), what_(what) {
  log_ = std::make_unique<lcm::LogFile>(tmp_path_, "w");
  if (!log_->good()) {
    throw std::runtime_error(what_ + " '" + path_ + "': cannot create '" + tmp_path_ +
                             "': " + std::strerror(errno));
  }
  // stdio's default buffer is one 4 KiB block: a write() every ten corrected wrenches. Nothing
  // has been written yet, so the buffer can still be set; nothing is flushed per event.
  buffer_.resize(kBufferBytes);
  std::setvbuf(log_->getFilePtr(), buffer_.data(), _IOFBF, buffer_.size());
}

AtomicLogFile::~AtomicLogFile() {
  if (!committed_) {
    log_.reset();
    ::unlink(tmp_path_.c_str());
  }
}

void AtomicLogFile::Write(int64_t utime, const std::string& channel, const void* data, int size) {
  if (committed_) throw std::logic_error(what_ + " '" + path_ + "': write after Commit()");
  // LCM's log format, written here in two stdio calls instead of lcm_eventlog_write_event()'s
  // seven (each takes the stream's lock; together they were a tenth of a corrector replay):
  // sync word, event number, timestamp, channel length, data length (big-endian), channel, data.
  // lcm::LogFile still opens and closes the file.
  if (channel.size() > kMaxChannelBytes || size < 0) {
    throw std::invalid_argument(what_ + " '" + path_ + "': event on '" + channel +
                                "' with a channel of " + std::to_string(channel.size()) +
                                " bytes or " + std::to_string(size) + " data bytes");
  }
  uint8_t head[28 + kMaxChannelBytes];
  auto put = [&head](int at, uint64_t v, int bytes) {
    for (int i = 0; i < bytes; ++i) head[at + i] = static_cast<uint8_t>(v >> (8 * (bytes - 1 - i)));
  };
  put(0, 0xEDA1DA01u, 4);
  put(4, static_cast<uint64_t>(event_number_), 8);
  put(12, static_cast<uint64_t>(utime), 8);
  put(20, channel.size(), 4);
  put(24, static_cast<uint32_t>(size), 4);
  std::memcpy(head + 28, channel.data(), channel.size());
  FILE* file = log_->getFilePtr();
  const size_t head_bytes = 28 + channel.size();
  if (::fwrite_unlocked(head, 1, head_bytes, file) != head_bytes ||
      ::fwrite_unlocked(data, 1, static_cast<size_t>(size), file) != static_cast<size_t>(size)) {
    throw std::runtime_error(what_ + " '" + tmp_path_ + "': write failed: " +
                             std::strerror(errno));
  }
  ++event_number_;
}

void AtomicLogFile::Commit() {
  if (committed_) return;
  FILE* file = log_->getFilePtr();
  if (std::fflush(file) != 0 || ::fsync(::fileno(file)) != 0) {
    throw std::runtime_error(what_ + " '" + tmp_path_ + "': " + std::strerror(errno));
  }
  log_.reset();  // closes
  if (std::rename(tmp_path_.c_str(), path_.c_str()) != 0) {
    throw std::runtime_error(what_ + ": cannot rename '" + tmp_path_ + "' to '" + path_ +
                             "': " + std::strerror(errno));
  }
  committed_ = true;
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
