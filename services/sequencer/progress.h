// The sequencer's progress file: where a run stands (the plan, the next resume point, the
// session), so that the next run of the same plan continues there (plan.h, "Resuming").
// Lines "plan NAME", "next_step N", "session ID"; written atomically.
#pragma once

#include <condition_variable>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

namespace ftcal::sequencer {

// Where the run stands, saved atomically after every finished unit of work.
struct Progress {
  std::string plan;
  int next_step = 0;  // the resume point to start from
  std::string session_id;
};
// nullopt when the file does not exist; throws std::runtime_error naming the file and line
// when it exists but cannot be read.
std::optional<Progress> LoadProgress(const std::string& path);
void SaveProgress(const std::string& path, const Progress& progress);

// Writes a progress file on a thread of its own. The atomic write ends in fsync, and on a disk
// busy with a recorder's log that can take seconds (ext4 commits the journal, and with it the
// log's pending data), while the sequencer must keep commanding the legs: in CI a sequencer
// blocked 3 s saving after a finished pose. Only the latest progress matters, so a Save
// replaces one not yet written.
class ProgressSaver {
 public:
  explicit ProgressSaver(std::string path);
  ~ProgressSaver();  // writes what is pending first
  ProgressSaver(const ProgressSaver&) = delete;
  ProgressSaver& operator=(const ProgressSaver&) = delete;

  void Save(const Progress& progress);
  // Waits until every Save so far is written; returns the error of a write that failed since
  // the last Flush or TakeError ("" when none).
  std::string Flush();
  // That error, without waiting.
  std::string TakeError();

 private:
  void Run();

  const std::string path_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::optional<Progress> pending_;
  bool writing_ = false;
  bool stop_ = false;
  std::string error_;
  std::thread thread_;
};

}  // namespace ftcal::sequencer
