// Text shared by the ftcal-status boards, so that the per-process table and the launcher's
// group table look alike and treat heartbeat text alike.
#pragma once

#include <string>
#include <vector>

namespace ftcal {

// A heartbeat is untrusted input: keep its text from moving the cursor or breaking the table.
std::string Printable(const std::string& text);

// `cells` as lines of left-aligned columns two spaces apart, without trailing blanks; the first
// line sets the number of columns.
std::string AlignColumns(const std::vector<std::vector<std::string>>& cells);

}  // namespace ftcal
