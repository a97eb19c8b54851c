#include "sift/scale_space.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <new>
#include <utility>

#include <sys/mman.h>

#include "sift/base/error.h"
#include "sift/base/parallel.h"

#include "sift/base/cpu.h"
#ifdef OXBOW_AVX2
#include <immintrin.h>
#endif

namespace oxbow::sift::internal {

WorkerTeam::WorkerTeam(int num_threads) : num_threads_(num_threads) { OXBOW_CHECK(num_threads >= 1); }

void WorkerTeam::ParallelFor(size_t n, size_t grain, const std::function<void(size_t, size_t, int)>& fn) const {
  oxbow::ParallelFor(n, num_threads_, grain, fn);
}

void Plane::Free::operator()(float* p) const { std::free(p); }

Plane::Plane(int width, int height) { Reshape(width, height); }

void Plane::Reshape(int width, int height) {
  OXBOW_CHECK(width >= 0 && height >= 0);
  const size_t stride = (static_cast<size_t>(width) + 15) / 16 * 16;
  // One extra row of padding so vector loads that run past the last column stay inside the buffer.
  const size_t needed = std::max<size_t>(16, stride * (static_cast<size_t>(height) + 1));
  if (needed > capacity_ || !data_) {
    constexpr size_t kHuge = size_t{2} << 20;
    size_t bytes = needed * sizeof(float);
    const bool huge = bytes >= 2 * kHuge;
    const size_t alignment = huge ? kHuge : 64;
    bytes = (bytes + alignment - 1) / alignment * alignment;
    data_.reset();
    void* memory = std::aligned_alloc(alignment, bytes);
    if (memory == nullptr) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
    if (huge) ::madvise(memory, bytes, MADV_HUGEPAGE);  // advisory; failure is harmless
#endif
    data_.reset(static_cast<float*>(memory));
    capacity_ = bytes / sizeof(float);
  }
  width_ = width;
  height_ = height;
  stride_ = stride;
}

int Reflect101(int i, int n) {
  if (n == 1) return 0;
  const int period = 2 * (n - 1);
  i = ((i % period) + period) % period;
  return i < n ? i : period - i;
}

std::vector<float> GaussianHalfKernel(double sigma, double radius_sigmas) {
  const int ksize = static_cast<int>(std::lrint(2.0 * radius_sigmas * sigma + 1.0)) | 1;
  const int radius = ksize / 2;
  std::vector<double> w(static_cast<size_t>(radius) + 1);
  double sum = 0;
  for (int x = 0; x <= radius; ++x) {
    w[static_cast<size_t>(x)] = std::exp(-0.5 * x * x / (sigma * sigma));
    sum += x == 0 ? w[0] : 2 * w[static_cast<size_t>(x)];
  }
  std::vector<float> half(w.size());
  for (size_t i = 0; i < w.size(); ++i) half[i] = static_cast<float>(w[i] / sum);
  return half;
}

namespace {

// Vertical pass for `count` (1..kRowBlock) consecutive output rows: out[m][x] = sum_{i=0..2r}
// kernel[i] * rows[m + i][x], accumulated in order of i (the i = 0 term a product, then fused
// multiply-adds); rows[j] is source row y - r + j, kernel is the full kernel c_r..c_0..c_r.
// Four rows at a time the AVX2 path loads each source row once for all four (1 load per 4 FMAs
// instead of 2 loads per FMA): the 2r + 4 rows live in L2, not L1, so loads are the limit otherwise.

#ifdef OXBOW_AVX2
// VerticalPass's AVX2 path.
OXBOW_AVX2_TARGET void VerticalPassAvx2(const float* const* rows, const float* kernel, int r, int count, int width,
                                        float* const* out) {
  const int taps = 2 * r + 1;
  int x = 0;
  if (count == kRowBlock && taps > kRowBlock) {
    for (; x + 8 <= width; x += 8) {
      // Source row j contributes to output m with kernel[j - m] for 0 <= j - m < taps.
      __m256 a[kRowBlock];
      const __m256 k0 = _mm256_broadcast_ss(kernel);
#pragma GCC unroll 8
      for (int m = 0; m < kRowBlock; ++m) a[m] = _mm256_mul_ps(k0, _mm256_loadu_ps(rows[m] + x));
      auto add_row = [&](int j, int m_begin, int m_end) OXBOW_AVX2_TARGET {
        const __m256 v = _mm256_loadu_ps(rows[j] + x);
#pragma GCC unroll 8
        for (int m = 0; m < kRowBlock; ++m) {
          if (m < m_begin || m >= m_end) continue;
          a[m] = _mm256_fmadd_ps(_mm256_broadcast_ss(kernel + (j - m)), v, a[m]);
        }
      };
      for (int j = 1; j < kRowBlock; ++j) add_row(j, 0, j);  // outputs m < j
      for (int j = kRowBlock; j < taps; ++j) add_row(j, 0, kRowBlock);
      for (int j = taps; j < taps + kRowBlock - 1; ++j) add_row(j, j - taps + 1, kRowBlock);
#pragma GCC unroll 8
      for (int m = 0; m < kRowBlock; ++m) _mm256_storeu_ps(out[m] + x, a[m]);
    }
  }
  for (int m = 0; m < count; ++m) {
    int xm = x;
    for (; xm + 8 <= width; xm += 8) {
      __m256 acc = _mm256_mul_ps(_mm256_broadcast_ss(kernel), _mm256_loadu_ps(rows[m] + xm));
      for (int i = 1; i < taps; ++i) acc = _mm256_fmadd_ps(_mm256_broadcast_ss(kernel + i), _mm256_loadu_ps(rows[m + i] + xm), acc);
      _mm256_storeu_ps(out[m] + xm, acc);
    }
    for (; xm < width; ++xm) {
      float acc = kernel[0] * rows[m][xm];
      for (int i = 1; i < taps; ++i) acc = std::fma(kernel[i], rows[m + i][xm], acc);
      out[m][xm] = acc;
    }
  }
}
#endif

#ifdef OXBOW_AVX512
// VerticalPass's AVX-512 path: the AVX2 path's formula 16 lanes at a time, the last partial vector
// masked (masked lanes are neither loaded nor stored).
OXBOW_AVX512_TARGET void VerticalPassAvx512(const float* const* rows, const float* kernel, int r, int count, int width, float* const* out) {
  const int taps = 2 * r + 1;
  int x = 0;
  if (count == kRowBlock && taps > kRowBlock) {
    for (; x + 32 <= width; x += 32) {
      __m512 a0[kRowBlock], a1[kRowBlock];
      const __m512 k0 = _mm512_set1_ps(kernel[0]);
#pragma GCC unroll 8
      for (int m = 0; m < kRowBlock; ++m) {
        a0[m] = _mm512_mul_ps(k0, _mm512_loadu_ps(rows[m] + x));
        a1[m] = _mm512_mul_ps(k0, _mm512_loadu_ps(rows[m] + x + 16));
      }
      auto add_row = [&](int j, int m_begin, int m_end) OXBOW_AVX512_TARGET {
        const __m512 v0 = _mm512_loadu_ps(rows[j] + x), v1 = _mm512_loadu_ps(rows[j] + x + 16);
#pragma GCC unroll 8
        for (int m = 0; m < kRowBlock; ++m) {
          if (m < m_begin || m >= m_end) continue;
          const __m512 k = _mm512_set1_ps(kernel[j - m]);
          a0[m] = _mm512_fmadd_ps(k, v0, a0[m]);
          a1[m] = _mm512_fmadd_ps(k, v1, a1[m]);
        }
      };
      for (int j = 1; j < kRowBlock; ++j) add_row(j, 0, j);
      for (int j = kRowBlock; j < taps; ++j) add_row(j, 0, kRowBlock);
      for (int j = taps; j < taps + kRowBlock - 1; ++j) add_row(j, j - taps + 1, kRowBlock);
#pragma GCC unroll 8
      for (int m = 0; m < kRowBlock; ++m) {
        _mm512_storeu_ps(out[m] + x, a0[m]);
        _mm512_storeu_ps(out[m] + x + 16, a1[m]);
      }
    }
  }
  for (int m = 0; m < count; ++m) {
    for (int xm = x; xm < width; xm += 16) {
      const __mmask16 lanes = width - xm >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (width - xm)) - 1);
      __m512 acc = _mm512_mul_ps(_mm512_set1_ps(kernel[0]), _mm512_maskz_loadu_ps(lanes, rows[m] + xm));
      for (int i = 1; i < taps; ++i)
        acc = _mm512_fmadd_ps(_mm512_set1_ps(kernel[i]), _mm512_maskz_loadu_ps(lanes, rows[m + i] + xm), acc);
      _mm512_mask_storeu_ps(out[m] + xm, lanes, acc);
    }
  }
}
#endif

