// config.cc's validation machinery, shared by its three files: config.cc (parsing, loading,
// the public helpers), config_validate_devices.cc (the robot and its devices: poses, ATI,
// servos, motion capture, the Dynamixel bus) and config_validate.cc (the run: stages,
// channels, plans, sequencer, authentication, launch groups, and Validate over the whole file).
// Internal to libcal.
#pragma once

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <google/protobuf/text_format.h>

#include "ftcal/config.h"
#include "ftcal/geometry.h"

namespace ftcal::config_detail {

namespace pb = google::protobuf;
using ParseInfoTree = pb::TextFormat::ParseInfoTree;

constexpr double kRotationTolerance = 1e-6;

inline std::string FormatNumber(double v) {
  std::ostringstream s;
  s.precision(10);
  s << v;
  return s.str();
}

struct Location {
  int line = 1;    // 1-based
  int column = 1;  // 1-based
};

// A message being validated: where it sits in the file (its field path and location) and the
// parser's location tree for its own fields, so an error can name the exact line of a field.
// A missing field has no location of its own and points at this enclosing message.
class Node {
 public:
  Node(const pb::Message& message, const ParseInfoTree* tree, std::string path, Location location,
       const std::string* source, std::vector<std::string>* errors)
      : message_(message),
        tree_(tree),
        path_(std::move(path)),
        location_(location),
        source_(source),
        errors_(errors) {}

  const std::string& path() const { return path_; }

  // Path and location of field `name` (element `index` of a repeated field).
  std::string FieldPath(std::string_view name, int index = -1) const {
    std::string p = path_.empty() ? std::string(name) : path_ + "." + std::string(name);
    if (index >= 0) p += "[" + std::to_string(index) + "]";
    return p;
  }

  Location FieldLocation(std::string_view name, int index = -1) const {
    const pb::FieldDescriptor* field = Field(name);
    if (tree_ == nullptr) return location_;
    // Repeated scalars written in list syntax ("f: [1, 2, 3]") record one location for the
    // whole list, so an element without its own location falls back to the first.
    int i = field->is_repeated() ? std::max(index, 0) : -1;
    pb::TextFormat::ParseLocation loc = tree_->GetLocation(field, i);
    if (loc.line < 0 && field->is_repeated()) loc = tree_->GetLocation(field, 0);
    if (loc.line < 0) return location_;
    return Location{loc.line + 1, loc.column + 1};
  }

  // The node of a singular message field (which must be present).
  Node Child(std::string_view name, const pb::Message& child) const {
    const pb::FieldDescriptor* field = Field(name);
    const ParseInfoTree* nested = tree_ ? tree_->GetTreeForNested(field, -1) : nullptr;
    return Node(child, nested, FieldPath(name), FieldLocation(name), source_, errors_);
  }

  // The node of element `index` of a repeated message field.
  Node Child(std::string_view name, int index, const pb::Message& child) const {
    const pb::FieldDescriptor* field = Field(name);
    const ParseInfoTree* nested = tree_ ? tree_->GetTreeForNested(field, index) : nullptr;
    return Node(child, nested, FieldPath(name, index), FieldLocation(name, index), source_,
                errors_);
  }

  void Error(std::string_view name, const std::string& what, int index = -1) const {
    ErrorAt(FieldLocation(name, index), FieldPath(name, index), what);
  }

  // An error about the message itself (e.g. a field missing from it).
  void SelfError(const std::string& what) const {
    ErrorAt(location_, path_.empty() ? std::string("<config>") : path_, what);
  }

  void Missing(std::string_view name) const {
    ErrorAt(location_, FieldPath(name), "required field is missing");
  }

  // Checks for finite numbers, with the value and the bound in the message.
  bool Finite(std::string_view name, double v, int index = -1) const {
    if (std::isfinite(v)) return true;
    Error(name, "must be a finite number, got " + FormatNumber(v), index);
    return false;
  }
  void Positive(std::string_view name, double v) const {
    if (Finite(name, v) && !(v > 0.0)) Error(name, "must be > 0, got " + FormatNumber(v));
  }

 private:
  const pb::FieldDescriptor* Field(std::string_view name) const {
    const pb::FieldDescriptor* field = message_.GetDescriptor()->FindFieldByName(std::string(name));
    if (field == nullptr) {
      // A misspelt name in the validation code, not bad input: stop loudly.
      throw std::logic_error("config validation: no field '" + std::string(name) + "' in " +
                             message_.GetDescriptor()->full_name());
    }
    return field;
  }

  void ErrorAt(Location loc, const std::string& path, const std::string& what) const {
    errors_->push_back(*source_ + ":" + std::to_string(loc.line) + ":" +
                       std::to_string(loc.column) + ": " + path + ": " + what);
  }

  const pb::Message& message_;
  const ParseInfoTree* tree_;
  std::string path_;
  Location location_;
  const std::string* source_;
  std::vector<std::string>* errors_;
};

// Bounds of plausibility: far beyond any hexapod this project calibrates, close enough to
// catch a unit typed wrong (grams for kg, mm for m).
constexpr double kMaxRobotMassKg = 1000.0;
constexpr double kMaxTransducerDistanceM = 10.0;
constexpr double kMinRatedRange = 1e-3;
constexpr double kMaxRatedRange = 1e6;
constexpr double kMaxSavgolWindowS = 60.0;

// The robot and its devices (config_validate_devices.cc).
std::string RotationProblem(const Mat3& R);
Mat3 RowMajor(const config::Pose& pose);
void ValidateRobot(const Node& node, const config::Robot& robot);
void ValidateMocap(const Node& node, const config::Mocap& mocap);
void ValidateDynamixel(const Node& node, const config::DynamixelBus& bus);
void ValidateDrift(const Node& node, const config::Drift& drift);

// Every section of a parsed config, each error with its file:line:column and field path
// (config_validate.cc).
void Validate(const config::Config& config, const ParseInfoTree* tree, const std::string& source,
              std::vector<std::string>* errors);

}  // namespace ftcal::config_detail
