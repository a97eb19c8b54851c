// Fuzz target: image bytes -> header sniffing, decoding (every format DecodeImage accepts) and a small
// SIFT extraction. Expected outcome for any input: keypoints, or a clean error value (never kInternal).
// Limits keep one execution fast: at most 4 MP declared, 2 MiB of bytes, downscaled to a 96 px side,
// one thread, no 2x first octave; the default 100 scans per progressive JPEG (the seeds include
// scan-heavy JPEGs and TIFFs with repeated dimension tags).
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <span>

#include "sift/image.h"
#include "sift/sift.h"

namespace {

const oxbow::sift::SiftExtractor& Extractor() {
  static const oxbow::sift::SiftExtractor extractor = [] {
    oxbow::sift::SiftOptions options;
    options.upsample_first_octave = false;
    options.num_threads = 1;
    options.max_features = 200;
    auto made = oxbow::sift::SiftExtractor::Create(options);
    if (!made) std::abort();
    return *made;
  }();
  return extractor;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace oxbow::sift;
  const std::span<const uint8_t> bytes(data, size);
  auto header = ReadImageHeader(bytes);
  if (header && header->format == ImageFormat::kUnknown) std::abort();  // a header result names its format

  DecodeOptions decode;
  decode.max_pixels = 4'000'000;
  decode.max_bytes = 2u << 20;
  decode.max_image_side_px = 96;
  auto decoded = DecodeImage(bytes, decode);
  if (!decoded) {
    if (decoded.error().code == oxbow::ErrorCode::kInternal) std::abort();
    return 0;
  }
  const GrayImage& gray = decoded->gray;
  if (gray.width <= 0 || gray.height <= 0 || gray.width > 96 || gray.height > 96 ||
      gray.pixels.size() != static_cast<size_t>(gray.width) * static_cast<size_t>(gray.height)) {
    std::fprintf(stderr, "decoded image of %dx%d with %zu pixels\n", gray.width, gray.height, gray.pixels.size());
    std::abort();
  }
  FeatureSet features = Extractor().ExtractFromDecoded(*decoded);
  if (features.descriptors.size() != features.keypoints.size() * kDescriptorDim) std::abort();
  return 0;
}
