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

// The parameters of eq. 3 from a calibration file and the config that supplies the nominal
// transducer poses. Throws std::runtime_error naming the field when the file does not match
// the config (leg names, count) or a value is missing or not finite.
RobotCalibration CalibrationFromProto(const calibration::Calibration& proto,
                                      const config::Robot& robot);

// Text format. Writing is atomic: a temporary file beside the target, fsync, rename.
calibration::Calibration ReadCalibrationFile(const std::string& path);
void WriteCalibrationFile(const calibration::Calibration& cal, const std::string& path);
// Atomic write of any bytes (used for every file ftcal writes).
void WriteFileAtomic(const std::string& path, const std::string& bytes);

}  // namespace ftcal
