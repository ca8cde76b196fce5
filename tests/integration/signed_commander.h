// A servo commander for the multi-process tests: a key made at test time (never a committed
// one), the config text that trusts it on SERVO_CMD, and signed ARM / MOVE / HEARTBEAT /
// DISARM commands over LCM, with a heartbeat thread for the dead-man.
#pragma once

#include <sodium.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include <lcm/lcm-cpp.hpp>

#include "common/envelope.h"
#include "ftcal/servo_command_t.hpp"

namespace ftcal::testing {

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
    const std::string key = "trusted_key { name: \"" + name + "\" public_key_hex: \"" +
                            PublicKeyHex() + "\" channel: \"" + channel_ + "\" }\n";
    const std::regex auth_open("(^|\n)auth \\{");
    if (std::regex_search(config_text, auth_open)) {
      return std::regex_replace(config_text, auth_open, "$1auth {\n  " + key,
                                std::regex_constants::format_first_only);
    }
    return config_text + "\nauth {\n  " + key + "}\n";
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

  static int64_t NowUs() {
    return std::chrono::duration_cast<std::chrono::microseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
  }

 private:
  static auth::Signer NewSigner() {
    auth::InitSodium();
    std::array<uint8_t, auth::kSeedBytes> seed{};
    randombytes_buf(seed.data(), seed.size());
    return auth::Signer::FromSeed(seed);
  }

  auth::Signer signer_;
  lcm::LCM lcm_;
  std::string channel_;
  std::mutex mu_;
  std::thread heartbeat_;
  std::atomic<bool> stop_{true};
};

}  // namespace ftcal::testing
