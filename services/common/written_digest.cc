#include "common/written_digest.h"

#include <optional>

#include "ftcal/config.h"
#include "ftcal/digest_cache.h"

namespace ftcal {

// With the cache off (FTCAL_CACHE_DIR set empty) nothing would take the digest: no hashing.
WrittenDigest::WrittenDigest() {
  if (DigestCache::FromEnvironment().enabled()) sha_ = std::make_unique<Sha256>();
}
WrittenDigest::~WrittenDigest() = default;

std::function<void(const char* data, size_t size)> WrittenDigest::Tap() {
  if (!sha_) return {};
  return [sha = sha_.get()](const char* data, size_t size) { sha->Update(data, size); };
}

void WrittenDigest::Update(const void* data, size_t size) {
  if (sha_) sha_->Update(data, size);
}

std::string WrittenDigest::HandOver(const std::string& path, const struct stat& written) {
  if (!sha_) return "";
  const std::string hex = sha_->HexDigest();
  const std::optional<FileKey> key = FileKeyOf(written);
  if (!key || !DigestCache::FromEnvironment().StoreWritten(path, *key, hex)) return "";
  return hex;
}

}  // namespace ftcal
