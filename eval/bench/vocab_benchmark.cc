// Vocabulary benchmark on real descriptors (RootSIFT from oxbow's extractor on the Paris subset):
//
//   training:   ours (k-means++ + exact Lloyd) vs cv::kmeans (k-means++) vs faiss::Clustering, same
//               sample, same k, same iterations, same threads; time and final objective (mean squared
//               distance to the nearest centroid, evaluated identically for all three);
//   assignment: one core, descriptors/s and recall@1 (share of queries given their exact nearest word)
//               for 10k / 100k / 1M words: ours (two-level quantiser, several probe counts) vs FLANN
//               kd-forest vs faiss IndexFlatL2 and IndexHNSWFlat. Timings interleaved over repetitions,
//               medians reported.
//
//   scale:      (--scale-words K) Train at scale on 2 threads: the real training descriptors plus
//               jittered copies up to --scale-descriptors N (see Expand); per-iteration wall time and
//               objective, seeding and final quantiser build time, total process CPU time and the load
//               average; --scale-out writes the vocabulary, which --vocab FILE then benchmarks for
//               assignment.
//
// Usage: vocab_benchmark [--images DIR] [--cache FILE] [--words 10000,100000,1000000|none] [--queries N]
//                        [--train-sample N] [--train-words K] [--train-iterations N] [--reps N] [--skip-train]
//                        [--synthetic] [--vocab-iterations N] [--vocab FILE] [--no-avx512] [--oxbow-only]
//                        [--scale-words K --scale-descriptors N --scale-iterations N --scale-threads T
//                         --scale-out FILE]
// --no-avx512: the AVX2 kernels where the AVX-512 ones are chosen at run time (a portable build on an
// AVX-512 CPU), to compare the two on one machine.
// --oxbow-only: the assignment table's two-level rows only (no exact search, FLANN or faiss), for
// comparing two builds of oxbow with runs in turn: seconds per run instead of minutes.
// Assignment vocabularies up to 200k words are trained with Train (inverted-file assignment,
// --vocab-iterations Lloyd iterations, default 8) on all training descriptors; larger ones, or all with
// --synthetic, are synthetic-from-data (training descriptors + Gaussian noise, sigma 0.01). Each is
// cached next to the descriptor cache under a name that encodes every input: word count, origin,
// iterations, seed, and a hash of the training descriptors and extractor settings.
#include <faiss/Clustering.h>
#include <faiss/IndexFlat.h>
#include <faiss/IndexHNSW.h>
#include <faiss/utils/distances.h>
#include <flann/flann.hpp>
#include <omp.h>
#include <opencv2/core.hpp>

#include <algorithm>
#include <chrono>
#include <ctime>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <numeric>
#include <string_view>
#include <random>
#include <string>
#include <vector>

#include "sift/base/log.h"
#include "sift/base/parallel.h"
#include "sift/sift.h"
#include "vocab/kernels.h"
#include "vocab/search.h"
#include "vocab/vocabulary.h"

namespace fs = std::filesystem;
using namespace oxbow;
using Clock = std::chrono::steady_clock;

