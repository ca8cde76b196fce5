// DigestCache: a stored digest comes back only while the file is the one that was hashed; any
// write, a file still being written, or a fresh file is a miss; a broken entry is a miss.
#include "ftcal/digest_cache.h"

#include <gtest/gtest.h>
#include <stdlib.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <optional>
#include <string>
#include <thread>

#include "ftcal/config.h"

namespace ftcal {
namespace {

namespace fs = std::filesystem;

class DigestCacheTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "ftcal_digest_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
    file_ = dir_ + "/session.lcmlog";
    Write("the bytes of a log");
  }
  void TearDown() override { fs::remove_all(dir_); }

  void Write(const std::string& bytes, std::ios::openmode mode = std::ios::trunc) {
    std::ofstream(file_, std::ios::binary | mode) << bytes;
  }
  // Past the kernel's timestamp tick (a jiffy, at most 10 ms): a write now gets a later ctime.
  static void NextTick() { std::this_thread::sleep_for(std::chrono::milliseconds(30)); }

  std::string dir_, file_;
};

TEST_F(DigestCacheTest, GivesTheStoredDigestWhileTheFileIsUnchanged) {
  const DigestCache cache(dir_ + "/cache");
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
  const std::string hex = Sha256File(file_);
  ASSERT_TRUE(cache.Store(file_, *FileKeyOf(file_), hex, /*settled_s=*/0.0));
  EXPECT_EQ(cache.Lookup(file_), hex);
  // Kept on disk: a later run (another object on the same directory) finds it.
  EXPECT_EQ(DigestCache(dir_ + "/cache").Lookup(file_), hex);
  // Even a new link changes the ctime (the link count is the inode's): conservative, a miss.
  fs::create_hard_link(file_, dir_ + "/link.lcmlog");
  EXPECT_EQ(cache.Lookup(dir_ + "/link.lcmlog"), std::nullopt);
}

TEST_F(DigestCacheTest, AnyWriteAfterwardsIsAMiss) {
  const DigestCache cache(dir_ + "/cache");
  auto store = [&] {
    ASSERT_TRUE(cache.Store(file_, *FileKeyOf(file_), Sha256File(file_), 0.0));
    ASSERT_TRUE(cache.Lookup(file_).has_value());
    NextTick();
  };
  store();
  Write("the bytes of a log");  // the same bytes again: still a write
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
  store();
  Write("THE BYTES OF A LOG");  // same size, other bytes
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
  store();
  Write("more", std::ios::app);
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
  store();
  fs::last_write_time(file_, fs::last_write_time(file_) - std::chrono::hours(1));
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
  store();
  fs::rename(file_, file_ + ".moved");  // renaming changes the ctime too
  fs::rename(file_ + ".moved", file_);
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
}

TEST_F(DigestCacheTest, StoresNeitherAFileChangedWhileReadNorOneTooFreshToTrust) {
  const DigestCache cache(dir_ + "/cache");
  const FileKey before = *FileKeyOf(file_);
  const std::string hex = Sha256File(file_);
  NextTick();
  Write("appended while it was hashed", std::ios::app);
  EXPECT_FALSE(cache.Store(file_, before, hex, 0.0));
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
  // Written just now: a write within the same tick would leave the key as it is.
  EXPECT_FALSE(cache.Store(file_, *FileKeyOf(file_), Sha256File(file_)));
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);
}

// A writer's digest (StoreWritten) is stored at once, without the settling time a reader's
// needs, but only while the file still has the key the writer took after its last change: not
// once the file was written to again, nor once another file took its name.
TEST_F(DigestCacheTest, AWritersDigestIsStoredAtOnceUnderTheKeyItsWriterTook) {
  const DigestCache cache(dir_ + "/cache");
  const std::string hex = Sha256File(file_);
  EXPECT_FALSE(cache.Store(file_, *FileKeyOf(file_), hex)) << "a reader's store of a fresh file";
  ASSERT_TRUE(cache.StoreWritten(file_, *FileKeyOf(file_), hex));
  EXPECT_EQ(cache.Lookup(file_), hex);
  EXPECT_FALSE(cache.StoreWritten(file_, *FileKeyOf(file_), "not a digest"));

  const FileKey written = *FileKeyOf(file_);
  NextTick();
  Write("the bytes of a lot");  // same size, other bytes
  EXPECT_FALSE(cache.StoreWritten(file_, written, hex)) << "the file changed since its writer";
  EXPECT_EQ(cache.Lookup(file_), std::nullopt);

  const FileKey before = *FileKeyOf(file_);
  const std::string other = dir_ + "/other.lcmlog";
  std::ofstream(other, std::ios::binary) << "the bytes of a lot";
  fs::rename(other, file_);
  EXPECT_FALSE(cache.StoreWritten(file_, before, Sha256File(file_)))
      << "another file renamed onto the name";
  EXPECT_FALSE(DigestCache("").StoreWritten(file_, *FileKeyOf(file_), Sha256File(file_)));
}

