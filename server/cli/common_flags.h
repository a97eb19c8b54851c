// Flags and helpers that several `oxbow` commands share, so that each concept has one flag name, one
// meaning and one default in every command (the defaults are the library options' in-class defaults):
//
//   --max-image-side PX   downscale decoded images so the longest side is at most PX (0 = no limit);
//                         default sift::DecodeOptions::max_image_side_px (1600)
//   --max-megapixels MP   refuse images whose header declares more pixels (before decoding); default
//                         sift::DecodeOptions::max_pixels (40)
//   --descriptor KIND     rootsift (default, sift::SiftOptions::descriptor) or sift; only where features
//                         are created from scratch (extract, vocab train, match): an index or a vocabulary
//                         fixes the descriptor of everything added to it
//   --threads N           CPU threads the command computes with, in total (0 = all cores); results never
//                         depend on it (SplitThreads decides between images and inside one image)
#pragma once

#include <CLI/CLI.hpp>

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <optional>
#include <string>
#include <vector>

#include "server/cli/cli.h"
#include "sift/base/error.h"
#include "sift/base/parallel.h"
#include "sift/image.h"
#include "sift/sift.h"

namespace oxbow::cli {

// --max-image-side and --max-megapixels.
struct ImageFlags {
  int max_image_side_px = sift::DecodeOptions{}.max_image_side_px.value_or(0);
  double max_megapixels = static_cast<double>(sift::DecodeOptions{}.max_pixels) / 1e6;

  // The decode options these flags ask for (CommandError exit 2 for values out of range).
  sift::DecodeOptions ToDecodeOptions() const {
    if (!(max_megapixels > 0 && max_megapixels <= 10000)) throw CommandError(2, "--max-megapixels must be in (0, 10000]");
    if (max_image_side_px != 0 && max_image_side_px < 16)
      throw CommandError(2, "--max-image-side must be 0 (no limit) or at least 16");
    sift::DecodeOptions decode;
    decode.max_pixels = static_cast<uint64_t>(max_megapixels * 1e6);
    decode.max_image_side_px = max_image_side_px > 0 ? std::optional<int>(max_image_side_px) : std::nullopt;
    return decode;
  }
};

inline void AddImageFlags(CLI::App* cmd, ImageFlags* flags) {
  cmd->add_option("--max-image-side", flags->max_image_side_px,
                  "downscale images so the longest side is at most PX pixels before extraction (keypoints are still "
                  "reported in original pixels); 0 = no limit")
      ->capture_default_str()
      ->check(CLI::Range(0, 1 << 20))
      ->group("Images");
  cmd->add_option("--max-megapixels", flags->max_megapixels,
                  "refuse images whose header declares more megapixels than this (checked before decoding)")
      ->capture_default_str()
      ->group("Images");
}

inline void AddDescriptorFlag(CLI::App* cmd, sift::DescriptorKind* kind) {
  cmd->add_option_function<std::string>(
         "--descriptor",
         [kind](const std::string& name) {
           *kind = name == "sift" ? sift::DescriptorKind::kSift : sift::DescriptorKind::kRootSift;
         },
         "descriptor kind: rootsift (L1 normalise + sqrt of SIFT, Arandjelovic & Zisserman 2012; retrieves "
         "and matches better) or sift (raw SIFT, e.g. for COLMAP)")
      ->transform(CLI::IsMember({"rootsift", "sift"}, CLI::ignore_case).description(""))  // SIFT -> sift
      ->type_name("rootsift|sift")
      ->default_str(sift::DescriptorKindName(*kind));
}

// --descriptor-magnification, --descriptor-row-step and --descriptor-sampling: the descriptor window of
// `options`.
inline std::vector<CLI::Option*> AddDescriptorWindowFlags(CLI::App* cmd, sift::SiftOptions* options) {
  const bool grid = options->descriptor_sampling == sift::DescriptorSampling::kGrid;
  return {cmd->add_option_function<std::string>(
                 "--descriptor-sampling",
                 [options](const std::string& name) {
                   options->descriptor_sampling =
                       name == "grid" ? sift::DescriptorSampling::kGrid : sift::DescriptorSampling::kPixels;
                 },
                 "where the descriptor takes its gradients: grid (16 x 16 points in the keypoint's frame, the "
                 "same 256 for every keypoint; about a quarter less extraction time) or pixels (every pixel "
                 "of the rotated window, as Lowe's and cv::SIFT's)")
              ->transform(CLI::IsMember({"grid", "pixels"}, CLI::ignore_case).description(""))
              ->type_name("grid|pixels")
              ->default_str(grid ? "grid" : "pixels"),
          cmd->add_option("--descriptor-magnification", options->descriptor_magnification,
                          "width of each of the descriptor's 4 x 4 cells in keypoint scales (VLFeat's magnif; Lowe's and "
                          "cv::SIFT's 3)")
              ->check(NumberIn(1, 10))
              ->capture_default_str(),
          cmd->add_option("--descriptor-row-step", options->descriptor_row_step,
                          "the descriptor samples every this-many rows of its window (1 = every row, as Lowe's and "
                          "cv::SIFT's; with --descriptor-sampling pixels only)")
              ->check(CLI::Range(1, 4))
              ->capture_default_str()};
}

inline void AddThreadsFlag(CLI::App* cmd, int* threads) {
  cmd->add_option("--threads", *threads, "CPU threads to compute with, in total; 0 = all cores (results do not depend on it)")
      ->capture_default_str()
      ->check(CLI::Range(0, 256));
}

// How `threads` (0 = all cores) are shared out over `items` independent images: `workers` images at
// once, each extracted with `per_item` threads. Many images: one thread each (no synchronisation
// inside an image); one image: all threads inside it.
struct ThreadSplit {
  int workers = 1;
  int per_item = 1;
};
inline ThreadSplit SplitThreads(int threads, size_t items) {
  const int total = ResolveThreadCount(threads);
  ThreadSplit split;
  split.workers = static_cast<int>(std::clamp<size_t>(items, 1, static_cast<size_t>(total)));
  split.per_item = std::max(1, total / split.workers);
  return split;
}

// An image file's features with the decode and extraction stages timed separately; keypoints in
// original-image pixels (SiftExtractor::ExtractFromDecoded).
struct TimedFeatures {
  sift::FeatureSet features;
  double decode_ms = 0;
  double extract_ms = 0;
};
inline Result<TimedFeatures> ExtractTimed(const sift::SiftExtractor& extractor, const std::string& path,
                                          const sift::DecodeOptions& decode) {
  using Clock = std::chrono::steady_clock;
  const auto ms_since = [](Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); };
  auto t0 = Clock::now();
  auto decoded = sift::ReadImage(path, decode);
  if (!decoded) return std::unexpected(decoded.error());
  TimedFeatures out;
  out.decode_ms = ms_since(t0);
  t0 = Clock::now();
  out.features = extractor.ExtractFromDecoded(*decoded);
  out.extract_ms = ms_since(t0);
  return out;
}

}  // namespace oxbow::cli
