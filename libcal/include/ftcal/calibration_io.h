// The calibration file (libcal/proto/calibration.proto) <-> the parameters eq. 3 uses.
#pragma once

#include <string>

#include "ftcal/sensing_model.h"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

// Values only (sigmas are filled by the method, which knows them): legs in config order,
// offsets, leg weights, CoM fits, mounting (quaternion, rotation vector, p~', p~), p^C_B.
void FillCalibrationValues(const RobotCalibration& cal, calibration::Calibration* out);

// The largest servo delay a calibration file may apply (latencies.applied_servo_delay_s), s.
constexpr double kMaxServoDelayS = 1.0;

// The parameters of eq. 3 from a calibration file and the config that supplies the nominal
// transducer poses. Throws std::runtime_error naming the field when the file does not match
// the config (leg names, count) or a value is missing or not finite.
RobotCalibration CalibrationFromProto(const calibration::Calibration& proto,
                                      const config::Robot& robot);

// A calibration that verified and parsed can still be absurd (a signature says who made it,
// not that it is sane): throws std::runtime_error naming the parameter, its value and the limit
// unless it fits the config's robot. Its total mass is the configured one within
// calibrator.mass_tolerance_kg; g0 within kG0ToleranceMs2 of the configured; each leg weight
// positive and the six together below the robot's weight (the legs are part of it); each offset
// component within the transducer's rated range (ati.rated_range, where given); p~', p^C_B and
// every leg CoM r_k(phi) within the robot's size (twice the farthest transducer from the body
// origin, at least kMinRobotSizeM).
constexpr double kG0ToleranceMs2 = 0.1;
constexpr double kMinRobotSizeM = 0.1;
void CheckCalibrationPlausible(const RobotCalibration& cal, const config::Config& config);

// Text format. Writing is atomic: a temporary file beside the target, fsync, rename.
calibration::Calibration ReadCalibrationFile(const std::string& path);
void WriteCalibrationFile(const calibration::Calibration& cal, const std::string& path);
// Atomic write of any bytes (used for every file ftcal writes).
void WriteFileAtomic(const std::string& path, const std::string& bytes);

}  // namespace ftcal
