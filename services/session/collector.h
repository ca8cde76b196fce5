// The collector: a session's phases into the datasets the calibration takes. ftcal-calibrator
// calibrates from what it collects; ftcal-pose-segmenter runs one in index-only mode to make the
// span index (span_index.h). Its jobs, each in a file of its own: reading the bus
// (collector.cc, collector_inputs.cc), the phases' starts and ends (collector_phases.cc), what
// the phases keep and hand over (collector_results.cc), and the span index
// (collector_spans.cc, span_noting.h).
//
// CalibrationCollector listens on a Bus (a LogReplayBus per input log, or live LCM) and turns
// FT_<LEG>, SERVO_STATE, MOCAP_BODY, EXPERIMENT and STEADY_POSE into what Calibrate() consumes:
//   - every aligned sample (libcal's Aligner, the same rule as ftcal-pose-segmenter) between a
//     HANG_* start and its stop marker goes into that series' HangingRecording (per leg: time,
//     shaft angle, reading; gravity_b from the start marker; the attitude when tracked);
//   - steady standing poses: the STEADY_POSE events of the log when it has any, else the
//     PoseSegmenter run over the STANDING spans (as ftcal-pose-segmenter would have);
//   - the aligned samples of the first WALKING phase (up to kMaxWalkingSamples), for the
//     report's walking figure (the report's Fig. 9): corrected vs naive tare;
//   - steady tripod stances (the same segmenter over the TRIPOD spans), with the legs turned
//     past calibrator.unloaded_leg_min_angle_deg marked unloaded: the per-leg equations of the
//     offset re-estimation (docs/method.md "Offset drift").
// Nothing is guessed: a series without its start..stop pair is missing, not reconstructed.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <stdexcept>
#include <regex>
#include <string>
#include <vector>

#include <spdlog/logger.h>
#include <spdlog/spdlog.h>

#include "common/batch_memory.h"
#include "common/bus.h"
#include "common/log_replay_bus.h"
#include "common/messages.h"
#include "ftcal/aligner.h"
#include "ftcal/calibrate.h"
#include "ftcal/dataset.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/experiment_phase.h"
#include "ftcal/offset_reestimation.h"
#include "ftcal/segmenter.h"
#include "ftcal/steady_pose_t.hpp"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"
#include "proto/log_index.pb.h"
#include "session/deferred_tail.h"
#include "session/span_noting.h"

namespace ftcal {

// The input cannot give a calibration (missing series, no markers, a config for another robot,
// a damaged log, a stage that refused its data). what() names the problem.
class CalibratorInputError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct CollectorCounters {
  int64_t markers = 0;
  int64_t aligned_samples = 0;
  int64_t hanging_samples = 0;
  int64_t standing_samples = 0;
  int64_t logged_poses = 0;            // STEADY_POSE events seen
  int64_t segmented_poses = 0;         // poses the collector's own segmenter found
  int64_t poses_dropped_markers = 0;   // logged poses without every marker
  int64_t walking_samples = 0;         // aligned samples inside WALKING phases (kept or not)
  int64_t tripod_samples = 0;          // aligned samples inside TRIPOD phases
  int64_t tripod_stances = 0;          // steady tripod stances with a leg unloaded, kept
  int64_t tripod_stances_dropped = 0;  // steady, but no leg lifted
  int64_t span_events_skipped = 0;     // events of STANDING spans not read (the span index)
  // Aligned inside a hanging series but stamped before its start marker: the previous phase's
  // last instant, which the aligner completes only when the next readings arrive. Left out: its
  // reading belongs to another attitude, and one such sample weighs on step 1 as thousands.
  int64_t hanging_before_start = 0;
};

// One completed phase's transducer records per leg, counted by the devices' RDT sequence
// numbers (ft_batch_t.rdt_sequence rises by 1 a record): what reached this input and what
// did not, wherever it was lost (network, bridge, the recorder's socket).
struct PhaseGaps {
  int phase = -1;  // experiment_marker_t phase code
  std::string session;
  std::array<int64_t, kNumLegs> received{};
  std::array<int64_t, kNumLegs> lost{};
  // A number that fell back far (a new RDT stream: the bridge or the device restarted): the
  // records of the outage have no numbers to miss, so it is counted apart from the gaps.
  std::array<int64_t, kNumLegs> restarts{};
  bool superseded = false;  // a hanging series recorded again later: this one is not used
  double LostShare(int k) const {
    const int64_t n = received[k] + lost[k];
    return n > 0 ? static_cast<double>(lost[k]) / static_cast<double>(n) : 0.0;
  }
};

class CalibrationCollector {
 public:
  // Throws std::invalid_argument for a config whose legs are not kLegNames in order.
  explicit CalibrationCollector(const config::Config& config);

