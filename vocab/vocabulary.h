// The visual vocabulary: k-means centroids of local descriptors and the quantiser that maps a
// descriptor to its nearest centroid ("visual word"), after Sivic & Zisserman 2003 (Video Google) and
// Philbin et al. 2007 (Object retrieval with large vocabularies and fast spatial matching, CVPR).
//
// Training (Train) runs Lloyd's k-means from a k-means++ seeding (Arthur & Vassilvitskii 2007). For
// small vocabularies every assignment is exact (a blocked matrix product, AVX2 FMA through Eigen); for
// large ones the nearest centroid is found approximately, as in the approximate k-means (AKM) of
// Philbin et al. 2007 (randomised kd-forest over the centroids, FLANN; Muja & Lowe 2009).
//
// Quantisation (Vocabulary::Quantize) uses a two-level inverted-file search over the centroids: the
// words are grouped under coarse centroids (stored in the vocabulary file), a descriptor is compared
// with every coarse centroid, then with the words of the `num_probes` nearest coarse lists. See
// QuantizerOptions for the measured speed/recall trade-off.
//
// Hamming embedding (Jegou, Douze & Schmid 2008, "Hamming embedding and weak geometric consistency"):
// a vocabulary may carry a random orthogonal projection P (64 x dimension) and, per word, the 64
// medians of the projected training descriptors assigned to it (WithHamming). A descriptor x of word
// w then gets the 64-bit signature b_i = [(P x)_i > median_{w,i}]: two descriptors of the same word
// that are close in descriptor space have a small Hamming distance, which separates true matches
// from the many unrelated descriptors that share a coarse word.
//
// Thread safety: a Vocabulary is immutable after construction; every const member may be called from
// any number of threads at once. Copies are cheap (shared immutable state).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "sift/base/error.h"
#include "sift/types.h"

namespace oxbow::vocab {

// Search parameters of Vocabulary::Quantize / QuantizeMulti. They trade speed for the share of
// descriptors that receive their exact nearest word (recall@1).
// Bits of a Hamming-embedding signature (one uint64_t per feature).
inline constexpr int kHammingBits = 64;

struct QuantizerOptions {
  // Threads used inside one Quantize call: 1 = the calling thread only (the right choice when the
  // caller already parallelises over images), 0 = all hardware threads. Range >= 0.
  int num_threads = 1;
  // Coarse lists scanned per descriptor (multi-probe). More probes: higher recall, linearly more time.
  // Range [1, number of coarse lists]; values above the list count are clamped.
  int num_probes = 16;
  // Compare with every word (brute force, exact). Slow for large vocabularies; for evaluation.
  bool exact = false;

  // An error message for invalid values, std::nullopt when valid.
  std::optional<std::string> Check() const;
};

// How the coarse level of the quantiser is built (Vocabulary::FromCentroids, Train).
struct QuantizerBuildOptions {
  // Number of coarse lists; 0 chooses from the vocabulary size (about 4 * sqrt(k), at least 1).
  // Range [0, k].
  size_t num_lists = 0;
  // Lloyd iterations of the coarse k-means over the words. Range [1, 100].
  int iterations = 8;
  // Seed of the coarse k-means++ seeding; the structure is deterministic for a given seed.
  uint64_t seed = 1;
  // Threads for building, 0 = all hardware threads. The result does not depend on it.
  int num_threads = 0;

  std::optional<std::string> Check() const;
};

class Vocabulary {
 public:
  // Reads a vocabulary file (see Write). kNotFound if missing, kCorruptData if damaged, truncated or
  // not a vocabulary, kIncompatible for an unknown format version. One read of the whole file.
  [[nodiscard]] static Result<Vocabulary> Read(const std::string& path);

  // Builds a vocabulary (and its quantiser) from `centroids` (k x dimension, row-major).
  // kInvalidArgument for an empty or ragged matrix, non-finite values or bad options.
  [[nodiscard]] static Result<Vocabulary> FromCentroids(std::vector<float> centroids, int dimension,
                                                        sift::DescriptorKind kind, std::string extractor_settings,
                                                        const QuantizerBuildOptions& build = {});

  // Writes the vocabulary atomically to `path` (container magic "OXBWVOCB", see binary_io.h).
  [[nodiscard]] Status Write(const std::string& path) const;

  size_t size() const;                               // number of words k
  int dimension() const;                             // descriptor dimension (128)
  sift::DescriptorKind descriptor_kind() const;      // SIFT or RootSIFT
  const std::string& extractor_settings() const;     // SiftOptions::Describe() of the training features
  uint64_t fingerprint() const;                      // hash of centroids, kind and settings
  std::span<const float> centroids() const;          // k x dimension, row-major
  size_t num_lists() const;                          // coarse lists of the quantiser
  bool has_hamming() const;                          // carries Hamming-embedding parameters

