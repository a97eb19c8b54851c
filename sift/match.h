// Descriptor matching: nearest neighbours in descriptor space with Lowe's ratio test, an optional
// mutual (cross) check, and one-to-one enforcement.
//
// Maths. SIFT and RootSIFT descriptors are unit-L2-norm 128-vectors (see types.h), so the squared
// Euclidean distance is ||q - d||^2 = 2 - 2 q.d and the nearest neighbour is the descriptor with the
// largest dot product. The exact matcher computes a blocked matrix product Q D^T (AVX2/FMA when compiled
// with it, a scalar loop computing the same sums otherwise) and keeps the two best neighbours per query.
// The approximate matcher uses FLANN randomised kd-trees (Silpa-Anan & Hartley 2008; Muja & Lowe 2009):
// `kd_trees` trees built over the db descriptors, `kd_checks` leaves visited per query. We use the FLANN
// copy inside OpenCV (cvflann) rather than libflann 1.9: libflann 1.9 shuffles with std::random_device
// when it builds trees, so its results change from run to run; cvflann draws from cv::theRNG(), which
// we seed with `kd_seed` (thread-local, restored afterwards), so the forest and the matches are
// reproducible.
//
// Ratio test (Lowe 2004, sec. 7.1): a query feature is matched to its nearest db feature only when
// dist(nearest) < ratio * dist(second nearest); Lowe found 0.8 removes 90% of false matches while
// losing under 5% of the correct ones. With fewer than two db features the ratio test cannot be applied
// and the query feature gets no match (unless ratio == 1, which disables the test).
//
// Mutual check: the match q -> d is kept only if q is also d's nearest neighbour among the query
// features (searched with the same method: exactly, or with a kd-forest over the query descriptors; no
// ratio test on the reverse side).
//
// One-to-one (after the above): when several query features matched the same db feature only the
// closest is kept (without it, spatial verification lowers Oxford mAP, as COLMAP found: colmap/colmap#288).
//
// Usage:
//   auto matches = MatchDescriptors(query_features, db_features, {.ratio = 0.8f});
//   if (!matches) return matches.error();
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "sift/base/error.h"
#include "sift/types.h"

namespace oxbow::sift {

// A tentative correspondence between feature `query_index` of the query FeatureSet and feature
// `db_index` of the db FeatureSet.
struct Match {
  uint32_t query_index = 0;  // index into the query FeatureSet's keypoints / descriptor rows
  uint32_t db_index = 0;     // index into the db FeatureSet's keypoints / descriptor rows
  float distance = 0;        // Euclidean (L2, not squared) descriptor distance, in [0, 2] for unit vectors

  friend bool operator==(const Match&, const Match&) = default;
};

struct MatchOptions {
  enum class Method {
    kBruteForce,  // exact: blocked dot products over all pairs, O(|Q| |D| 128); best below ~10k x 10k
    kKdForest,    // approximate: FLANN randomised kd-trees; O(|D| log |D|) build, ~kd_checks per query
  };
  // --- Behaviour
  Method method = Method::kBruteForce;  // search algorithm (CLI --method brute|kdtree)
  int kd_trees = 4;     // number of randomised kd-trees, [1, 64]; more trees = better recall, slower build
  int kd_checks = 64;   // leaves visited per query (FLANN `checks`), [1, 1 << 20]; more = better recall
  float ratio = 0.8f;   // Lowe's ratio test threshold on L2 distances, (0, 1]; 1 disables the test
                        // (then a single db feature suffices); Lowe 2004 sec. 7.1 recommends 0.8
  bool mutual = false;  // also require the query feature to be the db feature's nearest neighbour
  bool one_to_one = true;  // keep only the closest match per db feature (query side is unique by design)
  // --- Performance
  int num_threads = 0;  // worker threads for the search, >= 0; 0 means all hardware threads. The result
                        // does not depend on the thread count.
  uint32_t kd_seed = 42;  // seed of FLANN's tree randomisation; fixed so results are reproducible

  // Empty when every field is valid, else a message naming the field and its valid range.
  std::optional<std::string> Check() const;
};

// Matches every query feature against the db features (see the file comment for the rules).
// Returns matches sorted by query_index, at most one per query feature (and per db feature when
// one_to_one). Errors (kInvalidArgument): invalid options; descriptor arrays whose size is not
// keypoints.size() * 128; non-finite descriptor values. Mixing SIFT and RootSIFT sets is an error too:
// their distances are not comparable. Either set empty: an empty result, not an error.
// Deterministic: the same inputs and options give the same matches for any thread count.
// Thread-safe (no shared state). Complexity: see MatchOptions::Method.
[[nodiscard]] Result<std::vector<Match>> MatchDescriptors(const FeatureSet& query, const FeatureSet& db,
                                                          const MatchOptions& options = {});

// Keeps, among `matches`, the best (smallest distance) match for every db feature and then for every
// query feature, so that no query_index and no db_index appears twice. Ties are broken by the smaller
// (query_index, db_index). Result sorted by query_index. O(n log n).
std::vector<Match> EnforceOneToOne(std::span<const Match> matches);

}  // namespace oxbow::sift