void VerticalPass(const float* const* rows, const float* kernel, int r, int count, int width, float* const* out, bool simd) {
#ifdef OXBOW_AVX512
  if (simd && Avx512Available()) {
    VerticalPassAvx512(rows, kernel, r, count, width, out);
    return;
  }
#endif
#ifdef OXBOW_AVX2
  if (simd) {
    VerticalPassAvx2(rows, kernel, r, count, width, out);
    return;
  }
#endif
  const int taps = 2 * r + 1;
  for (int m = 0; m < count; ++m)
    for (int xm = 0; xm < width; ++xm) {
      float acc = kernel[0] * rows[m][xm];
      for (int i = 1; i < taps; ++i) acc = std::fma(kernel[i], rows[m + i][xm], acc);
      out[m][xm] = acc;
    }
}

#ifdef OXBOW_AVX2
// HorizontalPass's AVX2 path for whole vectors of outputs; returns the first output it left.
OXBOW_AVX2_TARGET int HorizontalPassAvx2(const float* t, std::span<const float> c, int width, float* out) {
  const int r = static_cast<int>(c.size()) - 1;
  int x = 0;
  for (; x + 32 <= width; x += 32) {
    const __m256 c0 = _mm256_set1_ps(c[0]);
    __m256 a0 = _mm256_mul_ps(c0, _mm256_loadu_ps(t + x));
    __m256 a1 = _mm256_mul_ps(c0, _mm256_loadu_ps(t + x + 8));
    __m256 a2 = _mm256_mul_ps(c0, _mm256_loadu_ps(t + x + 16));
    __m256 a3 = _mm256_mul_ps(c0, _mm256_loadu_ps(t + x + 24));
    for (int k = 1; k <= r; ++k) {
      const __m256 ck = _mm256_set1_ps(c[static_cast<size_t>(k)]);
      const float* m = t + x - k;
      const float* p = t + x + k;
      a0 = _mm256_fmadd_ps(ck, _mm256_add_ps(_mm256_loadu_ps(m), _mm256_loadu_ps(p)), a0);
      a1 = _mm256_fmadd_ps(ck, _mm256_add_ps(_mm256_loadu_ps(m + 8), _mm256_loadu_ps(p + 8)), a1);
      a2 = _mm256_fmadd_ps(ck, _mm256_add_ps(_mm256_loadu_ps(m + 16), _mm256_loadu_ps(p + 16)), a2);
      a3 = _mm256_fmadd_ps(ck, _mm256_add_ps(_mm256_loadu_ps(m + 24), _mm256_loadu_ps(p + 24)), a3);
    }
    _mm256_storeu_ps(out + x, a0);
    _mm256_storeu_ps(out + x + 8, a1);
    _mm256_storeu_ps(out + x + 16, a2);
    _mm256_storeu_ps(out + x + 24, a3);
  }
  for (; x + 8 <= width; x += 8) {
    __m256 acc = _mm256_mul_ps(_mm256_set1_ps(c[0]), _mm256_loadu_ps(t + x));
    for (int k = 1; k <= r; ++k)
      acc = _mm256_fmadd_ps(_mm256_set1_ps(c[static_cast<size_t>(k)]),
                            _mm256_add_ps(_mm256_loadu_ps(t + x - k), _mm256_loadu_ps(t + x + k)), acc);
    _mm256_storeu_ps(out + x, acc);
  }
  return x;
}
#endif

