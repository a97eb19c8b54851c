// Vocabulary: immutable centroids + two-level quantiser, and its file format.
//
// File (binary_io.h container, magic "OXBWVOCB", version 1 or 2), payload in host byte order (the
// container records it):
//   u32 dimension | u64 num_words | u8 descriptor kind (0 SIFT, 1 RootSIFT) | string extractor settings
//   (u32 length + bytes) | u64 fingerprint | u64 num_lists | u64 offsets[num_lists + 1]
//   | f32 coarse[num_lists x dimension] | f32 centroids[num_words x dimension]
// Version 2 (written only by a vocabulary with Hamming-embedding parameters; one without is still
// written as version 1, readable by older builds) appends
//   f32 projection[64 x dimension] | f32 medians[num_words x 64]   (medians in stored word order)
// The words are stored in coarse-list order (list l holds rows offsets[l]..offsets[l+1]), and a word's
// id is its row, so the quantiser needs no id table and loading is one read plus one copy. The coarse
// level is stored, not rebuilt, because rebuilding it for 1M words costs minutes.
#include "vocab/vocabulary.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <numeric>

#include "sift/base/binary_io.h"
#include "vocab/kernels.h"
#include "vocab/search.h"

namespace oxbow::vocab {

namespace {
constexpr char kMagic[] = "OXBWVOCB";
constexpr uint32_t kVersion = 1;
constexpr uint32_t kHammingVersion = 2;
constexpr int kMaxDimension = 4096;

// 64-bit hash of bytes (8-byte words folded through the SplitMix64 finaliser; tail bytewise).
uint64_t HashBytes(const void* data, size_t size, uint64_t h) {
  auto mix = [](uint64_t z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  };
  const auto* p = static_cast<const uint8_t*>(data);
  size_t i = 0;
  for (; i + 8 <= size; i += 8) {
    uint64_t v;
    std::memcpy(&v, p + i, 8);
    h = mix(h ^ v) + 0x9E3779B97F4A7C15ull;
  }
  for (; i < size; ++i) h = mix(h ^ p[i]) + 0x9E3779B97F4A7C15ull;
  return mix(h ^ size);
}

bool AllFinite(std::span<const float> values) {
  return std::all_of(values.begin(), values.end(), [](float v) { return std::isfinite(v); });
}

// Centroids average unit-norm descriptors, so their values lie in [-1, 1]. Far larger ones (a damaged or
// crafted file) overflow the quantiser's float scores (|w|^2 - 2<q, w>) to inf - inf = NaN, and then no
// coarse list or word is nearest; this bound keeps every score finite.
constexpr float kMaxCentroidValue = 1e6f;
bool AllWithinBound(std::span<const float> values) {
  return std::all_of(values.begin(), values.end(), [](float v) { return std::fabs(v) <= kMaxCentroidValue; });
}

// kHammingBits x dimension orthonormal rows: Gram-Schmidt over Gaussian rows (SplitMix64 + Box-Muller,
// so the matrix depends on the seed only, not on the standard library).
std::vector<float> RandomOrthogonalRows(int dimension, uint64_t seed) {
  uint64_t state = seed;
  auto uniform = [&state] {  // in (0, 1]
    uint64_t z = (state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return (static_cast<double>((z ^ (z >> 31)) >> 11) + 1.0) / 9007199254740992.0;
  };
  const auto d = static_cast<size_t>(dimension);
  std::vector<double> rows(kHammingBits * d);
  for (size_t r = 0; r < kHammingBits; ++r) {
    double* row = rows.data() + r * d;
    for (size_t c = 0; c < d; ++c) {
      row[c] = std::sqrt(-2.0 * std::log(uniform())) * std::cos(2.0 * 3.14159265358979323846 * uniform());
    }
    for (size_t p = 0; p < r; ++p) {  // twice: numerically orthogonal
      for (int pass = 0; pass < 2; ++pass) {
        const double* prev = rows.data() + p * d;
        const double dot = std::inner_product(row, row + d, prev, 0.0);
        for (size_t c = 0; c < d; ++c) row[c] -= dot * prev[c];
      }
    }
    const double norm = std::sqrt(std::inner_product(row, row + d, row, 0.0));
    for (size_t c = 0; c < d; ++c) row[c] /= norm;
  }
  return {rows.begin(), rows.end()};
}

// The 64 x dimension projection (row-major) transposed to dimension x 64, which Project reads.
std::vector<float> Transposed(const std::vector<float>& projection, int dimension) {
  const auto d = static_cast<size_t>(dimension);
  std::vector<float> out(projection.size());
  for (size_t r = 0; r < kHammingBits; ++r) {
    for (size_t c = 0; c < d; ++c) out[c * kHammingBits + r] = projection[r * d + c];
  }
  return out;
}

// out = projection * descriptor, from the transposed projection: the 64 sums run side by side (the
// compiler vectorises the inner loop); 64 dot products, each a serial float reduction, were about 19x
// slower (3000 descriptors: 12 ms against 0.6 ms, -O3 -march=native, one core).
void Project(const std::vector<float>& transposed, const float* descriptor, int dimension, float* out) {
  std::array<float, kHammingBits> sum{};
  for (size_t c = 0; c < static_cast<size_t>(dimension); ++c) {
    const float x = descriptor[c];
    const float* column = transposed.data() + c * kHammingBits;
    for (size_t r = 0; r < kHammingBits; ++r) sum[r] += column[r] * x;
  }
  std::copy(sum.begin(), sum.end(), out);
}
}  // namespace

struct Vocabulary::State {
  int dimension = 0;
  sift::DescriptorKind kind = sift::DescriptorKind::kSift;
  std::string settings;
  uint64_t fingerprint = 0;
  std::vector<float> centroids;  // k x dimension, in coarse-list order
  std::vector<float> norms;      // k squared norms
  internal::TwoLevelIndex index;
  std::vector<float> projection;  // Hamming embedding: kHammingBits x dimension, empty without it
  std::vector<float> medians;     // k x kHammingBits

