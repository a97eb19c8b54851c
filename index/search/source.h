// Where a search's candidates, stored features and verifications come from.
//
// The search pipeline (index/search/pipeline.h) is written once, against this interface; an
// implementation decides where the images are:
//   - one index's snapshot, in process (ImageIndex::OpenSearch, index/search/snapshot_source.cc), for a single
//     node and for each partition of a cluster;
//   - the partitions of a cluster, reached over gRPC (server/cluster/front.cc), each answering with its
//     own snapshot. Sharding wraps the same search, as faiss's IndexShards wraps an index.
// A Source serves one search: it may keep what one stage read for the next (the features of the
// candidates, the bags of transitive verification's ranking) and is not shared between threads.
//
// Every method works on a batch, so that a source over partitions makes one call per partition per
// stage. Images are named by ImageRef, whose meaning is the source's: an image number for one index, a
// partition and an entry of the source's own id table for a cluster. A ref the source gave out stays
// valid for the life of the source; an image removed meanwhile answers as empty (no features, score
// 0, not verified).
//
// Failures: a method returns an error when the search cannot go on (a partition failed and the
// caller allows no partial answer, or all of them failed). A source that allows partial answers
// answers for the images of the failed partitions as for removed ones and drops them from the end
// result (Source::Answered).
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "index/postings/inverted_file.h"
#include "sift/base/error.h"
#include "sift/types.h"
#include "sift/verify.h"

namespace oxbow::index::search {

// An image as a source names it (see the file comment). Ordered by (part, number).
struct ImageRef {
  uint32_t part = 0;    // the partition (0 for one index)
  uint32_t number = 0;  // the image's number within what `part` means to the source

  auto operator<=>(const ImageRef&) const = default;
};

// A query's features after region selection and quantisation: what every stage reads of the query.
struct QueryFeatures {
  std::vector<sift::Keypoint> keypoints;
  std::vector<uint32_t> words;        // nearest word of each keypoint
  std::vector<uint32_t> soft_words;   // with multiple assignment: distinct words ascending, else empty
  std::vector<float> soft_tf;         // their weighted counts
  std::vector<uint64_t> signatures;   // Hamming-embedding signature of each keypoint, or empty
  int width = 0;                      // the query image's size (its region when none is given)
  int height = 0;
};

// A tf-idf candidate.
struct ScoredRef {
  ImageRef ref;
  std::string id;
  float score = 0;
};

// What tf-idf scoring is asked: the query's bag (words with counts; `tf` empty: one per word, a
// word repeated counts again) or, for query expansion, a finished vector.
struct ScoreInput {
  std::span<const uint32_t> words{};
  std::span<const float> tf{};
  std::span<const QueryTerm> terms{};  // used when `words` is empty
};

struct ScoreOutput {
  std::vector<QueryTerm> terms;      // the L2-normalised tf-idf vector scored
  std::vector<ScoredRef> best;       // best first (ties: the source's order), at most max_results
  uint64_t candidates = 0;           // images with a non-zero score (allowed ones, with a filter)
};

// Features to verify candidates against: the query's, or an anchor's matched region in transitive
// verification. The spans must outlive the call.
struct GeometryQuery {
  std::span<const sift::Keypoint> keypoints{};
  std::span<const uint32_t> words{};        // one per keypoint
  std::span<const uint64_t> signatures{};   // one per keypoint, or empty (no Hamming filtering)
  std::array<float, 4> region = {0, 0, 0, 0};  // x1, y1, x2, y2 of the object in its image
};

// One verification task of a batch: candidate `ref` against the geometries `geometries` (indices into
// the batch's geometries), tried in order until one verifies it.
struct VerifyTask {
  ImageRef ref{};
  std::vector<uint32_t> geometries;
};

// A task's outcome: the geometry that verified it (or the last one tried) and that verification.
struct Verified {
  uint32_t geometry = 0;
  sift::VerificationResult result;
  bool overlay = false;  // that geometry's match was rejected as only an overlay (QueryGeometry::Verify)
};

// An image's stored features inside a region, as a search reads them.
struct RegionFeatures {
  std::vector<sift::Keypoint> keypoints;
  std::vector<uint32_t> words;        // one per keypoint
  std::vector<uint64_t> signatures;   // one per keypoint, or empty (the image has none, or not asked)
  std::vector<uint32_t> all_words;    // with FeaturesRequest::all_words: every word inside the region
};

struct FeaturesRequest {
  // At most this many features (0 = all): those of the rarest words (highest idf, ties by feature
  // order), in feature order. all_words still lists every word inside the region.
  size_t max_features = 0;
  bool signatures = false;   // with Hamming-embedding signatures, where the image has them
  bool all_words = false;    // fill RegionFeatures::all_words
};

class Source {
 public:
  virtual ~Source() = default;

