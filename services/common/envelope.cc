#include "common/envelope.h"

#include <fcntl.h>
#include <sodium.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <stdexcept>

namespace ftcal::auth {
namespace {

void PutBe(std::vector<uint8_t>& out, uint64_t v, int bytes) {
  for (int i = bytes - 1; i >= 0; --i) out.push_back(static_cast<uint8_t>(v >> (8 * i)));
}

int HexDigit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

// 2n hex digits into `out[0, n)`; false on anything else.
bool FromHex(const std::string& hex, uint8_t* out, size_t n) {
  if (hex.size() != 2 * n) return false;
  for (size_t i = 0; i < n; ++i) {
    const int hi = HexDigit(hex[2 * i]), lo = HexDigit(hex[2 * i + 1]);
    if (hi < 0 || lo < 0) return false;
    out[i] = static_cast<uint8_t>(hi << 4 | lo);
  }
  return true;
}

}  // namespace

void InitSodium() {
  if (sodium_init() < 0) throw std::runtime_error("libsodium could not be initialised");
}

std::string ToHex(const uint8_t* bytes, size_t n) {
  static constexpr char kHex[] = "0123456789abcdef";
  std::string hex;
  hex.reserve(2 * n);
  for (size_t i = 0; i < n; ++i) {
    hex += kHex[bytes[i] >> 4];
    hex += kHex[bytes[i] & 0xf];
  }
  return hex;
}

PublicKey PublicKeyFromHex(const std::string& hex, const std::string& what) {
  PublicKey key{};
  if (!FromHex(hex, key.data(), key.size())) {
    throw std::invalid_argument(what + ": '" + hex +
                                "' is not an Ed25519 public key (64 hex "
                                "digits)");
  }
  return key;
}

std::vector<uint8_t> SignedBytes(const std::string& channel, const signed_envelope_t& e) {
  std::vector<uint8_t> out(sizeof kDomainTag);  // the tag with its NUL
  std::memcpy(out.data(), kDomainTag, sizeof kDomainTag);
  out.reserve(out.size() + 4 + channel.size() + 32 + 28 + e.payload.size());
  PutBe(out, channel.size(), 4);
  out.insert(out.end(), channel.begin(), channel.end());
  out.insert(out.end(), e.signer, e.signer + kPublicKeyBytes);
  PutBe(out, static_cast<uint64_t>(e.sequence), 8);
  PutBe(out, static_cast<uint64_t>(e.utime), 8);
  PutBe(out, static_cast<uint64_t>(e.inner_fingerprint), 8);
  PutBe(out, static_cast<uint32_t>(e.size), 4);
  out.insert(out.end(), e.payload.begin(), e.payload.end());
  return out;
}

// ---- Signer ----

Signer Signer::FromSeed(const std::array<uint8_t, kSeedBytes>& seed) {
  InitSodium();
  Signer s;
  crypto_sign_seed_keypair(s.public_key_.data(), s.secret_key_.data(), seed.data());
  return s;
}

Signer Signer::FromSeedFile(const std::string& path) {
  const std::string what = "signing key '" + path + "'";
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
  if (fd < 0) throw std::runtime_error(what + ": cannot open: " + std::strerror(errno));
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    throw std::runtime_error(what + ": not a regular file");
  }
  // Refused before the seed is read: a key others can read is no longer only ours.
  if (st.st_uid != ::geteuid()) {
    ::close(fd);
    throw std::runtime_error(what + ": owned by uid " + std::to_string(st.st_uid) +
                             ", not by this user (" + std::to_string(::geteuid()) + ")");
  }
  if ((st.st_mode & (S_IRWXG | S_IRWXO)) != 0) {
    ::close(fd);
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    throw std::runtime_error(what + ": mode " + mode + " lets group or others at it; chmod 600 " +
                             path);
  }
  char text[80] = {};
  ssize_t got = 0;
  for (ssize_t r; (r = ::read(fd, text + got, sizeof text - 1 - static_cast<size_t>(got))) != 0;) {
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) {
      const int err = errno;
      ::close(fd);
      throw std::runtime_error(what + ": cannot read: " + std::strerror(err));
    }
    got += r;
    if (static_cast<size_t>(got) == sizeof text - 1) break;
  }
  ::close(fd);
  std::string hex(text, static_cast<size_t>(got));
  if (!hex.empty() && hex.back() == '\n') hex.pop_back();
  std::array<uint8_t, kSeedBytes> seed{};
  const bool ok = FromHex(hex, seed.data(), seed.size());
  sodium_memzero(text, sizeof text);
  sodium_memzero(hex.data(), hex.size());
  if (!ok) throw std::runtime_error(what + ": not a seed (64 hex digits; ftcal-keygen makes one)");
  Signer s = FromSeed(seed);
  sodium_memzero(seed.data(), seed.size());
  return s;
}

