#include "sift/sift.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstdio>
#include <sstream>

namespace oxbow::sift {

std::optional<std::string> SiftOptions::Check() const {
  if (!(sigma > 0.5 && sigma <= 10)) return "sigma must be in (0.5, 10], got " + std::to_string(sigma);
  if (!(assumed_blur >= 0 && assumed_blur < sigma)) return "assumed_blur must be in [0, sigma), got " + std::to_string(assumed_blur);
  if (intervals < 1 || intervals > 8) return "intervals must be in [1, 8], got " + std::to_string(intervals);
  if (!(contrast_threshold >= 0 && contrast_threshold <= 1)) return "contrast_threshold must be in [0, 1], got " + std::to_string(contrast_threshold);
  if (!(edge_threshold > 1 && edge_threshold <= 1e6)) return "edge_threshold must be > 1, got " + std::to_string(edge_threshold);
  if (max_features && *max_features < 1) return "max_features must be >= 1 when set, got " + std::to_string(*max_features);
  if (descriptor != DescriptorKind::kSift && descriptor != DescriptorKind::kRootSift) return "unknown descriptor kind";
  if (!(orientation_peak_ratio > 0 && orientation_peak_ratio <= 1)) return "orientation_peak_ratio must be in (0, 1], got " + std::to_string(orientation_peak_ratio);
  if (!(kernel_radius_sigmas >= 2.5 && kernel_radius_sigmas <= 6)) return "kernel_radius_sigmas must be in [2.5, 6], got " + std::to_string(kernel_radius_sigmas);
  if (max_octaves && (*max_octaves < 1 || *max_octaves > 32)) return "max_octaves must be in [1, 32] when set, got " + std::to_string(*max_octaves);
  if (num_threads < 0 || num_threads > 256) return "num_threads must be in [0, 256], got " + std::to_string(num_threads);
  return std::nullopt;
}

namespace {
// Shortest text that reads back to the same double ("%.17g" trimmed), so Describe() is canonical.
std::string CanonicalDouble(double v) {
  char buf[64];
  for (int precision = 1; precision <= 17; ++precision) {
    std::snprintf(buf, sizeof buf, "%.*g", precision, v);
    if (std::strtod(buf, nullptr) == v) break;
  }
  return buf;
}
}  // namespace

std::string SiftOptions::Describe() const {
  std::ostringstream s;
  s << "oxbow-sift/1"
    << ";upsample=" << (upsample_first_octave ? 1 : 0) << ";sigma=" << CanonicalDouble(sigma)
    << ";assumed_blur=" << CanonicalDouble(assumed_blur) << ";intervals=" << intervals
    << ";contrast=" << CanonicalDouble(contrast_threshold) << ";edge=" << CanonicalDouble(edge_threshold)
    << ";max_features=" << (max_features ? std::to_string(*max_features) : std::string("all"))
    << ";descriptor=" << DescriptorKindName(descriptor)
    << ";peak_ratio=" << CanonicalDouble(orientation_peak_ratio)
    << ";kernel_radius=" << CanonicalDouble(kernel_radius_sigmas)
    << ";max_octaves=" << (max_octaves ? std::to_string(*max_octaves) : std::string("all"));
  return s.str();
}

uint64_t SiftOptions::Fingerprint() const {
  uint64_t hash = 0xcbf29ce484222325ull;  // FNV-1a 64 offset basis
  for (const unsigned char c : Describe()) {
    hash ^= c;
    hash *= 0x100000001b3ull;  // FNV-1a 64 prime
  }
  return hash;
}

Result<SiftExtractor> SiftExtractor::Create(const SiftOptions& options) {
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, "invalid SIFT options: " + *message);
  return SiftExtractor(options);
}

FeatureSet SiftExtractor::Extract(const GrayImage& image) const {
  OXBOW_CHECK(false, "SiftExtractor::Extract is being implemented (issue 2)");
  return {};
}

Result<FeatureSet> SiftExtractor::ExtractFromBytes(std::span<const uint8_t> bytes, const DecodeOptions& decode) const {
  return Fail(ErrorCode::kInternal, "SiftExtractor::ExtractFromBytes is being implemented (issue 2)");
}

Result<FeatureSet> SiftExtractor::ExtractFromFile(const std::string& path, const DecodeOptions& decode) const {
  return Fail(ErrorCode::kInternal, "SiftExtractor::ExtractFromFile is being implemented (issue 2)");
}

void ToRootSift(std::span<float> descriptor) {
  double l1 = 0;
  for (const float v : descriptor) l1 += std::fabs(v);
  if (l1 <= 0) return;
  const float inv = static_cast<float>(1.0 / l1);
  for (float& v : descriptor) v = std::sqrt(std::fabs(v) * inv);
}

void DescriptorsToUint8(const FeatureSet& features, std::vector<uint8_t>* out) {
  out->resize(features.descriptors.size());
  for (size_t i = 0; i < features.descriptors.size(); ++i) {
    const float v = std::round(512.0f * features.descriptors[i]);
    (*out)[i] = static_cast<uint8_t>(std::clamp(v, 0.0f, 255.0f));
  }
}

}  // namespace oxbow::sift
