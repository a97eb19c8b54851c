#include "eval/report.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <unistd.h>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "tests/support/temp_dir.h"

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
    QueryOutcome q = ScoreRanking(queries[i], rankings[i], ApDefinition::kOxfordTrapezoid);
    q.latency_ms = 10.0 * (i + 1);
    q.stage_ms = {{"extract", 5.0}, {"score", 1.0}};
    run.queries.push_back(q);
  }
  Summarise(&run);
  return run;
}

TEST(Report, SummariseAndWriteMarkdownJsonPlots) {
  const std::vector<EvalQuery> queries = {{"q1", "a", std::nullopt, {{"a", "b"}, {}}, ""},
                                          {"q2", "c", std::nullopt, {{"c", "d"}, {"x"}}, ""}};
  const RunResult perfect = MakeRun("perfect", 1000, {{"a", "b", "x"}, {"c", "d"}}, queries);
  EXPECT_DOUBLE_EQ(perfect.map, 1.0);
  EXPECT_DOUBLE_EQ(perfect.query_p50_ms, 15.0);
  EXPECT_DOUBLE_EQ(perfect.extract_p50_ms, 5.0);
  const RunResult worse = MakeRun("worse", 10000, {{"x", "a", "b"}, {"c", "y", "d"}}, queries);
  EXPECT_LT(worse.map, 1.0);
  EXPECT_GT(worse.map, 0.0);

  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  ASSERT_TRUE(WriteReport(dir.string(), {perfect, worse}, "oxbow eval --test"));
  std::ifstream json_in(dir / "results.json");
  const auto json = nlohmann::json::parse(json_in);
  ASSERT_EQ(json["runs"].size(), 2u);
  EXPECT_DOUBLE_EQ(json["runs"][0]["map"].get<double>(), 1.0);
  EXPECT_NEAR(json["runs"][1]["map"].get<double>(), worse.map, 1e-12);
  const std::string md = oxbow::testing::FileBytes(dir / "report.md");
  EXPECT_NE(md.find("| toy | perfect | **1.000**"), std::string::npos) << md;
  EXPECT_NE(md.find("words = 10000"), std::string::npos);
  for (const char* plot : {"plots/ap_per_query.png", "plots/map_vs_vocabulary.png"}) {
    const cv::Mat img = cv::imread((dir / plot).string());
    EXPECT_FALSE(img.empty()) << plot;
  }
}

TEST(Report, GroupsMetricsRecallTopFourAndApPerGroup) {
  // Two groups: {a1, a2, a3} and {b1, b2}; each query is junk in its own ranking; d is a distractor.
  auto query = [](const std::string& id, const std::string& group, std::unordered_set<std::string> positives) {
    return EvalQuery{id, id, std::nullopt, {std::move(positives), {id}}, group};
  };
  const std::vector<EvalQuery> queries = {query("a1", "a", {"a2", "a3"}), query("a2", "a", {"a1", "a3"}),
                                          query("b1", "b", {"b2"})};
  const std::vector<std::vector<std::string>> rankings = {
      {"a1", "a2", "a3", "d", "b1"},  // perfect: AP 1, top-4 2 of 2, recall@1 1
      {"a2", "d", "a1", "b1", "b2", "a3"},  // positives at ranks 2 and 5 (1-based): AP (1/2 + 2/5) / 2 = 0.45
      {"d", "a1", "b1", "a2", "a3", "b2"}};  // b2 at rank 5: AP 1/5, outside the top 4
  RunResult run;
  run.protocol = "groups";
  run.label = "toy";
  run.ap_definition = ApDefinition::kNonInterpolated;
  run.distractors = 1;
  for (size_t i = 0; i < queries.size(); ++i) {
    run.queries.push_back(ScoreRanking(queries[i], rankings[i], ApDefinition::kNonInterpolated));
  }
  EXPECT_EQ(run.queries[1].top4_hits, 1);
  EXPECT_EQ(run.queries[1].top4_ceiling, 2);
  EXPECT_EQ(run.queries[2].top4_ceiling, 1);
  Summarise(&run);
  EXPECT_NEAR(run.map, (1.0 + 0.45 + 0.2) / 3.0, 1e-12);
  EXPECT_NEAR(run.recall_at_1, 1.0 / 3.0, 1e-12);
  EXPECT_NEAR(run.top4, (2.0 + 1.0 + 0.0) / 3.0, 1e-12);
  EXPECT_NEAR(run.top4_ceiling, (2.0 + 2.0 + 1.0) / 3.0, 1e-12);
  ASSERT_EQ(run.group_ap.size(), 2u);
  EXPECT_NEAR(run.group_ap.at("a"), 0.725, 1e-12);
  EXPECT_NEAR(run.group_ap.at("b"), 0.2, 1e-12);
  // The same ranking under the Oxford trapezoid scores lower: the definition is the protocol's choice.
  EXPECT_LT(ScoreRanking(queries[1], rankings[1], ApDefinition::kOxfordTrapezoid).ap, run.queries[1].ap);

  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  ASSERT_TRUE(WriteReport(dir.string(), {run}, "oxbow eval --protocol groups"));
  const std::string md = oxbow::testing::FileBytes(dir / "report.md");
  EXPECT_NE(md.find("| groups | toy | **0.550** | non-interpolated | 0.333 | 1.00 (1.67) |"), std::string::npos) << md;
  EXPECT_NE(md.find("| a | 2 | 0.725 |"), std::string::npos) << md;
  EXPECT_NE(md.find("| b | 1 | 0.200 |"), std::string::npos) << md;
  std::ifstream json_in(dir / "results.json");
  const auto json = nlohmann::json::parse(json_in);
  EXPECT_EQ(json["runs"][0]["ap_definition"], "non-interpolated");
  EXPECT_EQ(json["runs"][0]["distractors"], 1);
  EXPECT_NEAR(json["runs"][0]["group_ap"]["b"].get<double>(), 0.2, 1e-12);
}

TEST(Report, PercentileInterpolates) {
  EXPECT_DOUBLE_EQ(Percentile({}, 50), 0.0);
  EXPECT_DOUBLE_EQ(Percentile({3, 1, 2}, 50), 2.0);
  EXPECT_DOUBLE_EQ(Percentile({1, 2, 3, 4}, 50), 2.5);
  EXPECT_DOUBLE_EQ(Percentile({1, 2, 3, 4}, 100), 4.0);
}

}  // namespace
}  // namespace oxbow::eval
