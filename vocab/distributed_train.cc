// Distributed k-means (see distributed.h for the contract and why the result is rank-count free).
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <numeric>

#include "sift/base/binary_io.h"
#include "sift/base/hash.h"
#include "sift/base/log.h"
#include "sift/base/parallel.h"
#include "sift/base/system.h"
#include "vocab/distributed.h"
#include "vocab/train_internal.h"

namespace oxbow::vocab {

namespace {

using Clock = std::chrono::steady_clock;

constexpr std::string_view kCheckpointMagic = "OXBWKMCP";
constexpr uint32_t kCheckpointVersion = 1;

// The scale (a power of two) that turns values of magnitude <= bound into integers whose sum over
// `count` of them stays below 2^62, so int64 sums cannot overflow.
double FixedPointScale(double bound, uint64_t count) {
  if (!(bound > 0)) return 1.0;
  const int exponent = static_cast<int>(std::floor(std::log2(std::ldexp(1.0, 62) / (bound * static_cast<double>(count)))));
  return std::ldexp(1.0, std::clamp(exponent, -60, 60));
}

// Truncation (not rounding): as deterministic, and a single instruction in the hot loop.
int64_t ToFixed(double value, double scale) { return static_cast<int64_t>(value * scale); }

template <typename T>
std::vector<T> FromBytes(std::span<const uint8_t> bytes) {
  std::vector<T> out(bytes.size() / sizeof(T));
  if (!out.empty()) std::memcpy(out.data(), bytes.data(), out.size() * sizeof(T));
  return out;
}

void BroadcastFloats(Communicator& comm, std::vector<float>& values) {
  comm.Broadcast({reinterpret_cast<uint8_t*>(values.data()), values.size() * sizeof(float)});
}

// Rank 0's byte string on every rank (length first).
std::vector<uint8_t> BroadcastBlob(Communicator& comm, std::vector<uint8_t> blob) {
  uint64_t size = blob.size();
  comm.Broadcast({reinterpret_cast<uint8_t*>(&size), sizeof(size)});
  blob.resize(size);
  comm.Broadcast(blob);
  return blob;
}

// What a checkpoint must match to be resumed: the sample, the data and every option that changes
// the iterations' results (not max_iterations or the stopping rule, which only decide where to stop).
uint64_t CheckpointIdentity(const DistributedSample& sample, int64_t data_sum, size_t k, int dim,
                            sift::DescriptorKind kind, const std::string& settings, const TrainOptions& o,
                            AssignmentMethod method) {
  io::ByteWriter w;
  w.Put(sample.identity);
  w.Put(sample.total_rows);
  w.Put(data_sum);
  w.Put(uint64_t{k});
  w.Put(dim);
  w.Put(static_cast<uint32_t>(kind));
  w.Put(o.seed);
  w.Put(static_cast<uint32_t>(method));
  w.Put(o.ivf_probes);
  w.Put(o.kdtree_trees);
  w.Put(o.kdtree_checks);
  w.Put(uint64_t{o.kmeanspp_max_words});
  w.Put(uint64_t{o.seeding_points_per_word});
  w.Put(o.quantizer.iterations);
  w.PutString(settings);
  const auto& bytes = w.bytes();
  return Fnv1a64({reinterpret_cast<const char*>(bytes.data()), bytes.size()});
}

struct TrainingState {
  int done_iterations = 0;
  bool finished = false;
  double previous_objective = std::numeric_limits<double>::infinity();
  std::vector<float> centroids;     // k x dim
  std::vector<uint32_t> assign;     // this rank's rows
};

Status WriteCheckpoint(const std::string& path, uint64_t identity, const TrainingState& state,
                       std::span<const uint32_t> global_assign) {
  io::ByteWriter w;
  w.Put(identity);
  w.Put(static_cast<int32_t>(state.done_iterations));
  w.Put(static_cast<uint8_t>(state.finished));
  w.Put(state.previous_objective);
  w.Put(uint64_t{state.centroids.size()});
  w.PutArray(std::span<const float>(state.centroids));
  w.Put(uint64_t{global_assign.size()});
  w.PutArray(global_assign);
  return io::WriteContainerFile(path, kCheckpointMagic, kCheckpointVersion, 0, w.bytes());
}

// Parses a checkpoint payload into `state` (this rank's rows' words picked by their positions).
Status ParseCheckpoint(const std::string& path, std::span<const uint8_t> payload, uint64_t identity,
                       const DistributedSample& sample, size_t k, TrainingState& state) {
  io::ByteReader r(payload, "k-means checkpoint " + path);
  auto stored_identity = r.Get<uint64_t>();
  if (!stored_identity) return std::unexpected(stored_identity.error());
  if (*stored_identity != identity)
    return Fail(ErrorCode::kIncompatible, "the k-means checkpoint " + path +
                                              " belongs to other images, another sample or other options; delete it to start over");
  auto done = r.Get<int32_t>();
  auto finished = r.Get<uint8_t>();
  auto objective = r.Get<double>();
  auto num_centroid_values = r.Get<uint64_t>();
  if (!done || !finished || !objective || !num_centroid_values || *num_centroid_values != k * sample.dimension)
    return Fail(ErrorCode::kCorruptData, "k-means checkpoint " + path + ": damaged header");
  state.done_iterations = *done;
  state.finished = *finished != 0;
  state.previous_objective = *objective;
  state.centroids.resize(*num_centroid_values);
  if (auto s = r.GetArray(std::span<float>(state.centroids)); !s) return s;
  auto num_rows = r.Get<uint64_t>();
  if (!num_rows || *num_rows != sample.total_rows)
    return Fail(ErrorCode::kCorruptData, "k-means checkpoint " + path + ": wrong number of rows");
  std::vector<uint32_t> global(*num_rows);
  if (auto s = r.GetArray(std::span<uint32_t>(global)); !s) return s;
  state.assign.resize(sample.rows());
  for (size_t i = 0; i < sample.rows(); ++i) {
    state.assign[i] = global[sample.position[i]];
    if (state.assign[i] >= k) return Fail(ErrorCode::kCorruptData, "k-means checkpoint " + path + ": word out of range");
  }
  return Ok();
}

// An integer key of a finite float that orders as the float does: a < b iff OrderedKey(a) <
// OrderedKey(b). -0 and +0, equal as floats, get one key (+0's).
uint32_t OrderedKey(float value) {
  if (value == 0) value = 0.0f;
  uint32_t bits;
  std::memcpy(&bits, &value, sizeof(bits));
  return (bits & 0x80000000u) != 0 ? ~bits : bits | 0x80000000u;
}

float FromOrderedKey(uint32_t key) {
  const uint32_t bits = (key & 0x80000000u) != 0 ? key & 0x7FFFFFFFu : ~key;
  float value;
  std::memcpy(&value, &bits, sizeof(value));
  return value;
}

// Words whose medians are selected together: bounds the selection's buffers (20 bytes per word and bit).
constexpr size_t kSelectionBlockWords = 16384;

}  // namespace

// ---- Sampling -------------------------------------------------------------------------------------

NamedSampler::NamedSampler(const SampleOptions& options, int dimension) : options_(options), dimension_(dimension) {
  OXBOW_CHECK(!options.Check(), "invalid SampleOptions");
  OXBOW_CHECK(dimension > 0, "dimension must be positive");
}

void NamedSampler::AddImage(std::string_view name, std::span<const float> descriptors) {
  OXBOW_CHECK(descriptors.size() % dimension_ == 0, "descriptor buffer is not a multiple of the dimension");
  const size_t dim = static_cast<size_t>(dimension_);
  const size_t rows = descriptors.size() / dim;
  ++images_seen_;
  internal::SplitMix64 rng(Fnv1a64(name) ^ (options_.seed * 0x9E3779B97F4A7C15ull));
  std::vector<uint64_t> row_keys(rows);
  for (uint64_t& key : row_keys) key = rng.Next();
  std::vector<uint32_t> pick(rows);
  std::iota(pick.begin(), pick.end(), 0u);
  const size_t keep = std::min(rows, options_.max_per_image);
  std::nth_element(pick.begin(), pick.begin() + static_cast<ptrdiff_t>(keep), pick.end(),
                   [&](uint32_t a, uint32_t b) { return row_keys[a] < row_keys[b]; });
  pick.resize(keep);
  rows_seen_ += keep;
  for (uint32_t r : pick) {
    keys_.push_back(row_keys[r]);
    data_.insert(data_.end(), descriptors.begin() + static_cast<ptrdiff_t>(r * dim),
                 descriptors.begin() + static_cast<ptrdiff_t>((r + 1) * dim));
  }
  if (keys_.size() > 2 * options_.max_total) Prune(options_.max_total);
}

void NamedSampler::Prune(size_t keep) {
  const size_t dim = static_cast<size_t>(dimension_);
  std::vector<uint32_t> order(keys_.size());
  std::iota(order.begin(), order.end(), 0u);
  std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return keys_[a] < keys_[b]; });
  order.resize(std::min(keep, order.size()));
  std::vector<uint64_t> keys(order.size());
  std::vector<float> data(order.size() * dim);
  for (size_t i = 0; i < order.size(); ++i) {
    keys[i] = keys_[order[i]];
    std::copy_n(data_.begin() + static_cast<ptrdiff_t>(order[i] * dim), dim, data.begin() + static_cast<ptrdiff_t>(i * dim));
  }
  keys_ = std::move(keys);
  data_ = std::move(data);
}

