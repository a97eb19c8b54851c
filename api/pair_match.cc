#include "api/pair_match.h"

#include <chrono>
#include <cmath>
#include <span>
#include <string>

namespace oxbow::api {

namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
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

// The estimator settings with the one min_inliers of PairMatchOptions.
sift::RobustFitOptions FitOptions(const PairMatchOptions& options) {
  sift::RobustFitOptions fit = options.fit;
  fit.hough.min_inliers = options.min_inliers;
  return fit;
}

}  // namespace

sift::SiftOptions PairMatchExtractorOptions(const sift::SiftOptions& base) {
  sift::SiftOptions options = base;
  options.refine_in_scale = base.keypoint_style == sift::KeypointStyle::kVlfeat;
  return options;
}

std::optional<std::string> PairMatchOptions::Check() const {
  if (min_inliers < 3) return "min_inliers must be >= 3, got " + std::to_string(min_inliers);
  if (auto problem = match.Check()) return problem;
  if (auto problem = FitOptions(*this).Check()) return problem;
  return std::nullopt;
}

Result<PairMatchResult> MatchPair(const sift::FeatureSet& a, const sift::FeatureSet& b,
                                  const PairMatchOptions& options) {
  if (auto problem = options.Check()) return Fail(ErrorCode::kInvalidArgument, *problem);
  PairMatchResult result;
  result.model = options.model;
  result.width_a = a.image_width;
  result.height_a = a.image_height;
  result.width_b = b.image_width;
  result.height_b = b.image_height;
  result.keypoints_a = a.size();
  result.keypoints_b = b.size();

  auto start = std::chrono::steady_clock::now();
  auto matches = sift::MatchDescriptors(a, b, options.match);
  if (!matches) return std::unexpected(matches.error());
  result.matches = std::move(*matches);
  result.match_ms = MsSince(start);

  start = std::chrono::steady_clock::now();
  const sift::RobustFitOptions fit_options = FitOptions(options);
  // The whole of image a is the query region, as in a search without a bbox.
  const std::array<float, 4> a_region = {0, 0, static_cast<float>(a.image_width), static_cast<float>(a.image_height)};
  const std::array<int, 2> b_size = {b.image_width, b.image_height};
  Eigen::Matrix3d transform;
  if (options.model == sift::GeometricModel::kHoughAffine || options.model == sift::GeometricModel::kHoughHomography) {
    sift::VerificationResult v =
        sift::VerifyHoughAffine(a.keypoints, b.keypoints, result.matches, a_region, b_size, fit_options.hough);
    result.verified = v.verified;  // min_inliers and the plausible-affine test
    const auto& m = v.db_from_query.m;
    transform << m[0], m[1], m[2], m[3], m[4], m[5], 0, 0, 1;
    if (options.model == sift::GeometricModel::kHoughHomography && v.verified) {
      auto refined = sift::HomographyAgreeingWith(a.keypoints, b.keypoints, result.matches, v.inliers, fit_options);
      if (!refined) return std::unexpected(refined.error());
      std::optional<sift::RobustFitResult> homography = std::move(*refined);
      if (homography.has_value()) {
        transform = homography->db_from_query;
        v.inliers = std::move(homography->inliers);
      }
    }
    result.inliers = std::move(v.inliers);
  } else {
    auto fit = sift::FitRobust(options.model, a.keypoints, b.keypoints, result.matches, fit_options);
    if (!fit) return std::unexpected(fit.error());
    result.verified = fit->success && fit->num_inliers >= options.min_inliers;
    result.inliers = std::move(fit->inliers);
    transform = fit->db_from_query;
  }
  if (result.verified) {
    result.transform = transform;
    if (options.model != sift::GeometricModel::kFundamental) result.region = sift::ProjectBox(transform, a_region, b_size);
  }
  if (options.correspondences) result.correspondences = InlierPairs(a, b, result.matches, result.inliers);
  result.verify_ms = MsSince(start);
  return result;
}

nlohmann::json PairMatchToJson(const PairMatchResult& r, const PairMatchCallerTimings& timings) {
  nlohmann::json transform = nullptr;
  if (r.transform) {
    transform = nlohmann::json::array();
    for (int i = 0; i < 3; ++i) transform.push_back({(*r.transform)(i, 0), (*r.transform)(i, 1), (*r.transform)(i, 2)});
  }
  nlohmann::json json = {
      {"model", sift::GeometricModelName(r.model)},
      {"verified", r.verified},
      {"inliers", r.inliers.size()},
      {"tentative_matches", r.matches.size()},
      {"transform", std::move(transform)},
      {"region", r.region ? nlohmann::json(*r.region) : nlohmann::json(nullptr)},
      {"a", {{"width", r.width_a}, {"height", r.height_a}, {"keypoints", r.keypoints_a}}},
      {"b", {{"width", r.width_b}, {"height", r.height_b}, {"keypoints", r.keypoints_b}}},
      {"timings_ms",
       {{"decode_extract_a", timings.decode_extract_a},
        {"decode_extract_b", timings.decode_extract_b},
        {"match", r.match_ms},
        {"verify", r.verify_ms},
        {"total", timings.total}}}};
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
