// ftcal-sequencer: runs an experiment plan on the robot (sequencer.h says how).
#include <atomic>
#include <exception>
#include <iostream>
#include <optional>
#include <string>
#include <thread>

#include "common/exit_codes.h"
#include "common/service.h"
#include "common/shutdown.h"
#include "sequencer/sequencer.h"

namespace {

// Exit codes: 0 the plan ran to its end; 2 stopped before it (a safety rule, the operator, a
// signal) with the progress saved for a resume; 3 the plan or progress file cannot run.
constexpr int kDone = 0;
constexpr int kStopped = 2;
constexpr int kBadPlan = 3;

}  // namespace

int main(int argc, char** argv) try {
  ftcal::ServiceApp app(
      {"ftcal-sequencer",
       "Runs an experiment plan (config `plan`, docs/architecture.md): publishes SERVO_CMD "
       "(servo_command_t) and EXPERIMENT (experiment_marker_t), both signed with --signing-key, "
       "arming the Dynamixel bridge first, and watches FT_<LEG>, "
       "SERVO_STATE, MOCAP_BODY, FTCAL_STATUS and SEQUENCER_CONTROL (sequencer_control_t: "
       "CONFIRM, STOP). Phases that need the operator (hanging, tare) wait for a line on the "
       "terminal, a CONFIRM, or --yes. Pre-checks and limits are the config's `sequencer` "
       "section; a violation, a STOP or SIGINT/SIGTERM holds the legs, closes the marker and "
       "saves the progress for a resume. Exit: 0 plan done, 2 stopped before its end, 3 the "
       "plan cannot run.",
       /*replayable=*/false});
  ftcal::sequencer::Sequencer::Options options;
  app.cli().add_option("--plan", options.plan_name,
                       "experiment plan by name (default: the config's first)");
  app.cli().add_flag(
      "--yes", options.yes,
      "confirm every step that asks the operator (unattended plans that need no re-hanging)");
  app.cli().add_option("--progress", options.progress_file,
                       "progress file for resuming (default: sequencer.progress_file)");
  app.cli().add_option("--session", options.session_id, "session id for the EXPERIMENT markers");
  std::string signing_key;
  app.cli()
      .add_option("--signing-key", signing_key,
                  "Ed25519 seed file (owner-only; ftcal-keygen makes one) that signs SERVO_CMD "
                  "and EXPERIMENT; its public key must be in the config's auth.trusted_key for "
                  "both channels")
      ->required();
  if (auto rc = app.Init(argc, argv)) return *rc;

  std::optional<ftcal::auth::Signer> signer;
  try {
    signer.emplace(ftcal::auth::Signer::FromSeedFile(signing_key));
  } catch (const std::exception& e) {
    app.log().critical("--signing-key: {}", ftcal::UserText(e, "reading the signing key"));
    return kBadPlan;
  }
  std::unique_ptr<ftcal::sequencer::Sequencer> seq;
  try {
    seq = std::make_unique<ftcal::sequencer::Sequencer>(app.config(), app.bus(), *signer, options);
  } catch (const std::exception& e) {
    app.log().critical("{}", ftcal::UserText(e, "preparing the plan"));
    return ftcal::IsInternalError(e) ? ftcal::kExitInternal : kBadPlan;
  }
  app.log().info("plan '{}': {} steps, {:.0f} s of motion", seq->schedule().plan_name,
                 seq->schedule().steps.size(), seq->schedule().duration_s);

  // The terminal answers prompts: any line confirms the waiting step.
  std::atomic<int> lines{0};
  seq->OnPrompt(
      [](const std::string& prompt) { std::cout << prompt << " [press Enter]" << std::endl; });
  std::thread([&lines] {
    std::string line;
    while (std::getline(std::cin, line)) ++lines;
  }).detach();
  int confirmed_lines = 0;
  app.AddPeriodic(0.02, [&] {
    while (confirmed_lines < lines.load()) {
      ++confirmed_lines;
      seq->Confirm();
    }
    seq->Tick();
    if (seq->state() == ftcal::sequencer::Sequencer::State::kDone ||
        seq->state() == ftcal::sequencer::Sequencer::State::kStopped) {
      ftcal::RequestShutdown();
    }
  });
  app.AddPeriodic(1.0, [&] { app.log().info("{}", seq->ProgressLine()); });
  const int rc = app.Run();
  if (seq->state() != ftcal::sequencer::Sequencer::State::kDone &&
      seq->state() != ftcal::sequencer::Sequencer::State::kStopped) {
    seq->Stop("stopped by signal");
  }
  if (rc != 0) return rc;
  if (seq->state() == ftcal::sequencer::Sequencer::State::kDone) return kDone;
  app.log().error("plan '{}' stopped at step {}: {}", seq->schedule().plan_name, seq->step_index(),
                  seq->stop_reason());
  return kStopped;
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-sequencer");
}
