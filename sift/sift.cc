#include "sift/sift.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <cstdio>
#include <bit>
#include <charconv>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "sift/base/hash.h"
#include "sift/base/parallel.h"
#include "sift/scale_space.h"
#include "sift/sift_internal.h"

#include "sift/base/cpu.h"
#ifdef OXBOW_AVX2
#include <immintrin.h>
#endif

namespace oxbow::sift {

std::optional<std::string> SiftOptions::Check() const {
  if (!(sigma > 0.5 && sigma <= 10)) return "sigma must be in (0.5, 10], got " + std::to_string(sigma);
  if (!(assumed_blur >= 0 && assumed_blur < sigma)) return "assumed_blur must be in [0, sigma), got " + std::to_string(assumed_blur);
  if (intervals < 1 || intervals > 8) return "intervals must be in [1, 8], got " + std::to_string(intervals);
  if (!(contrast_threshold >= 0 && contrast_threshold <= 1)) return "contrast_threshold must be in [0, 1], got " + std::to_string(contrast_threshold);
  if (!(edge_threshold > 1 && edge_threshold <= 1e6)) return "edge_threshold must be > 1, got " + std::to_string(edge_threshold);
  if (max_features && *max_features < 1) return "max_features must be >= 1 when set, got " + std::to_string(*max_features);
  if (descriptor != DescriptorKind::kSift && descriptor != DescriptorKind::kRootSift) return "unknown descriptor kind";
  if (keypoint_style != KeypointStyle::kOpenCv && keypoint_style != KeypointStyle::kVlfeat) return "unknown keypoint style";
  if (!(orientation_peak_ratio > 0 && orientation_peak_ratio <= 1)) return "orientation_peak_ratio must be in (0, 1], got " + std::to_string(orientation_peak_ratio);
  if (!(kernel_radius_sigmas >= 2.5 && kernel_radius_sigmas <= 6)) return "kernel_radius_sigmas must be in [2.5, 6], got " + std::to_string(kernel_radius_sigmas);
  if (max_octaves && (*max_octaves < 1 || *max_octaves > 32)) return "max_octaves must be in [1, 32] when set, got " + std::to_string(*max_octaves);
  if (num_threads < 0 || num_threads > 256) return "num_threads must be in [0, 256], got " + std::to_string(num_threads);
  if (!(descriptor_magnification >= 1 && descriptor_magnification <= 10)) return "descriptor_magnification must be in [1, 10], got " + std::to_string(descriptor_magnification);
  if (descriptor_row_step < 1 || descriptor_row_step > 4) return "descriptor_row_step must be in [1, 4], got " + std::to_string(descriptor_row_step);
  if (descriptor_sampling != DescriptorSampling::kPixels && descriptor_sampling != DescriptorSampling::kGrid)
    return "unknown descriptor sampling";
  if (descriptor_sampling == DescriptorSampling::kGrid && descriptor_row_step != 1)
    return "descriptor_row_step applies to the pixel sampling only (the grid samples 16 x 16 points), got " +
           std::to_string(descriptor_row_step);
  if (refine_in_scale && keypoint_style != KeypointStyle::kVlfeat)
    return "refine_in_scale needs the vlfeat keypoint style (the opencv style always refines in scale)";
  if (thread_cache_mib < 0 || thread_cache_mib > 65536) return "thread_cache_mib must be in [0, 65536], got " + std::to_string(thread_cache_mib);
  return std::nullopt;
}

namespace {
// Lowe's descriptor window, which a description without the `magnification` and `row_step` fields means.
constexpr double kLoweMagnification = 3.0;
constexpr int kEveryRow = 1;

// Shortest text that reads back to the same double (std::to_chars), so Describe() is canonical.
std::string CanonicalDouble(double v) {
  char buf[64];
  const auto result = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, result.ptr);
}
}  // namespace

namespace {

bool ParseDescribedDouble(const std::string& text, double* out) {
  char* end = nullptr;
  *out = std::strtod(text.c_str(), &end);
  return !text.empty() && end == text.c_str() + text.size();
}

bool ParseDescribedInt(const std::string& text, int* out) {
  char* end = nullptr;
  const long v = std::strtol(text.c_str(), &end, 10);
  if (text.empty() || end != text.c_str() + text.size() || v < -1'000'000'000 || v > 1'000'000'000) return false;
  *out = static_cast<int>(v);
  return true;
}

}  // namespace

Result<SiftOptions> SiftOptions::FromDescription(const std::string& settings) {
  const std::string prefix = "oxbow-sift/1";
  auto incompatible = [&](const std::string& why) {
    return Fail(ErrorCode::kIncompatible, "extractor settings '" + settings + "' are not understood by this build (" +
                                              why + "); re-create the index with this version's vocabulary");
  };
  if (settings.rfind(prefix, 0) != 0) return incompatible("expected the prefix " + prefix);
  std::map<std::string, std::string> fields;
  size_t start = prefix.size();
  while (start < settings.size()) {
    if (settings[start] != ';') return incompatible("expected ';' at offset " + std::to_string(start));
    ++start;
    size_t end = settings.find(';', start);
    if (end == std::string::npos) end = settings.size();
    const std::string field = settings.substr(start, end - start);
    const size_t eq = field.find('=');
    if (eq == std::string::npos) return incompatible("field '" + field + "' has no '='");
    fields[field.substr(0, eq)] = field.substr(eq + 1);
    start = end;
  }
  SiftOptions o;
  o.keypoint_style = KeypointStyle::kOpenCv;  // descriptions without these fields were made that way
  o.descriptor_magnification = kLoweMagnification;
  o.descriptor_row_step = kEveryRow;
  o.descriptor_sampling = DescriptorSampling::kPixels;
  auto need = [&](const char* key) -> const std::string* {
    auto it = fields.find(key);
    return it == fields.end() ? nullptr : &it->second;
  };
  // An absent field keeps the default (and then fails the round trip below if the default changed).
  auto read_double = [&](const char* key, double* out) {
    const std::string* v = need(key);
    return v == nullptr || ParseDescribedDouble(*v, out);
  };
  auto read_int = [&](const char* key, int* out) {
    const std::string* v = need(key);
    return v == nullptr || ParseDescribedInt(*v, out);
  };
  if (const std::string* v = need("upsample")) o.upsample_first_octave = *v == "1";
  if (!read_double("sigma", &o.sigma)) return incompatible("sigma");
  if (!read_double("assumed_blur", &o.assumed_blur)) return incompatible("assumed_blur");
  if (!read_int("intervals", &o.intervals)) return incompatible("intervals");
  if (!read_double("contrast", &o.contrast_threshold)) return incompatible("contrast");
  if (!read_double("edge", &o.edge_threshold)) return incompatible("edge");
  if (const std::string* v = need("max_features"); v && *v != "all") {
    int n = 0;
    if (!ParseDescribedInt(*v, &n)) return incompatible("max_features");
    o.max_features = n;
  }
  if (const std::string* v = need("descriptor")) {
    if (*v == DescriptorKindName(DescriptorKind::kRootSift)) {
      o.descriptor = DescriptorKind::kRootSift;
    } else if (*v == DescriptorKindName(DescriptorKind::kSift)) {
      o.descriptor = DescriptorKind::kSift;
    } else {
      return incompatible("descriptor");
    }
  }
  if (const std::string* v = need("keypoints")) {
    if (*v != "vlfeat") return incompatible("keypoints");
    o.keypoint_style = KeypointStyle::kVlfeat;
  }
  if (const std::string* v = need("upright")) {
    if (*v != "1") return incompatible("upright");
    o.upright = true;
  }
  if (const std::string* v = need("sampling")) {
    if (*v != "grid") return incompatible("sampling");
    o.descriptor_sampling = DescriptorSampling::kGrid;
  }
  if (const std::string* v = need("refine_scale")) {
    if (*v != "1") return incompatible("refine_scale");
    o.refine_in_scale = true;
  }
  if (!read_double("peak_ratio", &o.orientation_peak_ratio)) return incompatible("peak_ratio");
  if (!read_double("kernel_radius", &o.kernel_radius_sigmas)) return incompatible("kernel_radius");
  if (!read_double("magnification", &o.descriptor_magnification)) return incompatible("magnification");
  if (!read_int("row_step", &o.descriptor_row_step)) return incompatible("row_step");
  if (const std::string* v = need("max_octaves"); v && *v != "all") {
    int n = 0;
    if (!ParseDescribedInt(*v, &n)) return incompatible("max_octaves");
    o.max_octaves = n;
  }
  // The round trip is the real test: any field this parser does not know, or a changed default, shows
  // up as a different description.
  if (o.Describe() != settings) return incompatible("this build describes them as '" + o.Describe() + "'");
  if (auto message = o.Check()) return incompatible(*message);
  return o;
}

std::string SiftOptions::Describe() const {
  std::ostringstream s;
  s << "oxbow-sift/1"
    << ";upsample=" << (upsample_first_octave ? 1 : 0) << ";sigma=" << CanonicalDouble(sigma)
    << ";assumed_blur=" << CanonicalDouble(assumed_blur) << ";intervals=" << intervals
    << ";contrast=" << CanonicalDouble(contrast_threshold) << ";edge=" << CanonicalDouble(edge_threshold)
    << ";max_features=" << (max_features ? std::to_string(*max_features) : std::string("all"))
    << ";descriptor=" << DescriptorKindName(descriptor)
    << ";peak_ratio=" << CanonicalDouble(orientation_peak_ratio)
    << ";kernel_radius=" << CanonicalDouble(kernel_radius_sigmas)
    << ";max_octaves=" << (max_octaves ? std::to_string(*max_octaves) : std::string("all"));
  // kOpenCv is written as no field: a description without it means kOpenCv.
  if (keypoint_style == KeypointStyle::kVlfeat) s << ";keypoints=vlfeat";
  // Off is written as no field, like kOpenCv above.
  if (upright) s << ";upright=1";
  // Lowe's window is written as no field, like kOpenCv above.
  if (descriptor_magnification != kLoweMagnification) s << ";magnification=" << CanonicalDouble(descriptor_magnification);
  if (descriptor_row_step != kEveryRow) s << ";row_step=" << descriptor_row_step;
  // The pixel sampling is written as no field, like kOpenCv above.
  if (descriptor_sampling == DescriptorSampling::kGrid) s << ";sampling=grid";
  // Off is written as no field, like kOpenCv above.
  if (refine_in_scale) s << ";refine_scale=1";
  return s.str();
}

uint64_t SiftOptions::Fingerprint() const { return Fnv1a64(Describe()); }

namespace internal {
namespace {

constexpr int kBorder = 5;             // extrema closer than this to an octave edge are ignored (as OpenCV)
constexpr int kMaxRefineSteps = 5;     // [L04 sec. 4]
constexpr int kOriBins = 36;           // orientation histogram bins [L04 sec. 5]
constexpr float kOriSigmaFactor = 1.5f;
constexpr float kOriRadiusFactor = 3.0f * kOriSigmaFactor;
constexpr int kDescCells = 4;          // d: 4x4 spatial cells
constexpr int kDescBins = 8;           // n: orientation bins per cell
constexpr float kDescClip = 0.2f;      // [L04 sec. 6.1]

// One octave of the Gaussian scale space: S + 3 images, each blurred more than the previous.
struct Octave {
  int index = 0;  // 0 = the first octave computed (the 2x upsampled one when upsampling)
  std::vector<Plane> gauss;
  float Dog(int layer, int r, int c) const { return gauss[static_cast<size_t>(layer) + 1].at(c, r) - gauss[static_cast<size_t>(layer)].at(c, r); }
};

struct Candidate {
  int layer, r, c;
};

// An extremum after sub-pixel/sub-scale refinement, in its octave's pixel grid.
struct Refined {
  int layer = 0, r = 0, c = 0;
  float xi = 0, xr = 0, xc = 0;  // offsets in scale, row, column
  float contrast = 0;
  int level = 0;  // the Gaussian level whose gradients give the orientation and the descriptor
};

// ---- Extrema scan ----------------------------------------------------------------------------------

#ifdef OXBOW_AVX2
// ScanRow's AVX2 path for whole vectors of columns from x0; returns the first column it left.
OXBOW_AVX2_TARGET int ScanRowAvx2(const float* const (&rows)[3][3], int x0, int x1, float threshold, std::vector<int>* out) {
  const float* cur = rows[1][1];
  int x = x0;
  const __m256 thr = _mm256_set1_ps(threshold);
  const __m256 zero = _mm256_setzero_ps();
  const __m256 abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
  for (; x + 8 <= x1; x += 8) {
    const __m256 v = _mm256_loadu_ps(cur + x);
    const __m256 strong = _mm256_cmp_ps(_mm256_and_ps(v, abs_mask), thr, _CMP_GT_OQ);
    if (_mm256_movemask_ps(strong) == 0) continue;
    // Own layer first: most samples fail here.
    __m256 mx = _mm256_max_ps(_mm256_loadu_ps(cur + x - 1), _mm256_loadu_ps(cur + x + 1));
    __m256 mn = _mm256_min_ps(_mm256_loadu_ps(cur + x - 1), _mm256_loadu_ps(cur + x + 1));
    for (const int dy : {0, 2}) {
      for (int dx = -1; dx <= 1; ++dx) {
        const __m256 n = _mm256_loadu_ps(rows[1][dy] + x + dx);
        mx = _mm256_max_ps(mx, n);
        mn = _mm256_min_ps(mn, n);
      }
    }
    __m256 is_max = _mm256_and_ps(_mm256_cmp_ps(v, zero, _CMP_GT_OQ), _mm256_cmp_ps(v, mx, _CMP_GE_OQ));
    __m256 is_min = _mm256_and_ps(_mm256_cmp_ps(v, zero, _CMP_LT_OQ), _mm256_cmp_ps(v, mn, _CMP_LE_OQ));
    __m256 any = _mm256_and_ps(strong, _mm256_or_ps(is_max, is_min));
    if (_mm256_movemask_ps(any) == 0) continue;
    for (const int l : {0, 2}) {
      for (int dy = 0; dy < 3; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const __m256 n = _mm256_loadu_ps(rows[l][dy] + x + dx);
          mx = _mm256_max_ps(mx, n);
          mn = _mm256_min_ps(mn, n);
        }
      }
    }
    is_max = _mm256_and_ps(is_max, _mm256_cmp_ps(v, mx, _CMP_GE_OQ));
    is_min = _mm256_and_ps(is_min, _mm256_cmp_ps(v, mn, _CMP_LE_OQ));
    int bits = _mm256_movemask_ps(_mm256_and_ps(strong, _mm256_or_ps(is_max, is_min)));
    while (bits != 0) {
      out->push_back(x + std::countr_zero(static_cast<unsigned>(bits)));
      bits &= bits - 1;
    }
  }
  return x;
}
#endif

#ifdef OXBOW_AVX512
OXBOW_AVX512_BEGIN
// ScanRowAvx2's formula 16 columns at a time.
OXBOW_AVX512_TARGET int ScanRowAvx512(const float* const (&rows)[3][3], int x0, int x1, float threshold, std::vector<int>* out) {
  const float* cur = rows[1][1];
  int x = x0;
  const __m512 thr = _mm512_set1_ps(threshold);
  const __m512 zero = _mm512_setzero_ps();
  for (; x + 16 <= x1; x += 16) {
    const __m512 v = _mm512_loadu_ps(cur + x);
    const __mmask16 strong = _mm512_cmp_ps_mask(_mm512_abs_ps(v), thr, _CMP_GT_OQ);
    if (strong == 0) continue;
    __m512 mx = _mm512_max_ps(_mm512_loadu_ps(cur + x - 1), _mm512_loadu_ps(cur + x + 1));
    __m512 mn = _mm512_min_ps(_mm512_loadu_ps(cur + x - 1), _mm512_loadu_ps(cur + x + 1));
    for (const int dy : {0, 2}) {
      for (int dx = -1; dx <= 1; ++dx) {
        const __m512 n = _mm512_loadu_ps(rows[1][dy] + x + dx);
        mx = _mm512_max_ps(mx, n);
        mn = _mm512_min_ps(mn, n);
      }
    }
    __mmask16 is_max = _mm512_cmp_ps_mask(v, zero, _CMP_GT_OQ) & _mm512_cmp_ps_mask(v, mx, _CMP_GE_OQ);
    __mmask16 is_min = _mm512_cmp_ps_mask(v, zero, _CMP_LT_OQ) & _mm512_cmp_ps_mask(v, mn, _CMP_LE_OQ);
    if ((strong & (is_max | is_min)) == 0) continue;
    for (const int l : {0, 2}) {
      for (int dy = 0; dy < 3; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const __m512 n = _mm512_loadu_ps(rows[l][dy] + x + dx);
          mx = _mm512_max_ps(mx, n);
          mn = _mm512_min_ps(mn, n);
        }
      }
    }
    is_max &= _mm512_cmp_ps_mask(v, mx, _CMP_GE_OQ);
    is_min &= _mm512_cmp_ps_mask(v, mn, _CMP_LE_OQ);
    for (unsigned bits = strong & (is_max | is_min); bits != 0; bits &= bits - 1)
      out->push_back(x + std::countr_zero(bits));
  }
  return x;
}

