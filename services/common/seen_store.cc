#include "common/seen_store.h"

#include <sys/stat.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "ftcal/calibration_io.h"

namespace ftcal::auth {
namespace {

std::string Env(const char* name) {
  const char* v = std::getenv(name);
  return v == nullptr ? std::string() : std::string(v);
}

// mkdir -p, the directories it makes closed to group and others (the marks are nobody else's).
void MakeDirs(const std::string& dir) {
  std::string sofar;
  std::istringstream parts(dir);
  std::string part;
  if (!dir.empty() && dir[0] == '/') sofar = "/";
  while (std::getline(parts, part, '/')) {
    if (part.empty()) continue;
    sofar += part + "/";
    if (::mkdir(sofar.c_str(), 0700) != 0 && errno != EEXIST) {
      throw std::runtime_error("state directory '" + sofar +
                               "': cannot create: " + std::strerror(errno));
    }
  }
}

}  // namespace

std::string SeenStore::DefaultDir() {
  if (std::string d = Env("FTCAL_STATE_DIR"); !d.empty()) return d;
  if (std::string d = Env("STATE_DIRECTORY"); !d.empty()) return d.substr(0, d.find(':'));
  if (std::string d = Env("XDG_STATE_HOME"); !d.empty()) return d + "/ftcal";
  if (std::string d = Env("HOME"); !d.empty()) return d + "/.local/state/ftcal";
  return "";
}

std::map<SeenStore::Key, int64_t> SeenStore::Read(const std::string& path) {
  std::map<Key, int64_t> marks;
  std::ifstream in(path);
  if (!in) {
    if (errno == ENOENT) return marks;
    throw std::runtime_error("state file '" + path + "': cannot read: " + std::strerror(errno));
  }
  std::string line;
  for (int n = 1; std::getline(in, line); ++n) {
    if (line.empty()) continue;
    std::istringstream fields(line);
    std::string kind, channel, signer, value, extra;
    fields >> kind >> channel >> signer >> value;
    const bool more = static_cast<bool>(fields >> extra);
    int64_t v = 0;
    bool ok = (kind == "sequence" || kind == "version") && !signer.empty() && !more;
    if (ok) {
      char* end = nullptr;
      errno = 0;
      v = std::strtoll(value.c_str(), &end, 10);
      ok = !value.empty() && *end == '\0' && errno == 0 && v >= 0;
    }
    if (!ok) {
      throw std::runtime_error("state file '" + path + "' line " + std::to_string(n) + ": '" +
                               line +
                               "' is not '<sequence|version> <channel> <signer> <value>' (remove "
                               "the file to forget what this process accepted)");
    }
    int64_t& mark = marks[Key{kind, channel, signer}];
    mark = std::max(mark, v);
  }
  return marks;
}

SeenStore::SeenStore(std::string path) : path_(std::move(path)), marks_(Read(path_)) {
  thread_ = std::thread([this] { Run(); });
}

SeenStore::~SeenStore() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

int64_t SeenStore::Sequence(const std::string& channel, const std::string& signer_hex) const {
  std::lock_guard<std::mutex> lock(mu_);
  const auto it = marks_.find(Key{"sequence", channel, signer_hex});
  return it == marks_.end() ? 0 : it->second;
}

int64_t SeenStore::Version(const std::string& channel, const std::string& signer_name) const {
  std::lock_guard<std::mutex> lock(mu_);
  const auto it = marks_.find(Key{"version", channel, signer_name});
  return it == marks_.end() ? 0 : it->second;
}

void SeenStore::RaiseSequence(const std::string& channel, const std::string& signer_hex,
                              int64_t value) {
  Raise(Key{"sequence", channel, signer_hex}, value);
}

void SeenStore::RaiseVersion(const std::string& channel, const std::string& signer_name,
                             int64_t value) {
  Raise(Key{"version", channel, signer_name}, value);
}

void SeenStore::Raise(const Key& key, int64_t value) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    int64_t& mark = marks_[key];
    if (value <= mark) return;
    mark = value;
    dirty_ = true;
  }
  cv_.notify_all();
}

std::string SeenStore::Flush() {
  std::unique_lock<std::mutex> lock(mu_);
  cv_.wait(lock, [this] { return !dirty_ && !writing_; });
  return std::exchange(error_, std::string());
}

std::string SeenStore::TakeError() {
  std::lock_guard<std::mutex> lock(mu_);
  return std::exchange(error_, std::string());
}

void SeenStore::Run() {
  std::unique_lock<std::mutex> lock(mu_);
  for (;;) {
    cv_.wait(lock, [this] { return stop_ || dirty_; });
    if (!dirty_) return;  // stopping with nothing left to write
    std::map<Key, int64_t> marks = marks_;
    dirty_ = false;
    writing_ = true;
    lock.unlock();
    std::string error;
    try {
      const size_t slash = path_.rfind('/');
      if (slash != std::string::npos && slash > 0) MakeDirs(path_.substr(0, slash));
      // Another instance with the same state file may have raised marks meanwhile: keep the
      // larger of each.
      for (const auto& [key, value] : Read(path_)) {
        int64_t& mark = marks[key];
        mark = std::max(mark, value);
      }
      std::string text;
      for (const auto& [key, value] : marks) {
        text += std::get<0>(key) + " " + std::get<1>(key) + " " + std::get<2>(key) + " " +
                std::to_string(value) + "\n";
      }
      WriteFileAtomic(path_, text);
    } catch (const std::exception& e) {
      error = e.what();
    }
    lock.lock();
    writing_ = false;
    if (!error.empty()) error_ = error;
    cv_.notify_all();
  }
}

}  // namespace ftcal::auth
