// Average precision and precision@k for instance retrieval, exactly as the reference evaluation code
// computes them, so that our numbers compare with published ones.
//
// Oxford/Paris (Philbin et al. 2007, the `compute_ap.cpp` shipped with the ground truth): walk the ranked
// list; an image on the junk list is skipped without advancing the rank; at every non-junk rank r
// (0-based, junk removed) recall and precision are updated and the area under the precision-recall curve
// is accumulated with the trapezoid rule, starting from precision 1 at recall 0:
//   AP = sum_r (recall_r - recall_{r-1}) * (precision_{r-1} + precision_r) / 2.
// Positives never returned contribute nothing (their recall is never reached). With no positives AP is
// undefined: the reference divides by zero; we return 0 and callers should not include such queries.
//
// Groups protocol (groups_dev/groups_hard READMEs, UKBench/Holidays style): non-interpolated AP, the mean
// over all positives of the precision at the rank where each is found (a positive never returned adds 0):
//   AP = (1 / |positives|) * sum_j (j + 1) / (r_j + 1),   r_j = 0-based rank of the j-th positive found.
// The trapezoid averages each positive's precision with the lower one just before it, so it is never
// above this AP (equal only when no negative precedes a positive): the two are not comparable.
//
// Revisited Oxford/Paris (Radenovic et al. 2018, `compute_map` in revisitop): the same AP, and
// mP@k where for each query kq = min(k, rank of the last retrieved positive) and P = |positives in the
// first kq| / kq (ranks after junk removal, 1-based); queries without positives are skipped.
#pragma once

#include <span>
#include <string>
#include <unordered_set>
#include <vector>

namespace oxbow::eval {

struct Relevance {
  std::unordered_set<std::string> positives;  // good + ok (Oxford), or the protocol's positives
  std::unordered_set<std::string> junk;       // ignored: neither helps nor hurts
};

// Which AP a protocol reports (see above).
enum class ApDefinition { kOxfordTrapezoid, kNonInterpolated };
const char* ApDefinitionName(ApDefinition definition);  // "Oxford trapezoid" | "non-interpolated"

// AP of one ranked list of image ids (best first). Duplicated ids count once (later copies are skipped).
double AveragePrecision(std::span<const std::string> ranked, const Relevance& relevance);
double NonInterpolatedAveragePrecision(std::span<const std::string> ranked, const Relevance& relevance);
double AveragePrecision(std::span<const std::string> ranked, const Relevance& relevance, ApDefinition definition);

// Positives among the first k results (junk and duplicates removed): k = 1 gives recall@1 (0 or 1),
// k = 4 the UKBench-style top-4 score.
int PositivesInTopK(std::span<const std::string> ranked, const Relevance& relevance, int k);

// Positions (0-based, junk removed, duplicates removed) at which positives appear in the ranked list.
std::vector<int> PositiveRanks(std::span<const std::string> ranked, const Relevance& relevance);

// Revisited mP@k for one query (see above); 0 when no positive is retrieved.
double PrecisionAtK(std::span<const std::string> ranked, const Relevance& relevance, int k);

// Precision/recall points of the ranked list (junk removed), starting at (recall 0, precision 1); for plots.
struct PrPoint {
  double recall = 0;
  double precision = 1;
};
std::vector<PrPoint> PrecisionRecallCurve(std::span<const std::string> ranked, const Relevance& relevance);

}  // namespace oxbow::eval
