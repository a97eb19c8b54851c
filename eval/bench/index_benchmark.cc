// Index benchmark (run by hand, not a test).
//
//   index_benchmark synthetic [--images N] [--features F] [--vocab V] [--zipf S] [--queries Q]
//                             [--max-df D] [--geometry 0|1] [--threads T]
//     Builds the in-memory inverted file directly (InvertedFile::Build, not through SQLite) for N images
//     of F features each, words drawn from a Zipf(S) law over a V-word vocabulary (rank r has
//     probability ~ r^-S), random geometry. Prints build time, memory per feature (postings, geometry,
//     per-image tables, and process RSS), tf-idf query latency on ONE core (Q queries of F Zipf words,
//     p50/p95) for several stop-list settings, and re-ranking latency for R = 100/200 candidates.
//     Peer for scoring, in the same run on the same postings: a plain sparse dot product over the
//     postings uncompressed in CSR form ((image, t(tf)) pairs per word, 8 bytes each, inverse norms
//     precomputed), dense accumulator, partial sort. Both get the same query vectors (built outside
//     the timers) and warm scratch memory, and run alternately query by query; printed with the ratio
//     of medians and the share of top-200 results they agree on. --peer 0 skips it (it needs 8 bytes
//     per posting of extra memory).
//
//   index_benchmark storage --images N --out DIR [--features F] [--vocab V.oxvoc] [--words K]
//                           [--threads T] [--batch B] [--queries Q] [--data DIR] [--cache DIR] [--reuse 1]
//                           [--max-df D] [--stop-list-min-images M] [--photos P] [--export-features DIR2]
//                           [--max-scored-postings B1,B2,...] [--hamming-shortlist S1,S2,...] [--paris-map 1]
//                           [--hamming 0|1]
//     Creates DIR as a normal index folder through ImageIndex (Create, AddBatch in batches of B = 1000,
//     the SQLite catalogue: the code the server uses), servable as it is by `oxbow serve --index DIR`.
//     Its N synthetic images (1024 x 768) have F = 1000 features each, drawn with replacement from the
//     pool of every feature of real photos (the Paris subset's 250, or OpenCV's sample photos when it
//     is absent; RootSIFT, long side <= 1024 px): each synthetic feature is one real feature's visual
//     word (quantised once with the index's vocabulary) and its keypoint (position scaled to the
//     synthetic image, scale and orientation kept). So words follow the real photos' word
//     distribution, with real joint word/geometry statistics; unlike a real photo, a synthetic image's
//     features are independent draws (no bursts, no objects). Vocabulary: --vocab, else K = 100000
//     RootSIFT words trained on those photos and cached in --cache (default DIR.cache), with
//     Hamming-embedding parameters as `oxbow vocab train` gives by default (--hamming 0: without).
//     With such a vocabulary every synthetic feature also carries its real feature's signature
//     (computed once per real feature, as the words are), so searches run as on a default index.
//     Prints: ingest images/s (time inside AddBatch; words already assigned: no extraction, no
//     quantisation; making the synthetic images is timed apart), disk bytes per
//     feature, ImageIndex::Open time, resident bytes per feature after Open (RSS growth), tf-idf only and
//     full default search (QueryOptions{}: re-ranking, QE, transitive verification; and without the
//     transitive stage) p50/p95/p99 for Q real photos' features (quantisation included, extraction
//     not), add p50/p99 of single images while another thread searches, remove p50/p99. --reuse 1
//     skips the ingest and measures the rest on the folder an earlier run left in DIR (give the same
//     --images and --features). --max-df and --stop-list-min-images replace IndexOptions' stop list.
//     --max-scored-postings B1,B2,... (default 0,4000000: none, and 4M, the default) measures the full default
//     search with each posting budget (QueryOptions::max_scored_postings), every query with each in turn;
//     --hamming-shortlist S1,S2,... (default: QueryOptions' default, 300) likewise QueryOptions::hamming_shortlist,
//     every pair of the two lists.
//     --paris-map 1 (the Paris subset as the real photos) adds its 250 photos to the collection, runs its
//     12 cropped queries (restricted protocol, top 1000) with each pair and prints mAP among the N
//     synthetic images, then removes them again.
//     --photos P uses only the first P real photos. --export-features DIR2 also writes every synthetic
//     image as DIR2/<id>.oxfeat (each feature with its real photo's descriptor), so that
//     `oxbow index build --features DIR2 --vocab V` builds the same collection through the CLI
//     (tests/storage_path_test.cc compares the two). The words are assigned with the quantiser settings
//     Add uses (IndexOptions::quantizer), so both paths give every feature the same word.
//
//   index_benchmark features --features DIR --vocab V.oxvoc [--threads 1,2] [--repeat 3] [--oxbow PATH]
//     Ingest of feature files (.oxfeat from `oxbow extract`) against the quantiser's own speed, per
//     thread count T: the real command `oxbow index build --features DIR --vocab V --threads T` into a
//     fresh folder (process start, reading the files, quantisation with the index's quantiser settings,
//     AddBatch, SQLite; wall time of the process), and its peer, the quantiser alone:
//     Vocabulary::Quantize of the same descriptors (read before the timer) with the same settings and T
//     threads (parallel over images, as AddBatch). Run alternately, medians of --repeat runs; prints
//     descriptors/s per thread of both and the ratio.
//
//   index_benchmark paris [--data DIR] [--words K] [--max-side PX] [--repeat N] [--cache DIR]
//                         [--vocab FILE] [--threads T] [--filter TEXT] [--verbose 1]
//     The Paris subset protocol (../shared/data/README.md): extracts RootSIFT from the 250 images,
//     trains a K-word vocabulary on them, indexes them, runs the 12 cropped queries with and without
//     re-ranking and query expansion; prints mAP and per-stage latency p50/p95.
//     --cache DIR keeps the extracted features and the vocabulary in DIR (feature files and a .oxvoc per
//     K and max side) so that later runs only index and query. --vocab FILE uses that vocabulary (e.g.
//     one from `oxbow vocab train`) instead of training or the cached one. --threads T verifies with T
//     threads (IndexOptions::num_threads; default 1). --filter runs only the settings whose name
//     contains TEXT. --verbose 1 prints each query's AP and verified counts.
//     Latency columns are wall times per stage; the CPU column is the CPU time of the whole query
//     (process CPU time, so it counts every verification thread), which other processes on a shared
//     machine disturb far less than wall time. The load average is printed with them.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <new>
#include <numbers>
#include <optional>
#include <random>
#include <set>
#include <span>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <malloc.h>
#include <time.h>

#include "eval/synthetic_collection.h"
#include "index/storage/feature_store.h"
#include "index/image_index.h"
#include "index/postings/inverted_file.h"
#include "index/search/rerank.h"
#include "sift/features_io.h"
#include "sift/base/parallel.h"
#include "sift/sift.h"
#include "vocab/vocabulary.h"

// Counts heap allocations through operator new (the verifier's containers use it), for the
// re-ranking table. Every unaligned form is replaced, nothrow and array ones included: the standard
// library allocates through them too (std::stable_sort's temporary buffer uses nothrow new), and a
// form left to the runtime would pair its allocation with this file's free() (AddressSanitizer
// reports that as alloc-dealloc-mismatch).
std::atomic<uint64_t> g_allocations{0};

namespace {
void* CountedMalloc(size_t size) noexcept {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
  return std::malloc(size == 0 ? 1 : size);
}
void* CountedNew(size_t size) {
  if (void* p = CountedMalloc(size)) return p;
  throw std::bad_alloc();
}
}  // namespace

void* operator new(size_t size) { return CountedNew(size); }
void* operator new[](size_t size) { return CountedNew(size); }
void* operator new(size_t size, const std::nothrow_t&) noexcept { return CountedMalloc(size); }
void* operator new[](size_t size, const std::nothrow_t&) noexcept { return CountedMalloc(size); }
// Not inlined: GCC would otherwise see free() on a pointer from a new-expression and warn.
[[gnu::noinline]] void operator delete(void* p) noexcept { std::free(p); }
[[gnu::noinline]] void operator delete[](void* p) noexcept { std::free(p); }
[[gnu::noinline]] void operator delete(void* p, size_t) noexcept { std::free(p); }
[[gnu::noinline]] void operator delete[](void* p, size_t) noexcept { std::free(p); }
[[gnu::noinline]] void operator delete(void* p, const std::nothrow_t&) noexcept { std::free(p); }
[[gnu::noinline]] void operator delete[](void* p, const std::nothrow_t&) noexcept { std::free(p); }

