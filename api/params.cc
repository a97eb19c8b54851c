#include "api/params.h"

#include <charconv>
#include <cmath>
#include <cstdlib>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "api/filter.h"
#include "api/json.h"
#include "sift/base/log.h"

namespace oxbow::api {

namespace {

std::string Quote(std::string_view text) {
  constexpr size_t kMaxShown = 64;  // do not echo a huge parameter back
  std::string shown(text.substr(0, kMaxShown));
  if (text.size() > kMaxShown) shown += "...";
  return "'" + shown + "'";
}

// `text` as a number when all of it is one (strtod's syntax: "nan" and "inf" included, the callers
// check the range); nullopt for an empty text or trailing characters.
std::optional<double> WholeNumber(const std::string& text) {
  if (text.empty()) return std::nullopt;
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (end != text.c_str() + text.size()) return std::nullopt;
  return v;
}

const std::string* Find(const Params& params, const std::string& name) {
  auto it = params.find(name);
  return it == params.end() ? nullptr : &it->second;
}

}  // namespace

Result<int64_t> ParseInt(std::string_view name, std::string_view text, int64_t min, int64_t max) {
  int64_t value = 0;
  const char* begin = text.data();
  const char* end = text.data() + text.size();
  if (!text.empty() && text.front() == '+') ++begin;
  auto [ptr, ec] = std::from_chars(begin, end, value);
  if (!text.empty() && ec == std::errc::result_out_of_range && ptr == end) {  // an integer, beyond 64 bits
    return Fail(ErrorCode::kInvalidArgument, "parameter '" + std::string(name) + "' must be in [" + std::to_string(min) +
                                                 ", " + std::to_string(max) + "], got " + Quote(text));
  }
  if (text.empty() || ec != std::errc() || ptr != end) {
    return Fail(ErrorCode::kInvalidArgument,
                "parameter '" + std::string(name) + "' must be an integer, got " + Quote(text));
  }
  if (value < min || value > max) {
    return Fail(ErrorCode::kInvalidArgument, "parameter '" + std::string(name) + "' must be in [" +
                                                 std::to_string(min) + ", " + std::to_string(max) + "], got " +
                                                 std::to_string(value));
  }
  return value;
}

Result<bool> ParseBool(std::string_view name, std::string_view text) {
  if (text.empty() || text == "true" || text == "1" || text == "yes" || text == "on") return true;
  if (text == "false" || text == "0" || text == "no" || text == "off") return false;
  return Fail(ErrorCode::kInvalidArgument,
              "parameter '" + std::string(name) + "' must be true or false (or 1/0, yes/no, on/off; empty is "
              "true), got " + Quote(text));
}

Result<std::array<float, 4>> ParseBox(std::string_view name, std::string_view text) {
  std::array<float, 4> box{};
  const std::string bad = "parameter '" + std::string(name) + "' must be x1,y1,x2,y2 (pixels, x1 < x2, y1 < y2), got " + Quote(text);
  size_t start = 0;
  for (int i = 0; i < 4; ++i) {
    const size_t comma = text.find(',', start);
    const bool last = i == 3;
    if (last != (comma == std::string_view::npos)) return Fail(ErrorCode::kInvalidArgument, bad);
    const std::string part(text.substr(start, last ? std::string_view::npos : comma - start));
    const std::optional<double> v = WholeNumber(part);
    if (!v || !std::isfinite(*v) || std::abs(*v) > 1e9) return Fail(ErrorCode::kInvalidArgument, bad);
    box[static_cast<size_t>(i)] = static_cast<float>(*v);
    start = comma + 1;
  }
  if (!(box[0] < box[2]) || !(box[1] < box[3])) return Fail(ErrorCode::kInvalidArgument, bad);
  return box;
}

Status CheckKnownParams(const Params& params, const std::set<std::string>& known) {
  for (auto it = params.begin(); it != params.end(); ++it) {
    const std::string& name = it->first;
    if (const size_t n = params.count(name); n > 1) {
      return Fail(ErrorCode::kInvalidArgument, "parameter " + Quote(name) + " is given " + std::to_string(n) +
                                                   " times (query string and multipart fields together); give it once");
    }
    if (known.contains(name)) continue;
    std::string list;
    for (const auto& k : known) list += (list.empty() ? "" : ", ") + k;
    return Fail(ErrorCode::kInvalidArgument, "unknown parameter " + Quote(name) + "; known: " + list);
  }
  return Ok();
}

namespace {

// The integer search parameters that map straight onto one QueryOptions field, with their ranges.
struct IntQueryParam {
  const char* name;
  int64_t min;
  int64_t max;
  int index::QueryOptions::*field;
};
constexpr IntQueryParam kIntQueryParams[] = {
    {"top_k", 1, 10000, &index::QueryOptions::top_k},
    {"qe_images", 1, 100, &index::QueryOptions::qe_images},
    {"max_pairs_per_word", 1, 100, &index::QueryOptions::max_pairs_per_word},
    {"transitive_depth", 0, 10000, &index::QueryOptions::transitive_depth},
    {"transitive_anchors", 1, 1000, &index::QueryOptions::transitive_anchors},
    {"transitive_neighbours", 1, 10000, &index::QueryOptions::transitive_neighbours},
    {"transitive_attempts", 1, 1000, &index::QueryOptions::transitive_attempts},
    {"query_assignments", 1, 8, &index::QueryOptions::query_assignments},
    {"quantizer_probes", 1, 4096, &index::QueryOptions::quantizer_probes},
    {"max_query_features", 0, 1000000, &index::QueryOptions::max_query_features},
    {"max_tentative_matches", 0, 1000000, &index::QueryOptions::max_tentative_matches},
    {"max_scored_postings", 0, 2000000000, &index::QueryOptions::max_scored_postings},
    {"asmk_weight", 0, 1000, &index::QueryOptions::asmk_weight},
    {"qe_asmk_weight", 0, 1000, &index::QueryOptions::qe_asmk_weight},
};

}  // namespace

const std::set<std::string>& QueryParamNames() {
  static const std::set<std::string> names = [] {
    std::set<std::string> n = {"rerank", "bbox", "qe", "min_inliers", "filter", "hamming", "hamming_norm_exponent"};
    for (const IntQueryParam& p : kIntQueryParams) n.insert(p.name);
    return n;
  }();
  return names;
}

Result<index::QueryOptions> ParseQueryParams(const Params& params, const index::QueryOptions& defaults) {
  if (auto known = CheckKnownParams(params, QueryParamNames()); !known) return std::unexpected(known.error());
  index::QueryOptions options = defaults;
  for (const IntQueryParam& p : kIntQueryParams) {
    if (const auto* v = Find(params, p.name)) {
      auto parsed = ParseInt(p.name, *v, p.min, p.max);
      if (!parsed) return std::unexpected(parsed.error());
      options.*p.field = static_cast<int>(*parsed);
    }
  }
  if (const auto* v = Find(params, "min_inliers")) {
    auto parsed = ParseInt("min_inliers", *v, 3, 1000000);
    if (!parsed) return std::unexpected(parsed.error());
    options.verify.min_inliers = static_cast<int>(*parsed);
  }
  if (const auto* v = Find(params, "hamming_norm_exponent")) {
    const std::optional<double> e = WholeNumber(*v);
    if (!e || !(*e >= 0 && *e <= 1)) {
      return Fail(ErrorCode::kInvalidArgument,
                  "parameter 'hamming_norm_exponent' must be a number in [0, 1], got " + Quote(*v));
    }
    options.hamming_norm_exponent = *e;
  }
  if (const auto* v = Find(params, "rerank")) {
    if (*v == "true" || *v == "false" || *v == "yes" || *v == "no" || *v == "on" || *v == "off") {
      options.rerank_depth = (*v == "false" || *v == "no" || *v == "off") ? 0 : (defaults.rerank_depth > 0 ? defaults.rerank_depth : index::QueryOptions{}.rerank_depth);
    } else {
      auto parsed = ParseInt("rerank", *v, 0, 10000);
      if (!parsed) return std::unexpected(parsed.error());
      options.rerank_depth = static_cast<int>(*parsed);
    }
  }
  if (const auto* v = Find(params, "bbox")) {
    auto parsed = ParseBox("bbox", *v);
    if (!parsed) return std::unexpected(parsed.error());
    options.region = *parsed;
  }
  if (const auto* v = Find(params, "filter")) {
    auto parsed = ParseFilter(*v, "parameter 'filter'");
    if (!parsed) return std::unexpected(parsed.error());
    options.filter = std::move(*parsed);
  }
  const auto* qe_param = Find(params, "qe");
  if (qe_param != nullptr) {
    auto parsed = ParseBool("qe", *qe_param);
    if (!parsed) return std::unexpected(parsed.error());
    options.query_expansion = *parsed;
  }
  if (const auto* v = Find(params, "hamming")) {
    auto parsed = ParseBool("hamming", *v);
    if (!parsed) return std::unexpected(parsed.error());
    options.hamming = *parsed;
  }
  if (options.query_expansion && options.rerank_depth == 0) {
    // QE averages verified results, so it needs re-ranking. Asked for explicitly, that is an error;
    // coming from the server's default (on), it simply does not apply to a tf-idf-only search.
    if (qe_param != nullptr) {
      return Fail(ErrorCode::kInvalidArgument, "parameter 'qe' needs re-ranking: set rerank > 0 (or leave it at its default)");
    }
    options.query_expansion = false;
  }
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, *message);
  return options;
}

