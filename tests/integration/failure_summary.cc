// Every failed assertion again, one short line each, as the last thing a failed test prints.
// The multi-process tests print pages of figures, tables and log tails; CI keeps only the head
// and the tail of a run's output, so without this the reason for a failure can fall in the part
// that was cut. Linked into every test that uses ftcal_child_process (an object library).
#include <algorithm>
#include <iostream>
#include <string>

#include <gtest/gtest.h>

namespace ftcal::testing {
namespace {

class FailureSummary : public ::testing::EmptyTestEventListener {
  void OnTestEnd(const ::testing::TestInfo& info) override {
    const ::testing::TestResult& result = *info.result();
    if (!result.Failed()) return;
    std::cout << "FAILURES of " << info.test_suite_name() << "." << info.name() << ":\n";
    for (int i = 0; i < result.total_part_count(); ++i) {
      const ::testing::TestPartResult& part = result.GetTestPartResult(i);
      if (!part.failed()) continue;
      std::string message = part.message();
      std::replace(message.begin(), message.end(), '\n', ' ');
      constexpr std::size_t kMaxChars = 400;
      if (message.size() > kMaxChars) message = message.substr(0, kMaxChars) + " ...";
      std::cout << "  " << (part.file_name() ? part.file_name() : "?") << ":" << part.line_number()
                << ": " << message << "\n";
    }
    std::cout.flush();
  }
};

// Before main (gtest_main's): the listener list outlives InitGoogleTest, which only replaces
// the default printer.
const bool kRegistered = [] {
  ::testing::UnitTest::GetInstance()->listeners().Append(new FailureSummary);
  return true;
}();

}  // namespace
}  // namespace ftcal::testing
