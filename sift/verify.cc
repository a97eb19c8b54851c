// Geometric verification: Lowe's Hough pose clustering with affine refinement, and robust model fits
// through OpenCV calib3d.
//
// Hough voting keeps bins in an open-addressing hash map whose entries head a linked list of votes, so a
// bin's members are read without a second pass; the map has at least twice as many slots as votes.
// All scratch memory lives in a thread_local arena that grows to the largest call seen, so repeated
// calls (re-ranking hundreds of candidates) do not allocate. Agreement with a fit is tested without
// trigonometry: the predicted keypoint direction A u must be within half an orientation bin of the db
// keypoint's direction w (A u . w >= cos(half bin) |A u|), and the scale ratio must be within
// sqrt(scale_bin_factor) of sqrt(det A) (compared squared).
#include "sift/verify.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

namespace oxbow::sift {
namespace {

constexpr uint64_t kEmptyKey = ~uint64_t{0};
constexpr int kScaleBinOffset = 2048;      // scale bin k is stored as k + 2048 in 12 bits
constexpr int64_t kLocationOffset = 1 << 20;  // location bins are stored as b + 2^20 in 21 bits

// One valid tentative match in structure-of-arrays form.
struct Points {
  std::vector<uint32_t> match_index;  // index into the caller's `matches`
  std::vector<double> qx, qy, dx, dy;
  std::vector<double> qcos, qsin;     // query keypoint direction
  std::vector<double> dcos, dsin;     // db keypoint direction
  std::vector<double> scale_ratio_sq; // (db scale / query scale)^2
  std::vector<double> log_scale;      // log(db scale / query scale)
  std::vector<double> rotation;       // db orientation - query orientation, radians in [0, 2 pi)

  void Clear() {
    for (auto* v : {&qx, &qy, &dx, &dy, &qcos, &qsin, &dcos, &dsin, &scale_ratio_sq, &log_scale, &rotation}) v->clear();
    match_index.clear();
  }
  void Reserve(size_t n) {
    for (auto* v : {&qx, &qy, &dx, &dy, &qcos, &qsin, &dcos, &dsin, &scale_ratio_sq, &log_scale, &rotation}) v->reserve(n);
    match_index.reserve(n);
  }
  size_t size() const { return match_index.size(); }
};

// Reused between calls on the same thread.
// One Hough bin: its key, how many matches voted for it, and the head of its list of votes. 16 bytes,
// so a probe touches one cache line.
struct Bin {
  uint64_t key = kEmptyKey;
  uint32_t count = 0;
  int32_t head = -1;
};

struct Scratch {
  Points points;
  std::vector<Bin> table;          // open addressing, linear probing; all empty between calls
  std::vector<uint32_t> occupied;  // slots used by this call, reset to empty on the way out
  std::vector<int32_t> vote_next;
  std::vector<uint32_t> vote_point;
  std::vector<uint32_t> clusters;  // table slots with enough votes, in the order they reached the minimum
  std::vector<uint32_t> ordered;   // `clusters` sorted by decreasing count (stable)
  std::vector<uint32_t> count_start;
  std::vector<uint32_t> members, selected, previous, best;
  std::vector<uint8_t> in_best;
  std::vector<double> scales;  // InlierSpread's
};

// Empties the bins a call used, so the next call starts from an all-empty table without clearing it all.
class TableReset {
 public:
  explicit TableReset(Scratch& s) : s_(s) {}
  ~TableReset() {
    for (uint32_t slot : s_.occupied) s_.table[slot] = Bin{};
    s_.occupied.clear();
  }
  TableReset(const TableReset&) = delete;
  TableReset& operator=(const TableReset&) = delete;