#ifdef OXBOW_AVX512
// HorizontalPassAvx512 for a kernel of radius R < 16 on a 64-byte aligned row t (readable from t - 16
// to t + width + 80): each block of 64 outputs loads the six aligned vectors around it once and makes
// t[x - k ...] and t[x + k ...] by aligning pairs of them, instead of two unaligned loads per tap that
// each straddle two cache lines. The same sums and fused multiply-adds in the same order.
template <int R>
OXBOW_AVX512_TARGET int HorizontalPassAlignedAvx512(const float* t, const float* c, int width, float* out) {
  int x = 0;
  for (; x + 64 <= width; x += 64) {
    __m512 v[6];
#pragma GCC unroll 6
    for (int m = 0; m < 6; ++m) v[m] = _mm512_load_ps(t + x - 16 + 16 * m);
    const __m512 c0 = _mm512_set1_ps(c[0]);
    __m512 a[4];
#pragma GCC unroll 4
    for (int m = 0; m < 4; ++m) a[m] = _mm512_mul_ps(c0, v[m + 1]);
    [&]<int... K>(std::integer_sequence<int, K...>) OXBOW_AVX512_TARGET {
      (
          [&]() OXBOW_AVX512_TARGET {
            constexpr int k = K + 1;
            const __m512 ck = _mm512_set1_ps(c[k]);
#pragma GCC unroll 4
            for (int m = 0; m < 4; ++m) {
              // (The all-lanes masked form: GCC 12's unmasked one warns of its undefined pass-through.)
              const __m512i lo = _mm512_castps_si512(v[m]), mid = _mm512_castps_si512(v[m + 1]);
              const __m512i hi = _mm512_castps_si512(v[m + 2]);
              const __m512 left = _mm512_castsi512_ps(_mm512_mask_alignr_epi32(mid, 0xffff, mid, lo, 16 - k));
              const __m512 right = _mm512_castsi512_ps(_mm512_mask_alignr_epi32(mid, 0xffff, hi, mid, k));
              a[m] = _mm512_fmadd_ps(ck, _mm512_add_ps(left, right), a[m]);
            }
          }(),
          ...);
    }(std::make_integer_sequence<int, R>{});
#pragma GCC unroll 4
    for (int m = 0; m < 4; ++m) _mm512_storeu_ps(out + x + 16 * m, a[m]);
  }
  return x;
}