  // Subscribes the handlers on `bus` (call once per bus; several logs = several buses, fed in
  // order). On a LogReplayBus the collector may skip spans of its log (SetSpanIndex); on any
  // other bus it reads everything.
  void Attach(Bus& bus);
  void Attach(LogReplayBus& bus);
  // Ends a phase in progress (its samples are kept only if its stop marker came).
  void Flush();

  // Called when a STANDING phase stops (live mode calibrates then).
  void SetOnStandingStop(std::function<void()> fn) { on_standing_stop_ = std::move(fn); }
  // Called after every STEADY_POSE event (live mode waits for the segmenter's last pose).
  void SetOnSteadyPose(std::function<void()> fn) { on_steady_pose_ = std::move(fn); }
  // Offline pipelining (EarlyCalibration, calibrator.h). `ready` runs when what Calibrate()
  // takes may be complete: a STANDING phase starts that is not segmented again (its poses were
  // read before), the rest of the session still to read. `before_change` runs before the
  // collector changes any of it: the hanging series (HangingRecordings() refers to them), the
  // standing poses, the tare.
  void SetCalibrationInputHooks(std::function<void()> ready, std::function<void()> before_change) {
    on_inputs_ready_ = std::move(ready);
    before_inputs_change_ = std::move(before_change);
  }
  // Offline, with the poses log read before the session: a STANDING phase whose session's
  // STEADY_POSE events were all read already, each with its within-pose scatter, is not
  // segmented again (that was a large share of the calibrator's time: docs/performance.md). Live,
  // the poses arrive during the phase, so the collector always segments it (the live calibrator
  // waits for the segmenter's last pose by comparing the two counts).
  void SetSkipSegmentingLoggedSessions(bool skip) { skip_logged_sessions_ = skip; }
  // Whether TRIPOD phases are segmented into steady stances (unloaded_samples()): what offset
  // drift re-estimation takes (RunOffsetReestimation) and nothing else. Offline calibration
  // does not, and then a TRIPOD phase is read as a STANDING phase not segmented again: its
  // records only counted (the recording gaps are the same), its span noted and skipped
  // another time. Default true (live, and --reestimate-offsets).
  void SetCollectTripodStances(bool collect) { collect_tripod_stances_ = collect; }
  // The span index (log_index.proto), offline. Reading a log whole, the collector notes the
  // spans of its STANDING phases not segmented again (and TRIPOD phases whose stances it does
  // not collect) where it only counted transducer records
  // and kept the last servo states and mocap frames (the events after such a span refill the
  // kept ones): TakeSpanIndex() gives them, with the counts before and after each, for the
  // digest cache. SetSpanIndex(index) before Attach(bus) lets the collector skip those spans
  // of the bus's log: on reaching a span with the counts it had then, it takes the counts it
  // had after and the bus reads on from the span's end. Everything collected is as if it had
  // read the span: the cache's key vouches that the bytes are the ones counted (the rule that
  // gives the log's digest), the rules string that they were counted the same way.
  void SetSpanIndex(const logindex::LogIndex* index) { use_index_ = index; }
  logindex::LogIndex TakeSpanIndex();
  // The rules a span index is made under: this code's version and the config's channels.
  std::string SpanIndexRules() const;
  // A collector that only makes the span index of a session log (SessionIndexer,
  // span_index.h), in a process that reads the log before the calibrator does: every STANDING
  // phase is read as the calibrator reads one whose poses it has from a poses log, TRIPOD
  // stances are not collected (as offline), and nothing is kept for a calibration (no hanging
  // series, walk or poses). Before Attach().
  void SetIndexOnly();
  // Where the collector's lines go (default: spdlog's default logger).
  void SetLogger(std::shared_ptr<spdlog::logger> log) { log_ = std::move(log); }

  // Poses with every marker tracked: from STEADY_POSE events, and found by the collector's own
  // segmenter over the completed STANDING phases (the same rule as ftcal-pose-segmenter).
  size_t logged_pose_count() const { return logged_poses_.size(); }
  size_t segmented_pose_count() const { return segmented_poses_.size(); }

