// ftcal-doctor's examination of a recording: per device stream its rates, what it lost (by the
// device's own counters) and when it stalled (by the host's receive times), its clock against
// the host's (DeviceClock, docs/method.md "Clocks and delays"), its flagged samples; the
// experiment's phases as the calibrator will see them (the same EXPERIMENT rules and signature
// checks); and a verdict: calibratable, calibratable with warnings, or not, with every reason.
//
// One pass over the log, reading the device messages in place (Peek*, common/messages.h): a
// recording of a whole experiment is ~1 GB, and the doctor runs before every calibration.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/bus.h"
#include "common/envelope.h"
#include "common/messages.h"
#include "doctor/sigma_forecast.h"
#include "ftcal/device_clock.h"
#include "ftcal/experiment_phase.h"
#include "ftcal/legs.h"
#include "proto/config.pb.h"

namespace ftcal::doctor {

// A stretch of a stream: where it starts (s since the recording's first event) and how long.
struct Stretch {
  double t_s = 0;
  double length_s = 0;
  int64_t samples = 0;  // samples lost in it (gaps); 0 for a stall
  std::string phase;    // the EXPERIMENT phase it fell in; empty between phases
};

// Receipt-minus-mapped-time (the queuing each sample met), in log-spaced bins.
class DelayHistogram {
 public:
  void Add(double delay_s);
  double Quantile(double q) const;  // s; 0 when empty
  double max_s() const { return max_s_; }
  int64_t count() const { return count_; }

 private:
  static constexpr int kBins = 160;  // 1 us .. ~10 s, 10 % apart
  std::array<int64_t, kBins> bins_{};
  int64_t count_ = 0;
  double max_s_ = 0;
};

struct StreamHealth {
  std::string name;    // the channel, e.g. FT_HL
  std::string device;  // what the counter is, e.g. "Net F/T sample counter, 7000 Hz"
  int64_t samples = 0;
  int64_t first_utime = -1, last_utime = -1;
  double rate_hz = 0;                      // from the device's counter over the stream's span
  int64_t lost = 0;                        // samples the device counted that never arrived
  std::vector<Stretch> gaps;               // where they were lost
  std::vector<Stretch> stalls;             // silences of the host's receipt with nothing lost
  int64_t duplicates = 0;                  // a counter seen twice
  int64_t counter_restarts = 0;            // a counter that fell (the device restarted)
  std::map<std::string, int64_t> flagged;  // "saturated", "stale HL", "untracked", ...
  bool has_clock = false;
  double skew_ppm = 0;
  int64_t clock_restarts = 0;
  DelayHistogram queuing;
};

struct PhaseHealth {
  int code = -1;
  std::string session;
  double start_s = 0, end_s = 0;  // since the recording's first event
  bool completed = false;
  int64_t poses = 0;       // STEADY_POSE events inside (the segmenter's, when it was recorded)
  double shaft_turns = 0;  // of the slowest servo, for a hanging phase: about its cycles
  Vec3 gravity_b = Vec3::Zero();  // a hanging phase's stated gravity (its start marker), in B
  std::array<int64_t, kNumLegs> ft_received{}, ft_lost{};
};

struct HealthReport {
  std::vector<std::string> logs;
  int64_t bytes = 0, events = 0;
  int64_t first_utime = -1, last_utime = -1;
  std::vector<StreamHealth> streams;  // FT_<LEG> x6, SERVO_STATE, MOCAP_BODY
  std::vector<PhaseHealth> phases;
  int64_t markers = 0, markers_refused = 0;
  std::string marker_refusal;  // the first refusal's kind
  int64_t steady_poses = 0;
  std::vector<PlannedPose> steady;  // those with every marker tracked, as the calibrator keeps
  SigmaForecast forecast;
  std::vector<std::string> problems;  // each makes the recording not calibratable
  std::vector<std::string> warnings;  // calibratable, but look first
  struct Note {
    std::string stream;  // the stream it is about; empty for the recording as a whole
    std::string text;
  };
  std::vector<Note> notes;  // worth knowing, nothing wrong
};

class LogExaminer {
 public:
  explicit LogExaminer(const config::Config& config);
  ~LogExaminer();
  // Subscribes to what a recording holds; then the bus's Run() feeds it. One bus per file, the
  // files of one recording in order.
  void Attach(Bus& bus);
  // After each file: its size and event count, and the refusals its bus counted.
  void FileDone(const std::string& path, int64_t bytes, int64_t events, const ServiceStats& stats);
  // Closes the open phase and judges.
  HealthReport Finish();

 private:
  struct FtState;
  struct ServoState;
  struct MocapState;
  void OnFt(int leg, const MessageInfo& info, const void* data, int size);
  void OnServo(const MessageInfo& info, const void* data, int size);
  void OnMocap(const MessageInfo& info, const void* data, int size);
  void OnMarker(const MessageInfo& info, const experiment_marker_t& m);
  void OnSteadyPose(const MessageInfo& info, const void* data, int size);
  void Forecast(HealthReport& r) const;
  void Seen(int64_t utime);
  // The open phase's name when a stretch starting at `start_s` lies in it, else "".
  std::string PhaseAt(double start_s) const;
  double Since(int64_t utime) const;
  void Judge(HealthReport& r) const;

  config::Config config_;
  DeviceInputs inputs_;
  auth::Verifier verifier_;
  HealthReport report_;
  std::array<std::unique_ptr<FtState>, kNumLegs> ft_;
  std::unique_ptr<ServoState> servo_;
  std::unique_ptr<MocapState> mocap_;
  PhaseTracker tracker_;
  std::optional<size_t> open_phase_;  // index in report_.phases
  std::function<std::string(double)> phase_at_ = [this](double t_s) { return PhaseAt(t_s); };
  servo_state_t servo_scratch_;
  ft_batch_t ft_scratch_;
  FtBatch ft_batch_;
  mocap_body_t mocap_scratch_;
  steady_pose_t pose_scratch_;
};

// The one-screen text of a report, and the exit code of its verdict (kExitDone, kExitWarnings,
// kExitRefused).
std::string Render(const HealthReport& report);
int ExitCodeOf(const HealthReport& report);

}  // namespace ftcal::doctor
