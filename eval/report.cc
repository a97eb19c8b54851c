#include "eval/report.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <map>
#include <ostream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "eval/plot.h"

namespace oxbow::eval {
namespace {

constexpr int kPrecisionKs[] = {1, 5, 10};

std::string Fixed(double v, int digits = 3) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", digits, v);
  return buf;
}

std::string SafeFileName(std::string s) {
  for (char& c : s) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') c = '_';
  }
  return s;
}

}  // namespace

double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const double rank = std::clamp(p, 0.0, 100.0) / 100.0 * (values.size() - 1);
  const size_t lo = static_cast<size_t>(std::floor(rank));
  const size_t hi = std::min(values.size() - 1, lo + 1);
  return values[lo] + (values[hi] - values[lo]) * (rank - lo);
}

QueryOutcome ScoreRanking(const EvalQuery& query, const std::vector<std::string>& ranking, ApDefinition definition) {
  QueryOutcome outcome;
  outcome.name = query.name;
  outcome.group = query.group;
  outcome.ap = AveragePrecision(ranking, query.relevance, definition);
  for (int k : kPrecisionKs) outcome.precision_at.push_back(PrecisionAtK(ranking, query.relevance, k));
  outcome.top1_hits = PositivesInTopK(ranking, query.relevance, 1);
  outcome.top4_hits = PositivesInTopK(ranking, query.relevance, 4);
  outcome.top4_ceiling = static_cast<int>(std::min<size_t>(4, query.relevance.positives.size()));
  outcome.pr_curve = PrecisionRecallCurve(ranking, query.relevance);
  outcome.top.assign(ranking.begin(), ranking.begin() + std::min<size_t>(10, ranking.size()));
  return outcome;
}

void Summarise(RunResult* run) {
  run->map = 0;
  run->recall_at_1 = run->top4 = run->top4_ceiling = 0;
  run->group_ap.clear();
  run->mean_precision_at.assign(std::size(kPrecisionKs), 0.0);
  std::map<std::string, int> group_queries;
  std::vector<double> latencies, extract, search;
  for (const QueryOutcome& q : run->queries) {
    run->map += q.ap;
    run->recall_at_1 += q.top1_hits;
    run->top4 += q.top4_hits;
    run->top4_ceiling += q.top4_ceiling;
    if (!q.group.empty()) {
      run->group_ap[q.group] += q.ap;
      ++group_queries[q.group];
    }
    for (size_t i = 0; i < q.precision_at.size() && i < run->mean_precision_at.size(); ++i) {
      run->mean_precision_at[i] += q.precision_at[i];
    }
    latencies.push_back(q.latency_ms);
    if (auto it = q.stage_ms.find("extract"); it != q.stage_ms.end()) extract.push_back(it->second);
    double s = 0;
    for (const char* stage : {"quantize", "score", "verify", "qe"}) {
      if (auto it = q.stage_ms.find(stage); it != q.stage_ms.end()) s += it->second;
    }
    search.push_back(s);
  }
  if (!run->queries.empty()) {
    const auto n = static_cast<double>(run->queries.size());
    for (double* mean : {&run->map, &run->recall_at_1, &run->top4, &run->top4_ceiling}) *mean /= n;
    for (double& p : run->mean_precision_at) p /= n;
  }
  for (auto& [group, ap] : run->group_ap) ap /= group_queries[group];
  run->query_p50_ms = Percentile(latencies, 50);
  run->query_p95_ms = Percentile(latencies, 95);
  run->extract_p50_ms = Percentile(extract, 50);
  run->search_p50_ms = Percentile(search, 50);
}

