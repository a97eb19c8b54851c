#include "eval/report.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

namespace oxbow::eval {
namespace {

namespace fs = std::filesystem;

RunResult MakeRun(const std::string& label, uint64_t words, const std::vector<std::vector<std::string>>& rankings,
                  const std::vector<EvalQuery>& queries) {
  RunResult run;
  run.protocol = "toy";
  run.label = label;
  run.settings = {{"features", "sift"}, {"rerank", "0"}, {"qe", "off"}, {"words", std::to_string(words)}};
  run.vocabulary_words = words;
  for (size_t i = 0; i < queries.size(); ++i) {
    QueryOutcome q = ScoreRanking(queries[i], rankings[i]);
    q.latency_ms = 10.0 * (i + 1);
    q.stage_ms = {{"extract", 5.0}, {"score", 1.0}};
    run.queries.push_back(q);
  }
  Summarise(&run);
  return run;
}

TEST(Report, SummariseAndWriteMarkdownJsonPlots) {
  const std::vector<EvalQuery> queries = {{"q1", "a", std::nullopt, {{"a", "b"}, {}}},
                                          {"q2", "c", std::nullopt, {{"c", "d"}, {"x"}}}};
  const RunResult perfect = MakeRun("perfect", 1000, {{"a", "b", "x"}, {"c", "d"}}, queries);
  EXPECT_DOUBLE_EQ(perfect.map, 1.0);
  EXPECT_DOUBLE_EQ(perfect.query_p50_ms, 15.0);
  EXPECT_DOUBLE_EQ(perfect.extract_p50_ms, 5.0);
  const RunResult worse = MakeRun("worse", 10000, {{"x", "a", "b"}, {"c", "y", "d"}}, queries);
  EXPECT_LT(worse.map, 1.0);
  EXPECT_GT(worse.map, 0.0);

  const fs::path dir = fs::temp_directory_path() / "oxbow_report_test";
  fs::remove_all(dir);
  ASSERT_TRUE(WriteReport(dir.string(), {perfect, worse}, "oxbow eval --test"));
  std::ifstream json_in(dir / "results.json");
  const auto json = nlohmann::json::parse(json_in);
  ASSERT_EQ(json["runs"].size(), 2u);
  EXPECT_DOUBLE_EQ(json["runs"][0]["map"].get<double>(), 1.0);
  EXPECT_NEAR(json["runs"][1]["map"].get<double>(), worse.map, 1e-12);
  std::ifstream md_in(dir / "report.md");
  const std::string md((std::istreambuf_iterator<char>(md_in)), std::istreambuf_iterator<char>());
  EXPECT_NE(md.find("| toy | perfect | **1.000**"), std::string::npos) << md;
  EXPECT_NE(md.find("words = 10000"), std::string::npos);
  for (const char* plot : {"plots/ap_per_query.png", "plots/map_vs_vocabulary.png"}) {
    const cv::Mat img = cv::imread((dir / plot).string());
    EXPECT_FALSE(img.empty()) << plot;
  }
  fs::remove_all(dir);
}

TEST(Report, PercentileInterpolates) {
  EXPECT_DOUBLE_EQ(Percentile({}, 50), 0.0);
  EXPECT_DOUBLE_EQ(Percentile({3, 1, 2}, 50), 2.0);
  EXPECT_DOUBLE_EQ(Percentile({1, 2, 3, 4}, 50), 2.5);
  EXPECT_DOUBLE_EQ(Percentile({1, 2, 3, 4}, 100), 4.0);
}

}  // namespace
}  // namespace oxbow::eval
