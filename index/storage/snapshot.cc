#include "index/storage/snapshot.h"

#include <algorithm>

#include "sift/base/parallel.h"

namespace oxbow::index {

const PackedFeatures& Entry::SignedFeatures(std::vector<uint8_t>* buffer, PackedFeatures* copy) const {
  if (part) {
    buffer->resize(GeometryPart::DataBytes(stored));
    if (part->CopyChecked(number, stored, checksum, *buffer, nullptr, copy)) return *copy;
  }
  *copy = features();
  return *copy;
}

std::shared_ptr<Snapshot> MakeSnapshot(InvertedFile inverted, std::vector<std::shared_ptr<const Entry>>& by_number,
                                       int num_threads) {
  auto snap = std::make_shared<Snapshot>(std::move(inverted));
  const auto num_numbers = static_cast<uint32_t>(std::max<size_t>(by_number.size(), snap->inverted.num_numbers()));
  // The id maps, a shard per task (sized first: a million ids would otherwise rehash each map ~20 times).
  static_assert(kIdShards <= 65536);
  std::vector<uint16_t> shard_of(by_number.size(), 0);
  ParallelFor(by_number.size(), num_threads, size_t{1} << 14, [&](size_t begin, size_t end, int) {
    for (size_t n = begin; n < end; ++n) {
      if (by_number[n]) shard_of[n] = static_cast<uint16_t>(ShardOf(by_number[n]->record.id));
    }
  });
  std::vector<std::vector<uint32_t>> members(kIdShards);
  for (uint32_t n = 0; n < by_number.size(); ++n) {
    if (by_number[n]) members[shard_of[n]].push_back(n);
  }
  std::vector<std::shared_ptr<IdShard>> shards(kIdShards);
  ParallelFor(kIdShards, num_threads, 64, [&](size_t begin, size_t end, int) {
    for (size_t i = begin; i < end; ++i) {
      shards[i] = std::make_shared<IdShard>();
      shards[i]->reserve(members[i].size());
      for (const uint32_t n : members[i]) shards[i]->emplace(by_number[n]->record.id, n);
    }
  });
  CowArray<std::shared_ptr<const Entry>>::Editor editor(&snap->entries);
  editor.Resize(num_numbers);
  for (uint32_t n = 0; n < by_number.size(); ++n) {
    if (!by_number[n]) continue;
    snap->geometry_bytes += by_number[n]->MemoryBytes();
    editor.Mutable(n) = std::move(by_number[n]);
  }
  for (size_t i = 0; i < kIdShards; ++i) snap->ids[i] = std::move(shards[i]);
  return snap;
}

}  // namespace oxbow::index
