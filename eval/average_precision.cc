#include "eval/average_precision.h"

#include <algorithm>

namespace oxbow::eval {

std::vector<int> PositiveRanks(std::span<const std::string> ranked, const Relevance& relevance) {
  std::vector<int> ranks;
  std::unordered_set<std::string> seen;
  int rank = 0;
  for (const std::string& id : ranked) {
    if (!seen.insert(id).second) continue;
    if (relevance.junk.contains(id)) continue;
    if (relevance.positives.contains(id)) ranks.push_back(rank);
    ++rank;
  }
  return ranks;
}

double AveragePrecision(std::span<const std::string> ranked, const Relevance& relevance) {
  const size_t num_positives = relevance.positives.size();
  if (num_positives == 0) return 0.0;
  // Equivalent to the reference loop: between consecutive positives recall is flat, so only the steps at
  // positives add area; the step at the positive found at rank r (0-based) after j earlier positives
  // goes from precision j / r (1 when r == 0) to (j + 1) / (r + 1).
  double ap = 0.0;
  const double recall_step = 1.0 / static_cast<double>(num_positives);
  const std::vector<int> ranks = PositiveRanks(ranked, relevance);
  for (size_t j = 0; j < ranks.size(); ++j) {
    const double r = ranks[j];
    const double precision_before = ranks[j] == 0 ? 1.0 : static_cast<double>(j) / r;
    const double precision_after = static_cast<double>(j + 1) / (r + 1.0);
    ap += (precision_before + precision_after) * recall_step / 2.0;
  }
  return ap;
}

double NonInterpolatedAveragePrecision(std::span<const std::string> ranked, const Relevance& relevance) {
  if (relevance.positives.empty()) return 0.0;
  const std::vector<int> ranks = PositiveRanks(ranked, relevance);
  double sum = 0.0;
  for (size_t j = 0; j < ranks.size(); ++j) sum += static_cast<double>(j + 1) / (ranks[j] + 1.0);
  return sum / static_cast<double>(relevance.positives.size());
}

double AveragePrecision(std::span<const std::string> ranked, const Relevance& relevance, ApDefinition definition) {
  return definition == ApDefinition::kNonInterpolated ? NonInterpolatedAveragePrecision(ranked, relevance)
                                                      : AveragePrecision(ranked, relevance);
}

const char* ApDefinitionName(ApDefinition definition) {
  return definition == ApDefinition::kNonInterpolated ? "non-interpolated" : "Oxford trapezoid";
}

int PositivesInTopK(std::span<const std::string> ranked, const Relevance& relevance, int k) {
  const std::vector<int> ranks = PositiveRanks(ranked, relevance);
  return static_cast<int>(std::count_if(ranks.begin(), ranks.end(), [&](int r) { return r < k; }));
}

double PrecisionAtK(std::span<const std::string> ranked, const Relevance& relevance, int k) {
  const std::vector<int> ranks = PositiveRanks(ranked, relevance);
  if (ranks.empty() || k <= 0) return 0.0;
  const int kq = std::min(k, ranks.back() + 1);
  const auto hits = std::count_if(ranks.begin(), ranks.end(), [&](int r) { return r + 1 <= kq; });
  return static_cast<double>(hits) / kq;
}

std::vector<PrPoint> PrecisionRecallCurve(std::span<const std::string> ranked, const Relevance& relevance) {
  std::vector<PrPoint> curve = {{0.0, 1.0}};
  const size_t num_positives = relevance.positives.size();
  if (num_positives == 0) return curve;
  const std::vector<int> ranks = PositiveRanks(ranked, relevance);
  for (size_t j = 0; j < ranks.size(); ++j) {
    curve.push_back({static_cast<double>(j + 1) / num_positives, static_cast<double>(j + 1) / (ranks[j] + 1)});
  }
  return curve;
}

}  // namespace oxbow::eval
