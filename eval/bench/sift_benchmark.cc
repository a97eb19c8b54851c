// SIFT benchmark: oxbow's extractor vs cv::SIFT (OpenCV) and vl_sift (VLFeat), same images, same
// process, interleaved repetitions. Prints median milliseconds per image, keypoints, repeatability and
// matching score under ground-truth homographies (raw SIFT, and RootSIFT applied to every side alike), and
// peak memory for a 4000x3000 photo.
//
//   build/eval/bench/sift_benchmark [--reps N] [--skip-large] [--quick] [--quality] [--processes]
//                                   [--descriptor-sampling grid|pixels]
//     --quick: graf1 only, oxbow vs cv::SIFT only, no quality table.
//     --descriptor-sampling: where oxbow's timed descriptors take their gradients (SiftOptions::
//     descriptor_sampling; pixels, the default, by default). The quality tables show both.
//     --quality: the quality tables only (no timing).
//     --processes: every method runs its repetitions of an image in a process of its own (forked from
//     this one before any extraction), so no method inherits another's allocator and page state.
//
// Both sides are timed alike: every method starts from the same decoded 8-bit image, and its timer
// includes its conversion to float (oxbow and VLFeat here, cv::SIFT inside detectAndCompute). Thread
// settings (cv::setNumThreads, and a parallel loop that wakes OpenCV's pool) are applied before the
// timer starts. Each side is measured in two states:
//   cold  each repetition on a newly started thread with a newly created extractor: oxbow's per-thread
//         pyramid cache starts empty, cv::SIFT allocates its pyramid as always;
//   warm  repetitions on one thread with one extractor: oxbow keeps its pyramid buffers between images
//         (SiftOptions::thread_cache_mib, the default), cv::SIFT has no such cache and allocates anew.
// Both sides run under one allocator policy, set first thing in main: blocks up to 32 MiB come from the
// heap and freed memory stays with the process (glibc's mallopt). Left to glibc's adaptive thresholds,
// what cv::SIFT frees after one image goes back to the kernel or not depending on the sizes freed before
// it, and its warm runs on 1024-pixel photos paid fresh zeroed pages on every run (2-4x its time with
// memory kept) while on 800x640 ones they did not.
// VLFeat is single-threaded and measured cold only. Paths: opencv-doc samples (always present) and
// ../shared/data (boat, Paris photos) when present. Every side uses cv::SIFT's contrast threshold (0.04).
#include <sys/wait.h>
#include <unistd.h>
#ifdef __GLIBC__
#include <malloc.h>
#endif

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
#include <thread>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/image.h"
#include "sift/sift.h"
#include "tests/support/feature_eval.h"

#ifdef OXBOW_HAVE_VLFEAT
extern "C" {
#include <vl/sift.h>
}
#endif

