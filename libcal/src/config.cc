#include "ftcal/config.h"

#include <arpa/inet.h>
#include <openssl/evp.h>

#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <set>
#include <memory>
#include <sstream>
#include <string_view>
#include <vector>

#include <google/protobuf/io/tokenizer.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>
#include <google/protobuf/text_format.h>

#include "config_internal.h"

namespace ftcal {
namespace {

using namespace config_detail;

// TextFormat reports 0-based positions; every message we print is 1-based. Its messages name
// the token, not the field ("Expected double, got: ..."), so the offending source line is
// quoted under the message with a caret, as compilers do.
class CollectingErrorCollector : public pb::io::ErrorCollector {
 public:
  CollectingErrorCollector(std::string source, const std::string& text)
      : source_(std::move(source)), text_(text) {}

  void AddError(int line, pb::io::ColumnNumber column, const std::string& message) override {
    std::string e = source_ + ":" + std::to_string(line + 1) + ":" + std::to_string(column + 1) +
                    ": " + message;
    const std::string quoted = Line(line);
    if (!quoted.empty()) {
      e += "\n    " + quoted + "\n    " + std::string(std::max(column, 0), ' ') + "^";
    }
    errors_.push_back(std::move(e));
  }

  const std::vector<std::string>& errors() const { return errors_; }

 private:
  std::string Line(int line) const {
    size_t begin = 0;
    for (int i = 0; i < line; ++i) {
      begin = text_.find('\n', begin);
      if (begin == std::string::npos) return {};
      ++begin;
    }
    const size_t end = text_.find('\n', begin);
    return text_.substr(begin, end == std::string::npos ? std::string::npos : end - begin);
  }

  std::string source_;
  const std::string& text_;
  std::vector<std::string> errors_;
};

std::string JoinErrors(const std::vector<std::string>& errors) {
  std::string out;
  for (const std::string& e : errors) {
    if (!out.empty()) out += "\n";
    out += e;
  }
  return out;
}

std::string ReadWholeFile(const std::string& path, const char* what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw ConfigError(std::string("cannot open ") + what + " '" + path +
                      "': " + std::strerror(errno));
  }
  std::ostringstream s;
  s << in.rdbuf();
  if (in.bad()) {
    throw ConfigError(std::string("cannot read ") + what + " '" + path +
                      "': " + std::strerror(errno));
  }
  return s.str();
}

std::string ToHex(const unsigned char* digest, unsigned int length) {
  static constexpr char kHex[] = "0123456789abcdef";
  std::string hex;
  hex.reserve(2 * length);
  for (unsigned int i = 0; i < length; ++i) {
    hex += kHex[digest[i] >> 4];
    hex += kHex[digest[i] & 0xf];
  }
  return hex;
}

}  // namespace

config::Config LoadConfigText(const std::string& text, const std::string& source_name) {
  config::Config config;
  CollectingErrorCollector collector(source_name, text);
  ParseInfoTree tree;
  pb::TextFormat::Parser parser;
  parser.RecordErrorsTo(&collector);
  parser.WriteLocationsTo(&tree);
  pb::io::ArrayInputStream input(text.data(), static_cast<int>(text.size()));
  if (!parser.Parse(&input, &config)) {
    if (collector.errors().empty()) {
      throw ConfigError(source_name + ":1:1: could not parse the config");
    }
    throw ConfigError(JoinErrors(collector.errors()));
  }
  std::vector<std::string> errors;
  Validate(config, &tree, source_name, &errors);
  if (!errors.empty()) throw ConfigError(JoinErrors(errors));
  return config;
}

config::Config LoadConfigFile(const std::string& path) {
  return LoadConfigText(ReadWholeFile(path, "config file"), path);
}

