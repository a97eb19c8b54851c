#include "api/service.h"

#include <unistd.h>

#include <algorithm>
#include <exception>
#include <functional>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <set>
#include <thread>

#include "api/params.h"
#include "api/partition.h"
#include "sift/base/log.h"
#include "sift/base/parallel.h"
#include "vocab/vocabulary.h"

namespace oxbow::api {

namespace {

using Clock = std::chrono::steady_clock;
constexpr const char* kThumbnailFile = "thumbnails.sqlite";  // in the index folder

double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

}  // namespace

std::optional<std::string> ServiceOptions::Check() const {
  if (max_image_bytes < 1) return "max_image_bytes must be >= 1";
  if (max_pixels < 1) return "max_pixels must be >= 1";
  if (max_image_side_px && *max_image_side_px < 16) return "max_image_side_px must be >= 16 when set";
  if (max_concurrent_extractions < 0 || max_concurrent_extractions > 1024) {
    return "max_concurrent_extractions must be in [0, 1024]";
  }
  if (extraction_wait_ms < 0 || extraction_wait_ms > 600'000) return "extraction_wait_ms must be in [0, 600000]";
  if (processing_timeout_ms < 1 || processing_timeout_ms > 3'600'000) return "processing_timeout_ms must be in [1, 3600000]";
  if (shutdown_grace_ms < 0 || shutdown_grace_ms > 3'600'000) return "shutdown_grace_ms must be in [0, 3600000]";
  if (threads_per_request < 0 || threads_per_request > 256) return "threads_per_request must be in [0, 256]";
  if (add_nice < 0 || add_nice > 19) return "add_nice must be in [0, 19]";
  if (auto message = default_query.Check()) return "default query: " + *message;
  if (auto message = thumbnails.Check()) return *message;
  return std::nullopt;
}

ExtractionOptions ServiceOptions::Extraction() const {
  ExtractionOptions extraction;
  extraction.slots = std::min(1024, ResolveThreadCount(max_concurrent_extractions));
  extraction.extraction_wait_ms = extraction_wait_ms;
  extraction.processing_timeout_ms = processing_timeout_ms;
  extraction.shutdown_grace_ms = shutdown_grace_ms;
  extraction.add_nice = add_nice;
  extraction.decode = Decode();
  return extraction;
}

sift::DecodeOptions ServiceOptions::Decode() const {
  sift::DecodeOptions decode;
  decode.max_bytes = max_image_bytes;
  decode.max_pixels = max_pixels;
  decode.max_image_side_px = max_image_side_px;
  return decode;
}

uint64_t ResidentMemoryBytes() {
  std::ifstream statm("/proc/self/statm");
  uint64_t size_pages = 0, resident_pages = 0;
  if (!(statm >> size_pages >> resident_pages)) return 0;
  const long page = sysconf(_SC_PAGESIZE);
  return resident_pages * static_cast<uint64_t>(page > 0 ? page : 4096);
}

Service::Service(std::unique_ptr<index::ImageIndex> index, const sift::SiftExtractor& extractor,
                 const ServiceOptions& options)
    : index_(std::move(index)),
      options_(options),
      extractions_(std::make_unique<Extractions>(extractor, options.Extraction())),
      opened_(Clock::now()) {}

Service::~Service() = default;

Result<std::unique_ptr<Service>> Service::Open(const std::string& index_dir,
                                               const std::optional<std::string>& vocabulary_path,
                                               const ServiceOptions& options,
                                               const index::IndexOptions& index_options) {
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, "service options: " + *message);
  std::unique_ptr<index::ImageIndex> index;
  if (index::ImageIndex::Exists(index_dir)) {
    auto opened = index::ImageIndex::Open(index_dir, index_options);
    if (!opened) return std::unexpected(opened.error());
    index = std::move(*opened);
    if (vocabulary_path) {
      auto vocabulary = vocab::Vocabulary::Read(*vocabulary_path);
      if (!vocabulary) return std::unexpected(vocabulary.error());
      if (vocabulary->fingerprint() != index->vocabulary().fingerprint()) {
        return Fail(ErrorCode::kIncompatible, "the index in '" + index_dir + "' was built with another vocabulary than '" +
                                                  *vocabulary_path + "'; drop --vocab to use the index's own copy");
      }
    }
  } else if (vocabulary_path) {
    auto vocabulary = vocab::Vocabulary::Read(*vocabulary_path);
    if (!vocabulary) return std::unexpected(vocabulary.error());
    std::string settings = vocabulary->extractor_settings();
    if (settings.empty()) {
      sift::SiftOptions defaults;
      defaults.descriptor = vocabulary->descriptor_kind();
      settings = defaults.Describe();
    }
    auto created = index::ImageIndex::Create(index_dir, *vocabulary, settings, index_options);
    if (!created) return std::unexpected(created.error());
    index = std::move(*created);
    OXBOW_LOG(kInfo) << "created an empty index in " << index_dir << " (vocabulary " << *vocabulary_path << ", "
                     << vocabulary->size() << " words)";
  } else {
    return Fail(ErrorCode::kNotFound, "no index in '" + index_dir +
                                          "'; pass --vocab VOCAB to create an empty one there (see `oxbow vocab train`)");
  }

  if (auto s = PinClusterStatistics(index_dir, *index); !s) return std::unexpected(s.error());

  auto sift_options = sift::SiftOptions::FromDescription(index->extractor_settings());
  if (!sift_options) return std::unexpected(sift_options.error());
  sift_options->num_threads = options.threads_per_request;
  auto extractor = sift::SiftExtractor::Create(*sift_options);
  if (!extractor) return std::unexpected(extractor.error());
  auto thumbnails = ThumbnailStore::Open(index_dir + "/" + kThumbnailFile);
  if (!thumbnails) return std::unexpected(thumbnails.error());
  std::unique_ptr<Service> service(new Service(std::move(index), *extractor, options));
  service->thumbnails_ = std::move(*thumbnails);
  service->SettleThumbnails();
  return service;
}

void Service::SettleThumbnails() {
  const std::string& path = thumbnails_->path();
  // A pending thumbnail belongs to a write that a crash cut short: the image is indexed (commit it) when
  // the index's write sequence moved past the stamp and the indexed image is the one it was made for;
  // else the index never committed it (drop it; the id keeps the thumbnail of its indexed image).
  const uint64_t sequence = index_->write_sequence();
  size_t committed = 0, dropped = 0, orphans = 0;
  auto pending_ids = thumbnails_->Ids(true);
  if (!pending_ids) {
    OXBOW_LOG(kWarning) << "pending thumbnails in '" << path << "' not settled: " << pending_ids.error().ToString();
    pending_ids = std::vector<std::string>();
  }
  for (const std::string& id : *pending_ids) {
    auto pending = thumbnails_->GetPending(id);
    auto record = index_->Get(id);
    bool indexed = false;
    if (pending && record) {
      const auto& found = *pending;
      indexed = found.has_value() && found->after_sequence < sequence && found->entry.image_width == record->width &&
                found->entry.image_height == record->height && found->entry.source == record->source_path;
    }
    auto settled = indexed ? thumbnails_->Commit(id) : thumbnails_->DropPending(id);
    if (!settled) {
      OXBOW_LOG(kWarning) << "pending thumbnail of '" << id << "' not settled: " << settled.error().ToString();
    } else {
      ++(indexed ? committed : dropped);
    }
  }
  // Thumbnails of ids the index does not hold: a crash between an image's delete and its thumbnail's.
  auto ids = thumbnails_->Ids(false);
  if (!ids) {
    OXBOW_LOG(kWarning) << "thumbnails in '" << path << "' not checked against the index: " << ids.error().ToString();
    ids = std::vector<std::string>();
  }
  for (const std::string& id : *ids) {
    if (index_->Contains(id)) continue;
    if (auto removed = thumbnails_->Remove(id); !removed) {
      OXBOW_LOG(kWarning) << "thumbnail of '" << id << "', not indexed, stays: " << removed.error().ToString();
    } else {
      ++orphans;
    }
  }
  if (committed + dropped + orphans > 0) {
    OXBOW_LOG(kInfo) << "thumbnails in '" << path << "' settled after an interrupted write: " << committed
                     << " pending committed with their indexed image, " << dropped
                     << " pending dropped (image not indexed), " << orphans << " of images not indexed removed";
  }
}

void Service::CommitThumbnail(const std::string& id) {
  // The image is indexed already: a failure here leaves its thumbnail pending, which GetThumbnail serves
  // and the next open commits.
  if (auto committed = thumbnails_->Commit(id); !committed) {
    OXBOW_LOG(kWarning) << "thumbnail of '" << id << "' stays pending until the next open: "
                        << committed.error().ToString();
  }
}

void Service::StopExtractions() { extractions_->Stop(); }

Result<AddImageResponse> Service::AddImage(const AddImageRequest& request) {
  // Cheap checks first, so a bad id or a taken id costs no extraction. The same rules as the HTTP
  // parameters' (api/params.h), for every transport: a cluster shard's gRPC Add comes here directly.
  if (auto ok = CheckNewImageId(request.id); !ok) return std::unexpected(ok.error());
  std::string metadata_json;
  if (!request.metadata_json.empty()) {
    auto metadata = ParseMetadata(request.metadata_json, "metadata");
    if (!metadata) return std::unexpected(metadata.error());
    metadata_json = std::move(*metadata);
  }
  if (!request.replace && index_->Contains(request.id)) {
    return Fail(ErrorCode::kAlreadyExists, "an image with id '" + request.id +
                                               "' is already indexed; add replace=true to replace it");
  }
  AddImageResponse response;
  Result<sift::FeatureSet> features = Fail(ErrorCode::kInternal, "extraction did not run");
  Result<api::Thumbnail> thumbnail = Fail(ErrorCode::kInternal, "thumbnail not made");
  features = extractions_->Extract(
      request.image, extractions_->Start(request.client_gone), &response.decode_extract_ms,
      [&] {
        thumbnail = MakeThumbnail(request.image, options_.thumbnails.stored_side_px, options_.thumbnails.jpeg_quality,
                                  options_.Decode());
      },
      Extractions::Use::kAdd);
  if (!features) return std::unexpected(features.error());
  if (!thumbnail) return std::unexpected(thumbnail.error());

  index::ImageInfo info;
  info.source_path = request.source_name;
  info.metadata_json = std::move(metadata_json);
  info.extractor_settings = index_->extractor_settings();

  const auto start = Clock::now();
  std::lock_guard<std::mutex> lock(write_mutex_);
  const bool replacing = index_->Contains(request.id);
  if (replacing && !request.replace) {
    return Fail(ErrorCode::kAlreadyExists, "an image with id '" + request.id +
                                               "' is already indexed; add replace=true to replace it");
  }
  // The thumbnail is durable (pending) before the image is indexed, and becomes the id's thumbnail only
  // once the index committed the image: a crash in between leaves the old image with its own thumbnail
  // (api/thumbnails.h, "Committing with the index"; Open settles what is left pending).
  ThumbnailStore::Entry entry{std::move(*thumbnail), features->image_width, features->image_height, info.source_path};
  if (auto stored = thumbnails_->PutPending(request.id, entry, index_->write_sequence()); !stored) {
    return std::unexpected(stored.error());
  }
  if (before_index_commit_for_testing_) before_index_commit_for_testing_(request.id);
  // A replacement is one transaction in the index: the old image or the new one, never neither.
  auto record = replacing ? index_->Replace(request.id, *features, info) : index_->Add(request.id, *features, info);
  if (!record) {
    if (auto dropped = thumbnails_->DropPending(request.id); !dropped) {
      OXBOW_LOG(kWarning) << "image '" << request.id << "' not indexed; its pending thumbnail stays until the next open: "
                          << dropped.error().ToString();
    }
    return std::unexpected(record.error());
  }
  CommitThumbnail(request.id);
  response.replaced = replacing;
  response.record = std::move(*record);
  response.add_ms = MsSince(start);
  return response;
}

Result<AddBatchResponse> Service::AddImages(const AddBatchRequest& request) {
  const size_t n = request.images.size();
  AddBatchResponse response;
  response.results.assign(n, Fail(ErrorCode::kInternal, "not processed"));
  std::vector<sift::FeatureSet> features(n);
  std::vector<api::Thumbnail> thumbnails(n);
  std::vector<char> extracted_ok(n, 0);  // features[i] and thumbnails[i] hold image i's
  // Cheap checks first, so a taken or repeated id costs no extraction; ids and metadata by the rules
  // of AddImage.
  std::vector<std::string> metadata_json(n);  // re-serialised, as AddImage stores it
  std::set<std::string> seen;
  std::vector<size_t> todo;
  for (size_t i = 0; i < n; ++i) {
    const std::string& id = request.images[i].id;
    Status valid = CheckNewImageId(id);
    if (valid && !request.images[i].metadata_json.empty()) {
      auto metadata = ParseMetadata(request.images[i].metadata_json, "metadata");
      if (metadata) {
        metadata_json[i] = std::move(*metadata);
      } else {
        valid = std::unexpected(metadata.error());
      }
    }
    if (!valid) {
      response.results[i] = std::unexpected(valid.error());
    } else if (!seen.insert(id).second) {
      response.results[i] = Fail(ErrorCode::kAlreadyExists, "image id '" + id + "' is repeated earlier in this batch");
    } else if (index_->Contains(id)) {
      response.results[i] = Fail(ErrorCode::kAlreadyExists, "an image with id '" + id + "' is already indexed");
    } else {
      todo.push_back(i);
    }
  }

  // Each image gets the deadline of one add from when its extraction is asked; the batch as a whole
  // stops only for a client gone or a shutdown (no deadline).
  const Extractions::Work batch{Clock::time_point::max(), &request.client_gone};
  const auto extract_start = Clock::now();
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t k = next++; k < todo.size() && !extractions_->StopReason(batch); k = next++) {
      const size_t i = todo[k];
      const AddBatchItem& item = request.images[i];
      Result<api::Thumbnail> thumbnail = Fail(ErrorCode::kInternal, "thumbnail not made");
      double ms = 0;
      auto extracted = extractions_->Extract(
          item.image, extractions_->Start(request.client_gone), &ms,
          [&] {
            thumbnail = MakeThumbnail(item.image, options_.thumbnails.stored_side_px, options_.thumbnails.jpeg_quality,
                                      options_.Decode());
          },
          Extractions::Use::kAdd);
      if (!extracted) {
        response.results[i] = std::unexpected(extracted.error());
      } else if (!thumbnail) {
        response.results[i] = std::unexpected(thumbnail.error());
      } else {
        features[i] = std::move(*extracted);
        thumbnails[i] = std::move(*thumbnail);
        extracted_ok[i] = 1;
      }
    }
  };
  // Extract blocks its caller until its job ran on the add threads, hence one caller per slot at most.
  std::exception_ptr error;  // the first exception of a caller, rethrown here as AddImage's would be
  std::mutex error_mutex;
  auto caller = [&] {
    try {
      work();
    } catch (...) {
      std::lock_guard<std::mutex> error_lock(error_mutex);
      if (!error) error = std::current_exception();
      next = todo.size();
    }
  };
  {
    std::vector<std::jthread> callers;
    const size_t count = std::min(todo.size(), static_cast<size_t>(extractions_->slots()));
    for (size_t t = 1; t < count; ++t) callers.emplace_back(caller);
    caller();
  }
  if (error) std::rethrow_exception(error);
  response.decode_extract_ms = MsSince(extract_start);
  if (auto reason = extractions_->StopReason(batch)) return std::unexpected(*reason);

  const auto add_start = Clock::now();
  std::lock_guard<std::mutex> lock(write_mutex_);
  std::vector<index::BatchImage> batch_images;
  std::vector<size_t> batch_index;  // position in the request of each of batch_images
  for (size_t i : todo) {
    if (extracted_ok[i] == 0) continue;
    const AddBatchItem& item = request.images[i];
    // Taken meanwhile by another writer: its thumbnail must not be overwritten.
    if (index_->Contains(item.id)) {
      response.results[i] = Fail(ErrorCode::kAlreadyExists, "an image with id '" + item.id + "' is already indexed");
      continue;
    }
    index::ImageInfo info;
    info.source_path = item.source_name;
    info.metadata_json = std::move(metadata_json[i]);
    info.extractor_settings = index_->extractor_settings();
    batch_images.push_back(index::BatchImage{item.id, &features[i], std::move(info), {}, {}});
    batch_index.push_back(i);
  }
  if (batch_images.empty()) return response;  // every image failed on its own: no transaction to make
  // The thumbnails are durable (pending) before the images are indexed and become theirs once the index
  // committed them, as in AddImage; those of images the index refused are dropped.
  auto drop_thumbnails = [&](auto failed) {
    for (size_t b = 0; b < batch_index.size(); ++b) {
      if (!failed(b)) continue;
      if (auto dropped = thumbnails_->DropPending(batch_images[b].id); !dropped) {
        OXBOW_LOG(kWarning) << "image '" << batch_images[b].id
                            << "' not indexed; its pending thumbnail stays until the next open: "
                            << dropped.error().ToString();
      }
    }
  };
  const uint64_t sequence = index_->write_sequence();
  for (size_t b = 0; b < batch_index.size(); ++b) {
    const size_t i = batch_index[b];
    ThumbnailStore::Entry entry{std::move(thumbnails[i]), features[i].image_width, features[i].image_height,
                                batch_images[b].info.source_path};
    if (auto stored = thumbnails_->PutPending(batch_images[b].id, entry, sequence); !stored) {
      drop_thumbnails([&](size_t k) { return k < b; });
      return std::unexpected(stored.error());
    }
  }
  if (before_index_commit_for_testing_) before_index_commit_for_testing_(batch_images.front().id);
  auto records = index_->AddBatch(batch_images);
  for (size_t b = 0; b < records.size(); ++b) {
    if (!records[b] && records[b].error().code == ErrorCode::kIoError) {  // the catalogue failed: nothing added
      drop_thumbnails([](size_t) { return true; });
      return std::unexpected(records[b].error());
    }
  }
  drop_thumbnails([&](size_t b) { return !records[b]; });
  for (size_t b = 0; b < records.size(); ++b) {
    if (records[b]) CommitThumbnail(batch_images[b].id);
  }
  for (size_t b = 0; b < records.size(); ++b) response.results[batch_index[b]] = std::move(records[b]);
  response.add_ms = MsSince(add_start);
  return response;
}

