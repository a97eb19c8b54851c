// Descriptor matching. The exact matcher works on scores |d|^2 - 2 q.d (the squared distance minus the
// query's constant |q|^2) so that the inner loop is a plain dot product: a 6-query x 16-db register tile
// over db descriptors packed dimension-major in blocks of 16 (one 8 KiB block stays in L1 while a chunk
// of queries streams past it). Both kernels add q[k] * d[k] with a fused multiply-add for k = 0..127 in
// order, so the AVX2 and the scalar kernel produce identical bits.
#include "sift/match.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define OXBOW_MATCH_AVX2 1
#endif

#include <opencv2/core.hpp>
#include <opencv2/flann.hpp>

#include "sift/match_internal.h"
#include "sift/base/parallel.h"

namespace oxbow::sift {
namespace {

constexpr size_t kDim = kDescriptorDim;
constexpr size_t kDbBlock = 16;      // db descriptors per packed block (two AVX2 registers wide)
constexpr size_t kQueryGroup = 6;    // query rows per register tile (12 accumulators + 2 db + 1 broadcast)
constexpr size_t kQueryChunk = 96;   // queries per parallel work item (a multiple of kQueryGroup)
constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr uint32_t kNone = std::numeric_limits<uint32_t>::max();

// The two best db candidates of one query (scores: smaller is nearer).
struct Nearest2 {
  float score1 = kInf;
  float score2 = kInf;
  uint32_t index1 = kNone;

  // Candidates arrive in increasing index order, so a tie keeps the smaller index.
  void Offer(float score, uint32_t index) {
    if (score < score1) {
      score2 = score1;
      score1 = score;
      index1 = index;
    } else if (score < score2) {
      score2 = score;
    }
  }
};

// The best query of one db feature (mutual check); ties go to the smaller query index whatever the order.
struct NearestQuery {
  float score = kInf;
  uint32_t index = kNone;

