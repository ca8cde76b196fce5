// ftcal-sequencer-control: the operator's word to a running ftcal-sequencer from a script or
// another host, one SEQUENCER_CONTROL message (sequencer_control_t) and done:
//
//   ftcal-sequencer-control --signing-key operator.key confirm [--step N]
//   ftcal-sequencer-control --signing-key operator.key stop [--note TEXT]
//
// Signed with --signing-key (its public key in the config's auth.trusted_key for
// SEQUENCER_CONTROL), since a CONFIRM moves the robot; without one the message goes bare, which
// only a config with auth.allow_unsigned (the loopback twin's) accepts.
#include <exception>
#include <optional>
#include <string>

#include "common/exit_codes.h"
#include "common/service.h"
#include "ftcal/sequencer_control_t.hpp"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-sequencer-control",
       "Publishes one SEQUENCER_CONTROL (sequencer_control_t) to a running ftcal-sequencer: "
       "'confirm' (the operator did what the waiting step asked; --step N confirms only step N, "
       "the sequencer's status counter `step`) or 'stop' (hold, close the marker, keep the "
       "progress). Signed with --signing-key; bare without it (accepted only where "
       "auth.allow_unsigned). Exit: 0 sent, 1 bad flag, 3 bad config, 4 bus or key file.",
       /*replayable=*/false});
  std::string action, signing_key, note;
  int step = -1;
  app.cli()
      .add_option("action", action, "confirm or stop")
      ->required()
      ->check(CLI::IsMember({"confirm", "stop"}));
  app.cli()
      .add_option("--step", step, "confirm only this step (-1: whatever waits)")
      ->capture_default_str();
  app.cli().add_option("--note", note, "free text the sequencer logs");
  app.cli().add_option("--signing-key", signing_key,
                       "Ed25519 seed file (owner-only; ftcal-keygen makes one) trusted for "
                       "SEQUENCER_CONTROL");
  if (auto rc = app.Init(argc, argv)) return *rc;

  ftcal::sequencer_control_t msg;
  msg.utime = app.bus().NowUtime();
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
}