// HorizontalPass's AVX-512 path for whole vectors of outputs; returns the first output it left.
OXBOW_AVX512_TARGET int HorizontalPassAvx512(const float* t, std::span<const float> c, int width, float* out) {
  const int r = static_cast<int>(c.size()) - 1;
  int x = 0;
  if (reinterpret_cast<uintptr_t>(t) % 64 == 0) {
    switch (r) {
#define OXBOW_ALIGNED_CASE(R) \
  case R: x = HorizontalPassAlignedAvx512<R>(t, c.data(), width, out); break;
      OXBOW_ALIGNED_CASE(1) OXBOW_ALIGNED_CASE(2) OXBOW_ALIGNED_CASE(3) OXBOW_ALIGNED_CASE(4) OXBOW_ALIGNED_CASE(5)
      OXBOW_ALIGNED_CASE(6) OXBOW_ALIGNED_CASE(7) OXBOW_ALIGNED_CASE(8) OXBOW_ALIGNED_CASE(9) OXBOW_ALIGNED_CASE(10)
      OXBOW_ALIGNED_CASE(11) OXBOW_ALIGNED_CASE(12) OXBOW_ALIGNED_CASE(13) OXBOW_ALIGNED_CASE(14) OXBOW_ALIGNED_CASE(15)
#undef OXBOW_ALIGNED_CASE
      default: break;
    }
  }
  for (; x + 64 <= width; x += 64) {
    const __m512 c0 = _mm512_set1_ps(c[0]);
    __m512 a0 = _mm512_mul_ps(c0, _mm512_loadu_ps(t + x));
    __m512 a1 = _mm512_mul_ps(c0, _mm512_loadu_ps(t + x + 16));
    __m512 a2 = _mm512_mul_ps(c0, _mm512_loadu_ps(t + x + 32));
    __m512 a3 = _mm512_mul_ps(c0, _mm512_loadu_ps(t + x + 48));
    for (int k = 1; k <= r; ++k) {
      const __m512 ck = _mm512_set1_ps(c[static_cast<size_t>(k)]);
      const float* m = t + x - k;
      const float* p = t + x + k;
      a0 = _mm512_fmadd_ps(ck, _mm512_add_ps(_mm512_loadu_ps(m), _mm512_loadu_ps(p)), a0);
      a1 = _mm512_fmadd_ps(ck, _mm512_add_ps(_mm512_loadu_ps(m + 16), _mm512_loadu_ps(p + 16)), a1);
      a2 = _mm512_fmadd_ps(ck, _mm512_add_ps(_mm512_loadu_ps(m + 32), _mm512_loadu_ps(p + 32)), a2);
      a3 = _mm512_fmadd_ps(ck, _mm512_add_ps(_mm512_loadu_ps(m + 48), _mm512_loadu_ps(p + 48)), a3);
    }
    _mm512_storeu_ps(out + x, a0);
    _mm512_storeu_ps(out + x + 16, a1);
    _mm512_storeu_ps(out + x + 32, a2);
    _mm512_storeu_ps(out + x + 48, a3);
  }
  for (; x + 16 <= width; x += 16) {
    __m512 acc = _mm512_mul_ps(_mm512_set1_ps(c[0]), _mm512_loadu_ps(t + x));
    for (int k = 1; k <= r; ++k)
      acc = _mm512_fmadd_ps(_mm512_set1_ps(c[static_cast<size_t>(k)]),
                            _mm512_add_ps(_mm512_loadu_ps(t + x - k), _mm512_loadu_ps(t + x + k)), acc);
    _mm512_storeu_ps(out + x, acc);
  }
  return x;
}
#endif