namespace {

using namespace oxbow::sift;
using Clock = std::chrono::steady_clock;

// Every side extracts with cv::SIFT's contrast threshold (oxbow's default is lower, 0.034), so the
// three find keypoints under the same rule.
constexpr double kPeerContrast = 0.04;

// Where oxbow's timed descriptors take their gradients (--descriptor-sampling); the quality tables show both.
DescriptorSampling g_sampling = DescriptorSampling::kPixels;

const std::string kOpencvData = "/usr/share/doc/opencv-doc/examples/data/";
const std::string kShared = OXBOW_SOURCE_DIR "/../shared/data/";

enum class Side { kOxbow, kOpencv, kVlfeat };

struct Method {
  std::string name;
  Side side;
  int threads;
  bool cold;
};

// Converts inside the caller's timer, as cv::SIFT converts inside its own.
GrayImage ToGray(const cv::Mat& m) { return GrayFromBytes(m.ptr<uint8_t>(0), m.cols, m.rows, m.step[0]); }

FeatureSet FromOpencv(const cv::Mat& gray8, const std::vector<cv::KeyPoint>& kps, const cv::Mat& desc) {
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
FeatureSet Vlfeat(const cv::Mat& gray8) {
  const GrayImage gray = ToGray(gray8);
  FeatureSet f;
  f.image_width = gray.width;
  f.image_height = gray.height;
  VlSiftFilt* filter = vl_sift_new(gray.width, gray.height, -1, 3, -1);
  vl_sift_set_peak_thresh(filter, kPeerContrast / 3);  // the same contrast threshold, image in [0, 1]
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

// Extractors of the warm methods, created once (outside every timer) and reused.
class Extractors {
 public:
  const SiftExtractor& Oxbow(int threads) {
    auto it = oxbow_.find(threads);
    if (it == oxbow_.end()) it = oxbow_.emplace(threads, NewOxbow(threads)).first;
    return it->second;
  }
  cv::SIFT& Opencv() {
    if (!opencv_) opencv_ = NewOpencv();
    return *opencv_;
  }
  static SiftExtractor NewOxbow(int threads) {
    SiftOptions options;
    options.num_threads = threads;
    options.contrast_threshold = kPeerContrast;
    options.descriptor_sampling = g_sampling;
    return *SiftExtractor::Create(options);
  }
  static cv::Ptr<cv::SIFT> NewOpencv() { return cv::SIFT::create(0, 3, kPeerContrast, 10, 1.6); }

 private:
  std::map<int, SiftExtractor> oxbow_;
  cv::Ptr<cv::SIFT> opencv_;
};

// The timed part of a method: conversion and extraction, with the extractor created inside when cold.
FeatureSet Extract(const Method& m, const cv::Mat& gray8, Extractors& warm) {
  switch (m.side) {
    case Side::kOxbow: {
      if (m.cold) return Extractors::NewOxbow(m.threads).Extract(ToGray(gray8));
      return warm.Oxbow(m.threads).Extract(ToGray(gray8));
    }
    case Side::kOpencv: {
      const cv::Ptr<cv::SIFT> fresh = m.cold ? Extractors::NewOpencv() : nullptr;
      std::vector<cv::KeyPoint> kps;
      cv::Mat desc;
      (m.cold ? *fresh : warm.Opencv()).detectAndCompute(gray8, cv::noArray(), kps, desc);
      return FromOpencv(gray8, kps, desc);
    }
    case Side::kVlfeat:
#ifdef OXBOW_HAVE_VLFEAT
      return Vlfeat(gray8);
#endif
      break;
  }
  return {};
}

// Untimed set-up before each timed run: OpenCV's thread count, and one parallel loop so that OpenCV's
// pool has its threads before the timer starts.
void PrepareThreads(const Method& m) {
  if (m.side != Side::kOpencv) return;
  cv::setNumThreads(m.threads);
  cv::parallel_for_(cv::Range(0, 4 * m.threads), [](const cv::Range&) {});
}

std::vector<Method> Methods() {
  std::vector<Method> m;
  for (const int threads : {1, 2}) {
    for (const bool cold : {true, false}) {
      m.push_back({"oxbow", Side::kOxbow, threads, cold});
      m.push_back({"cv::SIFT", Side::kOpencv, threads, cold});
    }
  }
#ifdef OXBOW_HAVE_VLFEAT
  m.push_back({"VLFeat", Side::kVlfeat, 1, true});
#endif
  return m;
}

std::string Label(const Method& m) { return m.name + " " + std::to_string(m.threads) + "T " + (m.cold ? "cold" : "warm"); }

struct Sample {
  double wall_ms = 0, cpu_ms = 0;
  size_t keypoints = 0;
};

double CpuMs() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec / 1e6;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : (v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]));
}