  // What was collected. Throws CalibratorInputError naming what is missing or inconsistent.
  // The four series in HangSeries order, by reference: a copy of them at the report's scale is
  // dear (docs/performance.md).
  const std::vector<HangingRecording>& HangingRecordings() const;
  std::vector<StandingPose> StandingPoses() const;
  // Throws CalibratorInputError when there were no EXPERIMENT markers (`phases`: what cannot be
  // told apart without them; when the config refused unsigned ones, how many and what to do)
  // or the FT_* channels seen are not the config's legs.
  void CheckMarkersAndLegs(const std::string& phases) const;

  // The aligned samples of the first completed WALKING phase (empty when there was none).
  // Bounded: ten minutes at 100 Hz is more than a figure shows.
  static constexpr size_t kMaxWalkingSamples = 60000;
  const std::vector<SyncSample>& walking_samples() const { return walking_; }

  // The naive tare of the last completed TARE phase (mean reading per leg; upright, feet in the
  // air, shafts at 0), when there was one.
  const std::optional<std::array<Vec6, kNumLegs>>& tare() const { return tare_; }

  // Steady tripod stances of the completed TRIPOD phases, with their unloaded legs.
  const std::vector<LoadSample>& unloaded_samples() const { return unloaded_; }

  // Every completed phase, in order, with its records counted (PhaseGaps).
  const std::vector<PhaseGaps>& phase_gaps() const { return phase_gaps_; }
  const std::string& ft_channel(int k) const { return inputs_.FtChannel(k); }

  const CollectorCounters& counters() const { return counters_; }
  const std::string& standing_session() const { return standing_session_; }

 private:
  static bool IsHangPhase(int phase) { return HangSeriesOfPhase(phase).has_value(); }
  // Records arriving a little out of order (two sockets, a busy receiver) are not lost: a
  // number up to this far below the highest seen fills a gap counted before.
  static constexpr int64_t kReorderWindow = 64;
  // Room for a first hanging series before any is known: the report's ten 20 s cycles at 100
  // aligned samples a second, and more.
  static constexpr size_t kFirstHangReserve = size_t{1} << 15;

  // The bus's messages (collector_inputs.cc).
  void OnFtRaw(int k, const MessageInfo& info, const void* data, int size);
  void OnServoRaw(const MessageInfo& info, const void* data, int size);
  void OnMocapRaw(const MessageInfo& info, const void* data, int size);
  // Whether a servo state or mocap frame may wait in a DeferredTail (deferred_ below).
  bool Deferring() const { return counting_only_ && aligner_.pending() == 0; }
  // While deferring: checks the message and keeps it in `tail` (its mark in `marks` when a span
  // is being noted) instead of aligning it. Returns whether it was kept.
  template <class Msg>
  bool Defer(const MessageInfo& info, const void* data, int size, DeferredTail& tail,
             MarkRing& marks);
  void FlushDeferred();
  void CountRecord(int k, int64_t sequence);
  void NoteChannel(const MessageInfo& info);
  void OnExperiment(const experiment_marker_t& msg);

  // The phases, each started and ended by its own step (collector_phases.cc).
  void StartPhase(const MarkedPhase& phase, const experiment_marker_t& msg);
  // Each Start* returns whether the phase's start is still to be logged.
  bool StartHanging(const MarkedPhase& phase, const experiment_marker_t& msg);
  void ReserveHangingRoom();
  bool StartStanding(const MarkedPhase& phase);
  void StartTare();
  bool StartTripod(const MarkedPhase& phase);
  void StartWalking();
  void StartSpanNoting(const MarkedPhase& phase);
  void EndPhase(const MarkedPhase& phase, bool completed);
  void EndCountingOnly(const MarkedPhase& phase, bool completed);
  SegmenterCounters EndSegmenting();
  void EndHanging(bool completed);
  void EndStanding(const MarkedPhase& phase, bool completed, bool not_segmented);
  void EndTare(const MarkedPhase& phase, bool completed);
  void EndTripod(const MarkedPhase& phase, bool completed, bool not_segmented,
                 const SegmenterCounters& segmented);
  void EndWalking(const MarkedPhase& phase, bool completed);

  // What the phases keep (collector_results.cc).
  void OnSteadyPose(const steady_pose_t& msg);
  void OnAligned(const AlignedSample& a);
  void OnTripodStance(const SteadyPoseOut& p);

