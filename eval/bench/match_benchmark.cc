// Matching and verification timings against OpenCV peers, on the same descriptors and the same
// tentative matches, measured in the same run with the contenders interleaved; prints Markdown tables
// of medians and ratios. Everything runs on one thread (cv::setNumThreads(1), num_threads = 1) unless
// --threads says otherwise for the matchers. Times are process CPU time (CLOCK_PROCESS_CPUTIME_ID):
// on one thread that is the work done, and unlike wall time it does not grow when other processes
// compete for the cores (with --threads > 1 it sums over threads; then read it as total work).
//
//   match_benchmark [--reps 15] [--threads 1] [--features 2000] [A B]
//
// A, B default to boat img1/img2 from ../shared/data/oxford_affine when present, else graf1/graf3 from
// opencv-doc. Matching: oxbow's exact matcher (AVX2 dot products) and oxbow's `kdtree` method, which runs
// the FLANN copy inside OpenCV (cvflann::Index, 4 randomised kd-trees, 64 checks; oxbow only drives it),
// vs cv::BFMatcher(NORM_L2) and cv::FlannBasedMatcher (the same cvflann kd-trees behind OpenCV's
// matcher API), all knnMatch k=2 + ratio 0.8. Verification: the
// N = 100, 1000, 5000 tentative matches with the smallest descriptor distance (nearest neighbours
// without ratio test, one-to-one, extracted without a feature cap so that 5000 exist) and N random ones
// of them (the natural inlier share of the pair), Hough/affine vs
// cv::findHomography with USAC_MAGSAC and with RANSAC (4 px, confidence 0.999, at most 10000 iterations).
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <functional>
#include <map>
#include <random>
#include <set>
#include <string>
#include <vector>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/flann.hpp>

#include "sift/match.h"
#include "sift/sift.h"
#include "sift/verify.h"

namespace {

using namespace oxbow::sift;
double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

double CpuMs() {
  timespec t;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return double(t.tv_sec) * 1e3 + double(t.tv_nsec) * 1e-6;
}

// CPU milliseconds per call of fn: repeats fn until at least `min_ms` of CPU time passed, divides.
double TimeOnce(const std::function<void()>& fn, double min_ms) {
  int calls = 0;
  const double start = CpuMs();
  double elapsed = 0;
  do {
    fn();
    ++calls;
    elapsed = CpuMs() - start;
  } while (elapsed < min_ms);
  return elapsed / calls;
}

struct Contender {
  std::string name;
  std::function<void()> run;
  std::vector<double> samples_ms;
};

// Runs every contender once per repetition, in rotating order, and returns the medians.
void RunInterleaved(std::vector<Contender>& contenders, int reps, double min_ms) {
  for (auto& c : contenders) c.run();  // warm-up (caches, thread pools, lazy init)
  for (int r = 0; r < reps; ++r) {
    for (size_t k = 0; k < contenders.size(); ++k) {
      Contender& c = contenders[(k + static_cast<size_t>(r)) % contenders.size()];
      c.samples_ms.push_back(TimeOnce(c.run, min_ms));
    }
  }
}

cv::Mat DescriptorMat(const FeatureSet& f) {
  return cv::Mat(static_cast<int>(f.size()), kDescriptorDim, CV_32F, const_cast<float*>(f.descriptors.data()));
}

std::vector<Match> RatioFilter(const std::vector<std::vector<cv::DMatch>>& knn, float ratio) {
  std::vector<Match> out;
  for (const auto& pair : knn) {
    if (pair.size() == 2 && pair[0].distance < ratio * pair[1].distance) {
      out.push_back({static_cast<uint32_t>(pair[0].queryIdx), static_cast<uint32_t>(pair[0].trainIdx), pair[0].distance});
    }
  }
  return EnforceOneToOne(out);
}

size_t Overlap(const std::vector<Match>& a, const std::vector<Match>& b) {
  std::set<std::pair<uint32_t, uint32_t>> s;
  for (const Match& m : a) s.insert({m.query_index, m.db_index});
  size_t n = 0;
  for (const Match& m : b) n += s.count({m.query_index, m.db_index});
  return n;
}

FeatureSet Extract(const std::string& path, std::optional<int> max_features) {
  SiftOptions options;
  options.max_features = max_features;
  auto extractor = SiftExtractor::Create(options);
  auto features = extractor->ExtractFromFile(path);
  if (!features) {
    std::fprintf(stderr, "cannot extract %s: %s\n", path.c_str(), features.error().ToString().c_str());
    std::exit(1);
  }
  return *features;
}

}  // namespace

