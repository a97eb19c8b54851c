// Partition routing and the global frequency file (see partition.h).
#include "api/partition.h"

#include "sift/base/binary_io.h"
#include "sift/base/hash.h"
#include "sift/base/log.h"

namespace oxbow::api {
namespace {
constexpr std::string_view kMagic = "OXBWGLDF";
constexpr uint32_t kVersion = 1;
}  // namespace

uint32_t PartitionOf(std::string_view id, uint32_t num_partitions) {
  OXBOW_CHECK(num_partitions >= 1, "a cluster has at least one partition");
  return static_cast<uint32_t>(Fnv1a64(id) % num_partitions);
}

std::string PartitionFolder(const std::string& cluster, uint32_t partition) {
  return cluster + "/partition-" + std::to_string(partition);
}

Status WriteGlobalFrequencies(const std::string& path, const GlobalFrequencies& f) {
  io::ByteWriter w;
  w.Put(f.num_partitions);
  w.Put(f.partition);
  w.Put(f.vocabulary_fingerprint);
  w.Put(f.num_images);
  w.Put(uint64_t{f.document_frequency.size()});
  w.PutArray(std::span<const uint32_t>(f.document_frequency));
  return io::WriteContainerFile(path, kMagic, kVersion, 0, w.bytes());
}

Result<GlobalFrequencies> ReadGlobalFrequencies(const std::string& path) {
  auto container = io::ReadContainerFile(path, kMagic, kVersion, kVersion);
  if (!container) return std::unexpected(container.error());
  io::ByteReader r(container->payload, "global frequencies " + path);
  GlobalFrequencies f;
  auto partitions = r.Get<uint32_t>();
  auto partition = r.Get<uint32_t>();
  auto fingerprint = r.Get<uint64_t>();
  auto images = r.Get<uint64_t>();
  auto words = r.Get<uint64_t>();
  if (!partitions || !partition || !fingerprint || !images || !words)
    return Fail(ErrorCode::kCorruptData, "global frequencies " + path + ": truncated header");
  if (*partitions == 0 || *partition >= *partitions || *words != r.remaining() / sizeof(uint32_t) ||
      r.remaining() % sizeof(uint32_t) != 0)
    return Fail(ErrorCode::kCorruptData, "global frequencies " + path + ": inconsistent header");
  f.num_partitions = *partitions;
  f.partition = *partition;
  f.vocabulary_fingerprint = *fingerprint;
  f.num_images = *images;
  f.document_frequency.resize(*words);
  if (auto s = r.GetArray(std::span<uint32_t>(f.document_frequency)); !s) return std::unexpected(s.error());
  for (uint32_t df : f.document_frequency)
    if (df > f.num_images)
      return Fail(ErrorCode::kCorruptData, "global frequencies " + path + ": a frequency exceeds the image count");
  return f;
}

Status PinClusterStatistics(const std::string& index_dir, index::ImageIndex& index) {
  const std::string path = index_dir + "/" + std::string(kGlobalFrequenciesFile);
  auto frequencies = ReadGlobalFrequencies(path);
  if (!frequencies && frequencies.error().code == ErrorCode::kNotFound) return Ok();
  if (!frequencies) return std::unexpected(frequencies.error());
  if (frequencies->vocabulary_fingerprint != index.vocabulary().fingerprint())
    return Fail(ErrorCode::kIncompatible, path + " counts the words of another vocabulary than the index's");
  if (auto s = index.PinCollectionStatistics(frequencies->num_images, frequencies->document_frequency); !s) return s;
  OXBOW_LOG(kInfo) << "partition " << frequencies->partition << " of " << frequencies->num_partitions
                   << ": scoring with the cluster's statistics (" << frequencies->num_images << " images)";
  return Ok();
}

Status StoreClusterStatistics(const std::string& index_dir, index::ImageIndex& index,
                              const GlobalFrequencies& frequencies) {
  if (frequencies.vocabulary_fingerprint != index.vocabulary().fingerprint())
    return Fail(ErrorCode::kIncompatible, "cluster statistics of another vocabulary than the index's");
  if (frequencies.document_frequency.size() != index.vocabulary().size())
    return Fail(ErrorCode::kInvalidArgument, "cluster statistics need one frequency per word of the vocabulary");
  if (frequencies.num_partitions == 0 || frequencies.partition >= frequencies.num_partitions)
    return Fail(ErrorCode::kInvalidArgument, "cluster statistics: the partition must be < the number of partitions");
  for (uint32_t df : frequencies.document_frequency)
    if (df > frequencies.num_images)
      return Fail(ErrorCode::kInvalidArgument, "cluster statistics: a frequency exceeds the image count");
  const std::string path = index_dir + "/" + std::string(kGlobalFrequenciesFile);
  if (auto s = WriteGlobalFrequencies(path, frequencies); !s) return s;
  if (auto s = index.PinCollectionStatistics(frequencies.num_images, frequencies.document_frequency); !s) return s;
  OXBOW_LOG(kInfo) << "partition " << frequencies.partition << " of " << frequencies.num_partitions
                   << ": scoring with refreshed cluster statistics (" << frequencies.num_images << " images)";
  return Ok();
}

}  // namespace oxbow::api
