// Evaluation runs and their reports: a Markdown summary, a JSON file with every number (for comparing
// runs), and PNG plots (precision-recall per query, AP per query, mAP vs vocabulary size).
#pragma once

#include <map>
#include <string>
#include <vector>

#include "eval/average_precision.h"
#include "eval/ground_truth.h"
#include "sift/base/error.h"

namespace oxbow::eval {

// One query's outcome in one configuration.
struct QueryOutcome {
  std::string name;
  double ap = 0;
  std::vector<double> precision_at;       // mP@1, @5, @10 (revisited definition)
  std::vector<PrPoint> pr_curve;
  double latency_ms = 0;                  // client-observed wall time of the search request
  std::map<std::string, double> stage_ms; // server-reported stage timings
  std::vector<std::string> top;           // first ids of the ranking (for the report)
  std::string group;                      // groups protocol: the query's group
  int top1_hits = 0;                      // positives among the first 1 / 4 results
  int top4_hits = 0;
  int top4_ceiling = 0;                   // min(4, positives): the best top4_hits possible
};

// One configuration evaluated on one protocol.
struct RunResult {
  std::string protocol;                          // e.g. "paris6k-restricted"
  std::string label;                             // short configuration label, e.g. "rootsift 20k +rerank"
  std::map<std::string, std::string> settings;   // every setting that shaped the numbers
  ApDefinition ap_definition = ApDefinition::kOxfordTrapezoid;
  double map = 0;                                // mean AP over queries
  std::vector<double> mean_precision_at;         // mP@1, @5, @10
  double recall_at_1 = 0;                        // share of queries whose first result is a positive
  double top4 = 0, top4_ceiling = 0;             // mean positives in the first 4 results, and its best value
  std::map<std::string, double> group_ap;        // groups protocol: mean AP of each group's queries
  size_t distractors = 0;                        // database images that are never positives (groups)
  std::vector<QueryOutcome> queries;
  double build_vocab_s = 0, build_index_s = 0;   // wall time (0 when reused from the work folder)
  double query_p50_ms = 0, query_p95_ms = 0;     // per-query latency
  double extract_p50_ms = 0;                     // server-reported decode + extract, p50
  double search_p50_ms = 0;                      // server-reported quantise + score + verify + qe, p50
  uint64_t index_images = 0, index_features = 0; // index size
  double index_bytes_per_feature = 0;
  uint64_t vocabulary_words = 0;
};

// Fills map, mean_precision_at, recall@1, top-4, per-group AP and the latency percentiles from the
// per-query outcomes.
void Summarise(RunResult* run);

// Scores a ranking against a query's relevance (AP as `definition`, mP@1/5/10, recall@1, top-4, PR
// curve, top 10).
QueryOutcome ScoreRanking(const EvalQuery& query, const std::vector<std::string>& ranking, ApDefinition definition);

// Writes report.md, results.json and plots/*.png into `dir` (created if missing).
[[nodiscard]] Status WriteReport(const std::string& dir, const std::vector<RunResult>& runs,
                                 const std::string& command_line);

double Percentile(std::vector<double> values, double p);  // p in [0, 100]; 0 for an empty list

}  // namespace oxbow::eval