namespace {

namespace fs = std::filesystem;

// The query named `name` in `run`, or nullptr.
const QueryOutcome* FindQuery(const RunResult& run, const std::string& name) {
  auto it = std::find_if(run.queries.begin(), run.queries.end(), [&](const QueryOutcome& q) { return q.name == name; });
  return it == run.queries.end() ? nullptr : &*it;
}

nlohmann::json RunToJson(const RunResult& run) {
  nlohmann::json r;
  r["protocol"] = run.protocol;
  r["label"] = run.label;
  r["settings"] = run.settings;
  r["ap_definition"] = ApDefinitionName(run.ap_definition);
  r["map"] = run.map;
  r["recall_at_1"] = run.recall_at_1;
  r["top4"] = run.top4;
  r["top4_ceiling"] = run.top4_ceiling;
  r["group_ap"] = run.group_ap;
  r["distractors"] = run.distractors;
  r["mean_precision_at"] = {{"1", run.mean_precision_at.at(0)}, {"5", run.mean_precision_at.at(1)},
                            {"10", run.mean_precision_at.at(2)}};
  r["build_vocab_s"] = run.build_vocab_s;
  r["build_index_s"] = run.build_index_s;
  r["query_p50_ms"] = run.query_p50_ms;
  r["query_p95_ms"] = run.query_p95_ms;
  r["extract_p50_ms"] = run.extract_p50_ms;
  r["search_p50_ms"] = run.search_p50_ms;
  r["index"] = {{"images", run.index_images},
                {"features", run.index_features},
                {"bytes_per_feature", run.index_bytes_per_feature},
                {"vocabulary_words", run.vocabulary_words}};
  r["queries"] = nlohmann::json::array();
  for (const QueryOutcome& q : run.queries) {
    nlohmann::json pr = nlohmann::json::array();
    for (const PrPoint& p : q.pr_curve) pr.push_back({p.recall, p.precision});
    r["queries"].push_back({{"name", q.name},
                            {"group", q.group},
                            {"ap", q.ap},
                            {"top4_hits", q.top4_hits},
                            {"precision_at", q.precision_at},
                            {"latency_ms", q.latency_ms},
                            {"stage_ms", q.stage_ms},
                            {"top", q.top},
                            {"pr_curve", pr}});
  }
  return r;
}

// results.json: every number.
Status WriteResultsJson(const std::string& dir, const std::vector<RunResult>& runs, const std::string& command_line) {
  nlohmann::json json = nlohmann::json::object();
  json["command"] = command_line;
  json["runs"] = nlohmann::json::array();
  for (const RunResult& run : runs) json["runs"].push_back(RunToJson(run));
  std::ofstream out(fs::path(dir) / "results.json");
  out << json.dump(2) << "\n";
  if (!out) return Fail(ErrorCode::kIoError, "cannot write '" + dir + "/results.json'");
  return Ok();
}

// One precision-recall chart per run.
Status WritePrCharts(const std::string& dir, const std::vector<RunResult>& runs, std::vector<std::string>* plot_files) {
  for (size_t i = 0; i < runs.size(); ++i) {
    const RunResult& run = runs[i];
    std::vector<Series> curves;
    for (const QueryOutcome& q : run.queries) {
      Series s{q.name + " (AP " + Fixed(q.ap, 2) + ")", {}};
      for (const PrPoint& p : q.pr_curve) s.points.emplace_back(p.recall, p.precision);
      curves.push_back(std::move(s));
    }
    const std::string pr_file = "plots/pr_" + std::to_string(i) + "_" + SafeFileName(run.label) + ".png";
    ChartOptions pr_options{.title = "Precision-recall per query: " + run.protocol + ", " + run.label,
                            .x_label = "recall",
                            .y_label = "precision"};
    if (auto st = WriteLineChart((fs::path(dir) / pr_file).string(), curves, pr_options); !st) return st;
    plot_files->push_back(pr_file);
  }
  return Ok();
}

// AP of each query of the first run's protocol, one bar per run of that protocol. `runs` is not empty.
Status WriteApPerQueryChart(const std::string& dir, const std::vector<RunResult>& runs,
                            std::vector<std::string>* plot_files) {
  std::vector<std::string> query_names;
  for (const QueryOutcome& q : runs[0].queries) query_names.push_back(q.name);
  std::vector<std::string> labels;
  std::vector<std::vector<double>> values;
  for (const RunResult& run : runs) {
    if (run.protocol != runs[0].protocol) continue;
    labels.push_back(run.label);
    std::vector<double> aps;
    for (const std::string& name : query_names) {
      const QueryOutcome* q = FindQuery(run, name);
      aps.push_back(q == nullptr ? 0.0 : q->ap);
    }
    values.push_back(std::move(aps));
  }
  ChartOptions ap_options{.title = "AP per query: " + runs[0].protocol, .x_label = "", .y_label = "AP"};
  if (auto st = WriteBarChart((fs::path(dir) / "plots/ap_per_query.png").string(), query_names, labels, values,
                              ap_options);
      !st) {
    return st;
  }
  plot_files->emplace_back("plots/ap_per_query.png");
  return Ok();
}

// mAP vs vocabulary size, one line per (features, re-ranking, transitive, QE) combination, when sizes
// vary. `runs` is not empty.
Status WriteMapVsVocabularyChart(const std::string& dir, const std::vector<RunResult>& runs,
                                 std::vector<std::string>* plot_files) {
  std::map<std::string, Series> by_variant;
  std::set<uint64_t> sizes;
  for (const RunResult& run : runs) {
    sizes.insert(run.vocabulary_words);
    std::string variant;
    for (const char* key : {"features", "rerank", "transitive", "qe"}) {
      auto it = run.settings.find(key);
      variant += std::string(key) + "=" + (it == run.settings.end() ? "?" : it->second) + " ";
    }
    by_variant[variant].name = variant;
    by_variant[variant].points.emplace_back(static_cast<double>(run.vocabulary_words), run.map);
  }
  if (sizes.size() <= 1) return Ok();
  std::vector<Series> lines;
  for (auto& [_, s] : by_variant) {
    std::sort(s.points.begin(), s.points.end());
    lines.push_back(s);
  }
  ChartOptions size_options{.title = "mAP vs vocabulary size: " + runs[0].protocol,
                            .x_label = "words",
                            .y_label = "mAP",
                            .x_min = 0,
                            .x_max = 0,
                            .log_x = true,
                            .x_ticks = std::vector<double>(sizes.begin(), sizes.end()),
                            .legend_at_bottom = true};
  if (auto st = WriteLineChart((fs::path(dir) / "plots/map_vs_vocabulary.png").string(), lines, size_options); !st) {
    return st;
  }
  plot_files->emplace_back("plots/map_vs_vocabulary.png");
  return Ok();
}

void WriteSummaryTable(std::ostream& md, const std::vector<RunResult>& runs) {
  md << "| protocol | configuration | mAP | AP | recall@1 | top-4 (ceiling) | mP@1 | mP@5 | mP@10 | "
        "query p50 ms | p95 ms | extract p50 ms | search p50 ms | images | distractors | features | B/feature |\n";
  md << "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const RunResult& run : runs) {
    md << "| " << run.protocol << " | " << run.label << " | **" << Fixed(run.map) << "** | "
       << ApDefinitionName(run.ap_definition) << " | " << Fixed(run.recall_at_1) << " | " << Fixed(run.top4, 2)
       << " (" << Fixed(run.top4_ceiling, 2) << ") | " << Fixed(run.mean_precision_at.at(0)) << " | "
       << Fixed(run.mean_precision_at.at(1)) << " | " << Fixed(run.mean_precision_at.at(2)) << " | "
       << Fixed(run.query_p50_ms, 1) << " | "
       << Fixed(run.query_p95_ms, 1) << " | " << Fixed(run.extract_p50_ms, 1) << " | " << Fixed(run.search_p50_ms, 1)
       << " | " << run.index_images << " | " << run.distractors << " | " << run.index_features << " | " << Fixed(run.index_bytes_per_feature, 1)
       << " |\n";
  }
}

