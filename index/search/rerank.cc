#include "index/search/rerank.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <limits>
#include <numeric>
#include <tuple>
#include <vector>

#include "index/search/overlay.h"

namespace oxbow::index {
namespace {

// The inlier tolerance of the overlay measure: api::DuplicateOptions::inlier_tolerance's default.
constexpr double kOverlayTolerance = 0.015;
// Above this median Hamming distance of the verifier's inliers a match is not measured as a possible
// overlay: pasted pixels measure at most search::kIdenticalHamming, but the verifier's inliers include
// features at the overlay's edge, where the surroundings differ (a logo on two photos: 8 bits), while
// other photos of one object differ by about a quarter of the 64 bits.
constexpr float kOverlaySuspectHamming = 12;
// A region's footprint in the db image may pass its edges by this share of its sides (the fit's error).
constexpr double kFootprintSlack = 0.05;
// An anchor's inliers with any one left out spread at least this many median keypoint scales across
// their principal axis (SpansAnArea). Below the verifier's 3.5 for all inliers: on the duplicate
// benchmark a row of caption letters plus one chance inlier measures 1.6-2.4, while a true Paris anchor
// of 7 inliers, whose farthest inlier left out leaves a narrow cluster, measures 2.9 and chains 16 views
// of its building (3.5 loses them: Paris subset mAP 0.937 -> 0.929).
constexpr double kAnchorSpread = 2.5;

// The features inside `box` (x1, y1, x2, y2) in the box's frame (shifted to its corner; its size as the
// image size), from `n` features given by feature(i) = (keypoint, word, signature).
template <typename Feature>
search::QueryFeatures InBox(size_t n, const std::array<float, 4>& box, const Feature& feature) {
  search::QueryFeatures out;
  out.width = std::max(1, static_cast<int>(std::ceil(box[2] - box[0])));
  out.height = std::max(1, static_cast<int>(std::ceil(box[3] - box[1])));
  for (size_t i = 0; i < n; ++i) {
    auto [k, word, signature] = feature(i);
    if (k.x < box[0] || k.x > box[2] || k.y < box[1] || k.y > box[3]) continue;
    k.x -= box[0];
    k.y -= box[1];
    out.keypoints.push_back(k);
    out.words.push_back(word);
    out.signatures.push_back(signature);
  }
  return out;
}

// The smallest standard deviation of `points` across their principal axis with any one of them left out,
// in pixels (sift::HoughVerifyOptions::min_inlier_spread's measure, before its division by the keypoint
// scale). O(n): each point's removal downdates the sums of the centred coordinates (which sum to zero, so
// the other points' mean is -(x, y) / (n - 1)).
double SpreadWithoutAnyOne(std::span<const std::array<double, 2>> points) {
  const size_t n = points.size();
  if (n < 4) return 0;
  double cx = 0, cy = 0;
  for (const auto& [x, y] : points) cx += x, cy += y;
  cx /= static_cast<double>(n), cy /= static_cast<double>(n);
  double sxx = 0, sxy = 0, syy = 0;
  for (const auto& [px, py] : points) {
    const double x = px - cx, y = py - cy;
    sxx += x * x, sxy += x * y, syy += y * y;
  }
  const auto m = static_cast<double>(n - 1);
  double smallest = std::numeric_limits<double>::infinity();
  for (const auto& [px, py] : points) {
    const double x = px - cx, y = py - cy;
    const double mx = -x / m, my = -y / m;
    const double vxx = (sxx - x * x - m * mx * mx) / (m - 1), vyy = (syy - y * y - m * my * my) / (m - 1);
    const double vxy = (sxy - x * y - m * mx * my) / (m - 1);
    // The smaller eigenvalue of the covariance: the variance across the principal axis.
    const double across = (vxx + vyy) / 2 - std::hypot((vxx - vyy) / 2, vxy);
    smallest = std::min(smallest, std::sqrt(std::max(0.0, across)));
  }
  return smallest;
}

// Whether a firm match's inliers span an area in both images with any one of them left out: at least
// kAnchorSpread of their median keypoint scale across their principal axis. The verifier's firmness
// leaves out the inlier farthest from the principal axis; when a single inlier lies far off a line of
// them (a word matched to the same word in another caption, plus one chance inlier across the image),
// that inlier sets the axis and the line passes for an area. Such a match verifies but does not anchor
// a chain. Off when the verifier's spread test is (min_inlier_spread 0).
bool SpansAnArea(std::span<const sift::Keypoint> query, std::span<const sift::Keypoint> db,
                 std::span<const sift::Match> matches, std::span<const uint32_t> inliers,
                 const sift::HoughVerifyOptions& options) {
  if (options.min_inlier_spread <= 0) return true;
  thread_local std::vector<std::array<double, 2>> points;
  thread_local std::vector<float> scales;
  for (const bool query_side : {true, false}) {
    points.clear();
    scales.clear();
    for (const uint32_t i : inliers) {
      const sift::Keypoint& k = query_side ? query[matches[i].query_index] : db[matches[i].db_index];
      points.push_back({k.x, k.y});
      scales.push_back(k.scale);
    }
    if (scales.empty()) return false;
    const auto middle = scales.begin() + static_cast<std::ptrdiff_t>(scales.size() / 2);
    std::nth_element(scales.begin(), middle, scales.end());
    if (SpreadWithoutAnyOne(points) < kAnchorSpread * std::max(*middle, 1e-6f)) return false;
  }
  return true;
}

// Whether a verified match is only pixels pasted on both images (a logo, a caption band, a viewer's
// frame around two different pictures: index/search/overlay.h) rather than the query's content. The
// query side: its keypoints, words and signatures and its region.
bool OnlyAnOverlay(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                   std::span<const uint64_t> signatures, const std::array<float, 4>& region,
                   const PackedFeatures& db, const sift::VerificationResult& result,
                   std::span<const sift::Match> matches) {
  // Only pasted pixels can be an overlay. When the measure's inliers have near-identical signatures
  // (median Hamming distance at most search::kIdenticalHamming) the duplicate finder's rule decides
  // (search::OnlyAnOverlay: coverage, density and central cells of the match on both images, its frame).
  // Another photo of one object is left alone, whatever part of either image it covers; when the
  // verifier's own inliers already differ by more than kOverlaySuspectHamming (a match's distance is its
  // Hamming distance here) it is not measured.
  std::vector<float> distances(result.inliers.size());
  for (size_t k = 0; k < distances.size(); ++k) distances[k] = matches[result.inliers[k]].distance;
  if (distances.empty()) return false;
  const auto middle = distances.begin() + static_cast<std::ptrdiff_t>(distances.size() / 2);
  std::nth_element(distances.begin(), middle, distances.end());
  if (*middle > static_cast<float>(kOverlaySuspectHamming)) return false;
  // The query side in its region's frame (the region is the query image, or an anchor's matched region).
  const float x0 = region[0], y0 = region[1];
  const search::QueryFeatures a = InBox(keypoints.size(), region, [&](size_t i) {
    return std::tuple{keypoints[i], words[i], signatures[i]};
  });
  // The db side in the frame of the region's footprint (the box around its corners' places in the db
  // image): a match that covers an anchor's small region covers its footprint, not the whole db image.
  const auto& t = result.db_from_query.m;
  const sift::Affine2D shifted{{t[0], t[1], t[0] * x0 + t[1] * y0 + t[2], t[3], t[4], t[3] * x0 + t[4] * y0 + t[5]}};
  double bx1 = db.width(), by1 = db.height(), bx2 = 0, by2 = 0;
  for (const auto& [cx, cy] : {std::pair{0, 0}, {a.width, 0}, {0, a.height}, {a.width, a.height}}) {
    const Eigen::Vector2d corner = shifted.Apply({cx, cy});
    bx1 = std::min(bx1, corner.x()), by1 = std::min(by1, corner.y());
    bx2 = std::max(bx2, corner.x()), by2 = std::max(by2, corner.y());
  }
  // A footprint reaching out of the db image (a query shifted or scaled against it: a logo in opposite
  // corners) is the whole db image, as the duplicate finder measures a pair.
  const double slack_x = kFootprintSlack * db.width(), slack_y = kFootprintSlack * db.height();
  if (bx1 < -slack_x || by1 < -slack_y || bx2 > db.width() + slack_x || by2 > db.height() + slack_y) {
    bx1 = 0, by1 = 0, bx2 = db.width(), by2 = db.height();
  }
  bx1 = std::max(0.0, bx1), by1 = std::max(0.0, by1);
  bx2 = std::min<double>(db.width(), bx2), by2 = std::min<double>(db.height(), by2);
  if (bx2 <= bx1 || by2 <= by1) return false;
  const std::array<float, 4> footprint = {static_cast<float>(bx1), static_cast<float>(by1), static_cast<float>(bx2),
                                           static_cast<float>(by2)};
  const search::QueryFeatures b = InBox(db.size(), footprint, [&](size_t j) {
    return std::tuple{db.keypoint(j), db.word(j), db.signature(j)};
  });
  // The region's frame to the footprint's: db_from_query between the two shifts.
  const sift::Affine2D b_from_a{{shifted.m[0], shifted.m[1], shifted.m[2] - bx1, shifted.m[3], shifted.m[4],
                                 shifted.m[5] - by1}};
  const search::MatchMeasure m = search::MeasureMatch(a, b, b_from_a, kOverlayTolerance);
  const search::OverlayRule rule;
  if (m.hamming_median <= search::kIdenticalHamming) return search::OnlyAnOverlay(m, /*mirrored=*/false, rule);
  // Pasted pixels resampled (an overlay scaled on one image, a caption in another font size) differ by
  // more bits: a dense match (most features of the matched part are inliers) over a small part of both
  // images, off the centre of one, is such an overlay; a similar photo of one object is not dense.
  const bool dense = std::max(m.density_a, m.density_b) >= rule.overlay_density &&
                     std::max(m.coverage_a, m.coverage_b) < rule.overlay_coverage;
  return dense && std::min(m.central_a, m.central_b) < search::kCentralShareOther * m.inliers;
}

}  // namespace

QueryGeometry::QueryGeometry(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                             const std::array<float, 4>& region, std::span<const uint64_t> signatures,
                             int hamming_threshold, int max_matches)
    : keypoints_(keypoints),
      words_(words),
      signatures_(signatures),
      hamming_threshold_(hamming_threshold),
      max_matches_(static_cast<size_t>(std::max(0, max_matches))),
      order_(words.size()),
      region_(region) {
  OXBOW_CHECK(keypoints.size() == words.size());
  OXBOW_CHECK(signatures.empty() || signatures.size() == words.size());
  std::iota(order_.begin(), order_.end(), 0u);
  std::stable_sort(order_.begin(), order_.end(), [&](uint32_t a, uint32_t b) { return words_[a] < words_[b]; });
  runs_ = WordRuns(order_.size(), [&](size_t i) { return words_[order_[i]]; });
}

sift::VerificationResult QueryGeometry::Verify(const PackedFeatures& db, int max_pairs_per_word,
                                               const sift::HoughVerifyOptions& options, bool* overlay) const {
  if (overlay != nullptr) *overlay = false;
  // Scratch reused by every call on this thread: a re-ranking pass verifies hundreds of candidates.
  thread_local std::vector<sift::Match> matches;
  thread_local std::vector<sift::Keypoint> db_keypoints;
  thread_local std::vector<std::array<uint32_t, 3>> close;  // Hamming distance, query k, db k of a word's pairs
  thread_local std::vector<uint8_t> query_used, db_used;
  matches.clear();
  const bool hamming = !signatures_.empty() && !db.signature_bytes().empty();
  const size_t nd = db.size();
  const auto limit = static_cast<size_t>(max_pairs_per_word);
  size_t r = 0;  // first query run whose word may still occur in the db (db words ascend)
  for (size_t j = 0; j < nd;) {
    // The db image's run of word w: [j, j2). Most words are not in the query: one bit test skips them.
    const uint32_t w = db.word(j);
    size_t j2 = j + 1;
    while (j2 < nd && db.word(j2) == w) ++j2;
    if (const auto [i, i_end] = runs_.Find(w, r); i_end > i) {
      const size_t cq = i_end - i, cd = j2 - j;
      if (hamming && cq == 1 && cd == 1) {
        // Most shared words: one feature on each side, one pair (the general case below, without its
        // scratch).
        const int h = std::popcount(signatures_[order_[i]] ^ db.signature(j));
        if (h <= hamming_threshold_) matches.push_back({order_[i], static_cast<uint32_t>(j), static_cast<float>(h)});
      } else if (hamming) {
        // Pairs within the threshold, one-to-one closest first (ties in (query, db) index order). A
        // match's distance is its Hamming distance.
        close.clear();
        for (size_t a = 0; a < cq; ++a) {
          for (size_t b = 0; b < cd; ++b) {
            const auto h = static_cast<uint32_t>(std::popcount(signatures_[order_[i + a]] ^ db.signature(j + b)));
            if (h <= static_cast<uint32_t>(hamming_threshold_)) close.push_back({h, static_cast<uint32_t>(a), static_cast<uint32_t>(b)});
          }
        }
        std::sort(close.begin(), close.end());
        query_used.assign(cq, 0);
        db_used.assign(cd, 0);
        for (const auto& [h, a, b] : close) {
          if (query_used[a] != 0 || db_used[b] != 0) continue;
          query_used[a] = db_used[b] = 1;
          matches.push_back({order_[i + a], static_cast<uint32_t>(j + b), static_cast<float>(h)});
        }
      } else if (cq <= limit && cd <= limit) {
        // The word's cq x cd pairs made one-to-one, as sift::EnforceOneToOne does for them: features of
        // different words never share a pair, all pairs of a word have the same "distance" cq * cd
        // (pairs from a word seen once on each side are the most reliable), and its tie-break by
        // (query index, db index) pairs the k-th smallest query index with the k-th smallest db index.
        // Both runs are ascending (stable sort by word; db features in index order).
        const auto distance = static_cast<float>(cq * cd);
        for (size_t k = 0; k < std::min(cq, cd); ++k) {
          // db_index numbers the compact keypoint array built below.
          matches.push_back({order_[i + k], static_cast<uint32_t>(j + k), distance});
        }
      }
    }
    j = j2;
  }
  // Inliers are a subset of the one-to-one matches: with fewer than min_inliers of them the candidate
  // cannot verify, so the verifier is not run (same result, no cost).
  if (matches.size() < static_cast<size_t>(std::max(3, options.min_inliers))) return {};
  if (hamming && max_matches_ > 0 && matches.size() > max_matches_) {
    // The closest max_matches_ (a query feature is in one match at most, so the order is total).
    std::nth_element(matches.begin(), matches.begin() + static_cast<std::ptrdiff_t>(max_matches_), matches.end(),
                     [](const sift::Match& a, const sift::Match& b) {
                       return a.distance != b.distance ? a.distance < b.distance : a.query_index < b.query_index;
                     });
    matches.resize(max_matches_);
  }
  std::sort(matches.begin(), matches.end(),
            [](const sift::Match& a, const sift::Match& b) { return a.query_index < b.query_index; });
  // Only the matched db keypoints are dequantised, into a compact array the matches index.
  db_keypoints.resize(matches.size());
  for (size_t m = 0; m < matches.size(); ++m) {
    db_keypoints[m] = db.keypoint(matches[m].db_index);
    matches[m].db_index = static_cast<uint32_t>(m);
  }
  sift::VerificationResult result =
      sift::VerifyHoughAffine(keypoints_, db_keypoints, matches, region_, {db.width(), db.height()}, options);
  if (result.verified && hamming && OnlyAnOverlay(keypoints_, words_, signatures_, region_, db, result, matches)) {
    result.verified = false;
    result.firm = false;
    if (overlay != nullptr) *overlay = true;
  }
  if (result.firm && !SpansAnArea(keypoints_, db_keypoints, matches, result.inliers, options)) result.firm = false;
  return result;
}

}  // namespace oxbow::index
