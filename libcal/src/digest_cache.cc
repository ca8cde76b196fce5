// DigestCache (digest_cache.h).
#include "ftcal/digest_cache.h"

#include <sys/stat.h>

#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "ftcal/calibration_io.h"

namespace ftcal {

namespace {

constexpr const char* kEntryTag = "ftcal-sha256-v1";

bool IsSha256Hex(const std::string& s) {
  if (s.size() != 64) return false;
  for (char c : s) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

int64_t Nanoseconds(const timespec& t) {
  return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + static_cast<int64_t>(t.tv_nsec);
}

// The kinds of note (DigestCache::StoreNote): a folder each, the only ones pruned besides sha256.
constexpr const char* kSpansKind = "spans";
constexpr const char* kNoteTag = "ftcal-note-v1";

const char* TagOf(const std::string& kind) { return kind == "sha256" ? kEntryTag : kNoteTag; }

}  // namespace

// One entry file: "<tag> <size> <mtime_ns> <ctime_ns> <field>", the file's path, then a body.
// A digest's field is its hex and it has no body; a note's field is the length of its body.
// The device and inode are the entry's name.
struct DigestCache::Entry {
  int64_t size = 0, mtime_ns = 0, ctime_ns = 0;
  std::string field, path, body;
  bool Holds(const FileKey& key) const {
    return size == key.size && mtime_ns == key.mtime_ns && ctime_ns == key.ctime_ns;
  }
};

// nullopt for a file that is not a whole entry of this version and kind.
std::optional<DigestCache::Entry> DigestCache::ReadEntry(const std::string& file,
                                                         const std::string& kind) {
  std::ifstream in(file, std::ios::binary);
  std::string tag;
  Entry e;
  if (!(in >> tag >> e.size >> e.mtime_ns >> e.ctime_ns >> e.field) || tag != TagOf(kind) ||
      in.get() != '\n' || !std::getline(in, e.path)) {
    return std::nullopt;
  }
  if (kind == "sha256") {
    if (!IsSha256Hex(e.field)) return std::nullopt;
    return e;
  }
  int64_t body_bytes = -1;
  if (!(std::istringstream(e.field) >> body_bytes) || body_bytes < 0 ||
      body_bytes > (int64_t{64} << 20)) {
    return std::nullopt;
  }
  e.body.resize(static_cast<size_t>(body_bytes));
  if (!in.read(e.body.data(), body_bytes) || in.peek() != std::char_traits<char>::eof()) {
    return std::nullopt;  // cut short, or more than it says
  }
  return e;
}

std::optional<FileKey> FileKeyOf(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return std::nullopt;
  return FileKeyOf(st);
}

std::optional<FileKey> FileKeyOf(const struct stat& st) {
  if (!S_ISREG(st.st_mode)) return std::nullopt;
  FileKey key;
  key.device = static_cast<uint64_t>(st.st_dev);
  key.inode = static_cast<uint64_t>(st.st_ino);
  key.size = static_cast<int64_t>(st.st_size);
  key.mtime_ns = Nanoseconds(st.st_mtim);
  key.ctime_ns = Nanoseconds(st.st_ctim);
  return key;
}

DigestCache DigestCache::FromEnvironment() {
  if (const char* dir = std::getenv("FTCAL_CACHE_DIR")) return DigestCache(dir);
  const char* xdg = std::getenv("XDG_CACHE_HOME");
  if (xdg != nullptr && xdg[0] == '/') return DigestCache(std::string(xdg) + "/ftcal");
  const char* home = std::getenv("HOME");
  if (home != nullptr && home[0] == '/') return DigestCache(std::string(home) + "/.cache/ftcal");
  return DigestCache("");
}

std::string DigestCache::EntryPath(const std::string& kind, const FileKey& key) const {
  return dir_ + "/" + kind + "/" + std::to_string(key.device) + "-" + std::to_string(key.inode);
}

std::optional<std::string> DigestCache::Lookup(const std::string& path) const {
  std::optional<Entry> entry = Find("sha256", path);
  if (!entry) return std::nullopt;
  return std::move(entry->field);
}

std::optional<std::string> DigestCache::LookupNote(const std::string& kind,
                                                   const std::string& path) const {
  if (kind != kSpansKind) return std::nullopt;
  std::optional<Entry> entry = Find(kind, path);
  if (!entry) return std::nullopt;
  return std::move(entry->body);
}

std::optional<DigestCache::Entry> DigestCache::Find(const std::string& kind,
                                                    const std::string& path) const {
  if (!enabled()) return std::nullopt;
  const std::optional<FileKey> key = FileKeyOf(path);
  if (!key) return std::nullopt;
  std::optional<Entry> entry = ReadEntry(EntryPath(kind, *key), kind);
  if (!entry || !entry->Holds(*key)) return std::nullopt;
  return entry;
}

bool DigestCache::StoreNote(const std::string& kind, const std::string& path,
                            const FileKey& key_before, const std::string& body,
                            double settled_s) const {
  if (kind != kSpansKind || !Settled(key_before, settled_s)) return false;
  return WriteEntry(kind, path, key_before, std::to_string(body.size()), body);
}

bool DigestCache::Settled(const FileKey& key_before, double settled_s) const {
  timespec now{};
  ::clock_gettime(CLOCK_REALTIME, &now);
  return static_cast<double>(Nanoseconds(now) - key_before.ctime_ns) >= settled_s * 1e9;
}

bool DigestCache::Store(const std::string& path, const FileKey& key_before,
                        const std::string& sha256_hex, double settled_s) const {
  if (!Settled(key_before, settled_s)) return false;
  // Settled, and StoreWritten() checks that the file still has the key it was hashed under.
  return StoreWritten(path, key_before, sha256_hex);
}

bool DigestCache::StoreWritten(const std::string& path, const FileKey& key_written,
                               const std::string& sha256_hex) const {
  if (!IsSha256Hex(sha256_hex)) return false;
  return WriteEntry("sha256", path, key_written, sha256_hex, "");
}

bool DigestCache::WriteEntry(const std::string& kind, const std::string& path, const FileKey& key,
                             const std::string& field, const std::string& body) const {
  if (!enabled()) return false;
  const std::optional<FileKey> now = FileKeyOf(path);
  if (!now || !(*now == key)) return false;  // changed, or replaced, since
  std::error_code ec;
  std::filesystem::create_directories(dir_ + "/" + kind, ec);
  if (ec) return false;
  std::ostringstream entry;
  entry << TagOf(kind) << ' ' << key.size << ' ' << key.mtime_ns << ' ' << key.ctime_ns << ' '
        << field << '\n'
        << std::filesystem::absolute(path, ec).string() << '\n'
        << body;
  try {
    WriteFileAtomic(EntryPath(kind, key), entry.str());
  } catch (const std::exception&) {
    return false;  // a read-only home, a full disk: the next run hashes (or reads) again
  }
  PruneWhenDue();
  return true;
}

void DigestCache::PruneWhenDue() const {
  // The stamp's mtime is when the cache was last pruned.
  const std::string stamp = dir_ + "/sha256.pruned";
  struct stat st {};
  timespec now{};
  ::clock_gettime(CLOCK_REALTIME, &now);
  if (::stat(stamp.c_str(), &st) == 0 &&
      static_cast<double>(Nanoseconds(now) - Nanoseconds(st.st_mtim)) < kPruneEveryS * 1e9) {
    return;
  }
  std::ofstream(stamp, std::ios::trunc) << "last pruned\n";
  Prune();
}

int DigestCache::Prune() const {
  if (!enabled()) return 0;
  namespace fs = std::filesystem;
  std::error_code ec;
  int removed = 0;
  // Only the folders this code writes: $FTCAL_CACHE_DIR may be a directory shared with others.
  for (const std::string kind : {"sha256", kSpansKind}) {
    for (const fs::directory_entry& e : fs::directory_iterator(dir_ + "/" + kind, ec)) {
      const std::string name = e.path().filename().string();
      if (name.empty() || name[0] == '.') continue;  // a writer's temporary file
      const std::optional<Entry> entry = ReadEntry(e.path().string(), kind);
      const std::optional<FileKey> key = entry ? FileKeyOf(entry->path) : std::nullopt;
      const bool holds =
          key && fs::path(EntryPath(kind, *key)).filename() == name && entry->Holds(*key);
      if (!holds && fs::remove(e.path(), ec)) ++removed;
    }
  }
  return removed;
}

}  // namespace ftcal