  // The span index (collector_spans.cc): the counts of the phase in progress, noted while a
  // phase is read whole, taken back where a span is skipped.
  CountState Counts() const;
  void SetCounts(const CountState& c);
  void NoteSpanEvent(const MessageInfo& info, bool barrier);
  void EndSpanNoting(const std::string& session, int phase);
  void ArmSkip(const std::string& session, int phase);

  const config::Config& config_;
  // EXPERIMENT is a signed channel (common/envelope.h).
  auth::Verifier verifier_ = auth::Verifier::FromConfig(config_);
  int64_t unsigned_markers_ = 0;  // refused as unsigned by the verifiers of earlier inputs
  DeviceInputs inputs_;
  SegmenterOptions segmenter_options_;
  Aligner aligner_;
  std::unique_ptr<PoseSegmenter> segmenter_;

  PhaseTracker phases_;  // the phase in progress
  HangingRecording current_hang_;
  int64_t hang_start_utime_ = 0;  // the open hanging series' start marker
  std::vector<StandingPose> current_poses_;
  std::vector<SyncSample> current_walk_;
  std::vector<SyncSample> walking_;
  std::vector<LoadSample> current_unloaded_;
  std::vector<LoadSample> unloaded_;
  std::array<Vec6, kNumLegs> tare_sum_;
  int64_t tare_count_ = 0;
  std::optional<std::array<Vec6, kNumLegs>> tare_;

  std::vector<HangingRecording> hang_ = std::vector<HangingRecording>(kNumHangSeries);
  std::array<bool, kNumHangSeries> have_hang_{};
  std::vector<StandingPose> segmented_poses_;
  std::vector<StandingPose> logged_poses_;
  // Per session of the STEADY_POSE events read: whether every one carried its scatter.
  std::map<std::string, bool> logged_sessions_scatter_;
  bool skip_logged_sessions_ = false;
  bool collect_tripod_stances_ = true;
  bool index_only_ = false;
  std::shared_ptr<spdlog::logger> log_ = spdlog::default_logger();
  // In a STANDING phase not segmented again, or a TRIPOD phase whose stances are not
  // collected: its records are only counted, its last servo states and mocap frames kept.
  bool counting_only_ = false;
  std::string standing_session_;
  std::set<std::string> ft_channels_seen_;
  std::set<std::string> channels_seen_;  // every channel, to name them when the config's are absent
  // This runs for every event, where a set lookup was a noticeable share of the reading
  // (docs/performance.md): on replay the bus's channel ids (reset per bus) answer with no
  // compare at all; live, channels_seen_ does.
  std::vector<bool> channel_ids_noted_;
  // The FT subscription's pattern, as the bus matches it (every FT_* channel, not just the
  // config's).
  std::regex ft_pattern_{config_.channels().ft_prefix() + ".*", std::regex::extended};
  ft_batch_t ft_scratch_;
  FtBatch batch_;
  std::array<int64_t, kMaxFtRecords> sequences_{};
  servo_state_t servo_scratch_;
  mocap_body_t mocap_scratch_;
  // Over a phase read only for its counts, the last servo states and mocap frames as bytes
  // (deferred_tail.h).
  DeferredTail deferred_servo_, deferred_mocap_;

  SpanNoting noting_;
  logindex::LogIndex produced_;
  const logindex::LogIndex* use_index_ = nullptr;
  LogReplayBus* replay_ = nullptr;         // the bus attached last, when a replay (SkipAt)
  int64_t event_end_ = -1;                 // the end of the event being handled (replay)
  std::vector<bool> channel_ids_barrier_;  // by channel id: a channel that is not only counted

  PhaseGaps current_gaps_;
  std::array<int64_t, kNumLegs> last_sequence_{};  // 0: none yet in this phase
  std::vector<PhaseGaps> phase_gaps_;
  std::array<int, kNumHangSeries> hang_gaps_index_;  // into phase_gaps_, -1: none
  std::function<void()> on_standing_stop_;
  std::function<void()> on_steady_pose_;
  std::function<void()> on_inputs_ready_;
  std::function<void()> before_inputs_change_;
  void BeforeInputsChange() {
    if (before_inputs_change_) before_inputs_change_();
  }
  CollectorCounters counters_;

  // The hanging series' room, faulted in on another thread while this one fills it
  // (ReserveHangingRoom). Last: destroyed, so waited for, before the buffers it touches are
  // freed.
  BatchMemory hang_memory_;
};

}  // namespace ftcal
