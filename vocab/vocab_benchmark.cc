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
// Usage: vocab_benchmark [--images DIR] [--cache FILE] [--words 10000,100000,1000000] [--queries N]
//                        [--train-sample N] [--train-words K] [--train-iterations N] [--reps N] [--skip-train] [--synthetic]
// The 10k and 100k vocabularies are trained with Train (inverted-file assignment); the 1M one is
// synthetic-from-data (training descriptors + Gaussian noise, sigma 0.01): training 1M words is too
// long for a benchmark run. Vocabularies are cached next to the descriptor cache.
#include <faiss/Clustering.h>
#include <faiss/IndexFlat.h>
#include <faiss/IndexHNSW.h>
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
#include <map>
#include <random>
#include <string>
#include <vector>

#include "sift/log.h"
#include "sift/parallel.h"
#include "sift/sift.h"
#include "vocab/kernels.h"
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
      times["oxbow Train (k-means++, exact AVX2)"].push_back(Seconds(t));
      objective["oxbow Train (k-means++, exact AVX2)"] =
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

void AssignmentComparison(const Descriptors& d, size_t k, size_t num_queries, int reps, const std::string& cache_dir,
                          bool synthetic) {
  // ---- The vocabulary ----
  const std::string path = cache_dir + "/oxbow_vocab_bench_" + std::to_string(k) + ".vocab";
  std::optional<vocab::Vocabulary> vocab;
  if (auto v = vocab::Vocabulary::Read(path)) vocab = std::move(*v);
  std::string origin;
  const size_t train_n = d.train.size() / 128;
  if (!synthetic && k <= 200000 && 2 * k <= train_n) {
    origin = "trained (Train, ivf assignment, 8 iterations)";
    if (!vocab) {
      vocab::TrainOptions o;
      o.num_words = k;
      o.max_iterations = 8;
      o.assignment = vocab::AssignmentMethod::kInvertedFile;
      const auto t = Clock::now();
      auto v = vocab::Train(d.train, 128, sift::DescriptorKind::kRootSift, d.settings, o);
      std::printf("(trained %zu words on %zu descriptors in %.1f s)\n", k, train_n, Seconds(t));
      vocab = std::move(*v);
      (void)vocab->Write(path);
    }
  } else {
    origin = "synthetic from data (training descriptors + N(0, 0.01^2) noise)";
    if (!vocab) {
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
      (void)vocab->Write(path);
    }
  }
  const std::vector<float> queries = Subsample(d.queries, num_queries, 11);
  const size_t nq = queries.size() / 128;
  std::vector<uint32_t> truth(nq);
  vocab->Quantize(queries, truth, {.num_threads = 0, .exact = true});
  const std::vector<float> centroids(vocab->centroids().begin(), vocab->centroids().end());

  // ---- Peers (built with all threads; searched on one) ----
  std::vector<Method> methods;
  for (int probes : {1, 2, 4, 8, 12, 16, 24, 32}) {
    if (static_cast<size_t>(probes) > vocab->num_lists()) continue;
    methods.push_back({"oxbow two-level, " + std::to_string(vocab->num_lists()) + " lists, " +
                           std::to_string(probes) + " probes",
                       [&, probes](const float* q, size_t n, uint32_t* out) {
                         vocab->Quantize({q, n * 128}, {out, n}, {.num_threads = 1, .num_probes = probes});
                       }});
  }
  methods.push_back({"oxbow exact (AVX2 tiles)", [&](const float* q, size_t n, uint32_t* out) {
                       vocab->Quantize({q, n * 128}, {out, n}, {.num_threads = 1, .exact = true});
                     }});
  flann::Matrix<float> dataset(const_cast<float*>(centroids.data()), k, 128);
  flann::Index<flann::L2<float>> kdforest(dataset, flann::KDTreeIndexParams(8));
  kdforest.buildIndex();
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
  omp_set_num_threads(ResolveThreadCount(0));
  faiss::IndexFlatL2 flat(128);
  flat.add(static_cast<faiss::Index::idx_t>(k), centroids.data());
  std::unique_ptr<faiss::IndexHNSWFlat> hnsw;
  if (k <= 200000) {
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
  if (k <= 200000)
    methods.push_back({"faiss IndexFlatL2 (exact)", [&](const float* q, size_t n, uint32_t* out) {
                         faiss_search(flat, q, n, out);
                       }});
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
  std::printf("\n## Assignment: %zu words (%s), %zu held-out queries, one core, thread CPU time (median of %d)\n\n", k, origin.c_str(),
              nq, reps);
  std::printf("| method | descriptors/s | recall@1 |\n|---|---|---|\n");
  for (size_t m = 0; m < methods.size(); ++m)
    std::printf("| %s | %.0f | %.3f |\n", methods[m].name.c_str(), Median(rates[m]), recall[m]);
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  std::string images = OXBOW_SOURCE_DIR "/../shared/data/paris6k/images";
  std::string cache = "/tmp/oxbow_vocab_bench_descriptors.bin";
  std::vector<size_t> words = {10000, 100000, 1000000};
  size_t num_queries = 20000, train_sample = 100000, train_words = 1000;
  int train_iterations = 10, reps = 3;
  bool skip_train = false, synthetic = false;
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
    else if (a == "--synthetic") synthetic = true;
    else if (a == "--words") {
      words.clear();
      std::string list = next();
      for (size_t p = 0; p < list.size();) {
        size_t q = list.find(',', p);
        if (q == std::string::npos) q = list.size();
        words.push_back(std::stoul(list.substr(p, q - p)));
        p = q + 1;
      }
    } else {
      std::fprintf(stderr, "usage: %s [--images DIR] [--cache FILE] [--words K,K,..] [--queries N] [--train-sample N]"
                           " [--train-words K] [--train-iterations N] [--reps N] [--skip-train] [--synthetic]\n", argv[0]);
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
#ifdef OXBOW_VOCAB_AVX2
              "AVX2+FMA kernels"
#else
              "scalar kernels"
#endif
  );
  if (!skip_train) TrainingComparison(d, train_sample, train_words, train_iterations, reps);
  for (size_t k : words) AssignmentComparison(d, k, num_queries, reps, fs::path(cache).parent_path().string(), synthetic || k > 200000);
  return 0;
}