Status CheckImageId(std::string_view id) {
  if (id.empty() || id.size() > 256) {
    return Fail(ErrorCode::kInvalidArgument, "image id must be 1 to 256 bytes long, got " + std::to_string(id.size()));
  }
  for (unsigned char c : id) {
    if (c < 0x20 || c == 0x7f) return Fail(ErrorCode::kInvalidArgument, "image id must not contain control characters");
  }
  // Ids come back in JSON bodies, which hold UTF-8 only: another byte sequence could not be returned as
  // it was given (the server would answer with U+FFFD in its place).
  if (!log::IsWellFormedUtf8(id)) return Fail(ErrorCode::kInvalidArgument, "image id must be valid UTF-8");
  return Ok();
}

Result<std::string> ParseMetadata(std::string_view text, std::string_view label) {
  // Both limits before parsing: the parse is linear, but the dump below recurses once per level.
  if (text.size() > kMaxMetadataBytes) {
    return Fail(ErrorCode::kInvalidArgument, std::string(label) + " must be at most " + std::to_string(kMaxMetadataBytes) +
                                                 " bytes, got " + std::to_string(text.size()));
  }
  if (JsonNestingDepth(text) > kMaxJsonDepth) {
    return Fail(ErrorCode::kInvalidArgument, std::string(label) + " must nest arrays and objects at most " +
                                                 std::to_string(kMaxJsonDepth) + " levels deep");
  }
  auto json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded()) {
    return Fail(ErrorCode::kInvalidArgument, std::string(label) + " must be a JSON document, got " + Quote(text));
  }
  return json.dump();
}