// d[x] = b[x] - a[x] for all x < w (the last vector masked).
OXBOW_AVX512_TARGET void SubtractAvx512(const float* b, const float* a, int w, float* d) {
  for (int x = 0; x < w; x += 16) {
    const __mmask16 lanes = w - x >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (w - x)) - 1);
    _mm512_mask_storeu_ps(d + x, lanes, _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, b + x), _mm512_maskz_loadu_ps(lanes, a + x)));
  }
}
OXBOW_AVX512_END
#endif

// Scans row y of a DoG layer for samples with |v| > threshold that are >= (or <=) all 26 neighbours;
// rows[l][dy] is row y - 1 + dy of layer (layer - 1 + l). Appends the columns found, in order.
void ScanRow(const float* const (&rows)[3][3], int x0, int x1, float threshold, bool simd, std::vector<int>* out) {
  const float* cur = rows[1][1];
  auto is_extremum = [&](int x) {
    const float v = cur[x];
    if (!(std::fabs(v) > threshold)) return false;
    if (v > 0) {
      for (int l = 0; l < 3; ++l)
        for (int dy = 0; dy < 3; ++dy) {
          const float* row = rows[l][dy];
          if (v < row[x - 1] || v < row[x] || v < row[x + 1]) return false;
        }
      return true;
    }
    if (v < 0) {
      for (int l = 0; l < 3; ++l)
        for (int dy = 0; dy < 3; ++dy) {
          const float* row = rows[l][dy];
          if (v > row[x - 1] || v > row[x] || v > row[x + 1]) return false;
        }
      return true;
    }
    return false;
  };
  int x = x0;
#ifdef OXBOW_AVX512
  if (simd && Avx512Available()) x = ScanRowAvx512(rows, x0, x1, threshold, out);
#endif
#ifdef OXBOW_AVX2
  if (simd) x = ScanRowAvx2(rows, x, x1, threshold, out);
#endif
  for (; x < x1; ++x)
    if (is_extremum(x)) out->push_back(x);
}

#ifdef OXBOW_AVX2
// d[x] = b[x] - a[x] for whole vectors of x from 0; returns the first x it left. Written out: GCC 12
// turns the plain loop into gathers in ScanOctave, ~4x slower.
OXBOW_AVX2_TARGET int SubtractAvx2(const float* b, const float* a, int w, float* d) {
  int x = 0;
  for (; x + 8 <= w; x += 8) _mm256_storeu_ps(d + x, _mm256_sub_ps(_mm256_loadu_ps(b + x), _mm256_loadu_ps(a + x)));
  return x;
}
#endif

// Row y of Gaussian level l of an octave (a strip's view: its own rows from the octave's planes, the
// rows just above and below it from its own copies).
using LevelRow = std::function<const float*(int level, int y)>;

// Finds the candidate extrema in rows [y0, y1) of an octave of w x h pixels (clipped to kBorder from its
// edges), in (layer, row, column) order. DoG rows are computed on the fly into a small ring buffer, so the
// DoG pyramid is never stored. rows_ready(n) is called before any row >= n - 2 of a level is read; it
// makes rows < n of every level final (rows y0 - 1 .. y1 at least are read) and returns false to abandon
// the scan (the candidates found so far are returned).
std::vector<Candidate> ScanRows(const LevelRow& level_row, int w, int h, size_t stride, int y0, int y1, int intervals,
                                float threshold, bool simd, const std::function<bool(int)>& rows_ready) {
  y0 = std::max(y0, kBorder);
  y1 = std::min(y1, h - kBorder);
  if (w <= 2 * kBorder || y0 >= y1) return {};
  const int dog_layers = intervals + 2;
  // A ring of 4 DoG rows per layer (rows y-1, y, y+1 and the next one): ~100 KB that stays in cache.
  // Row pointers for the scan are set per row, so the ring only needs consistent slots.
  constexpr int kRing = 4;
  std::unique_ptr<float[]> ring(new float[static_cast<size_t>(dog_layers) * kRing * stride + 16]);
  auto slot = [&](int layer, int y) {
    return ring.get() + (static_cast<size_t>(layer) * kRing + static_cast<size_t>((y % kRing + kRing) % kRing)) * stride;
  };
  [[maybe_unused]] const bool avx512 = simd && Avx512Available();
  auto compute_row = [&](int y) {
    for (int l = 0; l < dog_layers; ++l) {
      const float* pa = level_row(l, y);
      const float* pb = level_row(l + 1, y);
      float* d = slot(l, y);
      int x = 0;
#ifdef OXBOW_AVX512
      if (avx512) {
        SubtractAvx512(pb, pa, w, d);
        continue;
      }
#endif
#ifdef OXBOW_AVX2
      if (simd) x = SubtractAvx2(pb, pa, w, d);
#endif
      for (; x < w; ++x) d[x] = pb[x] - pa[x];
    }
  };
  // On the heap: GCC zeroes a stack array of vectors with aligned 64-byte stores, which ASan's
  // detect_stack_use_after_return frames (32-byte aligned) fault on.
  std::vector<std::vector<Candidate>> rows_found(static_cast<size_t>(intervals));
  std::vector<int> columns;
  if (!rows_ready(y0 + 1)) return {};
  compute_row(y0 - 1);
  compute_row(y0);
  for (int y = y0; y < y1; ++y) {
    if (!rows_ready(y + 2)) break;
    compute_row(y + 1);
    for (int layer = 1; layer <= intervals; ++layer) {
      columns.clear();
      const float* rows3[3][3];
      for (int l = 0; l < 3; ++l)
        for (int dy = 0; dy < 3; ++dy) rows3[l][dy] = slot(layer - 1 + l, y - 1 + dy);
      ScanRow(rows3, kBorder, w - kBorder, threshold, simd, &columns);
      for (int x : columns) rows_found[static_cast<size_t>(layer) - 1].push_back({layer, y, x});
    }
  }
  std::vector<Candidate> out;
  for (const auto& found : rows_found) out.insert(out.end(), found.begin(), found.end());
  return out;
}

// ---- Refinement [L04 sec. 4] ------------------------------------------------------------------------

// Solves H x = g for a symmetric 3x3 H by Gaussian elimination with partial pivoting; false if singular.
bool Solve3(double H[3][3], const double g[3], double x[3]) {
  double a[3][4];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) a[i][j] = H[i][j];
    a[i][3] = g[i];
  }
  for (int col = 0; col < 3; ++col) {
    int pivot = col;
    for (int i = col + 1; i < 3; ++i)
      if (std::fabs(a[i][col]) > std::fabs(a[pivot][col])) pivot = i;
    if (std::fabs(a[pivot][col]) < 1e-30) return false;
    if (pivot != col)
      for (int j = 0; j < 4; ++j) std::swap(a[col][j], a[pivot][j]);
    for (int i = col + 1; i < 3; ++i) {
      const double f = a[i][col] / a[col][col];
      for (int j = col; j < 4; ++j) a[i][j] -= f * a[col][j];
    }
  }
  for (int i = 2; i >= 0; --i) {
    double v = a[i][3];
    for (int j = i + 1; j < 3; ++j) v -= a[i][j] * x[j];
    x[i] = v / a[i][i];
  }
  return true;
}

// The 3D quadratic fit of D at (layer, r, c): grad = first derivatives (column, row, scale) and the
// offset = -H^-1 grad to the fitted extremum (zero when H is singular).
void FitQuadratic(const Octave& octave, int layer, int r, int c, double grad[3], double offset[3]) {
  const float v = octave.Dog(layer, r, c);
  const float right = octave.Dog(layer, r, c + 1), left = octave.Dog(layer, r, c - 1);
  const float down = octave.Dog(layer, r + 1, c), up = octave.Dog(layer, r - 1, c);
  const float next = octave.Dog(layer + 1, r, c), prev = octave.Dog(layer - 1, r, c);
  grad[0] = 0.5 * (right - left);
  grad[1] = 0.5 * (down - up);
  grad[2] = 0.5 * (next - prev);
  double H[3][3];
  H[0][0] = right + left - 2.0 * v;
  H[1][1] = down + up - 2.0 * v;
  H[2][2] = next + prev - 2.0 * v;
  H[0][1] = H[1][0] = 0.25 * (octave.Dog(layer, r + 1, c + 1) - octave.Dog(layer, r + 1, c - 1) -
                              octave.Dog(layer, r - 1, c + 1) + octave.Dog(layer, r - 1, c - 1));
  H[0][2] = H[2][0] = 0.25 * (octave.Dog(layer + 1, r, c + 1) - octave.Dog(layer + 1, r, c - 1) -
                              octave.Dog(layer - 1, r, c + 1) + octave.Dog(layer - 1, r, c - 1));
  H[1][2] = H[2][1] = 0.25 * (octave.Dog(layer + 1, r + 1, c) - octave.Dog(layer + 1, r - 1, c) -
                              octave.Dog(layer - 1, r + 1, c) + octave.Dog(layer - 1, r - 1, c));
  double x[3] = {0, 0, 0};
  if (!Solve3(H, grad, x)) x[0] = x[1] = x[2] = 0;
  for (int i = 0; i < 3; ++i) offset[i] = -x[i];
}

// The contrast test at the fitted extremum, D + 0.5 grad . offset, and the edge test on the 2x2 spatial
// Hessian [L04 sec. 4, 4.1], at the sample (layer, r, c) whose fit gave grad and offset: the keypoint,
// its descriptor taken at Gaussian level `level`, or nothing.
std::optional<Refined> AcceptFit(const Octave& octave, int layer, int r, int c, const double grad[3],
                                 const double offset[3], int level, const SiftOptions& options) {
  const float v = octave.Dog(layer, r, c);
  const double contrast = v + 0.5 * (grad[0] * offset[0] + grad[1] * offset[1] + grad[2] * offset[2]);
  if (std::fabs(contrast) * options.intervals < options.contrast_threshold) return std::nullopt;
  const double dxx = octave.Dog(layer, r, c + 1) + octave.Dog(layer, r, c - 1) - 2.0 * v;
  const double dyy = octave.Dog(layer, r + 1, c) + octave.Dog(layer, r - 1, c) - 2.0 * v;
  const double dxy = 0.25 * (octave.Dog(layer, r + 1, c + 1) - octave.Dog(layer, r + 1, c - 1) -
                             octave.Dog(layer, r - 1, c + 1) + octave.Dog(layer, r - 1, c - 1));
  const double tr = dxx + dyy, det = dxx * dyy - dxy * dxy;
  const double e = options.edge_threshold;
  if (det <= 0 || tr * tr * e >= (e + 1) * (e + 1) * det) return std::nullopt;
  Refined out;
  out.layer = layer;
  out.r = r;
  out.c = c;
  out.xc = static_cast<float>(offset[0]);
  out.xr = static_cast<float>(offset[1]);
  out.xi = static_cast<float>(offset[2]);
  out.contrast = static_cast<float>(contrast);
  out.level = level;
  return out;
}

// KeypointStyle::kOpenCv's refinement (cv::SIFT's adjustLocalExtrema): the sample moves to the rounded
// fitted extremum, in space and scale, until every offset is below half a sample, at most
// kMaxRefineSteps times.
std::optional<Refined> Refine(const Octave& octave, Candidate cand, const SiftOptions& options) {
  const int S = options.intervals;
  const int w = octave.gauss[0].width(), h = octave.gauss[0].height();
  int layer = cand.layer, r = cand.r, c = cand.c;
  double offset[3] = {0, 0, 0};  // (column, row, scale)
  double grad[3] = {0, 0, 0};
  int step = 0;
  for (; step < kMaxRefineSteps; ++step) {
    FitQuadratic(octave, layer, r, c, grad, offset);
    if (std::fabs(offset[0]) < 0.5 && std::fabs(offset[1]) < 0.5 && std::fabs(offset[2]) < 0.5) break;
    if (std::fabs(offset[0]) > 1e6 || std::fabs(offset[1]) > 1e6 || std::fabs(offset[2]) > 1e6) return std::nullopt;
    c += static_cast<int>(std::lrint(offset[0]));
    r += static_cast<int>(std::lrint(offset[1]));
    layer += static_cast<int>(std::lrint(offset[2]));
    if (layer < 1 || layer > S || c < kBorder || c >= w - kBorder || r < kBorder || r >= h - kBorder) return std::nullopt;
  }
  if (step >= kMaxRefineSteps) return std::nullopt;  // did not converge
  return AcceptFit(octave, layer, r, c, grad, offset, layer, options);
}