Signer::Signer(Signer&& other) noexcept
    : secret_key_(other.secret_key_),
      public_key_(other.public_key_),
      last_sequence_(other.last_sequence_) {
  sodium_memzero(other.secret_key_.data(), other.secret_key_.size());
}

Signer::~Signer() { sodium_memzero(secret_key_.data(), secret_key_.size()); }

signed_envelope_t Signer::Seal(const std::string& channel, const uint8_t* inner, int size,
                               int64_t utime) {
  if (size < 8) throw std::invalid_argument("Seal: an encoded message has its 8-byte fingerprint");
  signed_envelope_t e{};
  std::memcpy(e.signer, public_key_.data(), kPublicKeyBytes);
  // max(last + 1, now): see the header on sequences across restarts.
  last_sequence_ = std::max(last_sequence_ + 1, utime);
  e.sequence = last_sequence_;
  e.utime = utime;
  uint64_t fingerprint = 0;
  for (int i = 0; i < 8; ++i) fingerprint = fingerprint << 8 | inner[i];
  e.inner_fingerprint = static_cast<int64_t>(fingerprint);
  e.size = size;
  e.payload.assign(inner, inner + size);
  const std::vector<uint8_t> message = SignedBytes(channel, e);
  crypto_sign_detached(e.signature, nullptr, message.data(), message.size(), secret_key_.data());
  return e;
}

// ---- Verifier ----

Verifier::Verifier(std::vector<TrustedKey> keys) : keys_(std::move(keys)) {
  InitSodium();
  for (const TrustedKey& k : keys_) key_hex_.push_back(ToHex(k.key.data(), k.key.size()));
}

void Verifier::Persist(std::shared_ptr<SeenStore> store) { store_ = std::move(store); }

Verifier Verifier::FromConfig(const config::Config& config) {
  std::vector<TrustedKey> keys;
  for (const config::TrustedKey& k : config.auth().trusted_key()) {
    keys.push_back({k.name(),
                    PublicKeyFromHex(k.public_key_hex(), "auth.trusted_key " + k.name()),
                    {k.channel().begin(), k.channel().end()}});
  }
  Verifier v(std::move(keys));
  v.set_max_ahead_us(static_cast<int64_t>(config.auth().max_clock_ahead_s() * 1e6));
  return v;
}

bool Verifier::Trusts(const std::string& channel) const {
  for (const TrustedKey& k : keys_) {
    if (k.channels.count(channel)) return true;
  }
  return false;
}

