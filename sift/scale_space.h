// Internal building blocks of the SIFT Gaussian scale space (see sift.h for the maths): aligned image
// planes, separable Gaussian blur, 2x bilinear upsampling and 2x decimation. Exposed in a header so the
// tests can compare the vectorised and scalar paths; not part of the public API.
//
// Every function that takes `allow_simd` computes the same formula on all paths: the AVX-512 path (where
// Avx512Available()), the AVX2 path (where only Avx2FmaAvailable(); sift/base/cpu.h) and the scalar
// path use the same fused multiply-adds in the same order, so their results are bit-identical; tests
// assert that.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <vector>

#include "sift/base/cpu.h"  // OXBOW_AVX2, OXBOW_AVX512: which vector paths are compiled in

namespace oxbow::sift::internal {

// The worker count of an extraction and its parallel loops: oxbow::ParallelFor over num_threads workers
// (the process-wide persistent pool, so an extraction starts no threads).
class WorkerTeam {
 public:
  explicit WorkerTeam(int num_threads);  // num_threads >= 1; 1 runs everything in the caller

  int size() const { return num_threads_; }
  void ParallelFor(size_t n, size_t grain, const std::function<void(size_t begin, size_t end, int worker)>& fn) const;

 private:
  int num_threads_;
};

// A float image with rows padded to a multiple of 16 floats (64 bytes) and 64-byte aligned rows.
// Buffers of 4 MiB or more are 2 MiB aligned and advised to use transparent huge pages, which cuts the
// page faults of first touch (a pyramid of a 1 Mpixel photo is ~60 MiB) by 512x. Movable, not copyable. Not thread-safe to mutate; concurrent reads are fine.
class Plane {
 public:
  Plane() = default;
  Plane(int width, int height);
  Plane(Plane&&) noexcept = default;
  // Changes the size, keeping the buffer when it is large enough (contents are then unspecified).
  void Reshape(int width, int height);
  Plane& operator=(Plane&&) noexcept = default;

  int width() const { return width_; }
  int height() const { return height_; }
  size_t stride() const { return stride_; }  // floats between the starts of consecutive rows
  float* row(int y) { return data_.get() + static_cast<size_t>(y) * stride_; }
  const float* row(int y) const { return data_.get() + static_cast<size_t>(y) * stride_; }
  float at(int x, int y) const { return row(y)[x]; }
  bool empty() const { return width_ == 0 || height_ == 0; }
  size_t capacity_bytes() const { return capacity_ * sizeof(float); }  // allocated, >= stride * height

