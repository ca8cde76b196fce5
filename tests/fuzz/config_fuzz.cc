// libFuzzer target: arbitrary bytes as a config (libcal's LoadConfigText: protobuf's text
// parser, then ftcal's own validation, then the derived geometry). Invariants beyond "no
// crash": the only exception a user can see is ConfigError (any other would surface as an
// internal text such as basic_string::_M_replace, or be a bug: a std::logic_error is thrown
// for a field the validator names that the schema lacks); a config that loads prints to text
// that loads again to the same message (what `ftcal-launch` does when it copies a config into
// a host's run dir).
#include <cstdlib>
#include <exception>
#include <string>

#include <google/protobuf/text_format.h>
#include <google/protobuf/util/message_differencer.h>

#include "ftcal/config.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  ftcal::config::Config config;
  try {
    config = ftcal::LoadConfigText(text, "fuzz.pbtxt");
  } catch (const ftcal::ConfigError& e) {
    if (std::string(e.what()).empty()) std::abort();  // a refusal must say what was wrong
    return 0;
  } catch (...) {
    std::abort();
  }
  try {
    ftcal::NominalTransducerPoses(config.robot());
    ftcal::KWeights(config.calibrator());
  } catch (const ftcal::ConfigError&) {
    std::abort();  // validation passed a config the geometry then refuses
  } catch (...) {
    std::abort();
  }
  std::string printed;
  if (!google::protobuf::TextFormat::PrintToString(config, &printed)) std::abort();
  ftcal::config::Config again;
  try {
    again = ftcal::LoadConfigText(printed, "printed.pbtxt");
  } catch (...) {
    std::abort();
  }
  if (!google::protobuf::util::MessageDifferencer::Equals(config, again)) std::abort();
  return 0;
}
