// Spatial verification of one candidate image against a query, through shared visual words
// (Philbin et al. 2007): tentative matches are the query x candidate feature pairs with the same word
// (skipping words with more than max_pairs_per_word features on either side: bursts), made one-to-one
// (sift::EnforceOneToOne; pairs from words seen once on each side preferred), then verified with Lowe's
// Hough/affine verifier (sift::VerifyHoughAffine).
//
// The one-to-one step is done per word while merging (features of different words never share a
// pair), with exactly sift::EnforceOneToOne's result; with fewer one-to-one matches than
// options.min_inliers the verifier is skipped (it could not verify). Only the matched db keypoints are
// dequantised.
//
// With Hamming-embedding signatures on both sides (QueryOptions::hamming), a word's pairs are first
// filtered by the signatures' Hamming distance (at most the threshold: Jegou et al. 2008 use the same
// test to reject tentative matches before verification), then made one-to-one closest signatures first;
// bursty words are not skipped then, since the filter keeps only their plausible pairs (measured on
// groups_hard + distractors, Hamming search without QE: mAP 0.615 -> 0.620, eval/results/accuracy.md). At most
// max_matches of those go to the verifier, the closest signatures first (ties by query feature): an
// unrelated image still shares thousands of words with a large query and passes the loose threshold
// with about half of them, and the verifier's Hough votes for those were most of a transitive pass.
//
// Thread safety: a QueryGeometry is immutable after construction; Verify may run concurrently (its
// scratch buffers are thread-local).
// Cost of Verify: O(|query| + |candidate|) for the merge join, O(m log m) for m matches, plus the
// verifier (O(matches)).
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "index/storage/feature_store.h"
#include "index/search/word_runs.h"
#include "sift/types.h"
#include "sift/verify.h"

namespace oxbow::index {

class QueryGeometry {
 public:
  // keypoints[i] has word words[i] (and signature signatures[i], or no signatures); region x1,y1,x2,y2
  // is the query object (the whole image if unknown). The spans must outlive this object.
  QueryGeometry(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                const std::array<float, 4>& region, std::span<const uint64_t> signatures = {},
                int hamming_threshold = 64, int max_matches = 0);

  // With `overlay`: set to whether the verifier accepted the match and it was then rejected as only an
  // overlay shared by both images (index/search/overlay.h). The result is firm only when the verifier's
  // is and its inliers span an area with any one of them left out (a row of matched letters plus one
  // chance inlier far off it is not), so that it may anchor transitive verification.
  sift::VerificationResult Verify(const PackedFeatures& candidate, int max_pairs_per_word,
                                  const sift::HoughVerifyOptions& options, bool* overlay = nullptr) const;

 private:
  std::span<const sift::Keypoint> keypoints_;
  std::span<const uint32_t> words_;
  std::span<const uint64_t> signatures_;
  int hamming_threshold_;
  size_t max_matches_;                 // with signatures; 0 = no limit
  std::vector<uint32_t> order_;        // feature indices sorted by word
  WordRuns runs_;                      // of the words in order_'s order (positions into order_)
  std::array<float, 4> region_;
};

}  // namespace oxbow::index
