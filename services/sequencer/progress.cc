#include "sequencer/progress.h"

#include <fstream>
#include <stdexcept>
#include <utility>

#include "ftcal/calibration_io.h"

namespace ftcal::sequencer {

std::optional<Progress> LoadProgress(const std::string& path) {
  std::ifstream in(path);
  if (!in) return std::nullopt;
  Progress p;
  std::string line;
  int n = 0;
  bool have_step = false;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty()) continue;
    const size_t sp = line.find(' ');
    const std::string key = line.substr(0, sp);
    const std::string value = sp == std::string::npos ? "" : line.substr(sp + 1);
    if (key == "plan") {
      p.plan = value;
    } else if (key == "next_step") {
      try {
        size_t used = 0;
        p.next_step = std::stoi(value, &used);
        if (used != value.size() || p.next_step < 0) throw std::invalid_argument(value);
      } catch (const std::exception&) {
        throw std::runtime_error(path + ":" + std::to_string(n) + ": next_step '" + value +
                                 "' is not a step number");
      }
      have_step = true;
    } else if (key == "session") {
      p.session_id = value;
    } else {
      throw std::runtime_error(path + ":" + std::to_string(n) + ": unknown key '" + key + "'");
    }
  }
  if (p.plan.empty() || !have_step) {
    throw std::runtime_error(path + ": a progress file needs 'plan' and 'next_step' lines");
  }
  return p;
}

void SaveProgress(const std::string& path, const Progress& p) {
  WriteFileAtomic(path, "plan " + p.plan + "\nnext_step " + std::to_string(p.next_step) +
                            "\nsession " + p.session_id + "\n");
}

ProgressSaver::ProgressSaver(std::string path)
    : path_(std::move(path)), thread_([this] { Run(); }) {}

ProgressSaver::~ProgressSaver() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

void ProgressSaver::Save(const Progress& progress) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    pending_ = progress;
  }
  cv_.notify_all();
}

std::string ProgressSaver::Flush() {
  std::unique_lock<std::mutex> lock(mu_);
  cv_.wait(lock, [this] { return !pending_ && !writing_; });
  return std::exchange(error_, std::string());
}

std::string ProgressSaver::TakeError() {
  std::lock_guard<std::mutex> lock(mu_);
  return std::exchange(error_, std::string());
}

void ProgressSaver::Run() {
  std::unique_lock<std::mutex> lock(mu_);
  for (;;) {
    cv_.wait(lock, [this] { return stop_ || pending_.has_value(); });
    if (!pending_) return;  // stopping with nothing left to write
    const Progress p = *std::exchange(pending_, std::nullopt);
    writing_ = true;
    lock.unlock();
    std::string error;
    try {
      SaveProgress(path_, p);
    } catch (const std::exception& e) {
      error = e.what();
    }
    lock.lock();
    writing_ = false;
    if (!error.empty()) error_ = error;
    cv_.notify_all();
  }
}

}  // namespace ftcal::sequencer
