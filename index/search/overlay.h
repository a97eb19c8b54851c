// Whether a geometric match between two images shows the same content or only something pasted on
// both (a logo, a caption band, a viewer's frame around two different pictures). Used by the duplicate
// finder (api/duplicates.h, where the rule is documented with its settings) and by search's spatial
// verification (index/image_index.h, "Method"), so that a verified result shows the query's content.
//
// A match is measured against both images' features: its inliers are the features of `a` that land,
// under b_from_a, within a tolerance of a feature of `b` with the same word at a consistent scale; a
// twin is an inlier at the same place, scale and orientation (identical pixels there); coverage is the
// share of an image's feature-bearing cells of an 8 x 8 grid that hold an inlier; density the share of
// the features inside the matched region that are inliers.
#pragma once

#include <array>

#include "index/search/source.h"
#include "sift/types.h"

namespace oxbow::index::search {

// A small or dense match of distinct content is another photo of the same thing, not a shared overlay:
// the median Hamming distance of its inliers' signatures is above kIdenticalHamming (of 64 bits; pixels
// pasted on two photos give near-identical signatures, another photo of an object about a quarter of
// the bits), at least kCentralShare of its inliers lie in the central cells of one image and
// kCentralShareOther in those of the other (an overlay sits in a band, a corner or a border of both),
// and it covers at least kDistinctCoverage of one image.
inline constexpr int kIdenticalHamming = 6;
inline constexpr double kCentralShare = 0.1;
inline constexpr double kCentralShareOther = 0.01;
inline constexpr double kDistinctCoverage = 0.05;
// A mirrored match covers at least this much of one image: a mirror image of a photo matches most of
// it, while a symmetric logo or frame, or a symmetric part of a building, matches itself mirrored in part.
inline constexpr double kMirroredCoverage = 0.4;
// Two pictures in one frame (a screenshot of a viewer, a border, a template): the match is identical
// pixels at the same places (at least kFrameTwins of its inliers are twins, their signatures alike) around
// a block of the frame's centre where both images hold features and none match, which is at least
// kFramedContent of the cells the two images share (cells of a kFineGrid x kFineGrid grid). A copy
// differs from its original in scattered cells, a caption or a logo in a band or a corner.
inline constexpr double kFrameTwins = 0.5;
inline constexpr double kFramedContent = 0.2;
inline constexpr int kFineGrid = 16;

struct MatchMeasure {
  int inliers = 0;
  int twins = 0;           // inliers that are the same feature (same place, scale, orientation): identical pixels
  double density_a = 0, density_b = 0;  // inliers / features inside each region
  double coverage_a = 0, coverage_b = 0;
  bool central = false;  // some inlier in the central cells of a or b
  int central_a = 0, central_b = 0;  // inliers in the central cells of each
  int hamming_median = -1;           // of the inliers' signatures; -1 without signatures (mirrored)
  double framed = 0;                 // the frame measure (overlay.cc), the larger of both sides; 0 unless twins
  std::array<float, 4> region_a{}, region_b{};  // the inliers' bounding boxes
};

// The match of `a` onto `b` under b_from_a (a's pixels to b's); the inlier tolerance is
// tolerance_fraction of b's larger side, at least 4 pixels. a and b carry their images' sizes.
MatchMeasure MeasureMatch(const QueryFeatures& a, const QueryFeatures& b, const sift::Affine2D& b_from_a,
                          double tolerance_fraction);

// The thresholds of OnlyAnOverlay that a duplicate search can set (api::DuplicateOptions, same names).
struct OverlayRule {
  double min_coverage = 0.25;
  double overlay_coverage = 0.5;
  double overlay_density = 0.25;
};

// Whether a measured match shares only an overlay: it reaches no central cell, or it frames different
// content (kFrameTwins, kFramedContent), or it covers less than rule.min_coverage of both images (a
// mirrored one: less than kMirroredCoverage), or it is dense (identical pixels) over less than
// rule.overlay_coverage of both; unless its content is distinct (kIdenticalHamming, kCentralShare,
// kCentralShareOther, kDistinctCoverage; a mirrored match has no signatures to tell).
bool OnlyAnOverlay(const MatchMeasure& m, bool mirrored, const OverlayRule& rule);

}  // namespace oxbow::index::search
