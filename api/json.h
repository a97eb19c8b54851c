// JSON mapping of the service's responses (the bodies of the HTTP API; server/README.md documents each).
// Field names are snake_case, sizes in pixels, times in milliseconds, boxes as [x1, y1, x2, y2].
// User metadata is stored as a JSON document and returned as that document (not as a string).
// Thread-safe (pure functions).
#pragma once

#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "api/collections.h"
#include "api/service.h"
#include "index/image_index.h"

namespace oxbow::api {

// {"id", "width", "height", "features", "source", "metadata", "added_unix_ms"}
nlohmann::json ImageRecordToJson(const index::ImageRecord& record);
// ImageRecordToJson + {"replaced", "timings_ms": {"decode_extract", "add"}}
nlohmann::json AddImageResponseToJson(const AddImageResponse& response);
// {"images": [...], "offset", "limit", "total"}
nlohmann::json ListResponseToJson(const ListResponse& response);
// {"query": {"id"?, "width", "height", "features", "features_used", "bbox"},
//  "params": {"top_k", "rerank", "qe", "qe_images"}, "candidates",
//  "results": [{"rank", "id", "score", "verified", "inliers", "transform" (2x3 row-major db_from_query),
//               "region" (matched box in the db image), "width", "height", "metadata"}],
//  "timings_ms": {"decode_extract", "quantize", "score", "verify", "qe", "total"}}
nlohmann::json SearchResponseToJson(const SearchResponse& response);
// PairMatchToJson (api/pair_match.h) with the service's decode + extract and total times.
nlohmann::json MatchResponseToJson(const MatchResponse& response);
// {"images", "features", "words", "bytes_per_feature", "index_bytes": {...}, "memory_rss_bytes",
//  "uptime_s", "extractions_in_flight", "max_concurrent_extractions", "segments", "vocabulary_fingerprint"}
nlohmann::json StatsToJson(const ServiceStats& stats);
// A collection (GET /v1/collections/{name}): {"name", "public", "images", "features", "disk_bytes",
//  "vocabulary": {"words", "fingerprint" (16 hex digits), "descriptor", "hamming"},
//  "limits": {"max_images", "max_bytes"} (null: none)}; with `stats`, also "stats" (StatsToJson).
nlohmann::json CollectionToJson(const CollectionInfo& info, bool stats);
// The answer of a backup (POST /v1/admin/backup, `oxbow index backup`): {out, images, generation,
// bytes, attempts}.
nlohmann::json BackupToJson(const std::string& out, const index::BackupResult& result);

// The deepest nesting of arrays and objects accepted in a JSON document from a client (fixed). nlohmann-json
// parses without recursion but dumps, copies and compares recursively: a document nested ~74,000 levels
// deep overflows a worker thread's stack. Real metadata nests a few levels.
inline constexpr int kMaxJsonDepth = 64;

// The nesting depth of arrays and objects in a JSON text, counted in one pass over its bytes (brackets
// outside strings), without parsing or recursion, so that it is safe on any input; counting stops at
// `stop_above` + 1. Exact for a valid JSON text; for an invalid one the parser refuses it anyway.
[[nodiscard]] int JsonNestingDepth(std::string_view text, int stop_above = kMaxJsonDepth);

// The stored metadata text as JSON; null for "", the text as a JSON string if it does not parse or nests
// deeper than kMaxJsonDepth (returned, not parsed).
nlohmann::json MetadataToJson(const std::string& metadata_json);

}  // namespace oxbow::api
