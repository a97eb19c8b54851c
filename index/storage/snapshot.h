// The in-memory state of an index that a reader sees: one immutable Snapshot (the inverted file, every
// image's entry, the id map), published whole by the write path (image_index.cc) and by the
// checkpointer (checkpointer.h), read by searches (search/snapshot_source.h) and by the facade's
// Get/List/Stats. Internal to oxbow_index.
//
// Thread safety: a published Snapshot and the Entries it holds are never changed; any number of threads
// may read one. A writer copies the current one (sharing every unchanged chunk and shard), changes the
// copy, and publishes it through CurrentSnapshot.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "index/cow_array.h"
#include "index/image_index.h"
#include "index/postings/inverted_file.h"
#include "index/storage/feature_store.h"
#include "index/storage/geometry_parts.h"

namespace oxbow::index {

// One indexed image: its catalogue record and packed words + geometry. Immutable once published.
struct Entry {
  ImageRecord record;
  PackedFeatures stored;                      // read it through features()
  std::shared_ptr<const GeometryPart> part;   // set when `stored` views a checkpoint's geometry file
  uint32_t number = 0;                        // with `part`: the image's number
  std::optional<uint64_t> checksum;           // with `part`: its checksum in the file, when it has them

  // Its features to use: `stored` when they are in memory (a copy that shares them), else a checked
  // copy of its data in the geometry file (GeometryPart::Checked), which the result owns.
  PackedFeatures features() const { return part ? part->Checked(number, stored, checksum) : stored; }
  // Bytes of memory its features take (IndexStats::geometry_bytes): a view of a geometry file takes
  // none beyond itself (the file's pages are the page cache's).
  uint64_t MemoryBytes() const { return part ? sizeof(PackedFeatures) : stored.MemoryBytes(); }
  // features(), held by *copy (returned): when the image is in a geometry file, its data copied into
  // `buffer` (reused by the caller: a search reads a thousand candidates' features once each) and
  // checked there.
  const PackedFeatures& SignedFeatures(std::vector<uint8_t>* buffer, PackedFeatures* copy) const;
};

// A write copies the id-map shards it touches (readers keep the old ones), so their number sets a batch
// add's cost: with 64 shards a batch of 1000 images copied the whole map, which at 300k images took
// about 100 ms a batch and grew with the collection; with 16384 it copies about 6% of it, and a single
// add 1/16384 (each write also copies the 16384 pointers, 0.1-0.2 ms).
inline constexpr size_t kIdShards = 16384;
using IdShard = std::unordered_map<std::string, uint32_t>;
inline size_t ShardOf(const std::string& id) { return std::hash<std::string>{}(id) % kIdShards; }

// Everything a reader needs, immutable once published.
struct Snapshot {
  InvertedFile inverted;
  CowArray<std::shared_ptr<const Entry>> entries;  // by image number; null for unused/removed numbers
  std::array<std::shared_ptr<const IdShard>, kIdShards> ids;
  uint64_t geometry_bytes = 0;                     // sum of the entries' MemoryBytes()

  explicit Snapshot(InvertedFile file) : inverted(std::move(file)) {}

  // The entry of image `id` (null when not indexed); *number gets its number.
  const Entry* Find(const std::string& id, uint32_t* number = nullptr) const {
    const IdShard& shard = *ids[ShardOf(id)];
    const auto it = shard.find(id);
    if (it == shard.end()) return nullptr;
    if (number) *number = it->second;
    return entries[it->second].get();
  }
};

// The snapshot of `inverted` with the entries by_number[n] (moved from; null where no image), its id
// maps built on `num_threads` threads.
std::shared_ptr<Snapshot> MakeSnapshot(InvertedFile inverted, std::vector<std::shared_ptr<const Entry>>& by_number,
                                       int num_threads);

// Whether `record` agrees with `features` (count and image size).
inline bool RecordMatches(const ImageRecord& record, const PackedFeatures& features) {
  return features.size() == record.num_features && features.width() == record.width &&
         features.height() == record.height;
}

// The published snapshot of an index. Load and store are the only operations; whoever builds the next
// snapshot from Current() must hold the index's writer mutex (ImageIndex::Impl::writer_mutex) from the
// Current() to the Publish(), so that no change is lost.
class CurrentSnapshot {
 public:
  std::shared_ptr<const Snapshot> Current() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return snapshot_;
  }
  void Publish(std::shared_ptr<const Snapshot> next) {
    std::lock_guard<std::mutex> lock(mutex_);
    snapshot_ = std::move(next);
  }

 private:
  // mutex_ guards only the snapshot_ pointer, held for a copy of it: a leaf, taken under any other lock.
  mutable std::mutex mutex_;
  std::shared_ptr<const Snapshot> snapshot_;
};

}  // namespace oxbow::index
