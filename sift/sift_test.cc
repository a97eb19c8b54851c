#include "sift/sift.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <numbers>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/base/cpu.h"
#include "sift/base/hash.h"
#include "sift/scale_space.h"
#include "sift/sift_internal.h"
#include "tests/support/feature_eval.h"
#include "tests/support/shared_data.h"

namespace oxbow::sift {
namespace {

const std::string kOpencvData = "/usr/share/doc/opencv-doc/examples/data/";
constexpr double kPi = std::numbers::pi;

GrayImage FromMat(const cv::Mat& m8) { return GrayFromBytes(m8.ptr<uint8_t>(0), m8.cols, m8.rows, m8.step[0]); }

cv::Mat LoadGray(const std::string& path) { return cv::imread(path, cv::IMREAD_GRAYSCALE); }

// The comparisons with cv::SIFT compare raw SIFT descriptors (the product default is RootSIFT).
// cv::SIFT's settings: raw SIFT descriptors and its refinement and orientation assignment.
SiftOptions OpencvLike() {
  SiftOptions options;
  options.descriptor = DescriptorKind::kSift;
  options.keypoint_style = KeypointStyle::kOpenCv;
  options.contrast_threshold = 0.04;
  options.descriptor_magnification = 3;  // Lowe's descriptor, every row sampled
  options.descriptor_row_step = 1;
  return options;
}

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
    const FeatureSet ours = MakeExtractor(OpencvLike()).Extract(FromMat(gray));
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

// A dark image with one bright Gaussian blob of standard deviation `blob_sigma` centred at (cx, cy).
GrayImage Blob(int w, int h, double cx, double cy, double blob_sigma) {
  GrayImage g;
  g.width = w;
  g.height = h;
  g.pixels.resize(static_cast<size_t>(w) * static_cast<size_t>(h));
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const double r2 = (x - cx) * (x - cx) + (y - cy) * (y - cy);
      g.pixels[(static_cast<size_t>(y) * w) + x] = static_cast<float>(0.1 + 0.8 * std::exp(-r2 / (2 * blob_sigma * blob_sigma)));
    }
  return g;
}

TEST(SiftSynthetic, GaussianBlobGivesOneKeypointAtItsCentreAndScale) {
  // The scale-normalised Laplacian of a Gaussian blob of sigma s peaks at scale s (Lindeberg), so the
  // keypoint scale should be close to s. The DoG's negative ring around a wide blob has weak extrema of
  // its own (about an eighth of the centre's contrast at s = 6, just above the default threshold): every
  // keypoint of at least half the strongest's contrast is the blob's centre.
  for (const double s : {3.0, 6.0}) {
    const FeatureSet f = MakeExtractor().Extract(Blob(128, 96, 60.0, 50.0, s));
    ASSERT_GE(f.size(), 1u) << "sigma " << s;
    float strongest = 0;
    for (const Keypoint& k : f.keypoints) strongest = std::max(strongest, std::fabs(k.response));
    int at_centre = 0;
    for (const Keypoint& k : f.keypoints) {  // a round blob may give several orientations, same point
      EXPECT_GT(k.response, 0.0f);
      if (std::fabs(k.response) < 0.5f * strongest) {
        EXPECT_LT(std::fabs(k.response), 0.2f * strongest) << "sigma " << s;  // the ring, far weaker
        EXPECT_GT(std::hypot(k.x - 60.0, k.y - 50.0), s) << "sigma " << s;
        continue;
      }
      ++at_centre;
      EXPECT_NEAR(k.x, 60.0, 0.3) << "sigma " << s;
      EXPECT_NEAR(k.y, 50.0, 0.3) << "sigma " << s;
      EXPECT_NEAR(k.scale / s, 1.0, 0.15) << "sigma " << s << " scale " << k.scale;
    }
    EXPECT_GE(at_centre, 1) << "sigma " << s;
  }
}

TEST(SiftSynthetic, BlankImagesGiveNoKeypoints) {
  for (const float value : {0.0f, 0.5f, 1.0f}) {
    GrayImage g;
    g.width = 100;
    g.height = 80;
    g.pixels.assign(100 * 80, value);
    const FeatureSet f = MakeExtractor().Extract(g);
    EXPECT_EQ(f.size(), 0u);
    EXPECT_EQ(f.image_width, 100);
  }
}

TEST(SiftSynthetic, TinyAndOddSizedImagesDoNotCrash) {
  cv::RNG rng(7);
  for (const auto& [w, h] : std::vector<std::pair<int, int>>{{0, 0}, {1, 1}, {2, 3}, {8, 8}, {1, 100}, {100, 1}, {17, 33}, {31, 16}, {257, 129}}) {
    cv::Mat noise(std::max(h, 1), std::max(w, 1), CV_8U);
    rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
    GrayImage g = w == 0 ? GrayImage{} : FromMat(noise);
    for (const auto& [upsample, sampling] : {std::pair{true, DescriptorSampling::kPixels}, std::pair{false, DescriptorSampling::kPixels},
                                             std::pair{true, DescriptorSampling::kGrid}, std::pair{false, DescriptorSampling::kGrid}}) {
      SiftOptions options;
      options.upsample_first_octave = upsample;
      options.descriptor_sampling = sampling;
      const FeatureSet f = MakeExtractor(options).Extract(g);
      EXPECT_EQ(f.descriptors.size(), f.size() * kDescriptorDim);
      for (const Keypoint& k : f.keypoints) {
        EXPECT_TRUE(k.x >= -0.5f && k.x <= w - 0.5f && k.y >= -0.5f && k.y <= h - 0.5f) << w << "x" << h;
        EXPECT_TRUE(std::isfinite(k.scale) && k.scale > 0);
      }
    }
  }
}

bool SameFeatures(const FeatureSet& a, const FeatureSet& b) {
  if (a.size() != b.size() || a.descriptors != b.descriptors) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    const Keypoint &p = a.keypoints[i], &q = b.keypoints[i];
    if (p.x != q.x || p.y != q.y || p.scale != q.scale || p.orientation != q.orientation || p.response != q.response ||
        p.octave != q.octave)
      return false;
  }
  return true;
}

