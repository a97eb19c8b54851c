#include "api/pair_match.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <span>

namespace oxbow::api {

namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

// Bounding box x1,y1,x2,y2 of the keypoints of `features`; the whole image when it has none.
std::array<float, 4> KeypointBox(const sift::FeatureSet& features) {
  if (features.keypoints.empty()) {
    return {0, 0, static_cast<float>(features.image_width), static_cast<float>(features.image_height)};
  }
  std::array<float, 4> box = {std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
                              std::numeric_limits<float>::lowest(), std::numeric_limits<float>::lowest()};
  for (const auto& k : features.keypoints) {
    box[0] = std::min(box[0], k.x);
    box[1] = std::min(box[1], k.y);
    box[2] = std::max(box[2], k.x);
    box[3] = std::max(box[3], k.y);
  }
  return box;
}

// The inlier pairs as {ax, ay, bx, by}; `inliers` index `matches`.
std::vector<std::array<float, 4>> InlierPairs(const sift::FeatureSet& a, const sift::FeatureSet& b,
                                              std::span<const sift::Match> matches, std::span<const uint32_t> inliers) {
  std::vector<std::array<float, 4>> pairs;
  pairs.reserve(inliers.size());
  for (uint32_t i : inliers) {
    const auto& ka = a.keypoints[matches[i].query_index];
    const auto& kb = b.keypoints[matches[i].db_index];
    pairs.push_back({ka.x, ka.y, kb.x, kb.y});
  }
  return pairs;
}

}  // namespace

Result<PairMatchResult> MatchPair(const sift::FeatureSet& a, const sift::FeatureSet& b,
                                  const PairMatchOptions& options) {
  PairMatchResult result;
  result.model = options.model;
  result.keypoints_a = a.size();
  result.keypoints_b = b.size();

  auto start = std::chrono::steady_clock::now();
  auto matches = sift::MatchDescriptors(a, b, options.match);
  if (!matches) return std::unexpected(matches.error());
  result.match_ms = MsSince(start);
  result.tentative_matches = matches->size();

  start = std::chrono::steady_clock::now();
  const std::array<int, 2> b_size = {b.image_width, b.image_height};
  if (options.model == sift::GeometricModel::kHoughAffine) {
    const std::array<float, 4> a_region = {0, 0, static_cast<float>(a.image_width), static_cast<float>(a.image_height)};
    const sift::VerificationResult v =
        sift::VerifyHoughAffine(a.keypoints, b.keypoints, *matches, a_region, b_size, options.fit.hough);
    result.verified = v.verified;
    result.inliers = v.num_inliers;
    const auto& m = v.db_from_query.m;
    result.b_from_a << m[0], m[1], m[2], m[3], m[4], m[5], 0, 0, 1;
    result.region_b = v.db_region;
    if (options.correspondences) result.correspondences = InlierPairs(a, b, *matches, v.inliers);
  } else {
    auto fit = sift::FitRobust(options.model, a.keypoints, b.keypoints, *matches, options.fit);
    if (!fit) return std::unexpected(fit.error());
    result.verified = fit->success;
    result.inliers = fit->num_inliers;
    result.b_from_a = fit->db_from_query;
    if (options.correspondences) result.correspondences = InlierPairs(a, b, *matches, fit->inliers);
    if (fit->success && options.model != sift::GeometricModel::kFundamental) {
      result.region_b = sift::ProjectBox(fit->db_from_query, KeypointBox(a), b_size);
    }
  }
  result.verify_ms = MsSince(start);
  return result;
}

nlohmann::json PairMatchToJson(const PairMatchResult& r) {
  nlohmann::json transform = nlohmann::json::array();
  for (int i = 0; i < 3; ++i) {
    transform.push_back({r.b_from_a(i, 0), r.b_from_a(i, 1), r.b_from_a(i, 2)});
  }
  nlohmann::json json = {{"model", sift::GeometricModelName(r.model)},
          {"keypoints", {{"a", r.keypoints_a}, {"b", r.keypoints_b}}},
          {"tentative_matches", r.tentative_matches},
          {"verified", r.verified},
          {"inliers", r.inliers},
          {"transform", transform},
          {"region", r.region_b},
          {"timings_ms", {{"match", r.match_ms}, {"verify", r.verify_ms}}}};
  if (!r.correspondences.empty()) {
    // Hundredths of a pixel: plenty for drawing, and half the bytes of full float precision.
    nlohmann::json pairs = nlohmann::json::array();
    for (const auto& c : r.correspondences) {
      nlohmann::json pair = nlohmann::json::array();
      for (float v : c) pair.push_back(std::round(static_cast<double>(v) * 100) / 100);
      pairs.push_back(std::move(pair));
    }
    json["correspondences"] = std::move(pairs);
  }
  return json;
}

}  // namespace oxbow::api
