// Request parameters of the HTTP API, parsed and validated without any HTTP library: the transport
// collects query-string parameters and multipart text fields into a Params multimap (name -> every
// value given), these functions turn it into typed options or a kInvalidArgument error naming the
// parameter. Unknown parameter names are refused (a typo such as `topk` would otherwise silently run
// with the default), and so is a name given more than once (`top_k=5&top_k=500000`, or once in the
// query string and once as a multipart field): which value was meant cannot be known. Thread-safe
// (pure functions).
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "api/pair_match.h"
#include "index/image_index.h"
#include "sift/base/error.h"
#include "sift/verify.h"

namespace oxbow::api {

using Params = std::multimap<std::string, std::string>;

// ---- Scalars (exposed for tests and the transport) ------------------------------------------------

// Whole decimal integer in [min, max], no sign for min >= 0, no trailing characters.
[[nodiscard]] Result<int64_t> ParseInt(std::string_view name, std::string_view text, int64_t min, int64_t max);
// true|false|1|0|yes|no|on|off (case-sensitive lower case); "" counts as true (`?qe` alone).
[[nodiscard]] Result<bool> ParseBool(std::string_view name, std::string_view text);
// "x1,y1,x2,y2", four finite numbers with x1 < x2 and y1 < y2 (pixels).
[[nodiscard]] Result<std::array<float, 4>> ParseBox(std::string_view name, std::string_view text);

// Refuses a parameter given more than once (message names it), then any parameter whose name is not in
// `known` (message lists the known ones).
[[nodiscard]] Status CheckKnownParams(const Params& params, const std::set<std::string>& known);

// ---- Routes ---------------------------------------------------------------------------------------

// POST /v1/search, GET /v1/images/{id}/similar:
//   top_k      [1, 10000]            QueryOptions::top_k
//   rerank     [0, 10000] | true | false   QueryOptions::rerank_depth (false = 0, true = the default depth)
//   bbox       x1,y1,x2,y2           QueryOptions::region (query-image pixels)
//   qe         bool                  QueryOptions::query_expansion
//   qe_images  [1, 100]              QueryOptions::qe_images
//   min_inliers            [3, 1000000]  QueryOptions::verify.min_inliers
//   max_pairs_per_word     [1, 100]      QueryOptions::max_pairs_per_word
//   transitive_depth       [0, 10000]    QueryOptions::transitive_depth (0 = off)
//   transitive_anchors     [1, 1000]     QueryOptions::transitive_anchors
//   transitive_neighbours  [1, 10000]    QueryOptions::transitive_neighbours
//   transitive_attempts    [1, 1000]     QueryOptions::transitive_attempts
//   query_assignments      [1, 8]        QueryOptions::query_assignments
//   quantizer_probes       [1, 4096]     QueryOptions::quantizer_probes
//   max_query_features     [0, 1000000]  QueryOptions::max_query_features (0 = all)
//   max_tentative_matches  [0, 1000000]  QueryOptions::max_tentative_matches (0 = no limit)
//   max_scored_postings    [0, 2000000000]  QueryOptions::max_scored_postings (0 = no limit)
//   hamming                bool          QueryOptions::hamming
//   asmk_weight            [0, 1000]     QueryOptions::asmk_weight (0 = off)
//   qe_asmk_weight         [0, 1000]     QueryOptions::qe_asmk_weight (0 = off)
//   hamming_norm_exponent  [0, 1]        QueryOptions::hamming_norm_exponent
//   filter     a JSON object over the image metadata (api/filter.h)  QueryOptions::filter
// Starts from `defaults`; the result passes QueryOptions::Check().
[[nodiscard]] Result<index::QueryOptions> ParseQueryParams(const Params& params, const index::QueryOptions& defaults);
const std::set<std::string>& QueryParamNames();

// POST /v1/images: id (required, CheckNewImageId), replace (bool, default false), metadata (a JSON document of at most kMaxMetadataBytes nested at most
// kMaxJsonDepth deep (api/json.h), both checked before it is parsed; default none; stored re-serialised
// compactly).
inline constexpr size_t kMaxMetadataBytes = 16 * 1024;  // fixed; every search result carries it
struct AddParams {
  std::string id;
  bool replace = false;
  std::string metadata_json;  // "" when absent
};
[[nodiscard]] Result<AddParams> ParseAddParams(const Params& params);
// The id of a new image: CheckImageId, and none that another route would take for its own: ids ending
// in "/similar" or "/thumbnail" (GET /v1/images/{id}/similar and /thumbnail) and "batch" (POST
// /v1/images/batch). Only new ids: one stored before these rules stays reachable by GET and DELETE.
[[nodiscard]] Status CheckNewImageId(std::string_view id);

// POST /v1/images/batch: the multipart parts named `id` (one per image, in the order of the `image`
// parts) and `metadata` (none, or one per image in that order; an empty part = no metadata), plus every
// other parameter (`others`: query string and other text parts), of which there must be none. A count
// that does not match the images' refuses the request (kInvalidArgument); a bad id or metadata document
// is that image's own error (BatchAddItem::status), the others go on.
struct BatchAddItem {
  std::string id;
  std::string metadata_json;  // "" when absent
  Status status = Ok();        // why this image is refused, else Ok
};
[[nodiscard]] Result<std::vector<BatchAddItem>> ParseBatchAddParams(const std::vector<std::string>& ids,
                                                                    const std::vector<std::string>& metadata,
                                                                    size_t images, const Params& others);
// A metadata document (the rules of AddParams::metadata_json), re-serialised compactly; kInvalidArgument
// naming the broken rule, the value called `label` ("parameter 'metadata'", "--metadata"). Shared by
// POST /v1/images and `oxbow index add --metadata`.
[[nodiscard]] Result<std::string> ParseMetadata(std::string_view text, std::string_view label);

// GET /v1/images: offset [0, 2^53] (default 0), limit [1, 1000] (default 100).
struct ListParams {
  uint64_t offset = 0;
  uint64_t limit = 100;
};
[[nodiscard]] Result<ListParams> ParseListParams(const Params& params);

// POST /v1/match: model (hough-homography|hough-affine|similarity|affine|homography|fundamental, default
// PairMatchOptions's: hough-homography),
// ratio (0, 1], mutual (bool), method (brute|kdtree), min_inliers [3, 1000000] (default 6, as search),
// correspondences (bool, default false: return the inlier pairs).
struct MatchParams {
  sift::GeometricModel model = PairMatchOptions{}.model;
  sift::MatchOptions match;
  int min_inliers = PairMatchOptions{}.min_inliers;
  bool correspondences = false;
};
[[nodiscard]] Result<MatchParams> ParseMatchParams(const Params& params);

// Checks an image id as the index does (1..256 bytes, no control characters), with a message.
[[nodiscard]] Status CheckImageId(std::string_view id);

}  // namespace oxbow::api