  void Offer(float s, uint32_t i) {
    if (s < score || (s == score && i < index)) {
      score = s;
      index = i;
    }
  }
};

// a * b + c, rounded once where the target has FMA (as the AVX2 kernel computes it), else twice
// (std::fma without hardware support is a slow library call).
inline float MulAdd(float a, float b, float c) {
#ifdef __FMA__
  return std::fma(a, b, c);
#else
  return a * b + c;
#endif
}

// dots[r * 16 + j] = rows[r] . block column j, for a block packed as block[k * 16 + j]. Each sum runs
// over k = 0..127 in order, exactly as in DotTileAvx2.
void DotTileScalar(const float* const rows[kQueryGroup], const float* block, float* dots) {
  for (size_t r = 0; r < kQueryGroup; ++r) {
    float sums[kDbBlock] = {};
    for (size_t k = 0; k < kDim; ++k) {
      const float q = rows[r][k];
      for (size_t j = 0; j < kDbBlock; ++j) sums[j] = MulAdd(q, block[k * kDbBlock + j], sums[j]);
    }
    for (size_t j = 0; j < kDbBlock; ++j) dots[r * kDbBlock + j] = sums[j];
  }
}

#ifdef OXBOW_MATCH_AVX2
void DotTileAvx2(const float* const rows[kQueryGroup], const float* block, float* dots) {
  __m256 acc[kQueryGroup][2];
  for (size_t r = 0; r < kQueryGroup; ++r) acc[r][0] = acc[r][1] = _mm256_setzero_ps();
  const float* const r0 = rows[0];
  const float* const r1 = rows[1];
  const float* const r2 = rows[2];
  const float* const r3 = rows[3];
  const float* const r4 = rows[4];
  const float* const r5 = rows[5];
  static_assert(kQueryGroup == 6, "the tile below is written out for 6 rows");
  for (size_t k = 0; k < kDim; ++k) {
    const __m256 d0 = _mm256_loadu_ps(block + k * kDbBlock);
    const __m256 d1 = _mm256_loadu_ps(block + k * kDbBlock + 8);
    __m256 q = _mm256_broadcast_ss(r0 + k);
    acc[0][0] = _mm256_fmadd_ps(q, d0, acc[0][0]);
    acc[0][1] = _mm256_fmadd_ps(q, d1, acc[0][1]);
    q = _mm256_broadcast_ss(r1 + k);
    acc[1][0] = _mm256_fmadd_ps(q, d0, acc[1][0]);
    acc[1][1] = _mm256_fmadd_ps(q, d1, acc[1][1]);
    q = _mm256_broadcast_ss(r2 + k);
    acc[2][0] = _mm256_fmadd_ps(q, d0, acc[2][0]);
    acc[2][1] = _mm256_fmadd_ps(q, d1, acc[2][1]);
    q = _mm256_broadcast_ss(r3 + k);
    acc[3][0] = _mm256_fmadd_ps(q, d0, acc[3][0]);
    acc[3][1] = _mm256_fmadd_ps(q, d1, acc[3][1]);
    q = _mm256_broadcast_ss(r4 + k);
    acc[4][0] = _mm256_fmadd_ps(q, d0, acc[4][0]);
    acc[4][1] = _mm256_fmadd_ps(q, d1, acc[4][1]);
    q = _mm256_broadcast_ss(r5 + k);
    acc[5][0] = _mm256_fmadd_ps(q, d0, acc[5][0]);
    acc[5][1] = _mm256_fmadd_ps(q, d1, acc[5][1]);
  }
  for (size_t r = 0; r < kQueryGroup; ++r) {
    _mm256_storeu_ps(dots + r * kDbBlock, acc[r][0]);
    _mm256_storeu_ps(dots + r * kDbBlock + 8, acc[r][1]);
  }
}
#endif

using DotTileFn = void (*)(const float* const[kQueryGroup], const float*, float*);

DotTileFn SelectKernel([[maybe_unused]] internal::DotKernel kernel) {
#ifdef OXBOW_MATCH_AVX2
  if (kernel == internal::DotKernel::kAuto) return &DotTileAvx2;
#endif
  return &DotTileScalar;
}

std::vector<float> SquaredNorms(const FeatureSet& set) {
  std::vector<float> norms(set.size());
  for (size_t i = 0; i < set.size(); ++i) {
    const float* d = set.descriptors.data() + i * kDim;
    float sum = 0;
    for (size_t k = 0; k < kDim; ++k) sum = std::fma(d[k], d[k], sum);
    norms[i] = sum;
  }
  return norms;
}

// Result of a one-directional search: for each query, its nearest db index and the two distances.
struct ForwardResult {
  std::vector<uint32_t> nearest;  // kNone when no candidate
  std::vector<float> distance1;   // L2 distance to the nearest
  std::vector<float> distance2;   // L2 distance to the second nearest (inf if none)
  std::vector<uint32_t> reverse;  // when requested: for each db feature its nearest query (kNone if none)
};

ForwardResult BruteForce(const FeatureSet& query, const FeatureSet& db, bool want_reverse, int num_threads,
                         DotTileFn kernel) {
  const size_t nq = query.size();
  const size_t ndb = db.size();
  const size_t num_blocks = (ndb + kDbBlock - 1) / kDbBlock;

  // Dimension-major packing: packed[b][k][j] = db[b * 16 + j][k]; padding columns are zero.
  std::vector<float> packed(num_blocks * kDim * kDbBlock, 0.0f);
  for (size_t i = 0; i < ndb; ++i) {
    const float* d = db.descriptors.data() + i * kDim;
    float* out = packed.data() + (i / kDbBlock) * kDim * kDbBlock + (i % kDbBlock);
    for (size_t k = 0; k < kDim; ++k) out[k * kDbBlock] = d[k];
  }
  const std::vector<float> db_norms = SquaredNorms(db);
  const std::vector<float> query_norms = SquaredNorms(query);

  const int workers = ResolveThreadCount(num_threads);
  std::vector<Nearest2> nearest(nq);
  std::vector<std::vector<NearestQuery>> reverse_per_worker(want_reverse ? static_cast<size_t>(workers) : 0);

  ParallelFor(nq, workers, kQueryChunk, [&](size_t begin, size_t end, int worker) {
    std::vector<NearestQuery>* reverse = nullptr;
    if (want_reverse) {
      reverse = &reverse_per_worker[static_cast<size_t>(worker)];
      if (reverse->empty()) reverse->resize(ndb);
    }
    alignas(32) float dots[kQueryGroup * kDbBlock];
    for (size_t b = 0; b < num_blocks; ++b) {
      const float* block = packed.data() + b * kDim * kDbBlock;
      const size_t j0 = b * kDbBlock;
      const size_t width = std::min(kDbBlock, ndb - j0);
      for (size_t g = begin; g < end; g += kQueryGroup) {
        const size_t count = std::min(kQueryGroup, end - g);
        const float* rows[kQueryGroup];
        for (size_t r = 0; r < kQueryGroup; ++r) rows[r] = query.descriptors.data() + (g + std::min(r, count - 1)) * kDim;
        kernel(rows, block, dots);
        for (size_t r = 0; r < count; ++r) {
          Nearest2& n = nearest[g + r];
          const float* row_dots = dots + r * kDbBlock;
          for (size_t j = 0; j < width; ++j) n.Offer(db_norms[j0 + j] - 2.0f * row_dots[j], static_cast<uint32_t>(j0 + j));
          if (reverse != nullptr) {
            const float qn = query_norms[g + r];
            for (size_t j = 0; j < width; ++j) (*reverse)[j0 + j].Offer(qn - 2.0f * row_dots[j], static_cast<uint32_t>(g + r));
          }
        }
      }
    }
  });

  ForwardResult result;
  result.nearest.resize(nq);
  result.distance1.resize(nq);
  result.distance2.resize(nq);
  for (size_t i = 0; i < nq; ++i) {
    result.nearest[i] = nearest[i].index1;
    result.distance1[i] = std::sqrt(std::max(0.0f, query_norms[i] + nearest[i].score1));
    result.distance2[i] = std::sqrt(std::max(0.0f, query_norms[i] + nearest[i].score2));
  }
  if (want_reverse) {
    result.reverse.assign(ndb, kNone);
    std::vector<NearestQuery> merged(ndb);
    for (const auto& per_worker : reverse_per_worker) {
      if (per_worker.empty()) continue;
      for (size_t j = 0; j < ndb; ++j) merged[j].Offer(per_worker[j].score, per_worker[j].index);
    }
    for (size_t j = 0; j < ndb; ++j) result.reverse[j] = merged[j].index;
  }
  return result;
}

// Restores the calling thread's cv::theRNG() when it leaves scope.
class ScopedSeededRng {
 public:
  explicit ScopedSeededRng(uint64_t seed) : saved_(cv::theRNG()) { cv::theRNG() = cv::RNG(seed == 0 ? 1 : seed); }
  ~ScopedSeededRng() { cv::theRNG() = saved_; }
  ScopedSeededRng(const ScopedSeededRng&) = delete;
  ScopedSeededRng& operator=(const ScopedSeededRng&) = delete;

