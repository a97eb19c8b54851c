#include "index/rerank.h"

#include <algorithm>
#include <numeric>
#include <vector>

namespace oxbow::index {

QueryGeometry::QueryGeometry(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                             const std::array<float, 4>& region)
    : keypoints_(keypoints), words_(words), order_(words.size()), region_(region) {
  OXBOW_CHECK(keypoints.size() == words.size());
  std::iota(order_.begin(), order_.end(), 0u);
  std::stable_sort(order_.begin(), order_.end(), [&](uint32_t a, uint32_t b) { return words_[a] < words_[b]; });
}

sift::VerificationResult QueryGeometry::Verify(const PackedFeatures& db, int max_pairs_per_word,
                                               const sift::HoughVerifyOptions& options) const {
  // Scratch reused by every call on this thread: a re-ranking pass verifies hundreds of candidates.
  thread_local std::vector<sift::Match> matches;
  thread_local std::vector<sift::Keypoint> db_keypoints;
  matches.clear();
  size_t i = 0, j = 0;
  const size_t nq = order_.size(), nd = db.size();
  const auto limit = static_cast<size_t>(max_pairs_per_word);
  while (i < nq && j < nd) {
    const uint32_t wq = words_[order_[i]], wd = db.word(j);
    if (wq < wd) {
      ++i;
    } else if (wd < wq) {
      ++j;
    } else {
      size_t i2 = i, j2 = j;
      while (i2 < nq && words_[order_[i2]] == wq) ++i2;
      while (j2 < nd && db.word(j2) == wd) ++j2;
      const size_t cq = i2 - i, cd = j2 - j;
      if (cq <= limit && cd <= limit) {
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
      i = i2;
      j = j2;
    }
  }
  // Inliers are a subset of the one-to-one matches: with fewer than min_inliers of them the candidate
  // cannot verify, so the verifier is not run (same result, no cost).
  if (matches.size() < static_cast<size_t>(std::max(3, options.min_inliers))) return {};
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
