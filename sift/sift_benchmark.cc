// SIFT benchmark: oxbow's extractor vs cv::SIFT (OpenCV) and vl_sift (VLFeat), same images, same
// process, interleaved repetitions. Prints median milliseconds per image, keypoints, repeatability and
// matching score under ground-truth homographies, and peak memory for a 4000x3000 photo.
//
//   build-sift/sift/sift_benchmark [--reps N] [--skip-large] [--quick]   (--quick: graf1, oxbow vs cv::SIFT only)
//
// Timings exclude decoding (every method gets the same decoded grey image). cv::SIFT runs with
// cv::setNumThreads(1) or (2); VLFeat is single-threaded. Paths: opencv-doc samples (always present)
// and ../shared/data (boat, Paris photos) when present.
#include <sys/wait.h>
#include <unistd.h>

#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <numbers>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/testing/feature_eval.h"
#include "sift/image.h"
#include "sift/sift.h"

#ifdef OXBOW_HAVE_VLFEAT
extern "C" {
#include <vl/sift.h>
}
#endif

namespace {

using namespace oxbow::sift;
using Clock = std::chrono::steady_clock;

const std::string kOpencvData = "/usr/share/doc/opencv-doc/examples/data/";
const std::string kShared = OXBOW_SOURCE_DIR "/../shared/data/";

struct Method {
  std::string name;
  std::function<FeatureSet(const cv::Mat& gray8, const GrayImage& gray)> run;
};

FeatureSet Ours(const GrayImage& gray, int threads) {
  SiftOptions options;
  options.num_threads = threads;
  return SiftExtractor::Create(options)->Extract(gray);
}

FeatureSet Opencv(const cv::Mat& gray8, int threads) {
  cv::setNumThreads(threads);
  auto sift = cv::SIFT::create(0, 3, 0.04, 10, 1.6);
  std::vector<cv::KeyPoint> kps;
  cv::Mat desc;
  sift->detectAndCompute(gray8, cv::noArray(), kps, desc);
  FeatureSet f;
  f.image_width = gray8.cols;
  f.image_height = gray8.rows;
  for (int i = 0; i < static_cast<int>(kps.size()); ++i) {
    const cv::KeyPoint& k = kps[static_cast<size_t>(i)];
    f.keypoints.push_back({k.pt.x - 0.25f, k.pt.y - 0.25f, k.size / 2, static_cast<float>(k.angle * std::numbers::pi / 180),
                           k.response, 0});
    cv::Mat row;
    cv::normalize(desc.row(i), row);
    f.descriptors.insert(f.descriptors.end(), row.ptr<float>(0), row.ptr<float>(0) + kDescriptorDim);
  }
  return f;
}

#ifdef OXBOW_HAVE_VLFEAT
FeatureSet Vlfeat(const GrayImage& gray) {
  FeatureSet f;
  f.image_width = gray.width;
  f.image_height = gray.height;
  VlSiftFilt* filter = vl_sift_new(gray.width, gray.height, -1, 3, -1);
  vl_sift_set_peak_thresh(filter, 0.04 / 3);  // the same contrast threshold, image in [0, 1]
  vl_sift_set_edge_thresh(filter, 10);
  int err = vl_sift_process_first_octave(filter, gray.pixels.data());
  float desc[128];
  while (err == VL_ERR_OK) {
    vl_sift_detect(filter);
    const VlSiftKeypoint* kps = vl_sift_get_keypoints(filter);
    const int n = vl_sift_get_nkeypoints(filter);
    for (int i = 0; i < n; ++i) {
      double angles[4];
      const int na = vl_sift_calc_keypoint_orientations(filter, angles, &kps[i]);
      for (int a = 0; a < na; ++a) {
        vl_sift_calc_keypoint_descriptor(filter, desc, &kps[i], angles[a]);
        f.keypoints.push_back({kps[i].x, kps[i].y, kps[i].sigma, static_cast<float>(angles[a]), 0, kps[i].o});
        f.descriptors.insert(f.descriptors.end(), desc, desc + 128);
      }
    }
    err = vl_sift_process_next_octave(filter);
  }
  vl_sift_delete(filter);
  return f;
}
#endif

std::vector<Method> Methods() {
  std::vector<Method> m;
  m.push_back({"oxbow 1T", [](const cv::Mat&, const GrayImage& g) { return Ours(g, 1); }});
  m.push_back({"cv::SIFT 1T", [](const cv::Mat& g8, const GrayImage&) { return Opencv(g8, 1); }});
  m.push_back({"oxbow 2T", [](const cv::Mat&, const GrayImage& g) { return Ours(g, 2); }});
  m.push_back({"cv::SIFT 2T", [](const cv::Mat& g8, const GrayImage&) { return Opencv(g8, 2); }});
#ifdef OXBOW_HAVE_VLFEAT
  m.push_back({"VLFeat 1T", [](const cv::Mat&, const GrayImage& g) { return Vlfeat(g); }});
#endif
  return m;
}

double CpuMs() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec / 1e6;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : (v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]));
}

