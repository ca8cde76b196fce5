// ftcal-pose-segmenter: aligned samples and steady standing poses (pipeline item 2).
#include <exception>

#include "common/exit_codes.h"
#include "common/service.h"
#include "pose_segmenter/pose_segmenter_stage.h"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-pose-segmenter",
       "Reads FT_<LEG> (ft_sample_t, six legs), SERVO_STATE, MOCAP_BODY and EXPERIMENT. "
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
  if (auto rc = app.Init(argc, argv)) return *rc;
  try {
    ftcal::PoseSegmenterStage stage(app.config(), app.bus(),
                                    /*publish_sync=*/!app.replaying() || sync_samples);
    return app.Run();
  } catch (const std::exception& e) {
    app.log().critical("config: {}", ftcal::UserText(e, "running the segmenter"));
    return ftcal::ExitCodeFor(e, ftcal::kExitConfig);
  }
}
