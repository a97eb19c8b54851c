// The oxbow retrieval service: what the HTTP API does, without HTTP. It owns an index::ImageIndex and
// the sift::SiftExtractor configured as the index's features were extracted, and turns uploaded image
// bytes into index operations:
//
//   AddImage     decode + extract (bounded concurrency) -> ImageIndex::Add (durable when it returns)
//   AddImages    several decodes + extractions in parallel -> one ImageIndex::AddBatch
//   Search       decode + extract -> ImageIndex::Query (tf-idf, spatial re-ranking, query expansion)
//   SearchSimilar ImageIndex::QuerySimilar (an indexed image's stored features; no decoding)
//   Match        decode + extract both -> MatchPair (api/pair_match.h)
//   Get/Delete/List/Stats
//   GetThumbnail stored JPEG thumbnail (api/thumbnails.h), or one made from the source file
//
// Thread safety: every member may be called concurrently from any number of threads. Searches never
// wait for writers (ImageIndex reads an immutable snapshot); the only waits are (1) for an extraction
// slot (at most max_concurrent_extractions decode+extract run at once, bounding peak memory; a request
// waiting longer than extraction_wait_ms fails with kResourceExhausted -> 503; a request whose decode +
// extraction runs past processing_timeout_ms, whose client has gone, or that still runs
// shutdown_grace_ms after StopExtractions() is abandoned at the extractor's next check, its slot freed,
// nothing stored, kResourceExhausted -> 503) and (2) AddImage(s) /
// DeleteImage serialise among themselves on write_mutex_ (the index serialises writers anyway; the
// service lock makes the thumbnail and the index change one step for other writers; a replacement is one
// transaction in the index, ImageIndex::Replace). Searches take no service lock.
// Adds extract on low-priority threads (ServiceOptions::add_nice) so they yield the CPU to searches.
#pragma once

#include <atomic>
#include <chrono>
#include <functional>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "api/extractions.h"
#include "api/pair_match.h"
#include "api/partition.h"
#include "api/thumbnails.h"
#include "index/storage/backup.h"
#include "index/image_index.h"
#include "sift/base/error.h"
#include "sift/image.h"
#include "sift/sift.h"

namespace oxbow::api {

struct ServiceOptions {
  // --- Limits (memory and time per request)
  // Largest accepted encoded image, bytes (DecodeOptions::max_bytes); over it -> 413. >= 1.
  uint64_t max_image_bytes = 32ull << 20;
  // Largest accepted declared width * height, pixels (DecodeOptions::max_pixels), checked from the file
  // header before decoding; over it -> 413. >= 1. The product default (sift/image.h).
  uint64_t max_pixels = sift::DecodeOptions{}.max_pixels;
  // Images whose longest side exceeds this are downscaled before extraction (DecodeOptions::
  // max_image_side_px); keypoints are reported in original pixels. Bounds extraction memory and time
  // (SIFT peak memory ~ 48 bytes per pixel with the 2x first octave). Unset: never downscale. >= 16.
  // The product default (sift/image.h).
  std::optional<int> max_image_side_px = sift::DecodeOptions{}.max_image_side_px;
  // Decode + extract operations running at once (each holds its image pyramid in memory);
  // 0 = hardware threads. [0, 1024].
  int max_concurrent_extractions = 0;
  // How long a request waits for an extraction slot before failing with 503, milliseconds. [0, 600000].
  int extraction_wait_ms = 10'000;
  // Processing deadline of an add, search or match, milliseconds from when the service is asked: decoding
  // and extraction (waiting for a slot included) still running then are stopped (sift::StopRequested)
  // and the request fails with kResourceExhausted (503). A 1600-pixel image takes ~1-2 s on one core; the
  // deadline bounds what a hostile image can cost (the decoders' own limits bound the decode).
  // [1, 3600000].
  int processing_timeout_ms = 30'000;
  // After StopExtractions (shutdown), decodes and extractions still running this many milliseconds later
  // are stopped (503): a request almost done still gets its answer, and stopping waits at most this
  // long for extractions (less than `docker stop`'s 10 s before SIGKILL). 0 stops them at once.
  // [0, 3600000].
  int shutdown_grace_ms = 5'000;
  // Threads used inside one extraction and one pairwise match, 0 = all hardware threads: a search's
  // photo is extracted on every core (its octaves in strips, its keypoints split), the lowest latency.
  // Concurrent requests share one pool of threads, so under load each runs mostly on its own. Adds at a
  // lower priority (add_nice > 0) extract on their one thread. [0, 256].
  int threads_per_request = 0;
  // Adds decode and extract on dedicated threads running at this nice value (Linux; 0 = the callers'
  // threads at normal priority), so that on a busy machine the CPU goes to searches first and search
  // latency barely moves while images are added. The add still completes (lower priority is not
  // starvation on a machine that is not saturated for long). [0, 19].
  int add_nice = 10;
  // --- Query defaults (overridden per request by top_k, rerank, bbox, qe, qe_images)
  index::QueryOptions default_query;
  // --- Thumbnails (api/thumbnails.h): stored at add time in <index>/thumbnails.sqlite.
  ThumbnailOptions thumbnails;

