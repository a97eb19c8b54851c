#include "api/json.h"

#include <algorithm>
#include <cstdio>

namespace oxbow::api {

int JsonNestingDepth(std::string_view text, int stop_above) {
  int depth = 0;
  int deepest = 0;
  bool in_string = false;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (in_string) {
      if (c == '\\') {
        ++i;  // the escaped character, which may be a quote
      } else if (c == '"') {
        in_string = false;
      }
    } else if (c == '"') {
      in_string = true;
    } else if (c == '[' || c == '{') {
      deepest = std::max(deepest, ++depth);
      if (deepest > stop_above) break;
    } else if (c == ']' || c == '}') {
      depth = std::max(depth - 1, 0);
    }
  }
  return deepest;
}

nlohmann::json MetadataToJson(const std::string& metadata_json) {
  if (metadata_json.empty()) return nullptr;
  if (JsonNestingDepth(metadata_json) > kMaxJsonDepth) return metadata_json;
  auto parsed = nlohmann::json::parse(metadata_json, nullptr, /*allow_exceptions=*/false);
  if (parsed.is_discarded()) return metadata_json;
  return parsed;
}

nlohmann::json ImageRecordToJson(const index::ImageRecord& record) {
  return {{"id", record.id},
          {"width", record.width},
          {"height", record.height},
          {"features", record.num_features},
          {"source", record.source_path},
          {"metadata", MetadataToJson(record.metadata_json)},
          {"added_unix_ms", record.added_unix_ms}};
}

nlohmann::json AddImageResponseToJson(const AddImageResponse& response) {
  nlohmann::json json = ImageRecordToJson(response.record);
  json["replaced"] = response.replaced;
  json["timings_ms"] = {{"decode_extract", response.decode_extract_ms}, {"add", response.add_ms}};
  return json;
}

nlohmann::json ListResponseToJson(const ListResponse& response) {
  nlohmann::json images = nlohmann::json::array();
  for (const auto& record : response.images) images.push_back(ImageRecordToJson(record));
  return {{"images", std::move(images)},
          {"offset", response.offset},
          {"limit", response.limit},
          {"total", response.total}};
}

nlohmann::json SearchResponseToJson(const SearchResponse& response) {
  const auto& options = response.options;
  nlohmann::json query = {{"width", response.query_width},
                          {"height", response.query_height},
                          {"features", response.extracted_features},
                          {"features_used", response.index.query_features},
                          {"bbox", options.region ? nlohmann::json(*options.region) : nlohmann::json(nullptr)}};
  if (!response.query_id.empty()) query["id"] = response.query_id;
  nlohmann::json results = nlohmann::json::array();
  int rank = 0;
  for (const auto& r : response.index.results) {
    results.push_back({{"rank", ++rank},
                       {"id", r.id},
                       {"score", r.score},
                       {"verified", r.verified},
                       {"inliers", r.inliers},
                       {"via", r.via.empty() ? nlohmann::json(nullptr) : nlohmann::json(r.via)},
                       // As POST /v1/match: a transform and a region only for a verified result.
                       {"transform", r.verified ? nlohmann::json{{r.db_from_query.m[0], r.db_from_query.m[1],
                                                                  r.db_from_query.m[2]},
                                                                 {r.db_from_query.m[3], r.db_from_query.m[4],
                                                                  r.db_from_query.m[5]}}
                                                : nlohmann::json(nullptr)},
                       {"region", r.verified ? nlohmann::json(r.db_region) : nlohmann::json(nullptr)},
                       {"width", r.record.width},
                       {"height", r.record.height},
                       {"metadata", MetadataToJson(r.record.metadata_json)}});
  }
  const auto& t = response.index.timings;
  return {{"query", std::move(query)},
          {"params",
           {{"top_k", options.top_k},
            {"rerank", options.rerank_depth},
            {"qe", options.query_expansion},
            {"qe_images", options.qe_images}}},
          {"candidates", response.index.candidates},
          {"results", std::move(results)},
          {"timings_ms",
           {{"decode_extract", response.decode_extract_ms},
            {"quantize", t.quantize_ms},
            {"score", t.score_ms},
            {"verify", t.verify_ms},
            {"qe", t.qe_ms},
            {"total", response.total_ms}}}};
}

nlohmann::json MatchResponseToJson(const MatchResponse& response) {
  return PairMatchToJson(response.match, {.decode_extract_a = response.decode_extract_a_ms,
                                          .decode_extract_b = response.decode_extract_b_ms,
                                          .total = response.total_ms});
}

nlohmann::json CollectionToJson(const CollectionInfo& info, bool stats) {
  const index::IndexStats& s = info.stats.index;
  char fingerprint[17];
  std::snprintf(fingerprint, sizeof fingerprint, "%016llx", static_cast<unsigned long long>(s.vocabulary_fingerprint));
  auto optional = [](const std::optional<uint64_t>& v) { return v ? nlohmann::json(*v) : nlohmann::json(nullptr); };
  nlohmann::json out = {
      {"name", info.name},
      {"public", info.settings.is_public},
      {"images", s.num_images},
      {"features", s.num_features},
      {"disk_bytes", info.disk_bytes},
      {"vocabulary", {{"words", s.vocabulary_size}, {"fingerprint", fingerprint}, {"descriptor", info.descriptor},
                      {"hamming", info.hamming}}},
      {"limits", {{"max_images", optional(info.settings.max_images)}, {"max_bytes", optional(info.settings.max_bytes)}}}};
  if (stats) out["stats"] = StatsToJson(info.stats);
  return out;
}

nlohmann::json BackupToJson(const std::string& out, const index::BackupResult& result) {
  return {{"out", out},
          {"images", result.images},
          {"generation", result.generation},
          {"bytes", result.bytes},
          {"attempts", result.attempts}};
}

nlohmann::json StatsToJson(const ServiceStats& stats) {
  const auto& s = stats.index;
  char fingerprint[17];
  std::snprintf(fingerprint, sizeof fingerprint, "%016llx", static_cast<unsigned long long>(s.vocabulary_fingerprint));
  return {{"images", s.num_images},
          {"features", s.num_features},
          {"words", s.vocabulary_size},
          {"bytes_per_feature", s.bytes_per_feature},
          {"index_bytes",
           {{"postings", s.postings_bytes}, {"geometry", s.geometry_bytes}, {"other", s.other_bytes},
            {"total", s.postings_bytes + s.geometry_bytes + s.other_bytes}}},
          {"segments", s.num_segments},
          {"vocabulary_fingerprint", fingerprint},
          {"memory_rss_bytes", stats.rss_bytes},
          {"uptime_s", stats.uptime_s},
          {"extractions_in_flight", stats.extractions_in_flight},
          {"max_concurrent_extractions", stats.max_concurrent_extractions}};
}

}  // namespace oxbow::api
