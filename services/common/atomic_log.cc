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
  lcm::LogEvent event{};
  event.eventnum = event_number_++;
  event.timestamp = utime;
  event.channel = channel;
  event.datalen = size;
  event.data = const_cast<void*>(data);  // LogFile::writeEvent only reads it
  if (log_->writeEvent(&event) != 0) {
    throw std::runtime_error(what_ + " '" + tmp_path_ + "': write failed: " +
                             std::strerror(errno));
  }
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