  std::optional<std::string> Check() const;
  sift::DecodeOptions Decode() const;  // the decode limits above as DecodeOptions
  ExtractionOptions Extraction() const;  // the limits above as api::Extractions takes them
};


struct AddImageRequest {
  std::string id;                       // external id, 1..256 bytes, no control characters
  std::span<const uint8_t> image;       // encoded image bytes (JPEG, PNG, ...); not owned
  std::string metadata_json;            // a JSON document or ""
  std::string source_name;              // e.g. the multipart file name; informational
  bool replace = false;                 // an existing image with this id is replaced (else kAlreadyExists)
  // True once the client that asked has gone (may be empty): the add is then abandoned, nothing stored.
  sift::StopRequested client_gone;
};

struct AddImageResponse {
  index::ImageRecord record;
  bool replaced = false;                // an image with this id existed and was replaced (ImageIndex::Replace)
  double decode_extract_ms = 0;
  double add_ms = 0;                    // quantise + durable commit + publish
};

// One image of Service::AddImages.
struct AddBatchItem {
  std::string id;                       // as AddImageRequest::id
  std::span<const uint8_t> image;       // encoded image bytes; not owned
  std::string metadata_json;            // a JSON document or ""
  std::string source_name;              // informational, as AddImageRequest::source_name
};

struct AddBatchRequest {
  std::vector<AddBatchItem> images;
  // As AddImageRequest::client_gone: the whole batch is abandoned, nothing stored.
  sift::StopRequested client_gone;
};

struct AddBatchResponse {
  std::vector<Result<index::ImageRecord>> results;  // one per image, in order
  double decode_extract_ms = 0;         // wall time of all decodes + extractions (run in parallel)
  double add_ms = 0;                    // thumbnails + quantise + one durable commit + publish
};

struct SearchResponse {
  index::QueryResponse index;           // results + per-stage timings of the index
  index::QueryOptions options;          // the options the query ran with
  std::string query_id;                 // SearchSimilar: the indexed image queried with; else ""
  int query_width = 0;                  // pixels (original image)
  int query_height = 0;
  uint32_t extracted_features = 0;      // features of the whole query image (before the bbox)
  double decode_extract_ms = 0;         // 0 for SearchSimilar
  double total_ms = 0;
};

struct MatchResponse {
  PairMatchResult match;
  double decode_extract_a_ms = 0;
  double decode_extract_b_ms = 0;
  double total_ms = 0;
};

struct ListResponse {
  std::vector<index::ImageRecord> images;
  uint64_t offset = 0;
  uint64_t limit = 0;
  uint64_t total = 0;                   // live images in the index
};

inline constexpr int kMinThumbnailPx = 16;    // sizes Service::GetThumbnail accepts, pixels
inline constexpr int kMaxThumbnailPx = 2048;

struct ThumbnailResponse {
  Thumbnail thumbnail;                  // JPEG, longest side <= the size asked for
  bool from_source = false;             // made from the catalogue's source file (no stored thumbnail)
};

struct ServiceStats {
  index::IndexStats index;
  uint64_t rss_bytes = 0;               // resident memory of the process (/proc/self/statm), 0 if unknown
  double uptime_s = 0;                  // since the service was opened
  int extractions_in_flight = 0;
  int max_concurrent_extractions = 0;
};

class Service {
  using Clock = std::chrono::steady_clock;

 public:
  // Opens the index in `index_dir`, or creates it when the folder holds none and `vocabulary_path` is
  // given (the index then uses that vocabulary and its extractor settings). When both exist, the
  // vocabulary must be the index's (same fingerprint), else kIncompatible. kNotFound when there is no
  // index and no vocabulary. kInvalidArgument for invalid options.
  [[nodiscard]] static Result<std::unique_ptr<Service>> Open(const std::string& index_dir,
                                                             const std::optional<std::string>& vocabulary_path,
                                                             const ServiceOptions& options,
                                                             const index::IndexOptions& index_options = {});