// Search stages as the server reports them (timings_ms), p50 / p95 over the queries.
void WriteStageTable(std::ostream& md, const std::vector<RunResult>& runs) {
  md << "\n## Search stages (ms, p50 / p95 over the queries)\n\n";
  md << "| configuration | quantize | score | verify (incl. transitive) | qe | search total | extract |\n";
  md << "|---|---|---|---|---|---|---|\n";
  for (const RunResult& run : runs) {
    const auto stage = [&](std::initializer_list<const char*> names) {
      std::vector<double> v;
      for (const QueryOutcome& q : run.queries) {
        double sum = 0;
        for (const char* name : names) {
          if (auto it = q.stage_ms.find(name); it != q.stage_ms.end()) sum += it->second;
        }
        v.push_back(sum);
      }
      return Fixed(Percentile(v, 50), 1) + " / " + Fixed(Percentile(v, 95), 1);
    };
    md << "| " << run.label << " | " << stage({"quantize"}) << " | " << stage({"score"}) << " | " << stage({"verify"})
       << " | " << stage({"qe"}) << " | " << stage({"quantize", "score", "verify", "qe"}) << " | "
       << stage({"extract"}) << " |\n";
  }
}

void WriteSettings(std::ostream& md, const std::vector<RunResult>& runs) {
  md << "\n## Settings\n\n";
  for (const RunResult& run : runs) {
    md << "- **" << run.protocol << ", " << run.label << "**: ";
    bool first = true;
    for (const auto& [k, v] : run.settings) {
      md << (first ? "" : "; ") << k << " = " << v;
      first = false;
    }
    md << "; vocabulary build " << Fixed(run.build_vocab_s, 1) << " s, index build " << Fixed(run.build_index_s, 1)
       << " s\n";
  }
}