  // The Hamming-embedding signature of each of n descriptors (n x dimension row-major) given its word
  // (n entries, each < size()). OXBOW_CHECKs has_hamming() and the sizes. Cost O(n * 64 * dimension).
  void Signatures(std::span<const float> descriptors, std::span<const uint32_t> words,
                  std::span<uint64_t> signatures) const;

  // A copy of this vocabulary with Hamming-embedding parameters learnt from `training` (n x dimension
  // row-major, normally the k-means training sample): a random orthogonal projection drawn from
  // `seed` and, per word, the medians of the projected descriptors that `quantizer` assigns to it
  // (a word no descriptor reaches uses its projected centroid). Replaces existing parameters. The
  // fingerprint changes (it covers them): an index built without signatures does not open with it.
  // kInvalidArgument for an empty or ragged sample or non-finite values.
  [[nodiscard]] Result<Vocabulary> WithHamming(std::span<const float> training, uint64_t seed,
                                               const QuantizerOptions& quantizer = {}) const;

  // The pieces of WithHamming, for learning the parameters where the sample is not in one place
  // (vocab/distributed.h); used together they give what WithHamming gives.
  // The projection WithHamming draws from `seed`: kHammingBits x dimension() orthonormal rows, row-major.
  // OXBOW_CHECKs dimension() >= kHammingBits. Cost O(kHammingBits^2 * dimension).
  std::vector<float> HammingProjection(uint64_t seed) const;
  // Each of n descriptors (n x dimension() row-major) projected by `projection` (kHammingBits x
  // dimension()) into `projected` (n x kHammingBits), with the arithmetic of WithHamming and Signatures
  // (bit for bit). OXBOW_CHECKs the sizes. Cost O(n * kHammingBits * dimension).
  void ProjectForHamming(std::span<const float> projection, std::span<const float> descriptors,
                         std::span<float> projected) const;
  // A copy with the given parameters: `projection` (kHammingBits x dimension()) and `medians`
  // (size() x kHammingBits, by word id). Replaces existing parameters; the fingerprint changes as with
  // WithHamming. kInvalidArgument for other sizes, non-finite values or dimension() < kHammingBits.
  [[nodiscard]] Result<Vocabulary> WithHammingParameters(std::vector<float> projection,
                                                         std::vector<float> medians) const;

  // Nearest word of each of n descriptors (`descriptors` is n x dimension row-major, `words` has n
  // entries). Batched: pass many descriptors per call. Cost about (num_lists + num_probes * k /
  // num_lists) distance evaluations per descriptor. Thread-safe. OXBOW_CHECKs the sizes.
  void Quantize(std::span<const float> descriptors, std::span<uint32_t> words,
                const QuantizerOptions& options = {}) const;

  // The k nearest words of each descriptor with their squared L2 distances, ascending (multiple
  // assignment, Philbin et al. 2008 "Lost in quantization"). `words` and `sq_distances` are n x k
  // row-major. If fewer than k words are reachable, the tail is filled with word id size() and
  // distance +infinity. Thread-safe.
  void QuantizeMulti(std::span<const float> descriptors, int k, std::span<uint32_t> words,
                     std::span<float> sq_distances, const QuantizerOptions& options = {}) const;

  struct State;  // implementation detail (vocabulary.cc)

