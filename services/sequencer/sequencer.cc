// One file over 600 lines: the run is one state machine (TickSteps); progress.cc keeps its file.
#include "sequencer/sequencer.h"

#include <sodium.h>

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/servo_command_t.hpp"

namespace ftcal::sequencer {
namespace {

std::string Clock(double s) {
  const long total = std::lround(std::max(0.0, s));
  std::ostringstream o;
  o << total / 60 << ":" << (total % 60 < 10 ? "0" : "") << total % 60;
  return o.str();
}

// How long a pre-check waits for every input to be fresh before it fails.
constexpr double kInputWaitS = 5.0;

// The Dynamixel bridge's command gate modes, as its `mode` counter gives them (README, "The
// servo side"; services/dynamixel_bridge/command_gate.h).
constexpr int kGateArmed = 1;
constexpr const char* kGateModeNames[] = {"disarmed", "armed", "hold", "fault"};
constexpr const char kServoBridge[] = "ftcal-dynamixel-bridge";
// ARM again when the bridge's status (1 Hz) has not said armed this long after an ARM, and give
// up after this many ARMs.
constexpr double kArmRetryS = 2.5;
constexpr int kArmAttempts = 4;
// The open phase's start marker goes out again this often: markers are edges, and a stage
// (re)started inside a phase learns from the repeat that it is in one (the stages take a
// repeated start of the same phase and session as the same phase).
constexpr double kMarkerRepeatS = 1.0;

std::string GateModeName(int mode) {
  return mode >= 0 && mode < 4 ? kGateModeNames[mode] : "unknown (" + std::to_string(mode) + ")";
}

bool Timed(StepKind k) {
  return k == StepKind::kMove || k == StepKind::kHold || k == StepKind::kTurn ||
         k == StepKind::kWalk;
}

}  // namespace

Sequencer::Sequencer(const config::Config& config, Bus& bus, auth::Signer& signer, Options options)
    : config_(config),
      bus_(bus),
      signer_(signer),
      options_(std::move(options)),
      device_inputs_(config),
      safety_(config),
      schedule_(Expand(config, options_.plan_name)),
      watched_status_(WatchedStatusNames(config)) {
  if (options_.progress_file.empty()) options_.progress_file = config.sequencer().progress_file();
  if (!options_.progress_file.empty())
    saver_ = std::make_unique<ProgressSaver>(options_.progress_file);
  for (int k = 0; k < kNumLegs; ++k) servo_ids_[k] = config.robot().leg(k).servo().id();

  int resume = 0;
  std::optional<Progress> saved;
  if (!options_.progress_file.empty()) saved = LoadProgress(options_.progress_file);
  if (saved) {
    if (saved->plan != schedule_.plan_name) {
      throw std::invalid_argument("progress file " + options_.progress_file + " is for plan '" +
                                  saved->plan + "', not '" + schedule_.plan_name +
                                  "': remove it to start afresh");
    }
    if (saved->next_step < 0 || saved->next_step > static_cast<int>(schedule_.steps.size())) {
      throw std::invalid_argument("progress file " + options_.progress_file + ": next_step " +
                                  std::to_string(saved->next_step) + " is outside the plan's " +
                                  std::to_string(schedule_.steps.size()) + " steps");
    }
    resume = saved->next_step;
    session_id_ = saved->session_id;
  }
  if (!options_.session_id.empty()) session_id_ = options_.session_id;
  if (session_id_.empty()) session_id_ = "seq-" + std::to_string(bus_.NowUtime() / 1000000);

  // On resume inside a phase, its preparation runs again (the operator confirms, the checks
  // pass, the legs go to the resumed step's start) and its marker opens again.
  const auto& all = schedule_.steps;
  if (resume > 0 && resume < static_cast<int>(all.size()) &&
      all[resume].kind != StepKind::kConfirm && all[resume].kind != StepKind::kPrecheck) {
    const int phase = all[resume].phase;
    bool marker_open = false;
    for (int i = 0; i < resume; ++i) {
      if (all[i].phase != phase) continue;
      if (all[i].kind == StepKind::kConfirm || all[i].kind == StepKind::kPrecheck) {
        steps_.push_back(all[i]);
        step_of_.push_back(i);
      }
      if (all[i].kind == StepKind::kMarkerStart) marker_open = true;
      if (all[i].kind == StepKind::kMarkerStop) marker_open = false;
    }
    Step move = all[resume];
    move.kind = StepKind::kMove;
    // Straight to where the resumed step goes (a pose), or where it starts (a turn, a walk).
    move.to = all[resume].kind == StepKind::kMove ? all[resume].to : all[resume].from;
    move.duration_s = 0.0;  // timed from the measured angles when it begins
    move.resume_point = false;
    steps_.push_back(move);
    step_of_.push_back(-1);
    if (marker_open) {
      Step open = all[resume];
      open.kind = StepKind::kMarkerStart;
      steps_.push_back(open);
      step_of_.push_back(-1);
    }
  }
  for (int i = resume; i < static_cast<int>(all.size()); ++i) {
    steps_.push_back(all[i]);
    step_of_.push_back(i);
  }
  if (resume > 0) {
    bus_.stats().log().info("resuming plan '{}' at step {} of {} (session {})", schedule_.plan_name,
                            resume, all.size(), session_id_);
  }

  const config::Channels& ch = config.channels();
  DeviceInputs::Handlers handlers;
  // A message's extremes: per axis the value farthest from zero, the flags or-ed, the last
  // record's time, so the range check sees every record of a datagram, not only its last.
  handlers.ft = [this](const FtBatch& batch) {
    FtInput extreme = batch.records[static_cast<size_t>(batch.n - 1)].in;
    for (const FtRecord& r : batch) {
      for (int i = 0; i < 6; ++i) {
        if (!(std::abs(r.in.wrench[i]) <= std::abs(extreme.wrench[i]))) {
          extreme.wrench[i] = r.in.wrench[i];
        }
      }
      extreme.flags |= r.in.flags;
    }
    inputs_.ft[batch.leg] = extreme;
  };
  handlers.servo = [this](const ServoInput& in) {
    inputs_.servo = in;
    Tick();
  };
  handlers.mocap = [this](const MocapInput& in) { inputs_.mocap = in; };
  device_inputs_.Subscribe(bus_, handlers);
  bus_.Subscribe<service_status_t>(
      ch.status(), [this](const MessageInfo& i, const service_status_t& m) { OnStatus(i, m); });
  // The operator's word of the moment: seconds old at most, its sequence above any taken before
  // (also before a restart: Bus::seen_store), and a CONFIRM must carry the nonce of the prompt it
  // answers (Confirm).
  bus_.SubscribeSigned<sequencer_control_t>(
      ch.sequencer_control(), &verifier_,
      static_cast<int64_t>(config.auth().control_window_s() * 1e6), config.auth().allow_unsigned(),
      [this](const MessageInfo& i, const sequencer_control_t& m) { OnControl(i, m); });
  if (steps_.empty()) state_ = State::kDone;
}

void Sequencer::OnStatus(const MessageInfo&, const service_status_t& msg) {
  // Only the bridges gate the motion: the sequencer cannot move safely without their data.
  // FTCAL_STATUS is unsigned (docs/architecture.md): a name the sequencer does not watch is
  // counted and ignored, so an invented process cannot stop a run, and the names logged are
  // bounded.
  if (watched_status_.count(msg.name) == 0) {
    ++bus_.stats().Counter("status_ignored");
    if (ignored_names_.size() < kIgnoredNamesLogged && ignored_names_.insert(msg.name).second) {
      bus_.stats().log().info("FTCAL_STATUS from '{}' ignored: not a bridge this sequencer watches",
                              msg.name);
    }
    return;
  }
  StatusReading st{msg.utime, msg.state, msg.last_error};
  for (int i = 0; i < msg.num_counters && i < static_cast<int>(msg.counter_name.size()); ++i) {
    if (msg.counter_name[i] == "mode") st.mode = static_cast<int>(msg.counter_value[i]);
  }
  inputs_.status[msg.name] = st;
}

const StatusReading* Sequencer::ServoBridgeStatus() const {
  const auto it = inputs_.status.find(kServoBridge);
  return it == inputs_.status.end() ? nullptr : &it->second;
}

void Sequencer::OnControl(const MessageInfo&, const sequencer_control_t& msg) {
  if (msg.action == sequencer_control_t::STOP) {
    Stop("operator STOP on " + config_.channels().sequencer_control() +
         (msg.note.empty() ? std::string() : " (" + msg.note + ")"));
  } else if (msg.action == sequencer_control_t::CONFIRM) {
    // A signature says who confirmed, not what: a CONFIRM captured at one prompt must not answer
    // another (a later step, a later run, a resumed sequencer). Each prompt draws a nonce.
    if (state_ != State::kWaitingForOperator) {
      throw BadInput("confirm with nothing waiting",
                     "a CONFIRM (nonce " + std::to_string(msg.nonce) + ") while no step waits");
    }
    if (msg.nonce != confirm_nonce_) {
      throw BadInput("confirm of another prompt",
                     "a CONFIRM with nonce " + std::to_string(msg.nonce) +
                         ", not the waiting prompt's (status counter confirm_nonce; "
                         "ftcal-sequencer-control reads it)");
    }
    Confirm(msg.step);
  } else {
    throw BadInput("unknown sequencer_control_t action", "action " + std::to_string(msg.action));
  }
}

void Sequencer::Confirm(int step) {
  if (state_ != State::kWaitingForOperator) return;
  const int waiting = step_of_[index_];
  if (step >= 0 && step != waiting) {
    bus_.stats().log().warn("confirmation for step {} ignored: step {} is waiting", step, waiting);
    return;
  }
  confirmed_ = true;
  ++bus_.stats().Counter("confirms");
  Tick();
}

void Sequencer::NewPrompt() {
  // Positive and never 0 (0 is "no prompt"): drawn, not counted, so that no run or restart
  // repeats one.
  do {
    randombytes_buf(&confirm_nonce_, sizeof confirm_nonce_);
    confirm_nonce_ &= INT64_MAX;
  } while (confirm_nonce_ == 0);
  bus_.stats().Counter("confirm_nonce") = confirm_nonce_;
}

bool Sequencer::PhaseNeedsMocap(int phase) const {
  // Hanging and the tare work without motion capture (the report had none); on the ground the
  // tilt rule needs it.
  const int8_t m = schedule_.phase_marker[phase];
  return m == experiment_marker_t::STANDING || m == experiment_marker_t::TRIPOD ||
         m == experiment_marker_t::WALKING;
}

std::optional<std::string> Sequencer::SafetyViolation() const {
  const int phase = Current().phase;
  if (auto e = safety_.Stale(inputs_, bus_.NowUtime(), PhaseNeedsMocap(phase), own_stalls_))
    return e;
  if (auto e = safety_.OverRange(inputs_)) return e;
  if (PhaseNeedsMocap(phase)) {
    if (auto e = safety_.Tilted(inputs_)) return e;
  }
  // Armed, the bridge's own word counts: a dead-man hold or a fault there stops the run here.
  if (armed_) {
    const StatusReading* st = ServoBridgeStatus();
    if (st != nullptr && st->utime > arm_utime_ && st->mode != kGateArmed) {
      return std::string(kServoBridge) + " left armed mode: it is in " + GateModeName(st->mode) +
             (st->last_error.empty() ? std::string() : " (" + st->last_error + ")");
    }
  }
  return std::nullopt;
}

bool Sequencer::Arrived(const Angles& goals) const {
  if (!inputs_.servo) return false;
  for (int k = 0; k < kNumLegs; ++k) {
    if (std::abs(inputs_.servo->angle_rad[k] - goals[k]) >
        config_.sequencer().arrival_tolerance_rad()) {
      return false;
    }
  }
  return true;
}

void Sequencer::Publish(const Angles& goals, bool torque) {
  servo_command_t cmd;
  cmd.utime = bus_.NowUtime();
  cmd.num_servos = kNumLegs;
  cmd.id.assign(servo_ids_.begin(), servo_ids_.end());
  cmd.goal_angle_rad.assign(goals.begin(), goals.end());
  cmd.torque_enable = torque;
  cmd.action = servo_command_t::MOVE;
  bus_.PublishSigned(config_.channels().servo_cmd(), cmd, signer_);
  goals_ = goals;
  have_goals_ = true;
  last_command_utime_ = cmd.utime;
}

void Sequencer::SendAction(int8_t action) {
  servo_command_t cmd{};
  cmd.utime = bus_.NowUtime();
  cmd.action = action;
  cmd.num_servos = 0;
  cmd.torque_enable = true;
  bus_.PublishSigned(config_.channels().servo_cmd(), cmd, signer_);
  last_command_utime_ = cmd.utime;
}

bool Sequencer::EnsureArmed(int64_t now) {
  if (armed_) return true;
  const StatusReading* st = ServoBridgeStatus();
  if (arm_utime_ > 0 && st != nullptr && st->utime > arm_utime_ && st->mode == kGateArmed) {
    armed_ = true;
    bus_.stats().log().info("{} armed after {} ARM(s)", kServoBridge, arm_attempts_);
    return true;
  }
  if (arm_utime_ == 0 || (now - arm_utime_) * 1e-6 >= kArmRetryS) {
    if (arm_attempts_ >= kArmAttempts) {
      Stop(std::string(kServoBridge) + " did not arm after " + std::to_string(arm_attempts_) +
           " ARMs " + std::to_string(kArmRetryS) + " s apart: " +
           (st == nullptr ? std::string("no FTCAL_STATUS from it")
                          : "its status says " + GateModeName(st->mode) +
                                (st->last_error.empty() ? "" : " (" + st->last_error + ")")) +
           "; is this sequencer's key trusted for " + config_.channels().servo_cmd() +
           " (auth.trusted_key)?");
      return false;
    }
    SendAction(servo_command_t::ARM);
    arm_utime_ = now;
    ++arm_attempts_;
  } else if ((now - last_command_utime_) * 1e-6 >= 1.0 / config_.sequencer().command_rate_hz()) {
    SendAction(servo_command_t::HEARTBEAT);  // the ARM may have been taken: keep it alive
  }
  return false;
}

void Sequencer::KeepAlive(int64_t now) {
  if (state_ == State::kDone || state_ == State::kStopped) return;
  if (open_marker_phase_ >= 0 && (now - last_marker_utime_) * 1e-6 >= kMarkerRepeatS) {
    PublishMarker(open_marker_phase_, true);
  }
  if (!armed_) return;
  if ((now - last_command_utime_) * 1e-6 < 1.0 / config_.sequencer().command_rate_hz()) return;
  if (have_goals_) {
    Publish(goals_, true);
  } else {
    SendAction(servo_command_t::HEARTBEAT);
  }
}

void Sequencer::PublishMarker(int phase, bool start) {
  experiment_marker_t m;
  m.utime = bus_.NowUtime();
  m.session_id = session_id_;
  m.phase = schedule_.phase_marker[phase];
  m.start = start;
  for (int i = 0; i < 3; ++i) m.gravity_b[i] = schedule_.phase_gravity_b[phase][i];
  m.note = "ftcal-sequencer plan " + schedule_.plan_name + ": " + schedule_.phase_names[phase];
  bus_.PublishSigned(config_.channels().experiment(), m, signer_);
  last_marker_utime_ = m.utime;
  const bool repeat = start && open_marker_phase_ == phase;
  open_marker_phase_ = start ? phase : -1;
  if (!repeat)
    bus_.stats().log().info("{} {}", start ? "start" : "end", schedule_.phase_names[phase]);
}

Progress Sequencer::ResumePoint() const {
  // The resume point of the step under way (or the next one, when this one is finished).
  int next = static_cast<int>(schedule_.steps.size());
  for (size_t i = index_; i < steps_.size(); ++i) {
    if (step_of_[i] < 0) continue;
    next = step_of_[i];
    break;
  }
  // Back to the last resume point at or before it: a partly done unit is done again.
  if (next < static_cast<int>(schedule_.steps.size())) {
    const int phase = schedule_.steps[next].phase;
    for (int i = next; i >= 0 && schedule_.steps[i].phase == phase; --i) {
      if (schedule_.steps[i].resume_point) {
        next = i;
        break;
      }
      if (schedule_.steps[i].kind == StepKind::kConfirm ||
          schedule_.steps[i].kind == StepKind::kPrecheck) {
        next = i;
        break;
      }
    }
  }
  return Progress{schedule_.plan_name, next, session_id_};
}

void Sequencer::Save() {
  if (saver_) saver_->Save(ResumePoint());
}

void Sequencer::SaveNow(const Progress& progress) {
  if (!saver_) return;
  saver_->Save(progress);
  const std::string error = saver_->Flush();
  if (!error.empty()) bus_.stats().Error("progress not saved", error);
}

void Sequencer::Begin(int index) {
  index_ = index;
  step_started_ = false;
  confirmed_ = false;
  confirm_nonce_ = 0;
  bus_.stats().Counter("confirm_nonce") = 0;
  waiting_reason_.clear();
  if (index < static_cast<int>(step_of_.size())) {
    bus_.stats().Counter("step") = std::max(0, step_of_[index]);
  }
}

void Sequencer::Advance() {
  const Step& done = Current();
  // A finished unit (its last step) is saved so that a restart does not repeat it.
  const bool unit_done = done.unit >= 0 && (index_ + 1 >= static_cast<int>(steps_.size()) ||
                                            steps_[index_ + 1].unit != done.unit ||
                                            steps_[index_ + 1].phase != done.phase);
  Begin(index_ + 1);
  if (index_ >= static_cast<int>(steps_.size())) {
    state_ = State::kDone;
    SaveNow(Progress{schedule_.plan_name, static_cast<int>(schedule_.steps.size()), session_id_});
    bus_.stats().log().info("plan '{}' done", schedule_.plan_name);
    if (arm_utime_ > 0) SendAction(servo_command_t::DISARM);  // the bridge holds the last pose
    return;
  }
  if (unit_done) {
    ++bus_.stats().Counter("units_done");
    Save();
  }
}

void Sequencer::Awake(int64_t now) {
  const int64_t stalled = own_stalls_.Awake(now);
  if (stalled == 0) return;
  ++bus_.stats().Counter("own_stalls");
  bus_.stats().log().warn(
      "the sequencer itself did not run for {:.3f} s (a blocked write, or no core for it); its "
      "inputs' ages do not count that time",
      stalled * 1e-6);
}

void Sequencer::Tick() {
  Awake(bus_.NowUtime());
  if (saver_) {
    const std::string error = saver_->TakeError();
    if (!error.empty()) bus_.stats().Error("progress not saved", error);
  }
  TickSteps();
  KeepAlive(bus_.NowUtime());
}

void Sequencer::TickSteps() {
  // Several steps can finish at the same instant (markers, checks): run them in one call.
  for (int guard = 0; guard < 64 && state_ != State::kDone && state_ != State::kStopped; ++guard) {
    const int64_t now = bus_.NowUtime();
    Awake(now);  // a step before this one may have been descheduled or blocked
    Step& s = Current();
    if (!step_started_) {
      step_started_ = true;
      step_start_utime_ = now;
      // Moves start where the servos were last sent (or are, before the first command), so
      // that a resumed or re-timed move never jumps.
      if (s.kind == StepKind::kMove) {
        if (have_goals_) {
          s.from = goals_;
        } else if (inputs_.servo) {
          s.from = inputs_.servo->angle_rad;
        } else {
          step_started_ = false;  // no servo state yet: wait for one
          return;
        }
        s.duration_s = std::max(
            s.duration_s, MoveDurationS(s.from, s.to, config_.sequencer().max_velocity_rad_s()));
      }
    }
    const double t = (now - step_start_utime_) * 1e-6;
    switch (s.kind) {
      case StepKind::kConfirm:
        if (options_.yes || confirmed_) {
          Advance();
          continue;
        }
        if (state_ != State::kWaitingForOperator) {
          state_ = State::kWaitingForOperator;
          NewPrompt();
          const std::string prompt =
              s.prompt + (waiting_reason_.empty() ? "" : " (" + waiting_reason_ + ")");
          bus_.stats().log().info("waiting for the operator: {}", prompt);
          if (on_prompt_) on_prompt_(prompt);
        }
        return;
      case StepKind::kPrecheck: {
        state_ = State::kRunning;
        std::optional<std::string> why;
        if (auto e = safety_.Stale(inputs_, now, PhaseNeedsMocap(s.phase), own_stalls_)) {
          // The bridges may still be starting (or the operator plugging a cable): wait a while
          // for fresh inputs before calling it a failure.
          if (t < kInputWaitS) return;
          why = e;
        } else if (s.precheck == Precheck::kAirborne) {
          const auto& g = schedule_.phase_gravity_b[s.phase];
          why = safety_.Airborne(inputs_, Vec3(g[0], g[1], g[2]));
        } else if (s.precheck == Precheck::kStanding) {
          why = safety_.Standing(inputs_);
        }
        if (!why) {
          Advance();
          continue;
        }
        ++bus_.stats().Counter("prechecks_failed");
        const std::string reason = schedule_.phase_names[s.phase] + " cannot start: " + *why;
        // With an operator at hand, ask again (they may fix it); unattended, stop.
        if (!options_.yes && index_ > 0 && steps_[index_ - 1].kind == StepKind::kConfirm) {
          bus_.stats().log().warn("{}", reason);
          Begin(index_ - 1);
          waiting_reason_ = *why;
          state_ = State::kRunning;
          continue;
        }
        Stop(reason);
        return;
      }
      case StepKind::kMarkerStart:
        PublishMarker(s.phase, true);
        Advance();
        continue;
      case StepKind::kMarkerStop:
        PublishMarker(s.phase, false);
        Advance();
        continue;
      default:
        break;
    }
    // Timed steps: the robot moves (or holds) under the safety rules.
    state_ = State::kRunning;
    if (auto e = SafetyViolation()) {
      Stop(*e);
      return;
    }
    if (!EnsureArmed(now)) {
      step_start_utime_ = now;  // the step's clock starts once the bridge takes commands
      return;
    }
    if (!have_goals_ ||
        (now - last_command_utime_) * 1e-6 >= 1.0 / config_.sequencer().command_rate_hz()) {
      Publish(GoalAt(s, t), true);
    }
    if (t < s.duration_s) return;
    if (s.kind == StepKind::kMove && !Arrived(s.to)) {
      if (t > s.duration_s + config_.sequencer().arrival_timeout_s()) {
        std::string where;
        for (int k = 0; k < kNumLegs && inputs_.servo; ++k) {
          const double off = inputs_.servo->angle_rad[k] - s.to[k];
          if (std::abs(off) > config_.sequencer().arrival_tolerance_rad()) {
            where += (where.empty() ? "" : ", ") + std::string(kLegNames[k]) + " " +
                     std::to_string(off) + " rad";
          }
        }
        Stop("the servos did not reach their goals " +
             std::to_string(config_.sequencer().arrival_timeout_s()) +
             " s after the move's end (sequencer.arrival_timeout_s): off by " + where);
      }
      return;
    }
    Advance();
  }
}

void Sequencer::Stop(const std::string& reason) {
  if (state_ == State::kDone || state_ == State::kStopped) return;
  state_ = State::kStopped;
  stop_reason_ = reason;
  ++bus_.stats().Counter("stops");
  bus_.stats().Error("sequencer stopped", reason);
  bus_.stats().log().error("stopping the motion: {}", reason);
  // Hold where the legs are, not where they were going; then DISARM, on which the bridge holds
  // the measured angles itself. (Torque off is not disarmed: the bridge's DISARM and dead-man
  // holds power the servos again.)
  if (arm_utime_ > 0) {
    if (inputs_.servo) {
      Publish(inputs_.servo->angle_rad, true);
      if (config_.sequencer().safe_action() == config::SAFE_TORQUE_OFF) Publish(goals_, false);
    } else if (have_goals_) {
      Publish(goals_, config_.sequencer().safe_action() != config::SAFE_TORQUE_OFF);
    }
    if (config_.sequencer().safe_action() != config::SAFE_TORQUE_OFF) {
      SendAction(servo_command_t::DISARM);
    }
  }
  if (open_marker_phase_ >= 0) PublishMarker(open_marker_phase_, false);
  SaveNow(ResumePoint());
}

std::string Sequencer::ProgressLine() const {
  if (state_ == State::kDone) return "plan '" + schedule_.plan_name + "' done";
  if (index_ >= static_cast<int>(steps_.size())) return "";
  const Step& s = Current();
  std::string line = schedule_.phase_names[s.phase];
  if (s.unit >= 0) {
    int units = 0;
    for (const auto& x : schedule_.steps) {
      if (x.phase == s.phase) units = std::max(units, x.unit + 1);
    }
    line += " " + std::to_string(s.unit + 1) + "/" + std::to_string(units);
  }
  double left = 0.0;
  for (size_t i = index_; i < steps_.size(); ++i) {
    if (Timed(steps_[i].kind)) left += steps_[i].duration_s;
  }
  if (step_started_ && Timed(s.kind))
    left -= std::min(s.duration_s, (bus_.NowUtime() - step_start_utime_) * 1e-6);
  line += ", " + Clock(left) + " left";
  if (state_ == State::kWaitingForOperator) line += " (waiting for the operator)";
  return line;
}

}  // namespace ftcal::sequencer
