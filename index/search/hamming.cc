#include "index/search/hamming.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <numeric>

namespace oxbow::index {
double HammingWeight(uint64_t a, uint64_t b, const HammingWeighting& weighting) {
  const int h = std::popcount(a ^ b);
  if (h > weighting.threshold) return 0;
  return std::exp(-static_cast<double>(h * h) / (weighting.sigma * weighting.sigma));
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
}

double QuerySignatures::IdfSquared(uint32_t word) const {
  OXBOW_CHECK(word < idf_squared_->size(), "word outside the vocabulary");
  return (*idf_squared_)[word];
}

template <bool kSelf>
double QuerySignatures::Votes(const PackedFeatures& db, double* self_db) const {
  OXBOW_CHECK(db.has_signatures(), "Hamming scoring needs the candidate's signatures");
  thread_local std::vector<double> strength, query_total, db_total;
  const size_t nd = db.size();
  double votes = 0;
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
    if constexpr (kSelf) *self_db += idf2 * static_cast<double>(j2 - j);
    // The query's run of w, [i, i2): empty for most db words, which one bit test tells (an expanded
    // query holds tens of thousands of features: a merge step per feature was most of Score's time).
    const auto [i, i2] = runs_.Find(w, r);
    if (i2 == i + 1 && j2 == j + 1 && idf2 > 0) {
      // Most shared words: one feature on each side (the general case below, without its scratch).
      const double s = weight_[std::popcount(signatures_[i] ^ db.signature(j))];
      if (s > 0) votes += idf2 * (s * s / std::sqrt(s * s));
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
      votes += idf2 * word_votes;
    }
    j = j2;
  }
  return votes;
}

double QuerySignatures::Score(const PackedFeatures& db) const {
  double self_db = 0;
  const double votes = Votes<true>(db, &self_db);
  if (votes <= 0 || self_ <= 0 || self_db <= 0) return 0;
  return votes / std::sqrt(self_ * self_db);
}

double QuerySignatures::Score(const PackedFeatures& db, double candidate_self) const {
  const double votes = Votes<false>(db, nullptr);
  if (votes <= 0 || self_ <= 0 || candidate_self <= 0) return 0;
  return votes / std::sqrt(self_ * candidate_self);
}

}  // namespace oxbow::index
