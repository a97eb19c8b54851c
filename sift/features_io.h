// On-disk feature files: oxbow's versioned binary format and COLMAP's text format.
//
// oxbow format (a sift/base/binary_io.h container, magic "OXBWFEAT", version 1, flags 0):
//   payload (little-endian as the container header records):
//     u32 image_width, u32 image_height          input image size in pixels (after EXIF orientation)
//     u8  descriptor kind (0 sift, 1 rootsift), u8 descriptor encoding (0 = float32), u16 reserved (0)
//     u64 extractor fingerprint                  SiftOptions::Fingerprint() of the extractor
//     u32 length + bytes: extractor description  SiftOptions::Describe()
//     u64 keypoint count N
//     N x { f32 x, f32 y, f32 scale, f32 orientation, f32 response, i32 octave }   (24 bytes each)
//     N x 128 f32 descriptors
// The reader refuses a foreign magic, another version or byte order, a damaged header or payload (CRC),
// and a payload whose sizes or values do not add up, each with a message naming the file.
//
// COLMAP text format (what `colmap feature_importer` reads): first line "N 128", then one line per
// keypoint "x y scale orientation d1 ... d128" with descriptors as integers 0..255
// (DescriptorsToUint8 scaling). COLMAP's origin is the top-left image corner, so x and y are written
// +0.5 relative to oxbow's pixel-centre convention.
//
// Thread safety: reentrant. Writes are atomic (temporary file + rename).
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "sift/base/error.h"
#include "sift/types.h"

namespace oxbow::sift {

inline constexpr std::string_view kFeatureFileMagic = "OXBWFEAT";
inline constexpr uint32_t kFeatureFileVersion = 1;

struct FeatureFile {
  FeatureSet features;
  uint64_t extractor_fingerprint = 0;    // SiftOptions::Fingerprint() of the extractor that wrote it
  std::string extractor_description;     // SiftOptions::Describe() of that extractor
};

// Serialises / parses the container payload (exposed for tests and for embedding in other files).
std::vector<uint8_t> EncodeFeaturePayload(const FeatureFile& file);
[[nodiscard]] Result<FeatureFile> DecodeFeaturePayload(std::span<const uint8_t> payload, const std::string& what);

// Writes `file` to `path` atomically. kIoError when the OS refuses.
[[nodiscard]] Status WriteFeatureFile(const std::string& path, const FeatureFile& file);
// Reads and validates a feature file. kNotFound, kCorruptData (damaged or foreign), kIncompatible
// (other version or byte order).
[[nodiscard]] Result<FeatureFile> ReadFeatureFile(const std::string& path);

// Writes COLMAP's feature text format (see above) atomically.
[[nodiscard]] Status WriteColmapFeatures(const std::string& path, const FeatureSet& features);

}  // namespace oxbow::sift