Result<index::ImageRecord> Service::GetImage(const std::string& id) const { return index_->Get(id); }

namespace {
// What a backup copies beside the index: the thumbnails and, in a cluster partition, the cluster's
// statistics it scores with (a restored partition then scores as before).
index::BackupOptions BackupOptionsOfAFolder() {
  index::BackupOptions options;
  options.extra_databases = {kThumbnailFile};
  options.extra_files = {std::string(kGlobalFrequenciesFile)};
  return options;
}
}  // namespace

Status Service::StoreClusterStatistics(const GlobalFrequencies& frequencies) {
  std::lock_guard<std::mutex> lock(write_mutex_);
  return api::StoreClusterStatistics(index_->directory(), *index_, frequencies);
}

Status Service::DeleteImage(const std::string& id) {
  std::lock_guard<std::mutex> lock(write_mutex_);
  if (auto removed = index_->Remove(id); !removed) return removed;
  // A leftover thumbnail is not served (GetThumbnail needs the catalogue entry) and is removed at the
  // next open; the delete stands.
  if (auto dropped = thumbnails_->Remove(id); !dropped) {
    OXBOW_LOG(kWarning) << "image '" << id << "' deleted but its thumbnail stays: " << dropped.error().ToString();
  }
  return Ok();
}

Result<index::BackupResult> Service::Backup(const std::string& out) const {
  index::BackupOptions options = BackupOptionsOfAFolder();
  options.snapshot_mutex = &write_mutex_;
  return index::BackupIndex(index_->directory(), out, options);
}

