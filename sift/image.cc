#include "sift/image.h"

namespace oxbow::sift {

std::optional<std::string> DecodeOptions::Check() const {
  if (max_pixels < 1) return "max_pixels must be >= 1";
  if (max_bytes < 1) return "max_bytes must be >= 1";
  if (max_image_side_px && *max_image_side_px < 16) return "max_image_side_px must be >= 16 when set, got " + std::to_string(*max_image_side_px);
  return std::nullopt;
}

const char* ImageFormatName(ImageFormat format) {
  switch (format) {
    case ImageFormat::kUnknown: return "unknown";
    case ImageFormat::kJpeg: return "jpeg";
    case ImageFormat::kPng: return "png";
    case ImageFormat::kPnm: return "pnm";
    case ImageFormat::kWebp: return "webp";
    case ImageFormat::kTiff: return "tiff";
    case ImageFormat::kBmp: return "bmp";
  }
  return "unknown";
}

Result<ImageHeaderInfo> ReadImageHeader(std::span<const uint8_t> bytes) {
  return Fail(ErrorCode::kInternal, "ReadImageHeader is being implemented (issue 2)");
}

Result<DecodedImage> DecodeImage(std::span<const uint8_t> bytes, const DecodeOptions& options) {
  return Fail(ErrorCode::kInternal, "DecodeImage is being implemented (issue 2)");
}

Result<DecodedImage> ReadImage(const std::string& path, const DecodeOptions& options) {
  return Fail(ErrorCode::kInternal, "ReadImage is being implemented (issue 2)");
}

GrayImage GrayFromBytes(const uint8_t* data, int width, int height, size_t stride) {
  GrayImage image;
  image.width = width;
  image.height = height;
  image.pixels.resize(static_cast<size_t>(width) * static_cast<size_t>(height));
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x)
      image.pixels[static_cast<size_t>(y) * width + x] = data[y * stride + x] * (1.0f / 255.0f);
  return image;
}

}  // namespace oxbow::sift
