// Distance kernels of the vocabulary (internal to vocab/): squared L2 distances and nearest-neighbour
// scores between descriptors ("queries") and centroids ("words").
//
// Ranking score. For a query q and a word w the kernels compute score = |w|^2 - 2 <q, w>, which equals
// |q - w|^2 - |q|^2: the same order as the squared distance for one query, at one multiply-add per
// dimension. Exact distances for reporting are recomputed with SquaredL2.
//
// Determinism. Every (query, word) dot product is computed by one fixed formula whatever the tile it
// falls in: one fused multiply-add per dimension, in increasing dimension order, starting from 0. The
// vector paths (AVX2: 6 queries x 2 vectors of 8 words per register tile; AVX-512: 8 queries x 2
// vectors of 16) hold one pair per lane, so they and the scalar path (std::fma) give bit-identical scores, and
// a query's nearest word does not depend on which other queries share its batch, on the thread count,
// or on the instruction set the library was compiled for.
//
// Thread safety: pure functions.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "sift/base/cpu.h"

// The AVX2+FMA kernels (OXBOW_AVX2) and the AVX-512 ones (OXBOW_AVX512): compiled for this CPU, or by
// function attribute and taken where Avx2FmaAvailable() or Avx512Available() (sift/base/cpu.h).
#ifdef OXBOW_AVX2
#include <immintrin.h>
// Register tiles must be unrolled completely, or the compiler keeps the accumulators in memory.
#define OXBOW_UNROLL _Pragma("GCC unroll 16")
#endif

