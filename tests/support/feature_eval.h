// Evaluation of local features under a known homography (Mikolajczyk et al. 2005, "A Comparison of
// Affine Region Detectors", IJCV 65): repeatability and matching score. Used by the SIFT tests and
// the benchmark to compare oxbow's extractor with cv::SIFT and VLFeat on the same images.
#pragma once

#include <array>
#include <string>

#include "sift/base/error.h"
#include "sift/types.h"

namespace oxbow::sift {

// 3x3 row-major homography mapping pixel coordinates of image 1 to image 2.
using Homography = std::array<double, 9>;

// Reads a homography from an Oxford affine text file (9 numbers, e.g. H1to2p) or an OpenCV FileStorage
// XML/YAML file with a 3x3 matrix (e.g. opencv-doc's H1to3p.xml; the first matrix node is used).
[[nodiscard]] Result<Homography> ReadHomography(const std::string& path);

struct HomographyScore {
  int keypoints_1 = 0;      // keypoints of image 1 whose projection lands inside image 2
  int keypoints_2 = 0;      // keypoints of image 2 whose back-projection lands inside image 1
  int repeated = 0;         // one-to-one corresponding pairs (see ScoreUnderHomography)
  int correct_matches = 0;  // ratio-test nearest-neighbour matches (1 -> 2) that land within tolerance
  double repeatability = 0;   // repeated / min(keypoints_1, keypoints_2)
  double matching_score = 0;  // correct_matches / min(keypoints_1, keypoints_2)
};

// Scores features of two images related by `image2_from_image1`. Only keypoints whose projection lands
// inside the other image count. Repeatability: keypoint pairs whose projected position is within
// `tolerance_px` pixels (in image 2) and whose scales agree within a factor `scale_ratio` (after the
// homography's local scale change), matched one-to-one (greedy, closest first) — a stand-in for the
// paper's 40% region-overlap criterion that, unlike position alone, is not fooled by dense small
// keypoints. Matching score: nearest neighbours in descriptor space (L2) from image 1 to image 2 that
// pass Lowe's ratio test (`ratio`) and land within `tolerance_px` of the projection.
// Cost: O(n1 * n2 * 128) for the matching.
HomographyScore ScoreUnderHomography(const FeatureSet& image1, const FeatureSet& image2, const Homography& image2_from_image1,
                                     double tolerance_px = 3.0, double ratio = 0.8, double scale_ratio = 1.5);

// How far an estimated homography is from the true one (the HPatches "corner error"): the distances, in
// image 2's pixels, between where the two send each corner of image 1 (pixel centres (0, 0) to
// (width - 1, height - 1)). A corner either sends to infinity counts as infinitely far.
struct CornerError {
  double mean_px = 0;
  double max_px = 0;
};
CornerError CornerErrorOf(const Homography& estimate, const Homography& truth, int width, int height);

}  // namespace oxbow::sift