  // The image called `id`, or nullopt when there is none (kNotFound is not an error here).
  [[nodiscard]] virtual Result<std::optional<ImageRef>> Find(const std::string& id) = 0;

  // TF-IDF scoring (InvertedFile::Score) over every image `filter` allows (options.filter; null: all),
  // with options.max_scored_postings as the posting budget: the best `max_results`.
  [[nodiscard]] virtual Result<ScoreOutput> Score(const ScoreInput& input, size_t max_results,
                                                  const QueryOptions& options) = 0;

  // Asks for the features of `refs` to be read ahead (a hint; stages follow in this order).
  virtual void Prefetch(std::span<const ScoredRef> refs) = 0;

  // The Hamming-embedding score (index/hamming.h) of each image against query features `words` with
  // `signatures`, or NaN for an image stored without signatures. The first call of a search may keep
  // the images' features for the later stages.
  [[nodiscard]] virtual Result<std::vector<double>> HammingScores(std::span<const uint32_t> words,
                                                                  std::span<const uint64_t> signatures,
                                                                  std::span<const ImageRef> refs,
                                                                  const QueryOptions& options) = 0;

  // Spatial verification (index/rerank.h) of each task, with options.max_pairs_per_word,
  // options.verify and, where the geometry has signatures, options.hamming_threshold and
  // options.max_tentative_matches. A task stops at its first geometry that verifies it.
  [[nodiscard]] virtual Result<std::vector<Verified>> Verify(std::span<const GeometryQuery> geometries,
                                                            std::span<const VerifyTask> tasks,
                                                            const QueryOptions& options) = 0;

  // The stored features of each image inside its region (regions[i] for refs[i]).
  [[nodiscard]] virtual Result<std::vector<RegionFeatures>> Features(std::span<const ImageRef> refs,
                                                                     std::span<const std::array<float, 4>> regions,
                                                                     const FeaturesRequest& request) = 0;

  // The L2-normalised tf-idf vector of each image's features inside its region (query expansion).
  [[nodiscard]] virtual Result<std::vector<std::vector<QueryTerm>>> RegionTerms(
      std::span<const ImageRef> refs, std::span<const std::array<float, 4>> regions) = 0;

  // Transitive verification's ranking: the images `refs`, whose bags the source keeps until the next
  // call; then ScoreAmong gives, per query bag (words, one per feature), its tf-idf score against
  // each of them (InvertedFile::Subset), in order.
  [[nodiscard]] virtual Status RankAmong(std::span<const ImageRef> refs) = 0;
  [[nodiscard]] virtual Result<std::vector<std::vector<float>>> ScoreAmong(
      std::span<const std::vector<uint32_t>> queries) = 0;

  // The catalogue records of `refs` (the results), in order.
  [[nodiscard]] virtual Result<std::vector<ImageRecord>> Records(std::span<const ImageRef> refs) = 0;

  // False for an image of a partition that failed during the search (a partial answer leaves it out).
  [[nodiscard]] virtual bool Answered(const ImageRef& /*ref*/) const { return true; }
};

}  // namespace oxbow::index::search
