// Homography accuracy of `oxbow match` / POST /v1/match against OpenCV, on homography pairs with ground
// truth: the mean and the largest distance between where the estimated transform and the true
// homography send the four corners of image a (the HPatches "corner error"), per pair, beside each other.
//
//   pair_match_accuracy_benchmark [--threads 1]
//
// Pairs: graf1 -> graf3 (opencv-doc, H1to3p.xml) and boat 1 -> 3, 4, 5 (../shared/data/oxford_affine,
// skipped with a note when absent). Contenders, each from the same decoded grey image:
//   - oxbow with the defaults of `oxbow match` (api::MatchPair with PairMatchOptions{}, the extractor
//     with api::PairMatchExtractorOptions(SiftOptions{})), and the same with the homography and
//     hough-affine models;
//   - OpenCV 4.6: cv::SIFT (its defaults), RootSIFT (L1 normalisation, square root), brute-force
//     knnMatch k = 2 with Lowe's ratio 0.8, cv::findHomography(USAC_MAGSAC, 3 px).
// The bound it checks: oxbow's defaults no worse than OpenCV + 0.5 px in mean corner error on each pair.
// Accuracy only: timings are the match benchmarks' job (eval/bench/match_benchmark.cc).
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>

#include "api/pair_match.h"
#include "sift/sift.h"
#include "sift/verify.h"
#include "tests/support/feature_eval.h"

namespace {

using namespace oxbow;

struct Pair {
  std::string name, a, b, truth;
};

struct Outcome {
  bool ok = false;  // a transform was estimated
  int inliers = 0;
  int matches = 0;
  double mean_px = NAN, max_px = NAN;
};

// The corner errors of `estimate` against `truth` over the corners of a width x height image a.
void SetCornerErrors(const Eigen::Matrix3d& estimate, const sift::Homography& truth, int width, int height, Outcome* out) {
  sift::Homography e;
  for (int i = 0; i < 9; ++i) e[static_cast<size_t>(i)] = estimate(i / 3, i % 3);
  const sift::CornerError error = sift::CornerErrorOf(e, truth, width, height);
  out->mean_px = error.mean_px;
  out->max_px = error.max_px;
}

Outcome Oxbow(const sift::FeatureSet& a, const sift::FeatureSet& b, sift::GeometricModel model,
              const sift::Homography& truth, int threads) {
  api::PairMatchOptions options;
  options.model = model;
  options.match.num_threads = threads;
  Outcome out;
  const auto result = api::MatchPair(a, b, options);
  if (!result) {
    std::fprintf(stderr, "oxbow: %s\n", result.error().ToString().c_str());
    return out;
  }
  out.matches = static_cast<int>(result->matches.size());
  out.inliers = static_cast<int>(result->inliers.size());
  const std::optional<Eigen::Matrix3d> transform = result->transform;
  if (!transform.has_value()) return out;
  out.ok = true;
  SetCornerErrors(*transform, truth, a.image_width, a.image_height, &out);
  return out;
}

Outcome OpenCv(const cv::Mat& a, const cv::Mat& b, const sift::Homography& truth) {
  auto sift = cv::SIFT::create();
  std::vector<cv::KeyPoint> ka, kb;
  cv::Mat da, db;
  sift->detectAndCompute(a, cv::noArray(), ka, da);
  sift->detectAndCompute(b, cv::noArray(), kb, db);
  for (cv::Mat* d : {&da, &db}) {  // RootSIFT
    for (int r = 0; r < d->rows; ++r) {
      cv::Mat row = d->row(r);
      const double l1 = cv::norm(row, cv::NORM_L1);
      if (l1 > 0) row /= l1;
      cv::sqrt(row, row);
    }
  }
  std::vector<std::vector<cv::DMatch>> knn;
  cv::BFMatcher(cv::NORM_L2).knnMatch(da, db, knn, 2);
  std::vector<cv::Point2f> pa, pb;
  for (const auto& m : knn) {
    if (m.size() == 2 && m[0].distance < 0.8f * m[1].distance) {
      pa.push_back(ka[m[0].queryIdx].pt);
      pb.push_back(kb[m[0].trainIdx].pt);
    }
  }
  Outcome out;
  out.matches = static_cast<int>(pa.size());
  if (pa.size() < 4) return out;
  cv::Mat mask;
  const cv::Mat h = cv::findHomography(pa, pb, cv::USAC_MAGSAC, 3.0, mask);
  if (h.empty()) return out;
  out.ok = true;
  out.inliers = cv::countNonZero(mask);
  Eigen::Matrix3d e;
  for (int i = 0; i < 9; ++i) e(i / 3, i % 3) = h.at<double>(i / 3, i % 3);
  SetCornerErrors(e, truth, a.cols, a.rows, &out);
  return out;
}

std::string Cell(const Outcome& o) {
  if (!o.ok) return "no transform (" + std::to_string(o.inliers) + " / " + std::to_string(o.matches) + ")";
  char buf[96];
  std::snprintf(buf, sizeof buf, "%.2f / %.2f (%d / %d)", o.mean_px, o.max_px, o.inliers, o.matches);
  return buf;
}

}  // namespace

