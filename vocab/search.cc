#include "vocab/search.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include "sift/base/error.h"
#include "sift/base/parallel.h"
#include "vocab/kbest.h"
#include "vocab/kernels.h"

namespace oxbow::vocab::internal {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

void Reset(uint32_t* rows, float* scores, size_t count, uint32_t fill_row) {
  std::fill(rows, rows + count, fill_row);
  std::fill(scores, scores + count, kInf);
}

// Panels per cache block when scanning a whole matrix: 2^16 floats = 256 KiB (512 words of 128 dimensions).
size_t PanelBlock(int dim) {
  return std::max<size_t>(2, (size_t{1} << 16) / (static_cast<size_t>(dim) * kPanelWidth));
}

// Scores `queries` (count x dim) against all of `words`, blocked over panels, keeping k best per query
// in rows/scores.
void ScanAll(const PanelMatrix& words, const float* queries, size_t count, int k, uint32_t* rows, float* scores) {
  const size_t block = PanelBlock(words.dim);
  const size_t stride = static_cast<size_t>(words.dim) * kPanelWidth;
  const size_t num_panels = NumPanels(words.num_words);
  for (size_t p0 = 0; p0 < num_panels; p0 += block) {
    const size_t w0 = p0 * kPanelWidth;
    const size_t nw = std::min(block * kPanelWidth, words.num_words - w0);
    auto bound = [&](size_t qi) { return scores[qi * k + k - 1]; };
    WithKBestInsert(k, [&](auto insert) {
      auto sink = [&](size_t qi, size_t wj, float score) {
        insert(rows + qi * k, scores + qi * k, static_cast<uint32_t>(w0 + wj), score);
      };
      ScorePanels(queries, count, words.panels + p0 * stride, words.norms + w0, nw, words.dim, bound, sink);
    });
  }
}

constexpr size_t kQueryBatch = 2048;

// Queries per batch of the coarse pass: at most kCoarseBatch, in a number of equal batches that is a
// multiple of the thread count, so every thread gets the same share (2850 descriptors on 2 threads: 12
// batches of 238). Small batches keep the threads even when the machine is busy: with one batch per
// thread (1425 + 1425) a caller whose helper was descheduled holding half the work waited for it, and
// with another busy thread on the 2-core machine a 16-probe quantisation took 10.6-10.7 us per
// descriptor against 9.8-9.9 with batches of 256 (5.8 alone either way). Results do not depend on the batch.
constexpr size_t kCoarseBatch = 256;
size_t BalancedBatch(size_t n, int num_threads) {
  const size_t threads = static_cast<size_t>(ResolveThreadCount(num_threads));
  const size_t rounds = (n + threads * kCoarseBatch - 1) / (threads * kCoarseBatch);
  const size_t batches = std::max<size_t>(1, rounds * threads);
  return std::max<size_t>(1, (n + batches - 1) / batches);
}

}  // namespace

size_t DefaultNumLists(size_t num_words) {
  const double lists = std::round(4.0 * std::sqrt(static_cast<double>(num_words)));
  return std::clamp<size_t>(static_cast<size_t>(lists), 1, std::max<size_t>(1, num_words));
}

void ExactSearch(const WordMatrix& words, const float* queries, size_t n, int k, int num_threads, uint32_t* rows,
                 float* scores) {
  constexpr size_t kGrain = 256;
  const Panels panels(words);
  ParallelFor(n, num_threads, kGrain, [&](size_t begin, size_t end, int) {
    Reset(rows + begin * k, scores + begin * k, (end - begin) * k, static_cast<uint32_t>(words.num_words));
    ScanAll(panels.View(), queries + begin * words.dim, end - begin, k, rows + begin * k, scores + begin * k);
  });
}