  // Finishes a state whose dimension, kind, settings, centroids, index.coarse and index.offsets are set.
  void Finish() {
    const size_t k = centroids.size() / dimension;
    norms.resize(k);
    internal::RowSquaredNorms(centroids.data(), k, dimension, norms.data());
    index.dim = dimension;
    index.coarse_norms.resize(index.coarse.size() / dimension);
    internal::RowSquaredNorms(index.coarse.data(), index.coarse_norms.size(), dimension, index.coarse_norms.data());
    index.words = {centroids.data(), norms.data(), k, dimension};
    index.BuildPanels();
    fingerprint = ComputeFingerprint();
  }
  uint64_t ComputeFingerprint() const {
    uint64_t h = HashBytes(&dimension, sizeof(dimension), 0x0B0B0B0Bull);
    const auto kind_byte = static_cast<uint8_t>(kind);
    h = HashBytes(&kind_byte, 1, h);
    h = HashBytes(settings.data(), settings.size(), h);
    h = HashBytes(centroids.data(), centroids.size() * sizeof(float), h);
    if (projection.empty()) return h;  // the fingerprints of vocabularies without embedding are unchanged
    h = HashBytes(projection.data(), projection.size() * sizeof(float), h);
    return HashBytes(medians.data(), medians.size() * sizeof(float), h);
  }
};

std::optional<std::string> QuantizerOptions::Check() const {
  if (num_threads < 0) return "QuantizerOptions.num_threads must be >= 0 (0 = all hardware threads)";
  if (num_probes < 1) return "QuantizerOptions.num_probes must be >= 1";
  return std::nullopt;
}

std::optional<std::string> QuantizerBuildOptions::Check() const {
  if (iterations < 1 || iterations > 100) return "QuantizerBuildOptions.iterations must be in [1, 100]";
  if (num_threads < 0) return "QuantizerBuildOptions.num_threads must be >= 0";
  return std::nullopt;
}

Result<Vocabulary> Vocabulary::FromCentroids(std::vector<float> centroids, int dimension, sift::DescriptorKind kind,
                                             std::string extractor_settings, const QuantizerBuildOptions& build) {
  if (auto problem = build.Check()) return Fail(ErrorCode::kInvalidArgument, *problem);
  if (dimension < 1 || dimension > kMaxDimension)
    return Fail(ErrorCode::kInvalidArgument, "vocabulary dimension must be in [1, 4096], got " + std::to_string(dimension));
  if (centroids.empty() || centroids.size() % dimension != 0)
    return Fail(ErrorCode::kInvalidArgument, "centroid matrix must be non-empty with a multiple of " +
                                                 std::to_string(dimension) + " values, got " + std::to_string(centroids.size()));
  const size_t k = centroids.size() / dimension;
  if (k > std::numeric_limits<uint32_t>::max() - 1) return Fail(ErrorCode::kInvalidArgument, "too many words (max 2^32 - 2)");
  if (!AllFinite(centroids)) return Fail(ErrorCode::kInvalidArgument, "centroids contain NaN or infinity");
  if (build.num_lists > k)
    return Fail(ErrorCode::kInvalidArgument, "QuantizerBuildOptions.num_lists (" + std::to_string(build.num_lists) +
                                                 ") exceeds the number of words (" + std::to_string(k) + ")");
  const size_t lists = build.num_lists > 0 ? build.num_lists : internal::DefaultNumLists(k);
  internal::CoarseClustering coarse =
      internal::ClusterCoarse(centroids.data(), k, dimension, lists, build.iterations, build.seed, build.num_threads);
  // Renumber the words in list order (stable within a list).
  std::vector<uint32_t> order(k);
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) {
    return coarse.list_of_point[a] < coarse.list_of_point[b];
  });
  auto state = std::make_shared<State>();
  state->dimension = dimension;
  state->kind = kind;
  state->settings = std::move(extractor_settings);
  state->centroids.resize(centroids.size());
  for (size_t r = 0; r < k; ++r)
    std::copy_n(centroids.data() + size_t{order[r]} * dimension, dimension, state->centroids.data() + r * dimension);
  state->index.coarse = std::move(coarse.centroids);
  state->index.offsets.assign(lists + 1, 0);
  for (uint32_t l : coarse.list_of_point) ++state->index.offsets[l + 1];
  std::partial_sum(state->index.offsets.begin(), state->index.offsets.end(), state->index.offsets.begin());
  state->Finish();
  return Vocabulary(std::move(state));
}

