// OpenCV's image codecs (cv::imdecode, cv::imencode, cv::imread, cv::imwrite), loaded on first use.
//
// libopencv_imgcodecs links GDAL, GDCM, OpenEXR, libheif and their own dependencies: about 140 shared
// libraries that a process linked with it loads and relocates at every start (0.1-0.15 s of a 2-core
// machine's CPU before main). oxbow decodes JPEG, PNG and PNM itself (image.cc, with the same libraries
// and settings OpenCV uses, so the pixels are the same), so that `oxbow --version`, a one-image
// `oxbow extract` or a query of a JPEG never load it; WebP, TIFF and BMP decoding, thumbnails and drawings
// go through these functions, which dlopen the library the first time one of them is called.
//
// Errors: kUnsupportedFormat when the library cannot be loaded (the message names it and the Debian
// package that has it). An exception OpenCV throws is returned as kInvalidImage (decode, read) or kIoError
// (encode, write) with its text.
//
// Thread safety: every function may be called from any thread; the library is loaded once.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "sift/base/error.h"

namespace oxbow::sift::opencv_codecs {

// cv::imdecode(bytes, flags): an empty Mat when OpenCV cannot decode the bytes.
[[nodiscard]] Result<cv::Mat> Decode(std::span<const uint8_t> bytes, int flags);
// cv::imencode(extension, image, out, params): false when OpenCV has no encoder for it or it fails.
[[nodiscard]] Result<bool> Encode(const std::string& extension, const cv::Mat& image, std::vector<uint8_t>& out,
                                  const std::vector<int>& params = {});
// cv::imread(path, flags): an empty Mat when the file is missing or cannot be decoded.
[[nodiscard]] Result<cv::Mat> Read(const std::string& path, int flags);
// cv::imwrite(path, image, params): false when the extension is unknown or the file cannot be written.
[[nodiscard]] Result<bool> Write(const std::string& path, const cv::Mat& image, const std::vector<int>& params = {});

}  // namespace oxbow::sift::opencv_codecs
