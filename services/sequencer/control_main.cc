// ftcal-sequencer-control: the operator's word to a running ftcal-sequencer from a script or
// another host, one SEQUENCER_CONTROL message (sequencer_control_t) and done:
//
//   ftcal-sequencer-control --signing-key operator.key confirm [--step N] [--nonce N]
//   ftcal-sequencer-control --signing-key operator.key stop [--note TEXT]
//
// Signed with --signing-key (its public key in the config's auth.trusted_key for
// SEQUENCER_CONTROL), since a CONFIRM moves the robot; without one the message goes bare, which
// only a config with auth.allow_unsigned (the loopback twin's) accepts. A CONFIRM carries the
// nonce of the prompt it answers: the tool reads it from the sequencer's heartbeat (status
// counter confirm_nonce) unless --nonce gives it, so a CONFIRM captured off the bus answers no
// later prompt.
#include <chrono>
#include <exception>
#include <optional>
#include <string>

#include "common/exit_codes.h"
#include "common/service.h"
#include "ftcal/sequencer_control_t.hpp"
#include "ftcal/service_status_t.hpp"

namespace {

int64_t CounterOf(const ftcal::service_status_t& st, const std::string& name, int64_t absent) {
  for (int i = 0; i < st.num_counters && i < static_cast<int>(st.counter_name.size()); ++i) {
    if (st.counter_name[i] == name) return st.counter_value[i];
  }
  return absent;
}

}  // namespace

int main(int argc, char** argv) try {
  ftcal::ServiceApp app(
      {"ftcal-sequencer-control",
       "Publishes one SEQUENCER_CONTROL (sequencer_control_t) to a running ftcal-sequencer: "
       "'confirm' (the operator did what the waiting step asked; --step N confirms only step N, "
       "the sequencer's status counter `step`) or 'stop' (hold, close the marker, keep the "
       "progress). Signed with --signing-key; bare without it (accepted only where "
       "auth.allow_unsigned). A confirm carries the waiting prompt's nonce, read from the "
       "sequencer's FTCAL_STATUS (counter confirm_nonce) unless --nonce gives it. Exit: 0 sent, "
       "1 bad flag, 2 no prompt waiting within --wait-s, 3 bad config, 4 bus or key file.",
       /*replayable=*/false});
  std::string action, signing_key, note;
  int step = -1;
  int64_t nonce = 0;
  double wait_s = 5.0;
  app.cli()
      .add_option("action", action, "confirm or stop")
      ->required()
      ->check(CLI::IsMember({"confirm", "stop"}));
  app.cli()
      .add_option("--step", step, "confirm only this step (-1: whatever waits)")
      ->capture_default_str();
  app.cli().add_option("--note", note, "free text the sequencer logs");
  app.cli().add_option("--nonce", nonce,
                       "confirm: the prompt's nonce (default: read from the sequencer's status)");
  app.cli()
      .add_option("--wait-s", wait_s,
                  "confirm: how long to wait for a sequencer's status with a prompt waiting")
      ->capture_default_str();
  app.cli().add_option("--signing-key", signing_key,
                       "Ed25519 seed file (owner-only; ftcal-keygen makes one) trusted for "
                       "SEQUENCER_CONTROL");
  if (auto rc = app.Init(argc, argv)) return *rc;

  if (action == "confirm" && nonce == 0) {
    // The sequencer's heartbeat (1 Hz) names the waiting prompt: its step and nonce.
    std::optional<int64_t> heard;
    int64_t heard_step = -1;
    app.bus().Subscribe<ftcal::service_status_t>(
        app.config().channels().status(),
        [&](const ftcal::MessageInfo&, const ftcal::service_status_t& st) {
          if (st.name != "ftcal-sequencer") return;
          const int64_t n = CounterOf(st, "confirm_nonce", 0);
          const int64_t s = CounterOf(st, "step", -1);
          if (n != 0 && (step < 0 || s == step)) {
            heard = n;
            heard_step = s;
          }
        });
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(wait_s);
    while (!heard && std::chrono::steady_clock::now() < deadline) app.bus().HandleOnce(100);
    if (!heard) {
      app.log().critical(
          "no ftcal-sequencer on {} had a prompt waiting{} within {} s (--wait-s): nothing to "
          "confirm",
          app.config().channels().status(),
          step < 0 ? std::string() : " at step " + std::to_string(step), wait_s);
      return ftcal::kExitRefused;
    }
    nonce = *heard;
    if (step < 0) step = static_cast<int>(heard_step);
  }

  ftcal::sequencer_control_t msg;
  msg.utime = app.bus().NowUtime();
  msg.nonce = action == "confirm" ? nonce : 0;
  msg.action =
      action == "confirm" ? ftcal::sequencer_control_t::CONFIRM : ftcal::sequencer_control_t::STOP;
  msg.step = step;
  msg.note = note;
  const std::string& channel = app.config().channels().sequencer_control();
  try {
    if (signing_key.empty()) {
      app.bus().Publish(channel, msg);
    } else {
      ftcal::auth::Signer signer = ftcal::auth::Signer::FromSeedFile(signing_key);
      app.bus().PublishSigned(channel, msg, signer);
    }
  } catch (const std::exception& e) {
    app.log().critical("{}", ftcal::UserText(e, "sending the request"));
    return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
  app.log().info("{} sent on {}{}", action, channel, signing_key.empty() ? " (unsigned)" : "");
  return 0;
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-sequencer-control");
}