int main(int argc, char** argv) {
  int reps = 15;
  int threads = 1;
  int max_features = 2000;
  std::vector<std::string> paths;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--reps") && i + 1 < argc) {
      reps = std::atoi(argv[++i]);
    } else if (!std::strcmp(argv[i], "--threads") && i + 1 < argc) {
      threads = std::atoi(argv[++i]);
    } else if (!std::strcmp(argv[i], "--features") && i + 1 < argc) {
      max_features = std::atoi(argv[++i]);
    } else {
      paths.emplace_back(argv[i]);
    }
  }
  if (paths.size() != 2) {
    const std::string boat = std::string(OXBOW_SOURCE_DIR) + "/../shared/data/oxford_affine/images/boat/";
    if (std::filesystem::exists(boat + "img1.pgm")) {
      paths = {boat + "img1.pgm", boat + "img2.pgm"};
    } else {
      paths = {"/usr/share/doc/opencv-doc/examples/data/graf1.png", "/usr/share/doc/opencv-doc/examples/data/graf3.png"};
    }
  }
  cv::setNumThreads(threads);
  std::printf("images: %s, %s; %d repetitions interleaved, median CPU ms; matcher threads: %d; verification: 1 thread\n\n",
              paths[0].c_str(), paths[1].c_str(), reps, threads);

  // ---------------------------------------------------------------- matching
  const FeatureSet a = Extract(paths[0], max_features);
  const FeatureSet b = Extract(paths[1], max_features);
  const cv::Mat da = DescriptorMat(a), db = DescriptorMat(b);
  std::map<std::string, std::vector<Match>> found;

  MatchOptions exact;
  exact.num_threads = threads;
  MatchOptions kd = exact;
  kd.method = MatchOptions::Method::kKdForest;
  std::vector<Contender> matchers = {
      {"oxbow exact (AVX2 dot products)", [&] { found["exact"] = *MatchDescriptors(a, b, exact); }, {}},
      {"oxbow kdtree = OpenCV cvflann (4 trees, 64 checks)", [&] { found["kd"] = *MatchDescriptors(a, b, kd); }, {}},
      {"cv::BFMatcher L2 knn2", [&] {
         std::vector<std::vector<cv::DMatch>> knn;
         cv::BFMatcher(cv::NORM_L2).knnMatch(da, db, knn, 2);
         found["bf"] = RatioFilter(knn, 0.8f);
       }, {}},
      {"cv::FlannBasedMatcher (4 trees, 64 checks) knn2", [&] {
         std::vector<std::vector<cv::DMatch>> knn;
         cv::FlannBasedMatcher matcher(cv::makePtr<cv::flann::KDTreeIndexParams>(4), cv::makePtr<cv::flann::SearchParams>(64));
         matcher.knnMatch(da, db, knn, 2);
         found["flann"] = RatioFilter(knn, 0.8f);
       }, {}},
  };
  RunInterleaved(matchers, reps, 20.0);
  const char* keys[] = {"exact", "kd", "bf", "flann"};
  std::printf("### Matching %zu x %zu descriptors (ratio 0.8, one-to-one)\n\n", a.size(), b.size());
  std::printf("| matcher | median CPU ms | vs oxbow exact | matches | shared with oxbow exact |\n|---|---:|---:|---:|---:|\n");
  const double exact_ms = Median(matchers[0].samples_ms);
  for (size_t i = 0; i < matchers.size(); ++i) {
    const double ms = Median(matchers[i].samples_ms);
    std::printf("| %s | %.2f | %.2fx | %zu | %zu |\n", matchers[i].name.c_str(), ms, ms / exact_ms, found[keys[i]].size(),
                Overlap(found["exact"], found[keys[i]]));
  }

  // ---------------------------------------------------------------- verification
  const FeatureSet fa = Extract(paths[0], std::nullopt);
  const FeatureSet fb = Extract(paths[1], std::nullopt);
  MatchOptions nn;
  nn.ratio = 1.0f;
  nn.num_threads = 0;
  std::vector<Match> all = *MatchDescriptors(fa, fb, nn);
  std::sort(all.begin(), all.end(), [](const Match& x, const Match& y) {
    return x.distance != y.distance ? x.distance < y.distance : x.query_index < y.query_index;
  });
  // Two selections of N tentative matches: the N closest (nearly all correct: an easy pair), and N drawn
  // at random from all nearest neighbours (the pair's natural mix of correct and wrong matches, like the
  // tentative matches of a retrieval candidate).
  std::vector<Match> shuffled = all;
  std::mt19937 rng(7);
  std::shuffle(shuffled.begin(), shuffled.end(), rng);
  for (const bool closest : {true, false}) {
    const std::vector<Match>& pool = closest ? all : shuffled;
    std::printf("\n### Verification per pair, %s (%zu x %zu keypoints, %zu one-to-one nearest neighbours)\n\n",
                closest ? "the N closest matches" : "N random nearest-neighbour matches", fa.size(), fb.size(), all.size());
    std::printf("| N matches | Hough/affine ms | inliers | USAC MAGSAC++ H ms | inliers | ratio | RANSAC H ms | inliers | ratio |\n");
    std::printf("|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for (size_t n : {size_t{100}, size_t{1000}, size_t{5000}}) {
      if (n > pool.size()) {
        std::printf("| %zu | (only %zu matches) |||||||\n", n, pool.size());
        continue;
      }
      const std::vector<Match> subset(pool.begin(), pool.begin() + static_cast<std::ptrdiff_t>(n));
      std::vector<cv::Point2f> src, dst;
      for (const Match& m : subset) {
        src.emplace_back(fa.keypoints[m.query_index].x, fa.keypoints[m.query_index].y);
        dst.emplace_back(fb.keypoints[m.db_index].x, fb.keypoints[m.db_index].y);
      }
      const std::array<float, 4> region = {0, 0, float(fa.image_width), float(fa.image_height)};
      int hough_inliers = 0, magsac_inliers = 0, ransac_inliers = 0;
      std::vector<Contender> verifiers = {
          {"hough", [&] {
             hough_inliers = VerifyHoughAffine(fa.keypoints, fb.keypoints, subset, region, {fb.image_width, fb.image_height}).num_inliers;
           }, {}},
          {"magsac", [&] {
             std::vector<uchar> mask;
             cv::findHomography(src, dst, cv::USAC_MAGSAC, 4.0, mask, 10000, 0.999);
             magsac_inliers = cv::countNonZero(mask);
           }, {}},
          {"ransac", [&] {
             std::vector<uchar> mask;
             cv::findHomography(src, dst, cv::RANSAC, 4.0, mask, 10000, 0.999);
             ransac_inliers = cv::countNonZero(mask);
           }, {}},
      };
      cv::setNumThreads(1);
      RunInterleaved(verifiers, reps, 5.0);
      cv::setNumThreads(threads);
      const double h = Median(verifiers[0].samples_ms), m = Median(verifiers[1].samples_ms), r = Median(verifiers[2].samples_ms);
      std::printf("| %zu | %.3f | %d | %.3f | %d | %.1fx | %.3f | %d | %.1fx |\n", n, h, hough_inliers, m, magsac_inliers,
                  m / h, r, ransac_inliers, r / h);
    }
  }
  std::printf("\nratio = peer time / Hough time (higher: Hough is faster)\n");
  return 0;
}