// KeypointStyle::kVlfeat's refinement: the sample moves one pixel in space (and, with
// SiftOptions::refine_in_scale, one layer in scale) while an offset exceeds kMoveOffset, at most
// kMaxRefineSteps times; the fit at the final sample is kept when every offset is below kMaxOffset,
// then the contrast and edge tests as in Refine.
std::optional<Refined> RefineInSpace(const Octave& octave, Candidate cand, const SiftOptions& options) {
  constexpr double kMoveOffset = 0.6, kMaxOffset = 1.5;
  const int S = options.intervals;
  const int w = octave.gauss[0].width(), h = octave.gauss[0].height();
  int layer = cand.layer;
  int r = cand.r, c = cand.c;
  double grad[3], offset[3];
  FitQuadratic(octave, layer, r, c, grad, offset);
  for (int step = 0; step < kMaxRefineSteps; ++step) {
    const int dc = (offset[0] > kMoveOffset && c < w - kBorder - 1) ? 1 : (offset[0] < -kMoveOffset && c > kBorder) ? -1 : 0;
    const int dr = (offset[1] > kMoveOffset && r < h - kBorder - 1) ? 1 : (offset[1] < -kMoveOffset && r > kBorder) ? -1 : 0;
    const int dl = !options.refine_in_scale ? 0 : (offset[2] > kMoveOffset && layer < S) ? 1 : (offset[2] < -kMoveOffset && layer > 1) ? -1 : 0;
    if (dc == 0 && dr == 0 && dl == 0) break;
    c += dc;
    r += dr;
    layer += dl;
    FitQuadratic(octave, layer, r, c, grad, offset);
  }
  if (!(std::fabs(offset[0]) < kMaxOffset && std::fabs(offset[1]) < kMaxOffset && std::fabs(offset[2]) < kMaxOffset))
    return std::nullopt;
  return AcceptFit(octave, layer, r, c, grad, offset, std::clamp(static_cast<int>(std::lrint(layer + offset[2])), 0, S + 2),
                   options);
}

// ---- Gradients -------------------------------------------------------------------------------------

#ifdef OXBOW_AVX2
// The same formula as FastAtan2Deg, 8 lanes at a time (bit-identical).
OXBOW_AVX2_TARGET inline __m256 Atan2Deg8(__m256 y, __m256 x) {
  const __m256 abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff));
  const __m256 zero = _mm256_setzero_ps();
  const __m256 ax = _mm256_and_ps(x, abs_mask), ay = _mm256_and_ps(y, abs_mask);
  const __m256 t = _mm256_div_ps(_mm256_min_ps(ax, ay), _mm256_max_ps(_mm256_max_ps(ax, ay), _mm256_set1_ps(1.17549435e-38f)));
  const __m256 t2 = _mm256_mul_ps(t, t);
  __m256 p = _mm256_fmadd_ps(_mm256_set1_ps(kAtanC9), t2, _mm256_set1_ps(kAtanC7));
  p = _mm256_fmadd_ps(p, t2, _mm256_set1_ps(kAtanC5));
  p = _mm256_fmadd_ps(p, t2, _mm256_set1_ps(kAtanC3));
  p = _mm256_fmadd_ps(p, t2, _mm256_set1_ps(kAtanC1));
  __m256 a = _mm256_mul_ps(p, t);
  a = _mm256_blendv_ps(a, _mm256_sub_ps(_mm256_set1_ps(90.0f), a), _mm256_cmp_ps(ay, ax, _CMP_GT_OQ));
  a = _mm256_blendv_ps(a, _mm256_sub_ps(_mm256_set1_ps(180.0f), a), _mm256_cmp_ps(x, zero, _CMP_LT_OQ));
  a = _mm256_blendv_ps(a, _mm256_sub_ps(_mm256_set1_ps(360.0f), a), _mm256_cmp_ps(y, zero, _CMP_LT_OQ));
  const __m256 full = _mm256_set1_ps(360.0f);
  a = _mm256_blendv_ps(a, _mm256_sub_ps(a, full), _mm256_cmp_ps(a, full, _CMP_GE_OQ));
  return a;
}

// Gradient8 for the 8 samples x..x+7 of a row; see Gradient.
OXBOW_AVX2_TARGET inline void Gradient8(const float* row, const float* above, const float* below, int x, __m256* mag, __m256* ori) {
  const __m256 dx = _mm256_sub_ps(_mm256_loadu_ps(row + x + 1), _mm256_loadu_ps(row + x - 1));
  const __m256 dy = _mm256_sub_ps(_mm256_loadu_ps(above + x), _mm256_loadu_ps(below + x));
  *mag = _mm256_sqrt_ps(_mm256_fmadd_ps(dx, dx, _mm256_mul_ps(dy, dy)));
  *ori = Atan2Deg8(dy, dx);
}
#endif

#ifdef OXBOW_AVX512
OXBOW_AVX512_BEGIN
// FastAtan2Deg 16 lanes at a time (bit-identical).
OXBOW_AVX512_TARGET inline __m512 Atan2Deg16(__m512 y, __m512 x) {
  const __m512 zero = _mm512_setzero_ps();
  const __m512 ax = _mm512_abs_ps(x), ay = _mm512_abs_ps(y);
  const __m512 t = _mm512_div_ps(_mm512_min_ps(ax, ay), _mm512_max_ps(_mm512_max_ps(ax, ay), _mm512_set1_ps(1.17549435e-38f)));
  const __m512 t2 = _mm512_mul_ps(t, t);
  __m512 p = _mm512_fmadd_ps(_mm512_set1_ps(kAtanC9), t2, _mm512_set1_ps(kAtanC7));
  p = _mm512_fmadd_ps(p, t2, _mm512_set1_ps(kAtanC5));
  p = _mm512_fmadd_ps(p, t2, _mm512_set1_ps(kAtanC3));
  p = _mm512_fmadd_ps(p, t2, _mm512_set1_ps(kAtanC1));
  __m512 a = _mm512_mul_ps(p, t);
  a = _mm512_mask_sub_ps(a, _mm512_cmp_ps_mask(ay, ax, _CMP_GT_OQ), _mm512_set1_ps(90.0f), a);
  a = _mm512_mask_sub_ps(a, _mm512_cmp_ps_mask(x, zero, _CMP_LT_OQ), _mm512_set1_ps(180.0f), a);
  a = _mm512_mask_sub_ps(a, _mm512_cmp_ps_mask(y, zero, _CMP_LT_OQ), _mm512_set1_ps(360.0f), a);
  const __m512 full = _mm512_set1_ps(360.0f);
  return _mm512_mask_sub_ps(a, _mm512_cmp_ps_mask(a, full, _CMP_GE_OQ), a, full);
}

// Gradient for the 16 samples x..x+15 of a row; see Gradient.
OXBOW_AVX512_TARGET inline void Gradient16(const float* row, const float* above, const float* below, int x, __m512* mag, __m512* ori) {
  const __m512 dx = _mm512_sub_ps(_mm512_loadu_ps(row + x + 1), _mm512_loadu_ps(row + x - 1));
  const __m512 dy = _mm512_sub_ps(_mm512_loadu_ps(above + x), _mm512_loadu_ps(below + x));
  *mag = _mm512_sqrt_ps(_mm512_fmadd_ps(dx, dx, _mm512_mul_ps(dy, dy)));
  *ori = Atan2Deg16(dy, dx);
}
OXBOW_AVX512_END
#endif

// Gradient at column x of `row` (rows y-1 and y+1 in `above`, `below`): dx = I(x+1) - I(x-1),
// dy = I(y-1) - I(y+1) (y axis pointing up, as OpenCV, so descriptors are laid out like cv::SIFT's);
// magnitude and direction in degrees, [0, 360).
inline void Gradient(const float* row, const float* above, const float* below, int x, float* mag, float* ori) {
  const float dx = row[x + 1] - row[x - 1];
  const float dy = above[x] - below[x];
  *mag = std::sqrt(std::fma(dx, dx, dy * dy));
  *ori = FastAtan2Deg(dy, dx);
}

// The per-keypoint histograms are accumulated with explicit fused multiply-adds
// (h = fma(weight, value, h)) in both the vector and the scalar path: a plain `h += a * b` would be
// contracted into an FMA by the compiler in the scalar path only, and the paths would differ. One
// histogram per keypoint: interleaved copies against store-forwarding chains (sample j into copy
// j % k, summed at the end) measured 1-3% slower with k = 2, 4, 8 on Zen 3.

// ---- Orientation [L04 sec. 5] -----------------------------------------------------------------------

constexpr float kBinsPerDeg = kOriBins / 360.0f;

#ifdef OXBOW_AVX2
// OrientationHistogram's AVX2 path for the samples [x, x1) of a row, whole vectors of 8 (lanes past x1
// read valid memory: row padding or the next row, and are not added); returns where it stopped.
OXBOW_AVX2_TARGET int OrientationRowAvx2(const float* row, const float* above, const float* below, int x, int x1,
                                         float wy, const float* wx, int c, int radius, float* temp) {
  // Whole vectors of 8 samples; lanes past x1 read valid memory (row padding or the next row) and
  // are not added.
  const __m256 vwy = _mm256_set1_ps(wy);
  alignas(32) int bins[8];
  alignas(32) float weights[8], mags[8];
  for (; x < x1; x += 8) {
    __m256 mag, ori;
    Gradient8(row, above, below, x, &mag, &ori);
    __m256i bin = _mm256_cvtps_epi32(_mm256_mul_ps(ori, _mm256_set1_ps(kBinsPerDeg)));  // nearest, as lrint
    bin = _mm256_sub_epi32(bin, _mm256_and_si256(_mm256_cmpgt_epi32(bin, _mm256_set1_epi32(kOriBins - 1)),
                                                 _mm256_set1_epi32(kOriBins)));
    _mm256_store_si256(reinterpret_cast<__m256i*>(bins), bin);
    _mm256_store_ps(weights, _mm256_mul_ps(vwy, _mm256_loadu_ps(wx + (x - c + radius))));
    _mm256_store_ps(mags, mag);
    const int lanes = std::min(8, x1 - x);
    for (int lane = 0; lane < lanes; ++lane) {
      float& bin_sum = temp[bins[lane]];
      bin_sum = std::fma(weights[lane], mags[lane], bin_sum);
    }
  }
  return x;
}
#endif

// Smoothed 36-bin gradient orientation histogram around (c, r) of `img`; returns its maximum.
float OrientationHistogram(const Plane& img, int c, int r, int radius, float sigma, float* hist, bool simd) {
  float raw[kOriBins + 4] = {};
  float* temp = raw + 2;  // the 36 bins, padded by 2 on each side for the circular smoothing
  const int w = img.width(), h = img.height();
  const float exp_scale = -1.0f / (2.0f * sigma * sigma);
  alignas(32) float wx[256 + 8] = {};
  radius = std::min(radius, 120);
  for (int i = -radius; i <= radius; ++i) wx[i + radius] = std::exp(static_cast<float>(i * i) * exp_scale);
  const int x0 = std::max(c - radius, 1), x1 = std::min(c + radius + 1, w - 1);
  for (int i = -radius; i <= radius; ++i) {
    const int y = r + i;
    if (y <= 0 || y >= h - 1 || x0 >= x1) continue;
    const float* row = img.row(y);
    const float* above = img.row(y - 1);
    const float* below = img.row(y + 1);
    const float wy = wx[i + radius];
#ifdef OXBOW_AVX2
    if (y + 3 < h) {  // see OrientationHistogramCircular
      const float* ahead = img.row(y + 3);
      for (int k = x0 - 1; k < x1 + 16; k += 16) _mm_prefetch(reinterpret_cast<const char*>(ahead + k), _MM_HINT_T0);
    }
#endif
    int x = x0;
#ifdef OXBOW_AVX2
    if (simd) x = OrientationRowAvx2(row, above, below, x, x1, wy, wx, c, radius, temp);
#endif
    for (; x < x1; ++x) {
      float mag, ori;
      Gradient(row, above, below, x, &mag, &ori);
      int bin = static_cast<int>(std::lrint(ori * kBinsPerDeg));
      if (bin >= kOriBins) bin -= kOriBins;
      float& bin_sum = temp[bin];
      bin_sum = std::fma(wy * wx[x - c + radius], mag, bin_sum);
    }
  }
  temp[-1] = temp[kOriBins - 1];
  temp[-2] = temp[kOriBins - 2];
  temp[kOriBins] = temp[0];
  temp[kOriBins + 1] = temp[1];
  float max_value = 0;
  for (int i = 0; i < kOriBins; ++i) {
    hist[i] = (temp[i - 2] + temp[i + 2]) * (1.0f / 16.0f) + (temp[i - 1] + temp[i + 1]) * (4.0f / 16.0f) +
              temp[i] * (6.0f / 16.0f);
    max_value = std::max(max_value, hist[i]);
  }
  return max_value;
}

// KeypointStyle::kVlfeat's vote of one gradient (direction `ori` in degrees, weighted magnitude wm):
// shared linearly between the two nearest bins (bin b is centred on b * 10 degrees).
inline void AddOrientationVote(float* temp, float ori, float wm) {
  const float fbin = ori * kBinsPerDeg;
  int b0 = static_cast<int>(fbin);
  const float fraction = fbin - static_cast<float>(b0);
  if (b0 >= kOriBins) b0 -= kOriBins;
  const int b1 = b0 + 1 < kOriBins ? b0 + 1 : 0;
  temp[b0] += std::fma(-fraction, wm, wm);
  temp[b1] = std::fma(wm, fraction, temp[b1]);
}

#ifdef OXBOW_AVX512
OXBOW_AVX512_BEGIN
// One row of the circular orientation window for the AVX-512 path: samples j0 <= j < j1 (columns
// relative to the centre) of `row`, with the rows above and below and the row's Gaussian weight.
struct OrientationWindowRow {
  const float* row;
  const float* above;
  const float* below;
  int j0, j1;
  float wy;
};