Result<AddParams> ParseAddParams(const Params& params) {
  if (auto known = CheckKnownParams(params, {"id", "replace", "metadata"}); !known) return std::unexpected(known.error());
  AddParams add;
  const auto* id = Find(params, "id");
  if (id == nullptr) {
    return Fail(ErrorCode::kInvalidArgument, "parameter 'id' is required (POST /v1/images?id=NAME, or a multipart field 'id')");
  }
  if (auto ok = CheckNewImageId(*id); !ok) return std::unexpected(ok.error());
  add.id = *id;
  if (const auto* v = Find(params, "replace")) {
    auto parsed = ParseBool("replace", *v);
    if (!parsed) return std::unexpected(parsed.error());
    add.replace = *parsed;
  }
  if (const auto* v = Find(params, "metadata")) {
    auto metadata = ParseMetadata(*v, "parameter 'metadata'");
    if (!metadata) return std::unexpected(metadata.error());
    add.metadata_json = std::move(*metadata);
  }
  return add;
}

Status CheckNewImageId(std::string_view id) {
  if (auto ok = CheckImageId(id); !ok) return ok;
  // Not in CheckImageId, which GET and DELETE use too: an image stored before a rule stays reachable
  // (GET /v1/images/a%2Fsimilar, the slash encoded; GET /v1/images/batch).
  if (id.ends_with("/similar") || id.ends_with("/thumbnail")) {
    return Fail(ErrorCode::kInvalidArgument, "image id must not end in '/similar' or '/thumbnail' (the routes "
                                             "GET /v1/images/{id}/similar and /thumbnail), got " + Quote(id));
  }
  if (id == "batch") {
    return Fail(ErrorCode::kInvalidArgument, "image id must not be 'batch' (the route POST /v1/images/batch)");
  }
  return Ok();
}