TEST(SiftDeterminism, ThreadCountsAndSimdPathsAgreeExactly) {
  const cv::Mat gray = LoadGray(kOpencvData + "box.png");
  ASSERT_FALSE(gray.empty());
  const GrayImage image = FromMat(gray);
  for (const auto& [style, sampling] : {std::pair{KeypointStyle::kVlfeat, DescriptorSampling::kPixels},
                                        std::pair{KeypointStyle::kOpenCv, DescriptorSampling::kPixels},
                                        std::pair{KeypointStyle::kVlfeat, DescriptorSampling::kGrid}}) {
    SiftOptions options;
    options.keypoint_style = style;
    options.descriptor_sampling = sampling;
    options.num_threads = 1;
    const FeatureSet one = MakeExtractor(options).Extract(image);
    ASSERT_GT(one.size(), 100u);
    for (const int threads : {2, 3, 8}) {
      options.num_threads = threads;
      EXPECT_TRUE(SameFeatures(one, MakeExtractor(options).Extract(image))) << threads << " threads";
    }
    options.num_threads = 2;
    EXPECT_TRUE(SameFeatures(one, internal::ExtractImpl(image, options, /*allow_simd=*/false)))
        << "scalar and vector paths differ (vector paths available: " << Avx2FmaAvailable() << "), style "
        << static_cast<int>(style) << ", sampling " << static_cast<int>(sampling);
#ifdef OXBOW_AVX512_DISPATCH
    // A portable build on an AVX-512 CPU: `one` came from the AVX-512 paths; the AVX2 paths must agree.
    if (Avx512Available()) {
      AllowAvx512(false);
      const bool avx2_taken = !Avx512Available();
      const FeatureSet avx2 = MakeExtractor(options).Extract(image);
      AllowAvx512(true);
      EXPECT_TRUE(avx2_taken);
      EXPECT_TRUE(SameFeatures(one, avx2)) << "AVX-512 and AVX2 paths differ, style " << static_cast<int>(style)
                                           << ", sampling " << static_cast<int>(sampling);
    }
#endif
  }
}

// The features of one photo, hashed: the same bytes in a native build (its AVX-512 or AVX2 paths) and in
// a portable build for x86-64-v3 (OXBOW_PORTABLE_MARCH, CMakeLists.txt), so that an index or a
// vocabulary made by the Debian package or the Docker image is the one the README's build makes. A
// baseline x86-64 build (sift_portable_test compiles this file so) finds the same keypoints, bit for
// bit; its descriptors differ in the last bits: its scalar code cannot fuse multiply-adds, nor can that
// of a build optimised below -O2 (the sanitizer builds; sift/CMakeLists.txt). A deliberate change of the
// extractor changes the values below; a change of the build must not.
TEST(SiftDeterminism, FeaturesAreTheSameBytesInEveryBuild) {
  const cv::Mat gray = LoadGray(kOpencvData + "graf1.png");
  ASSERT_FALSE(gray.empty());
  SiftOptions options;
  options.num_threads = 2;
  const FeatureSet features = MakeExtractor(options).Extract(FromMat(gray));
  ASSERT_EQ(features.size(), 3360u);
  uint64_t keypoints = kFnv1a64Basis;
  for (const Keypoint& k : features.keypoints) {
    for (const float v : {k.x, k.y, k.scale, k.orientation, k.response}) {
      keypoints = Fnv1a64(std::string_view(reinterpret_cast<const char*>(&v), sizeof v), keypoints);
    }
    keypoints = Fnv1a64(std::string_view(reinterpret_cast<const char*>(&k.octave), sizeof k.octave), keypoints);
  }
  EXPECT_EQ(keypoints, 0x9beab537a9096b36ull);
#if defined(__AVX2__) && defined(__FMA__) && defined(OXBOW_SIFT_FUSED_FLOATS)
  const uint64_t descriptors = Fnv1a64(std::string_view(reinterpret_cast<const char*>(features.descriptors.data()),
                                                        features.descriptors.size() * sizeof(float)));
  EXPECT_EQ(descriptors, 0x1f916bb9a5aed511ull);
#endif
}

// A stop is asked on the calling thread only, also while other threads blur and scan their strips, and
// it ends the extraction early: fewer keypoints than a whole one.
TEST(SiftStop, IsAskedOnTheCallingThreadAndEndsTheExtraction) {
  const cv::Mat gray = LoadGray(kOpencvData + "box.png");
  ASSERT_FALSE(gray.empty());
  const GrayImage image = FromMat(gray);
  SiftOptions options;
  options.num_threads = 4;
  const FeatureSet whole = internal::ExtractImpl(image, options, true);
  ASSERT_GT(whole.size(), 100u);
  for (const int after : {0, 1, 3}) {
    const std::thread::id caller = std::this_thread::get_id();
    int asked = 0;
    bool elsewhere = false;
    const FeatureSet part = internal::ExtractImpl(image, options, true, [&] {
      elsewhere = elsewhere || std::this_thread::get_id() != caller;
      return ++asked > after;
    });
    EXPECT_FALSE(elsewhere) << after;
    EXPECT_GT(asked, after);
    EXPECT_LT(part.size(), whole.size()) << after;
  }
}