Result<index::BackupResult> Service::BackupFolder(const std::string& index_dir, const std::string& out) {
  return index::BackupIndex(index_dir, out, BackupOptionsOfAFolder());
}

Result<ListResponse> Service::ListImages(uint64_t offset, uint64_t limit) const {
  auto images = index_->List(offset, limit);
  if (!images) return std::unexpected(images.error());
  ListResponse response;
  response.images = std::move(*images);
  response.offset = offset;
  response.limit = limit;
  response.total = index_->Stats().num_images;
  return response;
}

Result<SearchResponse> Service::Search(std::span<const uint8_t> image, const index::QueryOptions& options,
                                       const sift::StopRequested& client_gone) const {
  const auto start = Clock::now();
  SearchResponse response;
  response.options = options;
  auto features = extractions_->Extract(image, extractions_->Start(client_gone), &response.decode_extract_ms);
  if (!features) return std::unexpected(features.error());
  response.query_width = features->image_width;
  response.query_height = features->image_height;
  response.extracted_features = static_cast<uint32_t>(features->size());
  index::QueryOptions query = options;
  query.extractor_settings = index_->extractor_settings();
  auto result = index_->Query(*features, query);
  if (!result) return std::unexpected(result.error());
  response.index = std::move(*result);
  response.total_ms = MsSince(start);
  return response;
}

