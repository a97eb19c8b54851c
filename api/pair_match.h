// The one match-then-verify pipeline of two images' features, behind both POST /v1/match (Service::Match)
// and `oxbow match`; the callers only decode and extract. MatchDescriptors (ratio test, optional mutual
// check, one-to-one), then the geometric model: Lowe's Hough/affine verifier (VerifyHoughAffine, as
// search re-ranking uses it) or a robust estimator (FitRobust), then the verified rule, the region and
// the JSON mapping, so both front ends give the same answer in the same shape.
//
// Verified rule (every model): at least PairMatchOptions::min_inliers inliers, and for hough-affine and
// hough-homography also the Hough verifier's plausible-affine test (sift/verify.h); for the robust models the estimator must have succeeded.
// Region: the same definition as a search result's "region" (index/image_index.cc, api/json.cc): the
// query region, here the whole image a (0,0,width,height), mapped through the fitted transform into b,
// as the axis-aligned bounding box of the four mapped corners clipped to b (sift::ProjectBox). Set only
// when verified and the model maps points (not for fundamental).
// Transport-free; thread-safe (no shared state).
#pragma once

#include <array>
#include <optional>
#include <vector>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "sift/base/error.h"
#include "sift/match.h"
#include "sift/sift.h"
#include "sift/types.h"
#include "sift/verify.h"

namespace oxbow::api {

// The extractor settings pair matching uses, from the settings `base` (the server's index or the
// command's flags): with the vlfeat keypoint style, refinement also in scale
// (sift::SiftOptions::refine_in_scale), with which graf 1 -> 3's homography came out 1.04 px from the
// true one at the corners against 3.44 px without, and boat 1 -> 3, 4, 5 at
// 0.17, 0.75, 1.33 px against 0.11, 0.87, 1.36 (eval/results/matching.md); everything else as `base`.
sift::SiftOptions PairMatchExtractorOptions(const sift::SiftOptions& base);

struct PairMatchOptions {
  sift::MatchOptions match;                                         // descriptor matching (sift/match.h)
  // Model fitted to the matches. hough-homography: the Hough/affine verifier decides, a homography
  // that agrees with it gives the transform (sift/verify.h); on the homography pairs its corner error
  // is within 0.1 px of OpenCV RootSIFT + MAGSAC's or better, where hough-affine's is 0.4-47 px worse
  // than this default's (eval/results/matching.md).
  sift::GeometricModel model = sift::GeometricModel::kHoughHomography;
  // Estimator settings, and the Hough verifier's in fit.hough (whose min_inliers is replaced by the one
  // below, so that one number rules every model).
  sift::RobustFitOptions fit;
  int min_inliers = sift::HoughVerifyOptions{}.min_inliers;  // "verified" needs this many inliers, >= 3
  // Fill PairMatchResult::correspondences with the inlier pairs (for drawing them; off by default to
  // keep responses small).
  bool correspondences = false;

  // Empty when every field is valid, else a message naming the field.
  std::optional<std::string> Check() const;
};

struct PairMatchResult {
  sift::GeometricModel model = sift::GeometricModel::kHoughAffine;
  int width_a = 0, height_a = 0, width_b = 0, height_b = 0;  // original image sizes, pixels
  size_t keypoints_a = 0;
  size_t keypoints_b = 0;
  std::vector<sift::Match> matches;  // tentative matches (after ratio test / mutual / one-to-one)
  bool verified = false;             // the verified rule of the file comment
  // Inliers of the best fit, indices into `matches`, also when the fit was rejected (as a search
  // result reports its inlier count when unverified).
  std::vector<uint32_t> inliers;
  // Set only when verified: image-a pixels -> image-b pixels (3x3; hough-affine, similarity and affine
  // (and hough-homography when no homography agreed)
  // have last row 0 0 1), or for fundamental F with x_b^T F x_a = 0.
  std::optional<Eigen::Matrix3d> transform;
  std::optional<std::array<float, 4>> region;  // x1,y1,x2,y2 in b (see the file comment); set only when verified
  // With PairMatchOptions::correspondences: one {ax, ay, bx, by} per inlier (keypoint positions in
  // original pixels of a and b), in `inliers` order; empty otherwise.
  std::vector<std::array<float, 4>> correspondences;
  double match_ms = 0;
  double verify_ms = 0;
};

// `a` plays the query, `b` the database image. Errors (kInvalidArgument): invalid options (Check()),
// errors of MatchDescriptors / FitRobust. Cost: O(|a| |b| 128) with brute force matching, plus the fit.
[[nodiscard]] Result<PairMatchResult> MatchPair(const sift::FeatureSet& a, const sift::FeatureSet& b,
                                                const PairMatchOptions& options);

// Stage times measured by the caller around MatchPair, ms.
struct PairMatchCallerTimings {
  double decode_extract_a = 0;
  double decode_extract_b = 0;
  double total = 0;  // decode + extract of both, matching and verification
};

// The JSON of a match, the same from the CLI and HTTP:
// {"model", "verified", "inliers", "tentative_matches",
//  "transform": 3x3 row-major (see PairMatchResult::transform) or null, "region": [x1,y1,x2,y2] or null,
//  "a": {"width", "height", "keypoints"}, "b": {...},
//  "timings_ms": {"decode_extract_a", "decode_extract_b", "match", "verify", "total"}},
// plus "correspondences": [[ax, ay, bx, by], ...] when they were asked for.
nlohmann::json PairMatchToJson(const PairMatchResult& result, const PairMatchCallerTimings& timings);

}  // namespace oxbow::api