DistributedSample NamedSampler::Finish(Communicator& comm) {
  Prune(options_.max_total);  // also sorts the rows by key
  const auto gathered = comm.Allgather({reinterpret_cast<const uint8_t*>(keys_.data()), keys_.size() * sizeof(uint64_t)});
  std::vector<uint64_t> all = FromBytes<uint64_t>(gathered);
  std::sort(all.begin(), all.end());
  all.resize(std::min<size_t>(all.size(), options_.max_total));
  OXBOW_CHECK(std::adjacent_find(all.begin(), all.end()) == all.end(),
              "two sampled descriptors have the same key: is an image given twice?");

  DistributedSample out;
  out.dimension = dimension_;
  out.total_rows = all.size();
  out.identity = Fnv1a64({reinterpret_cast<const char*>(all.data()), all.size() * sizeof(uint64_t)});
  const size_t dim = static_cast<size_t>(dimension_);
  for (size_t i = 0; i < keys_.size(); ++i) {
    auto it = std::lower_bound(all.begin(), all.end(), keys_[i]);
    if (it == all.end() || *it != keys_[i]) break;  // rows are sorted: the rest lie past the global cut
    out.position.push_back(static_cast<uint32_t>(it - all.begin()));
    out.descriptors.insert(out.descriptors.end(), data_.begin() + static_cast<ptrdiff_t>(i * dim),
                           data_.begin() + static_cast<ptrdiff_t>((i + 1) * dim));
  }
  std::vector<int64_t> counts = {static_cast<int64_t>(rows_seen_), static_cast<int64_t>(images_seen_)};
  comm.SumInPlace(counts);
  out.rows_seen = static_cast<uint64_t>(counts[0]);
  out.images_seen = static_cast<uint64_t>(counts[1]);
  keys_ = {};
  data_ = {};
  return out;
}