 private:
  struct Free {
    void operator()(float* p) const;
  };
  int width_ = 0;
  int height_ = 0;
  size_t stride_ = 0;
  size_t capacity_ = 0;  // floats allocated
  std::unique_ptr<float[], Free> data_;
};

// Maps any integer index into [0, n) by reflection without repeating the edge sample
// (OpenCV's BORDER_REFLECT_101: -1 -> 1, n -> n - 2). n >= 1.
int Reflect101(int i, int n);

// The right half c[0..r] of a normalised, truncated Gaussian kernel of standard deviation `sigma`:
// taps x = -r..r with weights c[|x|], r = ksize / 2 where ksize = round(2 * radius_sigmas * sigma + 1) | 1
// (OpenCV's rule for float images with radius_sigmas = 4). Weights exp(-x^2 / (2 sigma^2)) / sum.
std::vector<float> GaussianHalfKernel(double sigma, double radius_sigmas);

// dst = src blurred with the separable kernel, BORDER_REFLECT_101: a vertical pass over the 2r + 1 taps
// (fused multiply-adds in tap order, four output rows per sweep so each source row is loaded once for
// four), then a horizontal pass on each row while it is in L1 (symmetric taps added first). dst is
// (re)allocated to src's size; must not alias src. Rows are split over `num_threads` workers; the
// output does not depend on it. Cost: ~ 3r + 2 floating-point operations per pixel.
void GaussianBlur(const Plane& src, Plane* dst, std::span<const float> half_kernel, int num_threads,
                  bool allow_simd = true);
void GaussianBlur(const Plane& src, Plane* dst, std::span<const float> half_kernel, WorkerTeam& team, bool allow_simd);

// Rows blurred together by GaussianBlur's vertical pass (each source row loaded once for all of them).
inline constexpr int kRowBlock = 8;

// Scratch memory of GaussianBlurRows for one kernel and image width: the padded rows of one block, the
// source row pointers and the full kernel. Reusable across calls.
struct BlurScratch {
  void Prepare(int width, std::span<const float> half_kernel);
  std::vector<float> padded;
  float* t[kRowBlock] = {};
  std::vector<const float*> rows;
  std::vector<float> kernel;
};

// Rows [y, y + count) of GaussianBlur(src, dst, half_kernel, ...), the same values, computed alone:
// 1 <= count <= kRowBlock, dst already shaped like src, and the source rows y - r .. y + count - 1 + r
// (reflected at the edges) already final. Lets a caller interleave the levels of a pyramid row by row,
// so that each level's rows are read again while they are still in cache.
void GaussianBlurRows(const Plane& src, Plane* dst, std::span<const float> half_kernel, int y, int count,
                      BlurScratch* scratch, bool allow_simd);

// The same with the source given row by row: source_row(i) is row i (0 <= i < height) of a width x
// height image, called only for the rows the block reads.
void GaussianBlurRows(const std::function<const float*(int)>& source_row, int width, int height, Plane* dst,
                      std::span<const float> half_kernel, int y, int count, BlurScratch* scratch, bool allow_simd);

// The same with the destination given row by row too: row i of the blur is written to dest_row(i)
// (width floats, 64-byte aligned, with a row's padding after it).
void GaussianBlurRows(const std::function<const float*(int)>& source_row, const std::function<float*(int)>& dest_row,
                      int width, int height, std::span<const float> half_kernel, int y, int count, BlurScratch* scratch,
                      bool allow_simd);

// Row y (0 <= y < 2h) of the bilinear 2x enlargement of the w x h image at `src` (rows `src_stride`
// floats apart) into out (2w floats), with pixel-centre alignment (as cv::resize INTER_LINEAR):
// dst(2i) = 0.75 src(i) + 0.25 src(i-1), dst(2i+1) = 0.75 src(i) + 0.25 src(i+1), edges replicated, in
// both directions. v: scratch of w floats.
void Upsample2xRow(const float* src, int w, int h, size_t src_stride, int y, float* v, float* out);

// dst (floor(w/2) x floor(h/2)) = src sampled at even rows and columns (the next octave's base).
void Decimate2x(const Plane& src, Plane* dst);

// Fast atan2 in degrees, in [0, 360): an odd degree-9 polynomial on [0, 1] (fitted here by iteratively
// re-weighted least squares; max error 1.2e-5 rad = 0.0007 degrees) with octant folding.
float FastAtan2Deg(float y, float x);

// Coefficients of FastAtan2Deg's polynomial (degrees), shared with the vectorised copies of the formula.
inline constexpr double kRadiansToDegrees = 180.0 / 3.14159265358979323846;
inline constexpr float kAtanC1 = static_cast<float>(0.9998663287751239 * kRadiansToDegrees);
inline constexpr float kAtanC3 = static_cast<float>(-0.3303047434812105 * kRadiansToDegrees);
inline constexpr float kAtanC5 = static_cast<float>(0.1801590653843403 * kRadiansToDegrees);
inline constexpr float kAtanC7 = static_cast<float>(-0.08515596114258196 * kRadiansToDegrees);
inline constexpr float kAtanC9 = static_cast<float>(0.020844908008756245 * kRadiansToDegrees);

}  // namespace oxbow::sift::internal
