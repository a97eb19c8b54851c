#include "eval/average_precision.h"

#include <gtest/gtest.h>

#include <random>

namespace oxbow::eval {
namespace {

// The loop of the Oxford `compute_ap.cpp`, written out literally as an independent check.
double ReferenceAp(const std::vector<std::string>& ranked, const Relevance& rel) {
  double old_recall = 0, old_precision = 1, ap = 0;
  size_t intersect = 0, j = 0;
  for (const auto& id : ranked) {
    if (rel.junk.contains(id)) continue;
    if (rel.positives.contains(id)) ++intersect;
    const double recall = static_cast<double>(intersect) / rel.positives.size();
    const double precision = static_cast<double>(intersect) / (j + 1.0);
    ap += (recall - old_recall) * ((old_precision + precision) / 2.0);
    old_recall = recall;
    old_precision = precision;
    ++j;
  }
  return ap;
}

TEST(AveragePrecision, PerfectRankingIsOne) {
  const Relevance rel{{"a", "b"}, {}};
  const std::vector<std::string> ranked = {"a", "b", "x", "y"};
  EXPECT_DOUBLE_EQ(AveragePrecision(ranked, rel), 1.0);
}

TEST(AveragePrecision, HandComputedWithJunkSkipped) {
  // a at rank 0 (P 1 -> 1, R 0.5), x at 1, junk skipped, b at rank 2 (P 1/2 -> 2/3, R 1):
  // AP = 0.5 * (1 + 1) / 2 + 0.5 * (0.5 + 2/3) / 2 = 0.5 + 0.291666...
  const Relevance rel{{"a", "b"}, {"j"}};
  const std::vector<std::string> ranked = {"a", "x", "j", "b"};
  EXPECT_NEAR(AveragePrecision(ranked, rel), 0.5 + 0.5 * (0.5 + 2.0 / 3.0) / 2.0, 1e-12);
  // Junk at the top changes nothing.
  const std::vector<std::string> junk_first = {"j", "a", "x", "b"};
  EXPECT_NEAR(AveragePrecision(junk_first, rel), AveragePrecision(ranked, rel), 1e-12);
  // The same list without the junk entry treated as junk: b moves down one rank.
  const Relevance no_junk{{"a", "b"}, {}};
  EXPECT_NEAR(AveragePrecision(ranked, no_junk), 0.5 + 0.5 * (1.0 / 3.0 + 2.0 / 4.0) / 2.0, 1e-12);
}

TEST(AveragePrecision, MissingPositivesCostRecall) {
  // Only a is found, at rank 1: AP = (1/3) * (0/1 + 1/2) / 2.
  const Relevance rel{{"a", "b", "c"}, {}};
  const std::vector<std::string> ranked = {"x", "a"};
  EXPECT_NEAR(AveragePrecision(ranked, rel), (1.0 / 3.0) * 0.25, 1e-12);
  EXPECT_DOUBLE_EQ(AveragePrecision({}, rel), 0.0);
}

TEST(AveragePrecision, NoPositivesIsZeroAndDuplicatesCountOnce) {
  EXPECT_DOUBLE_EQ(AveragePrecision(std::vector<std::string>{"a"}, Relevance{}), 0.0);
  const Relevance rel{{"a", "b"}, {}};
  const std::vector<std::string> duplicated = {"a", "a", "b"};
  EXPECT_DOUBLE_EQ(AveragePrecision(duplicated, rel), 1.0);
}

TEST(AveragePrecision, MatchesReferenceLoopOnRandomRankings) {
  std::mt19937 rng(7);
  for (int trial = 0; trial < 200; ++trial) {
    const int n = 1 + static_cast<int>(rng() % 60);
    std::vector<std::string> ranked;
    ranked.reserve(static_cast<size_t>(n));
    for (int i = 0; i < n; ++i) ranked.push_back("img" + std::to_string(i));
    std::shuffle(ranked.begin(), ranked.end(), rng);
    Relevance rel;
    for (int i = 0; i < n + 5; ++i) {  // some positives are never retrieved
      const unsigned r = rng() % 4;
      if (r == 0) rel.positives.insert("img" + std::to_string(i));
      if (r == 1) rel.junk.insert("img" + std::to_string(i));
    }
    if (rel.positives.empty()) rel.positives.insert("img0");
    rel.junk.erase("img0");
    EXPECT_NEAR(AveragePrecision(ranked, rel), ReferenceAp(ranked, rel), 1e-9) << "trial " << trial;
  }
}

TEST(NonInterpolatedAveragePrecision, HandComputed) {
  // The query q is junk (left out of its own ranking). Positives a, b, c; found at ranks 0, 2 (junk
  // removed); c never returned: AP = (1/1 + 2/3 + 0) / 3.
  const Relevance rel{{"a", "b", "c"}, {"q"}};
  const std::vector<std::string> ranked = {"q", "a", "x", "b", "y"};
  EXPECT_NEAR(NonInterpolatedAveragePrecision(ranked, rel), (1.0 + 2.0 / 3.0) / 3.0, 1e-12);
  // The same ranking under the Oxford trapezoid: (1/3) * [(1 + 1) / 2 + (1/2 + 2/3) / 2], lower.
  EXPECT_NEAR(AveragePrecision(ranked, rel), (1.0 + (0.5 + 2.0 / 3.0) / 2.0) / 3.0, 1e-12);
  EXPECT_DOUBLE_EQ(AveragePrecision(ranked, rel, ApDefinition::kNonInterpolated),
                   NonInterpolatedAveragePrecision(ranked, rel));
  EXPECT_DOUBLE_EQ(AveragePrecision(ranked, rel, ApDefinition::kOxfordTrapezoid), AveragePrecision(ranked, rel));
  // One positive at rank 3 (1-based 4): AP = 1/4 (the trapezoid gives (0 + 1/4) / 2).
  const Relevance one{{"p"}, {}};
  const std::vector<std::string> late = {"x", "y", "z", "p"};
  EXPECT_DOUBLE_EQ(NonInterpolatedAveragePrecision(late, one), 0.25);
  EXPECT_DOUBLE_EQ(AveragePrecision(late, one), 0.125);
  // Perfect, empty and duplicated rankings.
  EXPECT_DOUBLE_EQ(NonInterpolatedAveragePrecision(std::vector<std::string>{"b", "a", "c"}, rel), 1.0);
  EXPECT_DOUBLE_EQ(NonInterpolatedAveragePrecision({}, rel), 0.0);
  EXPECT_DOUBLE_EQ(NonInterpolatedAveragePrecision(std::vector<std::string>{"a"}, Relevance{}), 0.0);
  EXPECT_NEAR(NonInterpolatedAveragePrecision(std::vector<std::string>{"a", "a", "x", "b"}, rel),
              (1.0 + 2.0 / 3.0) / 3.0, 1e-12);
}

TEST(PositivesInTopK, RecallAtOneAndTopFour) {
  // Junk (the query itself) is skipped before counting: the first four results are a, x, b, y.
  const Relevance rel{{"a", "b", "c", "d", "e"}, {"q"}};
  const std::vector<std::string> ranked = {"q", "a", "x", "b", "y", "c", "d"};
  EXPECT_EQ(PositivesInTopK(ranked, rel, 1), 1);
  EXPECT_EQ(PositivesInTopK(ranked, rel, 4), 2);
  EXPECT_EQ(PositivesInTopK(ranked, rel, 100), 4);
  const std::vector<std::string> miss_first = {"x", "a", "b", "c", "d"};
  EXPECT_EQ(PositivesInTopK(miss_first, rel, 1), 0);
  EXPECT_EQ(PositivesInTopK(miss_first, rel, 4), 3);
  EXPECT_EQ(PositivesInTopK(miss_first, rel, 0), 0);
}

TEST(PrecisionAtK, RevisitedDefinition) {
  // Positives at ranks 1, 3 (1-based, junk removed); the last positive is at rank 3, so kq = min(k, 3).
  const Relevance rel{{"a", "b"}, {"j"}};
  const std::vector<std::string> ranked = {"a", "j", "x", "b", "y"};
  EXPECT_DOUBLE_EQ(PrecisionAtK(ranked, rel, 1), 1.0);
  EXPECT_DOUBLE_EQ(PrecisionAtK(ranked, rel, 2), 0.5);
  EXPECT_DOUBLE_EQ(PrecisionAtK(ranked, rel, 5), 2.0 / 3.0);
  EXPECT_DOUBLE_EQ(PrecisionAtK(std::vector<std::string>{"x"}, rel, 5), 0.0);
}

TEST(PrecisionRecallCurve, StartsAtPrecisionOneAndEndsAtFoundRecall) {
  const Relevance rel{{"a", "b", "c", "d"}, {}};
  const std::vector<std::string> ranked = {"a", "x", "b"};
  const auto curve = PrecisionRecallCurve(ranked, rel);
  ASSERT_EQ(curve.size(), 3u);
  EXPECT_DOUBLE_EQ(curve[0].precision, 1.0);
  EXPECT_DOUBLE_EQ(curve[1].recall, 0.25);
  EXPECT_DOUBLE_EQ(curve[2].recall, 0.5);
  EXPECT_DOUBLE_EQ(curve[2].precision, 2.0 / 3.0);
}

}  // namespace
}  // namespace oxbow::eval