// The votes of 16 consecutive samples of a window row: lower bin, its share and the weighted magnitude.
struct OrientationVotes {
  int lanes;
  alignas(64) int bins[16];
  alignas(64) float v0[16];
  alignas(64) float wms[16];
  alignas(64) float fractions[16];
};

OXBOW_AVX512_TARGET inline void PrepareOrientationVotes(const OrientationWindowRow& r, int j, const float* wx, OrientationVotes* out) {
  const __m512 bins_per_deg = _mm512_set1_ps(kBinsPerDeg);
  const __m512i nbins = _mm512_set1_epi32(kOriBins);
  __m512 mag, ori;
  Gradient16(r.row, r.above, r.below, j, &mag, &ori);
  const __m512 fbin = _mm512_mul_ps(ori, bins_per_deg);
  __m512i b0 = _mm512_cvttps_epi32(fbin);
  const __m512 fraction = _mm512_sub_ps(fbin, _mm512_cvtepi32_ps(b0));
  b0 = _mm512_mask_sub_epi32(b0, _mm512_cmpge_epi32_mask(b0, nbins), b0, nbins);
  const __m512 wm = _mm512_mul_ps(mag, _mm512_mul_ps(_mm512_set1_ps(r.wy), _mm512_loadu_ps(wx + j)));
  _mm512_storeu_si512(out->bins, b0);
  _mm512_storeu_ps(out->v0, _mm512_fnmadd_ps(fraction, wm, wm));
  _mm512_storeu_ps(out->wms, wm);
  _mm512_storeu_ps(out->fractions, fraction);
  out->lanes = std::min(16, r.j1 - j);
}

inline void AddOrientationVotes(const OrientationVotes& v, float* temp) {
  for (int lane = 0; lane < v.lanes; ++lane) {
    const int b = v.bins[lane];
    temp[b] += v.v0[lane];
    float& next = temp[b + 1 < kOriBins ? b + 1 : 0];
    next = std::fma(v.wms[lane], v.fractions[lane], next);
  }
}

// Walks the rows of a window (each with j0, j1 and the `below` row pointer) 16 samples at a time:
// prepare(row, j, buffer) fills a buffer for samples j..j+15 of a row while add(buffer) adds the
// vector before it, so the long latency of a preparation overlaps the additions instead of stalling
// them. Vectors are added in order: rows in order, j increasing.
template <typename Buffer, typename Row, typename Prepare, typename Add>
OXBOW_AVX512_TARGET void WalkWindowPipelined(std::span<const Row> rows, const Prepare& prepare, const Add& add) {
  Buffer buffers[2];
  size_t row = 0;
  int j = rows.empty() ? 0 : rows[0].j0;
  int current = 0;
  bool pending = false;
  while (row < rows.size()) {
    if (j == rows[row].j0 && row + 3 < rows.size()) {
      // The window's rows are far apart in memory; ask for the row needed three rows from now.
      const Row& ahead = rows[row + 3];
      for (int k = ahead.j0 - 1; k < ahead.j1 + 16; k += 16) _mm_prefetch(reinterpret_cast<const char*>(ahead.below + k), _MM_HINT_T0);
    }
    prepare(rows[row], j, &buffers[current ^ 1]);
    if (pending) add(buffers[current]);
    current ^= 1;
    pending = true;
    j += 16;
    if (j >= rows[row].j1 && ++row < rows.size()) j = rows[row].j0;
  }
  if (pending) add(buffers[current]);
}

// OrientationHistogramCircular's AVX-512 path over the whole window, votes added in sample order.
OXBOW_AVX512_TARGET void OrientationWindowAvx512(std::span<const OrientationWindowRow> rows, const float* wx, float* temp) {
  WalkWindowPipelined<OrientationVotes>(
      rows,
      [&](const OrientationWindowRow& row, int j, OrientationVotes* votes)
          OXBOW_AVX512_TARGET { PrepareOrientationVotes(row, j, wx, votes); },
      [&](const OrientationVotes& votes) OXBOW_AVX512_TARGET { AddOrientationVotes(votes, temp); });
}
OXBOW_AVX512_END
#endif

#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)  // the AVX-512 path replaces it where it always runs
// OrientationHistogramCircular's AVX2 path for the samples [j, j1) of a row: votes 8 at a time, added
// in sample order.
OXBOW_AVX2_TARGET void OrientationCircularRowAvx2(const float* row, const float* above, const float* below, int j, int j1,
                                                  float wy, const float* wx, float* temp) {
  alignas(32) int bins[8];
  alignas(32) float v0[8], wms[8], fractions[8];
  const __m256 vwy = _mm256_set1_ps(wy), bins_per_deg = _mm256_set1_ps(kBinsPerDeg);
  const __m256i nbins = _mm256_set1_epi32(kOriBins), last = _mm256_set1_epi32(kOriBins - 1);
  for (; j < j1; j += 8) {
    __m256 mag, ori;
    Gradient8(row, above, below, j, &mag, &ori);
    const __m256 fbin = _mm256_mul_ps(ori, bins_per_deg);
    __m256i b0 = _mm256_cvttps_epi32(fbin);
    const __m256 fraction = _mm256_sub_ps(fbin, _mm256_cvtepi32_ps(b0));
    b0 = _mm256_sub_epi32(b0, _mm256_and_si256(_mm256_cmpgt_epi32(b0, last), nbins));
    const __m256 wm = _mm256_mul_ps(mag, _mm256_mul_ps(vwy, _mm256_loadu_ps(wx + j)));
    _mm256_store_si256(reinterpret_cast<__m256i*>(bins), b0);
    _mm256_store_ps(v0, _mm256_fnmadd_ps(fraction, wm, wm));
    _mm256_store_ps(wms, wm);
    _mm256_store_ps(fractions, fraction);
    const int lanes = std::min(8, j1 - j);
    for (int lane = 0; lane < lanes; ++lane) {
      const int b = bins[lane];
      temp[b] += v0[lane];
      float& next = temp[b + 1 < kOriBins ? b + 1 : 0];
      next = std::fma(wms[lane], fractions[lane], next);
    }
  }
}
#endif

// KeypointStyle::kVlfeat's smoothed 36-bin orientation histogram around the sub-pixel position
// (xf, yf) of `img`: gradients within radius floor(3 sigma) (squared distance < radius^2 + 0.6),
// Gaussian weight of `sigma`, votes shared between the two nearest bins, six passes of [1 1 1] / 3.
// Returns its maximum.
float OrientationHistogramCircular(const Plane& img, float xf, float yf, float sigma, float* hist, bool simd) {
  float temp[kOriBins] = {};
  const int w = img.width(), h = img.height();
  const int cx = static_cast<int>(std::lrint(xf)), cy = static_cast<int>(std::lrint(yf));
  const float fx = xf - static_cast<float>(cx), fy = yf - static_cast<float>(cy);
  const int radius = std::clamp(static_cast<int>(std::floor(3.0f * sigma)), 1, 120);
  const float limit = static_cast<float>(radius * radius) + 0.6f;
  const float exp_scale = -1.0f / (2.0f * sigma * sigma);
  alignas(64) float wx[256 + 16] = {};
  for (int j = -radius; j <= radius; ++j) {
    const float dj = static_cast<float>(j) - fx;
    wx[j + radius] = std::exp(dj * dj * exp_scale);
  }
#ifdef OXBOW_AVX512
  const bool avx512 = simd && Avx512Available();
  OrientationWindowRow window[2 * 120 + 1];
  size_t window_rows = 0;
#endif
  for (int i = -radius; i <= radius; ++i) {
    const int y = cy + i;
    if (y <= 0 || y >= h - 1) continue;
    const float di = static_cast<float>(i) - fy;
    const float di2 = di * di;
    // The columns inside the circle, an interval.
    auto inside = [&](int j) {
      const float dj = static_cast<float>(j) - fx;
      return std::fma(dj, dj, di2) < limit;
    };
    int j0 = -radius, j1 = radius + 1;
    while (j0 < j1 && !inside(j0)) ++j0;
    while (j1 > j0 && !inside(j1 - 1)) --j1;
    j0 = std::max(j0, 1 - cx);
    j1 = std::min(j1, w - 1 - cx);
    if (j0 >= j1) continue;
    const float wy = std::exp(di2 * exp_scale);
    const float* row = img.row(y) + cx;
    const float* above = img.row(y - 1) + cx;
    const float* below = img.row(y + 1) + cx;
#ifdef OXBOW_AVX512
    if (avx512) {
      window[window_rows++] = {row, above, below, j0, j1, wy};
      continue;
    }
#endif
#ifdef OXBOW_AVX2
    // The window's rows are far apart in memory; ask for the row needed three rows from now.
    if (y + 3 < h) {
      const float* ahead = img.row(y + 3) + cx;
      for (int k = j0 - 1; k < j1 + 16; k += 16) _mm_prefetch(reinterpret_cast<const char*>(ahead + k), _MM_HINT_T0);
    }
#endif
    if (simd) {
#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
      OrientationCircularRowAvx2(row, above, below, j0, j1, wy, wx + radius, temp);
      continue;
#endif
    }
    for (int j = j0; j < j1; ++j) {
      float mag, ori;
      Gradient(row, above, below, j, &mag, &ori);
      AddOrientationVote(temp, ori, mag * (wy * wx[j + radius]));
    }
  }
#ifdef OXBOW_AVX512
  if (avx512) OrientationWindowAvx512(std::span<const OrientationWindowRow>(window, window_rows), wx + radius, temp);
#endif
  for (int pass = 0; pass < 6; ++pass) {
    const float first = temp[0];
    float previous = temp[kOriBins - 1];
    for (int b = 0; b < kOriBins; ++b) {
      const float current = temp[b];
      temp[b] = (previous + current + (b + 1 < kOriBins ? temp[b + 1] : first)) / 3.0f;
      previous = current;
    }
  }
  float max_value = 0;
  for (int b = 0; b < kOriBins; ++b) {
    hist[b] = temp[b];
    max_value = std::max(max_value, hist[b]);
  }
  return max_value;
}

// ---- Descriptor [L04 sec. 6] ------------------------------------------------------------------------

// The descriptor histogram is accumulated as hist[k * 16 + cell]: orientation bin k (0..7), spatial
// cell = row * 4 + column. A sample at bin coordinates (rbin, cbin, obin) adds m * w to every bin, with
// the trilinear weight w = tent(rbin - row) * tent(cbin - column) * o(k), tent(t) = max(1 - |t|, 0),
// o(k0) = 1 - o1 and o(k0 + 1 mod n) = o1 where k0 = floor(obin), o1 = obin - k0, else 0: at most
// 2 x 2 x 2 weights are non-zero. Every path computes each weight by this same formula,
// (tent(rbin - row) * tent(cbin - column)) times (m * o(k)), and
// adds it with one fused multiply-add per bin, samples in order; the AVX-512 path adds every bin
// (the zero weights add +0, which leaves a bin unchanged: bins and weights are never negative) so that
// its 128 sums stay in registers, the others only the non-zero ones, with the same results.
constexpr int kDescCellCount = kDescCells * kDescCells;
static_assert(kDescCells == 4 && kDescBins == 8, "the vector paths hold 16 cells x 8 orientation bins");

inline float Tent(float t) {
  const float w = 1.0f - std::fabs(t);
  return w > 0.0f ? w : 0.0f;
}

// Adds one sample (bin coordinates rbin, cbin in (-1, d), obin in [0, n), weighted magnitude m) to the
// non-zero bins of hist.
inline void AccumulateSample(float* hist, float rbin, float cbin, float obin, float m) {
  constexpr int d = kDescCells, n = kDescBins;
  const int r0 = static_cast<int>(std::floor(rbin)), c0 = static_cast<int>(std::floor(cbin));
  const int k0 = static_cast<int>(obin), k1 = (k0 + 1) & (n - 1);
  const float o1 = obin - static_cast<float>(k0);
  const float mo1 = m * o1, mo0 = m * (1.0f - o1);
  for (int i = r0; i <= r0 + 1; ++i) {
    if (i < 0 || i >= d) continue;
    const float wr = Tent(rbin - static_cast<float>(i));
    for (int j = c0; j <= c0 + 1; ++j) {
      if (j < 0 || j >= d) continue;
      const float wcell = wr * Tent(cbin - static_cast<float>(j));
      float& b0 = hist[k0 * kDescCellCount + i * d + j];
      float& b1 = hist[k1 * kDescCellCount + i * d + j];
      b0 = std::fma(wcell, mo0, b0);
      b1 = std::fma(wcell, mo1, b1);
    }
  }
}

// Orientation bin of a gradient direction relative to the keypoint's, wrapped into [0, n).
inline float OrientationBin(float ori, float ori_deg, float bins_per_deg) {
  float obin = (ori - ori_deg) * bins_per_deg;
  if (obin < 0.0f) obin += static_cast<float>(kDescBins);
  if (obin >= static_cast<float>(kDescBins)) obin -= static_cast<float>(kDescBins);
  return obin;
}