Result<std::vector<BatchAddItem>> ParseBatchAddParams(const std::vector<std::string>& ids,
                                                      const std::vector<std::string>& metadata, size_t images,
                                                      const Params& others) {
  if (!others.empty()) {
    return Fail(ErrorCode::kInvalidArgument, "unknown parameter " + Quote(others.begin()->first) +
                                                 "; POST /v1/images/batch takes only multipart parts 'image', 'id' "
                                                 "and 'metadata'");
  }
  if (images == 0) {
    return Fail(ErrorCode::kInvalidArgument, "no 'image' part: send one multipart part 'image' per image");
  }
  if (ids.size() != images) {
    return Fail(ErrorCode::kInvalidArgument, std::to_string(ids.size()) + " 'id' parts for " + std::to_string(images) +
                                                 " 'image' parts: give one id per image, in the same order");
  }
  if (!metadata.empty() && metadata.size() != images) {
    return Fail(ErrorCode::kInvalidArgument, std::to_string(metadata.size()) + " 'metadata' parts for " +
                                                 std::to_string(images) +
                                                 " 'image' parts: give none, or one per image in the same order "
                                                 "(an empty part for an image without metadata)");
  }
  std::vector<BatchAddItem> items(images);
  for (size_t i = 0; i < images; ++i) {
    items[i].id = ids[i];
    if (auto ok = CheckNewImageId(ids[i]); !ok) {
      items[i].status = ok;
      continue;
    }
    if (metadata.empty() || metadata[i].empty()) continue;
    auto parsed = ParseMetadata(metadata[i], "metadata part " + std::to_string(i + 1));
    if (parsed) {
      items[i].metadata_json = std::move(*parsed);
    } else {
      items[i].status = std::unexpected(parsed.error());
    }
  }
  return items;
}

Result<ListParams> ParseListParams(const Params& params) {
  if (auto known = CheckKnownParams(params, {"offset", "limit"}); !known) return std::unexpected(known.error());
  ListParams list;
  if (const auto* v = Find(params, "offset")) {
    auto parsed = ParseInt("offset", *v, 0, int64_t{1} << 53);
    if (!parsed) return std::unexpected(parsed.error());
    list.offset = static_cast<uint64_t>(*parsed);
  }
  if (const auto* v = Find(params, "limit")) {
    auto parsed = ParseInt("limit", *v, 1, 1000);
    if (!parsed) return std::unexpected(parsed.error());
    list.limit = static_cast<uint64_t>(*parsed);
  }
  return list;
}

Result<MatchParams> ParseMatchParams(const Params& params) {
  if (auto known = CheckKnownParams(params, {"model", "ratio", "mutual", "method", "min_inliers", "correspondences"});
      !known) {
    return std::unexpected(known.error());
  }
  MatchParams match;
  if (const auto* v = Find(params, "model")) {
    auto model = sift::ParseGeometricModel(*v);
    if (!model) {
      return Fail(ErrorCode::kInvalidArgument,
                  "parameter 'model' must be hough-homography, hough-affine, similarity, affine, homography or fundamental, got " + Quote(*v));
    }
    match.model = *model;
  }
  if (const auto* v = Find(params, "ratio")) {
    const std::optional<double> ratio = WholeNumber(*v);
    if (!ratio || !(*ratio > 0 && *ratio <= 1)) {
      return Fail(ErrorCode::kInvalidArgument, "parameter 'ratio' must be a number in (0, 1], got " + Quote(*v));
    }
    match.match.ratio = static_cast<float>(*ratio);
  }
  if (const auto* v = Find(params, "mutual")) {
    auto parsed = ParseBool("mutual", *v);
    if (!parsed) return std::unexpected(parsed.error());
    match.match.mutual = *parsed;
  }
  if (const auto* v = Find(params, "method")) {
    if (*v == "brute") {
      match.match.method = sift::MatchOptions::Method::kBruteForce;
    } else if (*v == "kdtree") {
      match.match.method = sift::MatchOptions::Method::kKdForest;
    } else {
      return Fail(ErrorCode::kInvalidArgument, "parameter 'method' must be brute or kdtree, got " + Quote(*v));
    }
  }
  if (const auto* v = Find(params, "min_inliers")) {
    auto parsed = ParseInt("min_inliers", *v, 3, 1000000);
    if (!parsed) return std::unexpected(parsed.error());
    match.min_inliers = static_cast<int>(*parsed);
  }
  if (const auto* v = Find(params, "correspondences")) {
    auto parsed = ParseBool("correspondences", *v);
    if (!parsed) return std::unexpected(parsed.error());
    match.correspondences = *parsed;
  }
  if (auto message = match.match.Check()) return Fail(ErrorCode::kInvalidArgument, *message);
  return match;
}

}  // namespace oxbow::api
