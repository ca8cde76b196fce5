// ftcal-envelopes: prints the signed envelopes of an LCM log, opened.
//
//   ftcal-envelopes [--config FILE] session.lcmlog
//
// One line per envelope: log time, channel, the signer (its name when the config trusts it,
// else its key's first 16 hex digits), sequence, signing time, whether the signature verifies
// (for that signer, and for a signer the config trusts on that channel), and the inner message
// field by field. lcm-spy shows an envelope's fields but not the message inside; this does.
#include <sodium.h>

#include <cstdio>
#include <iostream>
#include <string>

#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include "common/envelope.h"
#include "common/exit_codes.h"
#include "common/user_errors.h"
#include "common/wire_guard.h"
#include "ftcal/config.h"

int main(int argc, char** argv) try {
  CLI::App cli(
      "Prints every signed envelope (SERVO_CMD, EXPERIMENT, CALIBRATION) in an LCM log: "
      "signer, sequence, signing time, signature verdict and the inner message's fields.",
      "ftcal-envelopes");
  std::string log_path, config_path;
  cli.add_option("log", log_path, "LCM log (lcm-logger format)")->required();
  cli.add_option("--config", config_path, "name the signers the config's auth trusts");
  CLI11_PARSE(cli, argc, argv);
  try {
    ftcal::auth::InitSodium();
    ftcal::config::Config config;
    if (!config_path.empty()) config = ftcal::LoadConfigFile(config_path);
    lcm::LogFile log(log_path, "r");
    if (!log.good()) {
      std::cerr << "ftcal-envelopes: cannot read '" << log_path << "'\n";
      return 2;
    }
    const auto envelope_fp = static_cast<uint64_t>(ftcal::signed_envelope_t::getHash());
    int64_t envelopes = 0, bad = 0;
    while (const lcm::LogEvent* e = log.readNextEvent()) {
      if (e->datalen < 8) continue;
      const auto* data = static_cast<const uint8_t*>(e->data);
      uint64_t fp = 0;
      for (int i = 0; i < 8; ++i) fp = fp << 8 | data[i];
      if (fp != envelope_fp) continue;
      ++envelopes;
      std::printf("%.6f %s ", static_cast<double>(e->timestamp) * 1e-6, e->channel.c_str());
      ftcal::signed_envelope_t env;
      if (auto refused = ftcal::wire::Decode(data, e->datalen, &env)) {
        std::printf("malformed envelope (%s: %s)\n", refused->kind.c_str(),
                    refused->detail.c_str());
        ++bad;
        continue;
      }
      std::string signer = ftcal::auth::ToHex(env.signer, 8);
      bool trusted = false;
      for (const auto& k : config.auth().trusted_key()) {
        if (k.public_key_hex() == ftcal::auth::ToHex(env.signer, 32)) {
          signer = k.name();
          for (const auto& c : k.channel()) trusted = trusted || c == e->channel;
        }
      }
      const auto message = ftcal::auth::SignedBytes(e->channel, env);
      const bool verifies = crypto_sign_verify_detached(env.signature, message.data(),
                                                        message.size(), env.signer) == 0;
      bad += !verifies;
      std::printf("signer=%s seq=%lld signed=%.6f %s%s ", signer.c_str(),
                  static_cast<long long>(env.sequence), static_cast<double>(env.utime) * 1e-6,
                  verifies ? "signature-ok" : "BAD-SIGNATURE",
                  config_path.empty() ? "" : (trusted ? " trusted" : " NOT-TRUSTED"));
      const ftcal::wire::Schema* inner =
          ftcal::wire::FindSchema(static_cast<uint64_t>(env.inner_fingerprint));
      if (inner == nullptr) {
        std::printf("<unknown inner type>\n");
      } else {
        std::printf("%s: %s\n", inner->name,
                    ftcal::wire::Describe(*inner, env.payload.data(), env.size).c_str());
      }
    }
    std::fprintf(stderr, "ftcal-envelopes: %lld envelopes, %lld malformed or badly signed\n",
                 static_cast<long long>(envelopes), static_cast<long long>(bad));
    return bad > 0 ? 1 : 0;
  } catch (const std::exception& e) {
    std::cerr << "ftcal-envelopes: " << ftcal::UserText(e, "reading the envelopes") << "\n";
    return ftcal::ExitCodeFor(e, 2);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-envelopes");
}