void TwoLevelIndex::Search(const float* queries, size_t n, int k, int num_probes, int num_threads, uint32_t* rows,
                           float* scores) const {
  const size_t lists = num_lists();
  const int probes = static_cast<int>(std::clamp<size_t>(static_cast<size_t>(std::max(1, num_probes)), 1, lists));
  OXBOW_CHECK(coarse_panels.num_words == lists && panel_offsets.size() == lists + 1,
              "TwoLevelIndex::BuildPanels was not called");
  const size_t stride = static_cast<size_t>(dim) * kPanelWidth;
  const auto threads = static_cast<size_t>(ResolveThreadCount(num_threads));
  const auto fill_row = static_cast<uint32_t>(words.num_words);
  // Rounds of up to kQueryBatch queries per thread. In a round the coarse pass splits the queries
  // between the threads, and the fine pass splits the lists: each list's words are read from memory
  // once per round, not once per thread (a search's 3000 descriptors on 2 threads read all 51 MB of a
  // 100k vocabulary's words once instead of twice), and a list is scored against every query of the
  // round that probes it, which fills the kernel's register tiles better. Each thread keeps its own
  // k best per query; merging them gives the same lists as one thread would, since a k-best list
  // under (score, row) does not depend on the order of its insertions.
  const size_t round = threads * kQueryBatch;
  std::vector<uint32_t> probe_lists, group_start, fill, members;
  std::vector<float> probe_scores;
  std::vector<std::vector<uint32_t>> worker_rows(threads);
  std::vector<std::vector<float>> worker_scores(threads);
  for (size_t r0 = 0; r0 < n; r0 += round) {
    const size_t count = std::min(round, n - r0);
    const float* batch = queries + r0 * dim;
    // 1. The `probes` nearest coarse centroids of every query.
    probe_lists.resize(count * probes);  // every slot is Reset below
    probe_scores.resize(count * probes);
    ParallelFor(count, num_threads, BalancedBatch(count, num_threads), [&](size_t begin, size_t end, int) {
      Reset(probe_lists.data() + begin * probes, probe_scores.data() + begin * probes, (end - begin) * probes,
            static_cast<uint32_t>(lists));
      ScanAll(coarse_panels.View(), batch + begin * dim, end - begin, probes, probe_lists.data() + begin * probes,
              probe_scores.data() + begin * probes);
    });
    // 2. Group the queries by probed list (counting sort). A slot left unfilled (row `lists`: a query
    //    whose scores are NaN, e.g. non-finite descriptors) probes nothing.
    group_start.assign(lists + 1, 0);
    for (uint32_t l : probe_lists) {
      if (l < lists) ++group_start[l + 1];
    }
    std::partial_sum(group_start.begin(), group_start.end(), group_start.begin());
    fill.assign(group_start.begin(), group_start.end() - 1);
    members.resize(probe_lists.size());
    for (size_t q = 0; q < count; ++q) {
      for (int p = 0; p < probes; ++p) {
        const uint32_t l = probe_lists[q * probes + p];
        if (l < lists) members[fill[l]++] = static_cast<uint32_t>(q);
      }
    }
    // 3. Score each list's words against the queries that probe it, lists shared out between the
    //    threads in chunks taken in turn; each thread's k best per query in buffers of its own.
    for (size_t w = 0; w < threads; ++w) {
      worker_rows[w].resize(count * k);
      worker_scores[w].resize(count * k);
      Reset(worker_rows[w].data(), worker_scores[w].data(), count * k, fill_row);
    }
    constexpr size_t kListsPerChunk = 16;
    ParallelFor(lists, num_threads, kListsPerChunk, [&](size_t l_begin, size_t l_end, int worker) {
      uint32_t* out_rows = worker_rows[static_cast<size_t>(worker)].data();
      float* out_scores = worker_scores[static_cast<size_t>(worker)].data();
      std::vector<float> group_queries;  // a list's queries, copied side by side for the kernel
      for (size_t l = l_begin; l < l_end; ++l) {
        const uint32_t g0 = group_start[l], g1 = group_start[l + 1];
        const uint64_t w0 = offsets[l], w1 = offsets[l + 1];
        if (g0 == g1 || w0 == w1) continue;
        group_queries.resize(size_t{g1 - g0} * dim);
        for (uint32_t g = g0; g < g1; ++g)
          std::copy_n(batch + size_t{members[g]} * dim, dim, group_queries.data() + size_t{g - g0} * dim);
        const uint32_t* group = members.data() + g0;
        auto bound = [&](size_t gi) { return out_scores[size_t{group[gi]} * k + k - 1]; };
        const uint64_t p0 = panel_offsets[l];
        WithKBestInsert(k, [&](auto insert) {
          auto sink = [&](size_t gi, size_t wj, float score) {
            const size_t q = group[gi];
            insert(out_rows + q * k, out_scores + q * k, static_cast<uint32_t>(w0 + wj), score);
          };
          ScorePanels(group_queries.data(), g1 - g0, word_panels.data() + p0 * stride,
                      word_panel_norms.data() + p0 * kPanelWidth, w1 - w0, dim, bound, sink);
        });
      }
    });
    // 4. Merge the threads' lists into the output (the first thread's, then the others' entries).
    uint32_t* out_rows = rows + r0 * k;
    float* out_scores = scores + r0 * k;
    std::copy_n(worker_rows[0].data(), count * k, out_rows);
    std::copy_n(worker_scores[0].data(), count * k, out_scores);
    for (size_t w = 1; w < threads; ++w) {
      for (size_t q = 0; q < count; ++q) {
        for (int j = 0; j < k; ++j) {
          const uint32_t row = worker_rows[w][q * k + j];
          if (row == fill_row) break;  // the rest of this list is unfilled
          InsertKBest(out_rows + q * k, out_scores + q * k, k, row, worker_scores[w][q * k + j]);
        }
      }
    }
  }
}

