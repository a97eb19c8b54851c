#include "index/search/rerank.h"

#include <algorithm>
#include <bit>
#include <numeric>
#include <vector>

namespace oxbow::index {

QueryGeometry::QueryGeometry(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                             const std::array<float, 4>& region, std::span<const uint64_t> signatures,
                             int hamming_threshold, int max_matches)
    : keypoints_(keypoints),
      words_(words),
      signatures_(signatures),
      hamming_threshold_(hamming_threshold),
      max_matches_(static_cast<size_t>(std::max(0, max_matches))),
      order_(words.size()),
      region_(region) {
  OXBOW_CHECK(keypoints.size() == words.size());
  OXBOW_CHECK(signatures.empty() || signatures.size() == words.size());
  std::iota(order_.begin(), order_.end(), 0u);
  std::stable_sort(order_.begin(), order_.end(), [&](uint32_t a, uint32_t b) { return words_[a] < words_[b]; });
  runs_ = WordRuns(order_.size(), [&](size_t i) { return words_[order_[i]]; });
}

sift::VerificationResult QueryGeometry::Verify(const PackedFeatures& db, int max_pairs_per_word,
                                               const sift::HoughVerifyOptions& options) const {
  // Scratch reused by every call on this thread: a re-ranking pass verifies hundreds of candidates.
  thread_local std::vector<sift::Match> matches;
  thread_local std::vector<sift::Keypoint> db_keypoints;
  thread_local std::vector<std::array<uint32_t, 3>> close;  // Hamming distance, query k, db k of a word's pairs
  thread_local std::vector<uint8_t> query_used, db_used;
  matches.clear();
  const bool hamming = !signatures_.empty() && !db.signature_bytes().empty();
  const size_t nd = db.size();
  const auto limit = static_cast<size_t>(max_pairs_per_word);
  size_t r = 0;  // first query run whose word may still occur in the db (db words ascend)
  for (size_t j = 0; j < nd;) {
    // The db image's run of word w: [j, j2). Most words are not in the query: one bit test skips them.
    const uint32_t w = db.word(j);
    size_t j2 = j + 1;
    while (j2 < nd && db.word(j2) == w) ++j2;
    if (const auto [i, i_end] = runs_.Find(w, r); i_end > i) {
      const size_t cq = i_end - i, cd = j2 - j;
      if (hamming && cq == 1 && cd == 1) {
        // Most shared words: one feature on each side, one pair (the general case below, without its
        // scratch).
        const int h = std::popcount(signatures_[order_[i]] ^ db.signature(j));
        if (h <= hamming_threshold_) matches.push_back({order_[i], static_cast<uint32_t>(j), static_cast<float>(h)});
      } else if (hamming) {
        // Pairs within the threshold, one-to-one closest first (ties in (query, db) index order). A
        // match's distance is its Hamming distance.
        close.clear();
        for (size_t a = 0; a < cq; ++a) {
          for (size_t b = 0; b < cd; ++b) {
            const auto h = static_cast<uint32_t>(std::popcount(signatures_[order_[i + a]] ^ db.signature(j + b)));
            if (h <= static_cast<uint32_t>(hamming_threshold_)) close.push_back({h, static_cast<uint32_t>(a), static_cast<uint32_t>(b)});
          }
        }
        std::sort(close.begin(), close.end());
        query_used.assign(cq, 0);
        db_used.assign(cd, 0);
        for (const auto& [h, a, b] : close) {
          if (query_used[a] != 0 || db_used[b] != 0) continue;
          query_used[a] = db_used[b] = 1;
          matches.push_back({order_[i + a], static_cast<uint32_t>(j + b), static_cast<float>(h)});
        }
      } else if (cq <= limit && cd <= limit) {
        // The word's cq x cd pairs made one-to-one, as sift::EnforceOneToOne does for them: features of
        // different words never share a pair, all pairs of a word have the same "distance" cq * cd
        // (pairs from a word seen once on each side are the most reliable), and its tie-break by
        // (query index, db index) pairs the k-th smallest query index with the k-th smallest db index.
        // Both runs are ascending (stable sort by word; db features in index order).
        const auto distance = static_cast<float>(cq * cd);
        for (size_t k = 0; k < std::min(cq, cd); ++k) {
          // db_index numbers the compact keypoint array built below.
          matches.push_back({order_[i + k], static_cast<uint32_t>(j + k), distance});
        }
      }
    }
    j = j2;
  }
  // Inliers are a subset of the one-to-one matches: with fewer than min_inliers of them the candidate
  // cannot verify, so the verifier is not run (same result, no cost).
  if (matches.size() < static_cast<size_t>(std::max(3, options.min_inliers))) return {};
  if (hamming && max_matches_ > 0 && matches.size() > max_matches_) {
    // The closest max_matches_ (a query feature is in one match at most, so the order is total).
    std::nth_element(matches.begin(), matches.begin() + static_cast<std::ptrdiff_t>(max_matches_), matches.end(),
                     [](const sift::Match& a, const sift::Match& b) {
                       return a.distance != b.distance ? a.distance < b.distance : a.query_index < b.query_index;
                     });
    matches.resize(max_matches_);
  }
  std::sort(matches.begin(), matches.end(),
            [](const sift::Match& a, const sift::Match& b) { return a.query_index < b.query_index; });
  // Only the matched db keypoints are dequantised, into a compact array the matches index.
  db_keypoints.resize(matches.size());
  for (size_t m = 0; m < matches.size(); ++m) {
    db_keypoints[m] = db.keypoint(matches[m].db_index);
    matches[m].db_index = static_cast<uint32_t>(m);
  }
  return sift::VerifyHoughAffine(keypoints_, db_keypoints, matches, region_, {db.width(), db.height()}, options);
}

}  // namespace oxbow::index
