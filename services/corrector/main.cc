// ftcal-corrector: ground-contact wrenches from every transducer sample, with a calibration
// applied (CONTACT_WRENCH per leg-sample, CONTACT_WRENCH_SUM per six).
#include <exception>

#include "common/exit_codes.h"
#include "common/service.h"
#include "corrector/corrector_stage.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"

int main(int argc, char** argv) try {
  ftcal::ServiceApp app(
      {"ftcal-corrector",
       "Reads FT_<LEG> (ft_batch_t), SERVO_STATE, MOCAP_BODY and CALIBRATION (calibration_t). "
       "Publishes CONTACT_WRENCH (contact_wrench_t) for every transducer sample: that leg's "
       "ground-contact wrench in W about the CoM (docs/method.md eq. 3), the servo and mocap "
       "ages and stale/saturated flags (inputs older than corrector.max_*_age_s); and "
       "CONTACT_WRENCH_SUM (contact_wrench_sum_t) at each sample instant of the pace leg (the "
       "first leg not silent), once every other leg has a sample at or after it: the six legs' "
       "samples nearest that instant summed, the residual against (0,0,G,0,0,0), the "
       "calibration version, the largest distance in time of a summed sample and the flags. "
       "A new CALIBRATION is "
       "validated against the config and used without a restart; a bad one is refused and "
       "logged. Publishes nothing (state DEGRADED) until a calibration is in use.",
       /*replayable=*/true});
  std::string calibration_path;
  app.cli().add_option("--calibration", calibration_path,
                       "start with this calibration file (text format, "
                       "libcal/proto/calibration.proto)");
  if (auto rc = app.Init(argc, argv)) return *rc;
  try {
    ftcal::CorrectorStage stage(app.config(), app.bus(),
                                [&app](int8_t state) { app.SetState(state); });
    if (!calibration_path.empty()) {
      try {
        const auto proto = ftcal::ReadCalibrationFile(calibration_path);
        std::string bytes;
        proto.SerializeToString(&bytes);
        stage.UseCalibration(proto, static_cast<int64_t>(proto.version()), ftcal::Sha256Hex(bytes));
      } catch (const std::exception& e) {
        app.log().critical("--calibration {}: {}", calibration_path,
                           ftcal::UserText(e, "reading the calibration"));
        return ftcal::ExitCodeFor(e, ftcal::kExitRefused);
      }
    }
    stage.ReportWaitingForCalibration();
    app.AtInputEnd([&stage] { stage.FinishSums(); });
    const int rc = app.Run();
    app.log().info("{} leg-samples corrected, {} sums published", stage.leg_samples(),
                   stage.sums());
    return rc;
  } catch (const std::exception& e) {
    app.log().critical("config: {}", ftcal::UserText(e, "starting the corrector"));
    return ftcal::ExitCodeFor(e, ftcal::kExitConfig);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-corrector");
}
