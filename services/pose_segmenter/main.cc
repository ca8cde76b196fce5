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
  if (auto rc = app.Init(argc, argv)) return *rc;
  try {
    ftcal::PoseSegmenterStage stage(app.config(), app.bus());
    return app.Run();
  } catch (const std::exception& e) {
    app.log().critical("config: {}", ftcal::UserText(e, "running the segmenter"));
    return ftcal::ExitCodeFor(e, ftcal::kExitConfig);
  }
}
