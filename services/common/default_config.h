// The default config (config/sim.pbtxt) compiled into every binary, so that a program run
// without --config works wherever it is: it never reads the source tree at run time.
#pragma once

#include <string>

#include "ftcal/config.h"

namespace ftcal {

// The text of config/sim.pbtxt as it was when this binary was built.
const char* DefaultConfigText();
// How error messages and logs name it.
inline const char* kDefaultConfigName = "embedded config/sim.pbtxt";

// `path`'s config, or the embedded default when `path` is empty. Throws ConfigError.
inline config::Config LoadConfigOrDefault(const std::string& path) {
  return path.empty() ? LoadConfigText(DefaultConfigText(), kDefaultConfigName)
                      : LoadConfigFile(path);
}

}  // namespace ftcal