Result<SearchResponse> Service::SearchSimilar(const std::string& id, const index::QueryOptions& options) const {
  const auto start = Clock::now();
  SearchResponse response;
  response.options = options;
  response.query_id = id;
  auto record = index_->Get(id);
  if (!record) return std::unexpected(record.error());
  response.query_width = record->width;
  response.query_height = record->height;
  response.extracted_features = record->num_features;
  auto result = index_->QuerySimilar(id, options);
  if (!result) return std::unexpected(result.error());
  response.index = std::move(*result);
  response.total_ms = MsSince(start);
  return response;
}

Result<MatchResponse> Service::Match(std::span<const uint8_t> image_a, std::span<const uint8_t> image_b,
                                     const PairMatchOptions& options, const sift::StopRequested& client_gone) const {
  return MatchImages(*extractions_, options_.threads_per_request, image_a, image_b, options, client_gone);
}

Result<MatchResponse> MatchImages(const Extractions& extractions, int threads_per_request,
                                  std::span<const uint8_t> image_a, std::span<const uint8_t> image_b,
                                  const PairMatchOptions& options, const sift::StopRequested& client_gone) {
  const auto start = Clock::now();
  MatchResponse response;
  const Extractions::Work work = extractions.Start(client_gone);  // one deadline for both images
  auto a = extractions.Extract(image_a, work, &response.decode_extract_a_ms, {}, Extractions::Use::kPairMatch);
  if (!a) {
    Error error = a.error();
    error.message = "image a: " + error.message;
    return std::unexpected(error);
  }
  auto b = extractions.Extract(image_b, work, &response.decode_extract_b_ms, {}, Extractions::Use::kPairMatch);
  if (!b) {
    Error error = b.error();
    error.message = "image b: " + error.message;
    return std::unexpected(error);
  }
  PairMatchOptions pair = options;
  pair.match.num_threads = threads_per_request;
  auto match = MatchPair(*a, *b, pair);
  if (!match) return std::unexpected(match.error());
  response.match = std::move(*match);
  response.total_ms = MsSince(start);
  return response;
}

