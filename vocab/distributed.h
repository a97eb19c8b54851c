// Distributed k-means vocabulary training over a Communicator (communicator.h): every rank extracts
// and samples its own share of the images, every Lloyd iteration assigns the rank's rows locally and
// combines the per-word sums and counts with one integer all-reduce. The result does not depend on the
// number of ranks, nor on which rank got which image:
//  - Sampling is by image name (NamedSampler): every descriptor row gets a key from a seeded hash of
//    its image's name and its row number; an image keeps its SampleOptions::max_per_image rows with
//    the smallest keys, the sample is the SampleOptions::max_total rows with the smallest keys over all
//    images, ordered by key. (A different sample from DescriptorSampler's, which depends on the order
//    images are offered; single-process `Train` is unchanged.)
//  - Seeding runs on the first rows of that global order (k-means++ on min(n, k * seeding_points_per_word)
//    rows, or the first k rows for random seeding), gathered on every rank, computed on rank 0 and
//    broadcast.
//  - Sums are exact: descriptor values and squared distances are converted to 64-bit fixed point with a
//    scale chosen from the global maximum so that no sum can overflow, and integer addition does not
//    depend on the order. Empty words are re-seeded at the farthest rows (ties: lower global position).
//
// Hamming embedding (DistributedTrainOptions::hamming, WithHammingDistributed): every rank quantises
// its rows with the finished vocabulary and projects them; each word's 64 medians are then found by an
// exact distributed selection (a binary search over the bits of the values' order-preserving integer
// keys, counting with integer all-reduces). A median is a value of the multiset of a word's projected
// rows, which does not depend on how the rows are split or ordered, so the parameters are those
// Vocabulary::WithHamming learns from all ranks' rows in one process, bit for bit.
//
// Checkpoints: after every iteration rank 0 writes the centroids, every row's word and the objective
// (container "OXBWKMCP", binary_io.h) atomically. TrainDistributed resumes from a checkpoint of the same
// sample and options (any number of ranks) and gives the vocabulary the uninterrupted run gives.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "sift/base/error.h"
#include "sift/types.h"
#include "vocab/communicator.h"
#include "vocab/vocabulary.h"

namespace oxbow::vocab {

// This rank's rows of a sample drawn by NamedSampler::Finish, in global (key) order.
struct DistributedSample {
  int dimension = 0;
  std::vector<float> descriptors;     // rows x dimension, row-major
  std::vector<uint32_t> position;     // each row's position in the global sample, ascending
  uint64_t total_rows = 0;            // rows on all ranks together
  uint64_t identity = 0;              // hash of the global key list: equal samples, equal identity
  uint64_t rows_seen = 0;             // rows offered after the per-image cap, all ranks
  uint64_t images_seen = 0;           // images offered, all ranks

  size_t rows() const { return position.size(); }
};

// Samples by image name (see the file comment). Not thread-safe; images may come in any order.
class NamedSampler {
 public:
  // OXBOW_CHECKs that options are valid and dimension > 0.
  NamedSampler(const SampleOptions& options, int dimension);

  // Offers one image's descriptors (rows x dimension). `name` must identify the image the same way on
  // every rank and in every run (e.g. its path relative to the image folder).
  void AddImage(std::string_view name, std::span<const float> descriptors);

  // Collective: the global sample's rows held by this rank. Memory: every rank receives every rank's
  // candidate keys (8 bytes each, at most max_total per rank).
  DistributedSample Finish(Communicator& comm);

 private:
  void Prune(size_t keep);  // keeps the `keep` rows with the smallest keys

  SampleOptions options_;
  int dimension_;
  std::vector<float> data_;
  std::vector<uint64_t> keys_;
  uint64_t rows_seen_ = 0;
  uint64_t images_seen_ = 0;
};

struct DistributedTrainOptions {
  TrainOptions train;            // as for Train; num_threads is per rank
  // Checkpoint file (written by rank 0 after every iteration, read on start when present); empty: none.
  std::string checkpoint_path;
  // End the run after this many iterations with the checkpoint kept (a batch scheduler's time slot);
  // 0 = no limit. A later run with the same inputs continues. Range >= 0.
  int stop_after_iterations = 0;
  // Also learn Hamming-embedding parameters from the sample once the iterations are done
  // (WithHammingDistributed, seeded by train.seed, quantising on train.num_threads threads with
  // QuantizerOptions' default probes, as `vocab train` does without --mpi).
  bool hamming = false;

  std::optional<std::string> Check() const;
};

struct DistributedTrainResult {
  bool finished = false;                 // false: stopped by stop_after_iterations
  int resumed_after_iteration = 0;       // iterations the checkpoint already held (0: fresh start)
  // When finished: on rank 0, and with DistributedTrainOptions::hamming on every rank (the same).
  std::optional<Vocabulary> vocabulary;
};

// Collective: trains on the rows of all ranks' `sample`s. Every rank must pass the same options, kind
// and settings. Errors: kInvalidArgument (options, fewer rows than words, non-finite values),
// kIncompatible (a checkpoint of another sample or other options), kCorruptData / kIoError
// (checkpoint). An error on one rank is not seen by the others: callers end the job on any error.
[[nodiscard]] Result<DistributedTrainResult> TrainDistributed(const DistributedSample& sample, Communicator& comm,
                                                              sift::DescriptorKind kind, std::string extractor_settings,
                                                              const DistributedTrainOptions& options,
                                                              TrainReport* report = nullptr);

// Collective: `vocabulary` (the same on every rank) with Hamming-embedding parameters learnt from the
// rows of all ranks' `sample`s, on every rank: bit for bit vocabulary.WithHamming(all ranks' rows, seed,
// quantizer) in one process, for any number of ranks. Memory per rank: 264 bytes per local row (word,
// 64 projected keys, an index) and, for the selection, 20 bytes per word and bit of a block of at most
// 16384 words (21 MB); 32 integer all-reduces of 512 bytes per word. Errors: kInvalidArgument (a
// vocabulary below 64 dimensions, a sample of another dimension, no rows on any rank, non-finite values).
[[nodiscard]] Result<Vocabulary> WithHammingDistributed(const Vocabulary& vocabulary, const DistributedSample& sample,
                                                        Communicator& comm, uint64_t seed,
                                                        const QuantizerOptions& quantizer = {});

}  // namespace oxbow::vocab