#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)  // the AVX-512 path replaces it where it always runs
// Descriptor's AVX2 path for the samples [j, j1) of a window row (wcol: the column weights, indexed
// by j), whole vectors of 8 (lanes past j1 read valid memory: row padding or the next row, and are not
// added): bin coordinates and weights 8 at a time, then AccumulateSample per sample in order.
OXBOW_AVX2_TARGET int DescriptorRowAvx2(const float* row, const float* above, const float* below, int j, int j1, float fx,
                                        float sin_t, float cos_t, float rb0, float cb0, float ori_deg,
                                        float bins_per_deg, float wrow, const float* wcol, float* hist) {
  constexpr int d = kDescCells, n = kDescBins;
  const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256 minus_one = _mm256_set1_ps(-1.0f), dv = _mm256_set1_ps(static_cast<float>(d));
  const __m256 vsin = _mm256_set1_ps(sin_t), vcos = _mm256_set1_ps(cos_t);
  const __m256 vrb0 = _mm256_set1_ps(rb0), vcb0 = _mm256_set1_ps(cb0);
  const __m256 vori = _mm256_set1_ps(ori_deg), vbins = _mm256_set1_ps(bins_per_deg), vwrow = _mm256_set1_ps(wrow);
  const __m256 zero = _mm256_setzero_ps(), nv = _mm256_set1_ps(static_cast<float>(n));
  const __m256i vend = _mm256_set1_epi32(j1);
  alignas(32) float rbins[8], cbins[8], obins[8], mags[8];
  for (; j < j1; j += 8) {
    const __m256i jv = _mm256_add_epi32(_mm256_set1_epi32(j), iota);
    const __m256 dj = _mm256_sub_ps(_mm256_cvtepi32_ps(jv), _mm256_set1_ps(fx));
    const __m256 rbin = _mm256_fmadd_ps(dj, vsin, vrb0);
    const __m256 cbin = _mm256_fmadd_ps(dj, vcos, vcb0);
    const __m256 valid = _mm256_and_ps(
        _mm256_and_ps(_mm256_and_ps(_mm256_cmp_ps(rbin, minus_one, _CMP_GT_OQ), _mm256_cmp_ps(rbin, dv, _CMP_LT_OQ)),
                      _mm256_and_ps(_mm256_cmp_ps(cbin, minus_one, _CMP_GT_OQ), _mm256_cmp_ps(cbin, dv, _CMP_LT_OQ))),
        _mm256_castsi256_ps(_mm256_cmpgt_epi32(vend, jv)));
    unsigned bits = static_cast<unsigned>(_mm256_movemask_ps(valid));
    if (bits == 0) continue;
    __m256 mag, ori;
    Gradient8(row, above, below, j, &mag, &ori);
    __m256 obin = _mm256_mul_ps(_mm256_sub_ps(ori, vori), vbins);
    obin = _mm256_add_ps(obin, _mm256_and_ps(_mm256_cmp_ps(obin, zero, _CMP_LT_OQ), nv));
    obin = _mm256_sub_ps(obin, _mm256_and_ps(_mm256_cmp_ps(obin, nv, _CMP_GE_OQ), nv));
    _mm256_store_ps(rbins, rbin);
    _mm256_store_ps(cbins, cbin);
    _mm256_store_ps(obins, obin);
    _mm256_store_ps(mags, _mm256_mul_ps(mag, _mm256_mul_ps(vwrow, _mm256_loadu_ps(wcol + j))));
    for (; bits != 0; bits &= bits - 1) {
      const int lane = std::countr_zero(bits);
      AccumulateSample(hist, rbins[lane], cbins[lane], obins[lane], mags[lane]);
    }
  }
  return j;
}
#endif

#ifdef OXBOW_AVX512
OXBOW_AVX512_BEGIN
// One row of the descriptor window for the AVX-512 path: samples j0 <= j < j1, at image columns cx + j
// of `row` (rows above and below for the gradient), with the row's bin offsets and Gaussian weight.
struct DescriptorWindowRow {
  const float* row;
  const float* above;
  const float* below;
  int j0, j1;
  float rb0, cb0, wrow;
};

// The constants of one keypoint's window.
struct DescriptorFrame {
  float fx, sin_t, cos_t, ori_deg, bins_per_deg;
  const float* wcol;  // column weights, indexed by j
};

// 16 consecutive samples of a window row made ready to add: which are inside the window, their bin
// coordinates and their weighted magnitude per orientation bin (m (1 - o1) for bin k0 = floor(obin),
// m o1 for bin (k0 + 1) mod n, else 0).
struct DescriptorVector {
  __mmask16 valid;
  // Rows of 16 lanes, lane i at [row * 16 + i]: row 0 rbin, row 1 cbin, row 2 + k the weighted magnitude
  // for orientation bin k. A lane's values are then at constant offsets from one address.
  alignas(64) float lanes[(2 + kDescBins) * 16];
};

OXBOW_AVX512_TARGET inline void PrepareDescriptorVector(const DescriptorWindowRow& r, int j, const DescriptorFrame& f, DescriptorVector* out) {
  constexpr int d = kDescCells, n = kDescBins;
  const __m512i iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  const __m512 minus_one = _mm512_set1_ps(-1.0f), dv = _mm512_set1_ps(static_cast<float>(d));
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f), nv = _mm512_set1_ps(static_cast<float>(n));
  const __m512i jv = _mm512_add_epi32(_mm512_set1_epi32(j), iota);
  const __m512 dj = _mm512_sub_ps(_mm512_cvtepi32_ps(jv), _mm512_set1_ps(f.fx));
  const __m512 rbin = _mm512_fmadd_ps(dj, _mm512_set1_ps(f.sin_t), _mm512_set1_ps(r.rb0));
  const __m512 cbin = _mm512_fmadd_ps(dj, _mm512_set1_ps(f.cos_t), _mm512_set1_ps(r.cb0));
  out->valid = _mm512_cmp_ps_mask(rbin, minus_one, _CMP_GT_OQ) & _mm512_cmp_ps_mask(rbin, dv, _CMP_LT_OQ) &
               _mm512_cmp_ps_mask(cbin, minus_one, _CMP_GT_OQ) & _mm512_cmp_ps_mask(cbin, dv, _CMP_LT_OQ) &
               _mm512_cmpgt_epi32_mask(_mm512_set1_epi32(r.j1), jv);
  if (out->valid == 0) return;
  __m512 mag, ori;
  Gradient16(r.row, r.above, r.below, j, &mag, &ori);
  __m512 obin = _mm512_mul_ps(_mm512_sub_ps(ori, _mm512_set1_ps(f.ori_deg)), _mm512_set1_ps(f.bins_per_deg));
  obin = _mm512_mask_add_ps(obin, _mm512_cmp_ps_mask(obin, zero, _CMP_LT_OQ), obin, nv);
  obin = _mm512_mask_sub_ps(obin, _mm512_cmp_ps_mask(obin, nv, _CMP_GE_OQ), obin, nv);
  const __m512 m = _mm512_mul_ps(mag, _mm512_mul_ps(_mm512_set1_ps(r.wrow), _mm512_loadu_ps(f.wcol + j)));
  _mm512_storeu_ps(out->lanes, rbin);
  _mm512_storeu_ps(out->lanes + 16, cbin);
  const __m512i k0 = _mm512_cvttps_epi32(obin);
  const __m512i k1 = _mm512_and_si512(_mm512_add_epi32(k0, _mm512_set1_epi32(1)), _mm512_set1_epi32(n - 1));
  const __m512 o1 = _mm512_sub_ps(obin, _mm512_cvtepi32_ps(k0));
  const __m512 mo1 = _mm512_mul_ps(m, o1), mo0 = _mm512_mul_ps(m, _mm512_sub_ps(one, o1));
  for (int k = 0; k < n; ++k) {
    const __m512i kv = _mm512_set1_epi32(k);
    _mm512_storeu_ps(out->lanes + (2 + k) * 16, _mm512_mask_mov_ps(_mm512_maskz_mov_ps(_mm512_cmpeq_epi32_mask(k0, kv), mo0),
                                                    _mm512_cmpeq_epi32_mask(k1, kv), mo1));
  }
}

// Adds the valid samples of `v` in order, each to all 128 bins held in h (8 registers of 16 cells, one
// per orientation bin; cell = row * 4 + column).
OXBOW_AVX512_TARGET inline void AddDescriptorVector(const DescriptorVector& v, __m512 (&h)[kDescBins]) {
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f);
  const __m512 cell_row = _mm512_setr_ps(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3);
  const __m512 cell_col = _mm512_setr_ps(0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3);
  for (unsigned bits = v.valid; bits != 0; bits &= bits - 1) {
    const int lane = std::countr_zero(bits);
    // One pointer to the lane: its values are at constant offsets from it, which the broadcasts take
    // as address displacements instead of computing an address for each.
    const float* x = v.lanes + lane;
    const __m512 wr = _mm512_max_ps(_mm512_sub_ps(one, _mm512_abs_ps(_mm512_sub_ps(_mm512_set1_ps(x[0]), cell_row))), zero);
    const __m512 wc = _mm512_max_ps(_mm512_sub_ps(one, _mm512_abs_ps(_mm512_sub_ps(_mm512_set1_ps(x[16]), cell_col))), zero);
    const __m512 wcell = _mm512_mul_ps(wr, wc);
#pragma GCC unroll 8
    for (int k = 0; k < kDescBins; ++k) h[k] = _mm512_fmadd_ps(wcell, _mm512_set1_ps(x[(2 + k) * 16]), h[k]);
  }
}

// Descriptor's AVX-512 path over the whole window (WalkWindowPipelined). Every bin receives the same
// fused multiply-adds in the same sample order as on the other paths (zero weights add +0).
OXBOW_AVX512_TARGET void DescriptorWindowAvx512(std::span<const DescriptorWindowRow> rows, const DescriptorFrame& frame, float* hist) {
  __m512 h[kDescBins];
  for (__m512& bin : h) bin = _mm512_setzero_ps();
  WalkWindowPipelined<DescriptorVector>(
      rows,
      [&](const DescriptorWindowRow& row, int j, DescriptorVector* v)
          OXBOW_AVX512_TARGET { PrepareDescriptorVector(row, j, frame, v); },
      [&](const DescriptorVector& v) OXBOW_AVX512_TARGET { AddDescriptorVector(v, h); });
  for (int k = 0; k < kDescBins; ++k) _mm512_storeu_ps(hist + k * kDescCellCount, h[k]);
}
OXBOW_AVX512_END
#endif

// Writes the histogram hist[k * 16 + cell] to `out` cell-major (out[cell * n + k]), normalised to unit
// L2 norm, clipped at kDescClip of the norm and normalised again [L04 sec. 6.1].
void FinishDescriptor(const float* hist, float* out) {
  constexpr int n = kDescBins;
  for (int c = 0; c < kDescCellCount; ++c)
    for (int k = 0; k < n; ++k) out[c * n + k] = hist[k * kDescCellCount + c];
  float norm2 = 0;
  for (int k = 0; k < kDescriptorDim; ++k) norm2 += out[k] * out[k];
  const float clip = std::sqrt(norm2) * kDescClip;
  norm2 = 0;
  for (int k = 0; k < kDescriptorDim; ++k) {
    out[k] = std::min(out[k], clip);
    norm2 += out[k] * out[k];
  }
  const float inv = 1.0f / std::max(std::sqrt(norm2), 1.1920929e-07f);
  for (int k = 0; k < kDescriptorDim; ++k) out[k] *= inv;
}

// Computes the 128-d descriptor of the keypoint at sub-pixel (x, y) of `img` (octave pixels), scale
// `scale` (octave pixels) and orientation `ori_deg` (degrees, y axis up), unit L2 norm, clipped.
// `magnification`: cell width in keypoint scales; `row_step`: every row_step-th row of the window is sampled.
void Descriptor(const Plane& img, float x, float y, float ori_deg, float scale, float magnification, int row_step, float* out,
                bool simd) {
  constexpr int d = kDescCells, n = kDescBins;
  const int cx = static_cast<int>(std::lrint(x)), cy = static_cast<int>(std::lrint(y));
  const float fx = x - static_cast<float>(cx), fy = y - static_cast<float>(cy);
  const float angle = ori_deg * static_cast<float>(3.14159265358979323846 / 180.0);
  const float hist_width = magnification * scale;
  const int w = img.width(), h = img.height();
  int radius = static_cast<int>(std::lrint(hist_width * 1.4142135623730951f * (d + 1) * 0.5f));
  radius = std::min(radius, static_cast<int>(std::sqrt(static_cast<double>(w) * w + static_cast<double>(h) * h)));
  radius = std::min(radius, 250);
  const float cos_t = std::cos(angle) / hist_width, sin_t = std::sin(angle) / hist_width;
  const float bins_per_deg = n / 360.0f;
  // Gaussian weight of half the window width: exp(-(u^2 + v^2) / (2 (d/2)^2)) in cell units, which is
  // rotation invariant, so separable in the image offsets (j - fx, i - fy).
  const float exp_scale = -1.0f / (d * d * 0.5f * hist_width * hist_width);
  alignas(64) float wcol[512 + 16] = {};
  for (int j = -radius; j <= radius; ++j) {
    const float dj = static_cast<float>(j) - fx;
    wcol[j + radius] = std::exp(dj * dj * exp_scale);
  }
  alignas(64) float hist[kDescBins * kDescCellCount] = {};
#ifdef OXBOW_AVX512
  const bool avx512 = simd && Avx512Available();
  DescriptorWindowRow window[2 * 250 + 1];
  size_t window_rows = 0;
#endif
  const float half = d / 2.0f - 0.5f;
  for (int i = -radius; i <= radius; i += row_step) {
    const int yy = cy + i;
    if (yy <= 0 || yy >= h - 1) continue;
    const float di = static_cast<float>(i) - fy;
    const float wrow = std::exp(di * di * exp_scale);
    // rbin = dj * sin_t + di * cos_t + half, cbin = dj * cos_t - di * sin_t + half, both in (-1, d).
    const float rb0 = di * cos_t + half, cb0 = half - di * sin_t;
    // Columns where both bins may be in range (conservative; each sample is checked again below).
    float lo = -static_cast<float>(radius), hi = static_cast<float>(radius);
    auto restrict_range = [&](float slope, float intercept) {
      if (std::fabs(slope) < 1e-12f) {
        if (!(intercept > -1.0f && intercept < static_cast<float>(d))) hi = lo - 1;
        return;
      }
      float a = (-1.0f - intercept) / slope, b = (static_cast<float>(d) - intercept) / slope;
      if (a > b) std::swap(a, b);
      lo = std::max(lo, a + fx - 1.0f);
      hi = std::min(hi, b + fx + 1.0f);
    };
    restrict_range(sin_t, rb0);
    restrict_range(cos_t, cb0);
    int j0 = static_cast<int>(std::ceil(lo)), j1 = static_cast<int>(std::floor(hi)) + 1;
    j0 = std::max(j0, 1 - cx);
    j1 = std::min(j1, w - 1 - cx);
    if (j0 >= j1) continue;
    // Samples j of this row are at image column cx + j.
    const float* row = img.row(yy) + cx;
    const float* above = img.row(yy - 1) + cx;
    const float* below = img.row(yy + 1) + cx;
#ifdef OXBOW_AVX512
    if (avx512) {
      window[window_rows++] = {row, above, below, j0, j1, rb0, cb0, wrow};
      continue;
    }
#endif
#ifdef OXBOW_AVX2
    // The window's rows are far apart in memory; ask for the row needed three rows from now.
    if (yy + 3 * row_step < h) {
      const float* ahead = img.row(yy + 3 * row_step) + cx;
      for (int k = j0 - 1; k < j1 + 8; k += 16) _mm_prefetch(reinterpret_cast<const char*>(ahead + k), _MM_HINT_T0);
    }
#endif
    int j = j0;
#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
    if (simd) {
      j = DescriptorRowAvx2(row, above, below, j, j1, fx, sin_t, cos_t, rb0, cb0, ori_deg, bins_per_deg, wrow,
                            wcol + radius, hist);
    }
#endif
    for (; j < j1; ++j) {
      const float dj = static_cast<float>(j) - fx;
      const float rbin = std::fma(dj, sin_t, rb0);
      const float cbin = std::fma(dj, cos_t, cb0);
      if (!(rbin > -1.0f && rbin < static_cast<float>(d) && cbin > -1.0f && cbin < static_cast<float>(d))) continue;
      float mag, ori;
      Gradient(row, above, below, j, &mag, &ori);
      AccumulateSample(hist, rbin, cbin, OrientationBin(ori, ori_deg, bins_per_deg), mag * (wrow * wcol[j + radius]));
    }
  }
#ifdef OXBOW_AVX512
  if (avx512)
    DescriptorWindowAvx512(std::span<const DescriptorWindowRow>(window, window_rows),
                           DescriptorFrame{fx, sin_t, cos_t, ori_deg, bins_per_deg, wcol + radius}, hist);
#endif
  FinishDescriptor(hist, out);
}

