// Signed channels: SERVO_CMD, EXPERIMENT, CALIBRATION and SEQUENCER_CONTROL travel in a
// signed_envelope_t.
//
// Ed25519 (libsodium's crypto_sign_*), so a receiver holds public keys only and can verify but
// never forge; the config says which key may sign which channel, so reading a channel never
// grants writing it (LCMsec's group keys give both to every member). The signature covers a
// domain tag, the channel, the signer, a sequence number, the signing time, the inner type's
// fingerprint and the inner bytes. A receiver checks, in this order and before the inner
// message is decoded: the envelope's shape (wire guard), that the signer is trusted on this
// channel, the inner type, the signature, that the sequence rises (per signer and channel: a
// replayed envelope is refused however recent), that neither the signing time nor the sequence
// is ahead of the receive time by more than auth.max_clock_ahead_s (adopting a far-future
// sequence would lock its signer out until the clock caught up), and, where the channel has one,
// the time window against the receive time. Only a good envelope advances the sequence, so a
// forgery cannot block its signer. A live process keeps the sequences it accepted on disk
// (Persist, common/seen_store.h), so a restart does not forget them.
//
// Sequence numbers rise across restarts without state on disk: a signer starts at its clock in
// us and counts up from max(last + 1, now), so a restarted signer continues above what it sent
// before unless its clock stepped back (README, "Signed channels": keep clocks synchronised).
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "common/seen_store.h"
#include "common/wire_guard.h"
#include "ftcal/signed_envelope_t.hpp"
#include "proto/config.pb.h"

namespace ftcal::auth {

constexpr char kDomainTag[] = "ftcal.signed_envelope.v1";
constexpr size_t kSeedBytes = 32;
constexpr size_t kPublicKeyBytes = 32;

using PublicKey = std::array<uint8_t, kPublicKeyBytes>;

std::string ToHex(const uint8_t* bytes, size_t n);
// 64 hex digits; throws std::invalid_argument naming `what` otherwise.
PublicKey PublicKeyFromHex(const std::string& hex, const std::string& what);

// Makes sure libsodium is initialised; throws std::runtime_error when it cannot be.
void InitSodium();

class Signer {
 public:
  // The seed file: 64 hex digits (and an optional newline), a regular file owned by this user
  // with no permission for group or others. Throws std::runtime_error naming the file and what
  // is wrong (missing, readable by others, not 32 bytes of hex, ...).
  static Signer FromSeedFile(const std::string& path);
  static Signer FromSeed(const std::array<uint8_t, kSeedBytes>& seed);
  Signer(const Signer&) = delete;
  Signer& operator=(const Signer&) = delete;
  Signer(Signer&& other) noexcept;
  Signer& operator=(Signer&&) = delete;
  ~Signer();

  const PublicKey& public_key() const { return public_key_; }
  // The envelope of `inner` (LCM-encoded, fingerprint first) for `channel`, signed at `utime`.
  signed_envelope_t Seal(const std::string& channel, const uint8_t* inner, int size, int64_t utime);
  template <class Msg>
  signed_envelope_t Seal(const std::string& channel, const Msg& msg, int64_t utime) {
    std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
    msg.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
    return Seal(channel, bytes.data(), static_cast<int>(bytes.size()), utime);
  }

 private:
  Signer() = default;
  std::array<uint8_t, 64> secret_key_{};  // libsodium's: seed then public key
  PublicKey public_key_{};
  int64_t last_sequence_ = 0;
};

struct TrustedKey {
  std::string name;
  PublicKey key{};
  std::set<std::string> channels;
};

// What a receiver got out of a good envelope.
struct Opened {
  const uint8_t* payload;
  int size;
  const std::string* signer;  // the trusted key's name
  int64_t sequence;
  int64_t utime;
};

// Checks envelopes for one process. Not thread-safe (one bus loop).
class Verifier {
 public:
  explicit Verifier(std::vector<TrustedKey> keys);
  // From the config's `auth` section.
  static Verifier FromConfig(const config::Config& config);

  // Checks `data` received on `channel` at `recv_utime` as an envelope of an inner message
  // with `inner_fingerprint`; `window_us` > 0 also requires |recv_utime - utime| <= window_us.
  // The refusal's kind names the sender when it is a trusted key ("bad signature from
  // operator"); every unknown key is one kind, "untrusted signer", so fresh keys cannot grow
  // the counts.
  std::pair<std::optional<Opened>, std::optional<wire::Refusal>> Open(const std::string& channel,
                                                                      const void* data, int size,
                                                                      uint64_t inner_fingerprint,
                                                                      int64_t recv_utime,
                                                                      int64_t window_us);

  // True when some trusted key may sign `channel`.
  bool Trusts(const std::string& channel) const;
  // Bare messages Open() was given where an envelope belongs (refused as "unsigned", whether
  // or not the subscriber then takes them unsigned): a reader can say why it saw none.
  int64_t unsigned_seen() const { return unsigned_seen_; }

  // Refuses envelopes signed or numbered more than `us` ahead of the receive time (FromConfig:
  // auth.max_clock_ahead_s).
  void set_max_ahead_us(int64_t us) { max_ahead_us_ = us; }
  // Keeps the accepted sequences in `store` too, and refuses what it holds: a restarted process
  // refuses what it accepted before. Bus::SubscribeSigned attaches the live process's store
  // unless set_persist(false) came first (the Dynamixel bridge: config validation keeps
  // auth.servo_cmd_window_s below dynamixel.start_quiet_s, so whatever it accepted before a
  // restart is stale once it listens again, and SERVO_CMD at 50 Hz is not worth a write each).
  void Persist(std::shared_ptr<SeenStore> store);
  void set_persist(bool persist) { persist_ = persist; }
  bool persist() const { return persist_; }
  const std::shared_ptr<SeenStore>& store() const { return store_; }

 private:
  std::vector<TrustedKey> keys_;
  std::vector<std::string> key_hex_;
  int64_t max_ahead_us_ = 2'000'000;
  int64_t unsigned_seen_ = 0;
  bool persist_ = true;
  std::shared_ptr<SeenStore> store_;
  signed_envelope_t envelope_;  // reused: decoding allocates the payload
  std::map<std::pair<size_t, std::string>, int64_t> last_sequence_;  // (key, channel)
};

// The bytes the signature covers.
std::vector<uint8_t> SignedBytes(const std::string& channel, const signed_envelope_t& e);

}  // namespace ftcal::auth