namespace oxbow::index {
namespace {

using Clock = std::chrono::steady_clock;
double Ms(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double, std::milli>(b - a).count(); }

// CPU time of this process (all its threads), milliseconds: far less disturbed by other processes on
// a shared machine than wall time. Only the timed query runs while it is read.
double ProcessCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) * 1e-6;
}

double LoadAverage1() {
  double load = 0;
  std::ifstream("/proc/loadavg") >> load;
  return load;
}

double Percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const size_t i = std::min(v.size() - 1, static_cast<size_t>(std::ceil(p * static_cast<double>(v.size()))) - (p > 0 ? 1 : 0));
  return v[i];
}

uint64_t RssBytes() {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stoull(line.substr(6)) * 1024;
  }
  return 0;
}

std::map<std::string, std::string> ParseFlags(int argc, char** argv, int first) {
  std::map<std::string, std::string> flags;
  for (int i = first; i + 1 < argc; i += 2) flags[argv[i]] = argv[i + 1];
  return flags;
}

double Flag(const std::map<std::string, std::string>& f, const std::string& name, double fallback) {
  const auto it = f.find(name);
  return it == f.end() ? fallback : std::stod(it->second);
}

// A tiny deterministic generator, seeded per image so both Build passes see the same bag.
using eval::SplitMix;

// Vose's alias method: O(1) sampling from a discrete distribution.
class AliasTable {
 public:
  explicit AliasTable(const std::vector<double>& weights) : prob_(weights.size()), alias_(weights.size()) {
    const size_t n = weights.size();
    double sum = 0;
    for (double w : weights) sum += w;
    std::vector<double> scaled(n);
    std::vector<uint32_t> small, large;
    for (size_t i = 0; i < n; ++i) {
      scaled[i] = weights[i] * static_cast<double>(n) / sum;
      (scaled[i] < 1 ? small : large).push_back(static_cast<uint32_t>(i));
    }
    while (!small.empty() && !large.empty()) {
      const uint32_t s = small.back(), l = large.back();
      small.pop_back();
      prob_[s] = static_cast<float>(scaled[s]);
      alias_[s] = l;
      scaled[l] -= 1 - scaled[s];
      if (scaled[l] < 1) {
        large.pop_back();
        small.push_back(l);
      }
    }
    for (uint32_t i : large) prob_[i] = 1;
    for (uint32_t i : small) prob_[i] = 1;
  }
  uint32_t Sample(SplitMix& rng) const {
    const uint64_t r = rng.Next();
    const auto i = static_cast<uint32_t>((r >> 32) * prob_.size() >> 32);
    const float u = static_cast<float>(r & 0xffffffffu) * 0x1.0p-32f;
    return u < prob_[i] ? i : alias_[i];
  }

 private:
  std::vector<float> prob_;
  std::vector<uint32_t> alias_;
};

struct SyntheticImage {
  std::vector<uint32_t> words;
  std::vector<sift::Keypoint> keypoints;
};

SyntheticImage MakeImage(const AliasTable& zipf, uint64_t seed, int features, bool geometry) {
  SplitMix rng{seed * 0x2545f4914f6cdd1dull + 17};
  SyntheticImage img;
  img.words.resize(static_cast<size_t>(features));
  for (auto& w : img.words) w = zipf.Sample(rng);
  if (geometry) {
    img.keypoints.resize(static_cast<size_t>(features));
    for (auto& k : img.keypoints) {
      k.x = static_cast<float>(rng.Uniform() * 1023);
      k.y = static_cast<float>(rng.Uniform() * 767);
      k.scale = static_cast<float>(1.6 * std::exp2(rng.Uniform() * 4));
      k.orientation = static_cast<float>(rng.Uniform() * 2 * std::numbers::pi);
    }
  }
  return img;
}

// The scoring peer (see the file comment): the same tf-idf cosine as InvertedFile::Score, computed the
// straightforward way over uncompressed postings.
class CsrPostings {
 public:
  CsrPostings(const InvertedFile& file, uint32_t num_images, const std::function<BagOfWords(uint32_t)>& bag_of)
      : offsets_(file.vocabulary_size() + 1, 0), inv_norm_(num_images) {
    for (size_t w = 0; w < file.vocabulary_size(); ++w) {
      offsets_[w + 1] = offsets_[w] + file.DocumentFrequency(static_cast<uint32_t>(w));
    }
    images_.resize(offsets_.back());
    tf_weights_.resize(offsets_.back());
    std::vector<uint64_t> cursor(offsets_.begin(), offsets_.end() - 1);
    for (uint32_t image = 0; image < num_images; ++image) {
      const BagOfWords bag = bag_of(image);
      for (size_t i = 0; i < bag.words.size(); ++i) {
        const uint64_t at = cursor[bag.words[i]]++;
        images_[at] = image;
        tf_weights_[at] = file.TermWeight(bag.counts[i]);
      }
      inv_norm_[image] = static_cast<float>(1.0 / file.Norm(image));
    }
    accumulator_.assign(num_images, 0.0f);
  }

  uint64_t bytes() const {
    return images_.size() * (sizeof(uint32_t) + sizeof(float)) + offsets_.size() * sizeof(uint64_t) +
           inv_norm_.size() * sizeof(float);
  }

  // Not thread-safe (one accumulator).
  std::vector<ScoredImage> Score(const InvertedFile& file, std::span<const QueryTerm> query, size_t max_results) {
    for (const QueryTerm& term : query) {
      if (offsets_[term.word] == offsets_[term.word + 1]) continue;
      const auto weight = static_cast<float>(static_cast<double>(term.weight) * file.Idf(term.word));
      for (uint64_t i = offsets_[term.word]; i < offsets_[term.word + 1]; ++i) {
        accumulator_[images_[i]] += weight * tf_weights_[i];
      }
    }
    candidates_.clear();
    for (size_t i = 0; i < accumulator_.size(); ++i) {
      if (accumulator_[i] == 0) continue;
      candidates_.push_back({static_cast<uint32_t>(i), accumulator_[i] * inv_norm_[i]});
      accumulator_[i] = 0;
    }
    const size_t k = std::min(max_results, candidates_.size());
    std::partial_sort(candidates_.begin(), candidates_.begin() + static_cast<std::ptrdiff_t>(k), candidates_.end(),
                      [](const ScoredImage& x, const ScoredImage& y) {
                        return x.score != y.score ? x.score > y.score : x.image < y.image;
                      });
    return {candidates_.begin(), candidates_.begin() + static_cast<std::ptrdiff_t>(k)};
  }

 private:
  std::vector<uint64_t> offsets_;  // per word, into images_ / tf_weights_
  std::vector<uint32_t> images_;
  std::vector<float> tf_weights_;  // t(tf)
  std::vector<float> inv_norm_;    // 1 / |v(d)|
  std::vector<float> accumulator_;
  std::vector<ScoredImage> candidates_;
};

// Share of b's images that are also in a.
double Agreement(const std::vector<ScoredImage>& a, const std::vector<ScoredImage>& b) {
  std::set<uint32_t> in_a;
  for (const ScoredImage& s : a) in_a.insert(s.image);
  size_t shared = 0;
  for (const ScoredImage& s : b) shared += in_a.count(s.image);
  return b.empty() ? 1.0 : static_cast<double>(shared) / static_cast<double>(b.size());
}

