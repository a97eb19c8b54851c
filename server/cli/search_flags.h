// Command-line flags for the search and index options (index/image_index.h), shared by `oxbow query`
// and `oxbow serve` so that both spell, range-check and document them the same way. Each flag maps 1:1
// onto one option field; its default is the field's in-class default (see the field's comment for the
// meaning and the paper), and the same names (with '_' for '-') are the HTTP search parameters
// (api/params.h).
#pragma once

#include <CLI/CLI.hpp>

#include "index/image_index.h"
#include "server/cli/cli.h"

namespace oxbow::cli {

// Per-search options beyond --top-k/--rerank/--qe (which each command words for its own use).
inline void AddSearchFlags(CLI::App* cmd, index::QueryOptions* o) {
  const auto add = [cmd](const char* name, auto* field, const char* help, auto min, auto max) {
    cmd->add_option(name, *field, help)->capture_default_str()->check(NumberIn(static_cast<double>(min), static_cast<double>(max)))->group("Search");
  };
  add("--qe-images", &o->qe_images, "verified results averaged into the expanded query", 1, 100);
  add("--min-inliers", &o->verify.min_inliers, "inliers needed to count as verified", 3, 1000000);
  add("--max-pairs-per-word", &o->max_pairs_per_word,
      "re-ranking: words with more features than this on either side give no tentative matches", 1, 100);
  add("--transitive-depth", &o->transitive_depth,
      "transitive verification: unverified results tried against verified ones (0 = off)", 0, 10000);
  add("--transitive-anchors", &o->transitive_anchors,
      "transitive verification: verified results used as anchors (only firm ones: inliers over an area, not a line "
      "or a band of text)",
      1, 1000);
  add("--transitive-neighbours", &o->transitive_neighbours,
      "transitive verification: an anchor only verifies its own best tf-idf neighbours", 1, 10000);
  add("--transitive-attempts", &o->transitive_attempts,
      "transitive verification: anchors a candidate is verified against at most, in each round of anchors", 1, 1000);
  add("--query-assignments", &o->query_assignments,
      "multiple assignment: nearest words each query descriptor counts for (1 = hard)", 1, 8);
  add("--assignment-sigma-sq", &o->assignment_sigma_sq, "multiple assignment: kernel width (squared distance)", 1e-9,
      4.0);
  cmd->add_flag("--hamming,!--no-hamming", o->hamming,
                "Hamming embedding, on by default: re-score the tf-idf shortlist by matching signatures (needs a "
                "vocabulary with the parameters, which 'vocab train' learns by default or 'vocab hamming' adds, and "
                "images indexed with it; ignored otherwise)")
      ->group("Search");
  add("--hamming-shortlist", &o->hamming_shortlist, "Hamming embedding: tf-idf candidates re-scored", 1, 10000);
  add("--hamming-threshold", &o->hamming_threshold, "Hamming embedding: largest distance (bits) that matches", 0, 64);
  add("--hamming-sigma", &o->hamming_sigma, "Hamming embedding: width (bits) of the weight exp(-h^2/sigma^2)", 1e-9,
      64.0);
  add("--hamming-norm-exponent", &o->hamming_norm_exponent,
      "Hamming embedding: the candidate's share e of the score's normalisation, score / (N_query^(1-e) "
      "N_candidate^e): 0.5 is symmetric, larger ranks a large image that matches by chance below a smaller one "
      "whose features match",
      0.0, 1.0);
  add("--asmk-weight", &o->asmk_weight,
      "Hamming embedding: weight of the aggregated score (ASMK*: one majority signature per word and image) "
      "added when re-scoring the tf-idf shortlist (0 = off)",
      0, 1000);
  add("--qe-asmk-weight", &o->qe_asmk_weight,
      "Hamming embedding: weight of the aggregated score (ASMK*) added when query expansion re-scores the "
      "unverified results (0 = off)",
      0, 1000);
  add("--max-query-features", &o->max_query_features,
      "an image query uses at most this many of its features, the strongest (0 = all)", 0, 1000000);
  add("--max-scored-postings", &o->max_scored_postings,
      "postings a tf-idf pass scans at most: a longer query drops its most frequent words first; faster at "
      "millions of images, less accurate (0 = no limit; eval/results/index-scale.md)",
      0, 2000000000);
  add("--max-tentative-matches", &o->max_tentative_matches,
      "Hamming embedding: tentative matches verified per candidate, the closest signatures (0 = no limit)", 0,
      1000000);
  add("--quantizer-probes", &o->quantizer_probes,
      "coarse quantiser lists probed per query descriptor (more: slower, closer to exact)", 1, 4096);
}

// Options of the opened index that change scores: fixed while it is open, not stored in it.
inline void AddIndexScoringFlags(CLI::App* cmd, index::IndexOptions* o) {
  const auto group = "Index scoring";
  cmd->add_option("--max-df", o->max_document_frequency,
                  "stop list: ignore query words in more than this fraction of the images (1 = off)")
      ->capture_default_str()
      ->check(NumberIn(0, 1, /*lo_open=*/true))
      ->group(group);
  cmd->add_option("--stop-list-min-images", o->stop_list_min_images,
                  "stop list: never drop a word contained in at most this many images")
      ->capture_default_str()
      ->group(group);
  cmd->add_flag("--sqrt-tf,!--raw-tf", o->sqrt_tf, "burstiness: sqrt of term frequencies (default) or raw counts")
      ->group(group);
}

}  // namespace oxbow::cli