// Groups protocol: one row per group of the first run, one column per run.
void WriteGroupApTable(std::ostream& md, const std::vector<RunResult>& runs) {
  if (runs.empty() || runs[0].group_ap.empty()) return;
  std::map<std::string, int> queries_per_group;
  for (const QueryOutcome& q : runs[0].queries) ++queries_per_group[q.group];
  md << "\n## AP per group (" << ApDefinitionName(runs[0].ap_definition) << ", mean over its queries)\n\n| group | queries |";
  for (const RunResult& run : runs) md << " " << run.label << " |";
  md << "\n|---|---|";
  for (size_t i = 0; i < runs.size(); ++i) md << "---|";
  md << "\n";
  for (const auto& [group, count] : queries_per_group) {
    md << "| " << group << " | " << count << " |";
    for (const RunResult& run : runs) {
      const auto it = run.group_ap.find(group);
      md << " " << (it == run.group_ap.end() ? "-" : Fixed(it->second)) << " |";
    }
    md << "\n";
  }
}

// One row per query of the first run, one column per run.
void WriteApTable(std::ostream& md, const std::vector<RunResult>& runs) {
  md << "\n## AP per query\n\n| query |";
  for (const RunResult& run : runs) md << " " << run.label << " |";
  md << "\n|---|";
  for (size_t i = 0; i < runs.size(); ++i) md << "---|";
  md << "\n";
  if (runs.empty()) return;
  for (const QueryOutcome& q0 : runs[0].queries) {
    md << "| " << q0.name << " |";
    for (const RunResult& run : runs) {
      const QueryOutcome* q = FindQuery(run, q0.name);
      md << " " << (q == nullptr ? "-" : Fixed(q->ap)) << " |";
    }
    md << "\n";
  }
}

}  // namespace

Status WriteReport(const std::string& dir, const std::vector<RunResult>& runs, const std::string& command_line) {
  std::error_code ec;
  fs::create_directories(fs::path(dir) / "plots", ec);
  if (ec) return Fail(ErrorCode::kIoError, "cannot create report folder '" + dir + "': " + ec.message());
  if (auto st = WriteResultsJson(dir, runs, command_line); !st) return st;

  std::vector<std::string> plot_files;
  if (auto st = WritePrCharts(dir, runs, &plot_files); !st) return st;
  if (!runs.empty()) {
    if (auto st = WriteApPerQueryChart(dir, runs, &plot_files); !st) return st;
    if (auto st = WriteMapVsVocabularyChart(dir, runs, &plot_files); !st) return st;
  }

  std::ostringstream md;
  md << "# oxbow retrieval evaluation\n\n";
  md << "Command: `" << command_line << "`\n\n";
  WriteSummaryTable(md, runs);
  WriteStageTable(md, runs);
  WriteSettings(md, runs);
  WriteGroupApTable(md, runs);
  WriteApTable(md, runs);
  md << "\n## Plots\n\n";
  for (const std::string& f : plot_files) md << "![" << f << "](" << f << ")\n\n";
  std::ofstream out(fs::path(dir) / "report.md");
  out << md.str();
  if (!out) return Fail(ErrorCode::kIoError, "cannot write '" + dir + "/report.md'");
  return Ok();
}

}  // namespace oxbow::eval
