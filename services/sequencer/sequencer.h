// ftcal-sequencer's work, transport-agnostic through the Bus: it runs an experiment plan's
// schedule (plan.h) against the robot, publishing SERVO_CMD and EXPERIMENT and watching
// FT_<LEG>, SERVO_STATE, MOCAP_BODY, FTCAL_STATUS and SEQUENCER_CONTROL.
//
// Each step runs to completion before the next: confirmations wait for the operator (the
// terminal, SEQUENCER_CONTROL, or --yes); pre-checks must pass (safety.h) before the phase
// moves; moves end when every servo is within arrival_tolerance_rad of the goal (or the
// sequencer stops when they are stuck); holds, turns and walks are timed from their start.
// While anything moves, the safety rules are checked on every input: a violation, an operator
// STOP or SIGINT/SIGTERM stops the motion (hold the measured angles, then the configured safe
// action), closes the open marker and saves the progress, so that the next run of the same plan
// with the same progress file continues at the first unfinished standing pose or tripod stance
// (plan.h, "Resuming"). While a phase runs its start marker is repeated once a second, so that
// a stage restarted inside the phase picks it up.
//
// SERVO_CMD, EXPERIMENT (and the operator's SEQUENCER_CONTROL) are signed channels
// (common/envelope.h). A SEQUENCER_CONTROL is taken only seconds fresh (auth.control_window_s),
// with a sequence above every one taken before, also before a restart; a CONFIRM must carry the
// nonce the sequencer drew for the prompt it answers (status counter confirm_nonce). The Dynamixel
// bridge moves the legs only for one armed commander that keeps talking (README, "The servo side"):
// before the first motion the sequencer sends ARM and waits until the bridge's FTCAL_STATUS says it
// is armed; while armed it sends a command at least every 1/command_rate_hz (the bridge's
// dead-man); a bridge that leaves armed mode (hold, fault) stops the run; at the end, or stopping,
// it holds and sends DISARM.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <set>
#include <optional>
#include <string>
#include <thread>

#include "common/bus.h"
#include "common/envelope.h"
#include "ftcal/sequencer_control_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "common/messages.h"
#include "proto/config.pb.h"
#include "sequencer/plan.h"
#include "sequencer/progress.h"
#include "sequencer/safety.h"

namespace ftcal::sequencer {

class Sequencer {
 public:
  enum class State { kRunning, kWaitingForOperator, kDone, kStopped };

  struct Options {
    std::string plan_name;      // "" = the config's first plan
    bool yes = false;           // confirm every step that asks (unattended plans)
    std::string progress_file;  // "" = the config's sequencer.progress_file
    std::string session_id;     // "" = from the progress file, else made from the start time
  };

  // Throws std::invalid_argument for a plan that cannot run (plan.h) or a progress file of
  // another plan. `signer` signs every SERVO_CMD and EXPERIMENT; it must outlive the sequencer.
  Sequencer(const config::Config& config, Bus& bus, auth::Signer& signer, Options options);

  // Advances the schedule to the bus's now: call from the loop's tick; SERVO_STATE calls it too.
  void Tick();
  // The operator said yes (terminal line); -1: whatever step is waiting.
  void Confirm(int step = -1);
  // The waiting prompt's nonce, which a CONFIRM on SEQUENCER_CONTROL must carry (status counter
  // confirm_nonce); 0 while nothing waits.
  int64_t confirm_nonce() const { return confirm_nonce_; }
  // Stops the motion with `reason` (SIGINT/SIGTERM, STOP): hold, safe action, marker, progress.
  void Stop(const std::string& reason);

  State state() const { return state_; }
  const std::string& stop_reason() const { return stop_reason_; }
  const Schedule& schedule() const { return schedule_; }
  int step_index() const { return index_; }
  // One line for the operator: phase, pose k/N, time left.
  std::string ProgressLine() const;
  // Called with the prompt whenever a step starts waiting for the operator.
  void OnPrompt(std::function<void(const std::string&)> fn) { on_prompt_ = std::move(fn); }

 private:
  void OnStatus(const MessageInfo& info, const service_status_t& msg);
  void OnControl(const MessageInfo& info, const sequencer_control_t& msg);
  // Draws the waiting prompt's nonce (status counter confirm_nonce).
  void NewPrompt();

  void Begin(int index);
  void Advance();
  void Publish(const Angles& goals, bool torque);
  void SendAction(int8_t action);
  // Arms the bridge (ARM, then HEARTBEAT until its status says armed); false while waiting.
  bool EnsureArmed(int64_t now);
  // While armed, a command at least every 1/command_rate_hz, whatever the step does.
  void KeepAlive(int64_t now);
  // Notes the sequencer's own stalls (OwnStalls) and says when one happened.
  void Awake(int64_t now);
  void TickSteps();
  const StatusReading* ServoBridgeStatus() const;
  void PublishMarker(int phase, bool start);
  bool Arrived(const Angles& goals) const;
  std::optional<std::string> SafetyViolation() const;
  bool PhaseNeedsMocap(int phase) const;
  // Where a restart would resume, as the run stands now.
  Progress ResumePoint() const;
  // Saves it without waiting (ProgressSaver).
  void Save();
  // Saves the end of the plan, or the stop's resume point, and waits until it is on disk.
  void SaveNow(const Progress& progress);
  const Step& Current() const { return steps_[index_]; }
  Step& Current() { return steps_[index_]; }

  const config::Config& config_;
  Bus& bus_;
  auth::Signer& signer_;
  // SEQUENCER_CONTROL is signed: a CONFIRM moves the robot.
  auth::Verifier verifier_ = auth::Verifier::FromConfig(config_);
  Options options_;
  DeviceInputs device_inputs_;
  Safety safety_;
  Schedule schedule_;
  // The steps this run executes: the schedule, or on resume the prelude of the resumed phase
  // followed by the schedule from the resume point. step_of_[i] is the schedule index of
  // steps_[i] (-1 for the prelude's own move).
  std::vector<Step> steps_;
  std::vector<int> step_of_;
  int index_ = 0;
  int64_t step_start_utime_ = 0;
  bool step_started_ = false;
  Angles goals_{};
  bool have_goals_ = false;
  int64_t last_command_utime_ = 0;
  // ARM sent at arm_utime_ (0: not yet), arm_attempts_ times; armed_ once the bridge said so.
  int64_t arm_utime_ = 0;
  int arm_attempts_ = 0;
  bool armed_ = false;
  int open_marker_phase_ = -1;
  int64_t last_marker_utime_ = 0;
  std::string session_id_;
  Inputs inputs_;
  OwnStalls own_stalls_;
  std::unique_ptr<ProgressSaver> saver_;  // null without a progress file
  State state_ = State::kRunning;
  std::string stop_reason_;
  std::string waiting_reason_;
  bool confirmed_ = false;
  int64_t confirm_nonce_ = 0;  // of the waiting prompt; 0 while none waits
  std::function<void(const std::string&)> on_prompt_;
  std::array<int32_t, kNumLegs> servo_ids_{};
  // The heartbeat names that gate the motion (WatchedStatusNames), and the other names heard.
  static constexpr size_t kIgnoredNamesLogged = 16;
  std::set<std::string> watched_status_;
  std::set<std::string> ignored_names_;
};

}  // namespace ftcal::sequencer
