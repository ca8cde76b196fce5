// Loading and validating configuration files (libcal/proto/config.proto, text format).
//
// A bad file is refused with the file, line, column and field named: parse errors come from
// protobuf's TextFormat parser (unknown fields are errors), and validation (ranges, rotations,
// leg names and order, duplicates) uses the parser's location tree to point at the offending
// field. Every error is a ConfigError whose what() reads
//   "<file>:<line>:<column>: <field.path>: <what is wrong>"
// (line and column 1-based; a missing field points at its enclosing message).
#pragma once

#include <array>
#include <cstddef>
#include <memory>
#include <stdexcept>
#include <string>

#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "proto/config.pb.h"

// OpenSSL's digest context (EVP_MD_CTX), kept out of this header.
struct evp_md_ctx_st;

namespace ftcal {

class ConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Parses and validates; throws ConfigError.
config::Config LoadConfigFile(const std::string& path);
// Same for text already in memory; `source_name` stands for the file name in messages.
config::Config LoadConfigText(const std::string& text, const std::string& source_name);

// Validated conversions.
Pose3 ToPose3(const config::Pose& pose);
std::array<Pose3, kNumLegs> NominalTransducerPoses(const config::Robot& robot);
// K-norm weights of eq. 8 (the configured ones, or the default 1,1,1,10,10,10).
Vec6 KWeights(const config::Calibrator& calibrator);

// Hex SHA-256 of bytes / of a file's contents (provenance of configs, logs and calibrations).
std::string Sha256Hex(const std::string& bytes);
std::string Sha256File(const std::string& path);

// SHA-256 of bytes given piece by piece (OpenSSL's digest): a file read for another purpose is
// hashed on the way instead of read a second time. Throws std::runtime_error when OpenSSL fails.
class Sha256 {
 public:
  Sha256();
  void Update(const void* data, size_t size);
  // Lowercase hex, as Sha256Hex and Sha256File; ends the digest (call once).
  std::string HexDigest();

 private:
  std::unique_ptr<evp_md_ctx_st, void (*)(evp_md_ctx_st*)> ctx_;
};

}  // namespace ftcal
