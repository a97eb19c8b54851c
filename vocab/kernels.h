// Distance kernels of the vocabulary (internal to vocab/): squared L2 distances and nearest-neighbour
// scores between descriptors ("queries") and centroids ("words").
//
// Ranking score. For a query q and a word w the kernels compute score = |w|^2 - 2 <q, w>, which equals
// |q - w|^2 - |q|^2: the same order as the squared distance for one query, at one multiply-add per
// dimension. Exact distances for reporting are recomputed with SquaredL2.
//
// Determinism. Every (query, word) dot product is computed by one fixed formula whatever the tile it
// falls in: 8 partial sums (lane l holds dimensions l, l+8, l+16, ...) accumulated with fused
// multiply-adds in increasing dimension order, then reduced as ((s0+s1)+(s2+s3)) + ((s4+s5)+(s6+s7))
// (the order of a horizontal-add tree, which reduces four pairs at once in the vector path).
// The AVX2 path (8-lane registers, 4 queries x 3 words per register tile) and the scalar path
// (std::fma) therefore give bit-identical scores, and a query's nearest word does not depend on which
// other queries share its batch or on the thread count.
//
// Thread safety: pure functions.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define OXBOW_VOCAB_AVX2 1
#endif

namespace oxbow::vocab::internal {

// Dot product by the fixed 8-lane formula above, scalar (any dim >= 1).
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

#ifdef OXBOW_VOCAB_AVX2
// Four 8-lane sums at once: lane i of the result is ((x0+x1)+(x2+x3)) + ((x4+x5)+(x6+x7)) of input i.
inline __m128 HorizontalSum4(__m256 a, __m256 b, __m256 c, __m256 d) {
  const __m256 ab = _mm256_hadd_ps(a, b);     // a01 a23 b01 b23 | a45 a67 b45 b67
  const __m256 cd = _mm256_hadd_ps(c, d);
  const __m256 abcd = _mm256_hadd_ps(ab, cd);  // a0123 b0123 c0123 d0123 | a4567 b4567 c4567 d4567
  return _mm_add_ps(_mm256_castps256_ps128(abcd), _mm256_extractf128_ps(abcd, 1));
}

inline float HorizontalSum(__m256 v) {
  const __m256 h = _mm256_hadd_ps(v, v);
  const __m256 hh = _mm256_hadd_ps(h, h);  // (v0+v1)+(v2+v3) | (v4+v5)+(v6+v7)
  return _mm_cvtss_f32(_mm_add_ss(_mm256_castps256_ps128(hh), _mm256_extractf128_ps(hh, 1)));
}

inline float SquaredL2Avx2(const float* a, const float* b, int dim) {
  __m256 acc = _mm256_setzero_ps();
  for (int i = 0; i < dim; i += 8) {
    const __m256 d = _mm256_sub_ps(_mm256_loadu_ps(a + i), _mm256_loadu_ps(b + i));
    acc = _mm256_fmadd_ps(d, d, acc);
  }
  return HorizontalSum(acc);
}
#endif

// True when the vector path handles this dimension (AVX2+FMA compiled in and dim % 8 == 0).
inline bool VectorPathAvailable(int dim) {
#ifdef OXBOW_VOCAB_AVX2
  return dim % 8 == 0;
#else
  (void)dim;
  return false;
#endif
}

inline float SquaredL2(const float* a, const float* b, int dim) {
#ifdef OXBOW_VOCAB_AVX2
  if (dim % 8 == 0) return SquaredL2Avx2(a, b, dim);
#endif
  return SquaredL2Scalar(a, b, dim);
}

#ifdef OXBOW_VOCAB_AVX2
// Scores of QN queries against WN consecutive words (register tile); dim % 8 == 0.
template <int QN, int WN, typename Sink>
inline void ScoreTileAvx2(const float* const* queries, size_t qi, const float* words, const float* norms, size_t wj,
                          int dim, Sink& sink) {
  __m256 acc[QN][WN];
  for (int a = 0; a < QN; ++a)
    for (int b = 0; b < WN; ++b) acc[a][b] = _mm256_setzero_ps();
  const float* w[WN];
  for (int b = 0; b < WN; ++b) w[b] = words + (wj + b) * static_cast<size_t>(dim);
  const float* q[QN];
  for (int a = 0; a < QN; ++a) q[a] = queries[qi + a];
  for (int i = 0; i < dim; i += 8) {
    __m256 wv[WN];
    for (int b = 0; b < WN; ++b) wv[b] = _mm256_loadu_ps(w[b] + i);
    for (int a = 0; a < QN; ++a) {
      const __m256 qv = _mm256_loadu_ps(q[a] + i);
      for (int b = 0; b < WN; ++b) acc[a][b] = _mm256_fmadd_ps(qv, wv[b], acc[a][b]);
    }
  }
  const __m256 zero = _mm256_setzero_ps();
  for (int b = 0; b < WN; ++b) {
    const __m128 dots = HorizontalSum4(acc[0][b], QN > 1 ? acc[QN > 1 ? 1 : 0][b] : zero,
                                       QN > 2 ? acc[QN > 2 ? 2 : 0][b] : zero, QN > 3 ? acc[QN > 3 ? 3 : 0][b] : zero);
    const __m128 scores = _mm_sub_ps(_mm_set1_ps(norms[wj + b]), _mm_add_ps(dots, dots));
    alignas(16) float out[4];
    _mm_store_ps(out, scores);
    for (int a = 0; a < QN; ++a) sink(qi + a, wj + b, out[a]);
  }
}

template <int QN, typename Sink>
inline void ScoreRowAvx2(const float* const* queries, size_t qi, const float* words, const float* norms,
                         size_t num_words, int dim, Sink& sink) {
  size_t j = 0;
  for (; j + 3 <= num_words; j += 3) ScoreTileAvx2<QN, 3>(queries, qi, words, norms, j, dim, sink);
  if (num_words - j == 2) ScoreTileAvx2<QN, 2>(queries, qi, words, norms, j, dim, sink);
  if (num_words - j == 1) ScoreTileAvx2<QN, 1>(queries, qi, words, norms, j, dim, sink);
}
#endif

// Calls sink(query_index, word_index, score) for every pair of queries[0..num_queries) and the rows
// words[0..num_words) (contiguous, num_words x dim) with their squared norms `norms`; score = |w|^2 -
// 2 <q, w>. The order of the calls is unspecified; each pair is scored exactly once.
template <typename Sink>
inline void ScoreBlockScalar(const float* const* queries, size_t num_queries, const float* words, const float* norms,
                             size_t num_words, int dim, Sink& sink) {
  for (size_t i = 0; i < num_queries; ++i)
    for (size_t j = 0; j < num_words; ++j)
      sink(i, j, norms[j] - 2.0f * DotScalar(queries[i], words + j * static_cast<size_t>(dim), dim));
}

template <typename Sink>
inline void ScoreBlock(const float* const* queries, size_t num_queries, const float* words, const float* norms,
                       size_t num_words, int dim, Sink& sink) {
#ifdef OXBOW_VOCAB_AVX2
  if (dim % 8 == 0) {
    size_t i = 0;
    for (; i + 4 <= num_queries; i += 4) ScoreRowAvx2<4>(queries, i, words, norms, num_words, dim, sink);
    switch (num_queries - i) {
      case 3: ScoreRowAvx2<3>(queries, i, words, norms, num_words, dim, sink); break;
      case 2: ScoreRowAvx2<2>(queries, i, words, norms, num_words, dim, sink); break;
      case 1: ScoreRowAvx2<1>(queries, i, words, norms, num_words, dim, sink); break;
      default: break;
    }
    return;
  }
#endif
  ScoreBlockScalar(queries, num_queries, words, norms, num_words, dim, sink);
}

// Squared L2 norms of n rows (same 8-lane formula as DotScalar(row, row)).
inline void RowSquaredNorms(const float* rows, size_t n, int dim, float* out) {
  for (size_t i = 0; i < n; ++i) {
    const float* r = rows + i * static_cast<size_t>(dim);
    out[i] = DotScalar(r, r, dim);
  }
}

}  // namespace oxbow::vocab::internal