Status Vocabulary::Write(const std::string& path) const {
  const State& s = *state_;
  io::ByteWriter w;
  w.Put<uint32_t>(static_cast<uint32_t>(s.dimension));
  w.Put<uint64_t>(size());
  w.Put<uint8_t>(static_cast<uint8_t>(s.kind));
  w.PutString(s.settings);
  w.Put<uint64_t>(s.fingerprint);
  w.Put<uint64_t>(s.index.num_lists());
  w.PutArray(std::span<const uint64_t>(s.index.offsets));
  w.PutArray(std::span<const float>(s.index.coarse));
  w.PutArray(std::span<const float>(s.centroids));
  if (!has_hamming()) return io::WriteContainerFile(path, std::string_view(kMagic, 8), kVersion, 0, w.bytes());
  w.PutArray(std::span<const float>(s.projection));
  w.PutArray(std::span<const float>(s.medians));
  return io::WriteContainerFile(path, std::string_view(kMagic, 8), kHammingVersion, 0, w.bytes());
}

Result<Vocabulary> Vocabulary::Read(const std::string& path) {
  auto container = io::ReadContainerFile(path, std::string_view(kMagic, 8), kVersion, kHammingVersion);
  if (!container) return std::unexpected(container.error());
  io::ByteReader r(container->payload, "vocabulary file '" + path + "'");
  auto corrupt = [&](const std::string& what) {
    return Fail(ErrorCode::kCorruptData, "vocabulary file '" + path + "': " + what);
  };
  auto state = std::make_shared<State>();
  auto dim = r.Get<uint32_t>();
  if (!dim) return std::unexpected(dim.error());
  if (*dim < 1 || *dim > kMaxDimension) return corrupt("dimension " + std::to_string(*dim) + " outside [1, 4096]");
  state->dimension = static_cast<int>(*dim);
  auto k = r.Get<uint64_t>();
  if (!k) return std::unexpected(k.error());
  auto kind = r.Get<uint8_t>();
  if (!kind) return std::unexpected(kind.error());
  if (*kind > 1) return corrupt("unknown descriptor kind " + std::to_string(*kind));
  state->kind = static_cast<sift::DescriptorKind>(*kind);
  auto settings = r.GetString();
  if (!settings) return std::unexpected(settings.error());
  state->settings = std::move(*settings);
  auto fingerprint = r.Get<uint64_t>();
  if (!fingerprint) return std::unexpected(fingerprint.error());
  auto lists = r.Get<uint64_t>();
  if (!lists) return std::unexpected(lists.error());
  if (*k < 1 || *lists < 1 || *lists > *k) return corrupt("bad word or list count");
  // Sizes must match the remaining bytes exactly before anything large is allocated.
  const uint64_t d = *dim;
  const bool hamming = container->version == kHammingVersion;
  const uint64_t expected =
      (*lists + 1) * 8 + (*lists * d + *k * d) * 4 + (hamming ? (kHammingBits * d + *k * kHammingBits) * 4 : 0);
  if (*k > (uint64_t{1} << 32) - 2 || *lists > *k || r.remaining() != expected)
    return corrupt("payload size does not match its " + std::to_string(*k) + " words and " + std::to_string(*lists) +
                   " lists");
  state->index.offsets.resize(*lists + 1);
  state->index.coarse.resize(*lists * d);
  state->centroids.resize(*k * d);
  if (auto s = r.GetArray(std::span<uint64_t>(state->index.offsets)); !s) return std::unexpected(s.error());
  if (auto s = r.GetArray(std::span<float>(state->index.coarse)); !s) return std::unexpected(s.error());
  if (auto s = r.GetArray(std::span<float>(state->centroids)); !s) return std::unexpected(s.error());
  if (hamming) {
    state->projection.resize(kHammingBits * d);
    state->medians.resize(*k * kHammingBits);
    if (auto s = r.GetArray(std::span<float>(state->projection)); !s) return std::unexpected(s.error());
    if (auto s = r.GetArray(std::span<float>(state->medians)); !s) return std::unexpected(s.error());
    if (!AllFinite(state->projection) || !AllFinite(state->medians)) return corrupt("NaN or infinite embedding values");
  }
  const auto& off = state->index.offsets;
  if (off.front() != 0 || off.back() != *k || !std::is_sorted(off.begin(), off.end()))
    return corrupt("list offsets are not a partition of the words");
  if (!AllFinite(state->centroids) || !AllFinite(state->index.coarse)) return corrupt("NaN or infinite centroid values");
  if (!AllWithinBound(state->centroids) || !AllWithinBound(state->index.coarse)) {
    return corrupt("centroid values beyond +-1e6 (centroids of unit-norm descriptors lie within +-1)");
  }
  state->Finish();
  if (state->fingerprint != *fingerprint) return corrupt("fingerprint does not match the centroids");
  // Vocabularies read from files of the same content share one State, so that the indexes of several
  // collections over one vocabulary (api/collections.h) hold it once. A State is immutable once built;
  // the registry holds weak references only.
  static std::mutex registry_mutex;
  static std::map<uint64_t, std::weak_ptr<const State>> registry;
  std::lock_guard<std::mutex> lock(registry_mutex);
  std::erase_if(registry, [](const auto& entry) { return entry.second.expired(); });
  if (auto it = registry.find(state->fingerprint); it != registry.end()) {
    if (auto held = it->second.lock(); held && held->dimension == state->dimension && held->kind == state->kind &&
                                       held->settings == state->settings && held->centroids == state->centroids &&
                                       held->index.offsets == state->index.offsets &&
                                       held->projection == state->projection && held->medians == state->medians) {
      return Vocabulary(std::move(held));
    }
  }
  std::shared_ptr<const State> shared = std::move(state);
  registry[shared->fingerprint] = shared;
  return Vocabulary(std::move(shared));
}

