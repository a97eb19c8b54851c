// k-best lists of the vocabulary's searches (internal to vocab/): for each query the k best (score, row)
// pairs, ascending by score, ties broken by the smaller row, in two arrays of k slots; an unfilled slot
// holds score +inf and a row that no word has.
//
// Insertion. A list is filled by scanning the words in an order unrelated to their scores, so about
// k + k ln(n / k) of n scanned words enter it (a 16-best list over 1265 coarse centroids: about 86). A
// scalar insertion shifts the entries after the new one one by one, with a loop whose exit the branch
// predictor cannot guess; for lists of 8 and 16 slots the vector insertions below (AVX-512, and AVX2 for
// the CPUs without it) compare the new pair with all entries at once and shift them with one permutation.
// Every insertion gives the same list, entry for entry, as InsertKBest.
#pragma once

#include <bit>
#include <cstddef>
#include <cstdint>

#include "sift/base/cpu.h"

#ifdef OXBOW_AVX2
#include <immintrin.h>
#endif

namespace oxbow::vocab::internal {

// Inserts (score, row) into the k-slot list `rows` / `scores` if it ranks before the last entry. The
// list must be sorted; score must not be NaN (the score kernels never report one).
inline void InsertKBest(uint32_t* rows, float* scores, int k, uint32_t row, float score) {
  const int last = k - 1;
  if (score > scores[last] || (score == scores[last] && row >= rows[last])) return;
  int pos = last;
  while (pos > 0 && (score < scores[pos - 1] || (score == scores[pos - 1] && row < rows[pos - 1]))) {
    scores[pos] = scores[pos - 1];
    rows[pos] = rows[pos - 1];
    --pos;
  }
  scores[pos] = score;
  rows[pos] = row;
}

#ifdef OXBOW_AVX512
OXBOW_AVX512_BEGIN
// InsertKBest for k = 16: the lanes whose entries rank after the new pair move up one slot (the last
// entry drops out) and the first of them takes the new pair.
OXBOW_AVX512_TARGET inline void InsertKBest16(uint32_t* rows, float* scores, uint32_t row, float score) {
  const __m512 s = _mm512_loadu_ps(scores);
  const __m512i r = _mm512_loadu_si512(rows);
  const __m512 sv = _mm512_set1_ps(score);
  const __m512i rv = _mm512_set1_epi32(static_cast<int>(row));
  const auto after = static_cast<__mmask16>(
      _mm512_cmp_ps_mask(sv, s, _CMP_LT_OQ) |
      (_mm512_cmp_ps_mask(sv, s, _CMP_EQ_OQ) & _mm512_cmp_epu32_mask(rv, r, _MM_CMPINT_LT)));
  if (after == 0) return;
  const auto first = static_cast<__mmask16>(after & (~after + 1u));
  const __m512i up = _mm512_set_epi32(14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0, 0);  // lane i <- i - 1
  const __m512 s_out = _mm512_mask_blend_ps(first, _mm512_mask_blend_ps(after, s, _mm512_permutexvar_ps(up, s)), sv);
  const __m512i r_out =
      _mm512_mask_blend_epi32(first, _mm512_mask_blend_epi32(after, r, _mm512_permutexvar_epi32(up, r)), rv);
  _mm512_storeu_ps(scores, s_out);
  _mm512_storeu_si512(rows, r_out);
}

// InsertKBest for k = 8, on 8-lane registers.
OXBOW_AVX512_TARGET inline void InsertKBest8(uint32_t* rows, float* scores, uint32_t row, float score) {
  const __m256 s = _mm256_loadu_ps(scores);
  const __m256i r = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(rows));
  const __m256 sv = _mm256_set1_ps(score);
  const __m256i rv = _mm256_set1_epi32(static_cast<int>(row));
  const auto after = static_cast<__mmask8>(
      _mm256_cmp_ps_mask(sv, s, _CMP_LT_OQ) |
      (_mm256_cmp_ps_mask(sv, s, _CMP_EQ_OQ) & _mm256_cmp_epu32_mask(rv, r, _MM_CMPINT_LT)));
  if (after == 0) return;
  const auto first = static_cast<__mmask8>(after & (~after + 1u));
  const __m256i up = _mm256_set_epi32(6, 5, 4, 3, 2, 1, 0, 0);
  const __m256 s_out = _mm256_mask_blend_ps(first, _mm256_mask_blend_ps(after, s, _mm256_permutexvar_ps(up, s)), sv);
  const __m256i r_out =
      _mm256_mask_blend_epi32(first, _mm256_mask_blend_epi32(after, r, _mm256_permutexvar_epi32(up, r)), rv);
  _mm256_storeu_ps(scores, s_out);
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(rows), r_out);
}
OXBOW_AVX512_END
#endif

