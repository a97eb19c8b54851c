#include "index/image_index.h"

#include <sys/mman.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <condition_variable>
#include <mutex>
#include <numeric>
#include <optional>
#include <set>
#include <span>
#include <string_view>
#include <unordered_map>
#include <unordered_set>

#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/storage/checkpointer.h"
#include "index/cow_array.h"
#include "index/storage/feature_store.h"
#include "index/storage/folder_lock.h"
#include "index/storage/geometry_parts.h"
#include "index/search/hamming.h"
#include "index/storage/huge_pages.h"
#include "index/storage/loader.h"
#include "index/storage/snapshot.h"
#include "index/postings/inverted_file.h"
#include "index/search/rerank.h"
#include "index/search/kept_memory.h"
#include "index/search/pipeline.h"
#include "index/search/snapshot_source.h"
#include "index/search/source.h"
#include "sift/base/log.h"
#include "sift/match.h"
#include "sift/base/parallel.h"

namespace oxbow::index {
namespace {

constexpr size_t kMaxIdBytes = 256;

using Clock = std::chrono::steady_clock;
double MsSince(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string JoinPath(const std::string& dir, const char* file) {
  return (std::filesystem::path(dir) / file).string();
}

Status CheckId(const std::string& id) {
  if (id.empty() || id.size() > kMaxIdBytes) {
    return Fail(ErrorCode::kInvalidArgument, "image id must be 1.." + std::to_string(kMaxIdBytes) + " bytes");
  }
  for (unsigned char c : id) {
    if (c < 0x20 || c == 0x7f) return Fail(ErrorCode::kInvalidArgument, "image id contains a control character");
  }
  return Ok();
}

// `words_given`: the caller assigned the words (BatchImage::words), so descriptors may be absent.
Status CheckFeatures(const sift::FeatureSet& f, const vocab::Vocabulary& vocabulary, const std::string& what,
                     bool words_given = false) {
  const bool may_omit = words_given && f.descriptors.empty();
  if (!may_omit && f.descriptors.size() != f.keypoints.size() * sift::kDescriptorDim) {
    return Fail(ErrorCode::kInvalidArgument, what + ": " + std::to_string(f.descriptors.size()) +
                                                 " descriptor values for " + std::to_string(f.keypoints.size()) +
                                                 " keypoints (expected 128 each)");
  }
  if (vocabulary.dimension() != sift::kDescriptorDim) {
    return Fail(ErrorCode::kIncompatible, "the index vocabulary has dimension " +
                                              std::to_string(vocabulary.dimension()) + ", features have 128");
  }
  if (f.kind != vocabulary.descriptor_kind()) {
    return Fail(ErrorCode::kIncompatible, what + " has " + sift::DescriptorKindName(f.kind) +
                                              " descriptors but the index vocabulary was trained on " +
                                              sift::DescriptorKindName(vocabulary.descriptor_kind()));
  }
  if (f.image_width <= 0 || f.image_height <= 0) {
    return Fail(ErrorCode::kInvalidArgument, what + ": image size must be positive");
  }
  for (const sift::Keypoint& k : f.keypoints) {
    if (!std::isfinite(k.x) || !std::isfinite(k.y) || !std::isfinite(k.scale) || !std::isfinite(k.orientation)) {
      return Fail(ErrorCode::kInvalidArgument, what + ": non-finite keypoint");
    }
  }
  return Ok();
}

Status CheckSettings(const std::string& given, const std::string& index_settings, const std::string& what) {
  if (!given.empty() && given != index_settings) {
    return Fail(ErrorCode::kIncompatible, what + " were extracted with settings '" + given +
                                              "' but the index uses '" + index_settings +
                                              "'; extract with the index's settings");
  }
  return Ok();
}


}  // namespace

std::optional<std::string> IndexOptions::Check() const {
  if (auto e = ToTfIdf(*this).Check()) return e;
  if (num_threads < 0 || num_threads > 256) return "num_threads must be in [0, 256]";
  if (checkpoint_changes < 1 || checkpoint_changes >= (uint64_t{1} << 32)) return "checkpoint_changes must be in [1, 2^32)";
  if (auto e = quantizer.Check()) return "quantizer: " + *e;
  return std::nullopt;
}

std::optional<std::string> QueryOptions::Check() const {
  if (top_k < 1 || top_k > 10000) return "top_k must be in [1, 10000], got " + std::to_string(top_k);
  if (rerank_depth < 0 || rerank_depth > 10000) {
    return "rerank_depth must be in [0, 10000], got " + std::to_string(rerank_depth);
  }
  if (region) {
    const auto& r = *region;
    for (float v : r) {
      if (!std::isfinite(v)) return std::string("region must be finite");
    }
    if (!(r[0] < r[2] && r[1] < r[3])) return std::string("region must satisfy x1 < x2 and y1 < y2");
  }
  if (qe_images < 1 || qe_images > 100) return "qe_images must be in [1, 100]";
  if (max_pairs_per_word < 1 || max_pairs_per_word > 100) return "max_pairs_per_word must be in [1, 100]";
  if (query_assignments < 1 || query_assignments > 8) {
    return "query_assignments must be in [1, 8], got " + std::to_string(query_assignments);
  }
  if (quantizer_probes < 1 || quantizer_probes > 4096) {
    return "quantizer_probes must be in [1, 4096], got " + std::to_string(quantizer_probes);
  }
  if (!(assignment_sigma_sq > 0 && assignment_sigma_sq <= 4)) return std::string("assignment_sigma_sq must be in (0, 4]");
  if (transitive_depth < 0 || transitive_depth > 10000) {
    return "transitive_depth must be in [0, 10000], got " + std::to_string(transitive_depth);
  }
  if (transitive_neighbours < 1 || transitive_neighbours > 10000) {
    return "transitive_neighbours must be in [1, 10000], got " + std::to_string(transitive_neighbours);
  }
  if (transitive_attempts < 1 || transitive_attempts > 1000) {
    return "transitive_attempts must be in [1, 1000], got " + std::to_string(transitive_attempts);
  }
  if (transitive_anchors < 1 || transitive_anchors > 1000) {
    return "transitive_anchors must be in [1, 1000], got " + std::to_string(transitive_anchors);
  }
  if (hamming_shortlist < 1 || hamming_shortlist > 10000) {
    return "hamming_shortlist must be in [1, 10000], got " + std::to_string(hamming_shortlist);
  }
  if (max_query_features < 0 || max_query_features > 1000000) {
    return "max_query_features must be in [0, 1000000], got " + std::to_string(max_query_features);
  }
  if (max_scored_postings < 0 || max_scored_postings > 2000000000) {
    return "max_scored_postings must be in [0, 2000000000], got " + std::to_string(max_scored_postings);
  }
  if (max_tentative_matches < 0 || max_tentative_matches > 1000000) {
    return "max_tentative_matches must be in [0, 1000000], got " + std::to_string(max_tentative_matches);
  }
  if (hamming_threshold < 0 || hamming_threshold > vocab::kHammingBits) {
    return "hamming_threshold must be in [0, 64], got " + std::to_string(hamming_threshold);
  }
  if (!(hamming_sigma > 0 && hamming_sigma <= vocab::kHammingBits)) return std::string("hamming_sigma must be in (0, 64]");
  if (!(hamming_norm_exponent >= 0 && hamming_norm_exponent <= 1)) {
    return std::string("hamming_norm_exponent must be in [0, 1]");
  }
  if (asmk_weight < 0 || asmk_weight > 1000) return "asmk_weight must be in [0, 1000], got " + std::to_string(asmk_weight);
  if (qe_asmk_weight < 0 || qe_asmk_weight > 1000) {
    return "qe_asmk_weight must be in [0, 1000], got " + std::to_string(qe_asmk_weight);
  }
  if (auto e = verify.Check()) return "verify: " + *e;
  return std::nullopt;
}

namespace {

// One block of memory for the catalogue BLOBs of a batch of images, each image's part then viewed by
// its features in memory until a checkpoint maps them from a geometry file (PackedFeatures::PackBlob).
// A bulk add packs about 17 MB of them per batch of 1000; made one buffer per image (two before), they
// took a page fault per 4 KiB on every batch (most of an ingest's faults, about 18 us each on a VM
// whose page tables are paravirtualised), as the memory freed by the previous checkpoint had gone back
// to the system. The block is mapped at once, in transparent huge pages where the kernel gives them,
// and every byte taken is written. It is unmapped when the last image viewing it is gone (the next
// checkpoint, usually); an image removed before that keeps its part until then.
class BlobBlock {
 public:
  // Room for `capacity` bytes; none (every Take empty) where the mapping fails.
  explicit BlobBlock(size_t capacity) {
    if (capacity == 0) return;
    void* p = ::mmap(nullptr, capacity, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED) return;
    AdviseHugePages(static_cast<uint8_t*>(p), capacity);
    block_ = std::shared_ptr<uint8_t>(static_cast<uint8_t*>(p), [capacity](uint8_t* q) { ::munmap(q, capacity); });
    capacity_ = capacity;
  }
  // `bytes` of the block (8-byte aligned), or an empty span when it has no room left. Thread-safe.
  std::span<uint8_t> Take(size_t bytes) {
    const size_t rounded = (bytes + 7) / 8 * 8;
    const size_t at = used_.fetch_add(rounded, std::memory_order_relaxed);
    if (block_ == nullptr || at > capacity_ || capacity_ - at < rounded) return {};
    return {block_.get() + at, bytes};
  }
  // What keeps the block mapped.
  std::shared_ptr<const void> owner() const { return block_; }