// ---- Grid descriptor (DescriptorSampling::kGrid) -----------------------------------------------------

// The same 4 x 4 x 8 histogram as Descriptor's, from gradients taken at a fixed grid of points in the
// keypoint's frame instead of at every pixel of the rotated window. The level is sampled bilinearly at
// (kGridSide + 2)^2 points spaced kGridStep cells apart over the window's kGridHalfWidth cells on each
// side of the keypoint (the trilinear weights' support), a ring included; the kGridSide^2 inner points
// take central differences along the frame's axes, so their directions are already relative to the
// keypoint's. Each inner point adds its weighted magnitude to the two nearest orientation bins of every
// cell, with a fixed cell weight: the Gaussian of Descriptor times the two spatial tents, tabulated once.
// The points are about one keypoint sigma apart (cells 3 sigmas wide), where the level is already
// blurred by a sigma: 256 gradients per keypoint instead of 500-2,300. The Oxford affine pairs match as
// well as with the pixels; retrieval is lower (SiftOptions::descriptor_sampling).
constexpr int kGridSide = 16;
constexpr int kGridRing = kGridSide + 2;
constexpr int kGridPoints = kGridRing * kGridRing;
constexpr int kGridPadded = (kGridPoints + 15) / 16 * 16;  // whole vectors of 16
constexpr float kGridHalfWidth = 0.5f * (kDescCells + 1);
constexpr float kGridStep = 2.0f * kGridHalfWidth / kGridSide;
static_assert(kGridSide == 16, "the AVX-512 path takes one row of inner points per vector");

struct GridTables {
  // Frame coordinates (cells) of the sample points, row-major over the (kGridRing)^2 grid; the padding
  // repeats the last point.
  alignas(64) float u[kGridPadded];
  alignas(64) float v[kGridPadded];
  // Weight of inner point (i, j) in each of the 16 cells: [(i * kGridSide + j) * 16 + cell].
  alignas(64) float cell_weight[kGridSide * kGridSide * kDescCellCount];

  GridTables() {
    const float first = -kGridHalfWidth - 0.5f * kGridStep;  // the ring's
    for (int k = 0; k < kGridPadded; ++k) {
      const int p = std::min(k, kGridPoints - 1);
      const int row = p / kGridRing, column = p % kGridRing;
      v[k] = first + static_cast<float>(row) * kGridStep;
      u[k] = first + static_cast<float>(column) * kGridStep;
    }
    const float half = kDescCells / 2.0f - 0.5f;
    for (int i = 0; i < kGridSide; ++i) {
      for (int j = 0; j < kGridSide; ++j) {
        const float vi = first + static_cast<float>(i + 1) * kGridStep, uj = first + static_cast<float>(j + 1) * kGridStep;
        // Descriptor's Gaussian of half the window width, in cells: exp(-(u^2 + v^2) / (2 (d/2)^2)).
        const float gauss = std::exp(-(uj * uj + vi * vi) / (kDescCells * kDescCells * 0.5f));
        for (int cell = 0; cell < kDescCellCount; ++cell) {
          const int cell_row = cell / kDescCells, cell_column = cell % kDescCells;
          cell_weight[(i * kGridSide + j) * kDescCellCount + cell] =
              gauss * Tent(vi + half - static_cast<float>(cell_row)) * Tent(uj + half - static_cast<float>(cell_column));
        }
      }
    }
  }
};

const GridTables& Grid() {
  static const GridTables tables;
  return tables;
}

// The frame of one keypoint's grid: point (u, v) in cells is at image position
// (x + u * c + v * s, y + v * c - u * s), with c, s the cosine and sine of the orientation times the cell
// width; positions are clamped to the image, so points outside repeat its edge.
struct GridFrame {
  const float* base;  // the level's row 0
  int stride;         // floats between rows
  float x, y, c, s, x_max, y_max;
};

// The level's value at the grid point (u, v): bilinear, in the same fused multiply-adds on every path.
inline float GridSample(const GridFrame& f, float u, float v) {
  const float px = std::min(std::max(std::fma(u, f.c, std::fma(v, f.s, f.x)), 0.0f), f.x_max);
  const float py = std::min(std::max(std::fma(-u, f.s, std::fma(v, f.c, f.y)), 0.0f), f.y_max);
  const int ix = static_cast<int>(px), iy = static_cast<int>(py);
  const float ax = px - static_cast<float>(ix), ay = py - static_cast<float>(iy);
  const float* p = f.base + static_cast<size_t>(iy) * static_cast<size_t>(f.stride) + ix;
  const float top = std::fma(ax, p[1] - p[0], p[0]);
  const float bottom = std::fma(ax, p[f.stride + 1] - p[f.stride], p[f.stride]);
  return std::fma(ay, bottom - top, top);
}

// Gradient of inner point (i, j) from the sampled grid: magnitude and orientation bin (in [0, n)).
inline void GridGradient(const float* samples, int i, int j, float* mag, float* obin) {
  const float* mid = samples + (i + 1) * kGridRing + j;
  const float gu = mid[2] - mid[0];
  const float gv = mid[kGridRing + 1] - mid[1 - kGridRing];
  *mag = std::sqrt(std::fma(gu, gu, gv * gv));
  // Direction in the frame, y axis up: along u, and against v (v points down the image when the
  // orientation is 0).
  float o = FastAtan2Deg(0.0f - gv, gu) * (kDescBins / 360.0f);
  if (o >= static_cast<float>(kDescBins)) o -= static_cast<float>(kDescBins);
  *obin = o;
}

void GridHistogramScalar(const GridFrame& f, float* hist) {
  const GridTables& t = Grid();
  float samples[kGridPadded];
  for (int k = 0; k < kGridPoints; ++k) samples[k] = GridSample(f, t.u[k], t.v[k]);
  for (int i = 0; i < kGridSide; ++i) {
    for (int j = 0; j < kGridSide; ++j) {
      float mag, obin;
      GridGradient(samples, i, j, &mag, &obin);
      const int k0 = static_cast<int>(obin), k1 = (k0 + 1) & (kDescBins - 1);
      const float o1 = obin - static_cast<float>(k0);
      const float mo1 = mag * o1, mo0 = mag * (1.0f - o1);
      const float* w = t.cell_weight + (i * kGridSide + j) * kDescCellCount;
      for (int cell = 0; cell < kDescCellCount; ++cell) {
        hist[k0 * kDescCellCount + cell] = std::fma(w[cell], mo0, hist[k0 * kDescCellCount + cell]);
        hist[k1 * kDescCellCount + cell] = std::fma(w[cell], mo1, hist[k1 * kDescCellCount + cell]);
      }
    }
  }
}

#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
// GridHistogramScalar 8 lanes at a time (bit-identical): the samples 8 points at a time, the
// gradients 8 inner points at a time, every bin added for every inner point (zero weights add +0).
OXBOW_AVX2_TARGET void GridHistogramAvx2(const GridFrame& f, float* hist) {
  const GridTables& t = Grid();
  alignas(32) float samples[kGridPadded];
  const __m256 vx = _mm256_set1_ps(f.x), vy = _mm256_set1_ps(f.y), vc = _mm256_set1_ps(f.c), vs = _mm256_set1_ps(f.s);
  const __m256 x_max = _mm256_set1_ps(f.x_max), y_max = _mm256_set1_ps(f.y_max), zero = _mm256_setzero_ps();
  const __m256i stride = _mm256_set1_epi32(f.stride);
  const float* below = f.base + f.stride;
  for (int k = 0; k < kGridPadded; k += 8) {
    const __m256 u = _mm256_load_ps(t.u + k), v = _mm256_load_ps(t.v + k);
    const __m256 px = _mm256_min_ps(_mm256_max_ps(_mm256_fmadd_ps(u, vc, _mm256_fmadd_ps(v, vs, vx)), zero), x_max);
    const __m256 py = _mm256_min_ps(_mm256_max_ps(_mm256_fnmadd_ps(u, vs, _mm256_fmadd_ps(v, vc, vy)), zero), y_max);
    const __m256i ix = _mm256_cvttps_epi32(px), iy = _mm256_cvttps_epi32(py);
    const __m256 ax = _mm256_sub_ps(px, _mm256_cvtepi32_ps(ix)), ay = _mm256_sub_ps(py, _mm256_cvtepi32_ps(iy));
    const __m256i at = _mm256_add_epi32(_mm256_mullo_epi32(iy, stride), ix);
    const __m256 p00 = _mm256_i32gather_ps(f.base, at, 4), p01 = _mm256_i32gather_ps(f.base + 1, at, 4);
    const __m256 p10 = _mm256_i32gather_ps(below, at, 4), p11 = _mm256_i32gather_ps(below + 1, at, 4);
    const __m256 top = _mm256_fmadd_ps(ax, _mm256_sub_ps(p01, p00), p00);
    const __m256 bottom = _mm256_fmadd_ps(ax, _mm256_sub_ps(p11, p10), p10);
    _mm256_store_ps(samples + k, _mm256_fmadd_ps(ay, _mm256_sub_ps(bottom, top), top));
  }
  __m256 h[kDescBins][2];
  for (auto& bin : h) bin[0] = bin[1] = _mm256_setzero_ps();
  const __m256 bins = _mm256_set1_ps(kDescBins / 360.0f), nv = _mm256_set1_ps(static_cast<float>(kDescBins));
  const __m256 one = _mm256_set1_ps(1.0f);
  alignas(32) float values[kDescBins][8];
  for (int i = 0; i < kGridSide; ++i) {
    for (int j0 = 0; j0 < kGridSide; j0 += 8) {
      const float* mid = samples + (i + 1) * kGridRing + j0;
      const __m256 gu = _mm256_sub_ps(_mm256_loadu_ps(mid + 2), _mm256_loadu_ps(mid));
      const __m256 gv = _mm256_sub_ps(_mm256_loadu_ps(mid + kGridRing + 1), _mm256_loadu_ps(mid + 1 - kGridRing));
      const __m256 mag = _mm256_sqrt_ps(_mm256_fmadd_ps(gu, gu, _mm256_mul_ps(gv, gv)));
      __m256 obin = _mm256_mul_ps(Atan2Deg8(_mm256_sub_ps(zero, gv), gu), bins);
      obin = _mm256_sub_ps(obin, _mm256_and_ps(_mm256_cmp_ps(obin, nv, _CMP_GE_OQ), nv));
      const __m256i k0 = _mm256_cvttps_epi32(obin);
      const __m256i k1 = _mm256_and_si256(_mm256_add_epi32(k0, _mm256_set1_epi32(1)), _mm256_set1_epi32(kDescBins - 1));
      const __m256 o1 = _mm256_sub_ps(obin, _mm256_cvtepi32_ps(k0));
      const __m256 mo1 = _mm256_mul_ps(mag, o1), mo0 = _mm256_mul_ps(mag, _mm256_sub_ps(one, o1));
      for (int k = 0; k < kDescBins; ++k) {
        const __m256i kv = _mm256_set1_epi32(k);
        const __m256 is0 = _mm256_castsi256_ps(_mm256_cmpeq_epi32(k0, kv));
        const __m256 is1 = _mm256_castsi256_ps(_mm256_cmpeq_epi32(k1, kv));
        _mm256_store_ps(values[k], _mm256_or_ps(_mm256_and_ps(is0, mo0), _mm256_and_ps(is1, mo1)));
      }
      const float* w = t.cell_weight + (i * kGridSide + j0) * kDescCellCount;
      for (int j = 0; j < 8; ++j) {
        const __m256 w0 = _mm256_load_ps(w + j * kDescCellCount), w1 = _mm256_load_ps(w + j * kDescCellCount + 8);
        for (int k = 0; k < kDescBins; ++k) {
          const __m256 value = _mm256_set1_ps(values[k][j]);
          h[k][0] = _mm256_fmadd_ps(w0, value, h[k][0]);
          h[k][1] = _mm256_fmadd_ps(w1, value, h[k][1]);
        }
      }
    }
  }
  for (int k = 0; k < kDescBins; ++k) {
    _mm256_storeu_ps(hist + k * kDescCellCount, h[k][0]);
    _mm256_storeu_ps(hist + k * kDescCellCount + 8, h[k][1]);
  }
}
#endif

