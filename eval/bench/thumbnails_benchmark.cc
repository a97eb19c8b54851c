// What a thumbnail costs an add: MakeThumbnail (colour decode at a reduced scale, area resize, JPEG
// encode) against the add's own decode + SIFT extraction, on the same photos, interleaved, one thread.
// Also the stored size per thumbnail and the cost of serving a smaller size made from the stored one.
//
//   thumbnails_benchmark [--list FILE | --dir DIR] [--max N] [--side 512] [--quality 80]
// Default: the Paris images of ../shared/data when present, else the opencv-doc photos.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "api/thumbnails.h"
#include "sift/sift.h"
#include "tests/support/samples.h"

namespace {

using Clock = std::chrono::steady_clock;

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

double Ms(Clock::time_point start) { return std::chrono::duration<double, std::milli>(Clock::now() - start).count(); }

}  // namespace

int main(int argc, char** argv) {
  using namespace oxbow;
  std::string list, dir;
  size_t max_images = 60;
  int side = 512, quality = 80;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i];
    if (flag == "--list") list = argv[i + 1];
    else if (flag == "--dir") dir = argv[i + 1];
    else if (flag == "--max") max_images = std::stoul(argv[i + 1]);
    else if (flag == "--side") side = std::stoi(argv[i + 1]);
    else if (flag == "--quality") quality = std::stoi(argv[i + 1]);
    else {
      std::fprintf(stderr, "unknown flag %s\n", flag.c_str());
      return 2;
    }
  }
  std::vector<std::string> paths;
  if (!list.empty()) {
    std::ifstream in(list);
    for (std::string line; std::getline(in, line);) if (!line.empty()) paths.push_back(line);
  } else {
    if (dir.empty()) {
      const std::string paris = std::string(OXBOW_SOURCE_DIR) + "/../shared/data/paris6k/images";
      dir = std::filesystem::exists(paris) ? paris : testing::kSampleDir;
    }
    for (const auto& e : std::filesystem::directory_iterator(dir)) {
      const auto ext = e.path().extension().string();
      if (ext == ".jpg" || ext == ".png") paths.push_back(e.path().string());
    }
    std::sort(paths.begin(), paths.end());
  }
  if (paths.size() > max_images) paths.resize(max_images);

  sift::SiftOptions options;  // the server's default extractor (RootSIFT as oxbow vocab train --root-sift)
  options.descriptor = sift::DescriptorKind::kRootSift;
  options.num_threads = 1;
  auto extractor = sift::SiftExtractor::Create(options);
  if (!extractor) return 1;
  sift::DecodeOptions decode;
  decode.max_image_side_px = 1600;  // oxbow serve's default

  std::vector<double> extract_ms, thumb_ms, resize_ms, bytes, pixels;
  for (const auto& path : paths) {
    const auto image = testing::ReadBytes(path);
    auto start = Clock::now();
    auto features = extractor->ExtractFromBytes(image, decode);
    extract_ms.push_back(Ms(start));
    if (!features) continue;
    start = Clock::now();
    auto thumb = api::MakeThumbnail(image, side, quality, decode);
    thumb_ms.push_back(Ms(start));
    if (!thumb) continue;
    bytes.push_back(static_cast<double>(thumb->jpeg.size()));
    pixels.push_back(static_cast<double>(features->image_width) * features->image_height / 1e6);
    start = Clock::now();
    auto smaller = api::MakeThumbnail({reinterpret_cast<const uint8_t*>(thumb->jpeg.data()), thumb->jpeg.size()},
                                      256, quality, decode);
    resize_ms.push_back(Ms(start));
  }
  double total_bytes = 0;
  for (double b : bytes) total_bytes += b;
  std::printf("%zu images (median %.2f MP) from %s; thumbnails: longest side %d, quality %d; 1 thread\n",
              thumb_ms.size(), Median(pixels), list.empty() ? dir.c_str() : list.c_str(), side, quality);
  std::printf("| step | median ms |\n|---|---:|\n");
  std::printf("| decode + extract (the add's work) | %.1f |\n", Median(extract_ms));
  std::printf("| MakeThumbnail %d px (added to each add) | %.1f |\n", side, Median(thumb_ms));
  std::printf("| %d -> 256 px (GET .../thumbnail?size=256) | %.1f |\n", side, Median(resize_ms));
  std::printf("thumbnail overhead per add: %.1f%% of decode + extract\n", 100 * Median(thumb_ms) / Median(extract_ms));
  std::printf("stored thumbnail: median %.1f KB, mean %.1f KB\n", Median(bytes) / 1024, total_bytes / bytes.size() / 1024);
  return 0;
}
