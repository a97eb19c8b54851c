// The search pipeline, written once for a single index and for a cluster (see source.h):
//   1. tf-idf scoring of the query's words, then the Hamming-embedding re-scoring of the shortlist;
//   2. spatial re-ranking of the top rerank_depth;
//   3. query expansion over the verified results;
//   4. transitive verification against the regions the verified results matched.
// The method and the meaning of every option: index/image_index.h ("Method") and QueryOptions.
#pragma once

#include <array>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "index/search/source.h"
#include "sift/base/error.h"
#include "sift/types.h"
#include "vocab/vocabulary.h"

namespace oxbow::index::search {

// The query's features inside `region` (all without one), appended: at most max_features of them
// (0 = all), the strongest by |response|, ties by index, in their order.
void SelectInRegion(const sift::FeatureSet& features, const std::optional<std::array<float, 4>>& region,
                    size_t max_features, std::vector<sift::Keypoint>* keypoints, std::vector<float>* descriptors);

// The features of an image query inside options.region, at most options.max_query_features of them
// (the strongest by |DoG response|, ties by index, kept in their order), quantised with
// `quantizer` (its num_probes replaced by options.quantizer_probes), with options.query_assignments
// soft words, and with Hamming-embedding signatures when options.hamming and the vocabulary has them.
// `query` must have been checked against the vocabulary (descriptor kind, sizes).
QueryFeatures PrepareQuery(const sift::FeatureSet& query, const vocab::Vocabulary& vocabulary,
                           const QueryOptions& options, vocab::QuantizerOptions quantizer);

// An indexed image's stored features inside options.region (all without one) as a query, with their
// signatures when options.hamming: what QuerySimilar searches with. kNotFound for an unknown id.
// *record receives the image's catalogue record.
[[nodiscard]] Result<QueryFeatures> StoredQuery(Source& source, const std::string& id, const QueryOptions& options,
                                                ImageRecord* record);

// Runs the stages over `source`. `timings` arrives with the preparation's (quantize_ms) and leaves
// with every stage's; total_ms is the caller's.
[[nodiscard]] Result<QueryResponse> Run(Source& source, const QueryFeatures& query, const QueryOptions& options,
                                        QueryTimings timings);

// Query expansion's vector: the L2-normalised average of the query's tf-idf vector and the regions'
// (added in order), restricted to the 2 x terms.size() strongest words.
std::vector<QueryTerm> ExpandedQuery(std::span<const QueryTerm> terms, std::span<const std::vector<QueryTerm>> regions);

// outer(inner(p)): the affine map that applies `inner` first (a transitively verified result's
// db_from_query: its own map from the anchor composed with the anchor's).
sift::Affine2D Compose(const sift::Affine2D& outer, const sift::Affine2D& inner);

}  // namespace oxbow::index::search
