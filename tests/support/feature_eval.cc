#include "tests/support/feature_eval.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>

namespace oxbow::sift {
namespace {

bool Project(const Homography& h, double x, double y, double* px, double* py) {
  const double w = h[6] * x + h[7] * y + h[8];
  if (std::fabs(w) < 1e-12) return false;
  *px = (h[0] * x + h[1] * y + h[2]) / w;
  *py = (h[3] * x + h[4] * y + h[5]) / w;
  return true;
}

bool Inside(double x, double y, int w, int h) { return x >= 0 && y >= 0 && x <= w - 1 && y <= h - 1; }

Homography Invert(const Homography& m) {
  cv::Matx33d a(m.data());
  const cv::Matx33d inv = a.inv();
  Homography out;
  for (int i = 0; i < 9; ++i) out[static_cast<size_t>(i)] = inv.val[i];
  return out;
}

}  // namespace

CornerError CornerErrorOf(const Homography& estimate, const Homography& truth, int width, int height) {
  CornerError out;
  double sum = 0;
  for (int c = 0; c < 4; ++c) {
    const double x = (c & 1) ? width - 1 : 0, y = (c & 2) ? height - 1 : 0;
    double ex = 0, ey = 0, tx = 0, ty = 0;
    const double d = Project(estimate, x, y, &ex, &ey) && Project(truth, x, y, &tx, &ty)
                         ? std::hypot(ex - tx, ey - ty)
                         : std::numeric_limits<double>::infinity();
    sum += d;
    out.max_px = std::max(out.max_px, d);
  }
  out.mean_px = sum / 4;
  return out;
}

Result<Homography> ReadHomography(const std::string& path) {
  std::ifstream in(path);
  if (!in) return Fail(ErrorCode::kNotFound, "cannot open homography file '" + path + "'");
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  Homography h{};
  if (text.find("<?xml") != std::string::npos || text.find("%YAML") != std::string::npos) {
    try {
      cv::FileStorage fs(path, cv::FileStorage::READ);
      cv::Mat m;
      for (const auto& node : fs.root()) {
        node >> m;
        if (!m.empty()) break;
      }
      if (m.rows != 3 || m.cols != 3) return Fail(ErrorCode::kCorruptData, "'" + path + "' holds no 3x3 matrix");
      m.convertTo(m, CV_64F);
      for (int i = 0; i < 9; ++i) h[static_cast<size_t>(i)] = m.at<double>(i / 3, i % 3);
      return h;
    } catch (const cv::Exception& e) {
      return Fail(ErrorCode::kCorruptData, "cannot parse '" + path + "': " + e.what());
    }
  }
  std::ifstream numbers(path);
  for (double& v : h)
    if (!(numbers >> v)) return Fail(ErrorCode::kCorruptData, "'" + path + "' does not hold 9 numbers");
  return h;
}

HomographyScore ScoreUnderHomography(const FeatureSet& a, const FeatureSet& b, const Homography& b_from_a, double tolerance_px,
                                     double ratio, double scale_ratio) {
  const Homography a_from_b = Invert(b_from_a);
  std::vector<int> common_a, common_b;
  std::vector<cv::Point2d> projected_a;
  for (size_t i = 0; i < a.size(); ++i) {
    double x, y;
    if (Project(b_from_a, a.keypoints[i].x, a.keypoints[i].y, &x, &y) && Inside(x, y, b.image_width, b.image_height)) {
      common_a.push_back(static_cast<int>(i));
      projected_a.emplace_back(x, y);
    }
  }
  for (size_t i = 0; i < b.size(); ++i) {
    double x, y;
    if (Project(a_from_b, b.keypoints[i].x, b.keypoints[i].y, &x, &y) && Inside(x, y, a.image_width, a.image_height))
      common_b.push_back(static_cast<int>(i));
  }
  HomographyScore score;
  score.keypoints_1 = static_cast<int>(common_a.size());
  score.keypoints_2 = static_cast<int>(common_b.size());
  const int denominator = std::min(score.keypoints_1, score.keypoints_2);
  if (denominator == 0) return score;

  // Repeatability: pairs (i in 1, j in 2) whose positions agree within tolerance and whose scales agree
  // within `scale_ratio` (after the local scale change of the homography), matched one-to-one greedily
  // by distance.
  const double tol2 = tolerance_px * tolerance_px;
  const double cell = std::max(tolerance_px, 1.0);
  const int gw = static_cast<int>(b.image_width / cell) + 1, gh = static_cast<int>(b.image_height / cell) + 1;
  std::vector<std::vector<int>> grid(static_cast<size_t>(gw) * static_cast<size_t>(gh));
  auto cell_of = [&](double v, int n) { return std::clamp(static_cast<int>(v / cell), 0, n - 1); };
  auto grid_cell = [&](int y, int x) -> std::vector<int>& {
    return grid[(static_cast<size_t>(y) * static_cast<size_t>(gw)) + static_cast<size_t>(x)];
  };
  for (int j : common_b) {
    const Keypoint& k = b.keypoints[static_cast<size_t>(j)];
    grid_cell(cell_of(k.y, gh), cell_of(k.x, gw)).push_back(j);
  }
  struct Pair {
    double d2;
    int i, j;
  };
  std::vector<Pair> pairs;
  const double log_ratio = std::log(scale_ratio);
  for (size_t n = 0; n < common_a.size(); ++n) {
    const Keypoint& ka = a.keypoints[static_cast<size_t>(common_a[n])];
    const cv::Point2d& p = projected_a[n];
    // Local scale change of the homography: sqrt of the Jacobian determinant, by finite differences.
    double x1 = p.x, y1 = p.y, x2 = p.x, y2 = p.y;
    Project(b_from_a, ka.x + 1.0, ka.y, &x1, &y1);
    Project(b_from_a, ka.x, ka.y + 1.0, &x2, &y2);
    const double local = std::sqrt(std::fabs((x1 - p.x) * (y2 - p.y) - (x2 - p.x) * (y1 - p.y)));
    const int cx = cell_of(p.x, gw), cy = cell_of(p.y, gh);
    for (int y = std::max(0, cy - 1); y <= std::min(gh - 1, cy + 1); ++y)
      for (int x = std::max(0, cx - 1); x <= std::min(gw - 1, cx + 1); ++x)
        for (int j : grid_cell(y, x)) {
          const Keypoint& k = b.keypoints[static_cast<size_t>(j)];
          const double dx = k.x - p.x, dy = k.y - p.y, d2 = dx * dx + dy * dy;
          if (d2 >= tol2 || std::fabs(std::log(k.scale / (ka.scale * local))) > log_ratio) continue;
          pairs.push_back({d2, static_cast<int>(n), j});
        }
  }
  std::sort(pairs.begin(), pairs.end(), [](const Pair& x, const Pair& y) {
    return x.d2 != y.d2 ? x.d2 < y.d2 : (x.i != y.i ? x.i < y.i : x.j < y.j);
  });
  std::vector<bool> used_a(common_a.size(), false), used_b(b.size(), false);
  for (const Pair& pair : pairs) {
    if (used_a[static_cast<size_t>(pair.i)] || used_b[static_cast<size_t>(pair.j)]) continue;
    used_a[static_cast<size_t>(pair.i)] = used_b[static_cast<size_t>(pair.j)] = true;
    ++score.repeated;
  }

  // Matching score: nearest neighbour in descriptor space with Lowe's ratio test.
  cv::Mat da(static_cast<int>(common_a.size()), kDescriptorDim, CV_32F), db(static_cast<int>(common_b.size()), kDescriptorDim, CV_32F);
  for (size_t i = 0; i < common_a.size(); ++i) std::copy_n(a.Descriptor(static_cast<size_t>(common_a[i])).data(), kDescriptorDim, da.ptr<float>(static_cast<int>(i)));
  for (size_t i = 0; i < common_b.size(); ++i) std::copy_n(b.Descriptor(static_cast<size_t>(common_b[i])).data(), kDescriptorDim, db.ptr<float>(static_cast<int>(i)));
  if (common_b.size() >= 2) {
    cv::BFMatcher matcher(cv::NORM_L2);
    std::vector<std::vector<cv::DMatch>> knn;
    matcher.knnMatch(da, db, knn, 2);
    for (const auto& m : knn) {
      if (m.size() < 2 || !(m[0].distance < ratio * m[1].distance)) continue;
      const Keypoint& k = b.keypoints[static_cast<size_t>(common_b[static_cast<size_t>(m[0].trainIdx)])];
      const cv::Point2d& p = projected_a[static_cast<size_t>(m[0].queryIdx)];
      const double dx = k.x - p.x, dy = k.y - p.y;
      if (dx * dx + dy * dy < tol2) ++score.correct_matches;
    }
  }
  score.repeatability = std::min(1.0, static_cast<double>(score.repeated) / denominator);
  score.matching_score = static_cast<double>(score.correct_matches) / denominator;
  return score;
}

}  // namespace oxbow::sift