Panels::Panels(const WordMatrix& rows) : num_words(rows.num_words), dim(rows.dim) {
  const size_t np = NumPanels(rows.num_words);
  data.resize(np * static_cast<size_t>(rows.dim) * kPanelWidth);
  norms.resize(np * kPanelWidth);
  MakePanels(rows.words, rows.norms, rows.num_words, rows.dim, data.data(), norms.data());
}

void TwoLevelIndex::BuildPanels() {
  const size_t lists = num_lists();
  coarse_panels = Panels(WordMatrix{coarse.data(), coarse_norms.data(), lists, dim});
  panel_offsets.assign(lists + 1, 0);
  for (size_t l = 0; l < lists; ++l)
    panel_offsets[l + 1] = panel_offsets[l] + NumPanels(offsets[l + 1] - offsets[l]);
  const size_t stride = static_cast<size_t>(dim) * kPanelWidth;
  word_panels.assign(panel_offsets[lists] * stride, 0.0f);
  word_panel_norms.assign(panel_offsets[lists] * kPanelWidth, 0.0f);
  for (size_t l = 0; l < lists; ++l) {
    const uint64_t w0 = offsets[l];
    MakePanels(words.words + w0 * dim, words.norms + w0, offsets[l + 1] - w0, dim,
               word_panels.data() + panel_offsets[l] * stride,
               word_panel_norms.data() + panel_offsets[l] * kPanelWidth);
  }
}

CoarseClustering ClusterCoarse(const float* points, size_t n, int dim, size_t num_lists, int iterations,
                               uint64_t seed, int num_threads) {
  num_lists = std::clamp<size_t>(num_lists, 1, std::max<size_t>(1, n));
  SplitMix64 rng(seed ^ 0xC0A125Eull);
  // Subsample (partial Fisher-Yates over indices): at most 64 points per list train the centroids.
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  const size_t sample = std::min(n, num_lists * 64);
  for (size_t i = 0; i < sample; ++i) std::swap(order[i], order[i + rng.Below(n - i)]);
  std::vector<float> train(sample * dim);
  for (size_t i = 0; i < sample; ++i) std::copy_n(points + size_t{order[i]} * dim, dim, train.data() + i * dim);
  // The first num_lists sampled points (distinct indices) seed the centroids.
  CoarseClustering out;
  out.centroids.assign(train.begin(), train.begin() + num_lists * dim);
  std::vector<float> norms(num_lists);
  std::vector<uint32_t> assign(sample);
  std::vector<float> score(sample);
  std::vector<double> sums(num_lists * dim);
  std::vector<uint32_t> counts(num_lists);
  for (int it = 0; it < iterations; ++it) {
    RowSquaredNorms(out.centroids.data(), num_lists, dim, norms.data());
    ExactSearch({out.centroids.data(), norms.data(), num_lists, dim}, train.data(), sample, 1, num_threads,
                assign.data(), score.data());
    std::fill(sums.begin(), sums.end(), 0.0);
    std::fill(counts.begin(), counts.end(), 0u);
    for (size_t i = 0; i < sample; ++i) {
      const uint32_t c = assign[i];
      ++counts[c];
      for (int d = 0; d < dim; ++d) sums[size_t{c} * dim + d] += train[i * dim + d];
    }
    for (size_t c = 0; c < num_lists; ++c) {
      if (counts[c] == 0) continue;  // an empty coarse list keeps its centroid
      for (int d = 0; d < dim; ++d)
        out.centroids[c * dim + d] = static_cast<float>(sums[c * dim + d] / counts[c]);
    }
  }
  RowSquaredNorms(out.centroids.data(), num_lists, dim, norms.data());
  out.list_of_point.resize(n);
  std::vector<float> all_scores(n);
  ExactSearch({out.centroids.data(), norms.data(), num_lists, dim}, points, n, 1, num_threads,
              out.list_of_point.data(), all_scores.data());
  return out;
}

}  // namespace oxbow::vocab::internal