// out[x] = c0 * t[x] + sum_k c_k * (t[x-k] + t[x+k]) for x in [0, width); t is padded by r on both sides.
void HorizontalPass(const float* t, std::span<const float> c, int width, float* out, bool simd) {
  const int r = static_cast<int>(c.size()) - 1;
  int x = 0;
#ifdef OXBOW_AVX512
  if (simd && Avx512Available()) x = HorizontalPassAvx512(t, c, width, out);
#endif
#ifdef OXBOW_AVX2
  if (simd) x += HorizontalPassAvx2(t + x, c, width - x, out + x);
#endif
  for (; x < width; ++x) {
    float acc = c[0] * t[x];
    for (int k = 1; k <= r; ++k) acc = std::fma(c[static_cast<size_t>(k)], t[x - k] + t[x + k], acc);
    out[x] = acc;
  }
}

size_t RowGrain(int height, int num_threads) {
  // A few chunks per thread for balance, but at least 8 rows so small octaves stay on one thread.
  return static_cast<size_t>(std::max(8, height / std::max(1, 4 * num_threads)));
}

}  // namespace

void GaussianBlur(const Plane& src, Plane* dst, std::span<const float> half_kernel, int num_threads, bool allow_simd) {
  WorkerTeam team(std::max(1, num_threads));
  GaussianBlur(src, dst, half_kernel, team, allow_simd);
}

namespace {

// Rows [y, y + count) (count <= kRowBlock) of the blur: the vertical pass into the padded rows t,
// their borders reflected, then the horizontal pass into dest_row(y + m). rows: room for 2 r + kRowBlock
// pointers.
template <typename SourceRow, typename DestRow>
void BlurBlock(const SourceRow& source_row, const DestRow& dest_row, int w, int h, std::span<const float> half_kernel,
               const float* kernel, int y, int count, float* const* t, const float** rows, bool simd) {
  const int r = static_cast<int>(half_kernel.size()) - 1;
  for (int j = 0; j < 2 * r + count; ++j) rows[j] = source_row(Reflect101(y - r + j, h));
  VerticalPass(rows, kernel, r, count, w, t, simd);
  for (int m = 0; m < count; ++m) {
    for (int i = 1; i <= r; ++i) {
      t[m][-i] = t[m][Reflect101(-i, w)];
      t[m][w - 1 + i] = t[m][Reflect101(w - 1 + i, w)];
    }
    HorizontalPass(t[m], half_kernel, w, dest_row(y + m), simd);
  }
}

// The padded rows of a block: 64-byte aligned at column 0, PaddedLead(r) floats before it (>= r, and
// >= 16 for the aligned horizontal pass's first block), and room after the last column for the pass's
// reads (r, or 80 past the last block of 64).
size_t PaddedLead(int r) { return (static_cast<size_t>(std::max(r, 16)) + 15) / 16 * 16; }
size_t PaddedPitch(int w, int r) {
  return PaddedLead(r) + (static_cast<size_t>(w) + 15) / 16 * 16 + (static_cast<size_t>(std::max(r, 80)) + 15) / 16 * 16;
}

}  // namespace

