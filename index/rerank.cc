#include "index/rerank.h"

#include <algorithm>
#include <numeric>

#include "sift/match.h"

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
  std::vector<sift::Match> matches;
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
        // Pairs from a word seen once on each side are the most reliable: smallest "distance".
        const auto distance = static_cast<float>(cq * cd);
        for (size_t a = i; a < i2; ++a) {
          for (size_t b = j; b < j2; ++b) matches.push_back({order_[a], static_cast<uint32_t>(b), distance});
        }
      }
      i = i2;
      j = j2;
    }
  }
  if (matches.size() < 3) return {};
  const std::vector<sift::Match> unique = sift::EnforceOneToOne(matches);
  // Only the matched db keypoints are dequantised; the verifier reads keypoints by match index.
  std::vector<sift::Keypoint> db_keypoints(nd);
  for (const sift::Match& m : unique) db_keypoints[m.db_index] = db.keypoint(m.db_index);
  return sift::VerifyHoughAffine(keypoints_, db_keypoints, unique, region_, {db.width(), db.height()}, options);
}

}  // namespace oxbow::index
