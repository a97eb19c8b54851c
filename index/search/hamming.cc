#include "index/search/hamming.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstddef>
#include <numeric>

namespace oxbow::index {
namespace {

// The bitwise majority of n >= 1 signatures sig(k) (ties: sig(0)'s bit).
template <typename SignatureAt>
uint64_t Majority(size_t n, SignatureAt sig) {
  // One or two signatures: the first (two that differ in a bit tie there). Three: the bitwise vote.
  if (n <= 2) return sig(0);
  if (n == 3) {
    const uint64_t a = sig(0), b = sig(1), c = sig(2);
    return (a & b) | (a & c) | (b & c);
  }
  std::array<int, 64> count{};
  for (size_t k = 0; k < n; ++k) {
    const uint64_t s = sig(k);
    for (size_t b = 0; b < 64; ++b) count[b] += (s >> b & 1) != 0 ? 1 : -1;
  }
  const uint64_t first = sig(0);
  uint64_t out = 0;
  for (size_t b = 0; b < 64; ++b) {
    if (count[b] > 0 || (count[b] == 0 && (first >> b & 1) != 0)) out |= uint64_t{1} << b;
  }
  return out;
}

}  // namespace

double HammingWeight(uint64_t a, uint64_t b, const HammingWeighting& weighting) {
  const int h = std::popcount(a ^ b);
  if (h > weighting.threshold) return 0;
  return std::exp(-static_cast<double>(h * h) / (weighting.sigma * weighting.sigma));
}

double AggregatedWeight(int h) {
  const double u = 1.0 - 2.0 * static_cast<double>(h) / 64.0;
  return u > 0.25 ? u * u * u : 0.0;
}

QuerySignatures::QuerySignatures(std::span<const uint32_t> words, std::span<const uint64_t> signatures,
                                 std::shared_ptr<const std::vector<double>> idf_squared,
                                 const HammingWeighting& weighting)
    : idf_squared_(std::move(idf_squared)) {
  OXBOW_CHECK(words.size() == signatures.size());
  OXBOW_CHECK(idf_squared_ != nullptr);
  // Same values as HammingWeight: popcount(a ^ b) is the distance.
  for (size_t h = 0; h < weight_.size(); ++h) {
    weight_[h] = HammingWeight(0, h == 64 ? ~0ull : (1ull << h) - 1, weighting);
  }
  std::vector<uint32_t> order(words.size());
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return words[a] < words[b]; });
  for (const uint32_t i : order) {
    words_.push_back(words[i]);
    signatures_.push_back(signatures[i]);
    self_ += IdfSquared(words[i]);
  }
  runs_ = WordRuns(words_.size(), [&](size_t i) { return words_[i]; });
  OXBOW_CHECK(weighting.norm_exponent >= 0 && weighting.norm_exponent <= 1);
  norm_exponent_ = weighting.norm_exponent;
  self_scale_ = std::pow(self_, 1.0 - norm_exponent_);
  OXBOW_CHECK(weighting.asmk_weight >= 0);
  asmk_weight_ = weighting.asmk_weight;
  if (asmk_weight_ > 0) {
    for (size_t i = 0; i < words_.size();) {
      size_t i2 = i + 1;
      while (i2 < words_.size() && words_[i2] == words_[i]) ++i2;
      aggregated_.push_back(Majority(i2 - i, [&](size_t k) { return signatures_[i + k]; }));
      self_distinct_ += IdfSquared(words_[i]);
      i = i2;
    }
  }
}

double QuerySignatures::IdfSquared(uint32_t word) const {
  OXBOW_CHECK(word < idf_squared_->size(), "word outside the vocabulary");
  return (*idf_squared_)[word];
}


template <bool kSelf, bool kAggregate>
QuerySignatures::Votes QuerySignatures::Count(const PackedFeatures& db) const {
  OXBOW_CHECK(db.has_signatures(), "Hamming scoring needs the candidate's signatures");
  thread_local std::vector<double> strength, query_total, db_total;
  const size_t nd = db.size();
  Votes votes;
  size_t r = 0;  // first query run whose word may still occur in the db (db words ascend)
  for (size_t j = 0; j < nd;) {
    const uint32_t w = db.word(j);
    // Without N_d to sum, a db word the query lacks (most of them: one bit test) needs nothing more.
    if (!kSelf && !runs_.Has(w)) {
      ++j;
      continue;
    }
    size_t j2 = j + 1;
    while (j2 < nd && db.word(j2) == w) ++j2;
    const double idf2 = IdfSquared(w);
    if constexpr (kSelf) {
      votes.self += idf2 * static_cast<double>(j2 - j);
      votes.distinct += idf2;
    }
    // The query's run of w, [i, i2): empty for most db words, which one bit test tells (an expanded
    // query holds tens of thousands of features: a merge step per feature was most of Score's time).
    const auto [i, i2] = runs_.Find(w, r);
    if constexpr (kAggregate) {
      if (i2 > i && idf2 > 0) {
        const uint64_t aggregated = Majority(j2 - j, [&db, j](size_t k) { return db.signature(j + k); });
        votes.aggregated += idf2 * AggregatedWeight(std::popcount(aggregated_[r] ^ aggregated));
      }
    }
    if (i2 == i + 1 && j2 == j + 1 && idf2 > 0) {
      // Most shared words: one feature on each side (the general case below, without its scratch).
      const double s = weight_[std::popcount(signatures_[i] ^ db.signature(j))];
      if (s > 0) votes.matched += idf2 * (s * s / std::sqrt(s * s));
    } else if (i2 > i && idf2 > 0) {
      const size_t cq = i2 - i, cd = j2 - j;
      strength.assign(cq * cd, 0.0);
      query_total.assign(cq, 0.0);
      db_total.assign(cd, 0.0);
      for (size_t a = 0; a < cq; ++a) {
        for (size_t b = 0; b < cd; ++b) {
          const double s = weight_[std::popcount(signatures_[i + a] ^ db.signature(j + b))];
          strength[a * cd + b] = s;
          query_total[a] += s;
          db_total[b] += s;
        }
      }
      double word_votes = 0;
      for (size_t a = 0; a < cq; ++a) {
        for (size_t b = 0; b < cd; ++b) {
          const double s = strength[a * cd + b];
          if (s > 0) word_votes += s * s / std::sqrt(query_total[a] * db_total[b]);
        }
      }
      votes.matched += idf2 * word_votes;
    }
    j = j2;
  }
  return votes;
}

double QuerySignatures::Combine(const Votes& votes, double candidate_self) const {
  double score = 0;
  if (votes.matched > 0 && self_ > 0 && candidate_self > 0) {
    score = votes.matched / (self_scale_ * std::pow(candidate_self, norm_exponent_));
  }
  if (asmk_weight_ > 0 && votes.aggregated > 0 && self_distinct_ > 0 && votes.distinct > 0) {
    score += asmk_weight_ * votes.aggregated / std::sqrt(self_distinct_ * votes.distinct);
  }
  return score;
}

double QuerySignatures::Score(const PackedFeatures& db) const {
  const Votes votes = asmk_weight_ > 0 ? Count<true, true>(db) : Count<true, false>(db);
  return Combine(votes, votes.self);
}

double QuerySignatures::Score(const PackedFeatures& db, double candidate_self) const {
  // With aggregation the candidate's M_d is summed over all its features anyway.
  if (asmk_weight_ > 0) return Combine(Count<true, true>(db), candidate_self);
  return Combine(Count<false, false>(db), candidate_self);
}

}  // namespace oxbow::index
