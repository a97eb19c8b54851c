// The main() of every GoogleTest executable (cmake/OxbowHelpers.cmake, tests/CMakeLists.txt): it makes
// skipped tests visible to ctest instead of letting them count as passed.
//  - Every test that ran was skipped: exit code kAllSkipped, which ctest (SKIP_RETURN_CODE) reports as
//    "Skipped" / "Not Run" rather than "Passed".
//  - Some were skipped: a line "SKIPPED n of m tests" and one line per test with its reason, on stderr
//    (ctest -V or --output-on-failure shows it; the gtest summary says the same).
//  - No test ran (a filter that matches nothing): a failure, so a misspelt filter cannot pass.
#include <gtest/gtest.h>

#include <cstdio>
#include <string>
#include <vector>

namespace {

constexpr int kAllSkipped = 77;  // also in OXBOW_GTEST_SKIP_CODE (cmake/OxbowHelpers.cmake)

class SkipCollector : public ::testing::EmptyTestEventListener {
 public:
  void OnTestEnd(const ::testing::TestInfo& info) override {
    const ::testing::TestResult& result = *info.result();
    if (!result.Skipped()) return;
    std::string reason;
    for (int i = 0; i < result.total_part_count(); ++i) {
      const ::testing::TestPartResult& part = result.GetTestPartResult(i);
      if (part.skipped() && part.message() != nullptr) reason += part.message();
    }
    skipped_.push_back(std::string(info.test_suite_name()) + "." + info.name() + ": " +
                       (reason.empty() ? "(no reason given)" : reason));
  }
  const std::vector<std::string>& skipped() const { return skipped_; }

 private:
  std::vector<std::string> skipped_;
};

}  // namespace

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  auto* collector = new SkipCollector;  // owned by the listener list
  ::testing::UnitTest::GetInstance()->listeners().Append(collector);
  const int status = RUN_ALL_TESTS();
  const ::testing::UnitTest& unit = *::testing::UnitTest::GetInstance();
  if (status != 0) return status;
  if (GTEST_FLAG_GET(list_tests)) return 0;
  const int ran = unit.test_to_run_count();
  if (ran == 0) {
    std::fprintf(stderr, "no test ran: the filter matches no test of this binary\n");
    return 1;
  }
  const auto& skipped = collector->skipped();
  if (skipped.empty()) return 0;
  std::fprintf(stderr, "SKIPPED %zu of %d tests:\n", skipped.size(), ran);
  for (const std::string& line : skipped) std::fprintf(stderr, "  SKIPPED %s\n", line.c_str());
  return static_cast<int>(skipped.size()) == ran ? kAllSkipped : 0;
}
