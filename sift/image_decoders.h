// The decoders image.cc runs itself, without OpenCV's codec library (sift/opencv_codecs.h says why):
// JPEG through libjpeg, PNG through libpng, binary 8-bit PGM by hand. Each produces the same grey pixels
// as cv::imdecode(bytes, IMREAD_GRAYSCALE) on Debian 12's OpenCV 4.6 (same libraries, same settings and
// transforms, the EXIF orientation applied the same way; image_decoders_test compares them), so features
// and indexes do not depend on which decoder ran. Data they do not cover (CMYK JPEG, 16-bit or colour
// PNM) is left to OpenCV: the functions then return an empty Mat without an error.
//
// Internal to oxbow_sift; image.h is the interface.
#pragma once

#include <cstdint>
#include <span>

#include <opencv2/core.hpp>

#include "sift/base/error.h"

namespace oxbow::sift::internal {

// Runs JPEG data through libjpeg with every report of missing or undecodable data an error, and refuses a
// progressive file with more than `max_scans` scans (kInvalidImage for both). With `want_gray` and a 1- or
// 3-component image it decodes at full size to 8-bit grey (libjpeg's own colour conversion, as OpenCV
// asks for it) and, with `apply_exif_orientation`, turns the result as the file's EXIF orientation says.
// Otherwise (a check only, or 4-component CMYK/YCCK data, which OpenCV converts itself) the data is
// entropy-decoded at 1/8 scale, about a third of a full decode's time, and an empty Mat returned.
[[nodiscard]] Result<cv::Mat> DecodeJpeg(std::span<const uint8_t> bytes, int max_scans, bool want_gray,
                                         bool apply_exif_orientation);

// PNG to 8-bit grey with libpng and OpenCV's transforms (16 bits stripped, alpha dropped, palette and
// 1/2/4-bit grey expanded, RGB to grey with weights 0.299 / 0.587), oriented by an eXIf chunk when asked.
// An empty Mat when libpng reports the data corrupt or truncated.
[[nodiscard]] cv::Mat DecodePngGray(std::span<const uint8_t> bytes, bool apply_exif_orientation);

// Binary PGM (P5) with maxval 255: the rows as stored from `data_start` on. An empty Mat for any other PNM
// (OpenCV's decoder scales other maxvals and converts colour with its own formulas).
[[nodiscard]] cv::Mat DecodePgmGray(std::span<const uint8_t> bytes, uint64_t width, uint64_t height, uint32_t maxval,
                                    size_t data_start);

// The orientation (1-8) an EXIF block (starting at its TIFF header, "II" or "MM") gives, read as OpenCV's
// ExifReader reads it: the first-directory entries are read in order up to the first that does not fit
// in the block; 1 (as stored) when the tag is missing or not reached.
int ExifOrientation(std::span<const uint8_t> exif);

// Turns `image` as EXIF orientation 1-8 says (transpose and flips, as cv::imdecode does); other values
// leave it as it is.
void ApplyExifOrientation(int orientation, cv::Mat& image);

}  // namespace oxbow::sift::internal
