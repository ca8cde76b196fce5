// SHA-256 digests of input files kept between runs, keyed by the file's identity and stat
// times, so a log calibrated again (another profile, the offset re-estimation, the demo's
// second run) is not hashed again: at report scale the hash was a fifth of the calibrator's
// CPU. The rule is git's index: an entry holds while the file's device, inode, size, mtime
// and ctime are the ones it was hashed under. Any write or rename changes the ctime, and no
// unprivileged process can set it back. Only a file that had settled (its ctime well before
// the hash began) is stored, since the kernel stamps ctime from a coarse clock: a write in
// the same tick as the hash would leave the key unchanged.
//
// The cache is a convenience: every failure to read or write it is a miss, never an error.
#pragma once

#include <sys/stat.h>

#include <cstdint>
#include <optional>
#include <string>

namespace ftcal {

struct FileKey {
  uint64_t device = 0;
  uint64_t inode = 0;
  int64_t size = 0;
  int64_t mtime_ns = 0;
  int64_t ctime_ns = 0;
  bool operator==(const FileKey& o) const {
    return device == o.device && inode == o.inode && size == o.size && mtime_ns == o.mtime_ns &&
           ctime_ns == o.ctime_ns;
  }
};

// nullopt when `path` cannot be stat'ed or is not a regular file.
std::optional<FileKey> FileKeyOf(const std::string& path);
// The key of a status already taken (a writer's, after its last change); nullopt for a status
// that is not a regular file's.
std::optional<FileKey> FileKeyOf(const struct stat& st);

class DigestCache {
 public:
  // Entries live in `dir`/sha256/; an empty `dir` is a cache that never hits nor stores.
  explicit DigestCache(std::string dir) : dir_(std::move(dir)) {}
  // $FTCAL_CACHE_DIR when set (set and empty: no cache), else $XDG_CACHE_HOME/ftcal, else
  // $HOME/.cache/ftcal, else none.
  static DigestCache FromEnvironment();

  // The digest stored for `path` when the file's key is still the one it was stored under.
  std::optional<std::string> Lookup(const std::string& path) const;
  // Stores `sha256_hex` for `path`, hashed from the file while its key was `key_before`: only
  // when the key is still that, and the file's ctime is at least `settled_s` before now.
  // Returns whether it stored.
  bool Store(const std::string& path, const FileKey& key_before, const std::string& sha256_hex,
             double settled_s = 2.0) const;
  // Stores the digest a writer took of the bytes it wrote (ftcal-sim log, the segmenter's poses
  // log, ftcal-record), when `path` still has `key_written`, the file's key after the writer's
  // last change (its rename or final flush): the first calibration of a new log then reads it
  // without hashing it. Unlike Store(), there is no waiting for the ctime to settle, because
  // the writer knows the content under that key. What it cannot see is another process
  // writing the same number of bytes into the file within the same clock tick (a few ms) as
  // the writer's own last change; a write at any later moment changes the ctime, and the
  // entry no longer holds.
  bool StoreWritten(const std::string& path, const FileKey& key_written,
                    const std::string& sha256_hex) const;

  // Another fact about a file, kept under the same rule as its digest: the calibrator's index
  // of a log (CalibrationCollector::TakeSpanIndex). `kind` names the folder of such entries:
  // "spans", the only kind so far (another is refused, so that Prune() knows every folder it may
  // clean); `body` is any bytes. LookupNote gives the body stored for `path` while its key holds;
  // StoreNote stores as Store() does (the key unchanged since `key_before`, the ctime settled).
  std::optional<std::string> LookupNote(const std::string& kind, const std::string& path) const;
  bool StoreNote(const std::string& kind, const std::string& path, const FileKey& key_before,
                 const std::string& body, double settled_s = 2.0) const;

  // Removes the entries (digests and notes) that can never hold again: their file is gone, or
  // is no longer the one they were stored under (any change moves the ctime on, and it never comes
  // back). Returns how many it removed. Storing runs it at most once a day (kPruneEveryS), so the
  // cache stays about as large as the set of logs that still exist.
  int Prune() const;
  static constexpr double kPruneEveryS = 24 * 3600.0;

  bool enabled() const { return !dir_.empty(); }
  const std::string& dir() const { return dir_; }

 private:
  std::string EntryPath(const std::string& kind, const FileKey& key) const;
  bool Settled(const FileKey& key_before, double settled_s) const;
  struct Entry;  // one entry file (digest_cache.cc)
  static std::optional<Entry> ReadEntry(const std::string& file, const std::string& kind);
  // The entry of `kind` for `path` while the file's key is the one it was stored under.
  std::optional<Entry> Find(const std::string& kind, const std::string& path) const;
  // Writes the entry of `kind` for `path` (digest_cache.cc's format) when `path` has `key` now.
  bool WriteEntry(const std::string& kind, const std::string& path, const FileKey& key,
                  const std::string& field, const std::string& body) const;
  void PruneWhenDue() const;
  std::string dir_;
};

}  // namespace ftcal
