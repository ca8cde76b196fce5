#include "sim/operator_fifo.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "ftcal/calibration_io.h"

namespace ftcal::sim {
namespace {

constexpr const char* kAccepted =
    "accepted: 'hang HANG_X_POS|HANG_X_NEG|HANG_Z_POS|HANG_Z_NEG', 'lift', 'stand'";
constexpr const char* kSeriesNames[] = {"HANG_X_POS", "HANG_X_NEG", "HANG_Z_POS", "HANG_Z_NEG"};

}  // namespace

std::optional<OperatorCommand> ParseOperatorLine(const std::string& line, std::string* error) {
  std::istringstream in(line);
  std::vector<std::string> words;
  for (std::string w; in >> w;) words.push_back(w);
  OperatorCommand c;
  using Support = BigAntTwin::Driven::Support;
  if (words.size() == 1 && words[0] == "lift") {
    c.support = Support::kLifted;
    return c;
  }
  if (words.size() == 1 && words[0] == "stand") {
    c.support = Support::kStanding;
    return c;
  }
  if (words.size() == 2 && words[0] == "hang") {
    for (int s = 0; s < kNumHangSeries; ++s) {
      if (words[1] == kSeriesNames[s]) {
        c.support = Support::kHanging;
        c.series = static_cast<HangSeries>(s);
        return c;
      }
    }
    if (error)
      *error = "unknown orientation '" + words[1] + "' in '" + line + "' (" + kAccepted + ")";
    return std::nullopt;
  }
  if (error) *error = "unknown operator command '" + line + "' (" + kAccepted + ")";
  return std::nullopt;
}

std::string SupportName(const OperatorCommand& c) {
  switch (c.support) {
    case BigAntTwin::Driven::Support::kStanding:
      return "STANDING";
    case BigAntTwin::Driven::Support::kLifted:
      return "LIFTED";
    case BigAntTwin::Driven::Support::kHanging:
      return kSeriesNames[static_cast<int>(c.series)];
  }
  return "?";
}

OperatorFifo::OperatorFifo(std::string path) : path_(std::move(path)) {
  if (path_.empty()) throw std::runtime_error("--control: empty path");
  struct stat st {};
  if (::lstat(path_.c_str(), &st) == 0) {
    if (!S_ISFIFO(st.st_mode)) {
      throw std::runtime_error("--control " + path_ + ": exists and is not a FIFO");
    }
  } else if (::mkfifo(path_.c_str(), 0600) != 0) {
    throw std::runtime_error("--control " + path_ + ": mkfifo: " + std::strerror(errno));
  }
  // Read-write: the twin holds a writer itself, so a driver closing its end is no end of file
  // and the next driver's lines still arrive.
  fd_ = ::open(path_.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) throw std::runtime_error("--control " + path_ + ": open: " + std::strerror(errno));
}

OperatorFifo::~OperatorFifo() {
  if (fd_ >= 0) ::close(fd_);
  ::unlink(path_.c_str());
  ::unlink((path_ + ".state").c_str());
}

std::vector<std::string> OperatorFifo::ReadLines() {
  char buf[1024];
  for (;;) {
    const ssize_t n = ::read(fd_, buf, sizeof buf);
    if (n <= 0) break;
    partial_.append(buf, static_cast<std::size_t>(n));
    // A driver that never sends a newline must not grow the twin without bound.
    if (partial_.size() > 64 * 1024) partial_.clear();
  }
  std::vector<std::string> lines;
  for (std::size_t nl; (nl = partial_.find('\n')) != std::string::npos;) {
    lines.push_back(partial_.substr(0, nl));
    partial_.erase(0, nl + 1);
  }
  return lines;
}

void OperatorFifo::WriteState(std::int64_t applied, const std::string& support) const {
  WriteFileAtomic(path_ + ".state", std::to_string(applied) + " " + support + "\n");
}

}  // namespace ftcal::sim