int RunSynthetic(const std::map<std::string, std::string>& flags) {
  const auto num_images = static_cast<uint32_t>(Flag(flags, "--images", 100000));
  const int features = static_cast<int>(Flag(flags, "--features", 1000));
  const auto vocab_size = static_cast<size_t>(Flag(flags, "--vocab", 1000000));
  const double zipf_s = Flag(flags, "--zipf", 1.0);
  const int num_queries = static_cast<int>(Flag(flags, "--queries", 50));
  const bool with_geometry = Flag(flags, "--geometry", 1) != 0;
  const int threads = static_cast<int>(Flag(flags, "--threads", 0));
  const bool with_peer = Flag(flags, "--peer", 1) != 0;
  std::printf("synthetic: %u images x %d features, vocabulary %zu words, Zipf exponent %.2f, %s\n", num_images,
              features, vocab_size, zipf_s, with_geometry ? "with geometry" : "postings only");

  std::vector<double> weights(vocab_size);
  for (size_t r = 0; r < vocab_size; ++r) weights[r] = std::pow(static_cast<double>(r + 1), -zipf_s);
  const AliasTable zipf(weights);

  const uint64_t rss0 = RssBytes();
  auto t0 = Clock::now();
  const InvertedFile file = InvertedFile::Build(
      vocab_size, TfIdfOptions{}, num_images,
      [&](uint32_t image, BagOfWords* bag) {
        const SyntheticImage img = MakeImage(zipf, image, features, false);
        *bag = BagOfWords::FromWords(img.words);
        return true;
      },
      threads);
  auto t1 = Clock::now();
  const InvertedFileStats stats = file.Stats();
  const uint64_t rss1 = RssBytes();
  std::printf("build (2 passes incl. generating the words): %.1f s on %d threads\n", Ms(t0, t1) / 1000,
              ResolveThreadCount(threads));

  // Geometry store, as the index keeps it (one PackedFeatures per image).
  std::vector<PackedFeatures> geometry;
  uint64_t geometry_bytes = 0;
  if (with_geometry) {
    t0 = Clock::now();
    geometry.resize(num_images);
    ParallelFor(num_images, ResolveThreadCount(threads), 256, [&](size_t b, size_t e, int) {
      for (size_t i = b; i < e; ++i) {
        const SyntheticImage img = MakeImage(zipf, i, features, true);
        geometry[i] = PackedFeatures::Pack(img.keypoints, img.words, 1024, 768);
      }
    });
    for (const auto& g : geometry) geometry_bytes += g.MemoryBytes() + 16;  // + malloc header
    std::printf("geometry store: %.1f s\n", Ms(t0, Clock::now()) / 1000);
  }
  const uint64_t rss2 = RssBytes();
  const double nf = static_cast<double>(stats.num_features);
  const double per_image_geometry_overhead = sizeof(PackedFeatures) + 16.0;  // when not materialised
  const double geometry_per_feature =
      with_geometry ? static_cast<double>(geometry_bytes) / nf : kPackedFeatureBytes + per_image_geometry_overhead / features;
  std::printf("\n| memory (bytes per indexed feature) | value |\n|---|---|\n");
  std::printf("| postings (varint, incl. word offset tables) | %.3f |\n", static_cast<double>(stats.postings_bytes) / nf);
  std::printf("| geometry (9 B/feature + per-image vector)%s | %.3f |\n", with_geometry ? "" : " (computed, not allocated)",
              geometry_per_feature);
  std::printf("| per-image norm state + per-word df | %.3f |\n",
              static_cast<double>(stats.image_table_bytes + stats.word_table_bytes) / nf);
  std::printf("| **total** | **%.3f** |\n",
              (static_cast<double>(stats.postings_bytes + stats.image_table_bytes + stats.word_table_bytes)) / nf +
                  geometry_per_feature);
  std::printf("| process RSS growth / feature (build%s) | %.3f |\n", with_geometry ? " + geometry" : "",
              static_cast<double>(rss2 - rss0) / nf);
  std::printf("postings: %llu (%.3f per feature; %.1f%% of features merged into a (word, image) posting with tf > 1)\n",
              static_cast<unsigned long long>(stats.num_postings), static_cast<double>(stats.num_postings) / nf,
              100.0 * (1 - static_cast<double>(stats.num_postings) / nf));
  (void)rss1;

  std::optional<CsrPostings> peer;
  if (with_peer) {
    t0 = Clock::now();
    peer.emplace(file, num_images, [&](uint32_t image) { return BagOfWords::FromWords(MakeImage(zipf, image, features, false).words); });
    std::printf("peer: the same postings in CSR form, %.3f bytes per feature, built in %.1f s\n",
                static_cast<double>(peer->bytes()) / nf, Ms(t0, Clock::now()) / 1000);
  }

  // Queries: one-core tf-idf scoring for several stop lists; the query vectors are made outside the timers.
  std::vector<BagOfWords> queries;
  queries.reserve(static_cast<size_t>(num_queries));
  for (int q = 0; q < num_queries; ++q) {
    queries.push_back(BagOfWords::FromWords(MakeImage(zipf, 1'000'000'000ull + q, features, false).words));
  }
  std::printf("\n| stop list (max document frequency) | query words kept | postings scanned | oxbow p50 ms | p95 ms |%s\n",
              peer ? " CSR dot product p50 ms | p95 ms | oxbow / CSR (p50) | top-200 agreement |" : "");
  std::printf("|---|---|---|---|---|%s\n", peer ? "---|---|---|---|" : "");
  for (double max_df : {1.0, 0.1, 0.03, 0.01}) {
    std::vector<double> ms, peer_ms;
    double kept = 0, scanned = 0, agreement = 0;
    ScoreScratch scratch;
    for (int rep = 0; rep < 2; ++rep) {  // the first repetition warms caches and scratch memory
      for (const BagOfWords& q : queries) {
        std::vector<QueryTerm> terms = file.QueryVector(q);
        // The same postings with another query-time stop list (QueryVector applies the file's own).
        std::erase_if(terms, [&](const QueryTerm& t) {
          return static_cast<double>(file.DocumentFrequency(t.word)) > max_df * static_cast<double>(file.num_images());
        });
        // Alternate which of the two runs first.
        std::vector<ScoredImage> top, peer_top;
        double oxbow_ms = 0, csr_ms = 0;
        const bool oxbow_first = (&q - queries.data()) % 2 == 0;
        for (int turn = 0; turn < 2; ++turn) {
          const auto s = Clock::now();
          if ((turn == 0) == oxbow_first) {
            top = file.Score(terms, 200, &scratch);
            oxbow_ms = Ms(s, Clock::now());
          } else if (peer) {
            peer_top = peer->Score(file, terms, 200);
            csr_ms = Ms(s, Clock::now());
          }
        }
        if (top.empty()) std::printf("(empty result)\n");
        if (rep == 0) continue;
        ms.push_back(oxbow_ms);
        kept += static_cast<double>(terms.size());
        for (const auto& t : terms) scanned += file.DocumentFrequency(t.word);
        if (peer) {
          peer_ms.push_back(csr_ms);
          agreement += Agreement(top, peer_top);
        }
      }
    }
    std::printf("| %.2f | %.0f | %.3g | %.1f | %.1f |", max_df, kept / num_queries, scanned / num_queries,
                Percentile(ms, 0.5), Percentile(ms, 0.95));
    if (peer) {
      std::printf(" %.1f | %.1f | %.2f | %.3f |", Percentile(peer_ms, 0.5), Percentile(peer_ms, 0.95),
                  Percentile(ms, 0.5) / Percentile(peer_ms, 0.5), agreement / num_queries);
    }
    std::printf("\n");
  }

  // Re-ranking: verify the top R candidates of a query that is a similarity-transformed half of one
  // indexed image plus clutter (one true match, R-1 false candidates), split over T threads with
  // ParallelFor as ImageIndex::Query does. Heap allocations are counted while the verification runs;
  // the first query of each setting is a warm-up and not counted.
  if (with_geometry) {
    std::printf("\n| re-ranking | threads | p50 ms | p95 ms | heap allocations per query | verified |\n|---|---|---|---|---|---|\n");
    for (int depth : {100, 200}) {
      for (int rerank_threads : {1, 2}) {
        std::vector<double> ms;
        uint64_t allocations = 0;
        int verified_right = 0;
        const int count = std::min(num_queries, 20);
        for (int q = -1; q < count; ++q) {
          const uint32_t target = static_cast<uint32_t>((std::max(q, 0) * 7919) % num_images);
          const SyntheticImage src = MakeImage(zipf, target, features, true);
          SyntheticImage query = MakeImage(zipf, 2'000'000'000ull + static_cast<uint64_t>(std::max(q, 0)), features / 2, true);
          const double a = 0.4, sc = 0.8, ca = std::cos(a) * sc, sa = std::sin(a) * sc;
          for (int i = 0; i < features; i += 2) {
            sift::Keypoint k = src.keypoints[static_cast<size_t>(i)];
            const float x = k.x, y = k.y;
            k.x = static_cast<float>(ca * x - sa * y + 200);
            k.y = static_cast<float>(sa * x + ca * y + 50);
            k.scale *= static_cast<float>(sc);
            k.orientation = static_cast<float>(std::fmod(k.orientation + a, 2 * std::numbers::pi));
            query.keypoints.push_back(k);
            query.words.push_back(src.words[static_cast<size_t>(i)]);
          }
          ScoreScratch scratch;
          const auto terms = file.QueryVector(BagOfWords::FromWords(query.words));
          const auto top = file.Score(terms, static_cast<size_t>(depth), &scratch);
          std::vector<int> inliers(top.size(), -1);
          const QueryGeometry geometry_q(query.keypoints, query.words, {0, 0, 1400, 1100});
          const uint64_t allocations0 = g_allocations.load();
          const auto s = Clock::now();
          ParallelFor(top.size(), rerank_threads, 1, [&](size_t begin, size_t end, int) {
            for (size_t c = begin; c < end; ++c) {
              const auto v = geometry_q.Verify(geometry[top[c].image], 4, {});
              if (v.verified) inliers[c] = v.num_inliers;
            }
          });
          const double elapsed = Ms(s, Clock::now());
          if (q < 0) continue;
          allocations += g_allocations.load() - allocations0;
          ms.push_back(elapsed);
          const auto best = std::max_element(inliers.begin(), inliers.end());
          if (best != inliers.end() && *best > 0 && top[static_cast<size_t>(best - inliers.begin())].image == target) ++verified_right;
        }
        std::printf("| R = %d | %d | %.1f | %.1f | %.1f | %d/%zu right image verified best |\n", depth, rerank_threads,
                    Percentile(ms, 0.5), Percentile(ms, 0.95), static_cast<double>(allocations) / static_cast<double>(count),
                    verified_right, ms.size());
      }
    }
  }
  return 0;
}

// ---- Paris ------------------------------------------------------------------------------------------

std::vector<std::string> ReadLines(const std::filesystem::path& p) {
  std::vector<std::string> out;
  std::ifstream in(p);
  std::string line;
  while (std::getline(in, line)) {
    while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.pop_back();
    if (!line.empty()) out.push_back(line);
  }
  return out;
}

// Oxford compute_ap: junk skipped, trapezoidal precision.
double AveragePrecision(const std::vector<std::string>& ranked, const std::set<std::string>& positives,
                        const std::set<std::string>& junk) {
  double old_recall = 0, old_precision = 1, ap = 0;
  size_t intersect = 0, j = 0;
  for (const auto& id : ranked) {
    if (junk.count(id)) continue;
    if (positives.count(id)) ++intersect;
    const double recall = static_cast<double>(intersect) / static_cast<double>(positives.size());
    const double precision = static_cast<double>(intersect) / static_cast<double>(j + 1);
    ap += (recall - old_recall) * ((old_precision + precision) / 2.0);
    old_recall = recall;
    old_precision = precision;
    ++j;
  }
  return ap;
}

// The Paris subset's 12 queries under the restricted protocol (../shared/data/README.md): official
// good + ok (positives) and junk, intersected with the database `names` (file names, sorted).
struct ParisQuery {
  std::string name, image;
  std::array<float, 4> box;
  std::set<std::string> positives, junk;
};
std::vector<ParisQuery> ReadParisQueries(const std::filesystem::path& data, const std::vector<std::string>& names) {
  std::vector<ParisQuery> queries;
  for (const auto& line : ReadLines(data / "subset_queries_present.txt")) {
    std::istringstream in(line);
    ParisQuery q;
    in >> q.name;
    std::istringstream box_line(ReadLines(data / "gt" / (q.name + "_query.txt")).at(0));
    box_line >> q.image >> q.box[0] >> q.box[1] >> q.box[2] >> q.box[3];
    auto in_database = [&](const std::string& id) {
      return std::binary_search(names.begin(), names.end(), id + ".jpg");
    };
    for (const char* kind : {"good", "ok"}) {
      for (const auto& id : ReadLines(data / "gt" / (q.name + "_" + kind + ".txt"))) {
        if (in_database(id)) q.positives.insert(id);
      }
    }
    for (const auto& id : ReadLines(data / "gt" / (q.name + "_junk.txt"))) {
      if (in_database(id)) q.junk.insert(id);
    }
    queries.push_back(std::move(q));
  }
  return queries;
}

// A deeper and costlier search than the defaults: re-ranking 200, 16 probes, 4 pairs per word, 1000
// transitive attempts.
void DeepSearch(QueryOptions* o) {
  o->rerank_depth = 200;
  o->quantizer_probes = 16;
  o->max_pairs_per_word = 4;
  o->transitive_attempts = 1000;
}

// RootSIFT features of `paths` (long side <= max_side), read from / written to `cache` (a folder, or
// empty for none) as .oxfeat files; an image that cannot be read gives an empty set.
std::vector<sift::FeatureSet> ExtractCached(const std::vector<std::string>& paths, const sift::SiftOptions& sift_options,
                                            int max_side, const std::filesystem::path& cache) {
  namespace fs = std::filesystem;
  const auto extractor = *sift::SiftExtractor::Create(sift_options);
  sift::DecodeOptions decode;
  decode.max_image_side_px = max_side;
  if (!cache.empty()) fs::create_directories(cache);
  const std::string cache_tag = "_" + std::to_string(max_side);
  std::vector<sift::FeatureSet> features(paths.size());
  const auto t0 = Clock::now();
  ParallelFor(paths.size(), 0, 1, [&](size_t b, size_t e, int) {
    for (size_t i = b; i < e; ++i) {
      const std::string name = fs::path(paths[i]).filename().string();
      const fs::path cached = cache.empty() ? fs::path() : cache / (name + cache_tag + ".oxfeat");
      if (!cached.empty()) {
        if (auto file = sift::ReadFeatureFile(cached.string()); file && file->extractor_description == sift_options.Describe()) {
          features[i] = std::move(file->features);
          continue;
        }
      }
      auto f = extractor.ExtractFromFile(paths[i], decode);
      if (!f) continue;
      features[i] = std::move(*f);
      if (!cached.empty()) {
        const sift::FeatureFile file{.features = features[i], .extractor_description = sift_options.Describe()};
        if (!sift::WriteFeatureFile(cached.string(), file)) std::printf("cannot write %s\n", cached.c_str());
      }
    }
  });
  size_t total = 0;
  for (const auto& f : features) total += f.size();
  std::printf("extracted %zu images, %zu RootSIFT features (%.0f/image) in %.0f s\n", paths.size(), total,
              static_cast<double>(total) / static_cast<double>(std::max<size_t>(1, paths.size())),
              Ms(t0, Clock::now()) / 1000);
  return features;
}

// --vocab FILE, else the `words`-word vocabulary cached in `cache`, else one trained on (a sample of)
// `features` (as in Philbin et al. 2007) and cached.
std::optional<vocab::Vocabulary> ReadOrTrainVocabulary(const std::map<std::string, std::string>& flags,
                                                       const std::vector<sift::FeatureSet>& features, size_t words,
                                                       const sift::SiftOptions& sift_options, int max_side,
                                                       const std::filesystem::path& cache, bool hamming = false) {
  namespace fs = std::filesystem;
  const std::string cache_tag = "_" + std::to_string(max_side) + (hamming ? "_he" : "");
  const fs::path vocab_file = flags.count("--vocab") ? fs::path(flags.at("--vocab"))
                              : cache.empty()        ? fs::path()
                                                     : cache / ("vocab_" + std::to_string(words) + cache_tag + ".oxvoc");
  Result<vocab::Vocabulary> vocabulary = std::unexpected(Error{});
  if (!vocab_file.empty()) vocabulary = vocab::Vocabulary::Read(vocab_file.string());
  if (vocabulary) {
    std::printf("vocabulary: %zu words read from %s\n", vocabulary->size(), vocab_file.c_str());
    return std::move(*vocabulary);
  }
  if (flags.count("--vocab")) {
    std::printf("cannot read %s: %s\n", vocab_file.c_str(), vocabulary.error().ToString().c_str());
    return std::nullopt;
  }
  vocab::DescriptorSampler sampler({.max_per_image = 2000, .max_total = std::max<size_t>(400000, words * 10), .seed = 1},
                                   128);
  for (const auto& f : features) sampler.AddImage(f.descriptors);
  vocab::TrainOptions train;
  train.num_words = words;
  train.max_iterations = 10;
  const auto t0 = Clock::now();
  vocabulary = vocab::Train(sampler.descriptors(), 128, sift::DescriptorKind::kRootSift, sift_options.Describe(), train);
  if (!vocabulary) {
    std::printf("training failed: %s\n", vocabulary.error().ToString().c_str());
    return std::nullopt;
  }
  if (hamming) {  // as `oxbow vocab train` does by default: the same sample, seed 1
    vocab::QuantizerOptions quantizer;
    quantizer.num_threads = 0;
    vocabulary = vocabulary->WithHamming(sampler.descriptors(), 1, quantizer);
    if (!vocabulary) {
      std::printf("Hamming embedding failed: %s\n", vocabulary.error().ToString().c_str());
      return std::nullopt;
    }
  }
  std::printf("vocabulary: %zu words%s from %zu descriptors in %.0f s\n", vocabulary->size(),
              hamming ? " with Hamming-embedding parameters" : "", sampler.size(), Ms(t0, Clock::now()) / 1000);
  if (!vocab_file.empty() && !vocabulary->Write(vocab_file.string())) std::printf("cannot write %s\n", vocab_file.c_str());
  return std::move(*vocabulary);
}

int RunParis(const std::map<std::string, std::string>& flags) {
  namespace fs = std::filesystem;
  const fs::path data = flags.count("--data") ? fs::path(flags.at("--data")) : fs::path(OXBOW_SOURCE_DIR "/../shared/data/paris6k");
  const auto words = static_cast<size_t>(Flag(flags, "--words", 20000));
  const int max_side = static_cast<int>(Flag(flags, "--max-side", 1024));
  const int repeat = static_cast<int>(Flag(flags, "--repeat", 3));
  const int threads = static_cast<int>(Flag(flags, "--threads", 1));
  if (!fs::is_directory(data / "images")) {
    std::printf("no Paris data at %s\n", data.c_str());
    return 1;
  }
  std::vector<std::string> names;
  for (const auto& e : fs::directory_iterator(data / "images")) names.push_back(e.path().filename().string());
  std::sort(names.begin(), names.end());

  sift::SiftOptions sift_options;
  sift_options.descriptor = sift::DescriptorKind::kRootSift;
  sift_options.num_threads = 1;
  const fs::path cache = flags.count("--cache") ? fs::path(flags.at("--cache")) : fs::path();
  std::vector<std::string> paths;
  paths.reserve(names.size());
  for (const auto& name : names) paths.push_back((data / "images" / name).string());
  const std::vector<sift::FeatureSet> features = ExtractCached(paths, sift_options, max_side, cache);
  auto vocabulary = ReadOrTrainVocabulary(flags, features, words, sift_options, max_side, cache);
  if (!vocabulary) return 1;

  const fs::path dir = fs::temp_directory_path() / ("oxbow_paris_bench_" + std::to_string(getpid()));
  fs::remove_all(dir);
  IndexOptions index_options;
  index_options.num_threads = 1;
  auto idx = *ImageIndex::Create(dir.string(), *vocabulary, sift_options.Describe(), index_options);
  auto t0 = Clock::now();
  for (size_t i = 0; i < names.size(); ++i) {
    if (!idx->Add(fs::path(names[i]).stem().string(), features[i], {})) std::printf("add failed: %s\n", names[i].c_str());
  }
  const IndexStats st = idx->Stats();
  std::printf("indexed %llu images (%llu features) in %.1f s (quantise + SQLite commit per image); %.2f bytes/feature in memory\n",
              static_cast<unsigned long long>(st.num_images), static_cast<unsigned long long>(st.num_features),
              Ms(t0, Clock::now()) / 1000, st.bytes_per_feature);

  const std::vector<ParisQuery> queries = ReadParisQueries(data, names);
  // The query features: the query image's features, with the box mapped into the (downscaled) frame.
  std::printf("\n| setting | mAP | quantise p50/p95 ms | score p50/p95 | verify p50/p95 | qe p50/p95 | total p50/p95 | CPU p50/p95 |\n");
  std::printf("|---|---|---|---|---|---|---|---|\n");
  struct Setting {
    std::string name;
    double max_df = 1.0;
    bool sqrt_tf = true;
    std::function<void(QueryOptions*)> tune;
    uint32_t stop_min_images = 0;  // applied on top of QueryOptions{} (the server's defaults)
  };
  const auto rerank = [](int r, bool qe) {
    return [=](QueryOptions* o) {
      o->rerank_depth = r;
      o->query_expansion = qe;
      o->transitive_depth = 0;
    };
  };
  // The server searches with QueryOptions{} and query expansion on.
  const auto server = [](const std::function<void(QueryOptions*)>& tune) {
    return [=](QueryOptions* o) {
      o->query_expansion = true;
      tune(o);
    };
  };
  const std::vector<Setting> settings = {
      {"tf-idf only", 1.0, true, rerank(0, false)},
      {"tf-idf, raw tf", 1.0, false, rerank(0, false)},
      {"tf-idf, stop list df > 10%", 0.1, true, rerank(0, false)},
      {"re-rank R=50", 1.0, true, rerank(50, false)},
      {"re-rank R=100", 1.0, true, rerank(100, false)},
      {"re-rank R=200", 1.0, true, rerank(200, false)},
      {"re-rank R=200 + QE", 1.0, true, rerank(200, true)},
      {"re-rank R=200 + QE, stop list df > 10%", 0.1, true, rerank(200, true)},
      {"QE, df > 5%", 0.05, true, rerank(200, true)},
      {"QE, df > 20%", 0.2, true, rerank(200, true)},
      {"QE 10 images, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_depth = 0; o->qe_images = 10; }},
      {"QE, min inliers 5, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_depth = 0; o->verify.min_inliers = 5; }},
      {"QE, min inliers 8, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_depth = 0; o->verify.min_inliers = 8; }},
      {"QE, pairs/word 16, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_depth = 0; o->max_pairs_per_word = 16; }},
      {"QE, MA 2, sigma^2 0.01, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_depth = 0; o->query_assignments = 2; o->assignment_sigma_sq = 0.01; }},
      {"QE, MA 3, sigma^2 0.05, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_depth = 0; o->query_assignments = 3; o->assignment_sigma_sq = 0.05; }},
      {"QE + transitive 200, 10 anchors, 10000 neighbours, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_anchors = 10; o->transitive_neighbours = 10000; }},
      {"QE + transitive 200, 20 anchors, 30 neighbours, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; }},
      {"QE + transitive 200, 40 anchors, 30 neighbours, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_anchors = 40; }},
      {"QE + transitive 200, 20 anchors, 20 neighbours, df > 10%", 0.1, true, [](QueryOptions* o) { o->query_expansion = true; o->transitive_neighbours = 20; }},
      {"R=100, QE + transitive 200, 20 anchors, 30 neighbours, df > 10%", 0.1, true, [](QueryOptions* o) { o->rerank_depth = 100; o->query_expansion = true; }},
      {"transitive 200, 20 anchors, 30 neighbours (no QE), df > 10%", 0.1, true, [](QueryOptions*) {}},
      {"R=100, transitive 200, 20 anchors, 30 neighbours (no QE), df > 10%", 0.1, true, [](QueryOptions* o) { o->rerank_depth = 100; }},
      {"QE, df > 10% unless in <= 10 images", 0.1, true, rerank(200, true), 10},
      {"defaults (QueryOptions{}, IndexOptions{})", IndexOptions{}.max_document_frequency, IndexOptions{}.sqrt_tf,
       [](QueryOptions*) {}, IndexOptions{}.stop_list_min_images},
      {"server defaults (QueryOptions{} + QE, IndexOptions{})", IndexOptions{}.max_document_frequency,
       IndexOptions{}.sqrt_tf, [](QueryOptions* o) { o->query_expansion = true; }, IndexOptions{}.stop_list_min_images},
      {"server defaults, no transitive", 1.0, true, server([](QueryOptions* o) { o->transitive_depth = 0; }), 10},
      {"deep: R=200, 16 probes, 4 pairs/word, 1000 attempts", 1.0, true, server([](QueryOptions* o) { DeepSearch(o); }), 10},
      {"deep + 2 attempts", 1.0, true, server([](QueryOptions* o) { DeepSearch(o); o->transitive_attempts = 2; }), 10},
      {"deep + 2 attempts + 8 probes", 1.0, true, server([](QueryOptions* o) { DeepSearch(o); o->transitive_attempts = 2; o->quantizer_probes = 8; }), 10},
      {"deep + 2 attempts + 2 pairs/word", 1.0, true, server([](QueryOptions* o) { DeepSearch(o); o->transitive_attempts = 2; o->max_pairs_per_word = 2; }), 10},
      {"server defaults, R=200", 1.0, true, server([](QueryOptions* o) { o->rerank_depth = 200; }), 10},
      {"server defaults, 1 attempt", 1.0, true, server([](QueryOptions* o) { o->transitive_attempts = 1; }), 10},
      {"server defaults, 20 neighbours", 1.0, true, server([](QueryOptions* o) { o->transitive_neighbours = 20; }), 10},
      {"server defaults, 30 anchors", 1.0, true, server([](QueryOptions* o) { o->transitive_anchors = 30; }), 10},
      {"server defaults, 16 probes", 1.0, true, server([](QueryOptions* o) { o->quantizer_probes = 16; }), 10},
      {"server defaults, depth 100", 1.0, true, server([](QueryOptions* o) { o->transitive_depth = 100; }), 10},
      {"server defaults, depth 100, 30 anchors", 1.0, true, server([](QueryOptions* o) { o->transitive_depth = 100; o->transitive_anchors = 30; }), 10},
      {"server defaults, depth 100, 40 anchors", 1.0, true, server([](QueryOptions* o) { o->transitive_depth = 100; o->transitive_anchors = 40; }), 10},
      {"server defaults, depth 100, 40 anchors, 1 attempt", 1.0, true, server([](QueryOptions* o) { o->transitive_depth = 100; o->transitive_anchors = 40; o->transitive_attempts = 1; }), 10},
  };
  const std::string filter = flags.count("--filter") ? flags.at("--filter") : std::string();
  const bool verbose = Flag(flags, "--verbose", 0) != 0;
  idx.reset();
  std::string opened_as;
  std::vector<double> loads;
  for (const Setting& s : settings) {
    if (!filter.empty() && s.name.find(filter) == std::string::npos) continue;
    const std::string key = std::to_string(s.max_df) + (s.sqrt_tf ? "s" : "r") + std::to_string(s.stop_min_images);
    if (key != opened_as) {
      IndexOptions o;
      o.num_threads = threads;
      o.max_document_frequency = s.max_df;
      o.sqrt_tf = s.sqrt_tf;
      o.stop_list_min_images = s.stop_min_images;
      idx.reset();
      idx = *ImageIndex::Open(dir.string(), o);
      opened_as = key;
    }
    std::vector<double> aps, quantize, score, verify, qe, totals, cpu;
    const double load_before = LoadAverage1();
    for (int rep = 0; rep < repeat; ++rep) {
      for (const ParisQuery& q : queries) {
        const auto it = std::find(names.begin(), names.end(), q.image + ".jpg");
        if (it == names.end()) continue;
        QueryOptions options;
        s.tune(&options);
        options.top_k = 250;
        options.region = q.box;
        const double cpu0 = ProcessCpuMs();
        const auto r = idx->Query(features[static_cast<size_t>(it - names.begin())], options);
        cpu.push_back(ProcessCpuMs() - cpu0);
        if (!r) {
          std::printf("query failed: %s\n", r.error().ToString().c_str());
          continue;
        }
        if (rep == 0) {
          std::vector<std::string> ranked;
          for (const auto& x : r->results) ranked.push_back(x.id);
          aps.push_back(AveragePrecision(ranked, q.positives, q.junk));
          if (verbose) {
            int verified = 0, verified_positive = 0, verified_junk = 0;
            for (const auto& x : r->results) {
              if (!x.verified) continue;
              ++verified;
              verified_positive += q.positives.count(x.id) ? 1 : 0;
              verified_junk += q.junk.count(x.id) ? 1 : 0;
            }
            std::printf("  %s: AP %.3f, %zu positives, %zu junk, %d verified (%d positive, %d junk); %u features, "
                        "CPU %.1f ms (quantise %.1f, verify %.1f)\n",
                        q.name.c_str(), aps.back(), q.positives.size(), q.junk.size(), verified, verified_positive,
                        verified_junk, r->query_features, cpu.back(), r->timings.quantize_ms, r->timings.verify_ms);
          }
        }
        quantize.push_back(r->timings.quantize_ms);
        score.push_back(r->timings.score_ms);
        verify.push_back(r->timings.verify_ms);
        qe.push_back(r->timings.qe_ms);
        totals.push_back(r->timings.total_ms);
      }
    }
    double map = 0;
    for (double ap : aps) map += ap;
    map /= static_cast<double>(std::max<size_t>(1, aps.size()));
    std::printf("| %s | %.3f | %.1f / %.1f | %.2f / %.2f | %.1f / %.1f | %.1f / %.1f | %.1f / %.1f | %.1f / %.1f |\n",
                s.name.c_str(), map, Percentile(quantize, .5), Percentile(quantize, .95), Percentile(score, .5),
                Percentile(score, .95), Percentile(verify, .5), Percentile(verify, .95), Percentile(qe, .5),
                Percentile(qe, .95), Percentile(totals, .5), Percentile(totals, .95), Percentile(cpu, .5),
                Percentile(cpu, .95));
    loads.push_back(std::max(load_before, LoadAverage1()));
  }
  if (!loads.empty()) {
    std::printf("(1-minute load average during the settings: %.2f .. %.2f on %u hardware threads)\n",
                *std::min_element(loads.begin(), loads.end()), *std::max_element(loads.begin(), loads.end()),
                std::thread::hardware_concurrency());
  }
  std::printf("(%zu queries x %d repetitions; %d verification thread(s); vocabulary %zu words; RootSIFT, long side <= %d px)\n",
              queries.size(), repeat, threads, vocabulary->size(), max_side);
  fs::remove_all(dir);
  return 0;
}


uint64_t FolderBytes(const std::filesystem::path& dir) {
  uint64_t bytes = 0;
  for (const auto& e : std::filesystem::recursive_directory_iterator(dir)) {
    if (e.is_regular_file()) bytes += e.file_size();
  }
  return bytes;
}

int RunStorage(const std::map<std::string, std::string>& flags) {
  namespace fs = std::filesystem;
  if (!flags.count("--images") || !flags.count("--out")) {
    std::fprintf(stderr, "usage: index_benchmark storage --images N --out DIR [...] (see the file comment)\n");
    return 2;
  }
  const auto num_images = static_cast<uint64_t>(Flag(flags, "--images", 0));
  const fs::path out = flags.at("--out");
  const int features_per_image = static_cast<int>(Flag(flags, "--features", 1000));
  const int threads = static_cast<int>(Flag(flags, "--threads", 0));
  const auto batch = static_cast<uint64_t>(Flag(flags, "--batch", 1000));
  const auto num_queries = static_cast<size_t>(Flag(flags, "--queries", 20));
  const auto words = static_cast<size_t>(Flag(flags, "--words", 100000));
  constexpr int kMaxSide = 1024;
  // --reuse 1 measures an index folder left by an earlier run (same --images and --features) instead of
  // ingesting it again: everything after ingest (disk, open, searches, writes) is measured as usual.
  const bool reuse = Flag(flags, "--reuse", 0) != 0;
  if (ImageIndex::Exists(out.string()) != reuse) {
    std::fprintf(stderr, reuse ? "%s holds no index to reuse\n" : "%s already holds an index; give a new folder or --reuse 1\n",
                 out.c_str());
    return 2;
  }

  // Real photos: the Paris subset, else OpenCV's samples.
  const fs::path paris = flags.count("--data") ? fs::path(flags.at("--data")) : fs::path(OXBOW_SOURCE_DIR "/../shared/data/paris6k");
  std::vector<std::string> photos;
  for (const fs::path& folder : {paris / "images", fs::path("/usr/share/doc/opencv-doc/examples/data")}) {
    if (auto listed = sift::ListImageFiles(folder.string()); listed && !listed->empty()) {
      photos = std::move(*listed);
      std::printf("real photos: %zu from %s\n", photos.size(), folder.c_str());
      break;
    }
  }
  if (photos.empty()) {
    std::printf("no real photos found (Paris subset or opencv-doc)\n");
    return 1;
  }
  if (const auto limit = static_cast<size_t>(Flag(flags, "--photos", 0)); limit > 0 && photos.size() > limit) {
    photos.resize(limit);
    std::printf("using the first %zu photos\n", limit);
  }
  const fs::path export_dir = flags.count("--export-features") ? fs::path(flags.at("--export-features")) : fs::path();
  sift::SiftOptions sift_options;
  sift_options.descriptor = sift::DescriptorKind::kRootSift;
  sift_options.num_threads = 1;
  const fs::path cache = flags.count("--cache") ? fs::path(flags.at("--cache")) : fs::path(out.string() + ".cache");
  const std::vector<sift::FeatureSet> real = ExtractCached(photos, sift_options, kMaxSide, cache);
  // The product's default vocabulary (`oxbow vocab train`) carries Hamming-embedding parameters, and
  // searches then use them; --hamming 0 trains one without (searches then run the tf-idf QE pass).
  const bool hamming = Flag(flags, "--hamming", 1) != 0;
  auto vocabulary = ReadOrTrainVocabulary(flags, real, words, sift_options, kMaxSide, cache, hamming);
  if (!vocabulary) return 1;

  IndexOptions options;
  options.num_threads = threads;
  // The pool: every real feature's word, keypoint and (with a Hamming-embedding vocabulary) signature,
  // quantised as Add would; with --export-features each synthetic feature keeps its real descriptor.
  vocab::QuantizerOptions quantizer = options.quantizer;  // the words Add would assign
  quantizer.num_threads = threads;
  const eval::SyntheticCollection collection(
      real, *vocabulary, quantizer,
      {.features_per_image = features_per_image, .image_width = 1024, .image_height = 768, .descriptors = !export_dir.empty()});
  std::printf("pool: %zu real features, vocabulary %zu words%s\n", collection.pool_size(), vocabulary->size(),
              collection.has_signatures() ? ", Hamming-embedding signatures" : ", no Hamming embedding");

  // Ingest.
  // Query-time stop list (the defaults unless given): compare settings on one folder with --reuse 1.
  options.max_document_frequency = Flag(flags, "--max-df", options.max_document_frequency);
  options.stop_list_min_images =
      static_cast<uint32_t>(Flag(flags, "--stop-list-min-images", options.stop_list_min_images));
  if (!reuse) {
    auto idx = ImageIndex::Create(out.string(), *vocabulary, sift_options.Describe(), options);
    if (!idx) {
      std::printf("create failed: %s\n", idx.error().ToString().c_str());
      return 1;
    }
    const auto t0 = Clock::now();
    uint64_t next_report = 0;
    eval::IngestOptions ingest{.count = num_images, .batch = batch, .num_threads = threads, .export_dir = export_dir,
                               .extractor = sift_options};
    ingest.progress = [&](uint64_t done) {
      if (done < next_report) return;
      const double s = Ms(t0, Clock::now()) / 1000;
      std::fprintf(stderr, "ingest: %llu / %llu images, %.0f s, %.0f images/s\n", static_cast<unsigned long long>(done),
                   static_cast<unsigned long long>(num_images), s, static_cast<double>(done) / s);
      next_report += std::max<uint64_t>(batch, num_images / 20);
    };
    const Result<eval::IngestReport> ingested = eval::IngestSynthetic(**idx, collection, ingest);
    if (!ingested) {
      std::printf("ingest failed: %s\n", ingested.error().ToString().c_str());
      return 1;
    }
    std::printf("ingest: %llu images x %d features, %.1f s inside AddBatch = %.0f images/s (AddBatch of %llu, words "
                "assigned, %d threads; %.1f s with making the synthetic images)\n",
                static_cast<unsigned long long>(num_images), features_per_image, ingested->add_seconds,
                static_cast<double>(num_images) / ingested->add_seconds, static_cast<unsigned long long>(batch),
                ResolveThreadCount(threads), ingested->total_seconds);
  }
  const double total_features = static_cast<double>(num_images) * features_per_image;
  std::printf("disk: %.2f bytes per feature (%.2f GB in %s)\n", static_cast<double>(FolderBytes(out)) / total_features,
              static_cast<double>(FolderBytes(out)) / 1e9, out.c_str());

  // Open, as a server would.
  malloc_trim(0);
  const uint64_t rss_before = RssBytes();
  auto t0 = Clock::now();
  auto opened = ImageIndex::Open(out.string(), options);
  if (!opened) {
    std::printf("open failed: %s\n", opened.error().ToString().c_str());
    return 1;
  }
  std::unique_ptr<ImageIndex> idx = std::move(*opened);
  const double open_s = Ms(t0, Clock::now()) / 1000;
  malloc_trim(0);
  const uint64_t rss_after = RssBytes();
  const IndexStats stats = idx->Stats();
  std::printf("open: %.1f s; resident %.2f bytes per feature (RSS growth %.2f GB; accounted in memory %.2f bytes/feature)\n",
              open_s, static_cast<double>(rss_after - rss_before) / total_features,
              static_cast<double>(rss_after - rss_before) / 1e9, stats.bytes_per_feature);

  // Searches with real photos' features.
  std::vector<const sift::FeatureSet*> queries;
  for (size_t i = 0; i < real.size() && queries.size() < num_queries; i += std::max<size_t>(1, real.size() / num_queries)) {
    if (real[i].size() > 0) queries.push_back(&real[i]);
  }
  QueryOptions tfidf;
  tfidf.rerank_depth = 0;
  tfidf.query_expansion = false;
  tfidf.transitive_depth = 0;
  QueryOptions no_transitive;
  no_transitive.transitive_depth = 0;
  for (const auto& [name, query_options] : {std::pair<const char*, QueryOptions>{"tf-idf only", tfidf},
                                            std::pair<const char*, QueryOptions>{"default without transitive", no_transitive},
                                            std::pair<const char*, QueryOptions>{"full default search", QueryOptions{}}}) {
    std::vector<double> ms, quantize, score, verify, qe;
    for (const auto* q : queries) {
      const auto r = idx->Query(*q, query_options);
      if (!r) continue;
      ms.push_back(r->timings.total_ms);
      quantize.push_back(r->timings.quantize_ms);
      score.push_back(r->timings.score_ms);
      verify.push_back(r->timings.verify_ms);
      qe.push_back(r->timings.qe_ms);
    }
    if (ms.empty()) {
      std::printf("%s: no searches ran (--queries 0, or every query failed)\n", name);
      continue;
    }
    std::printf("%s: p50 %.1f ms, p95 %.1f ms, p99 %.1f ms (%zu real photos, quantisation included; stage p50s: "
                "quantize %.1f, score %.1f, verify %.1f (transitive included), qe %.1f)\n",
                name, Percentile(ms, .5), Percentile(ms, .95), Percentile(ms, .99), ms.size(), Percentile(quantize, .5),
                Percentile(score, .5), Percentile(verify, .5), Percentile(qe, .5));
  }
  // The posting budget (QueryOptions::max_scored_postings), full default search otherwise: each value
  // on every query in turn, so that the machine's drift falls on all of them alike.
  // With --hamming-shortlist S1,S2,... every (budget, shortlist) pair likewise.
  const auto int_list = [&](const char* flag, const char* fallback) {
    std::vector<int> values;
    std::stringstream list(flags.count(flag) ? flags.at(flag) : std::string(fallback));
    for (std::string v; std::getline(list, v, ',');) values.push_back(std::stoi(v));
    return values;
  };
  std::vector<std::pair<int, int>> settings;  // (max_scored_postings, hamming_shortlist)
  const std::vector<int> shortlists =
      int_list("--hamming-shortlist", std::to_string(QueryOptions{}.hamming_shortlist).c_str());
  for (const int budget : int_list("--max-scored-postings", "0,4000000")) {
    for (const int shortlist : shortlists) settings.emplace_back(budget, shortlist);
  }
  const auto options_of = [](const std::pair<int, int>& setting) {
    QueryOptions o;
    o.max_scored_postings = setting.first;
    o.hamming_shortlist = setting.second;
    return o;
  };
  {
    std::vector<std::vector<double>> ms(settings.size()), score(settings.size()), qe(settings.size());
    for (const auto* q : queries) {
      for (size_t b = 0; b < settings.size(); ++b) {
        const auto r = idx->Query(*q, options_of(settings[b]));
        if (!r) continue;
        ms[b].push_back(r->timings.total_ms);
        score[b].push_back(r->timings.score_ms);
        qe[b].push_back(r->timings.qe_ms);
      }
    }
    for (size_t b = 0; b < settings.size(); ++b) {
      if (ms[b].empty()) continue;  // no searches ran: said above
      std::printf("full default search, max_scored_postings %d, hamming_shortlist %d: p50 %.1f ms, p95 %.1f ms, "
                  "p99 %.1f ms (score p50 %.1f, qe p50 %.1f; each setting on every query in turn)\n",
                  settings[b].first, settings[b].second, Percentile(ms[b], .5), Percentile(ms[b], .95),
                  Percentile(ms[b], .99), Percentile(score[b], .5), Percentile(qe[b], .5));
    }
  }
  // --paris-map 1: the Paris subset's photos added to the collection (their real features), its 12
  // cropped queries under the restricted protocol among the synthetic images, mAP per budget; then
  // the photos are removed again.
  if (Flag(flags, "--paris-map", 0) != 0) {
    if (!fs::is_regular_file(paris / "subset_queries_present.txt") || photos.size() != real.size() ||
        !fs::equivalent(fs::path(photos.front()).parent_path(), paris / "images")) {
      std::printf("--paris-map needs the Paris subset (%s) as the real photos\n", paris.c_str());
      return 1;
    }
    std::vector<std::string> names;
    std::vector<BatchImage> items;
    for (size_t i = 0; i < photos.size(); ++i) {
      names.push_back(fs::path(photos[i]).filename().string());
      items.push_back({fs::path(photos[i]).stem().string(), &real[i], {}, {}, {}});
    }
    std::sort(names.begin(), names.end());
    for (const auto& r : idx->AddBatch(items)) {
      if (!r) {
        std::printf("add failed: %s\n", r.error().ToString().c_str());
        return 1;
      }
    }
    const std::vector<ParisQuery> paris_queries = ReadParisQueries(paris, names);
    for (const auto& setting : settings) {
      double sum = 0;
      size_t n = 0;
      std::vector<double> ms;
      for (const ParisQuery& q : paris_queries) {
        const auto it = std::find_if(items.begin(), items.end(), [&](const BatchImage& b) { return b.id == q.image; });
        if (it == items.end()) continue;
        QueryOptions o = options_of(setting);
        o.top_k = 1000;
        o.region = q.box;
        const auto r = idx->Query(*it->features, o);
        if (!r) continue;
        std::vector<std::string> ranked;
        for (const auto& x : r->results) ranked.push_back(x.id);
        sum += AveragePrecision(ranked, q.positives, q.junk);
        ++n;
        ms.push_back(r->timings.total_ms);
      }
      std::printf("Paris subset among the %llu synthetic images, max_scored_postings %d, hamming_shortlist %d: mAP "
                  "%.4f (%zu queries, restricted protocol, top 1000; search p50 %.1f ms)\n",
                  static_cast<unsigned long long>(num_images), setting.first, setting.second,
                  sum / static_cast<double>(std::max<size_t>(1, n)), n, Percentile(ms, .5));
    }
    for (const BatchImage& item : items) {
      if (!idx->Remove(item.id)) std::printf("remove failed: %s\n", item.id.c_str());
    }
  }
  // Memory-mapped geometry (checkpoint files) becomes resident as searches read it.
  std::printf("resident after the searches: %.2f bytes per feature\n",
              static_cast<double>(RssBytes() - rss_before) / total_features);

  // Adds of single images while another thread searches (with --queries 0 the writes run alone), then
  // their removal.
  constexpr int kWrites = 50;
  const auto writes = eval::AddAndRemoveWhileSearching(*idx, collection, num_images, kWrites, queries);
  if (!writes) {
    std::printf("add or remove failed: %s\n", writes.error().ToString().c_str());
    return 1;
  }
  std::printf("add while searching: p50 %.1f ms, p99 %.1f ms; remove: p50 %.1f ms, p99 %.1f ms (%d each, %llu searches alongside)\n",
              Percentile(writes->add_ms, .5), Percentile(writes->add_ms, .99), Percentile(writes->remove_ms, .5),
              Percentile(writes->remove_ms, .99), kWrites, static_cast<unsigned long long>(writes->searches));
  std::printf("serve it: oxbow serve --index %s\n", out.c_str());
  return 0;
}


// The real `oxbow index build --features` against the quantiser alone on the same descriptors.
int RunFeatures(const std::map<std::string, std::string>& flags) {
  namespace fs = std::filesystem;
  if (!flags.count("--features") || !flags.count("--vocab")) {
    std::fprintf(stderr, "usage: index_benchmark features --features DIR --vocab V.oxvoc [...] (see the file comment)\n");
    return 2;
  }
  const std::string folder = flags.at("--features"), vocab_path = flags.at("--vocab");
  const std::string oxbow = flags.count("--oxbow") ? flags.at("--oxbow")
                                                   : (fs::canonical("/proc/self/exe").parent_path().parent_path() /
                                                      "server" / "oxbow").string();
  const int repeat = static_cast<int>(Flag(flags, "--repeat", 3));
  std::vector<int> thread_counts;
  {
    std::stringstream list(flags.count("--threads") ? flags.at("--threads") : std::string("1,2"));
    for (std::string t; std::getline(list, t, ',');) thread_counts.push_back(std::stoi(t));
  }
  auto vocabulary = vocab::Vocabulary::Read(vocab_path);
  if (!vocabulary) {
    std::printf("vocabulary: %s\n", vocabulary.error().ToString().c_str());
    return 1;
  }
  std::vector<sift::FeatureSet> sets;
  for (const auto& e : fs::recursive_directory_iterator(folder)) {
    if (e.path().extension() != ".oxfeat") continue;
    auto file = sift::ReadFeatureFile(e.path().string());
    if (!file) {
      std::printf("%s: %s\n", e.path().c_str(), file.error().ToString().c_str());
      return 1;
    }
    sets.push_back(std::move(file->features));
  }
  uint64_t descriptors = 0;
  for (const auto& f : sets) descriptors += f.size();
  std::printf("%zu feature files, %llu descriptors; vocabulary %zu words; quantiser as the index adds: %d probes\n",
              sets.size(), static_cast<unsigned long long>(descriptors), vocabulary->size(),
              IndexOptions{}.quantizer.num_probes);
  std::printf("| threads | index build --features, descriptors/s per thread | quantiser alone | build / quantiser |\n|---|---|---|---|\n");
  const fs::path out = fs::temp_directory_path() / ("oxbow-features-bench-" + std::to_string(getpid()));
  for (const int threads : thread_counts) {
    std::vector<double> command_s, quantiser_s;
    for (int r = 0; r < repeat; ++r) {
      fs::remove_all(out);
      std::string command = oxbow;
      command += " index build --features '" + folder;
      command += "' --vocab '" + vocab_path;
      command += "' --out '" + out.string();
      command += "' --threads " + std::to_string(threads);
      command += " > /dev/null 2>&1";
      auto t0 = Clock::now();
      if (std::system(command.c_str()) != 0) {
        std::printf("failed: %s\n", command.c_str());
        return 1;
      }
      command_s.push_back(Ms(t0, Clock::now()) / 1000);
      t0 = Clock::now();
      ParallelFor(sets.size(), threads, 1, [&](size_t b, size_t e, int) {
        std::vector<uint32_t> words;
        for (size_t i = b; i < e; ++i) {
          words.resize(sets[i].size());
          vocabulary->Quantize(sets[i].descriptors, words, IndexOptions{}.quantizer);
        }
      });
      quantiser_s.push_back(Ms(t0, Clock::now()) / 1000);
    }
    const double c = Percentile(command_s, .5), q = Percentile(quantiser_s, .5);
    const double per_thread = static_cast<double>(descriptors) / threads;
    std::printf("| %d | %.0f (%.2f s) | %.0f (%.2f s) | %.3f |\n", threads, per_thread / c, c, per_thread / q, q, c / q);
  }
  fs::remove_all(out);
  std::printf("(medians of %d alternating runs; 1-minute load average %.2f)\n", repeat, LoadAverage1());
  return 0;
}

}  // namespace
}  // namespace oxbow::index

int main(int argc, char** argv) {
  const std::string mode = argc >= 2 ? argv[1] : "";
  if (mode != "synthetic" && mode != "paris" && mode != "storage" && mode != "features") {
    std::fprintf(stderr, "usage: index_benchmark synthetic|paris|storage|features [--flag value ...] (see the file comment)\n");
    return 2;
  }
  const auto flags = oxbow::index::ParseFlags(argc, argv, 2);
  if (mode == "storage") return oxbow::index::RunStorage(flags);
  if (mode == "features") return oxbow::index::RunFeatures(flags);
  return mode == "synthetic" ? oxbow::index::RunSynthetic(flags) : oxbow::index::RunParis(flags);
}