#ifdef OXBOW_AVX512
OXBOW_AVX512_BEGIN
// GridHistogramScalar 16 lanes at a time (bit-identical): one row of inner points per vector, the 128
// bins in 8 registers of 16 cells, every bin added for every inner point (zero weights add +0).
OXBOW_AVX512_TARGET void GridHistogramAvx512(const GridFrame& f, float* hist) {
  const GridTables& t = Grid();
  alignas(64) float samples[kGridPadded];
  const __m512 vx = _mm512_set1_ps(f.x), vy = _mm512_set1_ps(f.y), vc = _mm512_set1_ps(f.c), vs = _mm512_set1_ps(f.s);
  const __m512 x_max = _mm512_set1_ps(f.x_max), y_max = _mm512_set1_ps(f.y_max), zero = _mm512_setzero_ps();
  const __m512i stride = _mm512_set1_epi32(f.stride);
  const float* below = f.base + f.stride;
  for (int k = 0; k < kGridPadded; k += 16) {
    const __m512 u = _mm512_load_ps(t.u + k), v = _mm512_load_ps(t.v + k);
    const __m512 px = _mm512_min_ps(_mm512_max_ps(_mm512_fmadd_ps(u, vc, _mm512_fmadd_ps(v, vs, vx)), zero), x_max);
    const __m512 py = _mm512_min_ps(_mm512_max_ps(_mm512_fnmadd_ps(u, vs, _mm512_fmadd_ps(v, vc, vy)), zero), y_max);
    const __m512i ix = _mm512_cvttps_epi32(px), iy = _mm512_cvttps_epi32(py);
    const __m512 ax = _mm512_sub_ps(px, _mm512_cvtepi32_ps(ix)), ay = _mm512_sub_ps(py, _mm512_cvtepi32_ps(iy));
    const __m512i at = _mm512_add_epi32(_mm512_mullo_epi32(iy, stride), ix);
    const __m512 p00 = _mm512_i32gather_ps(at, f.base, 4), p01 = _mm512_i32gather_ps(at, f.base + 1, 4);
    const __m512 p10 = _mm512_i32gather_ps(at, below, 4), p11 = _mm512_i32gather_ps(at, below + 1, 4);
    const __m512 top = _mm512_fmadd_ps(ax, _mm512_sub_ps(p01, p00), p00);
    const __m512 bottom = _mm512_fmadd_ps(ax, _mm512_sub_ps(p11, p10), p10);
    _mm512_store_ps(samples + k, _mm512_fmadd_ps(ay, _mm512_sub_ps(bottom, top), top));
  }
  __m512 h[kDescBins];
  for (__m512& bin : h) bin = _mm512_setzero_ps();
  const __m512 bins = _mm512_set1_ps(kDescBins / 360.0f), nv = _mm512_set1_ps(static_cast<float>(kDescBins));
  const __m512 one = _mm512_set1_ps(1.0f);
  alignas(64) float values[kDescBins][16];
  for (int i = 0; i < kGridSide; ++i) {
    const float* mid = samples + (i + 1) * kGridRing;
    const __m512 gu = _mm512_sub_ps(_mm512_loadu_ps(mid + 2), _mm512_loadu_ps(mid));
    const __m512 gv = _mm512_sub_ps(_mm512_loadu_ps(mid + kGridRing + 1), _mm512_loadu_ps(mid + 1 - kGridRing));
    const __m512 mag = _mm512_sqrt_ps(_mm512_fmadd_ps(gu, gu, _mm512_mul_ps(gv, gv)));
    __m512 obin = _mm512_mul_ps(Atan2Deg16(_mm512_sub_ps(zero, gv), gu), bins);
    obin = _mm512_mask_sub_ps(obin, _mm512_cmp_ps_mask(obin, nv, _CMP_GE_OQ), obin, nv);
    const __m512i k0 = _mm512_cvttps_epi32(obin);
    const __m512i k1 = _mm512_and_si512(_mm512_add_epi32(k0, _mm512_set1_epi32(1)), _mm512_set1_epi32(kDescBins - 1));
    const __m512 o1 = _mm512_sub_ps(obin, _mm512_cvtepi32_ps(k0));
    const __m512 mo1 = _mm512_mul_ps(mag, o1), mo0 = _mm512_mul_ps(mag, _mm512_sub_ps(one, o1));
    for (int k = 0; k < kDescBins; ++k) {
      const __m512i kv = _mm512_set1_epi32(k);
      _mm512_store_ps(values[k], _mm512_mask_mov_ps(_mm512_maskz_mov_ps(_mm512_cmpeq_epi32_mask(k0, kv), mo0),
                                                    _mm512_cmpeq_epi32_mask(k1, kv), mo1));
    }
    const float* w = t.cell_weight + i * kGridSide * kDescCellCount;
    for (int j = 0; j < kGridSide; ++j) {
      const __m512 wj = _mm512_load_ps(w + j * kDescCellCount);
#pragma GCC unroll 8
      for (int k = 0; k < kDescBins; ++k) h[k] = _mm512_fmadd_ps(wj, _mm512_set1_ps(values[k][j]), h[k]);
    }
  }
  for (int k = 0; k < kDescBins; ++k) _mm512_storeu_ps(hist + k * kDescCellCount, h[k]);
}
OXBOW_AVX512_END
#endif

// Computes the grid descriptor of the keypoint at sub-pixel (x, y) of `img` (octave pixels), scale
// `scale` (octave pixels) and orientation `ori_deg` (degrees, y axis up): the layout, normalisation
// and clipping of Descriptor's.
void GridDescriptor(const Plane& img, float x, float y, float ori_deg, float scale, float magnification, float* out,
                    bool simd) {
  const float angle = ori_deg * static_cast<float>(3.14159265358979323846 / 180.0);
  const float cell = magnification * scale;
  // x_max, y_max keep the bilinear reads inside the image (a position at the last column or row is moved
  // a thousandth of a pixel in).
  const GridFrame frame{img.row(0), static_cast<int>(img.stride()), x, y, std::cos(angle) * cell, std::sin(angle) * cell,
                        static_cast<float>(img.width() - 1) - 1e-3f, static_cast<float>(img.height() - 1) - 1e-3f};
  alignas(64) float hist[kDescBins * kDescCellCount] = {};
  // The vector paths index the level with 32-bit offsets.
  const bool vector_offsets = img.stride() * static_cast<size_t>(img.height()) < (size_t{1} << 31) - img.stride();
#ifdef OXBOW_AVX512
  if (simd && vector_offsets && Avx512Available()) {
    GridHistogramAvx512(frame, hist);
    FinishDescriptor(hist, out);
    return;
  }
#endif
#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
  if (simd && vector_offsets) {
    GridHistogramAvx2(frame, hist);
    FinishDescriptor(hist, out);
    return;
  }
#endif
  (void)simd;
  (void)vector_offsets;
  GridHistogramScalar(frame, hist);
  FinishDescriptor(hist, out);
}

// Orientations (degrees, y axis up, [0, 360)) found for one refined extremum; at most one per two bins
// since peaks are strict local maxima of the circular histogram.
struct PointOrientations {
  int count = 0;
  float degrees[kOriBins / 2];
};

// Pyramid buffers kept by a thread between calls, so that a thread extracting image after image does
// not pay the page faults (and the kernel's zeroing) of ~100 MB of fresh memory per image.
struct Scratch {
  std::vector<Plane> gauss;
  Plane spare;

  // Takes the octave planes back, then frees everything when the total exceeds `limit_mib`.
  void Keep(std::vector<Plane> planes, int limit_mib) {
    gauss = std::move(planes);
    size_t bytes = spare.capacity_bytes();
    for (const Plane& plane : gauss) bytes += plane.capacity_bytes();
    if (bytes > (static_cast<size_t>(limit_mib) << 20)) {
      gauss.clear();
      spare = Plane();
    }
  }
};

Scratch& ThreadScratch() {
  thread_local Scratch scratch;
  return scratch;
}

// Where level 0 of a strip comes from: the input image upsampled 2x row by row (`image`), a plane to
// blur (`base`), or, with neither, level 0 is already made (a later octave's decimated base).
struct StripSource {
  const GrayImage* image = nullptr;
  const Plane* base = nullptr;
};

// A strip recomputes the rows its blurs and scan read beyond its own (about 50 per level on the first
// octave): strips thinner than this would redo much of their neighbours' work.
constexpr int kMinStripRows = 128;

// A strip's own memory, kept by each thread between strips: per level the rows just above and below
// the strip, the upsampled base's rows and the blur's block.
struct StripScratch {
  std::vector<Plane> above, below;
  std::vector<float> base_ring, upsample;
  BlurScratch blur;

  size_t Bytes() const {
    size_t bytes = (base_ring.capacity() + upsample.capacity() + blur.padded.capacity()) * sizeof(float);
    for (const Plane& plane : above) bytes += plane.capacity_bytes();
    for (const Plane& plane : below) bytes += plane.capacity_bytes();
    return bytes;
  }
};

StripScratch& ThreadStripScratch() {
  thread_local StripScratch scratch;
  return scratch;
}

// Makes rows [s, e) of the octave's levels (from level 0, or from level 1 when level 0 is already
// made) and returns the candidate extrema among them, in (layer, row, column) order. Every level is
// blurred a block of rows at a time just before the scan (or the next level) reads it, so the rows a
// level reads come from cache. The rows above and below the strip that its blurs and scan read are
// made too, into the thread's own memory: the octave's planes receive only rows [s, e), so strips run
// at once on different threads, and each row has the same value whatever the strips. poll() returning
// false abandons the strip.
std::vector<Candidate> BuildStrip(Octave* octave, const StripSource& source, const std::vector<std::vector<float>>& kernels,
                                  int intervals, float threshold, int s, int e, bool simd, int cache_mib,
                                  const std::function<bool()>& poll) {
  const int levels = intervals + 3;
  const int w = octave->gauss[0].width(), h = octave->gauss[0].height();
  const int first = source.image || source.base ? 0 : 1;
  const auto radius = [&](int i) { return static_cast<int>(kernels[static_cast<size_t>(i)].size()) - 1; };
  // Rows [lo[i], hi[i]) of level i are made: the scan reads one row beyond the strip, and each blur
  // reads its radius beyond the rows it makes.
  std::vector<int> halo(static_cast<size_t>(levels), 1), lo(halo.size(), 0), hi(halo.size(), h), produced(halo.size(), h);
  for (int i = levels - 1; i > first; --i) halo[static_cast<size_t>(i) - 1] = halo[static_cast<size_t>(i)] + radius(i);
  StripScratch& scratch = ThreadStripScratch();
  scratch.above.resize(static_cast<size_t>(levels));
  scratch.below.resize(static_cast<size_t>(levels));
  for (int i = first; i < levels; ++i) {
    const auto l = static_cast<size_t>(i);
    lo[l] = std::max(0, s - halo[l]);
    hi[l] = std::min(h, e + halo[l]);
    produced[l] = lo[l];
    scratch.above[l].Reshape(w, s - lo[l]);
    scratch.below[l].Reshape(w, hi[l] - e);
  }
  const auto row = [&](int i, int y) -> float* {
    const auto l = static_cast<size_t>(i);
    if (i < first || (y >= s && y < e)) return octave->gauss[l].row(y);
    return y < s ? scratch.above[l].row(y - lo[l]) : scratch.below[l].row(y - e);
  };
  // The upsampled base's rows, made on demand into a ring that holds what one block of the first blur
  // reads: 2 r + kRowBlock rows.
  const int base_ring_rows = source.image ? 2 * radius(0) + kRowBlock : 0;
  const size_t base_pitch = (static_cast<size_t>(w) + 15) / 16 * 16;
  if (source.image) {
    scratch.base_ring.resize(static_cast<size_t>(base_ring_rows) * base_pitch);
    scratch.upsample.resize(static_cast<size_t>(source.image->width));
  }
  int base_made = source.image ? std::max(0, lo[0] - radius(0)) : 0;
  const std::function<const float*(int)> base_row = [&](int i) -> const float* {
    if (source.base) return source.base->row(i);
    return scratch.base_ring.data() + static_cast<size_t>(i % base_ring_rows) * base_pitch;
  };
  // Makes rows [lo[i], n) of level i final, first the rows of the levels below that it reads.
  std::function<void(int, int)> produce = [&](int i, int n) {
    const auto l = static_cast<size_t>(i);
    n = std::min(n, hi[l]);
    const std::function<float*(int)> dest = [&](int y) { return row(i, y); };
    while (produced[l] < n) {
      const int y = produced[l], count = std::min(kRowBlock, hi[l] - y);
      if (i > 0) {
        produce(i - 1, y + count + radius(i));
        GaussianBlurRows([&](int y2) -> const float* { return row(i - 1, y2); }, dest, w, h, kernels[l], y, count,
                         &scratch.blur, simd);
      } else {
        if (source.image) {
          const GrayImage& image = *source.image;
          for (; base_made < std::min(h, y + count + radius(0)); ++base_made)
            Upsample2xRow(image.pixels.data(), image.width, image.height, static_cast<size_t>(image.width), base_made,
                          scratch.upsample.data(),
                          scratch.base_ring.data() + static_cast<size_t>(base_made % base_ring_rows) * base_pitch);
        }
        GaussianBlurRows(base_row, dest, w, h, kernels[0], y, count, &scratch.blur, simd);
      }
      produced[l] += count;
    }
  };
  int polls = 0;
  bool stopped = false;
  std::vector<Candidate> candidates = ScanRows(
      [&](int i, int y) -> const float* { return row(i, y); }, w, h, octave->gauss[0].stride(), s, e, intervals, threshold,
      simd, [&](int n) {
        if ((++polls & 63) == 0 && !poll()) {
          stopped = true;
          return false;
        }
        produce(levels - 1, n);
        return true;
      });
  if (!stopped) produce(levels - 1, e);  // the strip's rows below the last scanned one
  if (scratch.Bytes() > (static_cast<size_t>(cache_mib) << 20)) scratch = StripScratch();
  return candidates;
}

}  // namespace