// The vector paths run wherever the CPU has AVX2 and FMA, and the AVX-512 ones wherever it has those,
// also in a portable build (sift/base/cpu.h), so that ThreadCountsAndSimdPathsAgreeExactly compares
// the paths there rather than the scalar one twice.
TEST(SiftDeterminism, VectorPathsRunWhereTheCpuHasThem) {
#if defined(__x86_64__) && defined(__GNUC__)
  EXPECT_EQ(Avx2FmaAvailable(), __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"));
  // The AVX-512 paths too: in a native build for such a CPU, or chosen at run time in any other.
  EXPECT_EQ(Avx512Available(), Avx2FmaAvailable() && __builtin_cpu_supports("avx512f") &&
                                   __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl") &&
                                   __builtin_cpu_supports("avx512bw"));
#else
  GTEST_SKIP() << "the vector paths are x86-64 only";
#endif
}

TEST(SiftDeterminism, ReusedPyramidBuffersGiveTheSameOutput) {
  const GrayImage small = FromMat(LoadGray(kOpencvData + "box.png"));
  const GrayImage large = FromMat(LoadGray(kOpencvData + "graf1.png"));
  ASSERT_GT(small.width, 0);
  ASSERT_GT(large.width, 0);
  // Reference: a fresh thread (empty cache) that frees its buffers after every call.
  SiftOptions no_cache;
  no_cache.num_threads = 1;
  no_cache.thread_cache_mib = 0;
  FeatureSet small_ref, large_ref;
  std::thread([&] {
    small_ref = MakeExtractor(no_cache).Extract(small);
    large_ref = MakeExtractor(no_cache).Extract(large);
  }).join();
  ASSERT_GT(small_ref.size(), 100u);
  // Cached buffers grown (small then large), then reused with stale contents for a smaller image, and
  // with a different number of intervals (planes per octave).
  SiftOptions cached = no_cache;
  cached.thread_cache_mib = 256;
  std::thread([&] {
    const SiftExtractor extractor = MakeExtractor(cached);
    EXPECT_TRUE(SameFeatures(small_ref, extractor.Extract(small)));
    EXPECT_TRUE(SameFeatures(large_ref, extractor.Extract(large)));
    EXPECT_TRUE(SameFeatures(small_ref, extractor.Extract(small)));
    SiftOptions four = cached;
    four.intervals = 4;
    EXPECT_GT(MakeExtractor(four).Extract(small).size(), 0u);
    EXPECT_TRUE(SameFeatures(large_ref, extractor.Extract(large)));
    SiftOptions two_threads = cached;
    two_threads.num_threads = 2;
    EXPECT_TRUE(SameFeatures(small_ref, MakeExtractor(two_threads).Extract(small)));
  }).join();
}

TEST(SiftWorkerTeam, CoversEveryItemOnceAcrossLoopsAndRethrows) {
  for (const int threads : {1, 2, 4}) {
    internal::WorkerTeam team(threads);
    EXPECT_EQ(team.size(), threads);
    for (const size_t n : {size_t{0}, size_t{1}, size_t{7}, size_t{1000}}) {
      std::vector<int> hits(n, 0);
      std::vector<int> workers(n, -1);
      team.ParallelFor(n, 3, [&](size_t begin, size_t end, int worker) {
        for (size_t i = begin; i < end; ++i) {
          ++hits[i];
          workers[i] = worker;
        }
      });
      for (size_t i = 0; i < n; ++i) {
        ASSERT_EQ(hits[i], 1) << threads << " threads, n " << n << ", item " << i;
        ASSERT_GE(workers[i], 0);
        ASSERT_LT(workers[i], threads);
      }
    }
    EXPECT_THROW(team.ParallelFor(100, 1,
                                  [](size_t begin, size_t end, int) {
                                    if (begin <= 42 && 42 < end) throw std::runtime_error("item 42");
                                  }),
                 std::runtime_error);
    // Still usable after an exception.
    std::vector<int> hits(50, 0);
    team.ParallelFor(50, 2, [&](size_t begin, size_t end, int) {
      for (size_t i = begin; i < end; ++i) ++hits[i];
    });
    EXPECT_EQ(std::count(hits.begin(), hits.end(), 1), 50);
  }
}

TEST(SiftDeterminism, VectorAndScalarKernelsAgree) {
  cv::RNG rng(3);
  internal::Plane src(77, 41);
  for (int y = 0; y < src.height(); ++y)
    for (int x = 0; x < src.width(); ++x) src.row(y)[x] = static_cast<float>(rng.uniform(0.0, 1.0));
  for (const double sigma : {0.8, 1.6, 3.1}) {
    const auto kernel = internal::GaussianHalfKernel(sigma, 4.0);
    double sum = kernel[0];
    for (size_t i = 1; i < kernel.size(); ++i) sum += 2 * kernel[i];
    EXPECT_NEAR(sum, 1.0, 1e-6);
    internal::Plane a, b, c;
    internal::GaussianBlur(src, &a, kernel, 1, true);
    internal::GaussianBlur(src, &b, kernel, 2, false);
    AllowAvx512(false);  // where the AVX-512 paths are chosen at run time: the AVX2 ones
    internal::GaussianBlur(src, &c, kernel, 1, true);
    AllowAvx512(true);
    // And against OpenCV's GaussianBlur with the same kernel size and border.
    cv::Mat in(src.height(), src.width(), CV_32F), ref;
    for (int y = 0; y < src.height(); ++y) std::copy_n(src.row(y), src.width(), in.ptr<float>(y));
    const int ksize = 2 * static_cast<int>(kernel.size()) - 1;
    cv::GaussianBlur(in, ref, cv::Size(ksize, ksize), sigma, sigma, cv::BORDER_REFLECT_101);
    for (int y = 0; y < src.height(); ++y)
      for (int x = 0; x < src.width(); ++x) {
        ASSERT_EQ(a.at(x, y), b.at(x, y)) << x << "," << y;
        ASSERT_EQ(a.at(x, y), c.at(x, y)) << x << "," << y;
        ASSERT_NEAR(a.at(x, y), ref.at<float>(y, x), 2e-5f) << x << "," << y;
      }
  }
  for (int iy = -8; iy <= 8; ++iy)
    for (int ix = -8; ix <= 8; ++ix) {
      if (ix == 0 && iy == 0) continue;
      const float y = 0.25f * static_cast<float>(iy);
      const float x = 0.25f * static_cast<float>(ix);
      double expected = std::atan2(y, x) * 180 / kPi;
      if (expected < 0) expected += 360;
      const double diff = std::fabs(internal::FastAtan2Deg(y, x) - expected);
      EXPECT_LT(std::min(diff, 360 - diff), 1e-3) << x << "," << y;
    }
}

// Keypoints of `a` mapped by `map` that find a keypoint of `b` within the tolerances; orientation
// expected to shift by `angle_shift`. Only keypoints of `a` with scale >= min_scale are counted.
template <typename Map>
double InvarianceShare(const FeatureSet& a, const FeatureSet& b, Map map, double scale_factor, double angle_shift, double min_scale,
                       double position_px, double scale_ratio, double angle_tol) {
  int counted = 0, found = 0;
  for (const Keypoint& k : a.keypoints) {
    if (k.scale < min_scale) continue;
    double x, y;
    map(k.x, k.y, &x, &y);
    if (x < 8 || y < 8 || x > b.image_width - 9 || y > b.image_height - 9) continue;
    ++counted;
    for (const Keypoint& q : b.keypoints) {
      if (std::fabs(q.x - x) > position_px || std::fabs(q.y - y) > position_px) continue;
      if (std::fabs(std::log(q.scale / (k.scale * scale_factor))) > std::log(scale_ratio)) continue;
      if (AngleDifference(q.orientation, k.orientation + angle_shift) > angle_tol) continue;
      ++found;
      break;
    }
  }
  return counted ? static_cast<double>(found) / counted : 0;
}

TEST(SiftInvariance, RotationBy90DegreesKeepsKeypointsAndTurnsOrientations) {
  const cv::Mat gray = LoadGray(kOpencvData + "graf1.png");
  ASSERT_FALSE(gray.empty());
  cv::Mat rotated;
  cv::rotate(gray, rotated, cv::ROTATE_90_CLOCKWISE);  // (x, y) -> (H - 1 - y, x)
  const auto extractor = MakeExtractor();
  const FeatureSet a = extractor.Extract(FromMat(gray)), b = extractor.Extract(FromMat(rotated));
  const double h = gray.rows;
  const double share = InvarianceShare(
      a, b, [&](double x, double y, double* u, double* v) { *u = h - 1 - y, *v = x; }, 1.0, kPi / 2, 0.0, 1.0, 1.1,
      10 * kPi / 180);
  std::printf("90-degree rotation: %.1f%% of keypoints found with the orientation turned by 90 degrees\n", 100 * share);
  EXPECT_GT(share, 0.75);
}

// Median over the keypoints of `a` of the smallest descriptor distance to a keypoint of `b` at the
// mapped position (0.5 px) and scale (5%); -1 when none pairs up.
template <typename Map>
double MedianPairedDistance(const FeatureSet& a, const FeatureSet& b, Map map) {
  std::vector<double> distances;
  for (size_t i = 0; i < a.size(); ++i) {
    double u = 0, v = 0;
    map(a.keypoints[i].x, a.keypoints[i].y, &u, &v);
    double best = -1;
    for (size_t j = 0; j < b.size(); ++j) {
      const Keypoint& k = b.keypoints[j];
      if (std::hypot(k.x - u, k.y - v) > 0.5 || std::fabs(k.scale / a.keypoints[i].scale - 1) > 0.05) continue;
      double d2 = 0;
      for (int e = 0; e < kDescriptorDim; ++e) d2 += std::pow(a.Descriptor(i)[e] - b.Descriptor(j)[e], 2);
      if (best < 0 || d2 < best * best) best = std::sqrt(d2);
    }
    if (best >= 0) distances.push_back(best);
  }
  if (distances.empty()) return -1;
  std::nth_element(distances.begin(), distances.begin() + static_cast<ptrdiff_t>(distances.size() / 2), distances.end());
  return distances[distances.size() / 2];
}

TEST(SiftUpright, OneKeypointPerExtremumAlongTheXAxisAndNoRotationInvariance) {
  const cv::Mat gray = LoadGray(kOpencvData + "graf1.png");
  ASSERT_FALSE(gray.empty());
  SiftOptions upright_options;
  upright_options.upright = true;
  upright_options.max_octaves = 3;  // the small keypoints are enough, and the pairing below is quadratic
  SiftOptions oriented_options;
  oriented_options.max_octaves = 3;
  const auto upright = MakeExtractor(upright_options), oriented = MakeExtractor(oriented_options);
  const FeatureSet a = oriented.Extract(FromMat(gray)), a_up = upright.Extract(FromMat(gray));
  // The oriented set's extrema, each once and in order (several orientations of one extremum are
  // consecutive), are the upright set's keypoints, each with orientation 0.
  std::vector<std::array<float, 3>> extrema;
  for (const Keypoint& k : a.keypoints) {
    const std::array<float, 3> e = {k.x, k.y, k.scale};
    if (extrema.empty() || extrema.back() != e) extrema.push_back(e);
  }
  ASSERT_EQ(a_up.size(), extrema.size());
  EXPECT_LT(a_up.size(), a.size());  // graf1 has extrema with two or more orientations
  for (size_t i = 0; i < a_up.size(); ++i) {
    const Keypoint& k = a_up.keypoints[i];
    EXPECT_EQ((std::array<float, 3>{k.x, k.y, k.scale}), extrema[i]) << i;
    EXPECT_EQ(k.orientation, 0.0f) << i;
  }
  // Turned by 90 degrees, an oriented keypoint keeps its descriptor; an upright one describes the
  // turned patch, which is another histogram.
  cv::Mat rotated;
  cv::rotate(gray, rotated, cv::ROTATE_90_CLOCKWISE);  // (x, y) -> (H - 1 - y, x)
  const double h = gray.rows;
  const auto map = [&](double x, double y, double* u, double* v) { *u = h - 1 - y, *v = x; };
  const double oriented_distance = MedianPairedDistance(a, oriented.Extract(FromMat(rotated)), map);
  const double upright_distance = MedianPairedDistance(a_up, upright.Extract(FromMat(rotated)), map);
  std::printf("90-degree rotation: median descriptor distance %.3f oriented, %.3f upright\n", oriented_distance,
              upright_distance);
  ASSERT_GE(oriented_distance, 0);
  ASSERT_GE(upright_distance, 0);
  EXPECT_LT(oriented_distance, 0.2);  // 0 here: a quarter turn maps the pixel grid onto itself
  EXPECT_GT(upright_distance, 0.5);   // unit-norm descriptors: 1.1 measured
}

TEST(SiftInvariance, HalfSizeKeepsTheLargerKeypoints) {
  const cv::Mat gray = LoadGray(kOpencvData + "graf1.png");
  ASSERT_FALSE(gray.empty());
  cv::Mat half;
  cv::resize(gray, half, cv::Size(gray.cols / 2, gray.rows / 2), 0, 0, cv::INTER_AREA);
  const auto extractor = MakeExtractor();
  const FeatureSet a = extractor.Extract(FromMat(gray)), b = extractor.Extract(FromMat(half));
  // Keypoints smaller than ~2x the smallest detectable scale cannot survive halving.
  const double share = InvarianceShare(
      a, b, [](double x, double y, double* u, double* v) { *u = (x + 0.5) / 2 - 0.5, *v = (y + 0.5) / 2 - 0.5; }, 0.5, 0.0, 4.0,
      1.5, 1.25, 15 * kPi / 180);
  std::printf("2x downscale: %.1f%% of keypoints with scale >= 4 px found at half position and scale\n", 100 * share);
  EXPECT_GT(share, 0.5);
}

TEST(SiftDescriptor, NormalisedClippedAndRootSiftConsistent) {
  const cv::Mat gray = LoadGray(kOpencvData + "box.png");
  SiftOptions options = OpencvLike();
  options.max_features = 300;
  const FeatureSet sift = MakeExtractor(options).Extract(FromMat(gray));
  ASSERT_EQ(sift.size(), 300u);
  // A descriptor whose largest element exceeds 0.2 must have been clipped (unclipped, the unit vector
  // would already be final). Clipping sets every clipped element to exactly 0.2 before the common
  // renormalisation, so they come out bit-identical: descriptors with 2+ elements tied at the maximum.
  // Without clipping such exact ties among 128 interpolated floats essentially never happen.
  int over_02 = 0, tied_at_max = 0;
  for (size_t i = 0; i < sift.size(); ++i) {
    double norm2 = 0;
    float max_value = 0;
    for (float v : sift.Descriptor(i)) {
      ASSERT_GE(v, 0.0f);
      norm2 += v * v;
      max_value = std::max(max_value, v);
    }
    EXPECT_NEAR(norm2, 1.0, 1e-4);
    // Clipping at 0.2 then renormalising bounds each element by 0.2 / (norm after clipping); with 128
    // elements the renormalised maximum stays well below 0.5 unless a descriptor is nearly one spike.
    EXPECT_LT(max_value, 0.5f);
    if (max_value <= 0.2f) continue;
    ++over_02;
    int at_max = 0;
    for (float v : sift.Descriptor(i)) at_max += v == max_value ? 1 : 0;
    tied_at_max += at_max >= 2 ? 1 : 0;
  }
  std::printf("%d of %zu descriptors above 0.2, %d of them with 2+ elements tied at the maximum\n", over_02, sift.size(),
              tied_at_max);
  ASSERT_GT(over_02, 30) << "too few descriptors reach the clipping for the check below to mean anything";
  EXPECT_GT(tied_at_max, over_02 / 2) << "clipped elements are not equal: the 0.2 clipping looks inactive";

  options.descriptor = DescriptorKind::kRootSift;
  const FeatureSet root = MakeExtractor(options).Extract(FromMat(gray));
  ASSERT_EQ(root.size(), sift.size());
  EXPECT_EQ(root.kind, DescriptorKind::kRootSift);
  for (size_t i = 0; i < sift.size(); ++i) {
    std::vector<float> expected(sift.Descriptor(i).begin(), sift.Descriptor(i).end());
    ToRootSift(expected);
    double norm2 = 0;
    for (int k = 0; k < kDescriptorDim; ++k) {
      ASSERT_NEAR(root.Descriptor(i)[static_cast<size_t>(k)], expected[static_cast<size_t>(k)], 1e-6f);
      norm2 += expected[static_cast<size_t>(k)] * expected[static_cast<size_t>(k)];
    }
    EXPECT_NEAR(norm2, 1.0, 1e-4);
  }

  std::vector<uint8_t> bytes;
  DescriptorsToUint8(sift, &bytes);
  ASSERT_EQ(bytes.size(), sift.descriptors.size());
  for (size_t i = 0; i < bytes.size(); ++i)
    EXPECT_EQ(bytes[i], static_cast<uint8_t>(std::min(255.0f, std::round(512.0f * sift.descriptors[i]))));
}

TEST(SiftDescriptor, ClippingOfASpikyHistogram) {
  // A keypoint on one straight edge: its gradients share one direction, so the descriptor is a few
  // spikes and clipping at 0.2 must flatten them to equal values.
  GrayImage g;
  g.width = g.height = 96;
  g.pixels.resize(96 * 96);
  for (int y = 0; y < 96; ++y)
    for (int x = 0; x < 96; ++x) g.pixels[(static_cast<size_t>(y) * 96) + x] = (x - 48) * (x - 48) + (y - 48) * (y - 48) < 15 * 15 ? 0.9f : 0.1f;
  const FeatureSet f = MakeExtractor().Extract(g);
  ASSERT_GT(f.size(), 0u);
  bool found_flattened = false;
  for (size_t i = 0; i < f.size(); ++i) {
    std::vector<float> d(f.Descriptor(i).begin(), f.Descriptor(i).end());
    std::sort(d.rbegin(), d.rend());
    if (d[0] > 0.2f && std::fabs(d[0] - d[1]) < 1e-6f) found_flattened = true;
  }
  EXPECT_TRUE(found_flattened);
}

// The corner error (tests/support/feature_eval.h) of a shifted and of a scaled homography, whose
// distances at the corners are known, and of one that sends a corner to infinity.
TEST(SiftHomography, CornerErrorOfKnownHomographies) {
  const Homography truth = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  const CornerError shifted = CornerErrorOf({1, 0, 3, 0, 1, 4, 0, 0, 1}, truth, 11, 21);
  EXPECT_DOUBLE_EQ(shifted.mean_px, 5.0);
  EXPECT_DOUBLE_EQ(shifted.max_px, 5.0);
  // Twice the size: the corner (0, 0) stays, (10, 0) moves 10 px, (0, 20) 20 px, (10, 20) sqrt(500) px.
  const CornerError scaled = CornerErrorOf({2, 0, 0, 0, 2, 0, 0, 0, 1}, truth, 11, 21);
  EXPECT_DOUBLE_EQ(scaled.max_px, std::sqrt(500.0));
  EXPECT_DOUBLE_EQ(scaled.mean_px, (0 + 10 + 20 + std::sqrt(500.0)) / 4);
  const CornerError degenerate = CornerErrorOf({1, 0, 0, 0, 1, 0, 0.1, 0, 0}, truth, 11, 21);
  EXPECT_TRUE(std::isinf(degenerate.max_px));
}

TEST(SiftHomography, Graf1To3NotWorseThanOpencv) {
  const cv::Mat g1 = LoadGray(kOpencvData + "graf1.png"), g3 = LoadGray(kOpencvData + "graf3.png");
  auto h = ReadHomography(kOpencvData + "H1to3p.xml");
  ASSERT_TRUE(h) << h.error().ToString();
  const auto extractor = MakeExtractor(OpencvLike());
  const HomographyScore ours = ScoreUnderHomography(extractor.Extract(FromMat(g1)), extractor.Extract(FromMat(g3)), *h);
  const HomographyScore cv = ScoreUnderHomography(OpencvSift(g1), OpencvSift(g3), *h);
  std::printf("graf1->graf3 (3 px): ours repeatability %.3f matching score %.3f; cv::SIFT %.3f %.3f\n", ours.repeatability,
              ours.matching_score, cv.repeatability, cv.matching_score);
  // Tolerance 0.02 absolute: the two implementations differ in sub-pixel details (our 0.25 px centre
  // correction, sub-pixel descriptor centring), which moves a handful of keypoints across the 3 px limit.
  EXPECT_GE(ours.repeatability, cv.repeatability - 0.02);
  EXPECT_GE(ours.matching_score, cv.matching_score - 0.02);
  EXPECT_GT(ours.matching_score, 0.05);
}

// The default keypoint style (KeypointStyle::kVlfeat) keeps extrema the cv::SIFT style drops and votes
// orientations more smoothly: on graf1->graf3 it repeats more keypoints and gives ~25% more correct
// matches (raw SIFT both).
TEST(SiftHomography, VlfeatStyleMatchesMoreThanOpencvStyle) {
  const cv::Mat g1 = LoadGray(kOpencvData + "graf1.png"), g3 = LoadGray(kOpencvData + "graf3.png");
  auto h = ReadHomography(kOpencvData + "H1to3p.xml");
  ASSERT_TRUE(h) << h.error().ToString();
  SiftOptions vlfeat = OpencvLike();
  vlfeat.keypoint_style = KeypointStyle::kVlfeat;
  const auto score = [&](const SiftOptions& options) {
    const auto extractor = MakeExtractor(options);
    return ScoreUnderHomography(extractor.Extract(FromMat(g1)), extractor.Extract(FromMat(g3)), *h);
  };
  const HomographyScore ours = score(vlfeat), opencv = score(OpencvLike());
  std::printf("graf1->graf3: vlfeat style repeatability %.3f matching score %.3f correct %d; opencv style %.3f %.3f %d\n",
              ours.repeatability, ours.matching_score, ours.correct_matches, opencv.repeatability,
              opencv.matching_score, opencv.correct_matches);
  EXPECT_GT(ours.repeatability, opencv.repeatability + 0.01);
  EXPECT_GT(ours.matching_score, opencv.matching_score);
  EXPECT_GT(ours.correct_matches, opencv.correct_matches * 11 / 10);
}

// graf1's features and their score against graf3's under the true homography, with `options`.
struct GrafScore {
  FeatureSet graf1;
  HomographyScore score;
};
GrafScore ScoreGraf(const SiftOptions& options) {
  const cv::Mat g1 = LoadGray(kOpencvData + "graf1.png"), g3 = LoadGray(kOpencvData + "graf3.png");
  auto h = ReadHomography(kOpencvData + "H1to3p.xml");
  EXPECT_TRUE(h) << h.error().ToString();
  if (!h) return {};
  const auto extractor = MakeExtractor(options);
  GrafScore out{extractor.Extract(FromMat(g1)), {}};
  out.score = ScoreUnderHomography(out.graf1, extractor.Extract(FromMat(g3)), *h);
  return out;
}

// A wider descriptor window (SiftOptions::descriptor_magnification) describes the same keypoints with more
// of their surroundings: on graf1->graf3 it gives more correct matches (sift_benchmark --quality has the
// Oxford affine pairs).
TEST(SiftHomography, WiderDescriptorSameKeypointsMoreMatches) {
  SiftOptions lowe = OpencvLike();
  lowe.keypoint_style = KeypointStyle::kVlfeat;
  lowe.descriptor_magnification = 3;
  SiftOptions wide = lowe;
  wide.descriptor_magnification = 4;
  const GrafScore narrow = ScoreGraf(lowe), wider = ScoreGraf(wide);
  ASSERT_EQ(narrow.graf1.size(), wider.graf1.size());
  size_t same_descriptor = 0;
  for (size_t i = 0; i < narrow.graf1.size(); ++i) {
    EXPECT_EQ(narrow.graf1.keypoints[i].x, wider.graf1.keypoints[i].x);
    EXPECT_EQ(narrow.graf1.keypoints[i].scale, wider.graf1.keypoints[i].scale);
    const auto a = narrow.graf1.Descriptor(i), b = wider.graf1.Descriptor(i);
    same_descriptor += std::equal(a.begin(), a.end(), b.begin());
  }
  EXPECT_EQ(same_descriptor, 0u);
  std::printf("graf1->graf3: magnification 3 matching score %.3f correct %d; 4: %.3f %d\n", narrow.score.matching_score,
              narrow.score.correct_matches, wider.score.matching_score, wider.score.correct_matches);
  EXPECT_GT(wider.score.correct_matches, narrow.score.correct_matches * 21 / 20);
}

// With cells 4 scales wide, sampling every second row of the descriptor window
// (SiftOptions::descriptor_row_step) describes the keypoints as well as every row does: on graf1->graf3
// the correct matches are within 2%.
TEST(SiftHomography, EverySecondDescriptorRowMatchesAsEveryRow) {
  SiftOptions every_row = OpencvLike();
  every_row.keypoint_style = KeypointStyle::kVlfeat;
  every_row.descriptor_magnification = 4;
  every_row.descriptor_row_step = 1;
  SiftOptions stepped = every_row;
  stepped.descriptor_row_step = 2;
  const GrafScore all = ScoreGraf(every_row), some = ScoreGraf(stepped);
  ASSERT_EQ(all.graf1.size(), some.graf1.size());
  EXPECT_NE(all.graf1.descriptors, some.graf1.descriptors);
  std::printf("graf1->graf3: every row correct %d, every second row %d\n", all.score.correct_matches,
              some.score.correct_matches);
  EXPECT_GE(some.score.correct_matches, all.score.correct_matches * 49 / 50);
}

// The grid sampling (DescriptorSampling::kGrid) describes the same keypoints as the pixel sampling, in
// the same layout: a keypoint's two descriptors are close (the median distance is a fraction of the
// distance to another keypoint's), and on graf1->graf3 the correct matches are within 3%.
TEST(SiftHomography, GridSamplingDescribesAsThePixels) {
  SiftOptions pixels = OpencvLike();
  pixels.keypoint_style = KeypointStyle::kVlfeat;
  SiftOptions grid = pixels;
  grid.descriptor_sampling = DescriptorSampling::kGrid;
  const GrafScore by_pixels = ScoreGraf(pixels), by_grid = ScoreGraf(grid);
  ASSERT_EQ(by_pixels.graf1.size(), by_grid.graf1.size());
  ASSERT_GT(by_pixels.graf1.size(), 1000u);
  std::vector<double> same, other;
  for (size_t i = 0; i < by_pixels.graf1.size(); ++i) {
    EXPECT_EQ(by_pixels.graf1.keypoints[i].x, by_grid.graf1.keypoints[i].x);
    EXPECT_EQ(by_pixels.graf1.keypoints[i].orientation, by_grid.graf1.keypoints[i].orientation);
    const auto a = by_pixels.graf1.Descriptor(i), b = by_grid.graf1.Descriptor(i);
    const auto c = by_grid.graf1.Descriptor((i + by_grid.graf1.size() / 2) % by_grid.graf1.size());
    double d_same = 0, d_other = 0;
    for (int e = 0; e < kDescriptorDim; ++e) {
      d_same += std::pow(a[e] - b[e], 2);
      d_other += std::pow(a[e] - c[e], 2);
    }
    same.push_back(std::sqrt(d_same));
    other.push_back(std::sqrt(d_other));
  }
  auto median = [](std::vector<double> v) {
    std::nth_element(v.begin(), v.begin() + static_cast<ptrdiff_t>(v.size() / 2), v.end());
    return v[v.size() / 2];
  };
  std::printf("graf1: median distance between a keypoint's pixel and grid descriptors %.3f, to another keypoint's %.3f\n",
              median(same), median(other));
  EXPECT_LT(median(same), median(other) / 3);
  std::printf("graf1->graf3: correct matches with the pixel sampling %d, the grid %d\n", by_pixels.score.correct_matches,
              by_grid.score.correct_matches);
  EXPECT_GE(by_grid.score.correct_matches, by_pixels.score.correct_matches * 97 / 100);
  EXPECT_GE(by_grid.score.matching_score, by_pixels.score.matching_score - 0.01);
}

TEST(SiftHomographySharedData, BoatSequenceNotWorseThanOpencv) {
  const std::string data = oxbow::testing::SharedDataDir().string();
  const std::string dir = data + "/oxford_affine/images/boat/";
  const std::string gt = data + "/oxford_affine/gt/boat/";
  if (!std::filesystem::exists(dir + "img1.pgm"))
    GTEST_SKIP() << "shared data not found at " << dir << " (set OXBOW_SHARED_DATA; see tests/support/shared_data.h)";
  // Half-size images (INTER_AREA) keep the test fast (brute-force matching is quadratic); the
  // homographies are conjugated accordingly. The benchmark scores the full-size images.
  auto image = [&](int i) {
    cv::Mat full = LoadGray(dir + "img" + std::to_string(i) + ".pgm"), half;
    if (full.empty()) return full;
    cv::resize(full, half, cv::Size(full.cols / 2, full.rows / 2), 0, 0, cv::INTER_AREA);
    return half;
  };
  auto half_homography = [](const Homography& h) {
    const cv::Matx33d a(0.5, 0, -0.25, 0, 0.5, -0.25, 0, 0, 1);
    const cv::Matx33d m = a * cv::Matx33d(h.data()) * a.inv();
    Homography out;
    for (int k = 0; k < 9; ++k) out[static_cast<size_t>(k)] = m.val[k];
    return out;
  };
  const cv::Mat g1 = image(1);
  ASSERT_FALSE(g1.empty());
  const auto extractor = MakeExtractor(OpencvLike());
  const FeatureSet ours1 = extractor.Extract(FromMat(g1)), cv1 = OpencvSift(g1);
  for (int i = 2; i <= 6; ++i) {
    auto h = ReadHomography(gt + "H1to" + std::to_string(i) + "p");
    ASSERT_TRUE(h) << h.error().ToString();
    const cv::Mat gi = image(i);
    const HomographyScore ours = ScoreUnderHomography(ours1, extractor.Extract(FromMat(gi)), half_homography(*h));
    const HomographyScore cv = ScoreUnderHomography(cv1, OpencvSift(gi), half_homography(*h));
    std::printf("boat (half size) 1->%d: ours repeatability %.3f matching %.3f; cv::SIFT %.3f %.3f\n", i, ours.repeatability,
                ours.matching_score, cv.repeatability, cv.matching_score);
    EXPECT_GE(ours.repeatability, cv.repeatability - 0.02) << "boat 1->" << i;
    EXPECT_GE(ours.matching_score, cv.matching_score - 0.02) << "boat 1->" << i;
  }
}

TEST(SiftOptions, CheckDescribeAndFingerprint) {
  // The product default is RootSIFT (every command and the server extract it unless told otherwise).
  SiftOptions options;
  EXPECT_EQ(options.descriptor, DescriptorKind::kRootSift);
  EXPECT_FALSE(options.Check().has_value());
  EXPECT_EQ(options.keypoint_style, KeypointStyle::kVlfeat);
  EXPECT_EQ(options.Describe(),
            "oxbow-sift/1;upsample=1;sigma=1.6;assumed_blur=0.5;intervals=3;contrast=0.034;edge=10;max_features=all;"
            "descriptor=rootsift;peak_ratio=0.8;kernel_radius=4;max_octaves=all;keypoints=vlfeat");
  // FNV-1a 64 of the string above; a change here means stored vocabularies/indexes will refuse the new
  // features, so it must be deliberate.
  EXPECT_EQ(options.Fingerprint(), 13843621742383744156u) << "got " << options.Fingerprint();
  SiftOptions threads = options;
  threads.num_threads = 7;
  EXPECT_EQ(threads.Fingerprint(), options.Fingerprint());
  SiftOptions sift = options;
  sift.descriptor = DescriptorKind::kSift;
  EXPECT_EQ(sift.Fingerprint(), 4792148495956217284u) << "got " << sift.Fingerprint();
  // The cv::SIFT style is described without a `keypoints` field, exactly as every description written
  // before the field existed, so vocabularies and indexes made then keep their fingerprints and meaning.
  // Those descriptions have cv::SIFT's contrast threshold, 0.04.
  SiftOptions opencv = options;
  opencv.keypoint_style = KeypointStyle::kOpenCv;
  opencv.contrast_threshold = 0.04;
  EXPECT_EQ(opencv.Fingerprint(), 15604930684332118585u) << "got " << opencv.Fingerprint();
  for (const SiftOptions& o : {options, sift, opencv}) {
    auto parsed = SiftOptions::FromDescription(o.Describe());
    ASSERT_TRUE(parsed) << parsed.error().ToString();
    EXPECT_EQ(parsed->keypoint_style, o.keypoint_style);
    EXPECT_EQ(parsed->Describe(), o.Describe());
  }
  EXPECT_FALSE(SiftOptions::FromDescription(opencv.Describe() + ";keypoints=opencv"));
  EXPECT_FALSE(SiftOptions::FromDescription(opencv.Describe() + ";keypoints=other"));
  // Upright features are described by an `upright=1` field; off is no field.
  SiftOptions upright = options;
  upright.upright = true;
  EXPECT_EQ(upright.Describe(), options.Describe() + ";upright=1");
  auto parsed_upright = SiftOptions::FromDescription(upright.Describe());
  ASSERT_TRUE(parsed_upright) << parsed_upright.error().ToString();
  EXPECT_TRUE(parsed_upright->upright);
  EXPECT_FALSE(SiftOptions::FromDescription(options.Describe() + ";upright=0"));
  // Refinement in scale: a `refine_scale=1` field; off is no field; the opencv style refuses it.
  SiftOptions in_scale = options;
  in_scale.refine_in_scale = true;
  EXPECT_EQ(in_scale.Describe(), options.Describe() + ";refine_scale=1");
  EXPECT_NE(in_scale.Fingerprint(), options.Fingerprint());
  auto parsed_in_scale = SiftOptions::FromDescription(in_scale.Describe());
  ASSERT_TRUE(parsed_in_scale) << parsed_in_scale.error().ToString();
  EXPECT_TRUE(parsed_in_scale->refine_in_scale);
  EXPECT_FALSE(SiftOptions::FromDescription(options.Describe() + ";refine_scale=0"));
  in_scale.keypoint_style = KeypointStyle::kOpenCv;
  EXPECT_TRUE(in_scale.Check().has_value());
  // The descriptor window is described by `magnification` and `row_step` fields unless it is Lowe's (cells 3
  // wide, every row), the default, which every description made before the fields had: the default
  // description above has neither, and one without them reads back as Lowe's window.
  auto parsed_default = SiftOptions::FromDescription(options.Describe());
  ASSERT_TRUE(parsed_default) << parsed_default.error().ToString();
  EXPECT_EQ(parsed_default->descriptor_magnification, 3.0);
  EXPECT_EQ(parsed_default->descriptor_row_step, 1);
  SiftOptions wide = options;
  wide.descriptor_magnification = 4.5;
  wide.descriptor_row_step = 2;
  EXPECT_EQ(wide.Describe(), options.Describe() + ";magnification=4.5;row_step=2");
  EXPECT_NE(wide.Fingerprint(), options.Fingerprint());
  auto parsed_wide = SiftOptions::FromDescription(wide.Describe());
  ASSERT_TRUE(parsed_wide) << parsed_wide.error().ToString();
  EXPECT_EQ(parsed_wide->descriptor_magnification, 4.5);
  EXPECT_EQ(parsed_wide->descriptor_row_step, 2);
  for (const char* field : {";magnification=3", ";row_step=1", ";magnification=wide", ";row_step=two"})
    EXPECT_FALSE(SiftOptions::FromDescription(options.Describe() + field)) << field;  // not canonical, or not a number
  // The grid sampling is a `sampling=grid` field; the pixel sampling is no field, as in every description
  // made before the field existed. It has no rows to step over.
  SiftOptions grid = options;
  grid.descriptor_sampling = DescriptorSampling::kGrid;
  EXPECT_FALSE(grid.Check().has_value());
  EXPECT_EQ(grid.Describe(), options.Describe() + ";sampling=grid");
  EXPECT_NE(grid.Fingerprint(), options.Fingerprint());
  auto parsed_grid = SiftOptions::FromDescription(grid.Describe());
  ASSERT_TRUE(parsed_grid) << parsed_grid.error().ToString();
  EXPECT_EQ(parsed_grid->descriptor_sampling, DescriptorSampling::kGrid);
  EXPECT_EQ(parsed_default->descriptor_sampling, DescriptorSampling::kPixels);
  for (const char* field : {";sampling=pixels", ";sampling=Grid"})
    EXPECT_FALSE(SiftOptions::FromDescription(options.Describe() + field)) << field;
  grid.descriptor_row_step = 2;
  EXPECT_TRUE(grid.Check().has_value());

  for (auto mutate : std::vector<void (*)(SiftOptions&)>{
           [](SiftOptions& o) { o.sigma = 0; }, [](SiftOptions& o) { o.intervals = 0; },
           [](SiftOptions& o) { o.contrast_threshold = -1; }, [](SiftOptions& o) { o.edge_threshold = 1; },
           [](SiftOptions& o) { o.max_features = 0; }, [](SiftOptions& o) { o.num_threads = -1; },
           [](SiftOptions& o) { o.assumed_blur = 2; }, [](SiftOptions& o) { o.kernel_radius_sigmas = 1; },
           [](SiftOptions& o) { o.thread_cache_mib = -1; }, [](SiftOptions& o) { o.descriptor_magnification = 0.5; },
           [](SiftOptions& o) { o.descriptor_magnification = std::nan(""); },
           [](SiftOptions& o) { o.descriptor_row_step = 0; }, [](SiftOptions& o) { o.descriptor_row_step = 5; }}) {
    SiftOptions bad;
    mutate(bad);
    EXPECT_TRUE(bad.Check().has_value());
    auto created = SiftExtractor::Create(bad);
    ASSERT_FALSE(created);
    EXPECT_EQ(created.error().code, ErrorCode::kInvalidArgument);
  }
}

TEST(SiftExtractor, MaxFeaturesKeepsTheStrongest) {
  const GrayImage image = FromMat(LoadGray(kOpencvData + "box.png"));
  const FeatureSet all = MakeExtractor().Extract(image);
  SiftOptions options;
  options.max_features = 100;
  const FeatureSet best = MakeExtractor(options).Extract(image);
  ASSERT_EQ(best.size(), 100u);
  std::vector<float> responses;
  responses.reserve(all.keypoints.size());
  for (const Keypoint& k : all.keypoints) responses.push_back(k.response);
  std::sort(responses.rbegin(), responses.rend());
  for (const Keypoint& k : best.keypoints) EXPECT_GE(k.response, responses[99]);
}

TEST(SiftExtractor, FromFileMapsDownscaledKeypointsToOriginalCoordinates) {
  const auto extractor = MakeExtractor();
  DecodeOptions decode;
  decode.max_image_side_px = 400;
  auto small = extractor.ExtractFromFile(kOpencvData + "graf1.png", decode);
  ASSERT_TRUE(small) << small.error().ToString();
  EXPECT_EQ(small->image_width, 800);
  EXPECT_EQ(small->image_height, 640);
  auto full = extractor.ExtractFromFile(kOpencvData + "graf1.png");
  ASSERT_TRUE(full);
  // The half-size extraction's keypoints, in original coordinates, should mostly repeat full-size ones.
  const Homography identity = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  const HomographyScore s = ScoreUnderHomography(*small, *full, identity, 3.0);
  EXPECT_GT(static_cast<double>(s.repeated) / s.keypoints_1, 0.6);
  float max_x = 0;
  for (const Keypoint& k : small->keypoints) max_x = std::max(max_x, k.x);
  EXPECT_GT(max_x, 600.0f);

  auto bad = extractor.ExtractFromFile("/nonexistent.png");
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, ErrorCode::kNotFound);
}

}  // namespace
}  // namespace oxbow::sift
