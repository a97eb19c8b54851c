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

// Parses sift::SiftOptions::Describe() text back into options ("oxbow-sift/1;upsample=1;sigma=1.6;...").
// The result must describe itself identically, else kIncompatible (settings from another version).
inline Result<sift::SiftOptions> SiftOptionsFromSettings(const std::string& settings) {
  sift::SiftOptions o;
  std::stringstream in(settings);
  std::string item;
  bool first = true;
  try {
    while (std::getline(in, item, ';')) {
      if (first) {
        if (item != "oxbow-sift/1") break;
        first = false;
        continue;
      }
      const size_t eq = item.find('=');
      if (eq == std::string::npos) continue;
      const std::string key = item.substr(0, eq), value = item.substr(eq + 1);
      if (key == "upsample") o.upsample_first_octave = value == "1";
      else if (key == "sigma") o.sigma = std::stod(value);
      else if (key == "assumed_blur") o.assumed_blur = std::stod(value);
      else if (key == "intervals") o.intervals = std::stoi(value);
      else if (key == "contrast") o.contrast_threshold = std::stod(value);
      else if (key == "edge") o.edge_threshold = std::stod(value);
      else if (key == "max_features") o.max_features = value == "all" ? std::nullopt : std::optional<int>(std::stoi(value));
      else if (key == "descriptor") o.descriptor = value == "rootsift" ? sift::DescriptorKind::kRootSift : sift::DescriptorKind::kSift;
      else if (key == "peak_ratio") o.orientation_peak_ratio = std::stod(value);
      else if (key == "kernel_radius") o.kernel_radius_sigmas = std::stod(value);
      else if (key == "max_octaves") o.max_octaves = value == "all" ? std::nullopt : std::optional<int>(std::stoi(value));
    }
  } catch (const std::exception&) {
    return Fail(ErrorCode::kIncompatible, "unreadable extractor settings '" + settings + "'");
  }
  if (o.Describe() != settings) {
    return Fail(ErrorCode::kIncompatible, "extractor settings '" + settings +
                                              "' are not those of this build's SIFT ('" + o.Describe() + "')");
  }
  return o;
}

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