GrayImage ToGray(const cv::Mat& m) { return GrayFromBytes(m.ptr<uint8_t>(0), m.cols, m.rows, m.step[0]); }

// Peak resident memory added by running `fn` once, measured in a forked child (VmHWM - VmRSS at start).
long PeakExtraMiB(const std::function<void()>& fn) {
  auto read_kib = [](const char* key) {
    std::ifstream in("/proc/self/status");
    std::string line;
    while (std::getline(in, line))
      if (line.rfind(key, 0) == 0) return std::atol(line.c_str() + std::strlen(key));
    return 0L;
  };
  int pipe_fds[2];
  if (::pipe(pipe_fds) != 0) return -1;
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::close(pipe_fds[0]);
    // Reset the high-water mark to the current RSS (Linux >= 4.0: write 5 to clear_refs).
    { std::ofstream("/proc/self/clear_refs") << "5"; }
    const long start = read_kib("VmRSS:");
    fn();
    const long peak = read_kib("VmHWM:");
    const long extra = (peak - start) / 1024;
    if (::write(pipe_fds[1], &extra, sizeof extra) != sizeof extra) _exit(1);
    _exit(0);
  }
  ::close(pipe_fds[1]);
  long extra = -1;
  if (::read(pipe_fds[0], &extra, sizeof extra) != sizeof extra) extra = -1;
  ::close(pipe_fds[0]);
  int status = 0;
  ::waitpid(pid, &status, 0);
  return extra;
}

}  // namespace

