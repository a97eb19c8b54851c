// Nearest-centroid search used by training and by Vocabulary (internal to vocab/).
//
//  - ExactSearch: every query against every word, cache-blocked register tiles (kernels.h).
//  - TwoLevelIndex: an inverted-file quantiser over the words (Jegou et al. 2011, "Product quantization
//    for nearest neighbor search", sec. IV, without the compression): words are grouped under coarse
//    centroids; a query scores all coarse centroids, keeps the `num_probes` nearest lists and scores
//    the words in them. Queries are processed in batches grouped by list, so each list's words are read
//    from memory once per batch rather than once per query (the words of a 100k vocabulary, 51 MB, do
//    not fit in cache; a list does).
//
// Results: for each query the k best (score, row) pairs ascending, ties broken by the smaller row, with
// score = |w|^2 - 2<q, w> (kernels.h). Deterministic whatever the batch composition or thread count.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace oxbow::vocab::internal {

// words: num_words x dim row-major; norms: their squared norms.
struct WordMatrix {
  const float* words = nullptr;
  const float* norms = nullptr;
  size_t num_words = 0;
  int dim = 0;
};

// Words in the score kernel's panel layout (kernels.h): NumPanels(num_words) panels and their norms.
struct PanelMatrix {
  const float* panels = nullptr;
  const float* norms = nullptr;  // NumPanels(num_words) * kPanelWidth, padded lanes +inf
  size_t num_words = 0;
  int dim = 0;
};

// An owned copy of a WordMatrix in panels.
struct Panels {
  Panels() = default;
  explicit Panels(const WordMatrix& rows);
  PanelMatrix View() const { return {data.data(), norms.data(), num_words, dim}; }

  size_t num_words = 0;
  int dim = 0;
  std::vector<float> data;
  std::vector<float> norms;
};

// k best rows per query (queries: n x dim). rows/scores: n x k; unfilled slots get row num_words and
// score +inf. num_threads 0 = all hardware threads.
void ExactSearch(const WordMatrix& words, const float* queries, size_t n, int k, int num_threads, uint32_t* rows,
                 float* scores);

struct TwoLevelIndex {
  int dim = 0;
  std::vector<float> coarse;        // num_lists x dim
  std::vector<float> coarse_norms;  // num_lists
  std::vector<uint64_t> offsets;    // num_lists + 1; list l holds word rows [offsets[l], offsets[l+1])
  WordMatrix words;                 // rows in list order (not owned)
  // The coarse centroids, and each list's words, in the score kernel's panels (BuildPanels()); a
  // list's words start a panel of their own, at panel panel_offsets[l].
  Panels coarse_panels;
  std::vector<float> word_panels;
  std::vector<float> word_panel_norms;
  std::vector<uint64_t> panel_offsets;  // num_lists + 1

  // Builds the panels from coarse, coarse_norms, offsets and words; call once they are set, before
  // Search (which checks it). Holds a second copy of the words (the row-major ones serve exact
  // distances and Hamming embedding).
  void BuildPanels();

  size_t num_lists() const { return coarse_norms.size(); }
  // k best word rows per query among the num_probes nearest lists.
  void Search(const float* queries, size_t n, int k, int num_probes, int num_threads, uint32_t* rows,
              float* scores) const;
};

// Groups `points` (n x dim) into num_lists clusters with k-means (random seeding from `seed`, exact
// assignment, `iterations` Lloyd steps on a subsample of at most 64 points per list, then one exact
// assignment of every point). Returns the coarse centroids (num_lists x dim) and each point's list.
struct CoarseClustering {
  std::vector<float> centroids;
  std::vector<uint32_t> list_of_point;
};
CoarseClustering ClusterCoarse(const float* points, size_t n, int dim, size_t num_lists, int iterations,
                               uint64_t seed, int num_threads);

// Default coarse list count for k words: round(4 sqrt(k)), clamped to [1, k].
size_t DefaultNumLists(size_t num_words);

// SplitMix64: a small seeded generator used for every random choice in vocab/ (reproducible across
// platforms, unlike std:: distributions).
struct SplitMix64 {
  uint64_t state;
  explicit SplitMix64(uint64_t seed) : state(seed) {}
  uint64_t Next() {
    uint64_t z = (state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  // Uniform in [0, bound), bound >= 1 (Lemire's multiply-shift; bias below 2^-32 for bound < 2^32).
  uint64_t Below(uint64_t bound) { return static_cast<uint64_t>((static_cast<__uint128_t>(Next()) * bound) >> 64); }
  double Uniform01() { return static_cast<double>(Next() >> 11) * 0x1.0p-53; }
};

}  // namespace oxbow::vocab::internal
