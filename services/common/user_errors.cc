#include "common/user_errors.h"

#include <functional>
#include <future>
#include <ios>
#include <memory>
#include <new>
#include <optional>
#include <regex>
#include <stdexcept>
#include <typeinfo>
#include <variant>

#include <spdlog/spdlog.h>

#include "common/exit_codes.h"

namespace ftcal {
namespace {

// The standard library's bare texts for a failed number conversion ("stoi", "stod"): the
// caller should have checked the text and named the field; it did not, which is a bug.
bool IsLibraryConversionText(std::string_view what) {
  return what.size() <= 5 && what.rfind("sto", 0) == 0;
}

}  // namespace

bool IsInternalError(const std::exception& e) {
  if (dynamic_cast<const std::bad_alloc*>(&e) != nullptr) return true;
  if (const auto* invalid = dynamic_cast<const std::invalid_argument*>(&e)) {
    return IsLibraryConversionText(invalid->what());
  }
  // Every other logic error (std::out_of_range included: stoi's "stoi" for a too-large
  // number as much as vector::at's range check) is a bug.
  if (dynamic_cast<const std::logic_error*>(&e) != nullptr) return true;
  return dynamic_cast<const std::bad_cast*>(&e) != nullptr ||
         dynamic_cast<const std::bad_typeid*>(&e) != nullptr ||
         dynamic_cast<const std::bad_function_call*>(&e) != nullptr ||
         dynamic_cast<const std::bad_optional_access*>(&e) != nullptr ||
         dynamic_cast<const std::bad_variant_access*>(&e) != nullptr ||
         dynamic_cast<const std::bad_weak_ptr*>(&e) != nullptr ||
         dynamic_cast<const std::bad_exception*>(&e) != nullptr ||
         dynamic_cast<const std::regex_error*>(&e) != nullptr ||
         dynamic_cast<const std::ios_base::failure*>(&e) != nullptr;
}

std::string UserText(const std::exception& e, std::string_view doing) {
  if (!IsInternalError(e)) return e.what();
  spdlog::debug("internal error while {}: {} ({})", doing, e.what(), typeid(e).name());
  if (dynamic_cast<const std::bad_alloc*>(&e) != nullptr) {
    return "out of memory while " + std::string(doing);
  }
  return "an internal error while " + std::string(doing) +
         " (a bug in ftcal, not in its input: please report it with the command line and the "
         "config; --log-level debug shows the detail)";
}

int ExitCodeFor(const std::exception& e, int otherwise) {
  return IsInternalError(e) ? kExitInternal : otherwise;
}

}  // namespace ftcal