// Pruning removes exactly the entries that can never hold again: a removed file's, a changed
// file's; the entry of a file unchanged stays and still hits. A store prunes when the last
// pruning is a day old, and not again the same day.
TEST_F(DigestCacheTest, PruningRemovesTheEntriesOfFilesGoneOrChanged) {
  const DigestCache cache(dir_ + "/cache");
  const std::string gone = dir_ + "/gone.lcmlog", changed = dir_ + "/changed.lcmlog";
  std::ofstream(gone) << "a log removed later";
  std::ofstream(changed) << "a log changed later";
  for (const std::string& f : {file_, gone, changed}) {
    ASSERT_TRUE(cache.StoreWritten(f, *FileKeyOf(f), Sha256File(f))) << f;
  }
  auto entries = [&] {
    int n = 0;
    for (const auto& e : fs::directory_iterator(dir_ + "/cache/sha256")) {
      if (e.path().filename().string()[0] != '.') ++n;
    }
    return n;
  };
  ASSERT_EQ(entries(), 3);
  fs::remove(gone);
  NextTick();
  std::ofstream(changed, std::ios::app) << ", appended";
  std::ofstream(dir_ + "/cache/sha256/1-2") << "not an entry\n";
  EXPECT_EQ(cache.Prune(), 3);
  EXPECT_EQ(entries(), 1);
  EXPECT_EQ(cache.Lookup(file_), Sha256File(file_));
  EXPECT_EQ(cache.Prune(), 0);

  // Due: the stamp is older than a day (set back), so the next store prunes.
  const std::string stamp = dir_ + "/cache/sha256.pruned";
  ASSERT_TRUE(fs::exists(stamp)) << "the first store did not prune";
  std::ofstream(dir_ + "/cache/sha256/3-4") << "not an entry either\n";
  std::ofstream(changed, std::ios::app) << " again";
  ASSERT_TRUE(cache.StoreWritten(changed, *FileKeyOf(changed), Sha256File(changed)));
  EXPECT_TRUE(fs::exists(dir_ + "/cache/sha256/3-4")) << "pruned twice the same day";
  fs::last_write_time(stamp, fs::file_time_type::clock::now() - std::chrono::hours(25));
  ASSERT_TRUE(cache.StoreWritten(changed, *FileKeyOf(changed), Sha256File(changed)));
  EXPECT_FALSE(fs::exists(dir_ + "/cache/sha256/3-4")) << "a day-old stamp, and no pruning";
  EXPECT_EQ(entries(), 2);
}

TEST_F(DigestCacheTest, BrokenEntriesAndADisabledCacheMiss) {
  const DigestCache off("");
  EXPECT_FALSE(off.enabled());
  EXPECT_FALSE(off.Store(file_, *FileKeyOf(file_), Sha256File(file_), 0.0));
  EXPECT_EQ(off.Lookup(file_), std::nullopt);

  const DigestCache cache(dir_ + "/cache");
  EXPECT_FALSE(cache.Store(file_, *FileKeyOf(file_), "not a digest", 0.0));
  ASSERT_TRUE(cache.Store(file_, *FileKeyOf(file_), Sha256File(file_), 0.0));
  ASSERT_EQ(std::distance(fs::directory_iterator(dir_ + "/cache/sha256"), {}), 1);
  const fs::path entry = fs::directory_iterator(dir_ + "/cache/sha256")->path();
  for (const std::string& broken :
       {std::string(""), std::string("garbage\n"), std::string("ftcal-sha256-v1 18 1 2 abc\n")}) {
    std::ofstream(entry, std::ios::trunc) << broken;
    EXPECT_EQ(cache.Lookup(file_), std::nullopt) << "entry '" << broken << "'";
  }
  EXPECT_EQ(cache.Lookup(dir_ + "/no such file"), std::nullopt);
  EXPECT_EQ(cache.Lookup(dir_), std::nullopt);  // not a regular file
  // A cache directory that cannot be made is a miss, not an error.
  const DigestCache unwritable(file_ + "/cache");
  EXPECT_FALSE(unwritable.Store(file_, *FileKeyOf(file_), Sha256File(file_), 0.0));
}