Pose3 ToPose3(const config::Pose& pose) {
  if (!pose.has_translation_m()) throw ConfigError("pose: translation_m is missing");
  const config::Vec3& t = pose.translation_m();
  const Vec3 p(t.x(), t.y(), t.z());
  if (!p.allFinite()) throw ConfigError("pose: translation_m is not finite");
  const bool has_matrix = pose.rotation_row_major_size() > 0;
  if (has_matrix == pose.has_rpy_deg()) {
    throw ConfigError("pose: give exactly one of rotation_row_major and rpy_deg");
  }
  if (pose.has_rpy_deg()) {
    const config::Vec3& a = pose.rpy_deg();
    const Vec3 rpy_rad = Vec3(a.x(), a.y(), a.z()) * (M_PI / 180.0);
    if (!rpy_rad.allFinite()) throw ConfigError("pose: rpy_deg is not finite");
    return Pose3(RotationFromRollPitchYaw(rpy_rad.x(), rpy_rad.y(), rpy_rad.z()), p);
  }
  if (pose.rotation_row_major_size() != 9) {
    throw ConfigError("pose: rotation_row_major needs 9 numbers, got " +
                      std::to_string(pose.rotation_row_major_size()));
  }
  const Mat3 R = RowMajor(pose);
  if (!R.allFinite()) throw ConfigError("pose: rotation_row_major is not finite");
  const std::string problem = RotationProblem(R);
  if (!problem.empty()) throw ConfigError("pose: rotation_row_major: " + problem);
  // A matrix typed with a few decimals is only orthonormal to ~1e-6; project it so that
  // everything downstream works with an exact rotation.
  return Pose3(ProjectToSO3(R), p);
}

std::array<Pose3, kNumLegs> NominalTransducerPoses(const config::Robot& robot) {
  if (robot.leg_size() != kNumLegs) {
    throw ConfigError("robot: expected " + std::to_string(kNumLegs) + " legs, got " +
                      std::to_string(robot.leg_size()));
  }
  std::array<Pose3, kNumLegs> poses;
  for (int k = 0; k < kNumLegs; ++k) {
    const config::Leg& leg = robot.leg(k);
    if (leg.name() != kLegNames[k]) {
      throw ConfigError("robot.leg[" + std::to_string(k) + "]: expected leg '" +
                        std::string(kLegNames[k]) + "', got '" + leg.name() + "'");
    }
    if (!leg.has_x_b_ft()) {
      throw ConfigError("robot.leg[" + std::to_string(k) + "].x_b_ft is missing");
    }
    try {
      poses[k] = ToPose3(leg.x_b_ft());
    } catch (const ConfigError& e) {
      throw ConfigError("robot.leg[" + std::to_string(k) + "].x_b_ft: " + e.what());
    }
  }
  return poses;
}

Vec6 KWeights(const config::Calibrator& calibrator) {
  if (calibrator.k_weights_size() == 0) {
    Vec6 k;
    k << 1, 1, 1, 10, 10, 10;  // docs/method.md eq. 8: torques weighted 10x (N vs N*m scales)
    return k;
  }
  if (calibrator.k_weights_size() != 6) {
    throw ConfigError("calibrator.k_weights: needs 0 or 6 entries, got " +
                      std::to_string(calibrator.k_weights_size()));
  }
  Vec6 k;
  for (int i = 0; i < 6; ++i) {
    k[i] = calibrator.k_weights(i);
    if (!std::isfinite(k[i]) || !(k[i] > 0.0)) {
      throw ConfigError("calibrator.k_weights[" + std::to_string(i) + "]: must be > 0, got " +
                        FormatNumber(k[i]));
    }
  }
  return k;
}

std::string Sha256Hex(const std::string& bytes) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  if (EVP_Digest(bytes.data(), bytes.size(), digest, &length, EVP_sha256(), nullptr) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL EVP_Digest failed");
  }
  return ToHex(digest, length);
}

Sha256::Sha256() : ctx_(EVP_MD_CTX_new(), EVP_MD_CTX_free) {
  if (!ctx_ || EVP_DigestInit_ex(ctx_.get(), EVP_sha256(), nullptr) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL digest init failed");
  }
}

void Sha256::Update(const void* data, size_t size) {
  if (size > 0 && EVP_DigestUpdate(ctx_.get(), data, size) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL digest update failed");
  }
}

std::string Sha256::HexDigest() {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  if (EVP_DigestFinal_ex(ctx_.get(), digest, &length) != 1) {
    throw std::runtime_error("SHA-256: OpenSSL digest final failed");
  }
  return ToHex(digest, length);
}

std::string Sha256File(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw std::runtime_error("SHA-256: cannot open '" + path + "': " + std::strerror(errno));
  }
  // Streamed: logs can be far larger than memory would like.
  Sha256 sha;
  std::vector<char> buffer(1 << 16);
  while (in) {
    in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    const std::streamsize n = in.gcount();
    if (n > 0) sha.Update(buffer.data(), static_cast<size_t>(n));
  }
  if (in.bad()) {
    throw std::runtime_error("SHA-256: cannot read '" + path + "': " + std::strerror(errno));
  }
  return sha.HexDigest();
}

}  // namespace ftcal