size_t Vocabulary::size() const { return state_->centroids.size() / state_->dimension; }
int Vocabulary::dimension() const { return state_->dimension; }
sift::DescriptorKind Vocabulary::descriptor_kind() const { return state_->kind; }
const std::string& Vocabulary::extractor_settings() const { return state_->settings; }
uint64_t Vocabulary::fingerprint() const { return state_->fingerprint; }
std::span<const float> Vocabulary::centroids() const { return state_->centroids; }
size_t Vocabulary::num_lists() const { return state_->index.num_lists(); }
bool Vocabulary::has_hamming() const { return !state_->projection.empty(); }

void Vocabulary::Signatures(std::span<const float> descriptors, std::span<const uint32_t> words,
                            std::span<uint64_t> signatures) const {
  const State& s = *state_;
  OXBOW_CHECK(has_hamming(), "the vocabulary has no Hamming-embedding parameters");
  OXBOW_CHECK(descriptors.size() == words.size() * s.dimension && signatures.size() == words.size(),
              "one word and one signature per descriptor");
  std::array<float, kHammingBits> projected{};
  const std::vector<float> transposed = Transposed(s.projection, s.dimension);
  for (size_t i = 0; i < words.size(); ++i) {
    OXBOW_CHECK(words[i] < size(), "word outside the vocabulary");
    Project(transposed, descriptors.data() + i * s.dimension, s.dimension, projected.data());
    const float* median = s.medians.data() + size_t{words[i]} * kHammingBits;
    uint64_t bits = 0;
    for (int b = 0; b < kHammingBits; ++b) bits |= uint64_t{projected[b] > median[b]} << b;
    signatures[i] = bits;
  }
}