std::pair<std::optional<Opened>, std::optional<wire::Refusal>> Verifier::Open(
    const std::string& channel, const void* data, int size, uint64_t inner_fingerprint,
    int64_t recv_utime, int64_t window_us) {
  auto refuse = [](std::string kind, std::string detail) {
    return std::make_pair(std::optional<Opened>(), std::optional<wire::Refusal>(wire::Refusal{
                                                       std::move(kind), std::move(detail)}));
  };
  if (size >= 8) {
    uint64_t fingerprint = 0;
    for (int i = 0; i < 8; ++i)
      fingerprint = fingerprint << 8 | static_cast<const uint8_t*>(data)[i];
    if (fingerprint == inner_fingerprint) {
      ++unsigned_seen_;
      return refuse("unsigned", "a bare message where a signed envelope is required");
    }
  }
  if (auto refused = wire::Decode(data, size, &envelope_)) {
    refused->kind = "malformed envelope (" + refused->kind + ")";
    return {std::nullopt, refused};
  }
  const signed_envelope_t& e = envelope_;
  size_t key = keys_.size();
  for (size_t i = 0; i < keys_.size(); ++i) {
    if (std::memcmp(keys_[i].key.data(), e.signer, kPublicKeyBytes) == 0) key = i;
  }
  if (key == keys_.size()) {
    // One kind for every unknown key: a kind per key would let anyone grow the counts (and the
    // log) by signing with fresh keys. The first one is logged with its key.
    return refuse("untrusted signer", "signer " + ToHex(e.signer, kPublicKeyBytes) +
                                          " is not in the config's auth.trusted_key");
  }
  const std::string& name = keys_[key].name;
  if (keys_[key].channels.count(channel) == 0) {
    return refuse("not allowed on channel from " + name,
                  name + " may not sign " + channel + " (auth.trusted_key.channel)");
  }
  if (static_cast<uint64_t>(e.inner_fingerprint) != inner_fingerprint || e.payload.size() < 8) {
    return refuse("wrong inner type from " + name, "the envelope holds another message type");
  }
  const std::vector<uint8_t> message = SignedBytes(channel, e);
  if (crypto_sign_verify_detached(e.signature, message.data(), message.size(), e.signer) != 0) {
    return refuse("bad signature from " + name, "the signature does not verify");
  }
  // The payload's own fingerprint is covered by the signature; it must agree with the one
  // signed beside it, or the decoder would be handed another type.
  uint64_t payload_fingerprint = 0;
  for (int i = 0; i < 8; ++i) payload_fingerprint = payload_fingerprint << 8 | e.payload[i];
  if (payload_fingerprint != inner_fingerprint) {
    return refuse("wrong inner type from " + name, "payload fingerprint differs");
  }
  int64_t& last = last_sequence_[{key, channel}];
  if (store_) last = std::max(last, store_->Sequence(channel, key_hex_[key]));
  if (e.sequence <= last) {
    return refuse(
        "replayed from " + name,
        "sequence " + std::to_string(e.sequence) + " not above " + std::to_string(last) +
            (store_ ? ", the last accepted here (also before a restart: " + store_->path() + ")"
                    : std::string(", the last accepted here")));
  }
  // Differences of wire values in 128 bits: a signer may put any int64 there.
  const __int128 utime_ahead = static_cast<__int128>(e.utime) - recv_utime;
  const __int128 sequence_ahead = static_cast<__int128>(e.sequence) - recv_utime;
  // Not adopted: a sequence far ahead would refuse every honest envelope of its signer after it.
  if (utime_ahead > max_ahead_us_ || sequence_ahead > max_ahead_us_) {
    const __int128 ahead = std::max(utime_ahead, sequence_ahead);
    return refuse("ahead of time from " + name,
                  (sequence_ahead > max_ahead_us_ ? "sequence " : "signing time ") +
                      std::to_string(static_cast<long double>(ahead) / 1e6L) +
                      " s ahead of the receive time (limit " +
                      std::to_string(max_ahead_us_ / 1000) +
                      " ms, auth.max_clock_ahead_s): is its signer's clock set ahead?");
  }
  if (window_us > 0 && (-utime_ahead > window_us || utime_ahead > window_us)) {
    const int64_t age_ms = static_cast<int64_t>(
        std::max<__int128>(std::min<__int128>(-utime_ahead / 1000, INT64_MAX), INT64_MIN));
    return refuse("stale from " + name,
                  "signed " + std::to_string(age_ms) + " ms before it was received (window " +
                      std::to_string(window_us / 1000) + " ms)" +
                      (age_ms > 10 * window_us / 1000
                           ? ": a live process takes only fresh envelopes (a recording played to "
                             "live processes? read it offline with --log or --replay)"
                           : ""));
  }
  last = e.sequence;
  if (store_) store_->RaiseSequence(channel, key_hex_[key], e.sequence);
  return {Opened{e.payload.data(), static_cast<int>(e.payload.size()), &name, e.sequence, e.utime},
          std::nullopt};
}

}  // namespace ftcal::auth
