// Hamming-embedding scoring of a candidate image (Jegou, Douze & Schmid 2008, "Hamming embedding and
// weak geometric consistency for large scale image search"), with intra-image burstiness
// normalisation (Jegou, Douze & Schmid 2009, "On the burstiness of visual elements").
//
// A query feature i and a db feature j of the same word w match with strength
//   s_ij = exp(-h_ij^2 / sigma^2) when their signatures' Hamming distance h_ij <= threshold, else 0.
// Burstiness: a feature matching many features of the other image (repeated texture, a word that
// covers a whole facade) would otherwise vote many times; each match is divided by the geometric mean
// of the total strengths of its two features in this image pair:
//   s'_ij = s_ij^2 / sqrt(S_i S_j),  S_i = sum_j s_ij,  S_j = sum_i s_ij,
// so a one-to-one match keeps s_ij and m equal matches of one feature count sqrt(m) together.
// The score is  sum_w idf_w^2 sum_ij s'_ij / (N_q^(1 - e) N_d^e)  with N_x = sum_w idf_w^2 tf_w(x) (the
// score of an image against itself when each feature matches only itself) and e = norm_exponent. With
// e = 0.5 it is the symmetric form, sqrt(N_q N_d), in [0, about 1]; a larger e weighs the candidate's own
// size more, as document-length normalisation does in text retrieval: a large image (a textured scene of
// 6,000 features) matched in part by chance then scores less against a small one whose features match.
//
// Aggregated matching (ASMK*, Tolias, Avrithis & Jegou 2013, "To aggregate or not to aggregate"),
// added with weight asmk_weight: each image is one aggregated signature per word it has, the bitwise
// majority of its features' signatures there (ties: the first feature's bit; ASMK* binarises the sum
// of the residuals, which the index does not keep: the majority of their binarised components is what
// the stored signatures allow), and two images' words match with the selectivity
//   sigma(u) = u^3 when u > 0.25, else 0,  u = 1 - 2 h / 64  (h: the aggregated signatures' distance),
// scored  sum_w idf_w^2 sigma(u_w) / sqrt(M_q M_d)  with M_x = sum of idf_w^2 over x's distinct words,
// in [0, 1]. A burst (a word repeated over a facade or a texture) is one vote however many features
// it has, and an expanded query (the query and its verified results together, where a word holds the
// features of several views) votes with each word's consensus. Nothing more is stored: the aggregated
// signatures are made from the features' signatures as a candidate is scored.
//
// Thread safety: a QuerySignatures is immutable after construction; Score may run concurrently.
// Cost of Score: O(|candidate|) plus a binary search per shared word, plus O(cq * cd) per shared word;
// the O(|candidate|) part is a 3-byte read and a bit test per feature when N_d is given and
// asmk_weight is 0 (with aggregation, M_d needs an idf look-up per distinct word), and with aggregation
// O(cd) more per shared word, O(64 cd) where the candidate has four or more features of it (the query's
// aggregated signatures are made once, at construction).
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <span>
#include <vector>

#include "index/storage/feature_store.h"
#include "index/search/word_runs.h"

namespace oxbow::index {

struct HammingWeighting {
  int threshold = 24;         // largest Hamming distance that matches, [0, 64]
  double sigma = 16;          // kernel width in bits, > 0
  double asmk_weight = 0;     // weight of the aggregated (ASMK*) score added to the score above, >= 0
  double norm_exponent = 0.5; // e above: the candidate's share of the normalisation, [0, 1]
};

// The ASMK* selectivity of two aggregated signatures at Hamming distance h (sigma(u) above).
double AggregatedWeight(int h);

// The match strength of two signatures (s_ij above).
double HammingWeight(uint64_t a, uint64_t b, const HammingWeighting& weighting);

class QuerySignatures {
 public:
  // words[i] and signatures[i] of each query feature (same length); idf_squared[w] the squared inverse
  // document frequency of word w (0 for a word in no image: such words are ignored), for every word of
  // the query and of the candidates (InvertedFile::IdfSquaredTable()).
  QuerySignatures(std::span<const uint32_t> words, std::span<const uint64_t> signatures,
                  std::shared_ptr<const std::vector<double>> idf_squared, const HammingWeighting& weighting);

  // The score of `candidate` (which must have signatures). 0 when nothing matches.
  double Score(const PackedFeatures& candidate) const;
  // The same with the candidate's N_d given (sum over its features of idf_w^2, with the statistics of
  // the idf table): then, without aggregation, only its features whose word the query has are looked
  // at, instead of an idf lookup per feature (most of Score's time over a shortlist). With sqrt(tf)
  // weighting N_d is the square of the candidate's tf-idf norm (InvertedFile::Norm), which the index
  // keeps per image.
  double Score(const PackedFeatures& candidate, double candidate_self) const;

 private:
  struct Votes {
    double matched = 0;     // sum_w idf_w^2 sum_ij s'_ij
    double aggregated = 0;  // sum_w idf_w^2 sigma(u_w), with aggregation
    double self = 0;        // with kSelf: the candidate's N_d
    double distinct = 0;    // with kSelf: the candidate's M_d
  };
  // The votes of `db`; with kSelf, also its N_d and M_d; with kAggregate, the aggregated votes.
  template <bool kSelf, bool kAggregate>
  Votes Count(const PackedFeatures& db) const;
  double Combine(const Votes& votes, double candidate_self) const;

  double IdfSquared(uint32_t word) const;  // idf(w)^2 (OXBOW_CHECKs the word is in the table)

  std::vector<uint32_t> words_;       // sorted
  std::vector<uint64_t> signatures_;  // in words_' order
  WordRuns runs_;                     // of words_
  std::array<double, 65> weight_{};   // s_ij by Hamming distance (0 above the threshold)
  double asmk_weight_ = 0;
  double norm_exponent_ = 0.5;        // e
  double self_scale_ = 0;             // N_q^(1 - e)
  std::vector<uint64_t> aggregated_;  // with aggregation: each run's majority signature, by run
  double self_distinct_ = 0;          // M_q
  // idf^2 by word, made once per statistics (a logarithm per word of every candidate was most of
  // Score's time when each query computed its own).
  std::shared_ptr<const std::vector<double>> idf_squared_;
  double self_ = 0;                   // N_q
};

}  // namespace oxbow::index