// Runs fn in a forked child and returns what it returned (empty if the child failed).
std::vector<double> InChild(const std::function<std::vector<double>()>& fn) {
  int pipe_fds[2];
  if (::pipe(pipe_fds) != 0) return {};
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::close(pipe_fds[0]);
#ifdef __GLIBC__
    // The parent keeps the memory it freed (the policy above); hand it back so that the child starts
    // from its live memory only, and no side reuses pages inherited from the parent's runs.
    malloc_trim(0);
#endif
    const std::vector<double> values = fn();
    const size_t n = values.size();
    const auto bytes = static_cast<ssize_t>(n * sizeof(double));
    if (::write(pipe_fds[1], &n, sizeof n) != sizeof n || ::write(pipe_fds[1], values.data(), n * sizeof(double)) != bytes) _exit(1);
    _exit(0);
  }
  ::close(pipe_fds[1]);
  size_t n = 0;
  std::vector<double> values;
  if (::read(pipe_fds[0], &n, sizeof n) == sizeof n && n < (1u << 20)) {
    values.resize(n);
    if (::read(pipe_fds[0], values.data(), n * sizeof(double)) != static_cast<ssize_t>(n * sizeof(double))) values.clear();
  }
  ::close(pipe_fds[0]);
  int status = 0;
  ::waitpid(pid, &status, 0);
  return values;
}

long ReadStatusKib(const char* key) {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind(key, 0) == 0) return std::atol(line.c_str() + std::strlen(key));
  return 0L;
}

// One timed run of m (a cold run on a newly started thread). Thread set-up happens before the timer.
Sample TimeOne(const Method& m, const cv::Mat& gray8, Extractors& warm) {
  PrepareThreads(m);
  Sample s;
  auto body = [&] {
    const auto start = Clock::now();
    const double cpu_start = CpuMs();
    const FeatureSet f = Extract(m, gray8, warm);
    s.wall_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
    s.cpu_ms = CpuMs() - cpu_start;
    s.keypoints = f.size();
  };
  if (m.cold) {
    std::thread(body).join();
  } else {
    body();
  }
  return s;
}

}  // namespace