void BlurScratch::Prepare(int width, std::span<const float> half_kernel) {
  const int r = static_cast<int>(half_kernel.size()) - 1;
  const size_t pitch = PaddedPitch(width, r);
  if (padded.size() < kRowBlock * pitch + 16) padded.resize(kRowBlock * pitch + 16);
  float* base = padded.data();
  base += (64 - reinterpret_cast<uintptr_t>(base) % 64) % 64 / sizeof(float);  // floats are 4-byte aligned
  for (int m = 0; m < kRowBlock; ++m) t[m] = base + static_cast<size_t>(m) * pitch + PaddedLead(r);
  rows.resize(2 * static_cast<size_t>(r) + kRowBlock);
  kernel.resize(2 * static_cast<size_t>(r) + 1);
  for (int i = 0; i <= 2 * r; ++i) kernel[static_cast<size_t>(i)] = half_kernel[static_cast<size_t>(std::abs(i - r))];
}

void GaussianBlurRows(const Plane& src, Plane* dst, std::span<const float> half_kernel, int y, int count,
                      BlurScratch* scratch, bool allow_simd) {
  OXBOW_CHECK(dst != &src);
  GaussianBlurRows([&src](int i) { return src.row(i); }, src.width(), src.height(), dst, half_kernel, y, count, scratch,
                   allow_simd);
}

void GaussianBlurRows(const std::function<const float*(int)>& source_row, int width, int height, Plane* dst,
                      std::span<const float> half_kernel, int y, int count, BlurScratch* scratch, bool allow_simd) {
  allow_simd = allow_simd && Avx2FmaAvailable();
  OXBOW_CHECK(dst->width() == width && dst->height() == height);
  OXBOW_CHECK(count >= 1 && count <= kRowBlock && y >= 0 && y + count <= height);
  scratch->Prepare(width, half_kernel);
  BlurBlock(source_row, [dst](int i) { return dst->row(i); }, width, height, half_kernel, scratch->kernel.data(), y,
            count, scratch->t, scratch->rows.data(), allow_simd);
}

void GaussianBlurRows(const std::function<const float*(int)>& source_row, const std::function<float*(int)>& dest_row,
                      int width, int height, std::span<const float> half_kernel, int y, int count, BlurScratch* scratch,
                      bool allow_simd) {
  allow_simd = allow_simd && Avx2FmaAvailable();
  OXBOW_CHECK(count >= 1 && count <= kRowBlock && y >= 0 && y + count <= height);
  scratch->Prepare(width, half_kernel);
  BlurBlock(source_row, dest_row, width, height, half_kernel, scratch->kernel.data(), y, count, scratch->t,
            scratch->rows.data(), allow_simd);
}

void GaussianBlur(const Plane& src, Plane* dst, std::span<const float> half_kernel, WorkerTeam& team, bool allow_simd) {
  allow_simd = allow_simd && Avx2FmaAvailable();  // the passes below trust it
  const int num_threads = team.size();
  OXBOW_CHECK(!half_kernel.empty());
  OXBOW_CHECK(dst != &src);
  const int w = src.width(), h = src.height();
  if (dst->width() != w || dst->height() != h) dst->Reshape(w, h);
  if (w == 0 || h == 0) return;
  // Row chunks are multiples of kRowBlock so that a row's formula does not depend on the thread count
  // (it does not anyway: every output row is computed by the same sequence of operations).
  const size_t grain = (RowGrain(h, num_threads) + kRowBlock - 1) / kRowBlock * kRowBlock;
  team.ParallelFor(static_cast<size_t>(h), grain, [&](size_t y0, size_t y1, int) {
    BlurScratch scratch;
    scratch.Prepare(w, half_kernel);
    for (int y = static_cast<int>(y0); y < static_cast<int>(y1); y += kRowBlock) {
      const int count = std::min(kRowBlock, static_cast<int>(y1) - y);
      BlurBlock([&src](int i) { return src.row(i); }, [dst](int i) { return dst->row(i); }, w, h, half_kernel,
                scratch.kernel.data(), y, count, scratch.t, scratch.rows.data(), allow_simd);
    }
  });
}