 private:
  Scratch& s_;
};

Scratch& ThreadScratch() {
  thread_local Scratch scratch;
  return scratch;
}

bool Finite(const Keypoint& k) {
  return std::isfinite(k.x) && std::isfinite(k.y) && std::isfinite(k.scale) && std::isfinite(k.orientation);
}

uint64_t PackKey(int orientation_bin, int scale_bin, int64_t x_bin, int64_t y_bin) {
  return (uint64_t(orientation_bin) << 54) | (uint64_t(scale_bin + kScaleBinOffset) << 42) |
         (uint64_t(x_bin + kLocationOffset) << 21) | uint64_t(y_bin + kLocationOffset);
}
int ScaleBinOfKey(uint64_t key) { return static_cast<int>((key >> 42) & 0xFFF) - kScaleBinOffset; }

size_t SlotOf(uint64_t key, int bits) { return static_cast<size_t>((key * 0x9E3779B97F4A7C15ull) >> (64 - bits)); }

// Least-squares affine fit d = A q + t over `subset` (indices into points), in centred coordinates.
// False when fewer than 3 points or they are (nearly) collinear.
bool FitAffine(const Points& p, std::span<const uint32_t> subset, Affine2D* fit) {
  if (subset.size() < 3) return false;
  double mqx = 0, mqy = 0, mdx = 0, mdy = 0;
  for (uint32_t i : subset) {
    mqx += p.qx[i];
    mqy += p.qy[i];
    mdx += p.dx[i];
    mdy += p.dy[i];
  }
  const double inv_n = 1.0 / static_cast<double>(subset.size());
  mqx *= inv_n;
  mqy *= inv_n;
  mdx *= inv_n;
  mdy *= inv_n;
  double sxx = 0, sxy = 0, syy = 0;      // query scatter
  double uxx = 0, uxy = 0, uyx = 0, uyy = 0;  // cross scatter sum d~ q~^T
  for (uint32_t i : subset) {
    const double x = p.qx[i] - mqx, y = p.qy[i] - mqy;
    const double u = p.dx[i] - mdx, v = p.dy[i] - mdy;
    sxx += x * x;
    sxy += x * y;
    syy += y * y;
    uxx += u * x;
    uxy += u * y;
    uyx += v * x;
    uyy += v * y;
  }
  const double det = sxx * syy - sxy * sxy;
  const double trace = sxx + syy;
  if (!(trace > 0) || !(det > 1e-9 * trace * trace)) return false;
  const double i00 = syy / det, i01 = -sxy / det, i11 = sxx / det;
  const double a11 = uxx * i00 + uxy * i01, a12 = uxx * i01 + uxy * i11;
  const double a21 = uyx * i00 + uyy * i01, a22 = uyx * i01 + uyy * i11;
  fit->m = {a11, a12, mdx - a11 * mqx - a12 * mqy, a21, a22, mdy - a21 * mqx - a22 * mqy};
  for (double v : fit->m) {
    if (!std::isfinite(v)) return false;
  }
  return true;
}

// Singular values of the 2x2 linear part, larger first.
std::pair<double, double> SingularValues(const Affine2D& a) {
  const double p = a.m[0], q = a.m[1], r = a.m[3], s = a.m[4];
  const double e = (p + s) / 2, f = (p - s) / 2, g = (r + q) / 2, h = (r - q) / 2;
  const double qq = std::hypot(e, h), rr = std::hypot(f, g);
  return {qq + rr, std::abs(qq - rr)};
}

bool Plausible(const Affine2D& a, const HoughVerifyOptions& o) {
  if (!(a.Determinant() > 0)) return false;
  const auto [s1, s2] = SingularValues(a);
  return s2 >= o.min_scale && s1 <= o.max_scale && s1 <= o.max_anisotropy * s2;
}

// The standard deviations of points (xs[i], ys[i]), i in `selected` but not selected[skip], across and
// along their principal axis; `farthest` (when given) receives the position in `selected` of the point
// farthest from that axis.
struct Deviations {
  double across = 0, along = 0;
};
Deviations AxisDeviations(std::span<const uint32_t> selected, const std::vector<double>& xs,
                          const std::vector<double>& ys, size_t skip, size_t* farthest) {
  const size_t n = selected.size() - (skip < selected.size() ? 1 : 0);
  if (n < 2) return {};
  double mx = 0, my = 0;
  for (size_t k = 0; k < selected.size(); ++k) {
    if (k != skip) mx += xs[selected[k]], my += ys[selected[k]];
  }
  mx /= double(n), my /= double(n);
  double sxx = 0, sxy = 0, syy = 0;
  for (size_t k = 0; k < selected.size(); ++k) {
    if (k == skip) continue;
    const double x = xs[selected[k]] - mx, y = ys[selected[k]] - my;
    sxx += x * x, sxy += x * y, syy += y * y;
  }
  sxx /= double(n - 1), sxy /= double(n - 1), syy /= double(n - 1);
  if (farthest != nullptr) {
    // The principal axis's angle; the minor axis is its normal.
    const double angle = 0.5 * std::atan2(2 * sxy, sxx - syy);
    const double nx = -std::sin(angle), ny = std::cos(angle);
    double worst = -1;
    for (size_t k = 0; k < selected.size(); ++k) {
      const double d = std::abs((xs[selected[k]] - mx) * nx + (ys[selected[k]] - my) * ny);
      if (d > worst) worst = d, *farthest = k;
    }
  }
  // The covariance's eigenvalues: the variances across and along the principal axis.
  const double mean = (sxx + syy) / 2, half_gap = std::hypot((sxx - syy) / 2, sxy);
  return {std::sqrt(std::max(0.0, mean - half_gap)), std::sqrt(std::max(0.0, mean + half_gap))};
}

constexpr size_t kNoSkip = std::numeric_limits<size_t>::max();

// The inliers' spread (HoughVerifyOptions::min_inlier_spread): in each image, the standard deviation of
// their positions across their principal axis divided by their median keypoint scale; the smaller of the
// two. Scale-invariant: a copy at another size measures the same. With leave_farthest_out, each image's
// deviation leaves out the inlier farthest from the principal axis (VerificationResult::firm).
double InlierSpread(std::span<const uint32_t> selected, const Points& p, std::span<const Keypoint> query,
                    std::span<const Keypoint> db, std::span<const Match> matches, bool leave_farthest_out,
                    std::vector<double>& scales) {
  const size_t n = selected.size();
  if (n < 2) return 0;
  double spread = std::numeric_limits<double>::infinity();
  for (const bool query_side : {true, false}) {
    const std::vector<double>& xs = query_side ? p.qx : p.dx;
    const std::vector<double>& ys = query_side ? p.qy : p.dy;
    size_t farthest = kNoSkip;
    double deviation = AxisDeviations(selected, xs, ys, kNoSkip, leave_farthest_out ? &farthest : nullptr).across;
    if (leave_farthest_out) deviation = AxisDeviations(selected, xs, ys, farthest, nullptr).across;
    scales.clear();
    for (const uint32_t i : selected) {
      const Match& m = matches[p.match_index[i]];
      scales.push_back(query_side ? query[m.query_index].scale : db[m.db_index].scale);
    }
    const auto middle = scales.begin() + static_cast<std::ptrdiff_t>(n / 2);
    std::nth_element(scales.begin(), middle, scales.end());
    spread = std::min(spread, deviation / std::max(double(*middle), 1e-6));
  }
  return spread;
}

// The inliers' aspect (HoughVerifyOptions::min_firm_aspect): in each image, their standard deviation
// across their principal axis over that along it; the smaller of the two. A line of text is long and thin.
double InlierAspect(std::span<const uint32_t> selected, const Points& p) {
  double aspect = std::numeric_limits<double>::infinity();
  for (const bool query_side : {true, false}) {
    const Deviations d = AxisDeviations(selected, query_side ? p.qx : p.dx, query_side ? p.qy : p.dy, kNoSkip, nullptr);
    aspect = std::min(aspect, d.along > 0 ? d.across / d.along : 0.0);
  }
  return aspect;
}

// Agreement tests with a fit; see the file comment.
struct Agreement {
  double tolerance_sq = 0;
  double cos_half_bin_sq = 0;
  double scale_low = 0, scale_high = 0;  // bounds on scale_ratio_sq
  bool check_pose = true;

