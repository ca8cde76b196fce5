// ftcal-pose-segmenter: the transducer, servo and mocap streams aligned into SYNC_SAMPLE, and
// the steady standing poses found in them published as STEADY_POSE (the calibrator's input).
#include <exception>
#include <future>
#include <memory>
#include <stdexcept>
#include <string>
#include <system_error>

#include "common/exit_codes.h"
#include "common/service.h"
#include "ftcal/calibration_io.h"
#include "pose_segmenter/pose_segmenter_stage.h"
#include "session/span_index.h"

int main(int argc, char** argv) try {
  ftcal::ServiceApp app(
      {"ftcal-pose-segmenter",
       "Reads FT_<LEG> (ft_batch_t, six legs), SERVO_STATE, MOCAP_BODY and EXPERIMENT. "
       "Publishes SYNC_SAMPLE (sync_sample_t) each time every leg has a newer reading: the six "
       "wrenches, the shaft angles interpolated to that time and the latest attitude; and, "
       "while the EXPERIMENT phase is STANDING, STEADY_POSE (steady_pose_t) for each steady "
       "pose (Savitzky-Golay force derivative below segmenter.max_force_rate_n_s for longer "
       "than min_steady_s; medians of its samples), with the session id and a running index. "
       "Channel names and parameters from the config.",
       /*replayable=*/true, /*digest_replay_output=*/true});
  bool sync_samples = false;
  app.cli().add_flag(
      "--sync-samples", sync_samples,
      "with --replay: write SYNC_SAMPLE (every aligned sample) into --out as well. Without it a "
      "replay writes the poses log the calibrator reads: STEADY_POSE and this process's status, "
      "0.5 MB for the report's experiment instead of 243 MB of SYNC_SAMPLE that nothing "
      "reads from a file. Live, SYNC_SAMPLE is always published");
  std::string calibration_path;
  app.cli().add_option("--calibration", calibration_path,
                       "a calibration file whose servo delay (latencies.applied_servo_delay_s) "
                       "to apply before aligning: servo stamps moved back by it");
  if (auto rc = app.Init(argc, argv)) return *rc;
  try {
    double servo_delay_s = 0.0;
    if (!calibration_path.empty()) {
      try {
        servo_delay_s = ftcal::CalibrationFromProto(ftcal::ReadCalibrationFile(calibration_path),
                                                    app.config().robot())
                            .servo_delay_s;
      } catch (const std::runtime_error& e) {
        throw std::invalid_argument("--calibration '" + calibration_path + "': " + e.what());
      }
    }
    ftcal::PoseSegmenterStage stage(app.config(), app.bus(),
                                    /*publish_sync=*/!app.replaying() || sync_samples,
                                    servo_delay_s);
    // A replayed session is read by the calibrator next: its span index, made on the other
    // core while this one segments, spares the first calibration the STANDING phase's bytes.
    std::future<ftcal::SpanIndexPass> index;
    if (app.replaying()) {
      const ftcal::DigestCache cache = ftcal::DigestCache::FromEnvironment();
      if (cache.enabled()) {
        try {
          auto indexer =
              std::make_shared<ftcal::SessionIndexer>(app.config(), app.replay_input(), cache);
          index = std::async(std::launch::async, [indexer] { return indexer->Run(); });
        } catch (const std::system_error&) {
          // No thread to spare: the calibrator makes the index when it first reads the log.
        }
      }
    }
    const int rc = app.Run();
    if (index.valid()) {
      const ftcal::SpanIndexPass pass = index.get();
      if (pass.stored) {
        app.log().info(
            "{}: span index for the calibrator in the digest cache: {} spans, {:.0f} MB it "
            "need not read",
            app.replay_input(), pass.spans, 1e-6 * static_cast<double>(pass.span_bytes));
      } else {
        app.log().info("{}: no span index for the calibrator: {}", app.replay_input(),
                       pass.why_not);
      }
    }
    return rc;
  } catch (const std::exception& e) {
    app.log().critical("config: {}", ftcal::UserText(e, "running the segmenter"));
    return ftcal::ExitCodeFor(e, ftcal::kExitConfig);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-pose-segmenter");
}