Result<Vocabulary> Vocabulary::WithHamming(std::span<const float> training, uint64_t seed,
                                           const QuantizerOptions& quantizer) const {
  const State& s = *state_;
  if (s.dimension < kHammingBits) {
    return Fail(ErrorCode::kInvalidArgument, "Hamming embedding needs descriptors of at least 64 dimensions");
  }
  if (training.empty() || training.size() % s.dimension != 0) {
    return Fail(ErrorCode::kInvalidArgument, "the Hamming-embedding sample must be a non-empty n x " +
                                                 std::to_string(s.dimension) + " matrix");
  }
  if (!AllFinite(training)) return Fail(ErrorCode::kInvalidArgument, "the Hamming-embedding sample is not finite");
  if (auto problem = quantizer.Check()) return Fail(ErrorCode::kInvalidArgument, *problem);
  const size_t n = training.size() / s.dimension;
  const size_t k = size();
  auto state = std::make_shared<State>(s);
  state->projection = RandomOrthogonalRows(s.dimension, seed);
  std::vector<uint32_t> words(n);
  Quantize(training, words, quantizer);
  // Rows of the sample grouped by word (counting sort), projected once.
  std::vector<size_t> begin(k + 1, 0);
  for (const uint32_t w : words) ++begin[w + 1];
  std::partial_sum(begin.begin(), begin.end(), begin.begin());
  std::vector<size_t> next(begin.begin(), begin.end() - 1);
  std::vector<float> projected(n * kHammingBits);
  const std::vector<float> transposed = Transposed(state->projection, s.dimension);
  for (size_t i = 0; i < n; ++i) {
    Project(transposed, training.data() + i * s.dimension, s.dimension,
            projected.data() + next[words[i]]++ * kHammingBits);
  }
  state->medians.resize(k * kHammingBits);
  std::vector<float> column;
  for (size_t w = 0; w < k; ++w) {
    float* median = state->medians.data() + w * kHammingBits;
    const size_t count = begin[w + 1] - begin[w];
    if (count == 0) {
      Project(transposed, s.centroids.data() + w * s.dimension, s.dimension, median);
      continue;
    }
    for (size_t b = 0; b < kHammingBits; ++b) {
      column.resize(count);
      for (size_t r = 0; r < count; ++r) column[r] = projected[(begin[w] + r) * kHammingBits + b];
      const auto mid = column.begin() + static_cast<std::ptrdiff_t>(count / 2);
      std::nth_element(column.begin(), mid, column.end());
      median[b] = *mid;
    }
  }
  state->Finish();
  return Vocabulary(std::move(state));
}

std::vector<float> Vocabulary::HammingProjection(uint64_t seed) const {
  OXBOW_CHECK(state_->dimension >= kHammingBits, "Hamming embedding needs descriptors of at least 64 dimensions");
  return RandomOrthogonalRows(state_->dimension, seed);
}

