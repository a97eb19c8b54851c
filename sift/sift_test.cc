#include "sift/sift.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <numbers>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/feature_eval.h"
#include "sift/scale_space.h"
#include "sift/sift_internal.h"

namespace oxbow::sift {
namespace {

const std::string kOpencvData = "/usr/share/doc/opencv-doc/examples/data/";
const std::string kSharedData = OXBOW_SOURCE_DIR "/../shared/data/";
constexpr double kPi = std::numbers::pi;

GrayImage FromMat(const cv::Mat& m8) { return GrayFromBytes(m8.ptr<uint8_t>(0), m8.cols, m8.rows, m8.step[0]); }

cv::Mat LoadGray(const std::string& path) { return cv::imread(path, cv::IMREAD_GRAYSCALE); }

SiftExtractor MakeExtractor(SiftOptions options = {}) {
  auto e = SiftExtractor::Create(options);
  EXPECT_TRUE(e) << e.error().ToString();
  return *e;
}

// cv::SIFT keypoints and descriptors as a FeatureSet in our conventions (pixel-centre coordinates: OpenCV
// maps the upsampled octave with x/2, we with x/2 - 0.25; scale = size / 2; y-down radians).
FeatureSet OpencvSift(const cv::Mat& gray) {
  auto sift = cv::SIFT::create(0, 3, 0.04, 10, 1.6);
  std::vector<cv::KeyPoint> kps;
  cv::Mat desc;
  sift->detectAndCompute(gray, cv::noArray(), kps, desc);
  FeatureSet f;
  f.image_width = gray.cols;
  f.image_height = gray.rows;
  for (size_t i = 0; i < kps.size(); ++i) {
    Keypoint k;
    k.x = kps[i].pt.x - 0.25f;
    k.y = kps[i].pt.y - 0.25f;
    k.scale = kps[i].size / 2;
    k.orientation = static_cast<float>(kps[i].angle * kPi / 180.0);
    k.response = kps[i].response;
    f.keypoints.push_back(k);
    cv::Mat row;
    cv::normalize(desc.row(static_cast<int>(i)), row);
    f.descriptors.insert(f.descriptors.end(), row.ptr<float>(0), row.ptr<float>(0) + kDescriptorDim);
  }
  return f;
}

double AngleDifference(double a, double b) {
  double d = std::fmod(std::fabs(a - b), 2 * kPi);
  return std::min(d, 2 * kPi - d);
}

// Share of `reference` keypoints that have a counterpart in `ours` within the tolerances.
double ShareWithCounterpart(const FeatureSet& reference, const FeatureSet& ours, double position_px, double scale_ratio,
                            double angle_rad, double* descriptor_share = nullptr) {
  int found = 0, descriptor_close = 0;
  for (size_t i = 0; i < reference.size(); ++i) {
    const Keypoint& r = reference.keypoints[i];
    int best = -1;
    for (size_t j = 0; j < ours.size(); ++j) {
      const Keypoint& o = ours.keypoints[j];
      if (std::fabs(o.x - r.x) > position_px || std::fabs(o.y - r.y) > position_px) continue;
      if (std::fabs(std::log(o.scale / r.scale)) > std::log(scale_ratio)) continue;
      if (AngleDifference(o.orientation, r.orientation) > angle_rad) continue;
      best = static_cast<int>(j);
      break;
    }
    if (best < 0) continue;
    ++found;
    double dist2 = 0;
    for (int k = 0; k < kDescriptorDim; ++k) {
      const double d = reference.Descriptor(i)[static_cast<size_t>(k)] - ours.Descriptor(static_cast<size_t>(best))[static_cast<size_t>(k)];
      dist2 += d * d;
    }
    if (std::sqrt(dist2) < 0.2) ++descriptor_close;
  }
  if (descriptor_share) *descriptor_share = found ? static_cast<double>(descriptor_close) / found : 0;
  return reference.size() ? static_cast<double>(found) / static_cast<double>(reference.size()) : 0;
}

TEST(SiftReference, MostOpencvKeypointsHaveACounterpart) {
  for (const std::string name : {"graf1.png", "box.png"}) {
    const cv::Mat gray = LoadGray(kOpencvData + name);
    ASSERT_FALSE(gray.empty()) << name;
    const FeatureSet reference = OpencvSift(gray);
    const FeatureSet ours = MakeExtractor().Extract(FromMat(gray));
    double descriptor_share = 0;
    const double share = ShareWithCounterpart(reference, ours, 0.5, 1.05, 3.0 * kPi / 180, &descriptor_share);
    std::printf("%s: cv::SIFT %zu keypoints, ours %zu; %.1f%% of cv's have a counterpart, %.1f%% of those with "
                "descriptor distance < 0.2\n",
                name.c_str(), reference.size(), ours.size(), 100 * share, 100 * descriptor_share);
    EXPECT_GT(share, 0.9) << name;
    EXPECT_GT(descriptor_share, 0.9) << name;
    EXPECT_NEAR(static_cast<double>(ours.size()), static_cast<double>(reference.size()), 0.05 * reference.size()) << name;
  }
}

}  // namespace
}  // namespace oxbow::sift