int main(int argc, char** argv) {
#ifdef __GLIBC__
  // The allocator policy of both sides (top of file): 32 MiB is the largest mapping threshold glibc takes.
  mallopt(M_MMAP_THRESHOLD, 32 << 20);
  mallopt(M_TRIM_THRESHOLD, 1 << 30);
#endif
  int reps = 5;
  bool skip_large = false, quick = false, quality_only = false, processes = false;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--reps") && i + 1 < argc) reps = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--skip-large")) skip_large = true;
    else if (!std::strcmp(argv[i], "--quick")) quick = skip_large = true;
    else if (!std::strcmp(argv[i], "--quality")) quality_only = skip_large = true;
    else if (!std::strcmp(argv[i], "--processes")) processes = true;
    else if (!std::strcmp(argv[i], "--descriptor-sampling") && i + 1 < argc && (!std::strcmp(argv[i + 1], "grid") || !std::strcmp(argv[i + 1], "pixels")))
      g_sampling = !std::strcmp(argv[++i], "grid") ? DescriptorSampling::kGrid : DescriptorSampling::kPixels;
    else {
      std::fprintf(stderr, "usage: %s [--reps N] [--skip-large] [--quick] [--quality] [--processes] [--descriptor-sampling grid|pixels]\n", argv[0]);
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
    std::erase_if(methods, [](const Method& m) { return m.side == Side::kVlfeat; });
  }
  if (quality_only) images.clear();
  Extractors warm;
  if (!images.empty()) {
    std::printf("SIFT benchmark: %d repetitions, %s; median ms per image from the decoded 8-bit image;\n"
                "oxbow's descriptors sampled at the %s\n", reps,
                processes ? "each method's repetitions in a process of its own" : "methods interleaved in one process",
                g_sampling == DescriptorSampling::kGrid ? "grid" : "pixels");
    std::printf("(conversion to float inside every timer; cold = new thread and new extractor per run, warm = one of each;\n"
                " blocks up to 32 MiB from the heap and freed memory kept by the process, for every side)\n\n");
    std::printf("| image | peer | threads | state | oxbow wall ms | peer wall ms | ours/peer wall | oxbow CPU ms | peer CPU ms "
                "| ours/peer CPU | keypoints ours / peer |\n");
    std::printf("|---|---|---:|---|---:|---:|---:|---:|---:|---:|---|\n");
  }
  for (const Image& image : images) {
    const cv::Mat gray8 = cv::imread(image.path, cv::IMREAD_GRAYSCALE);
    if (gray8.empty()) continue;
    std::vector<std::vector<Sample>> samples(methods.size());
    if (processes) {
      for (size_t m = 0; m < methods.size(); ++m) {
        const std::vector<double> flat = InChild([&] {
          std::vector<double> out;
          for (int r = 0; r < reps; ++r) {
            const Sample s = TimeOne(methods[m], gray8, warm);
            out.insert(out.end(), {s.wall_ms, s.cpu_ms, static_cast<double>(s.keypoints)});
          }
          return out;
        });
        for (size_t i = 0; i + 2 < flat.size(); i += 3) {
          samples[m].push_back({flat[i], flat[i + 1], static_cast<size_t>(flat[i + 2])});
        }
      }
    } else {
      for (int r = 0; r < reps; ++r) {
        for (size_t k = 0; k < methods.size(); ++k) {
          const size_t m = (k + static_cast<size_t>(r)) % methods.size();  // rotate who runs first
          samples[m].push_back(TimeOne(methods[m], gray8, warm));
        }
      }
    }
    auto median = [&](size_t m, double Sample::*field) {
      std::vector<double> v;
      for (const Sample& s : samples[m]) v.push_back(s.*field);
      return Median(v);
    };
    for (size_t p = 0; p < methods.size(); ++p) {
      if (methods[p].side == Side::kOxbow) continue;
      size_t o = 0;  // oxbow in the same threads and state
      while (methods[o].side != Side::kOxbow || methods[o].threads != methods[p].threads || methods[o].cold != methods[p].cold) ++o;
      if (samples[o].empty() || samples[p].empty()) continue;
      const double ow = median(o, &Sample::wall_ms), pw = median(p, &Sample::wall_ms);
      const double oc = median(o, &Sample::cpu_ms), pc = median(p, &Sample::cpu_ms);
      std::printf("| %s | %s | %d | %s | %.1f | %.1f | %.2f | %.1f | %.1f | %.2f | %zu / %zu |\n", image.name.c_str(),
                  methods[p].name.c_str(), methods[p].threads, methods[p].cold ? "cold" : "warm", ow, pw, ow / pw, oc, pc,
                  oc / pc, samples[o].back().keypoints, samples[p].back().keypoints);
    }
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
  // Every extractor's raw SIFT descriptors, scored as they are and with RootSIFT applied to all of them
  // alike (L1 normalise, square root), so that no side gains from its descriptor form.
  struct QualityMethod {
    std::string name;
    std::function<FeatureSet(const cv::Mat&)> extract;
  };
  auto oxbow_raw = [](KeypointStyle style, double magnification, int row_step,
                      DescriptorSampling sampling = DescriptorSampling::kPixels) {
    SiftOptions options;
    options.descriptor_sampling = sampling;
    options.descriptor = DescriptorKind::kSift;
    options.keypoint_style = style;
    options.contrast_threshold = kPeerContrast;
    options.descriptor_magnification = magnification;
    options.descriptor_row_step = row_step;
    return [extractor = *SiftExtractor::Create(options)](const cv::Mat& m) { return extractor.Extract(ToGray(m)); };
  };
  // oxbow's defaults, its descriptor with cells 4 scales wide and every second row sampled, its grid
  // sampling with cells 3 and 4 scales wide, and the cv::SIFT style.
  const SiftOptions defaults;
  std::vector<QualityMethod> quality = {
      {"oxbow", oxbow_raw(defaults.keypoint_style, defaults.descriptor_magnification, defaults.descriptor_row_step)},
      {"oxbow, cells 4 wide, every 2nd row", oxbow_raw(defaults.keypoint_style, 4, 2)},
      {"oxbow, grid", oxbow_raw(defaults.keypoint_style, 3, 1, DescriptorSampling::kGrid)},
      {"oxbow, grid, cells 4 wide", oxbow_raw(defaults.keypoint_style, 4, 1, DescriptorSampling::kGrid)},
      {"oxbow cv-style", oxbow_raw(KeypointStyle::kOpenCv, 3, 1)},
                                        {"cv::SIFT", [&](const cv::Mat& m) { return Extract({"cv::SIFT", Side::kOpencv, 1, true}, m, warm); }}};
#ifdef OXBOW_HAVE_VLFEAT
  quality.push_back({"VLFeat", [&](const cv::Mat& m) { return Extract({"VLFeat", Side::kVlfeat, 1, true}, m, warm); }});
#endif
  auto root_sift = [](FeatureSet f) {
    for (size_t i = 0; i < f.size(); ++i) ToRootSift(std::span<float>(f.descriptors.data() + i * kDescriptorDim, kDescriptorDim));
    f.kind = DescriptorKind::kRootSift;
    return f;
  };
  std::vector<std::vector<std::string>> cells[2];  // [raw, rootsift][pair][method]
  std::vector<std::string> pair_names;
  for (const Pair& p : pairs) {
    const cv::Mat a8 = cv::imread(p.a, cv::IMREAD_GRAYSCALE), b8 = cv::imread(p.b, cv::IMREAD_GRAYSCALE);
    auto h = ReadHomography(p.h);
    if (a8.empty() || b8.empty() || !h) continue;
    pair_names.push_back(p.name);
    for (auto& c : cells) c.emplace_back();
    cv::setNumThreads(1);
    for (const QualityMethod& m : quality) {
      const FeatureSet fa = m.extract(a8), fb = m.extract(b8);
      for (int form = 0; form < 2; ++form) {
        const HomographyScore s = form == 0 ? ScoreUnderHomography(fa, fb, *h) : ScoreUnderHomography(root_sift(fa), root_sift(fb), *h);
        char text[96];
        std::snprintf(text, sizeof text, "%.3f / %.3f / %d", s.repeatability, s.matching_score, s.correct_matches);
        cells[form].back().emplace_back(text);
      }
    }
  }
  for (int form = 0; form < 2; ++form) {
    std::printf("\nRepeatability / matching score / correct matches (3 px, Lowe ratio 0.8, scales within 1.5x, one-to-one), "
                "%s descriptors:\n| pair |", form == 0 ? "raw SIFT" : "RootSIFT (applied to every side)");
    for (const QualityMethod& m : quality) std::printf(" %s |", m.name.c_str());
    std::printf("\n|---|");
    for (size_t m = 0; m < quality.size(); ++m) std::printf("---|");
    std::printf("\n");
    for (size_t i = 0; i < pair_names.size(); ++i) {
      std::printf("| %s |", pair_names[i].c_str());
      for (const std::string& c : cells[form][i]) std::printf(" %s |", c.c_str());
      std::printf("\n");
    }
  }

  if (!skip_large) {
    // A 4000x3000 photo: a Paris (or opencv-doc) photo upscaled.
    std::string source = paris + "paris_defense_000000.jpg";
    if (!std::filesystem::exists(source)) source = kOpencvData + "building.jpg";
    cv::Mat small = cv::imread(source, cv::IMREAD_GRAYSCALE), large;
    cv::resize(small, large, cv::Size(4000, 3000), 0, 0, cv::INTER_CUBIC);
    std::printf("\n4000x3000 photo (%s upscaled): one cold run each in a process of its own, time and peak extra "
                "resident memory\n", source.c_str());
    for (const Method& m : methods) {
      if (!m.cold) continue;
      const std::vector<double> r = InChild([&] {
        // Reset the high-water mark to the current RSS (Linux >= 4.0: write 5 to clear_refs).
        { std::ofstream("/proc/self/clear_refs") << "5"; }
        const long start = ReadStatusKib("VmRSS:");
        const Sample s = TimeOne(m, large, warm);
        return std::vector<double>{s.wall_ms, static_cast<double>(ReadStatusKib("VmHWM:") - start) / 1024};
      });
      if (r.size() == 2) std::printf("  %-18s %8.0f ms  peak +%.0f MiB\n", Label(m).c_str(), r[0], r[1]);
    }
  }
  return 0;
}