// ---- Training -------------------------------------------------------------------------------------

std::optional<std::string> DistributedTrainOptions::Check() const {
  if (auto problem = train.Check()) return problem;
  if (stop_after_iterations < 0) return "DistributedTrainOptions.stop_after_iterations must be >= 0";
  return std::nullopt;
}

Result<DistributedTrainResult> TrainDistributed(const DistributedSample& sample, Communicator& comm,
                                                sift::DescriptorKind kind, std::string extractor_settings,
                                                const DistributedTrainOptions& options, TrainReport* report) {
  const auto start = Clock::now();
  if (auto problem = options.Check()) return Fail(ErrorCode::kInvalidArgument, *problem);
  const int dim = sample.dimension;
  if (dim < 1 || dim > 4096) return Fail(ErrorCode::kInvalidArgument, "dimension must be in [1, 4096]");
  OXBOW_CHECK(sample.descriptors.size() == sample.rows() * static_cast<size_t>(dim), "sample size mismatch");
  const TrainOptions& train = options.train;
  const size_t n = sample.total_rows;
  const size_t nl = sample.rows();
  const size_t k = train.num_words;
  if (n < k)
    return Fail(ErrorCode::kInvalidArgument, "k-means needs at least as many descriptors as words: " +
                                                 std::to_string(n) + " descriptors for " + std::to_string(k) + " words");
  if (n > std::numeric_limits<uint32_t>::max())
    return Fail(ErrorCode::kInvalidArgument, "at most 2^32 - 1 training descriptors");
  const float* x = sample.descriptors.data();
  double max_abs = 0;
  bool finite = true;
  for (float v : sample.descriptors) {
    finite = finite && std::isfinite(v);
    max_abs = std::max(max_abs, static_cast<double>(std::fabs(v)));
  }
  std::vector<int64_t> non_finite = {finite ? 0 : 1};
  comm.SumInPlace(non_finite);
  if (non_finite[0] != 0) return Fail(ErrorCode::kInvalidArgument, "training descriptors contain NaN or infinity");
  max_abs = comm.Max(max_abs);
  const double value_scale = FixedPointScale(max_abs, n);
  const double dist_scale = FixedPointScale(4.0 * max_abs * max_abs * dim, n);
  // The checkpoint's fingerprint of the sample adds every coordinate (n x dim values, not n per sum as
  // in the iterations), so its scale bounds that total.
  const double data_scale = FixedPointScale(max_abs, static_cast<uint64_t>(n) * static_cast<uint64_t>(dim));
  std::vector<int64_t> data_sum = {0};
  for (float v : sample.descriptors) data_sum[0] += ToFixed(v, data_scale);
  comm.SumInPlace(data_sum);

  const int threads = ResolveThreadCount(train.num_threads);
  const AssignmentMethod method = internal::ResolveAssignment(train);
  const bool approximate = method != AssignmentMethod::kExact;
  const uint64_t identity =
      CheckpointIdentity(sample, data_sum[0], k, dim, kind, extractor_settings, train, method);
  TrainReport local_report;
  TrainReport& rep = report ? *report : local_report;
  rep = {};
  DistributedTrainResult result;

  TrainingState state;
  std::vector<uint8_t> checkpoint;
  if (comm.rank() == 0 && !options.checkpoint_path.empty()) {
    std::error_code ec;
    if (std::filesystem::exists(options.checkpoint_path, ec)) {
      auto container = io::ReadContainerFile(options.checkpoint_path, kCheckpointMagic, kCheckpointVersion,
                                             kCheckpointVersion);
      if (!container) return std::unexpected(container.error());
      checkpoint = std::move(container->payload);
    }
  }
  checkpoint = BroadcastBlob(comm, std::move(checkpoint));
  if (!checkpoint.empty()) {
    if (auto s = ParseCheckpoint(options.checkpoint_path, checkpoint, identity, sample, k, state); !s)
      return std::unexpected(s.error());
    result.resumed_after_iteration = state.done_iterations;
    OXBOW_LOG(kInfo) << "k-means: resuming from " << options.checkpoint_path << " after iteration "
                     << state.done_iterations;
  } else {
    // Seeding on the first m rows of the global order (uniformly random rows: the keys are hashes).
    const bool plusplus = k <= train.kmeanspp_max_words;
    const size_t m = plusplus ? std::min(n, std::max(k, k * train.seeding_points_per_word)) : k;
    OXBOW_LOG(kInfo) << "k-means: " << k << " words from " << n << " descriptors on " << comm.size()
                     << " ranks (dim " << dim << "), seeding " << (plusplus ? "k-means++" : "random") << " on "
                     << m << " rows, assignment " << AssignmentMethodName(method) << ", " << threads
                     << " threads per rank";
    io::ByteWriter w;
    for (size_t i = 0; i < nl && sample.position[i] < m; ++i) {
      w.Put(sample.position[i]);
      w.PutArray(std::span<const float>(x + i * dim, static_cast<size_t>(dim)));
    }
    const std::vector<uint8_t> gathered = comm.Allgather(w.bytes());
    const size_t record = sizeof(uint32_t) + dim * sizeof(float);
    OXBOW_CHECK(gathered.size() == m * record, "seeding rows missing");
    std::vector<float> seeding(m * dim);
    for (size_t off = 0; off < gathered.size(); off += record) {
      uint32_t pos;
      std::memcpy(&pos, gathered.data() + off, sizeof(pos));
      std::memcpy(seeding.data() + size_t{pos} * dim, gathered.data() + off + sizeof(pos), dim * sizeof(float));
    }
    if (comm.rank() == 0) {
      internal::SplitMix64 rng(train.seed);
      state.centroids = plusplus ? internal::KMeansPlusPlus(seeding, dim, k, rng, threads)
                                 : std::vector<float>(seeding.begin(), seeding.begin() + static_cast<ptrdiff_t>(k * dim));
    } else {
      state.centroids.assign(k * dim, 0.0f);
    }
    BroadcastFloats(comm, state.centroids);
    state.assign.assign(nl, 0);
  }
  rep.seeding_seconds = SecondsSince(start);

  std::vector<uint32_t> proposal(nl);
  std::vector<float> dist(nl);
  // [changed rows, objective sum, counts per word, sums per word and dimension], fixed point.
  std::vector<int64_t> totals(2 + k + k * dim);
  std::vector<uint32_t> member_start(k + 1), members(nl);
  const int first_this_run = state.done_iterations + 1;
  for (int it = first_this_run; !state.finished && it <= train.max_iterations; ++it) {
    const auto t0 = Clock::now();
    IterationStats stats;
    stats.iteration = it;
    internal::Assign(method, state.centroids, k, x, nl, dim, train, train.seed * 1000003ull + static_cast<uint64_t>(it),
                     threads, proposal);
    const uint64_t changed = internal::AcceptAssignments(approximate, it == 1, state.centroids, x, nl, dim, threads,
                                                         proposal, state.assign, dist);
    std::fill(totals.begin(), totals.end(), 0);
    totals[0] = static_cast<int64_t>(changed);
    int64_t* counts = totals.data() + 2;
    int64_t* sums = counts + k;
    for (size_t i = 0; i < nl; ++i) {
      totals[1] += ToFixed(dist[i], dist_scale);
      ++counts[state.assign[i]];
    }
    // Per-word sums over the word's rows (a counting sort by word), words in parallel: integer sums, so
    // neither the thread count nor the order matters.
    member_start[0] = 0;
    for (size_t c = 0; c < k; ++c) member_start[c + 1] = member_start[c] + static_cast<uint32_t>(counts[c]);
    {
      std::vector<uint32_t> fill(member_start.begin(), member_start.end() - 1);
      for (size_t i = 0; i < nl; ++i) members[fill[state.assign[i]]++] = static_cast<uint32_t>(i);
    }
    ParallelFor(k, threads, 256, [&](size_t begin, size_t end, int) {
      for (size_t c = begin; c < end; ++c) {
        int64_t* s = sums + c * dim;
        for (uint32_t m = member_start[c]; m < member_start[c + 1]; ++m) {
          const float* xi = x + size_t{members[m]} * dim;
          for (int d = 0; d < dim; ++d) s[d] += ToFixed(xi[d], value_scale);
        }
      }
    });
    comm.SumInPlace(totals);
    stats.objective = static_cast<double>(totals[1]) / dist_scale / static_cast<double>(n);
    stats.reassigned_share = static_cast<double>(totals[0]) / static_cast<double>(n);
    std::vector<uint32_t> empty;
    for (size_t c = 0; c < k; ++c) {
      if (counts[c] == 0) {
        empty.push_back(static_cast<uint32_t>(c));
        continue;
      }
      for (int d = 0; d < dim; ++d)
        state.centroids[c * dim + d] =
            static_cast<float>(static_cast<double>(sums[c * dim + d]) / value_scale / static_cast<double>(counts[c]));
    }
    stats.empty_clusters = empty.size();
    if (!empty.empty()) {
      // The globally farthest rows (ties: lower position), each rank offering its own farthest.
      const auto farther = [](float da, uint32_t pa, float db, uint32_t pb) { return da > db || (da == db && pa < pb); };
      std::vector<uint32_t> local(nl);
      std::iota(local.begin(), local.end(), 0u);
      const size_t offer = std::min(empty.size(), nl);
      std::partial_sort(local.begin(), local.begin() + static_cast<ptrdiff_t>(offer), local.end(), [&](uint32_t a, uint32_t b) {
        return farther(dist[a], sample.position[a], dist[b], sample.position[b]);
      });
      io::ByteWriter w;
      for (size_t e = 0; e < offer; ++e) {
        w.Put(dist[local[e]]);
        w.Put(sample.position[local[e]]);
        w.PutArray(std::span<const float>(x + size_t{local[e]} * dim, static_cast<size_t>(dim)));
      }
      const std::vector<uint8_t> gathered = comm.Allgather(w.bytes());
      const size_t record = sizeof(float) + sizeof(uint32_t) + dim * sizeof(float);
      struct Candidate {
        float dist;
        uint32_t position;
        size_t offset;
      };
      std::vector<Candidate> candidates;
      for (size_t off = 0; off < gathered.size(); off += record) {
        Candidate c{0, 0, off + sizeof(float) + sizeof(uint32_t)};
        std::memcpy(&c.dist, gathered.data() + off, sizeof(float));
        std::memcpy(&c.position, gathered.data() + off + sizeof(float), sizeof(uint32_t));
        candidates.push_back(c);
      }
      std::sort(candidates.begin(), candidates.end(), [&](const Candidate& a, const Candidate& b) {
        return farther(a.dist, a.position, b.dist, b.position);
      });
      for (size_t e = 0; e < std::min(empty.size(), candidates.size()); ++e)
        std::memcpy(state.centroids.data() + size_t{empty[e]} * dim, gathered.data() + candidates[e].offset,
                    dim * sizeof(float));
    }
    // Every rank computed the same centroids from the same integers; rank 0's copy is the reference.
    BroadcastFloats(comm, state.centroids);

    const bool small_gain = it > 1 && state.previous_objective - stats.objective <
                                          train.min_relative_improvement * state.previous_objective;
    state.previous_objective = stats.objective;
    state.done_iterations = it;
    if (small_gain || totals[0] == 0) rep.converged = true;
    state.finished = rep.converged || it == train.max_iterations;
    const auto checkpoint_start = Clock::now();
    if (!options.checkpoint_path.empty()) {
      io::ByteWriter w;
      for (size_t i = 0; i < nl; ++i) {
        w.Put(sample.position[i]);
        w.Put(state.assign[i]);
      }
      const std::vector<uint8_t> gathered = comm.Allgather(w.bytes());
      if (comm.rank() == 0) {
        std::vector<uint32_t> global(n);
        for (size_t off = 0; off < gathered.size(); off += 2 * sizeof(uint32_t)) {
          uint32_t pos, word;
          std::memcpy(&pos, gathered.data() + off, sizeof(pos));
          std::memcpy(&word, gathered.data() + off + sizeof(pos), sizeof(word));
          global[pos] = word;
        }
        if (auto s = WriteCheckpoint(options.checkpoint_path, identity, state, global); !s)
          return std::unexpected(s.error());
      }
    }
    stats.seconds = SecondsSince(t0);
    rep.iterations.push_back(stats);
    OXBOW_LOG(kInfo) << "k-means iteration " << it << ": objective " << stats.objective << ", reassigned "
                     << 100.0 * stats.reassigned_share << "%, empty " << stats.empty_clusters << ", "
                     << stats.seconds << " s (checkpoint " << SecondsSince(checkpoint_start) << " s)";
    if (!state.finished && options.stop_after_iterations > 0 &&
        it - first_this_run + 1 >= options.stop_after_iterations) {
      rep.total_seconds = SecondsSince(start);
      return result;
    }
  }
  result.finished = true;
  if (comm.rank() == 0 || options.hamming) {
    auto vocabulary =
        Vocabulary::FromCentroids(std::move(state.centroids), dim, kind, std::move(extractor_settings), train.quantizer);
    if (!vocabulary) return std::unexpected(vocabulary.error());
    result.vocabulary = std::move(*vocabulary);
  }
  if (options.hamming) {
    // Every rank built its quantiser from the same centroids with the same seeded coarse k-means.
    const uint64_t fingerprint = result.vocabulary->fingerprint();
    const std::vector<uint64_t> all = FromBytes<uint64_t>(
        comm.Allgather({reinterpret_cast<const uint8_t*>(&fingerprint), sizeof(fingerprint)}));
    OXBOW_CHECK(std::all_of(all.begin(), all.end(), [&](uint64_t f) { return f == fingerprint; }),
                "the ranks built different vocabularies from the same centroids");
    const auto t0 = Clock::now();
    QuantizerOptions quantizer;
    quantizer.num_threads = train.num_threads;
    auto with = WithHammingDistributed(*result.vocabulary, sample, comm, train.seed, quantizer);
    if (!with) return std::unexpected(with.error());
    result.vocabulary = std::move(*with);
    OXBOW_LOG(kInfo) << "Hamming-embedding medians from " << n << " descriptors on " << comm.size() << " ranks: "
                     << SecondsSince(t0) << " s";
  }
  rep.total_seconds = SecondsSince(start);
  return result;
}

