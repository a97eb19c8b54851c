// The data types every module shares: keypoints and descriptor sets. index/ and vocab/ need these
// types, not the extractor (sift.h).
#pragma once

#include <cstdint>
#include <span>
#include <vector>

namespace oxbow::sift {

inline constexpr int kDescriptorDim = 128;  // 4x4 spatial cells x 8 orientation bins (Lowe 2004, sec. 6)

// One scale-space extremum, in the coordinates of the *input* image (before any upsampling or resizing
// the extractor does internally; after EXIF orientation has been applied).
struct Keypoint {
  float x = 0;            // column, pixels; the centre of the top-left pixel is (0, 0)
  float y = 0;            // row, pixels
  float scale = 0;        // Gaussian sigma of the detection, in input-image pixels (OpenCV's KeyPoint::size / 2)
  float orientation = 0;  // dominant gradient direction, radians in [0, 2*pi), measured from +x towards +y
  float response = 0;     // |DoG| at the refined extremum (contrast); larger is stronger
  int octave = 0;         // octave of detection; -1 is the 2x upsampled octave
};

enum class DescriptorKind : uint8_t {
  kSift = 0,      // L2-normalised, clipped at 0.2, renormalised (Lowe 2004)
  kRootSift = 1,  // L1-normalised then element-wise square root (Arandjelovic & Zisserman 2012); L2 norm 1
};

const char* DescriptorKindName(DescriptorKind kind);  // "sift" | "rootsift"

// Keypoints with their descriptors, as extracted from one image.
struct FeatureSet {
  int image_width = 0;   // input image size in pixels (after EXIF orientation)
  int image_height = 0;
  DescriptorKind kind = DescriptorKind::kSift;
  std::vector<Keypoint> keypoints;
  std::vector<float> descriptors;  // row-major, keypoints.size() x kDescriptorDim, each row unit L2 norm

  size_t size() const { return keypoints.size(); }
  std::span<const float> Descriptor(size_t i) const {
    return {descriptors.data() + i * kDescriptorDim, static_cast<size_t>(kDescriptorDim)};
  }
};

}  // namespace oxbow::sift