namespace {

double Seconds(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

// CPU time of the calling thread: the single-core searches are timed with it, so that other processes
// sharing the machine do not count (cache interference still does).
double ThreadCpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

// The 1, 5 and 15 minute load averages, to put wall times in context on a shared machine.
std::string LoadAverage() {
  std::ifstream in("/proc/loadavg");
  std::string a, b, c;
  in >> a >> b >> c;
  return in ? a + " " + b + " " + c : "unknown";
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

struct Descriptors {
  std::vector<float> train;    // descriptors of 9 of every 10 images
  std::vector<float> queries;  // descriptors of the other images (held out)
  std::string settings;
};

Descriptors Load(const std::string& dir, const std::string& cache) {
  Descriptors d;
  if (fs::exists(cache)) {
    std::ifstream in(cache, std::ios::binary);
    uint64_t nt = 0, nq = 0;
    in.read(reinterpret_cast<char*>(&nt), 8).read(reinterpret_cast<char*>(&nq), 8);
    d.train.resize(nt * 128);
    d.queries.resize(nq * 128);
    in.read(reinterpret_cast<char*>(d.train.data()), static_cast<std::streamsize>(nt * 512));
    in.read(reinterpret_cast<char*>(d.queries.data()), static_cast<std::streamsize>(nq * 512));
    std::getline(in, d.settings);
    if (in) return d;
    d = {};
  }
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(dir))
    if (e.path().extension() == ".jpg") files.push_back(e.path().string());
  std::sort(files.begin(), files.end());
  sift::SiftOptions options;
  options.descriptor = sift::DescriptorKind::kRootSift;
  auto extractor = sift::SiftExtractor::Create(options);
  if (!extractor) throw std::runtime_error(extractor.error().ToString());
  d.settings = options.Describe();
  log::Progress progress("extracting (oxbow SIFT, RootSIFT)", files.size(), "images");
  for (size_t i = 0; i < files.size(); ++i) {
    auto features = extractor->ExtractFromFile(files[i]);
    progress.Advance();
    if (!features) continue;
    auto& target = i % 10 == 0 ? d.queries : d.train;
    target.insert(target.end(), features->descriptors.begin(), features->descriptors.end());
  }
  std::ofstream out(cache, std::ios::binary);
  const uint64_t nt = d.train.size() / 128, nq = d.queries.size() / 128;
  out.write(reinterpret_cast<const char*>(&nt), 8).write(reinterpret_cast<const char*>(&nq), 8);
  out.write(reinterpret_cast<const char*>(d.train.data()), static_cast<std::streamsize>(nt * 512));
  out.write(reinterpret_cast<const char*>(d.queries.data()), static_cast<std::streamsize>(nq * 512));
  out << d.settings << "\n";
  return d;
}

std::vector<float> Subsample(const std::vector<float>& x, size_t count, uint32_t seed) {
  const size_t n = x.size() / 128;
  std::vector<size_t> idx(n);
  std::iota(idx.begin(), idx.end(), 0);
  std::mt19937_64 rng(seed);
  std::shuffle(idx.begin(), idx.end(), rng);
  idx.resize(std::min(n, count));
  std::sort(idx.begin(), idx.end());
  std::vector<float> out;
  out.reserve(idx.size() * 128);
  for (size_t i : idx) out.insert(out.end(), x.begin() + i * 128, x.begin() + (i + 1) * 128);
  return out;
}

// Mean squared distance of x to its nearest row of `centroids` (exact; evaluated the same way for all).
double Objective(const std::vector<float>& centroids, const std::vector<float>& x) {
  auto vocab = vocab::Vocabulary::FromCentroids(centroids, 128, sift::DescriptorKind::kRootSift, "", {.iterations = 1});
  const size_t n = x.size() / 128;
  std::vector<uint32_t> w(n);
  vocab->Quantize(x, w, {.num_threads = 0, .exact = true});
  double sum = 0;
  for (size_t i = 0; i < n; ++i)
    sum += vocab::internal::SquaredL2Scalar(x.data() + i * 128, vocab->centroids().data() + size_t{w[i]} * 128, 128);
  return sum / n;
}

void TrainingComparison(const Descriptors& d, size_t sample_size, size_t k, int iterations, int reps) {
  const std::vector<float> sample = Subsample(d.train, sample_size, 7);
  const size_t n = sample.size() / 128;
  const int threads = ResolveThreadCount(0);
  std::printf("\n## Training: %zu words from %zu RootSIFT descriptors, %d iterations, %d threads (median of %d)\n\n",
              k, n, iterations, threads, reps);
  std::map<std::string, std::vector<double>> times;
  std::map<std::string, double> objective;
  for (int rep = 0; rep < reps; ++rep) {
    {
      vocab::TrainOptions o;
      o.num_words = k;
      o.max_iterations = iterations;
      o.min_relative_improvement = 0;
      o.assignment = vocab::AssignmentMethod::kExact;
      const auto t = Clock::now();
      auto v = vocab::Train(sample, 128, sift::DescriptorKind::kRootSift, d.settings, o);
      times["oxbow Train (k-means++, exact)"].push_back(Seconds(t));
      objective["oxbow Train (k-means++, exact)"] =
          Objective(std::vector<float>(v->centroids().begin(), v->centroids().end()), sample);
    }
    {
      cv::setNumThreads(threads);
      cv::Mat data(static_cast<int>(n), 128, CV_32F, const_cast<float*>(sample.data()));
      cv::Mat labels, centers;
      cv::setRNGSeed(1);
      const auto t = Clock::now();
      cv::kmeans(data, static_cast<int>(k), labels, cv::TermCriteria(cv::TermCriteria::MAX_ITER, iterations, 0), 1,
                 cv::KMEANS_PP_CENTERS, centers);
      times["cv::kmeans (KMEANS_PP_CENTERS)"].push_back(Seconds(t));
      objective["cv::kmeans (KMEANS_PP_CENTERS)"] =
          Objective(std::vector<float>(centers.ptr<float>(), centers.ptr<float>() + k * 128), sample);
    }
    {
      omp_set_num_threads(threads);
      faiss::ClusteringParameters cp;
      cp.niter = iterations;
      cp.max_points_per_centroid = 1 << 30;  // use the whole sample, like the others
      cp.seed = 1;
      faiss::Clustering clustering(128, k, cp);
      faiss::IndexFlatL2 index(128);
      const auto t = Clock::now();
      clustering.train(n, sample.data(), index);
      times["faiss::Clustering (random init, flat)"].push_back(Seconds(t));
      objective["faiss::Clustering (random init, flat)"] = Objective(clustering.centroids, sample);
    }
  }
  std::printf("| method | time (s) | final objective (mean sq. distance) |\n|---|---|---|\n");
  for (const auto& [name, t] : times) std::printf("| %s | %.2f | %.5f |\n", name.c_str(), Median(t), objective[name]);
}

struct Method {
  std::string name;
  std::function<void(const float*, size_t, uint32_t*)> assign;
};

// Hash of the training descriptors and extractor settings: part of every cached vocabulary's name, so
// a cache made from other data is never reused.
uint64_t DataHash(const Descriptors& d) {
  const std::string_view bytes(reinterpret_cast<const char*>(d.train.data()), d.train.size() * sizeof(float));
  return std::hash<std::string_view>{}(bytes) ^ (std::hash<std::string>{}(d.settings) * 0x9E3779B97F4A7C15ull);
}

// The vocabulary of k words benchmarked for assignment: cached, or made now (trained, or synthetic from
// data) and cached. `origin` receives a description for the table title.
vocab::Vocabulary AssignmentVocabulary(const Descriptors& d, size_t k, int iterations, const std::string& cache_dir,
                                       bool synthetic, std::string& origin) {
  const size_t train_n = d.train.size() / 128;
  const bool trained = !synthetic && k <= 200000 && 2 * k <= train_n;
  constexpr uint64_t kSeed = 1;
  char key[160];
  if (trained) {
    std::snprintf(key, sizeof(key), "k%zu_trained_ivf_it%d_seed%llu_n%zu_data%016llx", k, iterations,
                  static_cast<unsigned long long>(kSeed), train_n, static_cast<unsigned long long>(DataHash(d)));
    origin = "trained with Train on " + std::to_string(train_n) + " descriptors, ivf assignment, " +
             std::to_string(iterations) + " iterations";
  } else {
    std::snprintf(key, sizeof(key), "k%zu_synthetic_sigma0.01_seed5_n%zu_data%016llx", k, train_n,
                  static_cast<unsigned long long>(DataHash(d)));
    origin = "synthetic from data (training descriptors + N(0, 0.01^2) noise), not trained";
  }
  const std::string path = cache_dir + "/oxbow_vocab_bench_" + key + ".vocab";
  if (auto v = vocab::Vocabulary::Read(path)) {
    std::printf("(vocabulary read from the cache %s)\n", path.c_str());
    return std::move(*v);
  }
  std::optional<vocab::Vocabulary> vocab;
  if (trained) {
    vocab::TrainOptions o;
    o.num_words = k;
    o.max_iterations = iterations;
    o.min_relative_improvement = 0;
    o.seed = kSeed;
    o.assignment = vocab::AssignmentMethod::kInvertedFile;
    vocab::TrainReport report;
    const auto t = Clock::now();
    auto v = vocab::Train(d.train, 128, sift::DescriptorKind::kRootSift, d.settings, o, &report);
    if (!v) throw std::runtime_error(v.error().ToString());
    std::printf("(trained %zu words on %zu descriptors in %.1f s wall, %zu iterations, objective %.5f)\n", k, train_n,
                Seconds(t), report.iterations.size(), report.iterations.back().objective);
    vocab = std::move(*v);
  } else {
    std::mt19937 rng(5);
    std::normal_distribution<float> noise(0.f, 0.01f);
    std::vector<float> c(k * 128);
    for (size_t w = 0; w < k; ++w) {
      const size_t src = (w * 2654435761u) % train_n;
      for (int j = 0; j < 128; ++j) c[w * 128 + j] = std::max(0.f, d.train[src * 128 + j] + noise(rng));
    }
    const auto t = Clock::now();
    vocab = *vocab::Vocabulary::FromCentroids(std::move(c), 128, sift::DescriptorKind::kRootSift, d.settings);
    std::printf("(built the quantiser of %zu words in %.1f s)\n", k, Seconds(t));
  }
  if (auto written = vocab->Write(path); !written)
    std::printf("(could not cache the vocabulary: %s)\n", written.error().ToString().c_str());
  return std::move(*vocab);
}

void AssignmentComparison(const Descriptors& d, const vocab::Vocabulary& vocab_ref, const std::string& origin,
                          size_t num_queries, int reps, bool peers) {
  const vocab::Vocabulary* vocab = &vocab_ref;
  const size_t k = vocab->size();
  const std::vector<float> queries = Subsample(d.queries, num_queries, 11);
  const size_t nq = queries.size() / 128;
  std::vector<uint32_t> truth(nq);
  vocab->Quantize(queries, truth, {.num_threads = 0, .exact = true});
  const std::vector<float> centroids(vocab->centroids().begin(), vocab->centroids().end());

  // ---- Peers (built with all threads; searched on one) ----
  std::vector<Method> methods;
  for (int probes : {1, 2, 4, 8, 12, 16, 24, 32, 48, 64}) {
    if (static_cast<size_t>(probes) > vocab->num_lists()) continue;
    methods.push_back({"oxbow two-level, " + std::to_string(vocab->num_lists()) + " lists, " +
                           std::to_string(probes) + " probes",
                       [&, probes](const float* q, size_t n, uint32_t* out) {
                         vocab->Quantize({q, n * 128}, {out, n}, {.num_threads = 1, .num_probes = probes});
                       }});
  }
  if (peers) {
    methods.push_back({"oxbow exact (panel kernel)", [&](const float* q, size_t n, uint32_t* out) {
                         vocab->Quantize({q, n * 128}, {out, n}, {.num_threads = 1, .exact = true});
                       }});
  }
  flann::Matrix<float> dataset(const_cast<float*>(centroids.data()), k, 128);
  flann::Index<flann::L2<float>> kdforest(dataset, flann::KDTreeIndexParams(8));
  if (peers) {
    const auto t = Clock::now();
    kdforest.buildIndex();
    std::printf("(FLANN kd-forest, 8 trees, built in %.1f s)\n", Seconds(t));
    for (int checks : {32, 128, 512}) {
      methods.push_back({"FLANN kd-forest, 8 trees, " + std::to_string(checks) + " checks",
                         [&, checks](const float* q, size_t n, uint32_t* out) {
                           std::vector<int> idx(n);
                           std::vector<float> dist(n);
                           flann::Matrix<float> qm(const_cast<float*>(q), n, 128);
                           flann::Matrix<int> im(idx.data(), n, 1);
                           flann::Matrix<float> dm(dist.data(), n, 1);
                           flann::SearchParams p(checks);
                           p.cores = 1;
                           kdforest.knnSearch(qm, im, dm, 1, p);
                           for (size_t i = 0; i < n; ++i) out[i] = static_cast<uint32_t>(idx[i]);
                         }});
    }
  }
  omp_set_num_threads(ResolveThreadCount(0));
  faiss::IndexFlatL2 flat(128);
  std::unique_ptr<faiss::IndexHNSWFlat> hnsw;
  const bool faiss_peers = peers && k <= 200000;
  if (faiss_peers) {
    flat.add(static_cast<faiss::Index::idx_t>(k), centroids.data());
    hnsw = std::make_unique<faiss::IndexHNSWFlat>(128, 32);
    const auto t = Clock::now();
    hnsw->add(static_cast<faiss::Index::idx_t>(k), centroids.data());
    std::printf("(faiss HNSW M=32 built in %.1f s on %d threads)\n", Seconds(t), ResolveThreadCount(0));
  }
  auto faiss_search = [](faiss::Index& index, const float* q, size_t n, uint32_t* out) {
    std::vector<faiss::Index::idx_t> labels(n);
    std::vector<float> dist(n);
    index.search(static_cast<faiss::Index::idx_t>(n), q, 1, dist.data(), labels.data());
    for (size_t i = 0; i < n; ++i) out[i] = static_cast<uint32_t>(labels[i]);
  };
  // faiss's flat search goes through BLAS sgemm for batches of 20 or more queries; Debian's default
  // libblas.so.3 is the reference (netlib) BLAS, so faiss's own SIMD distance loop (BLAS threshold
  // raised above the batch) is measured too.
  if (faiss_peers) {
    methods.push_back({"faiss IndexFlatL2 (exact, sgemm via Debian reference libblas)",
                       [&](const float* q, size_t n, uint32_t* out) { faiss_search(flat, q, n, out); }});
    methods.push_back({"faiss IndexFlatL2 (exact, faiss distance loop, no BLAS)",
                       [&](const float* q, size_t n, uint32_t* out) {
                         const int saved = faiss::distance_compute_blas_threshold;
                         faiss::distance_compute_blas_threshold = std::numeric_limits<int>::max();
                         faiss_search(flat, q, n, out);
                         faiss::distance_compute_blas_threshold = saved;
                       }});
  }
  if (hnsw) {
    for (int ef : {16, 32, 64}) {
      methods.push_back({"faiss HNSW M=32, efSearch " + std::to_string(ef), [&, ef](const float* q, size_t n, uint32_t* out) {
                           hnsw->hnsw.efSearch = ef;
                           faiss_search(*hnsw, q, n, out);
                         }});
    }
  }
  omp_set_num_threads(1);
  cv::setNumThreads(1);

  // ---- Interleaved timing ----
  std::vector<std::vector<double>> rates(methods.size());
  std::vector<double> recall(methods.size());
  // Slow exact peers search a prefix of the queries.
  auto batch_for = [&](const std::string& name) {
    if (name.find("exact") != std::string::npos && k >= 100000) return std::min<size_t>(nq, 2000);
    return nq;
  };
  std::vector<uint32_t> out(nq);
  for (int rep = 0; rep < reps; ++rep) {
    for (size_t m = 0; m < methods.size(); ++m) {
      const size_t n = batch_for(methods[m].name);
      const double t = ThreadCpuSeconds();
      methods[m].assign(queries.data(), n, out.data());
      rates[m].push_back(n / (ThreadCpuSeconds() - t));
      size_t hits = 0;
      for (size_t i = 0; i < n; ++i) hits += out[i] == truth[i];
      recall[m] = static_cast<double>(hits) / n;
    }
  }
  std::printf("\n## Assignment: %zu words (%s), %zu held-out queries, one core, thread CPU time (median of %d; load %s)\n\n",
              k, origin.c_str(), nq, reps, LoadAverage().c_str());
  std::printf("| method | descriptors/s | recall@1 | queries timed |\n|---|---|---|---|\n");
  for (size_t m = 0; m < methods.size(); ++m)
    std::printf("| %s | %.0f | %.3f | %zu |\n", methods[m].name.c_str(), Median(rates[m]), recall[m],
                batch_for(methods[m].name));
  std::fflush(stdout);
}

// The real training descriptors followed by jittered copies up to `total` rows: copy j of descriptor
// i is x_i + N(0, sigma^2) per component, negative components set to 0, then L2-normalised again
// (RootSIFT vectors have unit L2 norm). Copies cycle over the real descriptors in order.
std::vector<float> Expand(const std::vector<float>& real, size_t total, float sigma, uint64_t seed) {
  const size_t n = real.size() / 128;
  std::vector<float> out(total * 128);
  std::copy_n(real.data(), std::min(n, total) * 128, out.data());
  ParallelFor(total > n ? total - n : 0, 0, 65536, [&](size_t begin, size_t end, int) {
    for (size_t r = begin; r < end; ++r) {
      vocab::internal::SplitMix64 rng(seed * 0x9E3779B97F4A7C15ull + r);
      const float* src = real.data() + (r % n) * 128;
      float* dst = out.data() + (n + r) * 128;
      double norm = 0;
      for (int j = 0; j < 128; j += 2) {  // Box-Muller, two normals per draw
        const double u1 = 1.0 - rng.Uniform01(), u2 = rng.Uniform01();
        const double radius = std::sqrt(-2.0 * std::log(u1));
        dst[j] = std::max(0.f, src[j] + sigma * static_cast<float>(radius * std::cos(2 * M_PI * u2)));
        dst[j + 1] = std::max(0.f, src[j + 1] + sigma * static_cast<float>(radius * std::sin(2 * M_PI * u2)));
        norm += double{dst[j]} * dst[j] + double{dst[j + 1]} * dst[j + 1];
      }
      const float inv = norm > 0 ? static_cast<float>(1.0 / std::sqrt(norm)) : 0.f;
      for (int j = 0; j < 128; ++j) dst[j] *= inv;
    }
  });
  return out;
}

// Trains k words on `total` descriptors (Expand of the training descriptors) with `threads` threads
// and the default (auto) assignment, all iterations; prints the per-iteration table.
void ScaleTraining(const Descriptors& d, size_t k, size_t total, int iterations, int threads, float sigma,
                   const std::string& out_path) {
  const auto t_expand = Clock::now();
  const std::vector<float> x = Expand(d.train, total, sigma, 3);
  const size_t real = std::min(total, d.train.size() / 128);
  std::printf("\n## Scale: %zu words from %zu descriptors (%zu real RootSIFT + %zu jittered copies, sigma %.3f, "
              "clamped at 0, L2-renormalised; made in %.1f s), %d threads, %d iterations, load at start %s\n\n",
              k, total, real, total - real, sigma, Seconds(t_expand), threads, iterations, LoadAverage().c_str());
  std::fflush(stdout);
  vocab::TrainOptions o;
  o.num_words = k;
  o.max_iterations = iterations;
  o.min_relative_improvement = 0;
  o.num_threads = threads;
  o.quantizer.num_threads = threads;
  vocab::TrainReport report;
  const double cpu0 = [] { timespec ts; clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts); return ts.tv_sec + 1e-9 * ts.tv_nsec; }();
  auto v = vocab::Train(x, 128, sift::DescriptorKind::kRootSift, d.settings, o, &report);
  const double cpu = [] { timespec ts; clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts); return ts.tv_sec + 1e-9 * ts.tv_nsec; }() - cpu0;
  if (!v) throw std::runtime_error(v.error().ToString());
  double iteration_sum = 0;
  std::printf("| iteration | wall (s) | objective | reassigned | empty clusters |\n|---|---|---|---|---|\n");
  for (const auto& it : report.iterations) {
    iteration_sum += it.seconds;
    std::printf("| %d | %.1f | %.5f | %.1f%% | %zu |\n", it.iteration, it.seconds, it.objective,
                100 * it.reassigned_share, it.empty_clusters);
  }
  const double quantiser = report.total_seconds - report.seeding_seconds - iteration_sum;
  std::vector<double> iteration_seconds;
  iteration_seconds.reserve(report.iterations.size());
  for (const auto& it : report.iterations) iteration_seconds.push_back(it.seconds);
  std::printf("\nseeding %.1f s, iterations %.1f s (median %.1f s each), final quantiser build %.1f s, total %.1f s wall, "
              "%.1f s process CPU (%d threads), load at end %s\n",
              report.seeding_seconds, iteration_sum,
              Median(iteration_seconds),
              quantiser, report.total_seconds, cpu, threads, LoadAverage().c_str());
  if (!out_path.empty()) {
    if (auto w = v->Write(out_path); !w) std::printf("could not write %s: %s\n", out_path.c_str(), w.error().ToString().c_str());
    else std::printf("wrote %s (%zu words, %zu lists)\n", out_path.c_str(), v->size(), v->num_lists());
  }
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  std::string images = OXBOW_SOURCE_DIR "/../shared/data/paris6k/images";
  std::string cache = "/tmp/oxbow_vocab_bench_descriptors.bin";
  std::vector<size_t> words = {10000, 100000, 1000000};
  size_t num_queries = 20000, train_sample = 100000, train_words = 1000;
  int train_iterations = 10, reps = 3, vocab_iterations = 8;
  bool skip_train = false, synthetic = false, peers = true;
  std::string vocab_file, scale_out;
  size_t scale_words = 0, scale_descriptors = 5'000'000;
  int scale_iterations = 2, scale_threads = 2;
  float scale_sigma = 0.02f;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) throw std::runtime_error("missing value after " + a);
      return argv[++i];
    };
    if (a == "--images") images = next();
    else if (a == "--cache") cache = next();
    else if (a == "--queries") num_queries = std::stoul(next());
    else if (a == "--train-sample") train_sample = std::stoul(next());
    else if (a == "--train-words") train_words = std::stoul(next());
    else if (a == "--train-iterations") train_iterations = std::stoi(next());
    else if (a == "--reps") reps = std::stoi(next());
    else if (a == "--skip-train") skip_train = true;
    else if (a == "--no-avx512") AllowAvx512(false);
    else if (a == "--oxbow-only") peers = false;
    else if (a == "--synthetic") synthetic = true;
    else if (a == "--vocab-iterations") vocab_iterations = std::stoi(next());
    else if (a == "--vocab") vocab_file = next();
    else if (a == "--scale-words") scale_words = std::stoul(next());
    else if (a == "--scale-descriptors") scale_descriptors = std::stoul(next());
    else if (a == "--scale-iterations") scale_iterations = std::stoi(next());
    else if (a == "--scale-threads") scale_threads = std::stoi(next());
    else if (a == "--scale-sigma") scale_sigma = std::stof(next());
    else if (a == "--scale-out") scale_out = next();
    else if (a == "--words") {
      words.clear();
      std::string list = next();
      if (list == "none") list.clear();
      for (size_t p = 0; p < list.size();) {
        size_t q = list.find(',', p);
        if (q == std::string::npos) q = list.size();
        words.push_back(std::stoul(list.substr(p, q - p)));
        p = q + 1;
      }
    } else {
      std::fprintf(stderr, "usage: %s [--images DIR] [--cache FILE] [--words K,K,..|none] [--queries N] [--train-sample N]"
                           " [--train-words K] [--train-iterations N] [--reps N] [--skip-train] [--synthetic]"
                           " [--vocab-iterations N] [--vocab FILE] [--scale-words K] [--scale-descriptors N]"
                           " [--scale-iterations N] [--scale-threads T] [--scale-sigma S] [--scale-out FILE] [--no-avx512]"
                           " [--oxbow-only]\n", argv[0]);
      return 2;
    }
  }
  if (!fs::exists(images) && !fs::exists(cache)) {
    std::fprintf(stderr, "no images at %s (see /work/shared/data/README.md)\n", images.c_str());
    return 1;
  }
  const Descriptors d = Load(images, cache);
  std::printf("# oxbow vocabulary benchmark\n\n%zu training and %zu held-out RootSIFT descriptors (%s), %s\n",
              d.train.size() / 128, d.queries.size() / 128, d.settings.c_str(),
              Avx512Available()    ? "AVX-512 kernels (16-word panels)"
              : Avx2FmaAvailable() ? "AVX2+FMA kernels"
                                   : "scalar kernels"
  );
  if (!skip_train) TrainingComparison(d, train_sample, train_words, train_iterations, reps);
  if (scale_words > 0) ScaleTraining(d, scale_words, scale_descriptors, scale_iterations, scale_threads, scale_sigma, scale_out);
  if (!vocab_file.empty()) {
    auto v = vocab::Vocabulary::Read(vocab_file);
    if (!v) {
      std::fprintf(stderr, "%s\n", v.error().ToString().c_str());
      return 1;
    }
    AssignmentComparison(d, *v, "read from " + vocab_file, num_queries, reps, peers);
  }
  for (size_t k : words) {
    std::string origin;
    const vocab::Vocabulary v = AssignmentVocabulary(d, k, vocab_iterations, fs::path(cache).parent_path().string(),
                                                     synthetic || k > 200000, origin);
    AssignmentComparison(d, v, origin, num_queries, reps, peers);
  }
  return 0;
}
