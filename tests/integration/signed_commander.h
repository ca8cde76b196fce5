// A servo commander for the multi-process tests: a key made at test time (never a committed
// one), the config text that trusts it on SERVO_CMD, and signed ARM / MOVE / HEARTBEAT /
// DISARM commands over LCM, with a heartbeat thread for the dead-man.
#pragma once

#include <fcntl.h>
#include <sodium.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <stdexcept>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include <lcm/lcm-cpp.hpp>

#include "common/envelope.h"
#include "ftcal/servo_command_t.hpp"

namespace ftcal::testing {

inline int64_t NowUs() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

template <class Msg>
std::vector<uint8_t> Encode(const Msg& msg) {
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  msg.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  return bytes;
}

// A key made at test time (never a committed one).
inline auth::Signer NewSigner() {
  auth::InitSodium();
  std::array<uint8_t, auth::kSeedBytes> seed{};
  randombytes_buf(seed.data(), seed.size());
  return auth::Signer::FromSeed(seed);
}

// A fresh Ed25519 seed written to `path` as ftcal-keygen writes one (64 hex digits, mode 600);
// returns its public key in hex, for the config's auth.trusted_key.
inline std::string WriteKeyFile(const std::string& path) {
  auth::InitSodium();
  std::array<uint8_t, auth::kSeedBytes> seed{};
  randombytes_buf(seed.data(), seed.size());
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_NOFOLLOW, 0600);
  if (fd < 0) throw std::runtime_error("cannot write key file " + path);
  const std::string hex = auth::ToHex(seed.data(), seed.size()) + "\n";
  const bool ok = ::write(fd, hex.data(), hex.size()) == static_cast<ssize_t>(hex.size());
  ::close(fd);
  if (!ok) throw std::runtime_error("cannot write key file " + path);
  const auth::Signer signer = auth::Signer::FromSeed(seed);
  return auth::ToHex(signer.public_key().data(), signer.public_key().size());
}

// `config_text` with `public_key_hex` trusted as `name` on `channels` (in its auth section, or
// a new one).
inline std::string TrustKey(std::string config_text, const std::string& name,
                            const std::string& public_key_hex,
                            const std::vector<std::string>& channels) {
  std::string key =
      "trusted_key { name: \"" + name + "\" public_key_hex: \"" + public_key_hex + "\"";
  for (const std::string& c : channels) key += " channel: \"" + c + "\"";
  key += " }\n";
  const std::regex auth_open("(^|\n)auth \\{");
  if (std::regex_search(config_text, auth_open)) {
    return std::regex_replace(config_text, auth_open, "$1auth {\n  " + key,
                              std::regex_constants::format_first_only);
  }
  return config_text + "\nauth {\n  " + key + "}\n";
}

class SignedCommander {
 public:
  SignedCommander(const std::string& url, std::string channel = "SERVO_CMD")
      : signer_(NewSigner()), lcm_(url), channel_(std::move(channel)) {}
  ~SignedCommander() { StopHeartbeat(); }

  bool good() { return lcm_.good(); }
  std::string PublicKeyHex() const {
    return auth::ToHex(signer_.public_key().data(), signer_.public_key().size());
  }
  // `config_text` with this key trusted on the channel (in its auth section, or a new one).
  std::string Trusted(std::string config_text, const std::string& name = "test-commander") const {
    return TrustKey(std::move(config_text), name, PublicKeyHex(), {channel_});
  }

  int Send(int8_t action, const std::vector<int>& ids = {}, const std::vector<double>& goals = {},
           bool torque = true) {
    servo_command_t c{};
    c.utime = NowUs();
    c.action = action;
    c.num_servos = static_cast<int32_t>(ids.size());
    c.id.assign(ids.begin(), ids.end());
    c.goal_angle_rad = goals;
    c.torque_enable = torque;
    std::lock_guard<std::mutex> lock(mu_);
    const signed_envelope_t e = signer_.Seal(channel_, c, NowUs());
    return lcm_.publish(channel_, &e);
  }
  int Arm() { return Send(servo_command_t::ARM); }
  int Move(const std::vector<int>& ids, const std::vector<double>& goals) {
    return Send(servo_command_t::MOVE, ids, goals);
  }
  // HEARTBEAT every `period_s` until StopHeartbeat().
  void StartHeartbeat(double period_s) {
    StopHeartbeat();
    stop_ = false;
    heartbeat_ = std::thread([this, period_s] {
      while (!stop_) {
        Send(servo_command_t::HEARTBEAT);
        std::this_thread::sleep_for(std::chrono::duration<double>(period_s));
      }
    });
  }
  void StopHeartbeat() {
    stop_ = true;
    if (heartbeat_.joinable()) heartbeat_.join();
  }

 private:
  auth::Signer signer_;
  lcm::LCM lcm_;
  std::string channel_;
  std::mutex mu_;
  std::thread heartbeat_;
  std::atomic<bool> stop_{true};
};

}  // namespace ftcal::testing