 private:
  std::shared_ptr<uint8_t> block_;
  size_t capacity_ = 0;
  std::atomic<size_t> used_{0};
};

}  // namespace

struct ImageIndex::Impl {
  FolderLock folder_lock;                       // first: released after everything else (folder_lock.h)
  std::string dir;
  IndexOptions index_options;
  vocab::Vocabulary vocabulary;
  std::string extractor_settings;

  // writer_mutex: one writer at a time. Taken first (before any other lock of the index). It guards
  // the members below marked "writer_mutex", the building of the next snapshot from the current one
  // until it is published (so that no write is lost), and the checkpointer's state (checkpointer.h),
  // which the checkpointer takes it for. Held for the whole commit + publish of Add, AddBatch,
  // Replace, Remove and PinCollectionStatistics; never while a query runs.
  mutable std::mutex writer_mutex;
  std::unique_ptr<Catalogue> catalogue;         // the write connection; writer_mutex
  uint64_t next_number = 0;                     // writer_mutex: the number the catalogue gave last + 1 (a guess; AddBatch checks it)
  std::atomic<uint64_t> write_sequence{0};      // Catalogue::WriteSequence of the last commit (stored under writer_mutex)
  CurrentSnapshot snapshot;                     // what readers see; its own leaf mutex (snapshot.h)
  SearchActivity searches;                      // Query and QuerySimilar calls running (the geometry check waits)
  std::unique_ptr<Checkpointer> checkpointer;   // set before the index is returned (none when read_only); its thread runs until Close
  bool read_only = false;                       // OpenReadOnly: every write refused

  // The refusal of a write to a read-only open, or Ok.
  Status Writable() const {
    if (!read_only) return Ok();
    return Fail(ErrorCode::kIncompatible, "index " + dir + " is open read-only: it takes no writes");
  }