int main(int argc, char** argv) {
  int threads = 1;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::string(argv[i]) == "--threads") threads = std::stoi(argv[i + 1]);
  }
  cv::setNumThreads(threads);
  const std::string samples = "/usr/share/doc/opencv-doc/examples/data/";
  const std::string shared = OXBOW_SOURCE_DIR "/../shared/data/oxford_affine/";
  std::vector<Pair> pairs;
  if (std::filesystem::exists(samples + "graf1.png")) {
    pairs.push_back({"graf 1 -> 3", samples + "graf1.png", samples + "graf3.png", samples + "H1to3p.xml"});
  } else {
    std::printf("no opencv-doc samples in %s: graf skipped\n", samples.c_str());
  }
  if (std::filesystem::exists(shared + "images/boat/img1.pgm")) {
    for (int n : {3, 4, 5}) {
      pairs.push_back({"boat 1 -> " + std::to_string(n), shared + "images/boat/img1.pgm",
                       shared + "images/boat/img" + std::to_string(n) + ".pgm",
                       shared + "gt/boat/H1to" + std::to_string(n) + "p"});
    }
  } else {
    std::printf("no %s: the boat pairs skipped\n", shared.c_str());
  }
  sift::SiftOptions sift_options = api::PairMatchExtractorOptions(sift::SiftOptions{});  // `oxbow match`'s extractor
  sift_options.num_threads = threads;
  const auto extractor = sift::SiftExtractor::Create(sift_options);
  if (!extractor) {
    std::fprintf(stderr, "%s\n", extractor.error().ToString().c_str());
    return 1;
  }
  const sift::GeometricModel defaults = api::PairMatchOptions{}.model;
  std::printf("corner error of image a's corners, mean / max px (inliers / tentative matches); oxbow's default model: %s\n\n",
              sift::GeometricModelName(defaults));
  std::printf("| pair | oxbow defaults | oxbow homography | oxbow hough-affine | OpenCV RootSIFT + MAGSAC 3 px | defaults - OpenCV (target <= 0.5) |\n");
  std::printf("|---|---|---|---|---|---|\n");
  int missed = 0;
  for (const Pair& p : pairs) {
    const auto truth = sift::ReadHomography(p.truth);
    if (!truth) {
      std::fprintf(stderr, "%s: %s\n", p.truth.c_str(), truth.error().ToString().c_str());
      return 1;
    }
    const cv::Mat a = cv::imread(p.a, cv::IMREAD_GRAYSCALE), b = cv::imread(p.b, cv::IMREAD_GRAYSCALE);
    const auto fa = extractor->ExtractFromFile(p.a, sift::DecodeOptions{});
    const auto fb = extractor->ExtractFromFile(p.b, sift::DecodeOptions{});
    if (a.empty() || b.empty() || !fa || !fb) {
      std::fprintf(stderr, "%s: cannot read or extract the images\n", p.name.c_str());
      return 1;
    }
    const Outcome def = Oxbow(*fa, *fb, defaults, *truth, threads);
    const Outcome hom = Oxbow(*fa, *fb, sift::GeometricModel::kHomography, *truth, threads);
    const Outcome hough_affine = Oxbow(*fa, *fb, sift::GeometricModel::kHoughAffine, *truth, threads);
    const Outcome cv_out = OpenCv(a, b, *truth);
    std::string diff = "-";
    if (def.ok && cv_out.ok) {
      char buf[48];
      const double d = def.mean_px - cv_out.mean_px;
      std::snprintf(buf, sizeof buf, "%+.2f %s", d, d <= 0.5 ? "met" : "MISSED");
      diff = buf;
      if (d > 0.5) ++missed;
    } else if (!def.ok) {
      diff = "MISSED";
      ++missed;
    }
    std::printf("| %s | %s | %s | %s | %s | %s |\n", p.name.c_str(), Cell(def).c_str(), Cell(hom).c_str(),
                Cell(hough_affine).c_str(), Cell(cv_out).c_str(), diff.c_str());
  }
  std::printf("\n%d of %zu pairs miss the target\n", missed, pairs.size());
  return 0;
}
