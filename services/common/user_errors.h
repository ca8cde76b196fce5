// What a user reads when an exception reaches a program's top level, a handler's guard or a
// periodic task. ftcal's own exceptions carry texts written for the user (what was wrong and
// where: ConfigError, BadInput, the refusals); the standard library's texts for its own
// failures do not ("std::bad_alloc", "basic_string::_M_replace_aux", "vector::_M_range_check:
// __n (which is 7) >= this->size() (which is 6)", "stoi"), and neither do the logic errors
// that mark a bug in ftcal. Those are named as what they are, out of memory or a bug, with
// what the program was doing; the library's text goes to the debug log only.
#pragma once

#include <exception>
#include <string>
#include <string_view>

namespace ftcal {

// True for out of memory, for a logic error (a bug: an index out of range, a precondition
// broken) and for the standard library's own texts; false for the exceptions that carry a
// message meant for the user (runtime errors, std::invalid_argument from ftcal's checks).
bool IsInternalError(const std::exception& e);

// e.what() when it is meant for the user; otherwise "out of memory while <doing>" or "an
// internal error while <doing> (a bug in ftcal: ...)". `doing` is a phrase such as "reading
// the logs" or "handling FT_HL".
std::string UserText(const std::exception& e, std::string_view doing);

// kExitInternal for an internal error, else `otherwise` (what the caller's condition means).
int ExitCodeFor(const std::exception& e, int otherwise);

}  // namespace ftcal
