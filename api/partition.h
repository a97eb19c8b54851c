// A cluster: an index split into P partitions by image id, built by `oxbow index build --mpi`
// and served by one `oxbow serve --index CLUSTER/partition-k` per partition behind a front.
//
// Layout of a cluster folder:
//   CLUSTER/partition-0 .. partition-(P-1)   ordinary index folders (index/image_index.h)
//   CLUSTER/partition-k/global-frequencies.oxdf
//                                            the document frequency of every word over the whole
//                                            cluster and the cluster's image count (GlobalFrequencies),
//                                            so that every partition can score with the global idf
//
// An image belongs to partition PartitionOf(id, P): FNV-1a 64 of the id's bytes, modulo P. Builders
// and the front that routes writes must both call this function; changing it moves every image.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "index/image_index.h"
#include "sift/base/error.h"

namespace oxbow::api {

// The partition of image `id` among `num_partitions` (>= 1): Fnv1a64(id) % num_partitions.
uint32_t PartitionOf(std::string_view id, uint32_t num_partitions);

// "<cluster>/partition-<partition>".
std::string PartitionFolder(const std::string& cluster, uint32_t partition);

// File name of the global frequencies inside a partition folder.
inline constexpr std::string_view kGlobalFrequenciesFile = "global-frequencies.oxdf";

// Document frequencies over a whole cluster, as stored beside each partition. File: a binary_io.h
// container, magic "OXBWGLDF", version 1, payload (host byte order, recorded in the header):
//   u32 num_partitions, u32 partition, u64 vocabulary_fingerprint, u64 num_images,
//   u64 num_words, u32 document_frequency[num_words]
struct GlobalFrequencies {
  uint32_t num_partitions = 0;              // P of the cluster
  uint32_t partition = 0;                   // the partition this copy sits in, < P
  uint64_t vocabulary_fingerprint = 0;      // vocab::Vocabulary::fingerprint() of the words counted
  uint64_t num_images = 0;                  // images in the whole cluster (N of the idf)
  std::vector<uint32_t> document_frequency; // per word: images of the whole cluster containing it

  bool operator==(const GlobalFrequencies&) const = default;
};

// Atomic write (temp file, fsync, rename). kIoError on failure.
[[nodiscard]] Status WriteGlobalFrequencies(const std::string& path, const GlobalFrequencies& frequencies);
// kNotFound, kCorruptData (damaged, truncated, inconsistent), kIncompatible (unknown version).
[[nodiscard]] Result<GlobalFrequencies> ReadGlobalFrequencies(const std::string& path);

// When `index_dir` holds kGlobalFrequenciesFile (a partition of a cluster), makes `index` score with
// those statistics (index::ImageIndex::PinCollectionStatistics), so that its scores are the ones a
// single index of the whole cluster gives. Ok without the file; kIncompatible for another vocabulary.
[[nodiscard]] Status PinClusterStatistics(const std::string& index_dir, index::ImageIndex& index);

// Writes `frequencies` as `index_dir`'s kGlobalFrequenciesFile (atomic), then pins them on `index`: a
// refresh of the cluster's statistics (server/cluster/front.h). The file first, so that a restart
// scores as before it. kIncompatible for another vocabulary, kInvalidArgument (a frequency per word, each
// <= the image count, partition < partitions), kIoError.
[[nodiscard]] Status StoreClusterStatistics(const std::string& index_dir, index::ImageIndex& index,
                                            const GlobalFrequencies& frequencies);

}  // namespace oxbow::api
