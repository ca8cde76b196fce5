// ftcal-drift: the transducers' offsets tracked while the robot works (DRIFT once a second),
// live or over a log; with --out-calibration, the calibration with the offsets tracked at the
// end of the input; with --apply, a new CALIBRATION (signed with --signing-key) whenever a leg's
// offsets moved significantly, which the corrector takes up.
#include <exception>
#include <optional>
#include <string>

#include "common/envelope.h"
#include "common/exit_codes.h"
#include "common/service.h"
#include "drift/drift_stage.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"

int main(int argc, char** argv) try {
  ftcal::ServiceApp app(
      {"ftcal-drift",
       "Reads FT_<LEG> (ft_batch_t), SERVO_STATE, MOCAP_BODY, EXPERIMENT and CALIBRATION. "
       "Tracks each leg's transducer offsets (6 axes, with sigma) from the windows where that leg "
       "is in the air and quasi-static (foot force below drift.max_foot_force_n, shaft "
       "acceleration below drift.max_shaft_accel_rad_s2): there it reads its own leg's gravity "
       "plus its offset (docs/method.md, \"Offset drift while the robot works\"). Publishes DRIFT "
       "(drift_t) every drift.publish_period_s: per leg the offset change since the calibration "
       "+- sigma, the windows used, and the balance residual of the six corrected wrenches with "
       "and without the tracked offsets; WARN (and state DEGRADED) when a change exceeds "
       "drift.warn_factor x the calibration's own sigma of that offset. With --apply, publishes "
       "on CALIBRATION the calibration in use with a leg's offsets replaced by the tracked ones "
       "(version + 1) when that leg's change is significant (beyond drift.apply_factor x the "
       "tracker's sigma and the calibration's own), at most once per "
       "drift.apply_min_interval_s.",
       /*replayable=*/true});
  std::string calibration_path, out_calibration, csv_path, signing_key;
  bool apply = false;
  app.cli().add_option("--calibration", calibration_path,
                       "start with this calibration file (text format)");
  app.cli().add_option("--out-calibration", out_calibration,
                       "at the end of the input: the calibration with the offsets tracked then "
                       "(version + 1; offset_reestimation says how), written atomically");
  app.cli().add_option("--csv", csv_path,
                       "at the end of the input: the DRIFT series as CSV (one row per message "
                       "and leg), written atomically");
  app.cli().add_flag("--apply", apply,
                     "publish a calibration with the tracked offsets on CALIBRATION when a leg's "
                     "change is significant (docs/method.md, \"Applying the tracked offsets\"); "
                     "off by default");
  app.cli().add_option("--signing-key", signing_key,
                       "with --apply: sign CALIBRATION with the Ed25519 seed in this file "
                       "(owner-only; ftcal-keygen makes one; the config's auth must trust it "
                       "on CALIBRATION)");
  if (auto rc = app.Init(argc, argv)) return *rc;
  if (!signing_key.empty() && !apply) {
    app.log().critical("--signing-key is for --apply (nothing else is signed)");
    return ftcal::kExitUsage;
  }
  // CALIBRATION is a signed channel: without a key, receivers refuse what --apply publishes
  // unless their config allows unsigned (the loopback twin's does).
  std::optional<ftcal::auth::Signer> signer;
  if (!signing_key.empty()) {
    try {
      signer.emplace(ftcal::auth::Signer::FromSeedFile(signing_key));
    } catch (const std::exception& e) {
      app.log().critical("--signing-key: {}", ftcal::UserText(e, "reading the signing key"));
      return ftcal::kExitConfig;
    }
  } else if (apply) {
    app.log().warn(
        "--apply without --signing-key: {} goes out unsigned (refused unless "
        "auth.allow_unsigned)",
        app.config().channels().calibration());
  }
  try {
    ftcal::DriftStage stage(app.config(), app.bus(), [&app](int8_t state) { app.SetState(state); });
    if (apply) stage.EnableApply(signer ? &*signer : nullptr);
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
    if (!out_calibration.empty() && calibration_path.empty() && !app.replaying()) {
      app.log().critical("--out-calibration needs --calibration (the offsets it starts from)");
      return ftcal::kExitUsage;
    }
    app.AddPeriodic(app.config().drift().publish_period_s(), [&stage] { stage.PublishDrift(); });
    bool finished = false;
    app.AtInputEnd([&] {
      stage.Finish();
      finished = true;
    });
    int rc = app.Run();
    if (rc != 0 || !finished) return rc;
    try {
      if (!out_calibration.empty()) {
        std::string command_line;
        for (int i = 0; i < argc; ++i) command_line += (i ? " " : "") + std::string(argv[i]);
        const std::vector<std::string> inputs = app.replaying()
                                                    ? std::vector<std::string>{app.replay_input()}
                                                    : std::vector<std::string>{};
        ftcal::WriteCalibrationFile(
            stage.TrackedCalibrationProto(calibration_path, inputs, command_line), out_calibration);
        app.log().info("{}: the calibration with the tracked offsets", out_calibration);
      }
      if (!csv_path.empty()) ftcal::WriteFileAtomic(csv_path, stage.csv());
    } catch (const std::logic_error& e) {
      app.log().critical("--out-calibration {}: {}", out_calibration, e.what());
      return ftcal::kExitRefused;
    } catch (const std::exception& e) {
      app.log().critical("{}", ftcal::UserText(e, "writing the outputs"));
      return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
    }
    const ftcal::drift_t& last = stage.last();
    app.log().info("{} DRIFT messages; at the end: {}", stage.published(),
                   last.status == ftcal::drift_t::WARN ? "WARN (drift beyond the calibration)"
                   : last.status == ftcal::drift_t::OK ? "OK"
                                                       : "no calibration");
    return rc;
  } catch (const std::exception& e) {
    app.log().critical("config: {}", ftcal::UserText(e, "starting the drift tracker"));
    return ftcal::ExitCodeFor(e, ftcal::kExitConfig);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-drift");
}
