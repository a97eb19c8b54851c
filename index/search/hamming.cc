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
  // Each bit position's count of ones, bit-sliced: planes[k] holds bit k of the 64 counts, so adding a
  // signature is a ripple-carry add of 64 one-bit numbers (a few word operations, not 64 per signature).
  std::array<uint64_t, 64> planes{};
  const auto num_planes = static_cast<size_t>(std::bit_width(n));
  for (size_t k = 0; k < n; ++k) {
    uint64_t carry = sig(k);
    for (size_t p = 0; carry != 0 && p < num_planes; ++p) {
      const uint64_t next = planes[p] & carry;
      planes[p] ^= carry;
      carry = next;
    }
  }
  // A bit is set when its count c has 2c > n, or 2c == n (a tie) and sig(0) has it: compare every count
  // with half = floor(n / 2) from the top plane down.
  const size_t half = n / 2;
  uint64_t above = 0, equal = ~uint64_t{0};
  for (size_t p = num_planes; p-- > 0;) {
    if ((half >> p & 1) != 0) {
      equal &= planes[p];
    } else {
      above |= equal & planes[p];
      equal &= ~planes[p];
    }
  }
  return n % 2 == 0 ? above | (equal & sig(0)) : above;
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
      strength.resize(cq * cd);  // every entry is written below
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
      // s^2 / sqrt(query_total[a] * db_total[b]) summed as s^2 / sqrt(db_total[b]) per row, then over the
      // rows / sqrt(query_total[a]): one root per feature instead of a root and a division per pair (an
      // expanded query's bursts make this loop most of query expansion's time). A total of 0 has only
      // zero strengths beside it.
      for (double& total : db_total) total = total > 0 ? 1.0 / std::sqrt(total) : 0.0;
      double word_votes = 0;
      for (size_t a = 0; a < cq; ++a) {
        if (query_total[a] <= 0) continue;
        const double* row = &strength[a * cd];
        double sum = 0;
        for (size_t b = 0; b < cd; ++b) sum += row[b] * row[b] * db_total[b];
        word_votes += sum / std::sqrt(query_total[a]);
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
