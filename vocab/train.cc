// k-means training of the vocabulary (see vocabulary.h for the contract).
//
// Determinism (exact and inverted-file assignment): every parallel step writes per-descriptor or
// per-centroid outputs, or per-chunk partial sums over fixed-size chunks merged in chunk order, and every
// random choice of ours comes from SplitMix64 seeded by TrainOptions::seed; so the vocabulary depends on
// the seed and the data, not on the thread count. The kd-forest is not reproducible (see Assign). The
// centroid update sums each cluster's members in descriptor order (a counting sort by word), in double
// precision.
#include <flann/flann.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <numeric>
#include <sstream>

#include "sift/base/log.h"
#include "sift/base/parallel.h"
#include "sift/base/system.h"
#include "vocab/kernels.h"
#include "vocab/search.h"
#include "vocab/train_internal.h"
#include "vocab/vocabulary.h"

namespace oxbow::vocab {

const char* AssignmentMethodName(AssignmentMethod method) {
  switch (method) {
    case AssignmentMethod::kAuto: return "auto";
    case AssignmentMethod::kExact: return "exact";
    case AssignmentMethod::kKdForest: return "kdforest";
    case AssignmentMethod::kInvertedFile: return "ivf";
  }
  return "unknown";
}

std::optional<std::string> TrainOptions::Check() const {
  if (num_words < 1) return "TrainOptions.num_words must be >= 1";
  if (max_iterations < 1 || max_iterations > 1000) return "TrainOptions.max_iterations must be in [1, 1000]";
  if (!(min_relative_improvement >= 0 && min_relative_improvement < 1))
    return "TrainOptions.min_relative_improvement must be in [0, 1)";
  if (num_threads < 0) return "TrainOptions.num_threads must be >= 0 (0 = all hardware threads)";
  if (kdtree_trees < 1 || kdtree_trees > 64) return "TrainOptions.kdtree_trees must be in [1, 64]";
  if (kdtree_checks < 1 || kdtree_checks > 100000) return "TrainOptions.kdtree_checks must be in [1, 100000]";
  if (ivf_probes < 1) return "TrainOptions.ivf_probes must be >= 1";
  if (seeding_points_per_word < 1) return "TrainOptions.seeding_points_per_word must be >= 1";
  if (auto problem = quantizer.Check()) return problem;
  return std::nullopt;
}

namespace {

using Clock = std::chrono::steady_clock;

constexpr size_t kGrain = 4096;  // fixed chunking: results independent of the thread count

// Sum of values[0..n) in double, by fixed chunks merged in order.
double DeterministicSum(const float* values, size_t n, int threads) {
  const size_t chunks = (n + kGrain - 1) / kGrain;
  std::vector<double> partial(chunks, 0.0);
  ParallelFor(n, threads, kGrain, [&](size_t begin, size_t end, int) {
    double s = 0;
    for (size_t i = begin; i < end; ++i) s += values[i];
    partial[begin / kGrain] = s;
  });
  return std::accumulate(partial.begin(), partial.end(), 0.0);
}

// k-means++ on a uniform subsample; returns k x dim centroids.
std::vector<float> SeedKMeansPlusPlus(const float* x, size_t n, int dim, size_t k, size_t points_per_word,
                                      internal::SplitMix64& rng, int threads) {
  const size_t m = std::min(n, std::max(k, k * points_per_word));
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  for (size_t i = 0; i < m; ++i) std::swap(order[i], order[i + rng.Below(n - i)]);
  std::vector<float> sample(m * dim);
  for (size_t i = 0; i < m; ++i) std::copy_n(x + size_t{order[i]} * dim, dim, sample.data() + i * dim);
  return internal::KMeansPlusPlus(sample, dim, k, rng, threads);
}

}  // namespace

namespace internal {

std::vector<float> KMeansPlusPlus(const std::vector<float>& sample, int dim, size_t k, SplitMix64& rng, int threads) {
  const size_t m = sample.size() / dim;
  std::vector<float> centroids(k * dim);
  std::vector<float> nearest(m, std::numeric_limits<float>::infinity());
  size_t chosen = rng.Below(m);
  log::Progress progress("k-means++ seeding", k, "centres");
  for (size_t c = 0; c < k; ++c) {
    const float* centre = sample.data() + chosen * dim;
    std::copy_n(centre, dim, centroids.data() + c * dim);
    progress.Advance();
    if (c + 1 == k) break;
    ParallelFor(m, threads, 16384, [&](size_t begin, size_t end, int) {
      for (size_t i = begin; i < end; ++i)
        nearest[i] = std::min(nearest[i], internal::SquaredL2(sample.data() + i * dim, centre, dim));
    });
    double total = 0;
    for (float v : nearest) total += v;
    if (total <= 0) {  // every sample coincides with a centre: fall back to uniform choice
      chosen = rng.Below(m);
      continue;
    }
    double target = rng.Uniform01() * total;
    chosen = m - 1;
    for (size_t i = 0; i < m; ++i) {
      target -= nearest[i];
      if (target < 0 && nearest[i] > 0) {
        chosen = i;
        break;
      }
    }
  }
  return centroids;
}

}  // namespace internal

namespace {

// k distinct descriptors chosen uniformly at random.
std::vector<float> SeedRandom(const float* x, size_t n, int dim, size_t k, internal::SplitMix64& rng) {
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  for (size_t i = 0; i < k; ++i) std::swap(order[i], order[i + rng.Below(n - i)]);
  std::vector<float> centroids(k * dim);
  for (size_t c = 0; c < k; ++c) std::copy_n(x + size_t{order[c]} * dim, dim, centroids.data() + c * dim);
  return centroids;
}

}  // namespace

namespace internal {

void Assign(AssignmentMethod method, const std::vector<float>& centroids, size_t k, const float* x, size_t n,
            int dim, const TrainOptions& options, uint64_t iteration_seed, int threads, std::vector<uint32_t>& out) {
  std::vector<float> norms(k);
  std::vector<float> scores(n);
  if (method == AssignmentMethod::kExact) {
    internal::RowSquaredNorms(centroids.data(), k, dim, norms.data());
    internal::ExactSearch({centroids.data(), norms.data(), k, dim}, x, n, 1, threads, out.data(), scores.data());
    return;
  }
  if (method == AssignmentMethod::kInvertedFile) {
    internal::CoarseClustering coarse = internal::ClusterCoarse(
        centroids.data(), k, dim, internal::DefaultNumLists(k), options.quantizer.iterations, iteration_seed, threads);
    std::vector<uint32_t> order(k);
    std::iota(order.begin(), order.end(), 0u);
    std::stable_sort(order.begin(), order.end(),
                     [&](uint32_t a, uint32_t b) { return coarse.list_of_point[a] < coarse.list_of_point[b]; });
    std::vector<float> words(k * dim);
    for (size_t r = 0; r < k; ++r) std::copy_n(centroids.data() + size_t{order[r]} * dim, dim, words.data() + r * dim);
    internal::RowSquaredNorms(words.data(), k, dim, norms.data());
    internal::TwoLevelIndex index;
    index.dim = dim;
    index.coarse = std::move(coarse.centroids);
    const size_t lists = index.coarse.size() / dim;
    index.coarse_norms.resize(lists);
    internal::RowSquaredNorms(index.coarse.data(), lists, dim, index.coarse_norms.data());
    index.offsets.assign(lists + 1, 0);
    for (uint32_t l : coarse.list_of_point) ++index.offsets[l + 1];
    std::partial_sum(index.offsets.begin(), index.offsets.end(), index.offsets.begin());
    index.words = {words.data(), norms.data(), k, dim};
    index.BuildPanels();
    index.Search(x, n, 1, options.ivf_probes, threads, out.data(), scores.data());
    for (size_t i = 0; i < n; ++i) out[i] = order[out[i]];
    return;
  }
  // Randomised kd-forest (libflann 1.9). seed_random seeds the rand() it uses for split dimensions, but
  // its tree building also shuffles with a std::random_device of its own, so the forest, and with it
  // the vocabulary, differs from run to run whatever the seed (train_test.cc).
  flann::Matrix<float> dataset(const_cast<float*>(centroids.data()), k, dim);
  flann::seed_random(static_cast<unsigned>(iteration_seed));
  flann::Index<flann::L2<float>> index(dataset, flann::KDTreeIndexParams(options.kdtree_trees));
  index.buildIndex();
  flann::SearchParams params(options.kdtree_checks);
  params.cores = 1;
  ParallelFor(n, threads, kGrain, [&](size_t begin, size_t end, int) {
    const size_t m = end - begin;
    std::vector<int> idx(m);
    std::vector<float> dist(m);
    flann::Matrix<float> queries(const_cast<float*>(x + begin * dim), m, dim);
    flann::Matrix<int> indices(idx.data(), m, 1);
    flann::Matrix<float> dists(dist.data(), m, 1);
    index.knnSearch(queries, indices, dists, 1, params);
    for (size_t i = 0; i < m; ++i) out[begin + i] = static_cast<uint32_t>(std::max(0, idx[i]));
  });
}

uint64_t AcceptAssignments(bool approximate, bool first_iteration, const std::vector<float>& centroids, const float* x,
                           size_t n, int dim, int threads, const std::vector<uint32_t>& proposal,
                           std::vector<uint32_t>& assign, std::vector<float>& dist) {
  const size_t chunks = (n + kGrain - 1) / kGrain;
  std::vector<uint64_t> changed_in_chunk(chunks, 0);
  ParallelFor(n, threads, kGrain, [&](size_t begin, size_t end, int) {
    uint64_t changed = 0;
    for (size_t i = begin; i < end; ++i) {
      const float* xi = x + i * dim;
      float d = SquaredL2(xi, centroids.data() + size_t{proposal[i]} * dim, dim);
      uint32_t w = proposal[i];
      if (approximate && !first_iteration && w != assign[i]) {
        const float d_old = SquaredL2(xi, centroids.data() + size_t{assign[i]} * dim, dim);
        if (d_old <= d) {
          d = d_old;
          w = assign[i];
        }
      }
      if (first_iteration || w != assign[i]) ++changed;
      assign[i] = w;
      dist[i] = d;
    }
    changed_in_chunk[begin / kGrain] = changed;
  });
  return std::accumulate(changed_in_chunk.begin(), changed_in_chunk.end(), uint64_t{0});
}

AssignmentMethod ResolveAssignment(const TrainOptions& options) {
  if (options.assignment != AssignmentMethod::kAuto) return options.assignment;
  return options.num_words <= options.exact_assignment_max_words ? AssignmentMethod::kExact
                                                                 : AssignmentMethod::kInvertedFile;
}

}  // namespace internal

namespace {

std::string FormatSeconds(double s) {
  std::ostringstream out;
  if (s < 120) {
    out.precision(3);
    out << s << " s";
  } else {
    out << static_cast<long>(s / 60) << " min " << static_cast<long>(std::fmod(s, 60)) << " s";
  }
  return out.str();
}

}  // namespace

Result<Vocabulary> Train(std::span<const float> descriptors, int dimension, sift::DescriptorKind kind,
                         std::string extractor_settings, const TrainOptions& options, TrainReport* report) {
  const auto start = Clock::now();
  if (auto problem = options.Check()) return Fail(ErrorCode::kInvalidArgument, *problem);
  if (dimension < 1 || dimension > 4096) return Fail(ErrorCode::kInvalidArgument, "dimension must be in [1, 4096]");
  if (descriptors.size() % dimension != 0)
    return Fail(ErrorCode::kInvalidArgument, "descriptor buffer is not a multiple of the dimension");
  const size_t n = descriptors.size() / dimension;
  const size_t k = options.num_words;
  if (n < k)
    return Fail(ErrorCode::kInvalidArgument, "k-means needs at least as many descriptors as words: " +
                                                 std::to_string(n) + " descriptors for " + std::to_string(k) + " words");
  if (n > std::numeric_limits<uint32_t>::max())
    return Fail(ErrorCode::kInvalidArgument, "at most 2^32 - 1 training descriptors");
  if (!std::all_of(descriptors.begin(), descriptors.end(), [](float v) { return std::isfinite(v); }))
    return Fail(ErrorCode::kInvalidArgument, "training descriptors contain NaN or infinity");
  const int threads = ResolveThreadCount(options.num_threads);
  const float* x = descriptors.data();
  const int dim = dimension;
  const AssignmentMethod method = internal::ResolveAssignment(options);
  const bool approximate = method != AssignmentMethod::kExact;

  TrainReport local_report;
  TrainReport& rep = report ? *report : local_report;
  rep = {};
  internal::SplitMix64 rng(options.seed);
  const bool plusplus = k <= options.kmeanspp_max_words;
  OXBOW_LOG(kInfo) << "k-means: " << k << " words from " << n << " descriptors (dim " << dim << "), seeding "
                   << (plusplus ? "k-means++" : "random") << ", assignment " << AssignmentMethodName(method) << ", "
                   << threads << " threads";
  std::vector<float> centroids = plusplus ? SeedKMeansPlusPlus(x, n, dim, k, options.seeding_points_per_word, rng, threads)
                                          : SeedRandom(x, n, dim, k, rng);
  rep.seeding_seconds = SecondsSince(start);

  std::vector<uint32_t> assign(n, 0), proposal(n);
  std::vector<float> dist(n);
  std::vector<uint32_t> counts(k), member_start(k + 1), members(n);
  double previous_objective = std::numeric_limits<double>::infinity();
  log::Progress progress("k-means", static_cast<uint64_t>(options.max_iterations), "iterations");
  for (int it = 1; it <= options.max_iterations; ++it) {
    const auto t0 = Clock::now();
    IterationStats stats;
    stats.iteration = it;
    internal::Assign(method, centroids, k, x, n, dim, options, options.seed * 1000003ull + static_cast<uint64_t>(it), threads,
           proposal);
    const uint64_t changed =
        internal::AcceptAssignments(approximate, it == 1, centroids, x, n, dim, threads, proposal, assign, dist);
    stats.objective = DeterministicSum(dist.data(), n, threads) / static_cast<double>(n);
    stats.reassigned_share = static_cast<double>(changed) / static_cast<double>(n);

    // Update: counting sort by word, then each centroid is the mean of its members (descriptor order).
    std::fill(counts.begin(), counts.end(), 0u);
    for (size_t i = 0; i < n; ++i) ++counts[assign[i]];
    member_start[0] = 0;
    for (size_t c = 0; c < k; ++c) member_start[c + 1] = member_start[c] + counts[c];
    {
      std::vector<uint32_t> fill(member_start.begin(), member_start.end() - 1);
      for (size_t i = 0; i < n; ++i) members[fill[assign[i]]++] = static_cast<uint32_t>(i);
    }
    ParallelFor(k, threads, 256, [&](size_t begin, size_t end, int) {
      std::vector<double> sum(dim);
      for (size_t c = begin; c < end; ++c) {
        if (counts[c] == 0) continue;
        std::fill(sum.begin(), sum.end(), 0.0);
        for (uint32_t m = member_start[c]; m < member_start[c + 1]; ++m) {
          const float* xi = x + size_t{members[m]} * dim;
          for (int d = 0; d < dim; ++d) sum[d] += xi[d];
        }
        for (int d = 0; d < dim; ++d) centroids[c * dim + d] = static_cast<float>(sum[d] / counts[c]);
      }
    });
    // Empty clusters: re-seed each at one of the descriptors farthest from their word (distinct).
    std::vector<uint32_t> empty;
    for (size_t c = 0; c < k; ++c)
      if (counts[c] == 0) empty.push_back(static_cast<uint32_t>(c));
    stats.empty_clusters = empty.size();
    if (!empty.empty()) {
      std::vector<uint32_t> far(n);
      std::iota(far.begin(), far.end(), 0u);
      const size_t take = std::min(empty.size(), n);
      std::partial_sort(far.begin(), far.begin() + take, far.end(), [&](uint32_t a, uint32_t b) {
        return dist[a] > dist[b] || (dist[a] == dist[b] && a < b);
      });
      for (size_t e = 0; e < take; ++e)
        std::copy_n(x + size_t{far[e]} * dim, dim, centroids.data() + size_t{empty[e]} * dim);
    }
    stats.seconds = SecondsSince(t0);
    rep.iterations.push_back(stats);
    const double remaining = stats.seconds * (options.max_iterations - it);
    std::ostringstream status;
    status << "objective " << stats.objective << ", reassigned " << 100.0 * stats.reassigned_share << "%, empty "
           << stats.empty_clusters << ", " << FormatSeconds(stats.seconds) << "/iteration, ETA <= "
           << FormatSeconds(remaining);
    progress.SetStatus(status.str());
    progress.Advance();
    OXBOW_LOG(kDebug) << "k-means iteration " << it << ": " << status.str();
    const bool small_gain = it > 1 && previous_objective - stats.objective <
                                           options.min_relative_improvement * previous_objective;
    previous_objective = stats.objective;
    if (small_gain || changed == 0) {
      rep.converged = true;
      break;
    }
  }
  OXBOW_LOG(kInfo) << "k-means: " << rep.iterations.size() << " iterations, objective " << previous_objective
                   << (rep.converged ? " (converged)" : "") << ", building the quantiser";
  auto vocabulary =
      Vocabulary::FromCentroids(std::move(centroids), dim, kind, std::move(extractor_settings), options.quantizer);
  rep.total_seconds = SecondsSince(start);
  return vocabulary;
}

}  // namespace oxbow::vocab