FeatureSet ExtractImpl(const GrayImage& image, const SiftOptions& options, bool simd, const StopRequested& stop) {
  simd = simd && Avx2FmaAvailable();  // the functions below trust it
  OXBOW_CHECK(!options.Check().has_value(), "invalid SiftOptions");
  OXBOW_CHECK(image.pixels.size() == static_cast<size_t>(std::max(image.width, 0)) * static_cast<size_t>(std::max(image.height, 0)),
              "GrayImage pixel count does not match width * height");
  FeatureSet result;
  result.image_width = image.width;
  result.image_height = image.height;
  result.kind = options.descriptor;
  if (image.width <= 0 || image.height <= 0) return result;

  const auto stopped = [&stop] { return stop && stop(); };
  const int threads = ResolveThreadCount(options.num_threads);
  WorkerTeam team(threads);
  const int S = options.intervals;
  const double sigma = options.sigma;

  // Pyramid buffers: the calling thread's cache (see ThreadScratch); returned to it at the end.
  Scratch& scratch = ThreadScratch();
  Octave octave;
  octave.gauss.swap(scratch.gauss);
  octave.gauss.resize(static_cast<size_t>(S) + 3);


  // `spare` holds the base image of octave 0 when it is the input itself (still to be blurred from the
  // assumed camera blur to sigma), then the decimated base of each next octave. The 2x upsampled base is
  // never stored whole: each strip makes the rows its first blur reads (see BuildStrip).
  Plane& spare = scratch.spare;
  double present_blur = options.assumed_blur;
  if (options.upsample_first_octave) {
    present_blur *= 2;
  } else {
    spare.Reshape(image.width, image.height);
    for (int y = 0; y < image.height; ++y)
      std::copy_n(image.pixels.data() + static_cast<size_t>(y) * static_cast<size_t>(image.width), image.width, spare.row(y));
  }
  const double first_blur = std::sqrt(std::max(sigma * sigma - present_blur * present_blur, 0.01));

  const int base_width = options.upsample_first_octave ? 2 * image.width : image.width;
  const int base_height = options.upsample_first_octave ? 2 * image.height : image.height;
  const int min_side = std::min(base_width, base_height);
  // As cv::SIFT: round(log2(min side of the base) - 2) octaves, plus one for the upsampled octave.
  int octaves = static_cast<int>(std::lrint(std::log2(static_cast<double>(min_side)) - 2.0)) +
                (options.upsample_first_octave ? 1 : 0);
  if (options.max_octaves) octaves = std::min(octaves, *options.max_octaves);
  if (octaves <= 0) {
    scratch.Keep(std::move(octave.gauss), options.thread_cache_mib);
    return result;
  }

  // Incremental blurs: level i has total blur sigma * k^i; level i is level i-1 blurred by
  // sqrt(sigma_i^2 - sigma_{i-1}^2).
  std::vector<std::vector<float>> kernels(static_cast<size_t>(S) + 3);
  kernels[0] = GaussianHalfKernel(first_blur, options.kernel_radius_sigmas);
  const double k = std::pow(2.0, 1.0 / S);
  for (int i = 1; i < S + 3; ++i) {
    const double previous = std::pow(k, i - 1) * sigma, total = previous * k;
    kernels[static_cast<size_t>(i)] = GaussianHalfKernel(std::sqrt(total * total - previous * previous), options.kernel_radius_sigmas);
  }

  // OpenCV quantises the pre-filter threshold to 8-bit grey levels; doing the same keeps the candidate
  // set (and so the keypoints) identical to cv::SIFT's.
  const float scan_threshold = static_cast<float>(std::floor(0.5 * options.contrast_threshold / S * 255.0) / 255.0);
  const double coordinate_scale = options.upsample_first_octave ? 0.5 : 1.0;
  const double coordinate_shift = options.upsample_first_octave ? -0.25 : 0.0;  // pixel centres, see Upsample2xRow

  // The S + 3 planes of octave 0 are reused by the (smaller) later octaves; `spare` receives the
  // decimated base of the next octave.
  for (int o = 0; o < octaves && !stopped(); ++o) {
    octave.index = o;
    if (o > 0) std::swap(octave.gauss[0], spare);
    const int ow = o == 0 ? base_width : octave.gauss[0].width();
    const int oh = o == 0 ? base_height : octave.gauss[0].height();
    if (ow < 1 || oh < 1) break;
    for (int i = o == 0 ? 0 : 1; i < S + 3; ++i) octave.gauss[static_cast<size_t>(i)].Reshape(ow, oh);
    // The octave's rows in horizontal strips, one per worker (none thinner than kMinStripRows): each
    // strip blurs its levels a block of rows at a time just before the scan needs them, so that the rows
    // a level reads are recent and come from cache. Rows and candidates do not depend on the strips.
    const int strips = std::clamp(oh / kMinStripRows, 1, team.size());
    std::vector<std::vector<Candidate>> found(static_cast<size_t>(strips));
    std::atomic<bool> abandon{false};
    team.ParallelFor(static_cast<size_t>(strips), 1, [&](size_t begin, size_t end, int worker) {
      for (size_t strip = begin; strip < end; ++strip) {
        const int y0 = static_cast<int>(static_cast<int64_t>(oh) * static_cast<int64_t>(strip) / strips);
        const int y1 = static_cast<int>(static_cast<int64_t>(oh) * static_cast<int64_t>(strip + 1) / strips);
        // Only the calling thread (worker 0) may ask `stop`; the others follow `abandon`.
        const auto poll = [&] {
          if (worker == 0 && stopped()) abandon = true;
          return !abandon;
        };
        StripSource source;
        if (o == 0 && options.upsample_first_octave) {
          source.image = &image;
        } else if (o == 0) {
          source.base = &spare;
        }
        found[strip] = BuildStrip(&octave, source, kernels, S, scan_threshold, y0, y1, simd, options.thread_cache_mib, poll);
      }
    });
    if (abandon || stopped()) break;
    // Each strip's candidates are in (layer, row, column) order and the strips in row order.
    std::vector<Candidate> candidates;
    for (auto& f : found) candidates.insert(candidates.end(), f.begin(), f.end());
    std::stable_sort(candidates.begin(), candidates.end(), [](const Candidate& a, const Candidate& b) { return a.layer < b.layer; });
    std::vector<std::optional<Refined>> refined(candidates.size());
    team.ParallelFor(candidates.size(), 64, [&](size_t b, size_t e, int) {
      for (size_t i = b; i < e; ++i)
        refined[i] = options.keypoint_style == KeypointStyle::kVlfeat ? RefineInSpace(octave, candidates[i], options)
                                                                      : Refine(octave, candidates[i], options);
    });
    // Two candidates can converge onto the same sample; keep the first (as cv::SIFT removes duplicates).
    std::vector<Refined> unique;
    {
      std::vector<uint64_t> seen;
      for (const auto& r : refined) {
        if (!r) continue;
        const uint64_t key = (static_cast<uint64_t>(r->layer) << 58) | (static_cast<uint64_t>(r->r) << 29) | static_cast<uint64_t>(r->c);
        seen.push_back(key);
        unique.push_back(*r);
      }
      std::vector<size_t> order(unique.size());
      for (size_t i = 0; i < order.size(); ++i) order[i] = i;
      std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return seen[a] < seen[b]; });
      std::vector<bool> keep(unique.size(), true);
      for (size_t i = 1; i < order.size(); ++i)
        if (seen[order[i]] == seen[order[i - 1]]) keep[order[i]] = false;
      std::vector<Refined> kept;
      for (size_t i = 0; i < unique.size(); ++i)
        if (keep[i]) kept.push_back(unique[i]);
      unique.swap(kept);
    }

    // Orientations of every point first, then descriptors written straight into the result at offsets
    // known from the counts: no per-point allocation, and the order is that of `unique` for any
    // thread count.
    std::vector<PointOrientations> orientations(unique.size());
    std::vector<float> scales(unique.size());
    team.ParallelFor(unique.size(), 32, [&](size_t b, size_t e, int) {
      float hist[kOriBins];
      for (size_t i = b; i < e; ++i) {
        const Refined& p = unique[i];
        const float scale_octave = static_cast<float>(sigma * std::pow(2.0, (p.layer + p.xi) / S));
        scales[i] = scale_octave;
        if (options.upright) {
          orientations[i].count = 1;
          orientations[i].degrees[0] = 0.0f;
          continue;
        }
        const Plane& img = octave.gauss[static_cast<size_t>(p.level)];
        const float max_value =
            options.keypoint_style == KeypointStyle::kVlfeat
                ? OrientationHistogramCircular(img, static_cast<float>(p.c + p.xc), static_cast<float>(p.r + p.xr),
                                               kOriSigmaFactor * scale_octave, hist, simd)
                : OrientationHistogram(img, p.c, p.r, static_cast<int>(std::lrint(kOriRadiusFactor * scale_octave)),
                                       kOriSigmaFactor * scale_octave, hist, simd);
        const float threshold = static_cast<float>(max_value * options.orientation_peak_ratio);
        PointOrientations& out = orientations[i];
        for (int j = 0; j < kOriBins; ++j) {
          const int left = j > 0 ? j - 1 : kOriBins - 1, right = j < kOriBins - 1 ? j + 1 : 0;
          if (!(hist[j] > hist[left] && hist[j] > hist[right] && hist[j] >= threshold)) continue;
          float bin = j + 0.5f * (hist[left] - hist[right]) / (hist[left] - 2 * hist[j] + hist[right]);
          bin = bin < 0 ? kOriBins + bin : bin >= kOriBins ? bin - kOriBins : bin;
          out.degrees[out.count++] = (360.0f / kOriBins) * bin;  // degrees, y axis up
        }
      }
    });
    if (stopped()) break;
    std::vector<size_t> first(unique.size() + 1);
    first[0] = result.keypoints.size();
    for (size_t i = 0; i < unique.size(); ++i) first[i + 1] = first[i] + static_cast<size_t>(orientations[i].count);
    if (o == 0) {
      // Room for the later octaves' points now spares copying the descriptors as they grow. They add
      // 0.3-1.0 times octave 0's points in all (graf1 0.86, boat img1 0.28, Paris and distractor photos
      // 0.32-1.04), so some photos grow once more; twice octave 0's measured no faster over 40 Paris
      // photos in one process.
      const size_t expected = first.back() + first.back() / 2 + 64;
      result.keypoints.reserve(expected);
      result.descriptors.reserve(expected * kDescriptorDim);
    }
    result.keypoints.resize(first.back());
    result.descriptors.resize(first.back() * kDescriptorDim);
    const double octave_scale = std::ldexp(1.0, o);
    team.ParallelFor(unique.size(), 16, [&](size_t b, size_t e, int) {
      for (size_t i = b; i < e; ++i) {
        const Refined& p = unique[i];
        const float scale_octave = scales[i];
        const Plane& img = octave.gauss[static_cast<size_t>(p.level)];
        const double x_octave = p.c + p.xc, y_octave = p.r + p.xr;
        for (int a = 0; a < orientations[i].count; ++a) {
          const float ori_up = orientations[i].degrees[a];
          const size_t index = first[i] + static_cast<size_t>(a);
          Keypoint& kp = result.keypoints[index];
          kp.x = static_cast<float>(x_octave * octave_scale * coordinate_scale + coordinate_shift);
          kp.y = static_cast<float>(y_octave * octave_scale * coordinate_scale + coordinate_shift);
          kp.scale = static_cast<float>(scale_octave * octave_scale * coordinate_scale);
          // y-down orientation from +x towards +y = 360 - ori_up.
          double angle = 360.0 - ori_up;
          if (angle >= 360.0 - 1e-4) angle = 0.0;
          kp.orientation = static_cast<float>(angle * (3.14159265358979323846 / 180.0));
          kp.response = std::fabs(p.contrast);
          kp.octave = o - (options.upsample_first_octave ? 1 : 0);
          float* descriptor = result.descriptors.data() + index * kDescriptorDim;
          if (options.descriptor_sampling == DescriptorSampling::kGrid)
            GridDescriptor(img, static_cast<float>(x_octave), static_cast<float>(y_octave), ori_up == 360.0f ? 0.0f : ori_up,
                           scale_octave, static_cast<float>(options.descriptor_magnification), descriptor, simd);
          else
            Descriptor(img, static_cast<float>(x_octave), static_cast<float>(y_octave), ori_up == 360.0f ? 0.0f : ori_up,
                       scale_octave, static_cast<float>(options.descriptor_magnification), options.descriptor_row_step,
                       descriptor, simd);
          if (options.descriptor == DescriptorKind::kRootSift) ToRootSift(std::span<float>(descriptor, kDescriptorDim));
        }
      }
    });
    if (o + 1 < octaves) Decimate2x(octave.gauss[static_cast<size_t>(S)], &spare);
  }
  scratch.Keep(std::move(octave.gauss), options.thread_cache_mib);
  if (stopped()) return result;

  if (options.max_features && result.keypoints.size() > static_cast<size_t>(*options.max_features)) {
    std::vector<size_t> order(result.keypoints.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return result.keypoints[a].response > result.keypoints[b].response; });
    order.resize(static_cast<size_t>(*options.max_features));
    std::sort(order.begin(), order.end());  // keep the extraction order among the survivors
    FeatureSet kept;
    kept.image_width = result.image_width;
    kept.image_height = result.image_height;
    kept.kind = result.kind;
    for (size_t i : order) {
      kept.keypoints.push_back(result.keypoints[i]);
      kept.descriptors.insert(kept.descriptors.end(), result.descriptors.begin() + static_cast<ptrdiff_t>(i * kDescriptorDim),
                              result.descriptors.begin() + static_cast<ptrdiff_t>((i + 1) * kDescriptorDim));
    }
    return kept;
  }
  return result;
}

}  // namespace internal

Result<SiftExtractor> SiftExtractor::Create(const SiftOptions& options) {
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, "invalid SIFT options: " + *message);
  return SiftExtractor(options);
}

FeatureSet SiftExtractor::Extract(const GrayImage& image) const { return internal::ExtractImpl(image, options_, true); }

namespace {

// Keypoints of decoded.gray -> coordinates, scales and size of the original image.
FeatureSet ToOriginal(FeatureSet features, const DecodedImage& decoded) {
  const double s = decoded.scale_to_original;
  if (s != 1.0) {
    for (Keypoint& kp : features.keypoints) {
      kp.x = static_cast<float>(GrayToOriginal(kp.x, s));
      kp.y = static_cast<float>(GrayToOriginal(kp.y, s));
      kp.scale = static_cast<float>(kp.scale * s);
    }
  }
  features.image_width = decoded.original_width;
  features.image_height = decoded.original_height;
  return features;
}

}  // namespace

FeatureSet SiftExtractor::ExtractFromDecoded(const DecodedImage& decoded) const {
  return ToOriginal(Extract(decoded.gray), decoded);
}

Result<FeatureSet> SiftExtractor::ExtractFromBytes(std::span<const uint8_t> bytes, const DecodeOptions& decode,
                                                   const StopRequested& stop) const {
  auto decoded = DecodeImage(bytes, decode);
  if (!decoded) return std::unexpected(decoded.error());
  const auto stopped = [&stop] { return stop && stop(); };
  if (stopped()) return Fail(ErrorCode::kResourceExhausted, "stopped after decoding, before the extraction");
  FeatureSet features = internal::ExtractImpl(decoded->gray, options_, true, stop);
  if (stopped()) return Fail(ErrorCode::kResourceExhausted, "stopped during the extraction");
  return ToOriginal(std::move(features), *decoded);
}

Result<FeatureSet> SiftExtractor::ExtractFromFile(const std::string& path, const DecodeOptions& decode) const {
  auto decoded = ReadImage(path, decode);
  if (!decoded) return std::unexpected(decoded.error());
  return ExtractFromDecoded(*decoded);
}

void ToRootSift(std::span<float> descriptor) {
  double l1 = 0;
  for (const float v : descriptor) l1 += std::fabs(v);
  if (l1 <= 0) return;
  const float inv = static_cast<float>(1.0 / l1);
  for (float& v : descriptor) v = std::sqrt(std::fabs(v) * inv);
}

void DescriptorsToUint8(const FeatureSet& features, std::vector<uint8_t>* out) {
  out->resize(features.descriptors.size());
  for (size_t i = 0; i < features.descriptors.size(); ++i) {
    const float v = std::round(512.0f * features.descriptors[i]);
    (*out)[i] = static_cast<uint8_t>(std::clamp(v, 0.0f, 255.0f));
  }
}

}  // namespace oxbow::sift
