// Helpers shared by the `oxbow index ...` and `oxbow query` commands (index_command.cc,
// query_command.cc): rebuilding the extractor an index was made with, timed decode + extract, and
// listing image files.
#pragma once

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <sstream>
#include <string>
#include <vector>

#include "sift/error.h"
#include "sift/image.h"
#include "sift/sift.h"

namespace oxbow::cli {

struct TimedFeatures {
  sift::FeatureSet features;
  double decode_ms = 0;
  double extract_ms = 0;
};

// ExtractFromFile, with the decode and extraction stages timed separately.
inline Result<TimedFeatures> ExtractTimed(const sift::SiftExtractor& extractor, const std::string& path,
                                          const sift::DecodeOptions& decode) {
  using Clock = std::chrono::steady_clock;
  auto t0 = Clock::now();
  auto decoded = sift::ReadImage(path, decode);
  if (!decoded) return std::unexpected(decoded.error());
  TimedFeatures out;
  out.decode_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  t0 = Clock::now();
  out.features = extractor.Extract(decoded->gray);
  const double s = decoded->scale_to_original;
  if (s != 1.0) {
    for (sift::Keypoint& kp : out.features.keypoints) {
      kp.x = static_cast<float>(sift::GrayToOriginal(kp.x, s));
      kp.y = static_cast<float>(sift::GrayToOriginal(kp.y, s));
      kp.scale = static_cast<float>(kp.scale * s);
    }
  }
  out.features.image_width = decoded->original_width;
  out.features.image_height = decoded->original_height;
  out.extract_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  return out;
}

inline bool IsImageFile(const std::filesystem::path& p) {
  std::string ext = p.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  for (const char* e : {".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".pnm", ".bmp", ".tif", ".tiff", ".webp"}) {
    if (ext == e) return true;
  }
  return false;
}

}  // namespace oxbow::cli