 private:
  explicit Vocabulary(std::shared_ptr<const State> state) : state_(std::move(state)) {}
  std::shared_ptr<const State> state_;
};

// How Train finds each descriptor's nearest centroid in a Lloyd iteration.
enum class AssignmentMethod : uint8_t {
  kAuto,          // kExact up to TrainOptions::exact_assignment_max_words, kInvertedFile above (measured fastest)
  kExact,         // every centroid (blocked AVX2 register tiles); O(n k d) per iteration
  kKdForest,      // FLANN randomised kd-forest over the centroids, rebuilt every iteration (AKM, Philbin 2007)
  kInvertedFile,  // the two-level quantiser of Vocabulary, rebuilt every iteration
};

const char* AssignmentMethodName(AssignmentMethod method);  // "auto" | "exact" | "kdforest" | "ivf"

// Parameters of Train.
struct TrainOptions {
  // Number of visual words k. Range [1, number of training descriptors].
  size_t num_words = 10000;
  // Maximum Lloyd iterations (assignment + update). Range [1, 1000]. 10 with 4000 descriptors per image
  // (SampleOptions) measured best (eval/results/vocabulary.md): Paris subset 20k words mAP 0.896 +- 0.006 over
  // seeds 1-3 vs 0.882 +- 0.009 for 1000 per image / 20 iterations; groups_dev tied (0.985 vs 0.985).
  int max_iterations = 10;
  // Stop when the objective (mean squared distance to the assigned word) improves by less than this
  // fraction of its previous value in one iteration. Range [0, 1); 0 runs all iterations.
  double min_relative_improvement = 1e-4;
  // Seed of the seeding and of the approximate search structures; equal seeds and inputs give equal
  // vocabularies, whatever the thread count (not with kKdForest: libflann's trees are not reproducible).
  uint64_t seed = 1;
  // Threads, 0 = all hardware threads. The result does not depend on it.
  int num_threads = 0;
  // Nearest-centroid search during the iterations. With an approximate method a descriptor keeps its
  // previous word when the search returns a farther one, so the objective still never increases.
  AssignmentMethod assignment = AssignmentMethod::kAuto;
  // kAuto: vocabularies up to this many words use exact assignment. Range >= 0.
  size_t exact_assignment_max_words = 4096;
  // kKdForest: randomised kd-trees in the forest (Philbin et al. 2007 use 8). Range [1, 64].
  int kdtree_trees = 8;
  // kKdForest: leaves checked per search (FLANN "checks"). Range [1, 100000].
  int kdtree_checks = 64;
  // kInvertedFile: coarse lists probed per descriptor during training. Range >= 1.
  int ivf_probes = 8;
  // Seeding: k-means++ (D^2 sampling, Arthur & Vassilvitskii 2007) when k is at most this, run on a
  // uniform subsample of seeding_points_per_word * k descriptors; above it, k distinct descriptors
  // chosen uniformly at random (k-means++ costs O(k^2 d) sequential rounds, prohibitive for large k;
  // with many Lloyd iterations the difference fades). Range >= 0.
  size_t kmeanspp_max_words = 4096;
  // Subsample factor of the k-means++ seeding. Range >= 1.
  size_t seeding_points_per_word = 16;
  // How the coarse quantiser of the resulting vocabulary is built.
  QuantizerBuildOptions quantizer;

  std::optional<std::string> Check() const;
};

// Per-iteration statistics, reported through TrainReport.
struct IterationStats {
  int iteration = 0;              // 1-based
  double objective = 0;           // mean squared L2 distance of a descriptor to its word, after assignment
  double reassigned_share = 0;    // share of descriptors whose word changed in this iteration
  size_t empty_clusters = 0;      // clusters left empty by the assignment (re-seeded)
  double seconds = 0;             // wall time of the iteration
};

struct TrainReport {
  std::vector<IterationStats> iterations;
  double seeding_seconds = 0;
  double total_seconds = 0;
  bool converged = false;  // stopped by min_relative_improvement rather than max_iterations
};

// Trains a vocabulary on `descriptors` (n x dimension, row-major; dimension is the descriptor size,
// normally sift::kDescriptorDim) with k-means. Progress on stderr. `report` (optional) receives the
// per-iteration statistics. kInvalidArgument for bad options, too few descriptors or non-finite values.
// Complexity per iteration: O(n k d) exact, about O(n checks d) approximate.
[[nodiscard]] Result<Vocabulary> Train(std::span<const float> descriptors, int dimension, sift::DescriptorKind kind,
                                       std::string extractor_settings, const TrainOptions& options,
                                       TrainReport* report = nullptr);

// ---- Sampling training descriptors ---------------------------------------------------------------

struct SampleOptions {
  // At most this many descriptors kept from one image (uniform random subset). Range >= 1. See
  // TrainOptions::max_iterations for the measurement behind 4000.
  size_t max_per_image = 4000;
  // At most this many descriptors in total (reservoir sampling over all images). Range >= 1.
  size_t max_total = 1'000'000;
  // Seed; the sample depends on it and on the order images are added, nothing else.
  uint64_t seed = 1;

  std::optional<std::string> Check() const;
};

// Seeded two-stage sampler: a uniform subset of at most max_per_image rows per image, then a uniform
// reservoir (Vitter's algorithm R) of at most max_total rows over everything added. Not thread-safe:
// add images from one thread, in a fixed order (e.g. sorted file names) for a reproducible sample.
class DescriptorSampler {
 public:
  // OXBOW_CHECKs that options are valid and dimension > 0.
  DescriptorSampler(const SampleOptions& options, int dimension);

  // Offers the descriptors of one image (rows x dimension, row-major).
  void AddImage(std::span<const float> descriptors);

  size_t size() const { return rows_; }            // rows currently held
  uint64_t rows_seen() const { return seen_; }     // rows offered after the per-image cap
  size_t images_seen() const { return images_; }
  int dimension() const { return dimension_; }
  // The sample, size() x dimension row-major, in reservoir order.
  const std::vector<float>& descriptors() const { return data_; }
  std::vector<float> TakeDescriptors() { rows_ = 0; return std::move(data_); }

 private:
  SampleOptions options_;
  int dimension_;
  std::vector<float> data_;
  size_t rows_ = 0;
  uint64_t seen_ = 0;
  size_t images_ = 0;
  uint64_t rng_state_;
};

}  // namespace oxbow::vocab
