// JSON mapping of the service's responses (the bodies of the HTTP API; the README documents each).
// Field names are snake_case, sizes in pixels, times in milliseconds, boxes as [x1, y1, x2, y2].
// User metadata is stored as a JSON document and returned as that document (not as a string).
// Thread-safe (pure functions).
#pragma once

#include <string>

#include <nlohmann/json.hpp>

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

// The stored metadata text as JSON; null for "", the text as a JSON string if it does not parse.
nlohmann::json MetadataToJson(const std::string& metadata_json);

}  // namespace oxbow::api