namespace oxbow::vocab::internal {

// Dot product with 8 partial sums (lane l holds dimensions l, l+8, l+16, ...) reduced as
// ((s0+s1)+(s2+s3)) + ((s4+s5)+(s6+s7)), scalar (any dim >= 1): the words' squared norms.
inline float DotScalar(const float* a, const float* b, int dim) {
  float lane[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  for (int i = 0; i < dim; ++i) lane[i & 7] = std::fma(a[i], b[i], lane[i & 7]);
  return ((lane[0] + lane[1]) + (lane[2] + lane[3])) + ((lane[4] + lane[5]) + (lane[6] + lane[7]));
}

// Squared L2 distance |a - b|^2 (exact reporting; 8 lanes, same reduction order).
inline float SquaredL2Scalar(const float* a, const float* b, int dim) {
  float lane[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  for (int i = 0; i < dim; ++i) {
    const float d = a[i] - b[i];
    lane[i & 7] = std::fma(d, d, lane[i & 7]);
  }
  return ((lane[0] + lane[1]) + (lane[2] + lane[3])) + ((lane[4] + lane[5]) + (lane[6] + lane[7]));
}

#ifdef OXBOW_AVX2
OXBOW_AVX2_TARGET inline float HorizontalSum(__m256 v) {
  const __m256 h = _mm256_hadd_ps(v, v);
  const __m256 hh = _mm256_hadd_ps(h, h);  // (v0+v1)+(v2+v3) | (v4+v5)+(v6+v7)
  return _mm_cvtss_f32(_mm_add_ss(_mm256_castps256_ps128(hh), _mm256_extractf128_ps(hh, 1)));
}

OXBOW_AVX2_TARGET inline float SquaredL2Avx2(const float* a, const float* b, int dim) {
  __m256 acc = _mm256_setzero_ps();
  for (int i = 0; i < dim; i += 8) {
    const __m256 d = _mm256_sub_ps(_mm256_loadu_ps(a + i), _mm256_loadu_ps(b + i));
    acc = _mm256_fmadd_ps(d, d, acc);
  }
  return HorizontalSum(acc);
}
#endif

inline float SquaredL2(const float* a, const float* b, int dim) {
#ifdef OXBOW_AVX2
  if (dim % 8 == 0 && Avx2FmaAvailable()) return SquaredL2Avx2(a, b, dim);
#endif
  return SquaredL2Scalar(a, b, dim);
}

// Word panels. The score kernels read the words in panels of kPanelWidth consecutive words stored
// dimension-major: panel p holds, for d = 0..dim-1, the d-th value of its kPanelWidth words side by
// side, so one register load gives one dimension of all of them and a query's value is broadcast
// against it (an outer product per dimension, as a GEMM micro-kernel does: no horizontal sums, and a
// panel's scores come out together, to be compared with the queries' current k-th best at once). A
// last panel of fewer words is padded with zero values and +inf norms, and the kernels never report
// padded lanes.
// Where AVX-512 kernels are compiled in (every x86-64 build with AVX2), panels are 16 words wide, one
// AVX-512 register, which the AVX2 kernel reads as two halves; elsewhere 8.
#ifdef OXBOW_AVX512
inline constexpr size_t kPanelWidth = 16;
#else
inline constexpr size_t kPanelWidth = 8;
#endif

inline size_t NumPanels(size_t num_words) { return (num_words + kPanelWidth - 1) / kPanelWidth; }

// Writes the panels of `rows` (num_words x dim, row-major) with squared norms `norms` to `panels`
// (NumPanels(num_words) * dim * kPanelWidth floats) and `panel_norms` (NumPanels(num_words) *
// kPanelWidth floats).
inline void MakePanels(const float* rows, const float* norms, size_t num_words, int dim, float* panels,
                       float* panel_norms) {
  const size_t stride = static_cast<size_t>(dim) * kPanelWidth;
  for (size_t p = 0; p < NumPanels(num_words); ++p) {
    for (size_t j = 0; j < kPanelWidth; ++j) {
      const size_t w = p * kPanelWidth + j;
      panel_norms[p * kPanelWidth + j] = w < num_words ? norms[w] : INFINITY;
    }
    for (int d = 0; d < dim; ++d) {
      float* out = panels + p * stride + static_cast<size_t>(d) * kPanelWidth;
      for (size_t j = 0; j < kPanelWidth; ++j) {
        const size_t w = p * kPanelWidth + j;
        out[j] = w < num_words ? rows[w * dim + d] : 0.0f;
      }
    }
  }
}

// Calls sink(query_index, word_index, score) for every pair of the queries (num_queries x dim,
// row-major) and the words [0..num_words) of `panels` whose score is <= bound(query_index), and for no
// other pair; score = |w|^2 - 2 <q, w>. `bound` is read before each panel of a query, so a sink that
// lowers it (a k-best list) sees fewer calls. The order of the calls is unspecified; each pair is
// reported at most once. The dot product is one fused multiply-add per dimension in increasing
// dimension order from 0, in both paths.
template <typename Bound, typename Sink>
inline void ScorePanelsScalar(const float* queries, size_t num_queries, const float* panels,
                              const float* panel_norms, size_t num_words, int dim, Bound& bound, Sink& sink) {
  const size_t stride = static_cast<size_t>(dim) * kPanelWidth;
  for (size_t i = 0; i < num_queries; ++i) {
    const float* query = queries + i * dim;
    for (size_t w = 0; w < num_words; ++w) {
      const float* panel = panels + (w / kPanelWidth) * stride + w % kPanelWidth;
      float dot = 0;
      for (int d = 0; d < dim; ++d) dot = std::fma(query[d], panel[static_cast<size_t>(d) * kPanelWidth], dot);
      const float score = panel_norms[w] - (dot + dot);
      if (score <= bound(i)) sink(i, w, score);
    }
  }
}

#ifdef OXBOW_AVX512
// 16 words' lanes in one AVX-512 register (a whole panel): the operations the tile below needs.
struct Lanes16 {
  static constexpr size_t kLanes = 16;
  using V = __m512;
  OXBOW_AVX512_TARGET static V Zero() { return _mm512_setzero_ps(); }
  OXBOW_AVX512_TARGET static V Load(const float* p) { return _mm512_loadu_ps(p); }
  OXBOW_AVX512_TARGET static V Broadcast(const float* p) { return _mm512_set1_ps(*p); }
  OXBOW_AVX512_TARGET static V Fma(V a, V b, V c) { return _mm512_fmadd_ps(a, b, c); }
  OXBOW_AVX512_TARGET static V Score(V norm, V dot) { return _mm512_sub_ps(norm, _mm512_add_ps(dot, dot)); }
  OXBOW_AVX512_TARGET static unsigned AtMost(V v, float bound) {
    return static_cast<unsigned>(_mm512_cmp_ps_mask(v, _mm512_set1_ps(bound), _CMP_LE_OQ));
  }
  OXBOW_AVX512_TARGET static void Store(float* out, V v) { _mm512_storeu_ps(out, v); }
};
#endif

#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
// 8 words' lanes in one AVX2 register (half a 16-word panel, or a whole 8-word one).
struct Lanes8 {
  static constexpr size_t kLanes = 8;
  using V = __m256;
  OXBOW_AVX2_TARGET static V Zero() { return _mm256_setzero_ps(); }
  OXBOW_AVX2_TARGET static V Load(const float* p) { return _mm256_loadu_ps(p); }
  OXBOW_AVX2_TARGET static V Broadcast(const float* p) { return _mm256_broadcast_ss(p); }
  OXBOW_AVX2_TARGET static V Fma(V a, V b, V c) { return _mm256_fmadd_ps(a, b, c); }
  OXBOW_AVX2_TARGET static V Score(V norm, V dot) { return _mm256_sub_ps(norm, _mm256_add_ps(dot, dot)); }
  OXBOW_AVX2_TARGET static unsigned AtMost(V v, float bound) {
    return static_cast<unsigned>(_mm256_movemask_ps(_mm256_cmp_ps(v, _mm256_set1_ps(bound), _CMP_LE_OQ)));
  }
  OXBOW_AVX2_TARGET static void Store(float* out, V v) { _mm256_storeu_ps(out, v); }
};
#endif

#ifdef OXBOW_AVX2
// The register tiles below are written once for both lane types. They carry no target attribute of
// their own: they are always inlined into ScorePanelsWith<Lanes>'s entry points (ScorePanelsAvx512,
// ScorePanelsAvx2), which have the lanes' target, so each instantiation is compiled for its own
// instructions. (GCC warns that a vector passed between the tile and the lanes' functions has no ABI
// without AVX-512; they never call each other as functions.)
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

// QN queries against NV consecutive vectors of L::kLanes words from word `first` (a multiple of
// L::kLanes; a register tile: QN x NV accumulators). A vector is a panel or a part of one.
template <typename L, int QN, int NV, typename Bound, typename Sink>
[[gnu::always_inline]] inline void ScorePanelTile(const float* queries, size_t qi, const float* panels,
                                                  const float* panel_norms, size_t first, size_t num_words, int dim,
                                                  Bound& bound, Sink& sink) {
  static_assert(kPanelWidth % L::kLanes == 0);
  const size_t stride = static_cast<size_t>(dim) * kPanelWidth;
  typename L::V acc[QN][NV];
  OXBOW_UNROLL for (int a = 0; a < QN; ++a)
    OXBOW_UNROLL for (int b = 0; b < NV; ++b) acc[a][b] = L::Zero();
  const float* q = queries + qi * static_cast<size_t>(dim);
  const float* w[NV];
  OXBOW_UNROLL for (int b = 0; b < NV; ++b) {
    const size_t word = first + static_cast<size_t>(b) * L::kLanes;
    w[b] = panels + (word / kPanelWidth) * stride + word % kPanelWidth;
  }
  _Pragma("GCC unroll 4") for (int d = 0; d < dim; ++d) {
    typename L::V wv[NV];
    OXBOW_UNROLL for (int b = 0; b < NV; ++b) wv[b] = L::Load(w[b] + static_cast<size_t>(d) * kPanelWidth);
    OXBOW_UNROLL for (int a = 0; a < QN; ++a) {
      const typename L::V qv = L::Broadcast(q + static_cast<size_t>(a) * dim + d);
      OXBOW_UNROLL for (int b = 0; b < NV; ++b) acc[a][b] = L::Fma(qv, wv[b], acc[a][b]);
    }
  }
  OXBOW_UNROLL for (int b = 0; b < NV; ++b) {
    const size_t word = first + static_cast<size_t>(b) * L::kLanes;
    const size_t lanes = std::min(L::kLanes, num_words - word);  // the rest are padding
    const unsigned valid = (1u << lanes) - 1u;
    const typename L::V norm = L::Load(panel_norms + word);
    OXBOW_UNROLL for (int a = 0; a < QN; ++a) {
      const typename L::V score = L::Score(norm, acc[a][b]);
      unsigned mask = L::AtMost(score, bound(qi + a)) & valid;
      if (mask == 0) continue;
      float out[L::kLanes];
      L::Store(out, score);
      for (; mask != 0; mask &= mask - 1) {
        const int j = __builtin_ctz(mask);
        sink(qi + a, word + static_cast<size_t>(j), out[j]);
      }
    }
  }
}

// QN queries against all the words: tiles of two vectors, the last of one vector where the words end
// within it (every vector holds at least one word, so the AVX2 kernel skips the padding half of a last
// panel of at most 8 words).
template <typename L, int QN, typename Bound, typename Sink>
[[gnu::always_inline]] inline void ScorePanelRow(const float* queries, size_t qi, const float* panels,
                                                 const float* panel_norms, size_t num_words, int dim, Bound& bound,
                                                 Sink& sink) {
  const size_t end = (num_words + L::kLanes - 1) / L::kLanes * L::kLanes;
  size_t first = 0;
  for (; first + 2 * L::kLanes <= end; first += 2 * L::kLanes)
    ScorePanelTile<L, QN, 2>(queries, qi, panels, panel_norms, first, num_words, dim, bound, sink);
  if (first < end) ScorePanelTile<L, QN, 1>(queries, qi, panels, panel_norms, first, num_words, dim, bound, sink);
}

// Rows of kRows queries (AVX-512: 8 queries x 2 vectors, 16 accumulators of the 32 registers; AVX2:
// 6 x 2, 12 accumulators, 2 word vectors and a broadcast of the 16), then the remaining queries.
template <typename L, int kRows, typename Bound, typename Sink>
[[gnu::always_inline]] inline void ScorePanelsWith(const float* queries, size_t num_queries, const float* panels,
                                                   const float* panel_norms, size_t num_words, int dim, Bound& bound,
                                                   Sink& sink) {
  static_assert(kRows <= 8);
  size_t i = 0;
  for (; i + kRows <= num_queries; i += kRows)
    ScorePanelRow<L, kRows>(queries, i, panels, panel_norms, num_words, dim, bound, sink);
  switch (num_queries - i) {
    case 7: ScorePanelRow<L, 7>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    case 6: ScorePanelRow<L, 6>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    case 5: ScorePanelRow<L, 5>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    case 4: ScorePanelRow<L, 4>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    case 3: ScorePanelRow<L, 3>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    case 2: ScorePanelRow<L, 2>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    case 1: ScorePanelRow<L, 1>(queries, i, panels, panel_norms, num_words, dim, bound, sink); break;
    default: break;
  }
}
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
#endif

#ifdef OXBOW_AVX512
template <typename Bound, typename Sink>
OXBOW_AVX512_TARGET void ScorePanelsAvx512(const float* queries, size_t num_queries, const float* panels,
                                           const float* panel_norms, size_t num_words, int dim, Bound& bound, Sink& sink) {
  ScorePanelsWith<Lanes16, 8>(queries, num_queries, panels, panel_norms, num_words, dim, bound, sink);
}
#endif

#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
template <typename Bound, typename Sink>
OXBOW_AVX2_TARGET void ScorePanelsAvx2(const float* queries, size_t num_queries, const float* panels,
                                       const float* panel_norms, size_t num_words, int dim, Bound& bound, Sink& sink) {
  ScorePanelsWith<Lanes8, 6>(queries, num_queries, panels, panel_norms, num_words, dim, bound, sink);
}
#endif

// ScorePanelsScalar's contract, on the vector path where there is one (bit-identical scores): AVX-512
// where Avx512Available(), else AVX2 where Avx2FmaAvailable() (sift/base/cpu.h).
template <typename Bound, typename Sink>
inline void ScorePanels(const float* queries, size_t num_queries, const float* panels, const float* panel_norms,
                        size_t num_words, int dim, Bound& bound, Sink& sink) {
#ifdef OXBOW_AVX512
  if (Avx512Available()) {
    ScorePanelsAvx512(queries, num_queries, panels, panel_norms, num_words, dim, bound, sink);
    return;
  }
#endif
#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
  if (Avx2FmaAvailable()) {
    ScorePanelsAvx2(queries, num_queries, panels, panel_norms, num_words, dim, bound, sink);
    return;
  }
#endif
  ScorePanelsScalar(queries, num_queries, panels, panel_norms, num_words, dim, bound, sink);
}

// Squared L2 norms of n rows (same 8-lane formula as DotScalar(row, row)).
inline void RowSquaredNorms(const float* rows, size_t n, int dim, float* out) {
  for (size_t i = 0; i < n; ++i) {
    const float* r = rows + i * static_cast<size_t>(dim);
    out[i] = DotScalar(r, r, dim);
  }
}

}  // namespace oxbow::vocab::internal
