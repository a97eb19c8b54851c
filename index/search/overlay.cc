#include "index/search/overlay.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <unordered_map>
#include <vector>

namespace oxbow::index::search {
namespace {

constexpr int kGrid = 8;  // coverage cells per side

// Cell of an 8 x 8 grid over a width x height image.
int Cell(float x, float y, int width, int height, int grid = kGrid) {
  const int cx = std::clamp(static_cast<int>(x * grid / std::max(1, width)), 0, grid - 1);
  const int cy = std::clamp(static_cast<int>(y * grid / std::max(1, height)), 0, grid - 1);
  return cy * grid + cx;
}
int FineCell(float x, float y, int width, int height) { return Cell(x, y, width, height, kFineGrid); }

// The share of the cells `a` shares with `b` (fine cells holding a feature of a inside `region` whose
// place in b, by `b_from_a`, is in a fine cell holding a feature of b) that lie in the largest connected
// block of shared cells without an inlier (`hit`) that reaches the four central cells of a.
double FramedContent(const QueryFeatures& a, const std::array<float, 4>& region,
                     const std::vector<char>& hit, const QueryFeatures& b,
                     const std::vector<char>& b_cells, const sift::Affine2D& b_from_a) {
  std::vector<char> shared(kFineGrid * kFineGrid, 0);
  for (const auto& kp : a.keypoints) {
    if (kp.x < region[0] || kp.x > region[2] || kp.y < region[1] || kp.y > region[3]) continue;
    const Eigen::Vector2d q = b_from_a.Apply({kp.x, kp.y});
    if (q.x() < 0 || q.y() < 0 || q.x() >= b.width || q.y() >= b.height) continue;
    if (b_cells[FineCell(static_cast<float>(q.x()), static_cast<float>(q.y()), b.width, b.height)] != 0) {
      shared[FineCell(kp.x, kp.y, a.width, a.height)] = 1;
    }
  }
  const int total = static_cast<int>(std::count(shared.begin(), shared.end(), 1));
  if (total == 0) return 0;
  std::vector<char> seen(shared.size(), 0);
  int largest = 0;
  for (int start = 0; start < kFineGrid * kFineGrid; ++start) {
    if (shared[start] == 0 || hit[start] != 0 || seen[start] != 0) continue;
    std::vector<int> stack{start};
    seen[start] = 1;
    int size = 0;
    bool central = false;
    while (!stack.empty()) {
      const int cell = stack.back();
      stack.pop_back();
      ++size;
      const int x = cell % kFineGrid, y = cell / kFineGrid;
      central = central || ((x == kFineGrid / 2 - 1 || x == kFineGrid / 2) && (y == kFineGrid / 2 - 1 || y == kFineGrid / 2));
      for (int ny = std::max(0, y - 1); ny <= std::min(kFineGrid - 1, y + 1); ++ny) {
        for (int nx = std::max(0, x - 1); nx <= std::min(kFineGrid - 1, x + 1); ++nx) {
          const int next = ny * kFineGrid + nx;
          if (shared[next] != 0 && hit[next] == 0 && seen[next] == 0) {
            seen[next] = 1;
            stack.push_back(next);
          }
        }
      }
    }
    if (central) largest = std::max(largest, size);
  }
  return static_cast<double>(largest) / total;
}

bool Central(int cell) {
  const int cx = cell % kGrid, cy = cell / kGrid;
  return cx >= 2 && cx < kGrid - 2 && cy >= 2 && cy < kGrid - 2;
}

}  // namespace

MatchMeasure MeasureMatch(const QueryFeatures& a, const QueryFeatures& b,
                    const sift::Affine2D& b_from_a, double tolerance_fraction) {
  MatchMeasure m;
  const double tolerance = std::max(4.0, tolerance_fraction * std::max(b.width, b.height));
  const double tol_sq = tolerance * tolerance;
  const double scale_ratio = std::sqrt(std::abs(b_from_a.Determinant()));
  std::unordered_multimap<uint32_t, size_t> b_by_word;
  b_by_word.reserve(b.words.size());
  for (size_t j = 0; j < b.words.size(); ++j) b_by_word.emplace(b.words[j], j);
  std::vector<char> cells_a(kGrid * kGrid, 0), cells_b(kGrid * kGrid, 0), hit_a(kGrid * kGrid, 0), hit_b(kGrid * kGrid, 0);
  for (const auto& kp : a.keypoints) cells_a[Cell(kp.x, kp.y, a.width, a.height)] = 1;
  for (const auto& kp : b.keypoints) cells_b[Cell(kp.x, kp.y, b.width, b.height)] = 1;
  std::vector<char> fine_hit_a(kFineGrid * kFineGrid, 0), fine_hit_b(kFineGrid * kFineGrid, 0);
  float ax1 = 1e30f, ay1 = 1e30f, ax2 = -1e30f, ay2 = -1e30f, bx1 = 1e30f, by1 = 1e30f, bx2 = -1e30f, by2 = -1e30f;
  const bool signed_features = a.signatures.size() == a.words.size() && b.signatures.size() == b.words.size();
  std::vector<int> distances;  // Hamming distances of the inliers' signatures
  for (size_t i = 0; i < a.words.size(); ++i) {
    const sift::Keypoint& p = a.keypoints[i];
    const Eigen::Vector2d mapped = b_from_a.Apply({p.x, p.y});
    const auto [begin, end] = b_by_word.equal_range(a.words[i]);
    // The first feature of b within the tolerance is the match, unless one is a's twin (same place,
    // scale and orientation: identical pixels there).
    size_t match = b.keypoints.size();  // none
    bool twin = false;
    for (auto it = begin; it != end && !twin; ++it) {
      const sift::Keypoint& q = b.keypoints[it->second];
      const double dx = mapped.x() - q.x, dy = mapped.y() - q.y;
      if (dx * dx + dy * dy > tol_sq) continue;
      const double ratio = q.scale / std::max(1e-6, p.scale * scale_ratio);
      if (ratio < 0.5 || ratio > 2.0) continue;
      twin = std::abs(p.x - q.x) <= 0.5f && std::abs(p.y - q.y) <= 0.5f && std::abs(p.scale - q.scale) <= 0.05f * p.scale &&
             std::abs(std::remainder(p.orientation - q.orientation, 2 * M_PI)) <= 0.05;
      if (match == b.keypoints.size() || twin) match = it->second;
    }
    if (match != b.keypoints.size()) {
      const sift::Keypoint& q = b.keypoints[match];
      ++m.inliers;
      if (signed_features) distances.push_back(std::popcount(a.signatures[i] ^ b.signatures[match]));
      m.twins += twin ? 1 : 0;
      const int ca = Cell(p.x, p.y, a.width, a.height), cb = Cell(q.x, q.y, b.width, b.height);
      hit_a[ca] = 1;
      hit_b[cb] = 1;
      fine_hit_a[FineCell(p.x, p.y, a.width, a.height)] = 1;
      fine_hit_b[FineCell(q.x, q.y, b.width, b.height)] = 1;
      m.central = m.central || Central(ca) || Central(cb);
      m.central_a += Central(ca) ? 1 : 0;
      m.central_b += Central(cb) ? 1 : 0;
      ax1 = std::min(ax1, p.x), ay1 = std::min(ay1, p.y), ax2 = std::max(ax2, p.x), ay2 = std::max(ay2, p.y);
      bx1 = std::min(bx1, q.x), by1 = std::min(by1, q.y), bx2 = std::max(bx2, q.x), by2 = std::max(by2, q.y);
    }
  }
  auto share = [](const std::vector<char>& hit, const std::vector<char>& cells) {
    const int with = static_cast<int>(std::count(cells.begin(), cells.end(), 1));
    return with == 0 ? 0.0 : static_cast<double>(std::count(hit.begin(), hit.end(), 1)) / with;
  };
  if (!distances.empty()) {
    const auto middle = distances.begin() + static_cast<std::ptrdiff_t>(distances.size() / 2);
    std::nth_element(distances.begin(), middle, distances.end());
    m.hamming_median = *middle;
  }
  m.coverage_a = share(hit_a, cells_a);
  m.coverage_b = share(hit_b, cells_b);
  if (m.inliers > 0) {
    m.region_a = {ax1, ay1, ax2, ay2};
    m.region_b = {bx1, by1, bx2, by2};
    auto inside = [](const QueryFeatures& f, const std::array<float, 4>& r) {
      int n = 0;
      for (const auto& kp : f.keypoints) n += kp.x >= r[0] && kp.x <= r[2] && kp.y >= r[1] && kp.y <= r[3];
      return std::max(1, n);
    };
    m.density_a = static_cast<double>(m.inliers) / inside(a, m.region_a);
    m.density_b = static_cast<double>(m.inliers) / inside(b, m.region_b);
  }
  // Only a match of twins with alike (or no) signatures can be a frame (OnlyAnOverlay).
  if (m.inliers > 0 && m.hamming_median <= kIdenticalHamming && m.twins >= kFrameTwins * m.inliers) {
    std::vector<char> fine_a(kFineGrid * kFineGrid, 0), fine_b(kFineGrid * kFineGrid, 0);
    for (const auto& kp : a.keypoints) fine_a[FineCell(kp.x, kp.y, a.width, a.height)] = 1;
    for (const auto& kp : b.keypoints) fine_b[FineCell(kp.x, kp.y, b.width, b.height)] = 1;
    m.framed = FramedContent(a, m.region_a, fine_hit_a, b, fine_b, b_from_a);
    if (const auto a_from_b = b_from_a.Inverse()) {
      m.framed = std::max(m.framed, FramedContent(b, m.region_b, fine_hit_b, a, fine_a, *a_from_b));
    }
  }
  return m;
}

bool OnlyAnOverlay(const MatchMeasure& m, bool mirrored, const OverlayRule& rule) {
  if (!m.central) return true;
  // One frame around two pictures: twins (identical pixels at the same places) with alike signatures, or
  // without signatures to compare; a mirrored match's twins are a symmetric picture's.
  if (!mirrored && m.hamming_median <= kIdenticalHamming && m.twins >= kFrameTwins * m.inliers &&
      m.framed >= kFramedContent) {
    return true;
  }
  const double larger_coverage = std::max(m.coverage_a, m.coverage_b);
  if (mirrored && larger_coverage < std::max(rule.min_coverage, kMirroredCoverage)) return true;
  const bool dense = larger_coverage < rule.overlay_coverage &&
                     std::max(m.density_a, m.density_b) >= rule.overlay_density;
  if (larger_coverage >= rule.min_coverage && !dense) return false;
  const int central_more = std::max(m.central_a, m.central_b), central_less = std::min(m.central_a, m.central_b);
  return !(m.hamming_median > kIdenticalHamming && larger_coverage >= std::min(rule.min_coverage, kDistinctCoverage) &&
           central_more >= kCentralShare * m.inliers && central_less >= kCentralShareOther * m.inliers);
}

}  // namespace oxbow::index::search