#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)  // a native AVX-512 build takes only the AVX-512 ones
// The AVX2 insertions, on halves of 8 slots. AVX2 has no unsigned compare and no mask registers: rows
// are compared as signed after flipping their top bit, and the lanes to move are a vector mask.
namespace kbest_avx2 {

// Lanes of the half (s, r) where the new pair (sv, rv) ranks before the entry: a smaller score, or an
// equal score and a smaller row.
OXBOW_AVX2_TARGET inline __m256 RanksBefore(__m256 s, __m256i r, __m256 sv, __m256i rv) {
  const __m256i top = _mm256_set1_epi32(static_cast<int>(0x80000000u));
  const __m256i row_less = _mm256_cmpgt_epi32(_mm256_xor_si256(r, top), _mm256_xor_si256(rv, top));
  return _mm256_or_ps(_mm256_cmp_ps(sv, s, _CMP_LT_OQ),
                      _mm256_and_ps(_mm256_cmp_ps(sv, s, _CMP_EQ_OQ), _mm256_castsi256_ps(row_less)));
}

// The half moved up one slot where `after` is set, lane 0 taking `carry` (the previous half's last
// entry), and the new pair in the lane `first`, counted from this half's lane 0.
OXBOW_AVX2_TARGET inline __m256 Shifted(__m256 x, __m256 carry, __m256 after, __m256 value, int first) {
  const __m256i up = _mm256_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6);  // lane i <- i - 1
  const __m256 moved = _mm256_blend_ps(_mm256_permutevar8x32_ps(x, up), carry, 0x01);
  const __m256 at_first = _mm256_castsi256_ps(
      _mm256_cmpeq_epi32(_mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), _mm256_set1_epi32(first)));
  return _mm256_blendv_ps(_mm256_blendv_ps(x, moved, after), value, at_first);
}

}  // namespace kbest_avx2

// InsertKBest for k = 8 on AVX2.
OXBOW_AVX2_TARGET inline void InsertKBest8Avx2(uint32_t* rows, float* scores, uint32_t row, float score) {
  using namespace kbest_avx2;
  const __m256 s = _mm256_loadu_ps(scores);
  const __m256 r = _mm256_loadu_ps(reinterpret_cast<const float*>(rows));
  const __m256 sv = _mm256_set1_ps(score);
  const __m256i rv = _mm256_set1_epi32(static_cast<int>(row));
  const __m256 after = RanksBefore(s, _mm256_castps_si256(r), sv, rv);
  const auto bits = static_cast<unsigned>(_mm256_movemask_ps(after));
  if (bits == 0) return;
  const int first = std::countr_zero(bits);
  _mm256_storeu_ps(scores, Shifted(s, s, after, sv, first));
  _mm256_storeu_ps(reinterpret_cast<float*>(rows), Shifted(r, r, after, _mm256_castsi256_ps(rv), first));
}

// InsertKBest for k = 16 on AVX2: slots 0-7 and 8-15, the last entry of the first half carried into the
// second.
OXBOW_AVX2_TARGET inline void InsertKBest16Avx2(uint32_t* rows, float* scores, uint32_t row, float score) {
  using namespace kbest_avx2;
  const __m256 s0 = _mm256_loadu_ps(scores), s1 = _mm256_loadu_ps(scores + 8);
  const __m256 r0 = _mm256_loadu_ps(reinterpret_cast<const float*>(rows));
  const __m256 r1 = _mm256_loadu_ps(reinterpret_cast<const float*>(rows + 8));
  const __m256 sv = _mm256_set1_ps(score);
  const __m256i rv = _mm256_set1_epi32(static_cast<int>(row));
  const __m256 after1 = RanksBefore(s1, _mm256_castps_si256(r1), sv, rv);
  const auto bits1 = static_cast<unsigned>(_mm256_movemask_ps(after1));
  if (bits1 == 0) return;  // the lanes to move are a suffix: none in the second half, none at all
  const __m256 after0 = RanksBefore(s0, _mm256_castps_si256(r0), sv, rv);
  const auto bits = static_cast<unsigned>(_mm256_movemask_ps(after0)) | (bits1 << 8);
  const int first = std::countr_zero(bits);
  const __m256i last = _mm256_set1_epi32(7);
  const __m256 rv_ps = _mm256_castsi256_ps(rv);
  _mm256_storeu_ps(scores + 8, Shifted(s1, _mm256_permutevar8x32_ps(s0, last), after1, sv, first - 8));
  _mm256_storeu_ps(scores, Shifted(s0, s0, after0, sv, first));
  _mm256_storeu_ps(reinterpret_cast<float*>(rows + 8), Shifted(r1, _mm256_permutevar8x32_ps(r0, last), after1, rv_ps, first - 8));
  _mm256_storeu_ps(reinterpret_cast<float*>(rows), Shifted(r0, r0, after0, rv_ps, first));
}
#endif

// Calls body(insert), where insert(rows, scores, row, score) inserts into a list of k slots: an AVX-512
// insertion for k = 8 and 16 where Avx512Available(), else an AVX2 one where Avx2FmaAvailable(), else
// InsertKBest (the same lists).
template <typename Body>
inline void WithKBestInsert(int k, Body&& body) {
#ifdef OXBOW_AVX512
  if (Avx512Available()) {
    if (k == 16) {
      body([](uint32_t* rows, float* scores, uint32_t row, float score) { InsertKBest16(rows, scores, row, score); });
      return;
    }
    if (k == 8) {
      body([](uint32_t* rows, float* scores, uint32_t row, float score) { InsertKBest8(rows, scores, row, score); });
      return;
    }
  }
#endif
#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
  if (Avx2FmaAvailable()) {
    if (k == 16) {
      body([](uint32_t* rows, float* scores, uint32_t row, float score) { InsertKBest16Avx2(rows, scores, row, score); });
      return;
    }
    if (k == 8) {
      body([](uint32_t* rows, float* scores, uint32_t row, float score) { InsertKBest8Avx2(rows, scores, row, score); });
      return;
    }
  }
#endif
  body([k](uint32_t* rows, float* scores, uint32_t row, float score) { InsertKBest(rows, scores, k, row, score); });
}

}  // namespace oxbow::vocab::internal