void Vocabulary::ProjectForHamming(std::span<const float> projection, std::span<const float> descriptors,
                                   std::span<float> projected) const {
  const State& s = *state_;
  const auto d = static_cast<size_t>(s.dimension);
  OXBOW_CHECK(projection.size() == kHammingBits * d, "the projection must be 64 x dimension");
  OXBOW_CHECK(descriptors.size() % d == 0 && projected.size() == descriptors.size() / d * kHammingBits,
              "kHammingBits projected values per descriptor");
  const std::vector<float> transposed = Transposed({projection.begin(), projection.end()}, s.dimension);
  for (size_t i = 0; i < descriptors.size() / d; ++i)
    Project(transposed, descriptors.data() + i * d, s.dimension, projected.data() + i * kHammingBits);
}

Result<Vocabulary> Vocabulary::WithHammingParameters(std::vector<float> projection, std::vector<float> medians) const {
  const State& s = *state_;
  if (s.dimension < kHammingBits) {
    return Fail(ErrorCode::kInvalidArgument, "Hamming embedding needs descriptors of at least 64 dimensions");
  }
  if (projection.size() != kHammingBits * static_cast<size_t>(s.dimension) || medians.size() != size() * kHammingBits) {
    return Fail(ErrorCode::kInvalidArgument, "Hamming-embedding parameters must be a 64 x " +
                                                 std::to_string(s.dimension) + " projection and " +
                                                 std::to_string(size()) + " x 64 medians");
  }
  if (!AllFinite(projection) || !AllFinite(medians)) {
    return Fail(ErrorCode::kInvalidArgument, "the Hamming-embedding parameters are not finite");
  }
  auto state = std::make_shared<State>(s);
  state->projection = std::move(projection);
  state->medians = std::move(medians);
  state->Finish();
  return Vocabulary(std::move(state));
}

void Vocabulary::Quantize(std::span<const float> descriptors, std::span<uint32_t> words,
                          const QuantizerOptions& options) const {
  const State& s = *state_;
  OXBOW_CHECK(descriptors.size() % s.dimension == 0, "descriptor buffer is not a multiple of the dimension");
  const size_t n = descriptors.size() / s.dimension;
  OXBOW_CHECK(words.size() == n, "words must have one entry per descriptor");
  OXBOW_CHECK(!options.Check(), "invalid QuantizerOptions (see QuantizerOptions::Check)");
  if (n == 0) return;
  std::vector<float> scores(n);
  if (options.exact) {
    internal::ExactSearch(s.index.words, descriptors.data(), n, 1, options.num_threads, words.data(), scores.data());
  } else {
    s.index.Search(descriptors.data(), n, 1, options.num_probes, options.num_threads, words.data(), scores.data());
  }
}

void Vocabulary::QuantizeMulti(std::span<const float> descriptors, int k, std::span<uint32_t> words,
                               std::span<float> sq_distances, const QuantizerOptions& options) const {
  const State& s = *state_;
  OXBOW_CHECK(k >= 1, "k must be >= 1");
  OXBOW_CHECK(descriptors.size() % s.dimension == 0, "descriptor buffer is not a multiple of the dimension");
  const size_t n = descriptors.size() / s.dimension;
  OXBOW_CHECK(words.size() == n * k && sq_distances.size() == n * k, "outputs must hold n x k entries");
  OXBOW_CHECK(!options.Check(), "invalid QuantizerOptions (see QuantizerOptions::Check)");
  if (n == 0) return;
  if (options.exact) {
    internal::ExactSearch(s.index.words, descriptors.data(), n, k, options.num_threads, words.data(),
                          sq_distances.data());
  } else {
    s.index.Search(descriptors.data(), n, k, options.num_probes, options.num_threads, words.data(),
                   sq_distances.data());
  }
  // Replace scores by exact squared distances and re-sort (the score order can differ in the last bits).
  const size_t num_words = size();
  std::vector<std::pair<float, uint32_t>> row(k);
  for (size_t i = 0; i < n; ++i) {
    const float* q = descriptors.data() + i * s.dimension;
    for (int j = 0; j < k; ++j) {
      const uint32_t w = words[i * k + j];
      row[j] = {w < num_words ? internal::SquaredL2(q, s.centroids.data() + size_t{w} * s.dimension, s.dimension)
                              : std::numeric_limits<float>::infinity(),
                w};
    }
    std::sort(row.begin(), row.end());
    for (int j = 0; j < k; ++j) {
      sq_distances[i * k + j] = row[j].first;
      words[i * k + j] = row[j].second;
    }
  }
}

}  // namespace oxbow::vocab