  Agreement(const Affine2D& a, double tolerance_px, const HoughVerifyOptions& o, double orientation_bin_rad) {
    tolerance_sq = tolerance_px * tolerance_px;
    const double c = std::cos(orientation_bin_rad / 2);
    cos_half_bin_sq = c * c;
    const double det = std::abs(a.Determinant());
    scale_low = det / o.scale_bin_factor;
    scale_high = det * o.scale_bin_factor;
    check_pose = o.check_keypoint_pose;
  }

  bool operator()(const Affine2D& a, const Points& p, size_t i) const {
    const double* m = a.m.data();
    const double ex = m[0] * p.qx[i] + m[1] * p.qy[i] + m[2] - p.dx[i];
    const double ey = m[3] * p.qx[i] + m[4] * p.qy[i] + m[5] - p.dy[i];
    if (ex * ex + ey * ey > tolerance_sq) return false;
    if (!check_pose) return true;
    const double vx = m[0] * p.qcos[i] + m[1] * p.qsin[i];
    const double vy = m[3] * p.qcos[i] + m[4] * p.qsin[i];
    const double dot = vx * p.dcos[i] + vy * p.dsin[i];
    if (!(dot > 0) || dot * dot < cos_half_bin_sq * (vx * vx + vy * vy)) return false;
    return p.scale_ratio_sq[i] >= scale_low && p.scale_ratio_sq[i] <= scale_high;
  }
};

// Verifies one Hough cluster (members = point indices); on success `selected` holds the inliers.
bool VerifyCluster(const Points& p, std::vector<uint32_t>& members, double initial_tolerance_px,
                   const HoughVerifyOptions& o, double orientation_bin_rad, std::vector<uint32_t>& selected,
                   std::vector<uint32_t>& previous, Affine2D* fit_out) {
  Affine2D fit;
  if (!FitAffine(p, members, &fit)) return false;
  // Phase 1 (Lowe sec. 7.4): drop cluster members farther than half a bin from the fit, re-fit, repeat.
  for (int iteration = 0; iteration < o.max_refine_iterations; ++iteration) {
    const Agreement agree(fit, initial_tolerance_px, o, orientation_bin_rad);
    selected.clear();
    for (uint32_t i : members) {
      if (agree(fit, p, i)) selected.push_back(i);
    }
    if (selected.size() < 3) return false;
    if (selected.size() == members.size()) break;
    members.swap(selected);
    if (!FitAffine(p, members, &fit)) return false;
  }
  // Phase 2 (top-down): add back every tentative match agreeing with the fit, re-fit, and tighten the
  // tolerance by halves down to residual_px; then iterate at residual_px until the inlier set is stable.
  double tolerance = std::max(o.residual_px, initial_tolerance_px);
  previous.clear();
  int stable_rounds = 0;
  const size_t n = p.size();
  while (true) {
    const Agreement agree(fit, tolerance, o, orientation_bin_rad);
    selected.clear();
    for (size_t i = 0; i < n; ++i) {
      if (agree(fit, p, i)) selected.push_back(static_cast<uint32_t>(i));
    }
    if (selected.size() < 3) return false;
    const bool at_final = tolerance <= o.residual_px;
    if (at_final && selected == previous) break;  // fit == LS(selected) and selected == agree(fit): consistent
    if (at_final && ++stable_rounds > o.max_refine_iterations) break;  // selected agrees with `fit`
    Affine2D refit;
    if (!FitAffine(p, selected, &refit)) break;  // keep the previous fit, `selected` agrees with it
    fit = refit;
    previous.assign(selected.begin(), selected.end());
    tolerance = std::max(o.residual_px, tolerance / 2);
  }
  *fit_out = fit;
  return true;
}

}  // namespace

std::optional<Affine2D> Affine2D::Inverse() const {
  double scale = 0;
  for (double v : m) {
    if (!std::isfinite(v)) return std::nullopt;
  }
  for (int i : {0, 1, 3, 4}) scale = std::max(scale, std::abs(m[i]));
  const double det = Determinant();
  if (!(std::abs(det) > 1e-12 * scale * scale)) return std::nullopt;
  const double i11 = m[4] / det, i12 = -m[1] / det, i21 = -m[3] / det, i22 = m[0] / det;
  Affine2D inv;
  inv.m = {i11, i12, -(i11 * m[2] + i12 * m[5]), i21, i22, -(i21 * m[2] + i22 * m[5])};
  return inv;
}

std::optional<std::string> HoughVerifyOptions::Check() const {
  auto bad = [](const char* field, double value, const char* range) {
    return std::string(field) + " must be in " + range + ", got " + std::to_string(value);
  };
  if (!(orientation_bin_deg >= 1 && orientation_bin_deg <= 180)) return bad("orientation_bin_deg", orientation_bin_deg, "[1, 180]");
  if (!(scale_bin_factor >= 1.1 && scale_bin_factor <= 16)) return bad("scale_bin_factor", scale_bin_factor, "[1.1, 16]");
  if (!(location_bin_fraction > 0 && location_bin_fraction <= 1)) return bad("location_bin_fraction", location_bin_fraction, "(0, 1]");
  if (min_cluster_votes < 3) return bad("min_cluster_votes", min_cluster_votes, "[3, inf)");
  if (max_clusters_to_verify < 1) return bad("max_clusters_to_verify", max_clusters_to_verify, "[1, inf)");
  if (!(early_stop_fraction >= 0 && early_stop_fraction <= 1)) return bad("early_stop_fraction", early_stop_fraction, "[0, 1]");
  if (!(initial_residual_bin_fraction > 0 && initial_residual_bin_fraction <= 4)) {
    return bad("initial_residual_bin_fraction", initial_residual_bin_fraction, "(0, 4]");
  }
  if (!(residual_px > 0 && std::isfinite(residual_px))) return bad("residual_px", residual_px, "(0, inf)");
  if (max_refine_iterations < 1) return bad("max_refine_iterations", max_refine_iterations, "[1, inf)");
  if (min_inliers < 3) return bad("min_inliers", min_inliers, "[3, inf)");
  if (!(min_scale > 0 && min_scale <= max_scale && std::isfinite(max_scale))) {
    return "min_scale and max_scale must satisfy 0 < min_scale <= max_scale < inf, got " + std::to_string(min_scale) +
           " and " + std::to_string(max_scale);
  }
  if (!(max_anisotropy >= 1 && std::isfinite(max_anisotropy))) return bad("max_anisotropy", max_anisotropy, "[1, inf)");
  if (!(min_inlier_spread >= 0 && std::isfinite(min_inlier_spread))) {
    return bad("min_inlier_spread", min_inlier_spread, "[0, inf)");
  }
  if (!(min_firm_aspect >= 0 && min_firm_aspect <= 1)) return bad("min_firm_aspect", min_firm_aspect, "[0, 1]");
  return std::nullopt;
}

VerificationResult VerifyHoughAffine(std::span<const Keypoint> query, std::span<const Keypoint> db,
                                     std::span<const Match> matches, const std::array<float, 4>& query_region,
                                     const std::array<int, 2>& db_size, const HoughVerifyOptions& options) {
  VerificationResult result;
  if (options.Check()) return result;
  for (float v : query_region) {
    if (!std::isfinite(v)) return result;
  }
  const double region_w = double(query_region[2]) - query_region[0];
  const double region_h = double(query_region[3]) - query_region[1];
  const double region_size = std::max(region_w, region_h);
  if (!(region_w > 0 && region_h > 0)) return result;
  const double cx = (double(query_region[0]) + query_region[2]) / 2;
  const double cy = (double(query_region[1]) + query_region[3]) / 2;

  Scratch& s = ThreadScratch();
  Points& p = s.points;
  p.Clear();
  p.Reserve(matches.size());
  constexpr double kTwoPi = 2 * std::numbers::pi;
  for (size_t m = 0; m < matches.size(); ++m) {
    const Match& match = matches[m];
    if (match.query_index >= query.size() || match.db_index >= db.size()) continue;
    const Keypoint& a = query[match.query_index];
    const Keypoint& b = db[match.db_index];
    if (!Finite(a) || !Finite(b) || !(a.scale > 0) || !(b.scale > 0)) continue;
    p.match_index.push_back(static_cast<uint32_t>(m));
    p.qx.push_back(a.x);
    p.qy.push_back(a.y);
    p.dx.push_back(b.x);
    p.dy.push_back(b.y);
    // Single precision trigonometry is plenty for 30-degree bins and a 15-degree agreement test.
    p.qcos.push_back(std::cos(a.orientation));
    p.qsin.push_back(std::sin(a.orientation));
    p.dcos.push_back(std::cos(b.orientation));
    p.dsin.push_back(std::sin(b.orientation));
    const double ratio = double(b.scale) / double(a.scale);
    p.scale_ratio_sq.push_back(ratio * ratio);
    p.log_scale.push_back(std::log(ratio));
    double rotation = std::fmod(double(b.orientation) - double(a.orientation), kTwoPi);
    if (rotation < 0) rotation += kTwoPi;
    p.rotation.push_back(rotation);
  }
  const size_t n = p.size();
  if (n < 3) return result;

  // ---- Voting: 2 orientation x 2 scale x 2 x x 2 y bins per match.
  const int orientation_bins = std::max(2, static_cast<int>(std::lround(360.0 / options.orientation_bin_deg)));
  const double orientation_bin_rad = kTwoPi / orientation_bins;
  const double log_scale_bin = std::log(options.scale_bin_factor);
  const size_t max_votes = 16 * n;
  int bits = 4;
  while ((size_t{1} << bits) < max_votes + max_votes / 2) ++bits;  // load factor <= 2/3
  if (s.table.size() < (size_t{1} << bits)) s.table.assign(size_t{1} << bits, Bin{});
  while ((size_t{1} << bits) < s.table.size()) ++bits;  // a larger table left by an earlier call is fine
  const size_t capacity = size_t{1} << bits;
  TableReset reset(s);
  s.vote_next.resize(max_votes);
  s.vote_point.resize(max_votes);
  size_t votes = 0;
  s.clusters.clear();
  uint32_t max_count = 0;

  auto location_bin_size = [&](int scale_bin) {
    return options.location_bin_fraction * region_size * std::exp((scale_bin + 0.5) * log_scale_bin);
  };
  for (size_t i = 0; i < n; ++i) {
    const double o = p.rotation[i] / orientation_bin_rad - 0.5;  // in [-0.5, bins - 0.5)
    int o0 = static_cast<int>(std::floor(o));
    int o1 = o0 + 1;
    if (o0 < 0) o0 += orientation_bins;
    if (o1 >= orientation_bins) o1 -= orientation_bins;
    const int o_bins[2] = {o0, o1};
    const double sc = p.log_scale[i] / log_scale_bin - 0.5;
    const int s0 = static_cast<int>(std::floor(sc));
    if (s0 < -kScaleBinOffset + 1 || s0 > kScaleBinOffset - 2) continue;
    // Predicted position of the region centre in the db image: d + s R(theta) (c - q), with
    // s R(theta) from the two keypoints' directions and scales.
    const double ratio = std::sqrt(p.scale_ratio_sq[i]);
    const double cr = ratio * (p.dcos[i] * p.qcos[i] + p.dsin[i] * p.qsin[i]);
    const double sr = ratio * (p.dsin[i] * p.qcos[i] - p.dcos[i] * p.qsin[i]);
    const double ux = cx - p.qx[i], uy = cy - p.qy[i];
    const double px = p.dx[i] + cr * ux - sr * uy;
    const double py = p.dy[i] + sr * ux + cr * uy;
    const double size0 = location_bin_size(s0);
    for (int ds = 0; ds < 2; ++ds) {
      const int scale_bin = s0 + ds;
      const double size = ds == 0 ? size0 : size0 * options.scale_bin_factor;
      const double xf = px / size - 0.5, yf = py / size - 0.5;
      if (!(std::abs(xf) < double(kLocationOffset - 2) && std::abs(yf) < double(kLocationOffset - 2))) continue;
      const int64_t x0 = static_cast<int64_t>(std::floor(xf)), y0 = static_cast<int64_t>(std::floor(yf));
      for (int od : o_bins) {
        for (int dx = 0; dx < 2; ++dx) {
          for (int dy = 0; dy < 2; ++dy) {
            const uint64_t key = PackKey(od, scale_bin, x0 + dx, y0 + dy);
            size_t slot = SlotOf(key, bits);
            while (s.table[slot].key != kEmptyKey && s.table[slot].key != key) slot = (slot + 1) & (capacity - 1);
            Bin& bin = s.table[slot];
            if (bin.key == kEmptyKey) {
              bin.key = key;
              s.occupied.push_back(static_cast<uint32_t>(slot));
            }
            s.vote_point[votes] = static_cast<uint32_t>(i);
            s.vote_next[votes] = bin.head;
            bin.head = static_cast<int32_t>(votes);
            ++votes;
            if (++bin.count == static_cast<uint32_t>(options.min_cluster_votes)) s.clusters.push_back(static_cast<uint32_t>(slot));
            max_count = std::max(max_count, bin.count);
          }
        }
      }
    }
  }
  // Largest bins first (counting sort, O(clusters + n)); equal counts keep the order in which the bins
  // reached min_cluster_votes, which depends on the input only, not on the hash layout.
  s.count_start.assign(size_t{max_count} + 2, 0);
  for (uint32_t slot : s.clusters) ++s.count_start[max_count - s.table[slot].count + 1];
  for (size_t c = 1; c < s.count_start.size(); ++c) s.count_start[c] += s.count_start[c - 1];
  s.ordered.resize(s.clusters.size());
  for (uint32_t slot : s.clusters) s.ordered[s.count_start[max_count - s.table[slot].count]++] = slot;

  // ---- Verification, largest clusters first.
  s.in_best.assign(n, 0);
  s.best.clear();
  bool best_verified = false;
  bool have_fit = false;
  Affine2D best_fit;
  int best_votes = 0;
  int verified_clusters = 0;
  for (uint32_t slot : s.ordered) {
    if (verified_clusters >= options.max_clusters_to_verify) break;
    // Bins come in decreasing vote order: once they hold fewer votes than a fraction of the best verified
    // inlier count, no later bin can be the peak of a better-supported pose.
    if (best_verified && double(s.table[slot].count) < options.early_stop_fraction * double(s.best.size())) break;
    // A bin whose members mostly already support the best fit is the same pose hypothesis again (each
    // match votes into 16 neighbouring bins): skip it without counting it against the budget.
    s.members.clear();
    size_t already = 0;
    for (int32_t v = s.table[slot].head; v >= 0; v = s.vote_next[v]) {
      s.members.push_back(s.vote_point[v]);
      already += s.in_best[s.vote_point[v]];
    }
    if (have_fit && 2 * already > s.members.size()) continue;
    ++verified_clusters;
    std::sort(s.members.begin(), s.members.end());
    const int votes_here = static_cast<int>(s.members.size());
    const double tolerance = options.initial_residual_bin_fraction * location_bin_size(ScaleBinOfKey(s.table[slot].key));
    Affine2D fit;
    if (!VerifyCluster(p, s.members, tolerance, options, orientation_bin_rad, s.selected, s.previous, &fit)) continue;
    const bool verified = static_cast<int>(s.selected.size()) >= options.min_inliers && Plausible(fit, options) &&
                          (options.min_inlier_spread <= 0 ||
                           InlierSpread(s.selected, p, query, db, matches, false, s.scales) >= options.min_inlier_spread);
    const bool better = !have_fit || (verified && !best_verified) ||
                        (verified == best_verified && s.selected.size() > s.best.size());
    if (!better) continue;
    have_fit = true;
    best_verified = verified;
    best_fit = fit;
    best_votes = votes_here;
    std::fill(s.in_best.begin(), s.in_best.end(), 0);
    s.best = s.selected;
    for (uint32_t i : s.best) s.in_best[i] = 1;
  }
  if (!have_fit) return result;

  result.verified = best_verified;
  result.firm = best_verified && (options.min_inlier_spread <= 0 ||
                                  InlierSpread(s.best, p, query, db, matches, true, s.scales) >= options.min_inlier_spread) &&
                InlierAspect(s.best, p) >= options.min_firm_aspect;
  result.num_votes = best_votes;
  result.db_from_query = best_fit;
  result.inliers.reserve(s.best.size());
  for (uint32_t i : s.best) result.inliers.push_back(p.match_index[i]);
  std::sort(result.inliers.begin(), result.inliers.end());
  result.num_inliers = static_cast<int>(result.inliers.size());
  Eigen::Matrix3d h = Eigen::Matrix3d::Identity();
  h << best_fit.m[0], best_fit.m[1], best_fit.m[2], best_fit.m[3], best_fit.m[4], best_fit.m[5], 0, 0, 1;
  result.db_region = ProjectBox(h, query_region, db_size);
  return result;
}

std::array<float, 4> ProjectBox(const Eigen::Matrix3d& target_from_source, const std::array<float, 4>& box,
                                const std::array<int, 2>& target_size) {
  std::array<float, 4> zeros = {0, 0, 0, 0};
  if (!target_from_source.allFinite()) return zeros;
  double x1 = std::numeric_limits<double>::infinity(), y1 = x1, x2 = -x1, y2 = -x1;
  for (int c = 0; c < 4; ++c) {
    const Eigen::Vector3d corner(box[(c & 1) ? 2 : 0], box[(c & 2) ? 3 : 1], 1.0);
    const Eigen::Vector3d mapped = target_from_source * corner;
    if (!(mapped.z() > 1e-12) || !mapped.allFinite()) return zeros;
    const double x = mapped.x() / mapped.z(), y = mapped.y() / mapped.z();
    if (!std::isfinite(x) || !std::isfinite(y)) return zeros;
    x1 = std::min(x1, x);
    y1 = std::min(y1, y);
    x2 = std::max(x2, x);
    y2 = std::max(y2, y);
  }
  const double w = std::max(0, target_size[0]), h = std::max(0, target_size[1]);
  return {static_cast<float>(std::clamp(x1, 0.0, w)), static_cast<float>(std::clamp(y1, 0.0, h)),
          static_cast<float>(std::clamp(x2, 0.0, w)), static_cast<float>(std::clamp(y2, 0.0, h))};
}

const char* GeometricModelName(GeometricModel model) {
  switch (model) {
    case GeometricModel::kHoughAffine: return "hough-affine";
    case GeometricModel::kHoughHomography: return "hough-homography";
    case GeometricModel::kSimilarity: return "similarity";
    case GeometricModel::kAffine: return "affine";
    case GeometricModel::kHomography: return "homography";
    case GeometricModel::kFundamental: return "fundamental";
  }
  return "unknown";
}

std::optional<GeometricModel> ParseGeometricModel(std::string_view name) {
  for (GeometricModel m : {GeometricModel::kHoughAffine, GeometricModel::kHoughHomography, GeometricModel::kSimilarity,
                           GeometricModel::kAffine, GeometricModel::kHomography, GeometricModel::kFundamental}) {
    if (name == GeometricModelName(m)) return m;
  }
  return std::nullopt;
}

std::optional<std::string> RobustFitOptions::Check() const {
  if (estimator != Estimator::kMagsac && estimator != Estimator::kRansac) return "estimator: unknown value";
  if (!(reprojection_px > 0 && std::isfinite(reprojection_px))) return "reprojection_px must be > 0, got " + std::to_string(reprojection_px);
  if (!(confidence > 0 && confidence < 1)) return "confidence must be in (0, 1), got " + std::to_string(confidence);
  if (max_iterations < 1) return "max_iterations must be >= 1, got " + std::to_string(max_iterations);
  if (refine_iterations < 0) return "refine_iterations must be >= 0, got " + std::to_string(refine_iterations);
  if (auto problem = hough.Check()) return "hough." + *problem;
  return std::nullopt;
}

Result<RobustFitResult> FitRobust(GeometricModel model, std::span<const Keypoint> query, std::span<const Keypoint> db,
                                  std::span<const Match> matches, const RobustFitOptions& options) {
  if (auto problem = options.Check()) return Fail(ErrorCode::kInvalidArgument, "robust fit options: " + *problem);
  if (!ParseGeometricModel(GeometricModelName(model))) return Fail(ErrorCode::kInvalidArgument, "unknown geometric model");
  for (const Match& m : matches) {
    if (m.query_index >= query.size() || m.db_index >= db.size()) {
      return Fail(ErrorCode::kInvalidArgument, "match (" + std::to_string(m.query_index) + ", " + std::to_string(m.db_index) +
                                                   ") is out of range for " + std::to_string(query.size()) + " query and " +
                                                   std::to_string(db.size()) + " db keypoints");
    }
    if (!Finite(query[m.query_index]) || !Finite(db[m.db_index])) {
      return Fail(ErrorCode::kInvalidArgument, "a matched keypoint has a non-finite coordinate");
    }
  }
  RobustFitResult result;
  result.model = model;

  if (model == GeometricModel::kHoughAffine || model == GeometricModel::kHoughHomography) {
    float x1 = std::numeric_limits<float>::max(), y1 = x1, x2 = std::numeric_limits<float>::lowest(), y2 = x2;
    float dw = 1, dh = 1;
    for (const Keypoint& k : query) {
      if (!Finite(k)) continue;
      x1 = std::min(x1, k.x), y1 = std::min(y1, k.y), x2 = std::max(x2, k.x), y2 = std::max(y2, k.y);
    }
    for (const Keypoint& k : db) {
      if (Finite(k)) dw = std::max(dw, k.x + 1), dh = std::max(dh, k.y + 1);
    }
    if (!(x2 > x1 && y2 > y1)) return result;
    const VerificationResult v = VerifyHoughAffine(query, db, matches, {x1, y1, x2 + 1, y2 + 1},
                                                   {static_cast<int>(std::ceil(dw)), static_cast<int>(std::ceil(dh))}, options.hough);
    result.success = v.verified;
    result.num_inliers = v.num_inliers;
    result.inliers = v.inliers;
    const auto& m = v.db_from_query.m;
    result.db_from_query << m[0], m[1], m[2], m[3], m[4], m[5], 0, 0, 1;
    if (model == GeometricModel::kHoughHomography && v.verified) {
      auto refined = HomographyAgreeingWith(query, db, matches, v.inliers, options);
      if (!refined) return std::unexpected(refined.error());
      std::optional<RobustFitResult> homography = std::move(*refined);
      if (homography.has_value()) {
        result.num_inliers = homography->num_inliers;
        result.inliers = std::move(homography->inliers);
        result.db_from_query = homography->db_from_query;
      }
    }
    return result;
  }

  const size_t min_sample = model == GeometricModel::kSimilarity ? 2
                            : model == GeometricModel::kAffine   ? 3
                            : model == GeometricModel::kHomography ? 4
                                                                   : 8;
  if (matches.size() < min_sample) return result;
  std::vector<cv::Point2f> src, dst;
  src.reserve(matches.size());
  dst.reserve(matches.size());
  for (const Match& m : matches) {
    src.emplace_back(query[m.query_index].x, query[m.query_index].y);
    dst.emplace_back(db[m.db_index].x, db[m.db_index].y);
  }
  const bool magsac = options.estimator == RobustFitOptions::Estimator::kMagsac;
  const double threshold = options.reprojection_px;
  cv::Mat estimate;
  std::vector<uchar> mask;
  try {
    switch (model) {
      case GeometricModel::kSimilarity:
        estimate = cv::estimateAffinePartial2D(src, dst, mask, cv::RANSAC, threshold, static_cast<size_t>(options.max_iterations),
                                               options.confidence, static_cast<size_t>(options.refine_iterations));
        break;
      case GeometricModel::kAffine:
        estimate = cv::estimateAffine2D(src, dst, mask, magsac ? cv::USAC_MAGSAC : cv::RANSAC, threshold,
                                        static_cast<size_t>(options.max_iterations), options.confidence,
                                        static_cast<size_t>(options.refine_iterations));
        break;
      case GeometricModel::kHomography:
        estimate = cv::findHomography(src, dst, magsac ? cv::USAC_MAGSAC : cv::RANSAC, threshold, mask, options.max_iterations,
                                      options.confidence);
        break;
      case GeometricModel::kFundamental:
        estimate = cv::findFundamentalMat(src, dst, magsac ? static_cast<int>(cv::USAC_MAGSAC) : static_cast<int>(cv::FM_RANSAC), threshold, options.confidence,
                                          options.max_iterations, mask);
        break;
      case GeometricModel::kHoughAffine:
      case GeometricModel::kHoughHomography:
        break;
    }
  } catch (const cv::Exception&) {
    // OpenCV throws on degenerate configurations (e.g. all points identical): no model, not an error.
    return result;
  }
  if (estimate.empty()) return result;
  Eigen::Matrix3d h = Eigen::Matrix3d::Identity();
  cv::Mat e64;
  estimate.convertTo(e64, CV_64F);
  // findFundamentalMat may stack several 3x3 solutions (7-point); the first is the best.
  for (int r = 0; r < std::min(e64.rows, 3); ++r) {
    for (int c = 0; c < 3; ++c) h(r, c) = e64.at<double>(r, c);
  }
  if (model == GeometricModel::kHomography && std::abs(h(2, 2)) > 1e-12) h /= h(2, 2);
  if (!h.allFinite()) return result;
  for (size_t i = 0; i < mask.size() && i < matches.size(); ++i) {
    if (mask[i]) result.inliers.push_back(static_cast<uint32_t>(i));
  }
  result.num_inliers = static_cast<int>(result.inliers.size());
  result.db_from_query = h;
  result.success = result.inliers.size() >= min_sample;
  if (!result.success) {
    result.inliers.clear();
    result.num_inliers = 0;
    result.db_from_query = Eigen::Matrix3d::Identity();
  }
  return result;
}

Result<std::optional<RobustFitResult>> HomographyAgreeingWith(std::span<const Keypoint> query,
                                                              std::span<const Keypoint> db,
                                                              std::span<const Match> matches,
                                                              std::span<const uint32_t> hough_inliers,
                                                              const RobustFitOptions& options) {
  auto fit = FitRobust(GeometricModel::kHomography, query, db, matches, options);
  if (!fit) return std::unexpected(fit.error());
  if (!fit->success) return std::optional<RobustFitResult>();
  // Both lists are ascending indices into `matches`.
  size_t kept = 0;
  for (size_t i = 0, j = 0; i < hough_inliers.size() && j < fit->inliers.size();) {
    if (hough_inliers[i] == fit->inliers[j]) {
      ++kept, ++i, ++j;
    } else if (hough_inliers[i] < fit->inliers[j]) {
      ++i;
    } else {
      ++j;
    }
  }
  if (2 * kept < hough_inliers.size()) return std::optional<RobustFitResult>();
  // Its inliers become the answer's, and "verified" promises at least min_inliers of them.
  if (fit->num_inliers < options.hough.min_inliers) return std::optional<RobustFitResult>();
  return std::optional<RobustFitResult>(std::move(*fit));
}

}  // namespace oxbow::sift