  [[nodiscard]] Result<AddImageResponse> AddImage(const AddImageRequest& request);
  // Adds several new images (no replacement) as AddImage does each, but with one ImageIndex::AddBatch:
  // one durable transaction and one published snapshot for the batch. Decodes and extractions run in
  // parallel within the extraction slots, each image with its own processing deadline. An image that
  // fails (bad id, id taken or repeated earlier in the batch, undecodable, too large, its deadline or
  // slot wait passed) gets its own error and the others are added. The whole call fails, nothing
  // stored, when the client goes or the server stops meanwhile (kResourceExhausted) or the thumbnail
  // store or the catalogue fails (kIoError).
  [[nodiscard]] Result<AddBatchResponse> AddImages(const AddBatchRequest& request);
  [[nodiscard]] Result<index::ImageRecord> GetImage(const std::string& id) const;
  [[nodiscard]] Status DeleteImage(const std::string& id);
  [[nodiscard]] Result<ListResponse> ListImages(uint64_t offset, uint64_t limit) const;
  // `client_gone` (may be empty) as AddImageRequest::client_gone: the search or match is abandoned.
  [[nodiscard]] Result<SearchResponse> Search(std::span<const uint8_t> image, const index::QueryOptions& options,
                                              const sift::StopRequested& client_gone = {}) const;
  [[nodiscard]] Result<SearchResponse> SearchSimilar(const std::string& id, const index::QueryOptions& options) const;
  [[nodiscard]] Result<MatchResponse> Match(std::span<const uint8_t> image_a, std::span<const uint8_t> image_b,
                                            const PairMatchOptions& options,
                                            const sift::StopRequested& client_gone = {}) const;
  // A JPEG of image `id` whose longest side is at most min(max_side_px, thumbnails.stored_side_px)
  // (max_side_px in [kMinThumbnailPx, kMaxThumbnailPx]): the stored thumbnail (AddImage stores one durably before the image is indexed and commits it with the
  // image, so an acknowledged add has one), scaled down when smaller is asked for; else one made from the catalogue's source file when
  // it is readable (images indexed by `oxbow index build`), which is then stored for next time.
  // kNotFound for an unknown id or when neither exists; kInvalidArgument for a size out of range.
  [[nodiscard]] Result<ThumbnailResponse> GetThumbnail(const std::string& id, int max_side_px) const;
  ServiceStats Stats() const;
  // Backs up the index folder and its thumbnail cache into the new folder `out` while serving
  // (index/storage/backup.h; serve the copy to restore). The snapshots begin under the writers' lock, so the
  // copy's thumbnails are those of its images.
  [[nodiscard]] Result<index::BackupResult> Backup(const std::string& out) const;
  // The same from outside a server process (`oxbow index backup`), with `serve` running or not: the
  // thumbnail cache's snapshot begins just after the catalogue's, so an uploaded image deleted in
  // between may lack its thumbnail in the copy.
  [[nodiscard]] static Result<index::BackupResult> BackupFolder(const std::string& index_dir, const std::string& out);
  // Test seam: `hook` runs in GetThumbnail after it made a thumbnail from a source file and before it
  // stores it (lets a test change the image in exactly that window). Set it before concurrent use.
  void SetThumbnailMadeHookForTesting(std::function<void(const std::string& id)> hook) {
    thumbnail_made_for_testing_ = std::move(hook);
  }
  // Test seam: `hook` runs in AddImage and AddImages (with the batch's first id) once the thumbnails are
  // stored and before the index commits the images (lets a test crash in exactly that window).
  void SetBeforeIndexCommitHookForTesting(std::function<void(const std::string& id)> hook) {
    before_index_commit_for_testing_ = std::move(hook);
  }
  // For shutdown: decodes and extractions still running options().shutdown_grace_ms from now stop at
  // their next check (their requests fail with 503, nothing stored), as do later ones, so that stopping
  // the server does not wait for them. Irreversible; a second call does not extend the grace.
  void StopExtractions();

  // api::StoreClusterStatistics on this service's index (a cluster front's refresh, through the shard
  // API); one at a time.
  [[nodiscard]] Status StoreClusterStatistics(const GlobalFrequencies& frequencies);

  const ServiceOptions& options() const { return options_; }
  const index::ImageIndex& index() const { return *index_; }
  const sift::SiftExtractor& extractor() const { return extractions_->extractor(); }

  ~Service();

 private:
  Service(std::unique_ptr<index::ImageIndex> index, const sift::SiftExtractor& extractor, const ServiceOptions& options);
  // At open: commits or drops the thumbnails left pending by a write a crash cut short and removes those
  // of ids that are not indexed (api/thumbnails.h, "Committing with the index"). Failures are logged.
  void SettleThumbnails();
  // Makes the pending thumbnail of `id`, just committed in the index, its thumbnail (a failure is logged).
  void CommitThumbnail(const std::string& id);

  std::unique_ptr<index::ImageIndex> index_;
  ServiceOptions options_;
  // Serialises AddImage/DeleteImage and GetThumbnail's storing of a thumbnail it made, so that the check
  // "still the same image" and the store are one step for writers.
  mutable std::mutex write_mutex_;
  std::function<void(const std::string& id)> thumbnail_made_for_testing_;
  std::function<void(const std::string& id)> before_index_commit_for_testing_;
  std::unique_ptr<Extractions> extractions_;  // slots, deadlines and threads of every decode + extraction
  std::unique_ptr<ThumbnailStore> thumbnails_;      // <index>/thumbnails.sqlite (thread-safe itself)
  std::chrono::steady_clock::time_point opened_;
};

// Service::Match's work, for a server without an index (the cluster front): decode and extract both
// images under `extractions` (one deadline for both), then MatchPair with `threads_per_request` threads.
[[nodiscard]] Result<MatchResponse> MatchImages(const Extractions& extractions, int threads_per_request,
                                                std::span<const uint8_t> image_a, std::span<const uint8_t> image_b,
                                                const PairMatchOptions& options,
                                                const sift::StopRequested& client_gone = {});

// Resident set size of this process in bytes (Linux /proc/self/statm), 0 when unavailable.
uint64_t ResidentMemoryBytes();

}  // namespace oxbow::api
