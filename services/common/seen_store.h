// What a live receiver of signed channels has accepted, kept on disk so that a restarted process
// refuses it again: per signer and channel the highest sequence accepted, and per signer and
// channel the highest calibration version put in use (the corrector).
//
// A signature says who wrote a message, not when: a receiver that forgot its high-water marks on
// restart took a CONFIRM or a CALIBRATION it had taken before. The marks are written atomically
// (temporary file, fsync, rename) on a thread of their own, since an fsync on a disk busy with a
// recorder's log can take seconds and the receivers' loops must not wait (the sequencer feeds
// the Dynamixel bridge's dead-man from its loop). Only the latest marks matter, so a write
// replaces one not yet done; a mark accepted in the last write's time before a crash is the
// only one a restart can forget, and the channels' time windows refuse it once they pass.
//
// The file is text, one mark a line: `<kind> <channel> <signer> <value>` with kind `sequence`
// (signer: the public key in hex) or `version` (signer: the trusted key's name). Marks only
// rise: a write merges what the file holds (another instance of the same program with the same
// state directory) by taking the larger value.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <tuple>

namespace ftcal::auth {

class SeenStore {
 public:
  // Reads `path` (absent: no marks yet). Throws std::runtime_error naming the file and line of
  // anything it cannot read.
  explicit SeenStore(std::string path);
  ~SeenStore();  // writes what is pending first
  SeenStore(const SeenStore&) = delete;
  SeenStore& operator=(const SeenStore&) = delete;

  // The state directory of the processes of this user: $FTCAL_STATE_DIR, else systemd's
  // $STATE_DIRECTORY (the unit's StateDirectory=), else $XDG_STATE_HOME/ftcal, else
  // $HOME/.local/state/ftcal. Empty when none of them is set.
  static std::string DefaultDir();

  const std::string& path() const { return path_; }
  // 0 when nothing was accepted.
  int64_t Sequence(const std::string& channel, const std::string& signer_hex) const;
  int64_t Version(const std::string& channel, const std::string& signer_name) const;
  // Raise a mark (never lowers it) and have it written.
  void RaiseSequence(const std::string& channel, const std::string& signer_hex, int64_t value);
  void RaiseVersion(const std::string& channel, const std::string& signer_name, int64_t value);
  // Waits until every mark so far is written; returns the error of a write that failed since
  // the last Flush ("" when none).
  std::string Flush();
  // That error, without waiting.
  std::string TakeError();

  // The file's marks (exposed for tests).
  using Key = std::tuple<std::string, std::string, std::string>;  // kind, channel, signer
  static std::map<Key, int64_t> Read(const std::string& path);

 private:
  void Raise(const Key& key, int64_t value);
  void Run();

  const std::string path_;
  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::map<Key, int64_t> marks_;
  bool dirty_ = false;
  bool writing_ = false;
  bool stop_ = false;
  std::string error_;
  std::thread thread_;
};

}  // namespace ftcal::auth