// A note (the calibrator's span index) lives by the digest's rule: back while the file is
// unchanged, any bytes included; stored only when settled and unchanged since its key was
// taken; a miss once the file changes, and pruned then; cut short or overlong, a miss; only
// the kinds the cache knows (Prune() cleans no folder it did not write).
TEST_F(DigestCacheTest, ANoteLivesAsLongAsTheFileItDescribes) {
  const DigestCache cache(dir_ + "/cache");
  std::string body = "span {\n  from_offset: 10\n}\n";
  body.push_back('\0');
  body += "\nbinary too";
  EXPECT_EQ(cache.LookupNote("spans", file_), std::nullopt);
  EXPECT_FALSE(cache.StoreNote("spans", file_, *FileKeyOf(file_), body)) << "not settled";
  EXPECT_FALSE(cache.StoreNote("other", file_, *FileKeyOf(file_), body, 0.0)) << "unknown kind";
  EXPECT_FALSE(fs::exists(dir_ + "/cache/other"));
  ASSERT_TRUE(cache.StoreNote("spans", file_, *FileKeyOf(file_), body, 0.0));
  EXPECT_EQ(cache.LookupNote("spans", file_), body);
  EXPECT_EQ(cache.Lookup(file_), std::nullopt) << "a note is not a digest";

  const fs::path entry = fs::directory_iterator(dir_ + "/cache/spans")->path();
  std::string whole;
  {
    std::ifstream in(entry, std::ios::binary);
    whole.assign(std::istreambuf_iterator<char>(in), {});
  }
  for (const std::string& broken : {whole.substr(0, whole.size() - 1), whole + "x"}) {
    std::ofstream(entry, std::ios::binary | std::ios::trunc) << broken;
    EXPECT_EQ(cache.LookupNote("spans", file_), std::nullopt);
  }
  std::ofstream(entry, std::ios::binary | std::ios::trunc) << whole;
  ASSERT_EQ(cache.LookupNote("spans", file_), body);

  const FileKey before = *FileKeyOf(file_);
  NextTick();
  Write(", appended", std::ios::app);
  EXPECT_EQ(cache.LookupNote("spans", file_), std::nullopt);
  EXPECT_FALSE(cache.StoreNote("spans", file_, before, body, 0.0)) << "changed since its key";
  EXPECT_EQ(cache.Prune(), 1);
  EXPECT_FALSE(fs::exists(entry));
}

TEST(DigestCacheEnvironment, FtcalCacheDirThenXdgThenHome) {
  auto keep = [](const char* name) -> std::optional<std::string> {
    const char* v = std::getenv(name);
    return v ? std::optional<std::string>(v) : std::nullopt;
  };
  const auto ftcal = keep("FTCAL_CACHE_DIR"), xdg = keep("XDG_CACHE_HOME"), home = keep("HOME");
  ::setenv("FTCAL_CACHE_DIR", "/tmp/one", 1);
  ::setenv("XDG_CACHE_HOME", "/tmp/two", 1);
  ::setenv("HOME", "/tmp/three", 1);
  EXPECT_EQ(DigestCache::FromEnvironment().dir(), "/tmp/one");
  ::setenv("FTCAL_CACHE_DIR", "", 1);
  EXPECT_FALSE(DigestCache::FromEnvironment().enabled());
  ::unsetenv("FTCAL_CACHE_DIR");
  EXPECT_EQ(DigestCache::FromEnvironment().dir(), "/tmp/two/ftcal");
  ::setenv("XDG_CACHE_HOME", "relative", 1);  // the XDG rule: only absolute paths count
  EXPECT_EQ(DigestCache::FromEnvironment().dir(), "/tmp/three/.cache/ftcal");
  ::unsetenv("XDG_CACHE_HOME");
  ::unsetenv("HOME");
  EXPECT_FALSE(DigestCache::FromEnvironment().enabled());
  auto restore = [](const char* name, const std::optional<std::string>& v) {
    if (v) {
      ::setenv(name, v->c_str(), 1);
    } else {
      ::unsetenv(name);
    }
  };
  restore("FTCAL_CACHE_DIR", ftcal);
  restore("XDG_CACHE_HOME", xdg);
  restore("HOME", home);
}

}  // namespace
}  // namespace ftcal