namespace {

// Output columns 2x and 2x + 1 of Upsample2xRow from its vertical pass v.
[[gnu::always_inline]] inline void UpsampleColumns(const float* v, int w, int x, float* out) {
  const float centre = 0.75f * v[x];
  out[2 * x] = std::fma(0.25f, v[std::max(x - 1, 0)], centre);
  out[2 * x + 1] = std::fma(0.25f, v[std::min(x + 1, w - 1)], centre);
}

// Upsample2xRow's body. Every p * q + r in it is one fused multiply-add, on every path and in every
// build, so that a portable build enlarges the first octave exactly as a native one: inlined into a
// function compiled for FMA, std::fma is one instruction (and the loops vectorise); in a portable
// build's baseline copy, taken only on a CPU without FMA, it is libm's exact fma.
[[gnu::always_inline]] inline void Upsample2xRowBody(const float* src, int w, int h, size_t src_stride, int y, float* v,
                                                     float* out) {
  const int sy = y / 2;
  const int other = std::clamp(y % 2 == 0 ? sy - 1 : sy + 1, 0, h - 1);
  const float* a = src + static_cast<size_t>(sy) * src_stride;
  const float* b = src + static_cast<size_t>(other) * src_stride;
  for (int x = 0; x < w; ++x) v[x] = std::fma(0.75f, a[x], 0.25f * b[x]);
  UpsampleColumns(v, w, 0, out);
  int x = 1;
#ifdef OXBOW_AVX512_ALWAYS  // (under 1% of an extraction: not worth a run-time choice)
  // Columns x..x+15 from v[x-1..x+16], the even and odd outputs interleaved by two permutes.
  const __m512i lo = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
  const __m512i hi = _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
  const __m512 three_quarters = _mm512_set1_ps(0.75f), quarter = _mm512_set1_ps(0.25f);
  for (; x + 17 <= w; x += 16) {
    const __m512 centre = _mm512_mul_ps(three_quarters, _mm512_loadu_ps(v + x));
    const __m512 even = _mm512_fmadd_ps(quarter, _mm512_loadu_ps(v + x - 1), centre);
    const __m512 odd = _mm512_fmadd_ps(quarter, _mm512_loadu_ps(v + x + 1), centre);
    _mm512_storeu_ps(out + 2 * x, _mm512_permutex2var_ps(even, lo, odd));
    _mm512_storeu_ps(out + 2 * x + 16, _mm512_permutex2var_ps(even, hi, odd));
  }
#endif
  for (; x < w; ++x) UpsampleColumns(v, w, x, out);
}

#ifdef OXBOW_AVX2_DISPATCH
OXBOW_AVX2_TARGET void Upsample2xRowAvx2(const float* src, int w, int h, size_t src_stride, int y, float* v, float* out) {
  Upsample2xRowBody(src, w, h, src_stride, y, v, out);
}
#endif

}  // namespace

void Upsample2xRow(const float* src, int w, int h, size_t src_stride, int y, float* v, float* out) {
#ifdef OXBOW_AVX2_DISPATCH
  if (Avx2FmaAvailable()) {
    Upsample2xRowAvx2(src, w, h, src_stride, y, v, out);
    return;
  }
#endif
  Upsample2xRowBody(src, w, h, src_stride, y, v, out);
}

void Decimate2x(const Plane& src, Plane* dst) {
  const int w = src.width() / 2, h = src.height() / 2;
  dst->Reshape(w, h);
  for (int y = 0; y < h; ++y) {
    const float* in = src.row(2 * y);
    float* out = dst->row(y);
    int x = 0;
#ifdef OXBOW_AVX512_ALWAYS
    // The even samples of 32 inputs (2 * x + 31 < 2 * w <= src width) into 16 outputs.
    const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    for (; x + 16 <= w; x += 16)
      _mm512_storeu_ps(out + x, _mm512_permutex2var_ps(_mm512_loadu_ps(in + 2 * x), even, _mm512_loadu_ps(in + 2 * x + 16)));
#endif
    for (; x < w; ++x) out[x] = in[2 * x];
  }
}

float FastAtan2Deg(float y, float x) {
  const float ax = std::fabs(x), ay = std::fabs(y);
  const float t = std::min(ax, ay) / std::max(std::max(ax, ay), 1.17549435e-38f);
  const float t2 = t * t;
  float p = std::fma(kAtanC9, t2, kAtanC7);
  p = std::fma(p, t2, kAtanC5);
  p = std::fma(p, t2, kAtanC3);
  p = std::fma(p, t2, kAtanC1);
  float a = p * t;
  if (ay > ax) a = 90.0f - a;
  if (x < 0) a = 180.0f - a;
  if (y < 0) a = 360.0f - a;
  if (a >= 360.0f) a -= 360.0f;
  return a;
}

}  // namespace oxbow::sift::internal