// ---- Hamming embedding ----------------------------------------------------------------------------

Result<Vocabulary> WithHammingDistributed(const Vocabulary& vocabulary, const DistributedSample& sample,
                                          Communicator& comm, uint64_t seed, const QuantizerOptions& quantizer) {
  const int dim = vocabulary.dimension();
  if (dim < kHammingBits)
    return Fail(ErrorCode::kInvalidArgument, "Hamming embedding needs descriptors of at least 64 dimensions");
  if (sample.dimension != dim)
    return Fail(ErrorCode::kInvalidArgument, "the sample's dimension " + std::to_string(sample.dimension) +
                                                 " is not the vocabulary's " + std::to_string(dim));
  if (auto problem = quantizer.Check()) return Fail(ErrorCode::kInvalidArgument, *problem);
  OXBOW_CHECK(sample.descriptors.size() == sample.rows() * static_cast<size_t>(dim), "sample size mismatch");
  const bool finite =
      std::all_of(sample.descriptors.begin(), sample.descriptors.end(), [](float v) { return std::isfinite(v); });
  // Decided together, so that every rank returns the same error.
  std::vector<int64_t> checks = {static_cast<int64_t>(sample.rows()), finite ? 0 : 1};
  comm.SumInPlace(checks);
  if (checks[1] != 0) return Fail(ErrorCode::kInvalidArgument, "the Hamming-embedding sample is not finite");
  if (checks[0] == 0) return Fail(ErrorCode::kInvalidArgument, "the Hamming-embedding sample has no rows");

  const size_t k = vocabulary.size();
  const size_t nl = sample.rows();
  const size_t d = static_cast<size_t>(dim);
  constexpr size_t kBits = kHammingBits;
  const int threads = ResolveThreadCount(quantizer.num_threads);
  std::vector<uint32_t> words(nl);
  vocabulary.Quantize(sample.descriptors, words, quantizer);
  const std::vector<float> projection = vocabulary.HammingProjection(seed);

  // This rank's rows grouped by word (a counting sort), each as its kBits projected values' keys.
  std::vector<size_t> begin(k + 1, 0);
  for (const uint32_t w : words) ++begin[w + 1];
  std::partial_sum(begin.begin(), begin.end(), begin.begin());
  std::vector<uint32_t> slot(nl);
  {
    std::vector<size_t> next(begin.begin(), begin.end() - 1);
    for (size_t i = 0; i < nl; ++i) slot[i] = static_cast<uint32_t>(next[words[i]]++);
  }
  std::vector<uint32_t> keys(nl * kBits);
  constexpr size_t kChunkRows = 1024;
  ParallelFor((nl + kChunkRows - 1) / kChunkRows, threads, 1, [&](size_t lo, size_t hi, int) {
    std::vector<float> projected;
    for (size_t c = lo; c < hi; ++c) {
      const size_t first = c * kChunkRows;
      const size_t rows = std::min(kChunkRows, nl - first);
      projected.resize(rows * kBits);
      vocabulary.ProjectForHamming(projection, std::span<const float>(sample.descriptors).subspan(first * d, rows * d),
                                   projected);
      for (size_t r = 0; r < rows; ++r) {
        uint32_t* key = keys.data() + size_t{slot[first + r]} * kBits;
        for (size_t b = 0; b < kBits; ++b) key[b] = OrderedKey(projected[r * kBits + b]);
      }
    }
  });
  slot = {};
  words = {};

  std::vector<int64_t> count(k);
  for (size_t w = 0; w < k; ++w) count[w] = static_cast<int64_t>(begin[w + 1] - begin[w]);
  comm.SumInPlace(count);

  std::vector<float> medians(k * kBits);
  // A word no row reaches: its projected centroid (as WithHamming).
  for (size_t w = 0; w < k; ++w) {
    if (count[w] == 0)
      vocabulary.ProjectForHamming(projection, vocabulary.centroids().subspan(w * d, d),
                                   std::span<float>(medians).subspan(w * kBits, kBits));
  }
  // Per word and bit, the key of sorted position count / 2 (std::nth_element's median in WithHamming),
  // decided one key bit at a time from the top: `below` counts the values that agree with the prefix
  // found so far and have a 0 at the current bit; the wanted position lies among them or after them.
  std::vector<uint32_t> prefix;
  std::vector<int64_t> position, below;
  for (size_t w0 = 0; w0 < k; w0 += kSelectionBlockWords) {
    const size_t block = std::min(kSelectionBlockWords, k - w0);
    prefix.assign(block * kBits, 0);
    position.resize(block * kBits);
    below.resize(block * kBits);
    for (size_t w = 0; w < block; ++w) std::fill_n(position.begin() + w * kBits, kBits, count[w0 + w] / 2);
    for (int bit = 31; bit >= 0; --bit) {
      ParallelFor(block, threads, 64, [&](size_t lo, size_t hi, int) {
        std::array<uint32_t, kBits> local;
        for (size_t w = lo; w < hi; ++w) {
          local.fill(0);
          const uint32_t* p = prefix.data() + w * kBits;
          for (size_t r = begin[w0 + w]; r < begin[w0 + w + 1]; ++r) {
            const uint32_t* key = keys.data() + r * kBits;
            for (size_t b = 0; b < kBits; ++b) local[b] += (key[b] >> bit) == (p[b] >> bit) ? 1u : 0u;
          }
          std::copy(local.begin(), local.end(), below.begin() + static_cast<ptrdiff_t>(w * kBits));
        }
      });
      comm.SumInPlace(below);
      for (size_t i = 0; i < block * kBits; ++i) {
        if (position[i] >= below[i]) {
          prefix[i] |= 1u << bit;
          position[i] -= below[i];
        }
      }
    }
    for (size_t w = 0; w < block; ++w) {
      if (count[w0 + w] == 0) continue;
      for (size_t b = 0; b < kBits; ++b) medians[(w0 + w) * kBits + b] = FromOrderedKey(prefix[w * kBits + b]);
    }
  }
  return vocabulary.WithHammingParameters(projection, std::move(medians));
}

}  // namespace oxbow::vocab
