// The peer of `oxbow extract --threads 1 --format colmap` as a whole process: OpenCV's own SIFT
// (cv::SIFT::create() with its defaults) on one image, on one thread, written in the same COLMAP text
// format (`N 128`, then `x y scale orientation d1..d128` per keypoint, descriptors 0..255). What a user of
// OpenCV would run instead of oxbow; eval/bench/extract_process.sh times the two against each other.
//
//   cv_sift_extract IMAGE OUT.txt
#include <cmath>
#include <cstdio>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: cv_sift_extract IMAGE OUT.txt\n");
    return 2;
  }
  cv::setNumThreads(1);
  const cv::Mat image = cv::imread(argv[1], cv::IMREAD_GRAYSCALE);
  if (image.empty()) {
    std::fprintf(stderr, "cv_sift_extract: cannot read %s\n", argv[1]);
    return 3;
  }
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;
  cv::SIFT::create()->detectAndCompute(image, cv::noArray(), keypoints, descriptors);
  std::FILE* out = std::fopen(argv[2], "w");
  if (out == nullptr) {
    std::fprintf(stderr, "cv_sift_extract: cannot write %s\n", argv[2]);
    return 7;
  }
  std::fprintf(out, "%zu 128\n", keypoints.size());
  for (size_t i = 0; i < keypoints.size(); ++i) {
    const cv::KeyPoint& k = keypoints[i];
    // COLMAP's convention: pixel centres at +0.5, scale as the sigma, orientation in radians.
    std::fprintf(out, "%.4f %.4f %.4f %.6f", k.pt.x + 0.5, k.pt.y + 0.5, k.size / 2.0, k.angle * CV_PI / 180.0);
    const float* d = descriptors.ptr<float>(static_cast<int>(i));
    for (int j = 0; j < 128; ++j) std::fprintf(out, " %d", static_cast<int>(std::lround(d[j])));
    std::fputc('\n', out);
  }
  return std::fclose(out) == 0 ? 0 : 7;
}