namespace {

// Reads a whole file of at most max_bytes; kNotFound when it cannot be opened.
Result<std::vector<uint8_t>> ReadSourceFile(const std::string& path, uint64_t max_bytes) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  if (!in) return Fail(ErrorCode::kNotFound, "source file '" + path + "' cannot be read");
  const auto size = static_cast<uint64_t>(in.tellg());
  if (size > max_bytes) return Fail(ErrorCode::kImageTooLarge, "source file '" + path + "' is over the size limit");
  std::vector<uint8_t> bytes(size);
  in.seekg(0);
  if (!in.read(reinterpret_cast<char*>(bytes.data()), static_cast<std::streamsize>(size))) {
    return Fail(ErrorCode::kIoError, "cannot read source file '" + path + "'");
  }
  return bytes;
}

}  // namespace

Result<ThumbnailResponse> Service::GetThumbnail(const std::string& id, int max_side_px) const {
  const int stored_side = options_.thumbnails.stored_side_px;
  if (max_side_px < kMinThumbnailPx || max_side_px > kMaxThumbnailPx) {
    return Fail(ErrorCode::kInvalidArgument, "thumbnail size must be in [" + std::to_string(kMinThumbnailPx) + ", " +
                                                 std::to_string(kMaxThumbnailPx) + "] pixels");
  }
  max_side_px = std::min(max_side_px, stored_side);  // nothing larger than the stored one is kept
  auto record = index_->Get(id);
  if (!record) return std::unexpected(record.error());
  auto stored = thumbnails_->Get(id);
  if (!stored) return std::unexpected(stored.error());
  std::optional<ThumbnailStore::Entry>& kept = *stored;
  // An entry made for another image under the same id (replaced while the server was down) is stale.
  auto made_for_record = [&](const ThumbnailStore::Entry& entry) {
    return entry.image_width == record->width && entry.image_height == record->height &&
           entry.source == record->source_path;
  };
  if (kept && !made_for_record(*kept)) kept.reset();
  if (!kept) {
    // Between a writer's index commit and its thumbnail's, the image's thumbnail is still pending.
    auto pending = thumbnails_->GetPending(id);
    if (!pending) return std::unexpected(pending.error());
    auto& found = *pending;
    if (found.has_value() && made_for_record(found->entry)) kept = std::move(found->entry);
  }
  ThumbnailResponse response;
  api::Thumbnail full;
  if (kept) {
    full = std::move(kept->thumbnail);
  } else {
    // Images indexed from files (oxbow index build) have their path in the catalogue. Uploads record
    // "http[:<client's file name>]", never a path to open (the name is the client's).
    const bool uploaded = record->source_path == "http" || record->source_path.rfind("http:", 0) == 0;
    auto bytes = uploaded ? Result<std::vector<uint8_t>>(Fail(ErrorCode::kNotFound, "uploaded"))
                          : ReadSourceFile(record->source_path, options_.max_image_bytes);
    if (!bytes) {
      return Fail(ErrorCode::kNotFound, "image '" + id + "' has no stored thumbnail and its source '" +
                                            record->source_path + "' is not a readable file");
    }
    auto made = MakeThumbnail(*bytes, stored_side, options_.thumbnails.jpeg_quality, options_.Decode());
    if (!made) return std::unexpected(made.error());
    full = *made;
    response.from_source = true;
    if (thumbnail_made_for_testing_) thumbnail_made_for_testing_(id);
    // Kept only if `id` is still the image it was made from, checked under the writers' lock: a delete
    // + re-add or a replacement since the record was read has stored the new image's own thumbnail,
    // which this one must not overwrite.
    std::lock_guard<std::mutex> lock(write_mutex_);
    if (auto now = index_->Get(id); now && *now == *record) {
      ThumbnailStore::Entry entry{std::move(*made), record->width, record->height, record->source_path};
      if (auto cached = thumbnails_->Put(id, entry); !cached) {
        OXBOW_LOG(kWarning) << "thumbnail of '" << id << "' not cached: " << cached.error().ToString();
      }
    }
  }
  if (std::max(full.width, full.height) <= max_side_px) {
    response.thumbnail = std::move(full);
    return response;
  }
  auto scaled = MakeThumbnail({reinterpret_cast<const uint8_t*>(full.jpeg.data()), full.jpeg.size()}, max_side_px,
                              options_.thumbnails.jpeg_quality, options_.Decode());
  if (!scaled) return std::unexpected(scaled.error());
  response.thumbnail = std::move(*scaled);
  return response;
}

ServiceStats Service::Stats() const {
  ServiceStats stats;
  stats.index = index_->Stats();
  stats.rss_bytes = ResidentMemoryBytes();
  stats.uptime_s = std::chrono::duration<double>(Clock::now() - opened_).count();
  stats.extractions_in_flight = extractions_->in_flight();
  stats.max_concurrent_extractions = extractions_->slots();
  return stats;
}

}  // namespace oxbow::api