int main(int argc, char** argv) {
  int reps = 5;
  bool skip_large = false, quick = false;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--reps") && i + 1 < argc) reps = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--skip-large")) skip_large = true;
    else if (!std::strcmp(argv[i], "--quick")) quick = skip_large = true;
    else {
      std::fprintf(stderr, "usage: %s [--reps N] [--skip-large] [--quick]\n", argv[0]);
      return 2;
    }
  }
  struct Image {
    std::string name, path;
  };
  std::vector<Image> images = {{"graf1 800x640", kOpencvData + "graf1.png"}, {"graf3 800x640", kOpencvData + "graf3.png"}};
  const std::string boat = kShared + "oxford_affine/images/boat/";
  if (std::filesystem::exists(boat + "img1.pgm")) images.push_back({"boat1 850x680", boat + "img1.pgm"});
  const std::string paris = kShared + "paris6k/images/";
  for (const std::string p : {"paris_defense_000000.jpg", "paris_eiffel_000059.jpg", "paris_louvre_000081.jpg"})
    if (std::filesystem::exists(paris + p)) images.push_back({p.substr(6, p.size() - 10), paris + p});

  std::vector<Method> methods = Methods();
  if (quick) {  // graf1 only, oxbow and cv::SIFT only, no quality table
    images.resize(1);
    methods.resize(4);
  }
  std::printf("SIFT benchmark: %d interleaved repetitions, median ms per image (decode excluded)\n\n", reps);
  std::printf("Per method: median wall ms, median process CPU ms (robust to other load for 1T runs), keypoints.\n");
  std::printf("Ratios ours/cv: 1T wall, 1T CPU | 2T wall.\n\n%-22s", "image");
  for (const Method& m : methods) std::printf(" | %-22s", m.name.c_str());
  std::printf(" | ours/cv 1T  | 2T\n");
  std::map<std::string, std::vector<double>> all_ratios;
  for (const Image& image : images) {
    const cv::Mat gray8 = cv::imread(image.path, cv::IMREAD_GRAYSCALE);
    if (gray8.empty()) continue;
    const GrayImage gray = ToGray(gray8);
    std::vector<std::vector<double>> ms(methods.size()), cpu(methods.size());
    std::vector<size_t> keypoints(methods.size());
    for (int r = 0; r < reps; ++r)
      for (size_t m = 0; m < methods.size(); ++m) {
        const auto start = Clock::now();
        const double cpu_start = CpuMs();
        const FeatureSet f = methods[m].run(gray8, gray);
        ms[m].push_back(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
        cpu[m].push_back(CpuMs() - cpu_start);
        keypoints[m] = f.size();
      }
    std::printf("%-22s", image.name.c_str());
    for (size_t m = 0; m < methods.size(); ++m) std::printf(" | %7.1f %7.1f %6zu", Median(ms[m]), Median(cpu[m]), keypoints[m]);
    std::printf(" | %5.2f %5.2f | %5.2f\n", Median(ms[0]) / Median(ms[1]), Median(cpu[0]) / Median(cpu[1]),
                Median(ms[2]) / Median(ms[3]));
  }

  // Quality under ground-truth homographies (3 px, ratio 0.8, scale within 1.5x, one-to-one).
  struct Pair {
    std::string name, a, b, h;
  };
  std::vector<Pair> pairs;
  if (!quick) pairs = {{"graf 1->3", kOpencvData + "graf1.png", kOpencvData + "graf3.png", kOpencvData + "H1to3p.xml"}};
  const std::string gt = kShared + "oxford_affine/gt/boat/";
  if (!quick && std::filesystem::exists(boat + "img1.pgm"))
    for (int i = 2; i <= 6; ++i)
      pairs.push_back({"boat 1->" + std::to_string(i), boat + "img1.pgm", boat + "img" + std::to_string(i) + ".pgm",
                       gt + "H1to" + std::to_string(i) + "p"});
  std::printf("\nRepeatability / matching score (3 px, Lowe ratio 0.8, scales within 1.5x, one-to-one):\n%-12s", "pair");
  for (const Method& m : methods)
    if (m.name.find("2T") == std::string::npos) std::printf(" | %-13s", m.name.c_str());
  std::printf("\n");
  for (const Pair& p : pairs) {
    const cv::Mat a8 = cv::imread(p.a, cv::IMREAD_GRAYSCALE), b8 = cv::imread(p.b, cv::IMREAD_GRAYSCALE);
    auto h = ReadHomography(p.h);
    if (a8.empty() || b8.empty() || !h) continue;
    std::printf("%-12s", p.name.c_str());
    for (const Method& m : methods) {
      if (m.name.find("2T") != std::string::npos) continue;
      const HomographyScore s = ScoreUnderHomography(m.run(a8, ToGray(a8)), m.run(b8, ToGray(b8)), *h);
      std::printf(" | %.3f / %.3f", s.repeatability, s.matching_score);
    }
    std::printf("\n");
  }

  if (!skip_large) {
    // A 4000x3000 photo: a Paris (or opencv-doc) photo upscaled.
    std::string source = paris + "paris_defense_000000.jpg";
    if (!std::filesystem::exists(source)) source = kOpencvData + "building.jpg";
    cv::Mat small = cv::imread(source, cv::IMREAD_GRAYSCALE), large;
    cv::resize(small, large, cv::Size(4000, 3000), 0, 0, cv::INTER_CUBIC);
    const GrayImage large_gray = ToGray(large);
    std::printf("\n4000x3000 photo (%s upscaled): one run each, time and peak extra resident memory\n", source.c_str());
    for (const Method& m : methods) {
      const auto start = Clock::now();
      size_t n = 0;
      const long mib = PeakExtraMiB([&] { n = m.run(large, large_gray).size(); });
      const double total = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
      std::printf("  %-12s %8.0f ms (incl. fork)  peak +%ld MiB\n", m.name.c_str(), total, mib);
      (void)n;
    }
  }
  return 0;
}
