#include "sift/features_io.h"

#include <array>
#include <charconv>
#include <cmath>
#include <cstring>
#include <string>

#include "sift/base/binary_io.h"
#include "sift/sift.h"

namespace oxbow::sift {
namespace {
constexpr uint8_t kEncodingFloat32 = 0;
constexpr size_t kKeypointBytes = 24;
}  // namespace

std::vector<uint8_t> EncodeFeaturePayload(const FeatureFile& file) {
  const FeatureSet& f = file.features;
  OXBOW_CHECK(f.descriptors.size() == f.keypoints.size() * kDescriptorDim, "descriptor count does not match keypoints");
  io::ByteWriter w;
  w.bytes().reserve(64 + file.extractor_description.size() + f.size() * (kKeypointBytes + 4 * kDescriptorDim));
  w.Put<uint32_t>(static_cast<uint32_t>(f.image_width));
  w.Put<uint32_t>(static_cast<uint32_t>(f.image_height));
  w.Put<uint8_t>(static_cast<uint8_t>(f.kind));
  w.Put<uint8_t>(kEncodingFloat32);
  w.Put<uint16_t>(0);
  w.Put<uint64_t>(file.extractor_fingerprint);
  w.PutString(file.extractor_description);
  w.Put<uint64_t>(f.size());
  for (const Keypoint& k : f.keypoints) {
    w.Put<float>(k.x);
    w.Put<float>(k.y);
    w.Put<float>(k.scale);
    w.Put<float>(k.orientation);
    w.Put<float>(k.response);
    w.Put<int32_t>(k.octave);
  }
  w.PutArray<float>(f.descriptors);
  return w.Release();
}

Result<FeatureFile> DecodeFeaturePayload(std::span<const uint8_t> payload, const std::string& what) {
  io::ByteReader r(payload, what);
  auto corrupt = [&](const std::string& message) { return Fail(ErrorCode::kCorruptData, what + ": " + message); };
  FeatureFile file;
  FeatureSet& f = file.features;
  auto width = r.Get<uint32_t>();
  auto height = r.Get<uint32_t>();
  auto kind = r.Get<uint8_t>();
  auto encoding = r.Get<uint8_t>();
  auto reserved = r.Get<uint16_t>();
  auto fingerprint = r.Get<uint64_t>();
  if (!width || !height || !kind || !encoding || !reserved || !fingerprint) return corrupt("feature header is truncated");
  if (*width > (1u << 30) || *height > (1u << 30)) return corrupt("image size is implausible");
  if (*kind > static_cast<uint8_t>(DescriptorKind::kRootSift)) return corrupt("unknown descriptor kind " + std::to_string(*kind));
  if (*encoding != kEncodingFloat32) return corrupt("unknown descriptor encoding " + std::to_string(*encoding));
  auto description = r.GetString(1 << 16);
  if (!description) return std::unexpected(description.error());
  auto count = r.Get<uint64_t>();
  if (!count) return std::unexpected(count.error());
  const uint64_t per_point = kKeypointBytes + 4 * kDescriptorDim;
  if (*count > r.remaining() / per_point || *count * per_point != r.remaining())
    return corrupt("keypoint count " + std::to_string(*count) + " does not match the payload size");
  f.image_width = static_cast<int>(*width);
  f.image_height = static_cast<int>(*height);
  f.kind = static_cast<DescriptorKind>(*kind);
  file.extractor_fingerprint = *fingerprint;
  file.extractor_description = std::move(*description);
  f.keypoints.resize(*count);
  for (Keypoint& k : f.keypoints) {
    k.x = *r.Get<float>();
    k.y = *r.Get<float>();
    k.scale = *r.Get<float>();
    k.orientation = *r.Get<float>();
    k.response = *r.Get<float>();
    k.octave = *r.Get<int32_t>();
    if (!std::isfinite(k.x) || !std::isfinite(k.y) || !(k.scale > 0) || !std::isfinite(k.scale) || !std::isfinite(k.orientation))
      return corrupt("a keypoint has a non-finite position or a non-positive scale");
  }
  f.descriptors.resize(*count * kDescriptorDim);
  if (auto status = r.GetArray<float>(f.descriptors); !status) return std::unexpected(status.error());
  for (const float v : f.descriptors)
    if (!std::isfinite(v)) return corrupt("a descriptor holds a non-finite value");
  return file;
}

Status WriteFeatureFile(const std::string& path, const FeatureFile& file) {
  const std::vector<uint8_t> payload = EncodeFeaturePayload(file);
  return io::WriteContainerFile(path, kFeatureFileMagic, kFeatureFileVersion, 0, payload);
}

Result<FeatureFile> ReadFeatureFile(const std::string& path) {
  auto container = io::ReadContainerFile(path, kFeatureFileMagic, kFeatureFileVersion, kFeatureFileVersion);
  if (!container) return std::unexpected(container.error());
  if (container->flags != 0)
    return Fail(ErrorCode::kIncompatible, "'" + path + "' uses feature-file flags " + std::to_string(container->flags) +
                                              " this version does not understand");
  return DecodeFeaturePayload(container->payload, "'" + path + "'");
}

Status WriteColmapFeatures(const std::string& path, const FeatureSet& features) {
  std::vector<uint8_t> bytes;
  DescriptorsToUint8(features, &bytes);
  // " 0" .. " 255" and, in the 5th byte, the length: each descriptor value is one copy of 4 bytes.
  static const auto kByteText = [] {
    std::array<std::array<char, 5>, 256> table{};
    for (size_t v = 0; v < table.size(); ++v) {
      char* text = table[v].data();
      text[0] = ' ';
      text[4] = static_cast<char>(std::to_chars(text + 1, text + 4, v).ptr - text);
    }
    return table;
  }();
  std::string text = std::to_string(features.size()) + " " + std::to_string(kDescriptorDim) + "\n";
  // A line: four numbers of at most 13 characters each ("-1.23457e+06" as printf's %.6g writes them),
  // three spaces, 128 values of at most 4 characters and the newline.
  constexpr size_t kMaxLine = 4 * 13 + 3 + 4 * kDescriptorDim + 1;
  const size_t head = text.size();
  text.resize(head + features.size() * kMaxLine);
  char* out = text.data() + head;
  for (size_t i = 0; i < features.size(); ++i) {
    const Keypoint& k = features.keypoints[i];
    const double numbers[4] = {k.x + 0.5, k.y + 0.5, k.scale, k.orientation};
    for (int j = 0; j < 4; ++j) {
      if (j > 0) *out++ = ' ';
      // std::to_chars with a precision writes exactly what printf's %.6g does.
      out = std::to_chars(out, out + 13, numbers[j], std::chars_format::general, 6).ptr;
    }
    const uint8_t* row = bytes.data() + i * kDescriptorDim;
    for (int d = 0; d < kDescriptorDim; ++d) {
      const auto& t = kByteText[row[d]];
      std::memcpy(out, t.data(), 4);
      out += t[4];
    }
    *out++ = '\n';
  }
  text.resize(static_cast<size_t>(out - text.data()));
  return io::WriteFileAtomically(path, std::span(reinterpret_cast<const uint8_t*>(text.data()), text.size()));
}

}  // namespace oxbow::sift
