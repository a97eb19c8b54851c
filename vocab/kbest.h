// k-best lists of the vocabulary's searches (internal to vocab/): for each query the k best (score, row)
// pairs, ascending by score, ties broken by the smaller row, in two arrays of k slots; an unfilled slot
// holds score +inf and a row that no word has.
//
// Insertion. A list is filled by scanning the words in an order unrelated to their scores, so about
// k + k ln(n / k) of n scanned words enter it (a 16-best list over 1265 coarse centroids: about 86). A
// scalar insertion shifts the entries after the new one one by one, with a loop whose exit the branch
// predictor cannot guess; for lists of 8 and 16 slots the AVX-512 insertions below compare the new pair
// with all entries at once and shift them with one permutation. Every insertion gives the same list,
// entry for entry, as InsertKBest.
#pragma once

#include <cstddef>
#include <cstdint>

#include "sift/base/cpu.h"

#ifdef OXBOW_AVX512
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

// Calls body(insert), where insert(rows, scores, row, score) inserts into a list of k slots: an AVX-512
// insertion for k = 8 and 16 where Avx512Available(), InsertKBest otherwise (the same lists).
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
  body([k](uint32_t* rows, float* scores, uint32_t row, float score) { InsertKBest(rows, scores, k, row, score); });
}

}  // namespace oxbow::vocab::internal