 private:
  cv::RNG saved_;
};

// k nearest (k = 1 or 2) of every `query` row among the `data` rows with a randomised kd-forest.
// Fills nearest / distance1 / distance2 (L2, not squared).
void KdForestSearch(const FeatureSet& query, const FeatureSet& data, int knn, const MatchOptions& options,
                    std::vector<uint32_t>* nearest, std::vector<float>* distance1, std::vector<float>* distance2) {
  const size_t nq = query.size();
  nearest->assign(nq, kNone);
  distance1->assign(nq, kInf);
  if (distance2 != nullptr) distance2->assign(nq, kInf);
  if (nq == 0 || data.size() == 0) return;
  knn = std::min<int>(knn, static_cast<int>(data.size()));

  // cvflann only reads the data through this view (the const_cast is for its non-const Matrix type).
  cvflann::Matrix<float> dataset(const_cast<float*>(data.descriptors.data()), data.size(), kDim);
  cvflann::Index<cvflann::L2<float>> index(dataset, cvflann::KDTreeIndexParams(options.kd_trees));
  {
    ScopedSeededRng rng(options.kd_seed);
    index.buildIndex();
  }
  const cvflann::SearchParams search(options.kd_checks);
  ParallelFor(nq, options.num_threads, 256, [&](size_t begin, size_t end, int) {
    const size_t count = end - begin;
    std::vector<int> indices(count * static_cast<size_t>(knn), -1);
    std::vector<float> dists(count * static_cast<size_t>(knn), kInf);
    cvflann::Matrix<float> queries(const_cast<float*>(query.descriptors.data() + begin * kDim), count, kDim);
    cvflann::Matrix<int> index_view(indices.data(), count, static_cast<size_t>(knn));
    cvflann::Matrix<float> dist_view(dists.data(), count, static_cast<size_t>(knn));
    index.knnSearch(queries, index_view, dist_view, knn, search);
    for (size_t i = 0; i < count; ++i) {
      const int best = indices[i * knn];
      if (best < 0) continue;
      (*nearest)[begin + i] = static_cast<uint32_t>(best);
      (*distance1)[begin + i] = std::sqrt(std::max(0.0f, dists[i * knn]));
      if (distance2 != nullptr && knn > 1 && indices[i * knn + 1] >= 0) {
        (*distance2)[begin + i] = std::sqrt(std::max(0.0f, dists[i * knn + 1]));
      }
    }
  });
}

ForwardResult KdForest(const FeatureSet& query, const FeatureSet& db, bool want_reverse, const MatchOptions& options) {
  ForwardResult result;
  KdForestSearch(query, db, 2, options, &result.nearest, &result.distance1, &result.distance2);
  if (want_reverse) {
    std::vector<float> unused;
    KdForestSearch(db, query, 1, options, &result.reverse, &unused, nullptr);
  }
  return result;
}

Status ValidateSet(const FeatureSet& set, const char* name) {
  if (set.descriptors.size() != set.keypoints.size() * kDim) {
    return Fail(ErrorCode::kInvalidArgument, std::string(name) + " features: " + std::to_string(set.descriptors.size()) +
                                                 " descriptor values for " + std::to_string(set.keypoints.size()) +
                                                 " keypoints (expected 128 per keypoint)");
  }
  if (set.size() >= kNone) {
    return Fail(ErrorCode::kInvalidArgument, std::string(name) + " features: too many keypoints for 32-bit indices");
  }
  for (const float v : set.descriptors) {
    if (!std::isfinite(v)) return Fail(ErrorCode::kInvalidArgument, std::string(name) + " features: a descriptor value is not finite");
  }
  return Ok();
}

}  // namespace

std::optional<std::string> MatchOptions::Check() const {
  if (method != Method::kBruteForce && method != Method::kKdForest) return "method: unknown matching method";
  if (kd_trees < 1 || kd_trees > 64) return "kd_trees must be in [1, 64], got " + std::to_string(kd_trees);
  if (kd_checks < 1 || kd_checks > (1 << 20)) return "kd_checks must be in [1, 1048576], got " + std::to_string(kd_checks);
  if (!(ratio > 0.0f && ratio <= 1.0f)) return "ratio must be in (0, 1], got " + std::to_string(ratio);
  if (num_threads < 0) return "num_threads must be >= 0 (0 = all hardware threads), got " + std::to_string(num_threads);
  return std::nullopt;
}

std::vector<Match> EnforceOneToOne(std::span<const Match> matches) {
  std::vector<Match> sorted(matches.begin(), matches.end());
  std::sort(sorted.begin(), sorted.end(), [](const Match& a, const Match& b) {
    if (a.distance != b.distance) return a.distance < b.distance;
    if (a.query_index != b.query_index) return a.query_index < b.query_index;
    return a.db_index < b.db_index;
  });
  uint32_t max_query = 0, max_db = 0;
  for (const Match& m : sorted) {
    max_query = std::max(max_query, m.query_index);
    max_db = std::max(max_db, m.db_index);
  }
  std::vector<bool> query_used(sorted.empty() ? 0 : size_t{max_query} + 1, false);
  std::vector<bool> db_used(sorted.empty() ? 0 : size_t{max_db} + 1, false);
  std::vector<Match> kept;
  kept.reserve(sorted.size());
  for (const Match& m : sorted) {
    if (query_used[m.query_index] || db_used[m.db_index]) continue;
    query_used[m.query_index] = true;
    db_used[m.db_index] = true;
    kept.push_back(m);
  }
  std::sort(kept.begin(), kept.end(), [](const Match& a, const Match& b) { return a.query_index < b.query_index; });
  return kept;
}

namespace internal {

bool HaveAvx2Kernel() {
#ifdef OXBOW_MATCH_AVX2
  return true;
#else
  return false;
#endif
}

Result<std::vector<Match>> MatchDescriptorsWithKernel(const FeatureSet& query, const FeatureSet& db,
                                                      const MatchOptions& options, DotKernel kernel) {
  if (auto problem = options.Check()) return Fail(ErrorCode::kInvalidArgument, "match options: " + *problem);
  if (auto status = ValidateSet(query, "query"); !status) return std::unexpected(status.error());
  if (auto status = ValidateSet(db, "db"); !status) return std::unexpected(status.error());
  if (query.kind != db.kind) {
    return Fail(ErrorCode::kInvalidArgument, std::string("cannot match ") + DescriptorKindName(query.kind) +
                                                 " descriptors against " + DescriptorKindName(db.kind) +
                                                 " descriptors: extract both with the same descriptor kind");
  }
  std::vector<Match> matches;
  if (query.size() == 0 || db.size() == 0) return matches;

  const ForwardResult found = options.method == MatchOptions::Method::kBruteForce
                                  ? BruteForce(query, db, options.mutual, options.num_threads, SelectKernel(kernel))
                                  : KdForest(query, db, options.mutual, options);
  const bool ratio_test = options.ratio < 1.0f;
  matches.reserve(query.size() / 4);
  for (size_t i = 0; i < query.size(); ++i) {
    const uint32_t j = found.nearest[i];
    if (j == kNone) continue;
    // No second neighbour (one db feature): the ratio test cannot vouch for the match.
    if (ratio_test && (std::isinf(found.distance2[i]) || !(found.distance1[i] < options.ratio * found.distance2[i]))) continue;
    if (options.mutual && found.reverse[j] != i) continue;
    matches.push_back({static_cast<uint32_t>(i), j, found.distance1[i]});
  }
  if (options.one_to_one) matches = EnforceOneToOne(matches);
  return matches;
}

}  // namespace internal

Result<std::vector<Match>> MatchDescriptors(const FeatureSet& query, const FeatureSet& db, const MatchOptions& options) {
  return internal::MatchDescriptorsWithKernel(query, db, options, internal::DotKernel::kAuto);
}

}  // namespace oxbow::sift
