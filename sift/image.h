// Image decoding into the float grey images the SIFT extractor works on.
//
// DecodeImage accepts JPEG, PNG, PPM/PGM (binary P5/P6), WebP, TIFF and BMP. Before any pixel is
// allocated it reads the image dimensions from the file header itself (not from OpenCV, which would
// decode first) and refuses images whose declared width*height exceeds DecodeOptions::max_pixels, so a
// small file declaring a huge image (a "decompression bomb") costs nothing (TIFF: the dimensions libtiff
// will use, i.e. the first of repeated tags). Truncated files are refused: JPEG without its EOI marker,
// PNG without its IEND chunk, PNM shorter than width*height*channels bytes. JPEG and TIFF data is first
// decoded by libjpeg / libtiff with every report of missing or corrupt data an error (OpenCV would fill
// in grey and go on), so a JPEG cut short with an end marker appended, a frame header larger than its
// data, or a TIFF strip that does not decompress are refused; so is a progressive JPEG with more than
// DecodeOptions::max_jpeg_scans scans (each scan costs a pass over every block of the image).
// The EXIF orientation tag of JPEG files is honoured (the image is rotated/flipped upright), and the
// result can be downscaled (area averaging) so that its longest side is at most max_image_side_px.
//
// Thread safety: all functions are reentrant (no shared state).
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::sift {

// A single-channel image of floats, row-major, values in [0, 1] (0 black, 1 white).
struct GrayImage {
  int width = 0;   // pixels
  int height = 0;  // pixels
  std::vector<float> pixels;  // width * height values; pixel (x, y) is pixels[y * width + x]

  bool empty() const { return width <= 0 || height <= 0; }
  float at(int x, int y) const { return pixels[static_cast<size_t>(y) * static_cast<size_t>(width) + static_cast<size_t>(x)]; }
};

// These defaults are the product's: every command (extract, vocab train, index build/add, query, match,
// eval) and the server use them unless a flag says otherwise (--max-megapixels, --max-image-side).
struct DecodeOptions {
  // Largest accepted declared width * height of the encoded image (before any downscaling), pixels.
  // Checked from the file header before pixels are allocated; over it -> kImageTooLarge. Must be >= 1.
  // 40 MP: every camera photo of 2024 below medium format, with one decode bounded at about 0.5 GiB.
  uint64_t max_pixels = 40'000'000;
  // Largest accepted encoded file size, bytes; over it -> kImageTooLarge. Must be >= 1.
  uint64_t max_bytes = 256ull << 20;
  // Most scans a progressive JPEG may have; more -> kInvalidImage, after at most this many scans were
  // read. libjpeg walks every block of the frame for each scan, even an almost empty one (~2.3 ms per
  // scan of a 36 MP frame: 215 KiB of 10-byte scans cost ~50 s of CPU). libjpeg's progression writes
  // 6 (grey) or 10 (colour) scans; 100 is also libtiff's default limit for JPEG inside TIFF
  // (LIBTIFF_JPEG_MAX_ALLOWED_SCAN_NUMBER). [1, 10000].
  int max_jpeg_scans = 100;
  // When set, the decoded image is downscaled with area averaging (cv::INTER_AREA) so that its longest
  // side is at most this many pixels; never upscaled; keypoints are still reported in original pixels.
  // Unset: no limit. Must be >= 16 when set. 1600 px bounds extraction time and memory (a 12 MP photo
  // costs ~4x less) and keeps enough detail for retrieval: Paris photos (<= 1024 px) are unaffected.
  std::optional<int> max_image_side_px = 1600;
  // Rotate/flip JPEG images as their EXIF Orientation tag says (what a photo viewer shows). When false
  // the pixels are returned as stored.
  bool apply_exif_orientation = true;

  // Error message for an invalid setting, or nullopt.
  [[nodiscard]] std::optional<std::string> Check() const;
};

// The container formats DecodeImage recognises from the first bytes of a file.
enum class ImageFormat { kUnknown, kJpeg, kPng, kPnm, kWebp, kTiff, kBmp };

const char* ImageFormatName(ImageFormat format);  // "jpeg", "png", ...

// What a file header declares, read without decoding pixels.
struct ImageHeaderInfo {
  ImageFormat format = ImageFormat::kUnknown;
  uint64_t width = 0;   // pixels, as declared (before EXIF orientation)
  uint64_t height = 0;  // pixels
};

// Reads the format and declared dimensions from the header bytes. kInvalidImage for an empty, unknown or
// damaged header. Cost: O(header size) (JPEG: walks the marker segments up to the first SOFn).
[[nodiscard]] Result<ImageHeaderInfo> ReadImageHeader(std::span<const uint8_t> bytes);

struct DecodedImage {
  GrayImage gray;           // the decoded (oriented, possibly downscaled) grey image
  int original_width = 0;   // pixels of the full-resolution image after EXIF orientation
  int original_height = 0;
  // Multiply coordinates in `gray` by this to get coordinates in the original (oriented) image:
  // x_orig = x_gray * scale_to_original (>= 1; exactly 1 when not downscaled). Pixel centres are
  // mapped as in cv::resize: x_orig = (x_gray + 0.5) * s - 0.5 per axis; with one uniform s this equals
  // x_gray * s + (s - 1) / 2 — see GrayToOriginal().
  double scale_to_original = 1.0;
};

// Maps a pixel coordinate of DecodedImage::gray into original-image coordinates (pixel-centre aware).
inline double GrayToOriginal(double coordinate, double scale_to_original) {
  return (coordinate + 0.5) * scale_to_original - 0.5;
}

// Decodes an encoded image into grey. Errors: kInvalidArgument for bad options; kInvalidImage for empty,
// truncated, corrupt or unrecognised bytes and JPEGs over max_jpeg_scans; kImageTooLarge when
// bytes.size() > max_bytes or the declared width*height > max_pixels; kUnsupportedFormat for a recognised
// format this OpenCV build cannot decode at all (GIF; WebP or TIFF when built without them).
[[nodiscard]] Result<DecodedImage> DecodeImage(std::span<const uint8_t> bytes, const DecodeOptions& options = {});

// Reads the file (kNotFound / kIoError) and decodes it as DecodeImage does; messages name the path.
[[nodiscard]] Result<DecodedImage> ReadImage(const std::string& path, const DecodeOptions& options = {});

// True when the file name ends in an extension DecodeImage may accept (.jpg .jpeg .png .ppm .pgm .pnm
// .bmp .tif .tiff .webp, any case). The content decides in the end: this only filters folder listings.
bool IsImageFile(const std::string& path);

// The image files (IsImageFile) under `folder` and all its sub-folders, sorted by path, so that every
// command lists a folder the same way. kNotFound when `folder` is not a folder; kIoError when it cannot
// be read.
[[nodiscard]] Result<std::vector<std::string>> ListImageFiles(const std::string& folder);
// The same walk for any files: those whose path `keep` accepts (e.g. feature files).
[[nodiscard]] Result<std::vector<std::string>> ListFiles(const std::string& folder,
                                                         const std::function<bool(const std::string&)>& keep);

// Converts an 8-bit grey image (row-major, `stride` bytes per row) to [0,1] floats.
GrayImage GrayFromBytes(const uint8_t* data, int width, int height, size_t stride);

}  // namespace oxbow::sift