  Impl(std::string d, const IndexOptions& o, vocab::Vocabulary v, std::string settings)
      : dir(std::move(d)), index_options(o), vocabulary(std::move(v)), extractor_settings(std::move(settings)) {}

  std::shared_ptr<const Snapshot> Current() const { return snapshot.Current(); }
  void Publish(std::shared_ptr<const Snapshot> next) { snapshot.Publish(std::move(next)); }

  // After a committed write (writer_mutex held): counts it and tells the checkpointer.
  void Changed(uint64_t images);
  // Makes the checkpointer (catalogue and snapshot set) and starts its thread.
  void StartCheckpointer(Checkpointer::Start start) {
    checkpointer = std::make_unique<Checkpointer>(dir, index_options, writer_mutex, *catalogue, snapshot, searches,
                                                  std::move(start));
    checkpointer->Run();
  }

  // An image ready to commit: validated, quantised, packed and serialised (no shared state used).
  struct Prepared {
    std::shared_ptr<Entry> entry;
    BagOfWords bag;
    std::span<const uint8_t> blob;  // the catalogue BLOB, which entry->stored views (and keeps alive)
  };
  // `words`: pre-assigned words (BatchImage::words), or empty to quantise the descriptors with
  // `quantizer_threads` threads (a single add uses the index's threads, a batch one per image);
  // `signatures`: their pre-computed signatures (BatchImage::signatures), or empty. The BLOB is made
  // in `block` where it has room, else in a buffer of its own.
  Result<Prepared> Prepare(const std::string& id, const sift::FeatureSet& features, const ImageInfo& info,
                           std::span<const uint32_t> words, std::span<const uint64_t> signatures,
                           int quantizer_threads, BlobBlock* block = nullptr) const;
  // Add (replace false) and Replace (true): prepare, commit, publish one new snapshot.
  Result<ImageRecord> Write(const std::string& id, const sift::FeatureSet& features, const ImageInfo& info,
                            bool replace);
  // `next` (a copy of the current snapshot) gains the committed images `numbers` (ascending).
  static void Link(std::span<const uint32_t> numbers, std::span<Prepared* const> images, Snapshot& next);
  // Makes `next` (a copy of `current`) lose image `n` (`entry`): postings, entry, id, geometry bytes.
  // `bag`: entry.features().Bag(), read before the catalogue row is deleted (a damaged checkpoint
  // image is read from that row).
  static void Unlink(const Snapshot& current, uint32_t n, const Entry& entry, const BagOfWords& bag, Snapshot& next);
};

ImageIndex::ImageIndex(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
ImageIndex::~ImageIndex() {
  if (impl_->checkpointer) impl_->checkpointer->Close();
}

void ImageIndex::Impl::Changed(uint64_t images) {
  write_sequence.fetch_add(images);  // as the commit moved Catalogue::WriteSequence
  checkpointer->Changed(images);
}

bool ImageIndex::Exists(const std::string& dir) {
  std::error_code ec;
  return std::filesystem::is_regular_file(JoinPath(dir, kCatalogueFile), ec);
}

Result<std::unique_ptr<ImageIndex>> ImageIndex::Create(const std::string& dir, const vocab::Vocabulary& vocabulary,
                                                       std::string extractor_settings, const IndexOptions& options) {
  if (auto e = options.Check()) return Fail(ErrorCode::kInvalidArgument, "index options: " + *e);
  if (Exists(dir)) return Fail(ErrorCode::kAlreadyExists, dir + " already holds an index");
  if (!vocabulary.extractor_settings().empty() && extractor_settings != vocabulary.extractor_settings()) {
    return Fail(ErrorCode::kIncompatible, "the vocabulary was trained on features extracted with '" +
                                              vocabulary.extractor_settings() + "', not '" + extractor_settings + "'");
  }
  if (vocabulary.size() == 0 || vocabulary.size() > kMaxPackedWord + size_t{1}) {
    return Fail(ErrorCode::kInvalidArgument, "vocabulary size must be in [1, 2^24]");
  }
  std::error_code ec;
  // A folder of someone's files (a mistyped --out) is not mixed with an index's: only a new or empty
  // folder, or one left by a creation that did not finish (its lock and vocabulary copy), is taken.
  // Hidden entries and a file system's lost+found (a volume mounted as the index folder) do not count.
  std::string foreign;
  for (const auto& entry : std::filesystem::directory_iterator(dir, ec)) {
    const std::string name = entry.path().filename().string();
    const bool own = name == "LOCK" || name.rfind(kVocabularyFile, 0) == 0 || name.rfind(kCatalogueFile, 0) == 0 ||
                     name.front() == '.' || name == "lost+found";
    if (!own) {
      foreign = name;
      break;
    }
  }
  if (!foreign.empty()) {
    return Fail(ErrorCode::kAlreadyExists,
                dir + " holds other files ('" + foreign + "') and no index: give a new or empty folder for an index");
  }
  ec.clear();
  std::filesystem::create_directories(dir, ec);
  if (ec) return Fail(ErrorCode::kIoError, "cannot create " + dir + ": " + ec.message());
  auto lock = FolderLock::Acquire(dir);
  if (!lock) return std::unexpected(lock.error());
  if (Exists(dir)) return Fail(ErrorCode::kAlreadyExists, dir + " already holds an index");  // made meanwhile
  // The vocabulary copy first (atomic write); the catalogue, created in one transaction, marks the index
  // as complete. A crash in between leaves a folder that Exists() does not report as an index.
  if (auto s = vocabulary.Write(JoinPath(dir, kVocabularyFile)); !s) return std::unexpected(s.error());
  CatalogueMeta meta;
  meta.vocabulary_fingerprint = vocabulary.fingerprint();
  meta.vocabulary_size = vocabulary.size();
  meta.descriptor_kind = sift::DescriptorKindName(vocabulary.descriptor_kind());
  meta.extractor_settings = extractor_settings;
  auto catalogue = Catalogue::Create(JoinPath(dir, kCatalogueFile), meta);
  if (!catalogue) return std::unexpected(catalogue.error());

  auto impl = std::make_unique<Impl>(dir, options, vocabulary, std::move(extractor_settings));
  impl->folder_lock = std::move(*lock);
  impl->catalogue = std::move(*catalogue);
  auto snap = std::make_shared<Snapshot>(InvertedFile(vocabulary.size(), ToTfIdf(options)));
  for (auto& shard : snap->ids) shard = std::make_shared<IdShard>();
  impl->Publish(std::move(snap));
  impl->StartCheckpointer({});
  return std::unique_ptr<ImageIndex>(new ImageIndex(std::move(impl)));
}

namespace {

// Where the checkpointer of an index opened from `loaded` starts; its snapshot and damaged images go to
// *snap and *damaged (a null snapshot: the checkpoint is unusable, rebuild).
Checkpointer::Start StartFrom(LoadedCheckpoint loaded, const std::string& dir, std::shared_ptr<Snapshot>* snap,
                              std::vector<DamagedBlob>* damaged) {
  Checkpointer::Start start;
  if (!loaded.snapshot) {
    // Keep the generation: the new files must not take the names of those the old manifest lists.
    start.manifest.generation = loaded.manifest.generation;
    return start;
  }
  *damaged = std::move(loaded.damaged);
  *snap = std::move(loaded.snapshot);
  start.manifest = std::move(loaded.manifest);
  start.parts = std::move(loaded.parts);
  start.contents = std::move(loaded.contents);
  start.forced = loaded.compact;
  start.segment_files = std::move(loaded.segment_files);
  start.changes = loaded.changes;
  if (loaded.recoded) {
    OXBOW_LOG(kInfo) << "index " << dir << ": its postings file was written in an older format by an earlier "
                     << "build and was converted while loading; a checkpoint in the current format is written "
                     << "in the background";
    start.forced = true;
  }
  return start;
}

}  // namespace

Result<std::unique_ptr<ImageIndex>> ImageIndex::Open(const std::string& dir, const IndexOptions& options) {
  return OpenFolder(dir, options, /*read_only=*/false);
}

Result<std::unique_ptr<ImageIndex>> ImageIndex::OpenReadOnly(const std::string& dir, const IndexOptions& options) {
  return OpenFolder(dir, options, /*read_only=*/true);
}

Result<std::unique_ptr<ImageIndex>> ImageIndex::OpenFolder(const std::string& dir, const IndexOptions& options,
                                                           bool read_only) {
  if (auto e = options.Check()) return Fail(ErrorCode::kInvalidArgument, "index options: " + *e);
  const std::string catalogue_path = JoinPath(dir, kCatalogueFile);
  if (!Exists(dir)) return Fail(ErrorCode::kNotFound, "no index at " + dir + " (missing " + kCatalogueFile + ")");
  auto lock = FolderLock::Acquire(dir, /*shared=*/read_only);
  if (!lock) return std::unexpected(lock.error());
  auto catalogue = Catalogue::Open(catalogue_path);
  if (!catalogue) return std::unexpected(catalogue.error());
  if (read_only && (*catalogue)->meta().schema_version != kSchemaVersion) {
    return Fail(ErrorCode::kIncompatible, "index " + dir + " was written by an earlier build: open it once for "
                                          "writing (oxbow index info) to migrate it, then read it");
  }
  // Every record is read below, but a damaged row can read as another valid one (an id changed in
  // place): SQLite's check of the records and their id index finds it.
  if (auto s = (*catalogue)->CheckRecords(); !s) return std::unexpected(s.error());
  const CatalogueMeta& meta = (*catalogue)->meta();
  // The vocabulary (about a second for 100k words with Hamming parameters) is read while the checkpoint
  // loads, which needs only its size; any fault of the vocabulary is still reported first.
  auto reading = std::async(std::launch::async, [path = JoinPath(dir, kVocabularyFile)] { return vocab::Vocabulary::Read(path); });
  std::optional<Result<LoadedCheckpoint>> loaded;
  if (meta.schema_version == kSchemaVersion && !meta.checkpoint.empty()) {
    loaded = LoadCheckpoint(dir, **catalogue, meta.vocabulary_size, options);
  }
  auto vocabulary = reading.get();
  if (auto s = CheckVocabularyCopy(dir, meta, vocabulary); !s) return std::unexpected(s.error());
  if (meta.descriptor_kind != sift::DescriptorKindName(vocabulary->descriptor_kind())) {
    return Fail(ErrorCode::kIncompatible, "index " + dir + ": descriptor kind of the catalogue and vocabulary differ");
  }

  const size_t vocab_size = vocabulary->size();
  auto impl = std::make_unique<Impl>(dir, options, std::move(*vocabulary), meta.extractor_settings);
  impl->folder_lock = std::move(*lock);
  std::shared_ptr<Snapshot> snap;
  std::vector<DamagedBlob> damaged;
  Checkpointer::Start start;
  if (loaded) {
    if (!*loaded) return std::unexpected(loaded->error());
    start = StartFrom(std::move(**loaded), dir, &snap, &damaged);
  }
  const bool rebuild = snap == nullptr;
  if (rebuild) {
    auto built = BuildFromCatalogue(**catalogue, vocab_size, options, &damaged);
    if (!built) return std::unexpected(built.error());
    snap = std::move(*built);
  }
  if (read_only) {
    // Nothing is written: a damaged image is only left out of the snapshot, a checkpoint to rebuild is
    // rebuilt in memory only, and there is no checkpointer.
    for (const DamagedBlob& blob : damaged) {
      OXBOW_LOG(kError) << "index " << dir << ": " << blob.why << "; the image is left out of this read-only open "
                        << "(open the index for writing to drop it, then add it again from its source image)";
    }
    auto sequence = (*catalogue)->WriteSequence();
    if (!sequence) return std::unexpected(sequence.error());
    impl->write_sequence = *sequence;
    impl->read_only = true;
    impl->catalogue = std::move(*catalogue);
    impl->Publish(std::move(snap));
    return std::unique_ptr<ImageIndex>(new ImageIndex(std::move(impl)));
  }
  // Everything read is validated: only now may the catalogue be opened for writing (catalogue.h).
  if (auto writable = (*catalogue)->OpenForWriting(); !writable) return std::unexpected(writable.error());
  // The images whose BLOB is damaged are not in the snapshot: their rows go too, so that the catalogue
  // and the index agree (a checkpoint covers their numbers) and their ids may be added again.
  for (const DamagedBlob& blob : damaged) {
    OXBOW_LOG(kError) << "index " << dir << ": " << blob.why << "; the image is dropped from the index (its catalogue "
                      << "row deleted): add it again from its source image";
    if (auto s = (*catalogue)->Delete(blob.number); !s) return std::unexpected(s.error());
  }
  auto sequence = (*catalogue)->WriteSequence();
  if (!sequence) return std::unexpected(sequence.error());
  impl->write_sequence = *sequence;
  impl->catalogue = std::move(*catalogue);
  if (rebuild) {
    start.forced = true;  // written in the background: the index is ready now
  } else {
    RemoveUnreferencedCheckpointFiles(dir, start.manifest);  // leftovers of a crash
  }
  impl->Publish(std::move(snap));
  impl->StartCheckpointer(std::move(start));
  return std::unique_ptr<ImageIndex>(new ImageIndex(std::move(impl)));
}

Result<ImageRecord> ImageIndex::Add(const std::string& id, const sift::FeatureSet& features, const ImageInfo& info) {
  return impl_->Write(id, features, info, /*replace=*/false);
}

Result<ImageRecord> ImageIndex::Replace(const std::string& id, const sift::FeatureSet& features,
                                        const ImageInfo& info) {
  return impl_->Write(id, features, info, /*replace=*/true);
}

Result<ImageIndex::Impl::Prepared> ImageIndex::Impl::Prepare(const std::string& id, const sift::FeatureSet& features,
                                                              const ImageInfo& info,
                                                              std::span<const uint32_t> assigned,
                                                              std::span<const uint64_t> assigned_signatures,
                                                              int quantizer_threads, BlobBlock* block) const {
  if (auto s = CheckId(id); !s) return std::unexpected(s.error());
  const std::string what = "image '" + id + "'";
  if (auto s = CheckFeatures(features, vocabulary, what, !assigned.empty()); !s) return std::unexpected(s.error());
  if (!assigned.empty()) {
    if (assigned.size() != features.keypoints.size()) {
      return Fail(ErrorCode::kInvalidArgument, what + ": " + std::to_string(assigned.size()) + " words for " +
                                                   std::to_string(features.keypoints.size()) + " keypoints");
    }
    const size_t vocabulary_size = vocabulary.size();
    for (const uint32_t w : assigned) {
      if (w >= vocabulary_size) return Fail(ErrorCode::kInvalidArgument, what + ": word outside the vocabulary");
    }
  }
  if (!assigned_signatures.empty()) {
    if (assigned.empty() || assigned_signatures.size() != assigned.size()) {
      return Fail(ErrorCode::kInvalidArgument, what + ": " + std::to_string(assigned_signatures.size()) +
                                                   " signatures for " + std::to_string(assigned.size()) +
                                                   " assigned words");
    }
    if (!vocabulary.has_hamming()) {
      return Fail(ErrorCode::kInvalidArgument,
                  what + ": signatures given, but the index's vocabulary has no Hamming-embedding parameters");
    }
  }
  if (auto s = CheckSettings(info.extractor_settings, extractor_settings, "features of '" + id + "'"); !s) {
    return std::unexpected(s.error());
  }
  std::vector<uint32_t> words(assigned.begin(), assigned.end());
  if (assigned.empty()) {
    words.resize(features.size());
    vocab::QuantizerOptions quantizer = index_options.quantizer;
    quantizer.num_threads = quantizer_threads;
    vocabulary.Quantize(features.descriptors, words, quantizer);
  }
  // Signatures need the descriptors, which pre-assigned words may come without.
  std::span<const uint64_t> signatures = assigned_signatures;
  std::vector<uint64_t> computed;
  if (signatures.empty() && vocabulary.has_hamming() &&
      features.descriptors.size() == words.size() * vocabulary.dimension()) {
    computed.resize(words.size());
    vocabulary.Signatures(features.descriptors, words, computed);
    signatures = computed;
  }
  Prepared out;
  out.entry = std::make_shared<Entry>();
  const size_t blob_bytes = PackedFeatures::BlobBytes(words.size(), !signatures.empty());
  std::span<uint8_t> blob = block != nullptr ? block->Take(blob_bytes) : std::span<uint8_t>();
  std::shared_ptr<const void> owner;
  if (blob.empty()) {
    auto own = std::make_shared<std::vector<uint8_t>>(blob_bytes);
    blob = *own;
    owner = std::move(own);
  } else {
    owner = block->owner();
  }
  out.entry->stored = PackedFeatures::PackBlob(features.keypoints, words, features.image_width,
                                               features.image_height, signatures, blob, std::move(owner));
  out.entry->record = ImageRecord{.id = id, .source_path = info.source_path, .width = features.image_width,
                                  .height = features.image_height,
                                  .num_features = static_cast<uint32_t>(features.size()),
                                  .metadata_json = info.metadata_json, .added_unix_ms = NowUnixMs()};
  out.bag = out.entry->stored.Bag();
  out.blob = blob;
  return out;
}

void ImageIndex::Impl::Link(std::span<const uint32_t> numbers, std::span<Prepared* const> images, Snapshot& next) {
  std::vector<const BagOfWords*> bags;
  bags.reserve(images.size());
  for (const Prepared* p : images) bags.push_back(&p->bag);
  next.inverted = next.inverted.WithAdded(numbers, bags);
  {
    CowArray<std::shared_ptr<const Entry>>::Editor editor(&next.entries);
    editor.Resize(std::max<size_t>(next.entries.size(), size_t{numbers.back()} + 1));
    for (size_t i = 0; i < numbers.size(); ++i) editor.Mutable(numbers[i]) = images[i]->entry;
  }
  std::map<size_t, std::shared_ptr<IdShard>> shards;  // each touched shard copied once
  for (size_t i = 0; i < numbers.size(); ++i) {
    const std::string& id = images[i]->entry->record.id;
    auto& shard = shards[ShardOf(id)];
    if (!shard) shard = std::make_shared<IdShard>(*next.ids[ShardOf(id)]);
    (*shard)[id] = numbers[i];
    next.geometry_bytes += images[i]->entry->MemoryBytes();
  }
  for (auto& [i, shard] : shards) next.ids[i] = std::move(shard);
}

Result<ImageRecord> ImageIndex::Impl::Write(const std::string& id, const sift::FeatureSet& features,
                                            const ImageInfo& info, bool replace) {
  if (auto writable = Writable(); !writable) return std::unexpected(writable.error());
  const auto taken = [&] { return Fail(ErrorCode::kAlreadyExists, "an image with id '" + id + "' is already indexed"); };
  if (!replace && Current()->Find(id)) return taken();
  // Quantise outside the writer lock: it is the expensive part and needs no shared state.
  auto prepared = Prepare(id, features, info, {}, {}, index_options.num_threads);
  if (!prepared) return std::unexpected(prepared.error());

  std::lock_guard<std::mutex> writer(writer_mutex);
  const auto current = Current();
  uint32_t old_number = 0;
  const Entry* old = current->Find(id, &old_number);
  if (old && !replace) return taken();
  const BagOfWords old_bag = old ? old->features().Bag() : BagOfWords{};
  // Durable first: once the catalogue returns, the row is committed (a replacement in the same
  // transaction as the removal of the old row); the snapshot then makes it visible.
  const ImageRecord& record = prepared->entry->record;
  auto number = old ? catalogue->Replace(old_number, record, prepared->blob) : catalogue->Insert(record, prepared->blob);
  if (!number) return std::unexpected(number.error());
  next_number = static_cast<uint64_t>(*number) + 1;

  // One snapshot with both changes: a query sees the old image or the new one, never neither.
  auto next = std::make_shared<Snapshot>(*current);
  if (old) Unlink(*current, old_number, *old, old_bag, *next);
  const std::array<uint32_t, 1> numbers = {static_cast<uint32_t>(*number)};
  const std::array<Prepared*, 1> images = {&*prepared};
  Link(numbers, images, *next);
  Publish(std::move(next));
  Changed(old ? 2 : 1);
  return record;
}

std::vector<Result<ImageRecord>> ImageIndex::AddBatch(std::span<const BatchImage> images) {
  if (auto writable = impl_->Writable(); !writable) {
    return std::vector<Result<ImageRecord>>(images.size(), std::unexpected(writable.error()));
  }
  std::vector<Result<ImageRecord>> results(images.size(), Fail(ErrorCode::kInvalidArgument, "not processed"));
  std::vector<Impl::Prepared> prepared(images.size());  // valid where state[i] is kReady
  // Per image, under state_mutex while the images are prepared: the commit below reads them as they
  // are decided.
  enum : uint8_t { kPending, kReady, kFailed };
  std::vector<uint8_t> state(images.size(), kPending);
  std::mutex state_mutex;
  std::condition_variable decided;
  bool abandoned = false;  // state_mutex: preparing stopped by an exception; the commit rolls back
  size_t blob_capacity = 0;  // every image's BLOB with signatures (8-byte aligned): an upper bound
  for (const BatchImage& b : images) {
    if (b.features != nullptr) blob_capacity += (PackedFeatures::BlobBytes(b.features->size(), true) + 7) / 8 * 8;
  }
  BlobBlock block(blob_capacity);

  const auto prepare_all = [&] {
    ParallelFor(images.size(), impl_->index_options.num_threads, 1, [&](size_t begin, size_t end, int) {
      for (size_t i = begin; i < end; ++i) {
        uint8_t outcome = kFailed;
        if (images[i].features == nullptr) {
          results[i] = Fail(ErrorCode::kInvalidArgument, "image '" + images[i].id + "': no features");
        } else if (auto p = impl_->Prepare(images[i].id, *images[i].features, images[i].info, images[i].words,
                                           images[i].signatures, 1, &block)) {
          prepared[i] = std::move(*p);
          outcome = kReady;
        } else {
          results[i] = std::unexpected(p.error());
        }
        {
          std::lock_guard<std::mutex> lock(state_mutex);
          state[i] = outcome;
        }
        decided.notify_one();
      }
    });
  };
  // Images to quantise are prepared before the writer lock is taken: quantising is the long part, and
  // other writers go on meanwhile. With every image's words given (bulk ingest), preparing is short,
  // and the lock is taken first: the catalogue then takes each image's rows while the later images are
  // still prepared, so that only the last rows and the COMMIT are left after them.
  const bool quantise = std::any_of(images.begin(), images.end(), [](const BatchImage& b) { return b.words.empty(); });
  if (quantise) prepare_all();
  std::lock_guard<std::mutex> writer(impl_->writer_mutex);
  const auto current = impl_->Current();
  // An image is added unless its id is indexed or came earlier in the batch. Asked in order, once by
  // the commit (as the images become ready) and once after preparing: the same answers.
  const auto admitted = [&](size_t i, std::unordered_set<std::string_view>* seen) {
    return !current->Find(images[i].id) && seen->insert(images[i].id).second;
  };
  // One transaction for the batch. Where no thread can be started, std::async runs it in this thread
  // at get(), when every image is decided.
  auto commit = std::async(std::launch::async | std::launch::deferred, [&] {
    std::unordered_set<std::string_view> seen;
    size_t i = 0;
    return impl_->catalogue->InsertMany([&]() -> Result<std::optional<Catalogue::Row>> {
      for (; i < images.size(); ++i) {
        {
          std::unique_lock<std::mutex> lock(state_mutex);
          decided.wait(lock, [&] { return state[i] != kPending || abandoned; });
          if (abandoned) return Fail(ErrorCode::kInternal, "the batch was abandoned");
          if (state[i] != kReady) continue;
        }
        if (!admitted(i, &seen)) continue;
        const Impl::Prepared& p = prepared[i++];
        return Catalogue::Row{&p.entry->record, p.blob};
      }
      return std::nullopt;
    });
  });
  if (!quantise) {
    try {
      prepare_all();
    } catch (...) {
      {
        std::lock_guard<std::mutex> lock(state_mutex);
        abandoned = true;
      }
      decided.notify_one();
      commit.wait();
      throw;
    }
  }

  std::vector<size_t> chosen;  // positions committed, in order
  std::unordered_set<std::string_view> seen;
  for (size_t i = 0; i < images.size(); ++i) {
    if (state[i] != kReady) continue;
    if (!admitted(i, &seen)) {
      results[i] = Fail(ErrorCode::kAlreadyExists, "an image with id '" + images[i].id + "' is already indexed");
      continue;
    }
    chosen.push_back(i);
  }
  if (chosen.empty()) {
    (void)commit.get();  // an empty transaction: nothing written
    return results;
  }
  std::vector<Impl::Prepared*> linked;
  linked.reserve(chosen.size());
  for (const size_t i : chosen) linked.push_back(&prepared[i]);
  // The next snapshot is built while the catalogue commits (they share nothing but `current` and the
  // prepared images, read-only), on the numbers the catalogue will most likely give: AUTOINCREMENT
  // numbers a transaction's rows consecutively after the highest number it ever gave. It is published
  // only after the commit, and built again on the numbers given when the guess was wrong.
  const uint64_t first = std::max<uint64_t>({impl_->next_number, current->entries.size(), 1});
  std::vector<uint32_t> guessed;
  std::shared_ptr<Snapshot> next;
  if (first + chosen.size() <= uint64_t{1} << 31) {
    guessed.resize(chosen.size());
    std::iota(guessed.begin(), guessed.end(), static_cast<uint32_t>(first));
    next = std::make_shared<Snapshot>(*current);
    Impl::Link(guessed, linked, *next);
  }
  auto numbers = commit.get();
  if (!numbers) {
    for (const size_t i : chosen) results[i] = std::unexpected(numbers.error());
    return results;
  }
  OXBOW_CHECK(numbers->size() == chosen.size(), "the commit and the snapshot chose different images");
  std::vector<uint32_t> committed(numbers->begin(), numbers->end());
  impl_->next_number = uint64_t{committed.back()} + 1;
  if (committed != guessed) {
    next = std::make_shared<Snapshot>(*current);
    Impl::Link(committed, linked, *next);
  }
  impl_->Publish(std::move(next));
  impl_->Changed(committed.size());
  for (const size_t i : chosen) results[i] = prepared[i].entry->record;
  return results;
}

void ImageIndex::Impl::Unlink(const Snapshot& current, uint32_t n, const Entry& entry, const BagOfWords& bag,
                              Snapshot& next) {
  const std::array<uint32_t, 1> numbers = {n};
  const std::array<const BagOfWords*, 1> bags = {&bag};
  next.inverted = current.inverted.WithRemoved(numbers, bags);
  next.geometry_bytes -= entry.MemoryBytes();
  {
    CowArray<std::shared_ptr<const Entry>>::Editor editor(&next.entries);
    editor.Mutable(n) = nullptr;
  }
  auto shard = std::make_shared<IdShard>(*current.ids[ShardOf(entry.record.id)]);
  shard->erase(entry.record.id);
  next.ids[ShardOf(entry.record.id)] = std::move(shard);
}

Status ImageIndex::Remove(const std::string& id) {
  if (auto writable = impl_->Writable(); !writable) return writable;
  std::lock_guard<std::mutex> writer(impl_->writer_mutex);
  const auto current = impl_->Current();
  uint32_t n = 0;
  const Entry* entry = current->Find(id, &n);
  if (!entry) return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
  const BagOfWords bag = entry->features().Bag();
  if (auto s = impl_->catalogue->Delete(n); !s) return s;

  auto next = std::make_shared<Snapshot>(*current);
  Impl::Unlink(*current, n, *entry, bag, *next);
  impl_->Publish(std::move(next));
  impl_->Changed(1);
  return Ok();
}

uint64_t ImageIndex::write_sequence() const { return impl_->write_sequence.load(); }

Result<ImageRecord> ImageIndex::Get(const std::string& id) const {
  const auto snap = impl_->Current();
  const Entry* entry = snap->Find(id);
  if (!entry) return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
  return entry->record;
}

bool ImageIndex::Contains(const std::string& id) const { return impl_->Current()->Find(id) != nullptr; }

Result<std::vector<ImageRecord>> ImageIndex::List(uint64_t offset, uint64_t limit) const {
  const auto snap = impl_->Current();
  std::vector<std::pair<std::string, uint32_t>> all;
  for (const auto& shard : snap->ids) all.insert(all.end(), shard->begin(), shard->end());
  std::sort(all.begin(), all.end());
  std::vector<ImageRecord> out;
  for (uint64_t i = offset; i < all.size() && out.size() < limit; ++i) {
    out.push_back(snap->entries[all[i].second]->record);
  }
  return out;
}


std::unique_ptr<search::Source> ImageIndex::OpenSearch() const {
  return search::OpenSnapshotSearch(impl_->Current(), impl_->index_options.num_threads);
}

Result<QueryResponse> ImageIndex::Query(const sift::FeatureSet& query, const QueryOptions& options) const {
  const auto t0 = Clock::now();
  const SearchActivity::Scope in_flight(impl_->searches);
  const LatencySensitiveScope latency;  // the pool's helpers stay awake between this search's stages
  if (auto e = options.Check()) return Fail(ErrorCode::kInvalidArgument, "query options: " + *e);
  if (auto s = CheckFeatures(query, impl_->vocabulary, "the query"); !s) return std::unexpected(s.error());
  if (auto s = CheckSettings(options.extractor_settings, impl_->extractor_settings, "the query features"); !s) {
    return std::unexpected(s.error());
  }
  const std::unique_ptr<search::Source> source = search::OpenSnapshotSearch(impl_->Current(), impl_->index_options.num_threads);
  // A query's descriptors on the index's threads, as its re-ranking: latency, not throughput.
  vocab::QuantizerOptions quantizer = impl_->index_options.quantizer;
  quantizer.num_threads = impl_->index_options.num_threads;
  const search::QueryFeatures q = search::PrepareQuery(query, impl_->vocabulary, options, quantizer);
  QueryTimings timings;
  timings.quantize_ms = MsSince(t0);
  auto response = search::Run(*source, q, options, timings);
  if (response) response->timings.total_ms = MsSince(t0);
  return response;
}

Result<QueryResponse> ImageIndex::QuerySimilar(const std::string& id, const QueryOptions& options) const {
  const auto t0 = Clock::now();
  const SearchActivity::Scope in_flight(impl_->searches);
  const LatencySensitiveScope latency;  // the pool's helpers stay awake between this search's stages
  if (auto e = options.Check()) return Fail(ErrorCode::kInvalidArgument, "query options: " + *e);
  const std::unique_ptr<search::Source> source = search::OpenSnapshotSearch(impl_->Current(), impl_->index_options.num_threads);
  ImageRecord record;
  auto q = search::StoredQuery(*source, id, options, &record);
  if (!q) return std::unexpected(q.error());
  auto response = search::Run(*source, *q, options, QueryTimings{});
  if (response) response->timings.total_ms = MsSince(t0);
  return response;
}

Status ImageIndex::PinCollectionStatistics(uint64_t num_images, std::span<const uint32_t> document_frequency) {
  if (auto writable = impl_->Writable(); !writable) return writable;
  if (document_frequency.size() != impl_->vocabulary.size())
    return Fail(ErrorCode::kInvalidArgument, "collection statistics of " + std::to_string(document_frequency.size()) +
                                                 " words for a vocabulary of " + std::to_string(impl_->vocabulary.size()));
  std::lock_guard<std::mutex> writer(impl_->writer_mutex);
  auto next = std::make_shared<Snapshot>(*impl_->Current());
  next->inverted = next->inverted.WithPinnedStatistics(num_images, document_frequency, impl_->index_options.num_threads);
  impl_->Publish(std::move(next));
  return Ok();
}

ImageIndex::LiveCounts ImageIndex::CountLive() const {
  const auto snap = impl_->Current();
  LiveCounts counts;
  counts.num_images = snap->inverted.num_images();
  counts.document_frequency.resize(impl_->vocabulary.size());
  for (uint32_t w = 0; w < counts.document_frequency.size(); ++w)
    counts.document_frequency[w] = snap->inverted.DocumentFrequency(w);
  return counts;
}

IndexStats ImageIndex::Stats() const {
  const auto snap = impl_->Current();
  const InvertedFileStats s = snap->inverted.Stats();
  IndexStats out;
  out.num_images = s.num_images;
  out.num_features = s.num_features;
  out.postings_bytes = s.postings_bytes;
  out.geometry_bytes = snap->geometry_bytes;
  out.other_bytes = s.image_table_bytes + s.word_table_bytes + snap->entries.MemoryBytes();
  for (const auto& shard : snap->ids) out.other_bytes += shard->size() * 64;
  const uint64_t total = out.postings_bytes + out.geometry_bytes + out.other_bytes;
  out.bytes_per_feature = out.num_features ? static_cast<double>(total) / static_cast<double>(out.num_features) : 0.0;
  out.num_segments = s.num_segments;
  out.vocabulary_size = impl_->vocabulary.size();
  out.vocabulary_fingerprint = impl_->vocabulary.fingerprint();
  return out;
}

const vocab::Vocabulary& ImageIndex::vocabulary() const { return impl_->vocabulary; }
const std::string& ImageIndex::extractor_settings() const { return impl_->extractor_settings; }
const std::string& ImageIndex::directory() const { return impl_->dir; }

}  // namespace oxbow::index
