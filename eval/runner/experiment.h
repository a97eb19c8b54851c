// The evaluation runner behind `oxbow eval` (server/README.md, "oxbow eval"): for every configuration
// of the experiment matrix it trains a vocabulary and builds an index with the `oxbow` binary's `vocab
// train` and `index build` (cached in the work folder), starts `oxbow serve` on an ephemeral loopback
// port and runs every query through the HTTP API, the way users call it; optionally also in process, or
// against a running server or cluster front. Each run is scored and summarised (eval/report.h); the
// caller writes the report.
#pragma once

#include <array>
#include <cstdint>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include "eval/report.h"
#include "index/image_index.h"

namespace oxbow::eval {

// The experiment: the data set, the matrix of configurations and how to run it. One field per flag of
// `oxbow eval`, with the same defaults.
struct ExperimentOptions {
  std::string oxbow_binary;              // the `oxbow` binary whose vocab train, index build and serve run
  std::string protocol = "oxford";       // oxford | restricted | revisited | groups
  std::string images;                    // database images folder
  std::string distractors;               // groups: images added to the database, never queries or positives
  std::string gt;                        // ground-truth folder (oxford/restricted) or JSON (revisited)
  std::string setting = "medium";        // revisited: easy | medium | hard
  std::string train_images;              // vocabulary training images (default: the database images)
  std::string work = "eval-work";        // cache of vocabularies and indexes
  std::string out = "eval-report";       // report folder
  std::vector<std::string> features = {"rootsift"};
  std::vector<int> words = {20000};
  std::vector<int> rerank = {index::QueryOptions{}.rerank_depth};  // the server's default
  std::vector<std::string> qe = {"on"};
  std::vector<std::string> transitive = {"on"};  // transitive verification (the server's default) on/off
  // Hamming-embedding re-scoring on/off (the server's default).
  std::vector<std::string> hamming = {index::QueryOptions{}.hamming ? "on" : "off"};
  // With hamming on: the match thresholds and weight widths to compare (the server's defaults).
  std::vector<int> hamming_threshold = {index::QueryOptions{}.hamming_threshold};
  std::vector<double> hamming_sigma = {index::QueryOptions{}.hamming_sigma};
  int top_k = 0;                         // results requested per query; 0 = the whole database (max 10000)
  int sample = 1000000;                  // vocabulary training sample
  int per_image = 0;                     // per-image cap on the training sample; 0 = the command's default
  int iterations = 0;                    // k-means iterations; 0 = the command's default
  uint64_t seed = 1;
  int threads = 0;
  bool full_image = false;               // ignore the query boxes
  std::string mode = "http";             // http | in-process | both
  int max_queries = 0;                   // evaluate only the first N queries (0 = all), for smoke runs
  std::string server;                    // a running server or cluster front to evaluate (http://HOST:PORT)
  // With --server: which of kServerSearchSettings were given on the command line. Only these are sent
  // with each search; the others are the server's own (its defaults and the flags it was started
  // with), and the report says so.
  std::set<std::string> server_settings_given;
};

// The search settings of `oxbow eval` (its flags without the dashes) that a running server (--server)
// receives only when they are given.
inline constexpr std::array<const char*, 4> kServerSearchSettings = {"rerank", "qe", "transitive", "hamming"};

// The target of one search request for a run with these settings: `/v1/search?top_k=N`, then those of
// kServerSearchSettings that are sent (to a server eval starts itself, all of them; to a running
// server, those given): `rerank`, `qe`, `transitive_depth` (0 for off, the built-in depth for on) and
// `hamming`. The query's box is the caller's to add.
std::string SearchTarget(const ExperimentOptions& a, int rerank, bool qe, bool transitive, bool hamming, int top_k);

// A failed experiment: the message and the exit code `oxbow eval` ends with (as sift/base/error.h's
// ExitCodeFor: 1 internal, 2 invalid argument, 4 not found, 7 I/O).
class ExperimentError : public std::runtime_error {
 public:
  ExperimentError(int exit_code, const std::string& message) : std::runtime_error(message), exit_code_(exit_code) {}
  int exit_code() const { return exit_code_; }

 private:
  int exit_code_;
};

struct Experiments {
  std::string protocol;                     // the protocol's name
  ApDefinition ap = ApDefinition::kOxfordTrapezoid;
  std::vector<RunResult> runs;              // one per configuration and mode, in matrix order, summarised
};

// Runs every configuration of `options`; throws ExperimentError.
Experiments RunExperiments(const ExperimentOptions& options);

}  // namespace oxbow::eval
