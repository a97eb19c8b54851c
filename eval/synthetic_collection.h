// Synthetic collections for measuring the index at scale (eval/README.md, "Benchmarks"): images whose
// features are drawn with replacement from the pool of every feature of some real photos. Each
// synthetic feature is one real feature's visual word (quantised once, with the quantiser settings
// ImageIndex::Add uses) and its keypoint (position scaled to the synthetic image, scale and orientation
// kept), and with a Hamming-embedding vocabulary its signature; so words follow the real photos' word
// distribution with their joint word/geometry statistics, while a synthetic image's features are
// independent draws (no bursts, no objects).
//
// IngestSynthetic adds such images through the storage path the server uses (ImageIndex::AddBatch with
// the words already assigned, in batches) and can export each image as a feature file, so that
// `oxbow index build --features` builds the same collection through the command line. The storage
// benchmark (eval/bench/index_benchmark.cc, `storage`) and tests/storage_path_test.cc both run it.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <span>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "sift/base/error.h"
#include "sift/sift.h"
#include "sift/types.h"
#include "vocab/vocabulary.h"

namespace oxbow::eval {

// SplitMix64 (Steele, Lea & Flood 2014): a tiny deterministic generator for synthetic data.
struct SplitMix {
  uint64_t s;
  uint64_t Next() {
    uint64_t z = (s += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  double Uniform() { return static_cast<double>(Next() >> 11) * 0x1.0p-53; }  // [0, 1)
};

struct SyntheticOptions {
  int features_per_image = 1000;  // features of each synthetic image, > 0
  int image_width = 1024;         // the synthetic images' frame, pixels
  int image_height = 768;
  // Keep each feature's real descriptor (needed to export feature files; 512 bytes per feature).
  bool descriptors = false;
};

// One synthetic image: its features (descriptors only with SyntheticOptions::descriptors) and their
// visual words and (with a Hamming-embedding vocabulary) signatures, one per keypoint.
struct SyntheticImage {
  sift::FeatureSet features;
  std::vector<uint32_t> words;
  std::vector<uint64_t> signatures;
};

class SyntheticCollection {
 public:
  // The pool: every feature of `photos` (RootSIFT), quantised with `vocabulary` and `quantizer`.
  // `photos` must outlive the collection when options.descriptors is set.
  SyntheticCollection(std::span<const sift::FeatureSet> photos, const vocab::Vocabulary& vocabulary,
                      const vocab::QuantizerOptions& quantizer, const SyntheticOptions& options);

  // Image `number`: a deterministic function of the number, the pool and the options.
  SyntheticImage Make(uint64_t number) const;
  // Its id in an index: "s<number>".
  static std::string Id(uint64_t number);

  size_t pool_size() const { return pool_.size(); }
  bool has_signatures() const { return signatures_; }
  const SyntheticOptions& options() const { return options_; }

 private:
  struct PoolFeature {
    uint32_t word;
    float rx, ry, scale, orientation;  // position relative to the photo's frame
    uint32_t photo, feature;
    uint64_t signature;
  };
  std::span<const sift::FeatureSet> photos_;
  SyntheticOptions options_;
  bool signatures_ = false;
  std::vector<PoolFeature> pool_;
};

struct IngestOptions {
  uint64_t first = 0;            // images first .. first + count - 1
  uint64_t count = 0;
  uint64_t batch = 1000;         // images per AddBatch, > 0
  int num_threads = 0;           // making the synthetic images (0: all cores)
  // Non-empty: also write each image as <export_dir>/<id>.oxfeat (the collection needs
  // SyntheticOptions::descriptors), stamped with `extractor`'s fingerprint and description.
  std::filesystem::path export_dir;
  sift::SiftOptions extractor;
  // Called after each batch with the images added so far.
  std::function<void(uint64_t done)> progress = nullptr;
};

struct IngestReport {
  double add_seconds = 0;    // inside AddBatch: the storage path alone
  double total_seconds = 0;  // with making (and exporting) the synthetic images
};

// Adds the images through ImageIndex::AddBatch with their words (and signatures) already assigned.
[[nodiscard]] Result<IngestReport> IngestSynthetic(index::ImageIndex& index, const SyntheticCollection& collection,
                                                   const IngestOptions& options);

struct WriteLatencies {
  std::vector<double> add_ms, remove_ms;  // one per image
  uint64_t searches = 0;                  // searches completed alongside
};

// Adds `count` synthetic images one at a time (ids "added0", "added1", ..., made from numbers first,
// first + 1, ...) while another thread searches `queries` in turn with QueryOptions{} (none without
// queries), then removes them again; the index holds the same images afterwards.
[[nodiscard]] Result<WriteLatencies> AddAndRemoveWhileSearching(index::ImageIndex& index,
                                                                const SyntheticCollection& collection, uint64_t first,
                                                                int count,
                                                                std::span<const sift::FeatureSet* const> queries);

}  // namespace oxbow::eval
