// Tests of geometric verification: synthetic matches from known transforms with 50% outliers, real
// pairs with ground-truth homographies, unrelated pairs that must be rejected, and degenerate input.
#include "sift/verify.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <numbers>
#include <random>
#include <set>

#include <Eigen/Dense>
#include <opencv2/core.hpp>

#include "sift/match.h"
#include "sift/sift.h"
#include "tests/support/shared_data.h"

namespace oxbow::sift {
namespace {

constexpr double kPi = std::numbers::pi;

// ---------------------------------------------------------------- synthetic scenarios

struct Scenario {
  std::vector<Keypoint> query, db;
  std::vector<Match> matches;
  std::set<uint32_t> true_inliers;  // indices into matches
};

double WrapAngle(double a) {
  a = std::fmod(a, 2 * kPi);
  return a < 0 ? a + 2 * kPi : a;
}

// Query keypoints uniformly in a 640x480 image; inliers map into the db image through `truth` with
// `noise_px` Gaussian position noise and keypoint orientation/scale transformed consistently (a few
// degrees and ~10% of noise, as real SIFT detections have); outliers pair random query and db
// keypoints. Matches are shuffled.
Scenario MakeScenario(const Affine2D& truth, int num_inliers, int num_outliers, double noise_px, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> qx(10, 630), qy(10, 470), dx(0, 900), dy(0, 700);
  std::uniform_real_distribution<double> angle(0, 2 * kPi), log_scale(std::log(1.2), std::log(10.0));
  std::normal_distribution<double> pos_noise(0, noise_px), angle_noise(0, 3 * kPi / 180), scale_noise(0, 0.1);
  Scenario s;
  const double det_root = std::sqrt(std::abs(truth.Determinant()));
  for (int i = 0; i < num_inliers + num_outliers; ++i) {
    Keypoint q;
    q.x = static_cast<float>(qx(rng));
    q.y = static_cast<float>(qy(rng));
    q.orientation = static_cast<float>(angle(rng));
    q.scale = static_cast<float>(std::exp(log_scale(rng)));
    Keypoint d;
    if (i < num_inliers) {
      const Eigen::Vector2d p = truth.Apply({q.x, q.y});
      d.x = static_cast<float>(p.x() + pos_noise(rng));
      d.y = static_cast<float>(p.y() + pos_noise(rng));
      const Eigen::Vector2d dir(truth.m[0] * std::cos(q.orientation) + truth.m[1] * std::sin(q.orientation),
                                truth.m[3] * std::cos(q.orientation) + truth.m[4] * std::sin(q.orientation));
      d.orientation = static_cast<float>(WrapAngle(std::atan2(dir.y(), dir.x()) + angle_noise(rng)));
      d.scale = static_cast<float>(q.scale * det_root * std::exp(scale_noise(rng)));
    } else {
      d.x = static_cast<float>(dx(rng));
      d.y = static_cast<float>(dy(rng));
      d.orientation = static_cast<float>(angle(rng));
      d.scale = static_cast<float>(std::exp(log_scale(rng)));
    }
    s.query.push_back(q);
    s.db.push_back(d);
  }
  std::vector<uint32_t> order(s.query.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = static_cast<uint32_t>(i);
  std::shuffle(order.begin(), order.end(), rng);
  for (size_t m = 0; m < order.size(); ++m) {
    s.matches.push_back({order[m], order[m], 0.1f});
    if (order[m] < static_cast<uint32_t>(num_inliers)) s.true_inliers.insert(static_cast<uint32_t>(m));
  }
  return s;
}

Affine2D Similarity(double scale, double degrees, double tx, double ty) {
  const double c = scale * std::cos(degrees * kPi / 180), s = scale * std::sin(degrees * kPi / 180);
  return Affine2D{{c, -s, tx, s, c, ty}};
}

Eigen::Matrix3d ToMatrix(const Affine2D& a) {
  Eigen::Matrix3d h;
  h << a.m[0], a.m[1], a.m[2], a.m[3], a.m[4], a.m[5], 0, 0, 1;
  return h;
}

Eigen::Vector2d MapPoint(const Eigen::Matrix3d& h, double x, double y) {
  const Eigen::Vector3d p = h * Eigen::Vector3d(x, y, 1);
  return p.head<2>() / p.z();
}

// Largest (or mean) distance between where `estimate` and `truth` send the corners of a w x h image.
double MaxCornerError(const Eigen::Matrix3d& estimate, const Eigen::Matrix3d& truth, double w, double h) {
  double worst = 0;
  for (auto [x, y] : {std::pair{0.0, 0.0}, {w, 0.0}, {0.0, h}, {w, h}}) {
    worst = std::max(worst, (MapPoint(estimate, x, y) - MapPoint(truth, x, y)).norm());
  }
  return worst;
}
double MeanCornerError(const Eigen::Matrix3d& estimate, const Eigen::Matrix3d& truth, double w, double h) {
  double sum = 0;
  for (auto [x, y] : {std::pair{0.0, 0.0}, {w, 0.0}, {0.0, h}, {w, h}}) {
    sum += (MapPoint(estimate, x, y) - MapPoint(truth, x, y)).norm();
  }
  return sum / 4;
}

double KeptShare(const std::vector<uint32_t>& inliers, const std::set<uint32_t>& truth) {
  size_t kept = 0;
  for (uint32_t i : inliers) kept += truth.count(i);
  return double(kept) / double(truth.size());
}

size_t FalseInliers(const std::vector<uint32_t>& inliers, const std::set<uint32_t>& truth) {
  size_t wrong = 0;
  for (uint32_t i : inliers) wrong += truth.count(i) == 0;
  return wrong;
}

bool AllFinite(const VerificationResult& r) {
  for (double v : r.db_from_query.m) {
    if (!std::isfinite(v)) return false;
  }
  for (float v : r.db_region) {
    if (!std::isfinite(v)) return false;
  }
  return true;
}

struct Truth {
  const char* name;
  Affine2D transform;
};

const Truth kTruths[] = {
    {"similarity", Similarity(1.3, 25, 100, -40)},
    {"rotation_150", Similarity(0.7, 150, 600, 500)},
    {"affine", Affine2D{{1.1, 0.3, 20, -0.1, 0.8, 60}}},
};

TEST(VerifyHoughAffine, RecoversKnownTransformsWithHalfOutliers) {
  for (const Truth& truth : kTruths) {
    for (int num : {60, 400}) {
      const Scenario s = MakeScenario(truth.transform, num, num, 1.0, 42 + num);
      const VerificationResult r = VerifyHoughAffine(s.query, s.db, s.matches, {0, 0, 640, 480}, {900, 700});
      SCOPED_TRACE(std::string(truth.name) + " with " + std::to_string(num) + " inliers");
      EXPECT_TRUE(r.verified);
      EXPECT_EQ(r.num_inliers, static_cast<int>(r.inliers.size()));
      EXPECT_TRUE(std::is_sorted(r.inliers.begin(), r.inliers.end()));
      EXPECT_GE(KeptShare(r.inliers, s.true_inliers), 0.95);
      EXPECT_LE(FalseInliers(r.inliers, s.true_inliers), static_cast<size_t>(num) / 20);
      EXPECT_LT(MaxCornerError(ToMatrix(r.db_from_query), ToMatrix(truth.transform), 640, 480), 3.0);
      // db_region: the projected query image, clipped to the db image.
      const std::array<float, 4> expected = ProjectBox(ToMatrix(truth.transform), {0, 0, 640, 480}, {900, 700});
      for (int k = 0; k < 4; ++k) EXPECT_NEAR(r.db_region[k], expected[k], 3.0);
      EXPECT_GT(r.num_votes, 0);
    }
  }
}

TEST(VerifyHoughAffine, QueryRegionRestrictsTheModel) {
  // Only matches inside the region are the object; the region's box maps to where it lies in the db image.
  const Affine2D truth = Similarity(1.2, -30, 200, 250);
  const Scenario s = MakeScenario(truth, 200, 200, 0.8, 7);
  const std::array<float, 4> region = {100, 80, 400, 300};
  const VerificationResult r = VerifyHoughAffine(s.query, s.db, s.matches, region, {900, 700});
  ASSERT_TRUE(r.verified);
  const std::array<float, 4> expected = ProjectBox(ToMatrix(truth), region, {900, 700});
  for (int k = 0; k < 4; ++k) EXPECT_NEAR(r.db_region[k], expected[k], 3.0);
}

TEST(VerifyHoughAffine, PoseCheckRejectsMatchesWithInconsistentOrientation) {
  // Positions agree with the transform but orientations are random: without the keypoint pose check
  // they would be inliers; with it (default) they are not.
  Scenario s = MakeScenario(Similarity(1.0, 40, 50, 50), 100, 0, 0.5, 11);
  std::mt19937 rng(12);
  std::uniform_real_distribution<double> angle(0, 2 * kPi);
  std::set<uint32_t> scrambled;
  for (size_t m = 0; m < s.matches.size(); m += 4) {
    Keypoint& d = s.db[s.matches[m].db_index];
    d.orientation = static_cast<float>(WrapAngle(d.orientation + kPi / 2 + angle(rng) / 2));  // 90..270 deg off
    scrambled.insert(static_cast<uint32_t>(m));
  }
  const VerificationResult with_check = VerifyHoughAffine(s.query, s.db, s.matches, {0, 0, 640, 480}, {900, 700});
  ASSERT_TRUE(with_check.verified);
  for (uint32_t i : with_check.inliers) EXPECT_EQ(scrambled.count(i), 0u) << "match " << i;
  HoughVerifyOptions no_check;
  no_check.check_keypoint_pose = false;
  const VerificationResult without = VerifyHoughAffine(s.query, s.db, s.matches, {0, 0, 640, 480}, {900, 700}, no_check);
  EXPECT_GT(without.num_inliers, with_check.num_inliers);
}

// Matches at the given query points under one similarity; small keypoints (scale 1.5 px, a text's
// strokes; 2.7 px in the db image).
Scenario AtPoints(const std::vector<Eigen::Vector2d>& points) {
  const Affine2D truth = Similarity(1.8, 0, 40, 300);
  Scenario s;
  for (uint32_t i = 0; i < points.size(); ++i) {
    Keypoint q;
    q.x = static_cast<float>(points[i].x());
    q.y = static_cast<float>(points[i].y());
    q.scale = 1.5f;
    q.orientation = static_cast<float>(WrapAngle(0.5 * i));
    const Eigen::Vector2d p = truth.Apply(points[i]);
    Keypoint d = q;
    d.x = static_cast<float>(p.x());
    d.y = static_cast<float>(p.y());
    d.scale = 1.5f * 1.8f;
    s.query.push_back(q);
    s.db.push_back(d);
    s.matches.push_back({i, i, 0.1f});
  }
  return s;
}

// Twelve matches along one line of text (across it they spread by about half a stroke) or over an area
// of the same length.
Scenario LineOrArea(bool line) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> jitter(-1, 1);
  std::vector<Eigen::Vector2d> points;
  points.reserve(12);
  for (int i = 0; i < 12; ++i) points.emplace_back(100 + 18 * i, line ? 200 + jitter(rng) : 100 + 18 * ((i * 5) % 12));
  return AtPoints(points);
}

TEST(VerifyHoughAffine, InliersAlongALineDoNotVerify) {
  // Along a line the affine is undetermined across it (a word matched to the same word in another
  // text): the fit holds all twelve matches, yet the rule does not verify it unless the spread test is off.
  const Scenario line = LineOrArea(true);
  const VerificationResult r = VerifyHoughAffine(line.query, line.db, line.matches, {0, 0, 640, 480}, {900, 900});
  EXPECT_FALSE(r.verified);
  EXPECT_EQ(r.num_inliers, 12);
  HoughVerifyOptions no_spread;
  no_spread.min_inlier_spread = 0;
  const VerificationResult off = VerifyHoughAffine(line.query, line.db, line.matches, {0, 0, 640, 480}, {900, 900}, no_spread);
  EXPECT_TRUE(off.verified);
  EXPECT_EQ(off.num_inliers, 12);
  // The same twelve matches spread over an area verify.
  const Scenario area = LineOrArea(false);
  EXPECT_TRUE(VerifyHoughAffine(area.query, area.db, area.matches, {0, 0, 640, 480}, {900, 900}).verified);
  HoughVerifyOptions bad;
  bad.min_inlier_spread = -1;
  EXPECT_TRUE(bad.Check().has_value());
}

TEST(VerifyHoughAffine, FirmNeedsAnAreaWithoutItsStrayPointAndNotAThinBand) {
  const std::array<float, 4> region = {0, 0, 640, 480};
  const std::array<int, 2> db_size = {900, 900};
  // Over an area: verified and firm.
  const Scenario area = LineOrArea(false);
  const VerificationResult a = VerifyHoughAffine(area.query, area.db, area.matches, region, db_size);
  EXPECT_TRUE(a.verified);
  EXPECT_TRUE(a.firm);
  // A line of twelve plus one point 100 px off it: the thirteen span an area and verify, but without
  // the stray point they are a line: not firm.
  std::vector<Eigen::Vector2d> line;
  line.reserve(13);
  for (int i = 0; i < 12; ++i) line.emplace_back(100 + 18 * i, 200 + (i % 2 == 0 ? 0.5 : -0.5));
  line.emplace_back(200, 300);
  const Scenario stray = AtPoints(line);
  const VerificationResult l = VerifyHoughAffine(stray.query, stray.db, stray.matches, region, db_size);
  EXPECT_TRUE(l.verified);
  EXPECT_EQ(l.num_inliers, 13);
  EXPECT_FALSE(l.firm);
  // A band 24 px high and 200 px long (a line of text): its spread across passes min_inlier_spread with
  // or without any one point, but it is seven times longer than high: not firm unless the aspect test is off.
  std::vector<Eigen::Vector2d> band;
  band.reserve(12);
  for (int i = 0; i < 12; ++i) band.emplace_back(100 + 18 * i, 200 + 12 * std::array{-1.0, -0.33, 0.33, 1.0}[i % 4]);
  const Scenario text = AtPoints(band);
  const VerificationResult b = VerifyHoughAffine(text.query, text.db, text.matches, region, db_size);
  EXPECT_TRUE(b.verified);
  EXPECT_EQ(b.num_inliers, 12);
  EXPECT_FALSE(b.firm);
  HoughVerifyOptions no_aspect;
  no_aspect.min_firm_aspect = 0;
  EXPECT_TRUE(VerifyHoughAffine(text.query, text.db, text.matches, region, db_size, no_aspect).firm);
  // Unverified results are never firm.
  const Scenario thin = LineOrArea(true);
  EXPECT_FALSE(VerifyHoughAffine(thin.query, thin.db, thin.matches, region, db_size).firm);
  HoughVerifyOptions bad;
  bad.min_firm_aspect = 1.5;
  EXPECT_TRUE(bad.Check().has_value());
  bad.min_firm_aspect = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(bad.Check().has_value());
}

TEST(VerifyHoughAffine, RejectsRandomMatches) {
  for (uint32_t seed : {1u, 2u, 3u}) {
    const Scenario s = MakeScenario(Affine2D{}, 0, 300, 1.0, seed);
    const VerificationResult r = VerifyHoughAffine(s.query, s.db, s.matches, {0, 0, 640, 480}, {900, 700});
    EXPECT_FALSE(r.verified) << "seed " << seed << ": " << r.num_inliers << " inliers";
    EXPECT_TRUE(AllFinite(r));
  }
}

TEST(VerifyHoughAffine, DegenerateInputGivesFiniteUnverifiedResult) {
  const Scenario s = MakeScenario(Similarity(1, 0, 0, 0), 10, 0, 0.0, 3);
  const std::array<float, 4> region = {0, 0, 640, 480};
  // Zero and one match.
  for (size_t n : {size_t{0}, size_t{1}}) {
    const VerificationResult r = VerifyHoughAffine(s.query, s.db, std::span(s.matches).first(n), region, {900, 700});
    EXPECT_FALSE(r.verified);
    EXPECT_EQ(r.num_inliers, 0);
    EXPECT_TRUE(AllFinite(r));
  }
  // The same match 50 times: every vote in one bin, but no affine is determined.
  const std::vector<Match> same(50, s.matches[0]);
  VerificationResult r = VerifyHoughAffine(s.query, s.db, same, region, {900, 700});
  EXPECT_FALSE(r.verified);
  EXPECT_TRUE(AllFinite(r));
  // Collinear points (a translation along a line): the affine is undetermined.
  std::vector<Keypoint> q, d;
  std::vector<Match> line;
  for (int i = 0; i < 40; ++i) {
    q.push_back({10.0f + 10 * i, 20.0f + 5 * i, 2, 0.5f, 0, 0});
    d.push_back({15.0f + 10 * i, 22.0f + 5 * i, 2, 0.5f, 0, 0});
    line.push_back({static_cast<uint32_t>(i), static_cast<uint32_t>(i), 0.1f});
  }
  r = VerifyHoughAffine(q, d, line, region, {900, 700});
  EXPECT_FALSE(r.verified);
  EXPECT_TRUE(AllFinite(r));
  // Out-of-range indices, NaN keypoints, zero scales are ignored, not fatal.
  std::vector<Keypoint> bad_q = s.query;
  bad_q[0].x = std::numeric_limits<float>::quiet_NaN();
  bad_q[1].scale = 0;
  std::vector<Match> bad = s.matches;
  bad.push_back({1000, 0, 0.1f});
  bad.push_back({0, 1000, 0.1f});
  r = VerifyHoughAffine(bad_q, s.db, bad, region, {900, 700});
  EXPECT_TRUE(AllFinite(r));
  for (uint32_t i : r.inliers) {
    EXPECT_LT(i, s.matches.size());
    EXPECT_GE(s.matches[i].query_index, 2u);
  }
  // An empty region or invalid options: unverified.
  EXPECT_FALSE(VerifyHoughAffine(s.query, s.db, s.matches, {5, 5, 5, 100}, {900, 700}).verified);
  HoughVerifyOptions invalid;
  invalid.min_inliers = 2;
  EXPECT_TRUE(invalid.Check().has_value());
  EXPECT_FALSE(VerifyHoughAffine(s.query, s.db, s.matches, region, {900, 700}, invalid).verified);
}

TEST(VerifyHoughAffine, IsDeterministicAndIndependentOfMatchOrder) {
  const Scenario s = MakeScenario(Affine2D{{0.9, 0.2, 40, -0.2, 1.1, 30}}, 150, 150, 1.0, 5);
  const VerificationResult a = VerifyHoughAffine(s.query, s.db, s.matches, {0, 0, 640, 480}, {900, 700});
  const VerificationResult b = VerifyHoughAffine(s.query, s.db, s.matches, {0, 0, 640, 480}, {900, 700});
  EXPECT_EQ(a.inliers, b.inliers);
  EXPECT_EQ(a.db_from_query.m, b.db_from_query.m);
  std::vector<Match> reversed(s.matches.rbegin(), s.matches.rend());
  const VerificationResult c = VerifyHoughAffine(s.query, s.db, reversed, {0, 0, 640, 480}, {900, 700});
  ASSERT_TRUE(c.verified);
  // Same inlier matches, reported by their new positions.
  std::set<std::pair<uint32_t, uint32_t>> pa, pc;
  for (uint32_t i : a.inliers) pa.insert({s.matches[i].query_index, s.matches[i].db_index});
  for (uint32_t i : c.inliers) pc.insert({reversed[i].query_index, reversed[i].db_index});
  EXPECT_EQ(pa, pc);
}

TEST(Affine2D, InverseAndProjectBox) {
  const Affine2D a{{1.1, 0.3, 20, -0.1, 0.8, 60}};
  const auto inv = a.Inverse();
  ASSERT_TRUE(inv.has_value());
  const Eigen::Vector2d p(123, -45);
  EXPECT_LT((inv.value().Apply(a.Apply(p)) - p).norm(), 1e-9);
  EXPECT_FALSE((Affine2D{{1, 2, 0, 2, 4, 0}}.Inverse().has_value()));  // rank 1
  EXPECT_FALSE((Affine2D{{std::numeric_limits<double>::quiet_NaN(), 0, 0, 0, 1, 0}}.Inverse().has_value()));
  const std::array<float, 4> box = ProjectBox(ToMatrix(Similarity(2, 0, 10, 20)), {0, 0, 100, 50}, {150, 1000});
  EXPECT_EQ(box, (std::array<float, 4>{10, 20, 150, 120}));  // x2 = 210 clipped to 150
  Eigen::Matrix3d behind = Eigen::Matrix3d::Identity();
  behind(2, 0) = -0.1;  // the corner x = 100 maps behind the camera
  EXPECT_EQ(ProjectBox(behind, {0, 0, 100, 50}, {150, 1000}), (std::array<float, 4>{0, 0, 0, 0}));
}

// ---------------------------------------------------------------- robust estimators

TEST(FitRobust, RecoversKnownTransformsWithHalfOutliers) {
  struct Case {
    GeometricModel model;
    const Truth* truth;
  };
  const Case cases[] = {
      {GeometricModel::kSimilarity, &kTruths[0]}, {GeometricModel::kSimilarity, &kTruths[1]},
      {GeometricModel::kAffine, &kTruths[0]},     {GeometricModel::kAffine, &kTruths[2]},
      {GeometricModel::kHomography, &kTruths[1]}, {GeometricModel::kHomography, &kTruths[2]},
      {GeometricModel::kHoughAffine, &kTruths[2]},
  };
  for (const Case& c : cases) {
    for (auto estimator : {RobustFitOptions::Estimator::kMagsac, RobustFitOptions::Estimator::kRansac}) {
      const Scenario s = MakeScenario(c.truth->transform, 200, 200, 1.0, 99);
      RobustFitOptions options;
      options.estimator = estimator;
      auto fit = FitRobust(c.model, s.query, s.db, s.matches, options);
      SCOPED_TRACE(std::string(GeometricModelName(c.model)) + " on " + c.truth->name +
                   (estimator == RobustFitOptions::Estimator::kMagsac ? " (MAGSAC++)" : " (RANSAC)"));
      ASSERT_TRUE(fit.has_value()) << fit.error().ToString();
      EXPECT_TRUE(fit->success);
      EXPECT_EQ(fit->model, c.model);
      EXPECT_GE(KeptShare(fit->inliers, s.true_inliers), 0.95);
      EXPECT_LE(FalseInliers(fit->inliers, s.true_inliers), 10u);
      EXPECT_LT(MaxCornerError(fit->db_from_query, ToMatrix(c.truth->transform), 640, 480), 3.0);
    }
  }
}

TEST(FitRobust, FundamentalMatrixFromTwoViewsOfA3dScene) {
  // Two pinhole cameras (f = 500 px, principal point at the image centre) looking at a random point cloud.
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> xy(-2, 2), depth(4, 9), u(0, 640), v(0, 480);
  std::normal_distribution<double> noise(0, 0.5);
  Eigen::Matrix3d k;
  k << 500, 0, 320, 0, 500, 240, 0, 0, 1;
  const Eigen::Matrix3d rotation = Eigen::AngleAxisd(12 * kPi / 180, Eigen::Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  const Eigen::Vector3d translation(-1.0, 0.1, 0.3);
  Scenario s;
  for (int i = 0; i < 400; ++i) {
    Eigen::Vector3d x1, x2;
    if (i < 200) {
      const Eigen::Vector3d point(xy(rng), xy(rng), depth(rng));
      x1 = k * point;
      x2 = k * (rotation * point + translation);
      x1 /= x1.z();
      x2 /= x2.z();
      s.true_inliers.insert(static_cast<uint32_t>(i));
    } else {
      x1 = {u(rng), v(rng), 1};
      x2 = {u(rng), v(rng), 1};
    }
    s.query.push_back({static_cast<float>(x1.x() + noise(rng)), static_cast<float>(x1.y() + noise(rng)), 2, 0, 0, 0});
    s.db.push_back({static_cast<float>(x2.x() + noise(rng)), static_cast<float>(x2.y() + noise(rng)), 2, 0, 0, 0});
    s.matches.push_back({static_cast<uint32_t>(i), static_cast<uint32_t>(i), 0.1f});
  }
  RobustFitOptions options;
  options.reprojection_px = 2.0;
  auto fit = FitRobust(GeometricModel::kFundamental, s.query, s.db, s.matches, options);
  ASSERT_TRUE(fit.has_value());
  ASSERT_TRUE(fit->success);
  EXPECT_GE(KeptShare(fit->inliers, s.true_inliers), 0.95);
  EXPECT_LE(FalseInliers(fit->inliers, s.true_inliers), 20u);
  // x_db^T F x_query = 0: the db point lies on the epipolar line of the query point.
  double worst = 0;
  for (uint32_t i : s.true_inliers) {
    const Eigen::Vector3d xq(s.query[i].x, s.query[i].y, 1), xd(s.db[i].x, s.db[i].y, 1);
    const Eigen::Vector3d line = fit->db_from_query * xq;
    worst = std::max(worst, std::abs(xd.dot(line)) / line.head<2>().norm());
  }
  EXPECT_LT(worst, 4.0);
}

TEST(FitRobust, DegenerateAndInvalidInput) {
  const Scenario s = MakeScenario(Similarity(1, 10, 5, 5), 10, 0, 0.0, 8);
  for (GeometricModel model : {GeometricModel::kHoughAffine, GeometricModel::kSimilarity, GeometricModel::kAffine,
                               GeometricModel::kHomography, GeometricModel::kFundamental}) {
    SCOPED_TRACE(GeometricModelName(model));
    EXPECT_EQ(ParseGeometricModel(GeometricModelName(model)), model);
    for (size_t n : {size_t{0}, size_t{1}}) {
      auto fit = FitRobust(model, s.query, s.db, std::span(s.matches).first(n));
      ASSERT_TRUE(fit.has_value());
      EXPECT_FALSE(fit->success);
      EXPECT_TRUE(fit->db_from_query.allFinite());
    }
    const std::vector<Match> same(30, s.matches[0]);
    auto fit = FitRobust(model, s.query, s.db, same);
    ASSERT_TRUE(fit.has_value());
    EXPECT_FALSE(fit->success);
    EXPECT_TRUE(fit->db_from_query.allFinite());
    const std::vector<Match> out_of_range = {{0, 0, 0.1f}, {0, 99, 0.1f}};
    EXPECT_EQ(FitRobust(model, s.query, s.db, out_of_range).error().code, ErrorCode::kInvalidArgument);
  }
  EXPECT_FALSE(ParseGeometricModel("projective").has_value());
  RobustFitOptions invalid;
  invalid.reprojection_px = 0;
  EXPECT_EQ(FitRobust(GeometricModel::kHomography, s.query, s.db, s.matches, invalid).error().code,
            ErrorCode::kInvalidArgument);
}

// ---------------------------------------------------------------- real images

std::string OpenCvData(const std::string& name) { return "/usr/share/doc/opencv-doc/examples/data/" + name; }
std::string SharedData(const std::string& path) { return (oxbow::testing::SharedDataDir() / path).string(); }

const FeatureSet& Features(const std::string& path) {
  static std::map<std::string, FeatureSet> cache;
  auto it = cache.find(path);
  if (it != cache.end()) return it->second;
  SiftOptions options;
  options.max_features = 3000;
  auto extractor = SiftExtractor::Create(options);
  EXPECT_TRUE(extractor.has_value());
  auto features = extractor->ExtractFromFile(path);
  EXPECT_TRUE(features.has_value()) << path << ": " << features.error().ToString();
  return cache[path] = features.has_value() ? std::move(*features) : FeatureSet{};
}

std::vector<Match> MatchPair(const FeatureSet& a, const FeatureSet& b) {
  auto matches = MatchDescriptors(a, b);
  EXPECT_TRUE(matches.has_value());
  return matches.has_value() ? *matches : std::vector<Match>{};
}

VerificationResult Verify(const FeatureSet& a, const FeatureSet& b, const std::vector<Match>& matches) {
  return VerifyHoughAffine(a.keypoints, b.keypoints, matches,
                           {0, 0, static_cast<float>(a.image_width), static_cast<float>(a.image_height)},
                           {b.image_width, b.image_height});
}

Eigen::Matrix3d ReadTextHomography(const std::string& path) {
  std::ifstream in(path);
  Eigen::Matrix3d h;
  for (int i = 0; i < 9; ++i) in >> h(i / 3, i % 3);
  EXPECT_TRUE(in.good() || in.eof()) << path;
  return h;
}

// Fits a homography to our matches and compares it with the ground truth at the image corners (the
// HPatches "mean corner error", and the worst corner). The corners lie outside the matched area, so they
// extrapolate the fit: on graf1 -> graf3 (40 degrees of viewpoint change) homographies that fit the
// matches as well as the ground truth does (about 1.5 px) still differ by up to ~9 px at a corner.
void ExpectHomographyMatchesTruth(const std::string& a_path, const std::string& b_path, const Eigen::Matrix3d& truth,
                                  double mean_corner_error_px, double max_corner_error_px) {
  const FeatureSet& a = Features(a_path);
  const FeatureSet& b = Features(b_path);
  ASSERT_GT(a.size(), 500u);
  ASSERT_GT(b.size(), 500u);
  const std::vector<Match> matches = MatchPair(a, b);
  auto fit = FitRobust(GeometricModel::kHomography, a.keypoints, b.keypoints, matches);
  ASSERT_TRUE(fit.has_value());
  ASSERT_TRUE(fit->success);
  EXPECT_GE(fit->num_inliers, 50);
  const double w = a.image_width - 1, h = a.image_height - 1;
  const double mean_error = MeanCornerError(fit->db_from_query, truth, w, h);
  const double max_error = MaxCornerError(fit->db_from_query, truth, w, h);
  EXPECT_LT(mean_error, mean_corner_error_px) << a_path << " -> " << b_path;
  EXPECT_LT(max_error, max_corner_error_px) << a_path << " -> " << b_path;
  std::printf("%s -> %s: %d inliers of %zu matches, corner error mean %.2f px, max %.2f px\n", a_path.c_str(),
              b_path.c_str(), fit->num_inliers, matches.size(), mean_error, max_error);
  // The Hough/affine verifier accepts the pair too.
  const VerificationResult v = Verify(a, b, matches);
  EXPECT_TRUE(v.verified);
  EXPECT_GE(v.num_inliers, 20);
  std::printf("  hough-affine: %d inliers\n", v.num_inliers);
}

TEST(RealImages, Graf1ToGraf3HomographyMatchesGroundTruth) {
  cv::FileStorage fs(OpenCvData("H1to3p.xml"), cv::FileStorage::READ);
  ASSERT_TRUE(fs.isOpened());
  cv::Mat h;
  fs.getFirstTopLevelNode() >> h;
  ASSERT_EQ(h.rows, 3);
  Eigen::Matrix3d truth;
  for (int i = 0; i < 9; ++i) truth(i / 3, i % 3) = h.at<double>(i / 3, i % 3);
  ExpectHomographyMatchesTruth(OpenCvData("graf1.png"), OpenCvData("graf3.png"), truth, 6.0, 12.0);
}

TEST(RealImagesSharedData, BoatSequenceHomographiesMatchGroundTruth) {
  const std::string dir = SharedData("oxford_affine/");
  if (!std::filesystem::exists(dir + "images/boat/img1.pgm"))
    GTEST_SKIP() << "no " << dir << " (set OXBOW_SHARED_DATA; see tests/support/shared_data.h)";
  for (int n : {2, 3, 4}) {
    SCOPED_TRACE("boat 1 -> " + std::to_string(n));
    ExpectHomographyMatchesTruth(dir + "images/boat/img1.pgm", dir + "images/boat/img" + std::to_string(n) + ".pgm",
                                 ReadTextHomography(dir + "gt/boat/H1to" + std::to_string(n) + "p"), 3.0, 5.0);
  }
}

// hough-homography: the Hough verifier decides, and a homography that keeps most of its inliers
// replaces the affine map; one that disagrees with them is not taken.
TEST(FitRobust, HoughHomographyTakesOnlyAHomographyThatAgreesWithTheHoughInliers) {
  const Scenario s = MakeScenario(kTruths[2].transform, 200, 200, 1.0, 7);
  const std::vector<uint32_t> inliers(s.true_inliers.begin(), s.true_inliers.end());
  auto agreeing = HomographyAgreeingWith(s.query, s.db, s.matches, inliers, {});
  ASSERT_TRUE(agreeing.has_value()) << agreeing.error().ToString();
  ASSERT_TRUE(agreeing->has_value());
  EXPECT_GE(KeptShare((*agreeing)->inliers, s.true_inliers), 0.95);
  // "Hough inliers" that are the outliers: the homography keeps none of them.
  std::vector<uint32_t> outliers;
  for (uint32_t i = 0; i < s.matches.size(); ++i) {
    if (s.true_inliers.count(i) == 0) outliers.push_back(i);
  }
  auto disagreeing = HomographyAgreeingWith(s.query, s.db, s.matches, outliers, {});
  ASSERT_TRUE(disagreeing.has_value());
  EXPECT_FALSE(disagreeing->has_value());
}

// hough-homography: a homography with fewer inliers than the verification floor does not replace the
// affine answer, even when it keeps most of the Hough inliers, since its inliers would be the verified
// answer's. Five matches on an exact map among five random ones: the homography finds those five.
TEST(FitRobust, HoughHomographyTakesOnlyAHomographyWithMinInliersOfItsOwn) {
  const Scenario s = MakeScenario(Similarity(1.3, 25, 40, 30), 5, 5, 0.0, 11);
  ASSERT_EQ(s.true_inliers.size(), 5u);
  // "Hough inliers": four of the five and two of the random matches.
  std::vector<uint32_t> hough(s.true_inliers.begin(), std::next(s.true_inliers.begin(), 4));
  for (uint32_t i = 0; i < s.matches.size() && hough.size() < 6; ++i) {
    if (s.true_inliers.count(i) == 0) hough.push_back(i);
  }
  std::sort(hough.begin(), hough.end());
  RobustFitOptions options;
  options.hough.min_inliers = 6;
  auto six = HomographyAgreeingWith(s.query, s.db, s.matches, hough, options);
  ASSERT_TRUE(six.has_value()) << six.error().ToString();
  EXPECT_FALSE(six->has_value()) << "a homography with " << (*six)->num_inliers << " inliers replaced the answer";
  // The same homography is taken where the floor is five.
  options.hough.min_inliers = 5;
  auto five = HomographyAgreeingWith(s.query, s.db, s.matches, hough, options);
  ASSERT_TRUE(five.has_value()) << five.error().ToString();
  ASSERT_TRUE(five->has_value());
  EXPECT_EQ((*five)->num_inliers, 5);
  EXPECT_EQ(std::set<uint32_t>((*five)->inliers.begin(), (*five)->inliers.end()), s.true_inliers);
}

// Under a 40-degree viewpoint change an affine map is off by tens of pixels at graf1's corners; the
// default model of `oxbow match` (hough-homography) follows the perspective.
TEST(RealImages, HoughHomographyFollowsThePerspectiveOfGraf1ToGraf3) {
  cv::FileStorage fs(OpenCvData("H1to3p.xml"), cv::FileStorage::READ);
  ASSERT_TRUE(fs.isOpened());
  cv::Mat h;
  fs.getFirstTopLevelNode() >> h;
  Eigen::Matrix3d truth;
  for (int i = 0; i < 9; ++i) truth(i / 3, i % 3) = h.at<double>(i / 3, i % 3);
  const FeatureSet& a = Features(OpenCvData("graf1.png"));
  const FeatureSet& b = Features(OpenCvData("graf3.png"));
  const std::vector<Match> matches = MatchPair(a, b);
  const double w = a.image_width - 1, hh = a.image_height - 1;
  auto affine = FitRobust(GeometricModel::kHoughAffine, a.keypoints, b.keypoints, matches);
  auto refined = FitRobust(GeometricModel::kHoughHomography, a.keypoints, b.keypoints, matches);
  ASSERT_TRUE(affine && refined);
  ASSERT_TRUE(affine->success && refined->success);
  EXPECT_EQ(refined->model, GeometricModel::kHoughHomography);
  const double affine_error = MeanCornerError(affine->db_from_query, truth, w, hh);
  const double refined_error = MeanCornerError(refined->db_from_query, truth, w, hh);
  std::printf("graf1 -> graf3 corner error: hough-affine %.2f px (%d inliers), hough-homography %.2f px (%d inliers)\n",
              affine_error, affine->num_inliers, refined_error, refined->num_inliers);
  EXPECT_GT(affine_error, 10.0);
  EXPECT_LT(refined_error, 6.0);  // this file's features and matches; `oxbow match`'s defaults: 0.93 px
  EXPECT_GT(refined->num_inliers, affine->num_inliers);
}

TEST(RealImages, UnrelatedPairsAreRejected) {
  std::vector<std::pair<std::string, std::string>> pairs = {
      {OpenCvData("graf1.png"), OpenCvData("box_in_scene.png")},
      {OpenCvData("leuvenA.jpg"), OpenCvData("graf1.png")},
      {OpenCvData("box.png"), OpenCvData("leuvenB.jpg")},
      {OpenCvData("graf3.png"), OpenCvData("leuvenA.jpg")},
  };
  const std::string boat = SharedData("oxford_affine/images/boat/img1.pgm");
  if (std::filesystem::exists(boat)) pairs.emplace_back(boat, OpenCvData("graf1.png"));
  for (const auto& [a_path, b_path] : pairs) {
    const FeatureSet& a = Features(a_path);
    const FeatureSet& b = Features(b_path);
    ASSERT_GT(a.size(), 100u);
    ASSERT_GT(b.size(), 100u);
    const std::vector<Match> matches = MatchPair(a, b);
    const VerificationResult v = Verify(a, b, matches);
    EXPECT_FALSE(v.verified) << a_path << " vs " << b_path << ": " << v.num_inliers << " inliers of " << matches.size();
    std::printf("unrelated %s vs %s: %zu matches, %d inliers\n", a_path.c_str(), b_path.c_str(), matches.size(), v.num_inliers);
    EXPECT_LT(v.num_inliers, 6);
    EXPECT_TRUE(AllFinite(v));
  }
}

TEST(RealImages, BoxIsFoundInTheScene) {
  const FeatureSet& box = Features(OpenCvData("box.png"));
  const FeatureSet& scene = Features(OpenCvData("box_in_scene.png"));
  const std::vector<Match> matches = MatchPair(box, scene);
  const VerificationResult v = Verify(box, scene, matches);
  ASSERT_TRUE(v.verified);
  EXPECT_GE(v.num_inliers, 15);
  // In the 512x384 scene the box's front face spans about x in [95, 285], y in [150, 295] (read off the
  // --draw picture of this pair); the region must land there, within a margin of ~25 px.
  EXPECT_NEAR(v.db_region[0], 95, 25);
  EXPECT_NEAR(v.db_region[1], 150, 25);
  EXPECT_NEAR(v.db_region[2], 285, 25);
  EXPECT_NEAR(v.db_region[3], 295, 25);
  EXPECT_LE(v.db_region[2], scene.image_width);
  EXPECT_LE(v.db_region[3], scene.image_height);
}

}  // namespace
}  // namespace oxbow::sift
