// The document frequencies of one cluster partition's images, kept durable beside the partition while
// `oxbow index build --mpi` builds it (partition-frequencies.oxdf, container "OXBWPDFJ" v1), so that a
// resumed build knows the words of the images an earlier run indexed. Before each batch is committed
// to the index the journal is written with that batch as "pending" (ids and distinct words); on
// recovery, the pending images the index holds are counted and the others (never committed) dropped.
//
// Payload: u64 vocabulary fingerprint, u64 images counted, u64 num_words, u32 df[num_words], u64 pending
// count, per pending image: u32 id length, id bytes, u64 word count, u32 words. The container's
// atomic write (temporary file, fsync, rename) means a crash leaves the previous journal or the new
// one; a damaged file (a torn copy, flipped bits) fails the container's checksum and is refused as
// corrupt_data, as is a payload that ends early.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "index/image_index.h"
#include "sift/base/error.h"

namespace oxbow::cluster {

class FrequencyJournal {
 public:
  static constexpr std::string_view kFile = "partition-frequencies.oxdf";  // in the partition's folder

  // A journal at `path` counting words of a vocabulary with this fingerprint and size; empty until
  // Load or Recover reads the file.
  FrequencyJournal(std::string path, uint64_t vocabulary_fingerprint, size_t vocabulary_size);

  // Reads the journal if the file exists (a missing file is an empty journal) and settles its pending
  // batch: the pending images for which `committed(id)` holds are counted. kIncompatible for another
  // vocabulary's journal, kCorruptData for a damaged one.
  [[nodiscard]] Status Load(const std::function<bool(const std::string& id)>& committed);
  // Load against `idx`; the counted images must then be exactly the index's (kIncompatible otherwise:
  // the partition was changed outside `index build --mpi`).
  [[nodiscard]] Status Recover(const index::ImageIndex& idx);

  // Durably records `batch` (ids and their distinct words, each < the vocabulary size) as about to be
  // committed.
  [[nodiscard]] Status Prepare(std::vector<std::pair<std::string, std::vector<uint32_t>>> batch);
  // Counts the pending images that the index accepted (`added[i]` for the i-th of the batch).
  void Commit(const std::vector<bool>& added);
  // Writes the journal (counts and the pending batch) atomically.
  [[nodiscard]] Status Write() const;

  uint64_t images() const { return images_; }
  const std::vector<uint32_t>& document_frequency() const { return df_; }

 private:
  void Count(const std::vector<uint32_t>& distinct_words);

  std::string path_;
  uint64_t fingerprint_;
  uint64_t images_ = 0;
  std::vector<uint32_t> df_;
  std::vector<std::pair<std::string, std::vector<uint32_t>>> pending_;
};

}  // namespace oxbow::cluster
