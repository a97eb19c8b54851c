// Matching two images' features and fitting a geometric model: the computation behind POST /v1/match
// (and the same steps as `oxbow match`): MatchDescriptors (ratio test, optional mutual check,
// one-to-one) then either Lowe's Hough/affine verifier (VerifyHoughAffine, whole-image query region) or
// a robust estimator (FitRobust). Transport-free; thread-safe (no shared state).
#pragma once

#include <array>
#include <vector>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "sift/base/error.h"
#include "sift/match.h"
#include "sift/types.h"
#include "sift/verify.h"

namespace oxbow::api {

struct PairMatchOptions {
  sift::MatchOptions match;                                   // descriptor matching (sift/match.h)
  sift::GeometricModel model = sift::GeometricModel::kHoughAffine;  // model fitted to the matches
  sift::RobustFitOptions fit;                                 // estimator settings (and Hough settings)
  // Fill PairMatchResult::correspondences with the inlier pairs (for drawing them; off by default to
  // keep responses small).
  bool correspondences = false;
};

struct PairMatchResult {
  sift::GeometricModel model = sift::GeometricModel::kHoughAffine;
  size_t keypoints_a = 0;
  size_t keypoints_b = 0;
  size_t tentative_matches = 0;   // after ratio test / mutual / one-to-one
  bool verified = false;          // the model was fitted (Hough: accepted by its rule)
  int inliers = 0;
  Eigen::Matrix3d b_from_a = Eigen::Matrix3d::Identity();  // image-a pixels -> image-b pixels
  std::array<float, 4> region_b = {0, 0, 0, 0};  // where image a's keypoint bounding box lands in b (x1,y1,x2,y2)
  // With PairMatchOptions::correspondences: one {ax, ay, bx, by} per inlier (keypoint positions in
  // original pixels of a and b), in the verifier's order; empty otherwise.
  std::vector<std::array<float, 4>> correspondences;
  double match_ms = 0;
  double verify_ms = 0;
};

// `a` plays the query, `b` the database image. Errors from MatchDescriptors / FitRobust
// (kInvalidArgument). Cost: O(|a| |b| 128) with brute force matching, plus the model fit.
[[nodiscard]] Result<PairMatchResult> MatchPair(const sift::FeatureSet& a, const sift::FeatureSet& b,
                                                const PairMatchOptions& options);

// {"model", "keypoints": {"a", "b"}, "tentative_matches", "verified", "inliers",
//  "transform": 3x3 row-major b_from_a, "region": [x1,y1,x2,y2] in b, "timings_ms": {"match", "verify"}},
//  plus "correspondences": [[ax, ay, bx, by], ...] when they were asked for.
nlohmann::json PairMatchToJson(const PairMatchResult& result);

}  // namespace oxbow::api
