#include "sift/draw.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/base/binary_io.h"
#include "sift/opencv_codecs.h"

namespace oxbow::sift {

Status DrawKeypoints(const GrayImage& background, const FeatureSet& features, double features_to_background,
                     const std::string& out_path) {
  if (background.empty()) return Fail(ErrorCode::kInvalidArgument, "cannot draw on an empty image");
  cv::Mat grey(background.height, background.width, CV_8U);
  for (int y = 0; y < background.height; ++y)
    for (int x = 0; x < background.width; ++x)
      grey.at<uint8_t>(y, x) = static_cast<uint8_t>(std::lround(std::clamp(background.at(x, y), 0.0f, 1.0f) * 255.0f));
  cv::Mat canvas;
  cv::cvtColor(grey, canvas, cv::COLOR_GRAY2BGR);
  static const cv::Scalar kColours[] = {{0, 255, 255}, {0, 255, 0}, {255, 255, 0}, {255, 128, 0},
                                        {255, 0, 255}, {0, 128, 255}, {0, 0, 255}};
  constexpr int kShift = 4;  // sub-pixel drawing precision
  const double unit = 1 << kShift;
  for (const Keypoint& k : features.keypoints) {
    const double x = (k.x + 0.5) * features_to_background - 0.5, y = (k.y + 0.5) * features_to_background - 0.5;
    const double radius = std::max(2.0, 3.0 * k.scale * features_to_background);
    const cv::Scalar& colour = kColours[static_cast<size_t>(std::clamp(k.octave + 1, 0, 6))];
    const cv::Point centre(static_cast<int>(std::lround(x * unit)), static_cast<int>(std::lround(y * unit)));
    cv::circle(canvas, centre, static_cast<int>(std::lround(radius * unit)), colour, 1, cv::LINE_AA, kShift);
    const cv::Point tip(static_cast<int>(std::lround((x + radius * std::cos(k.orientation)) * unit)),
                        static_cast<int>(std::lround((y + radius * std::sin(k.orientation)) * unit)));
    cv::line(canvas, centre, tip, colour, 1, cv::LINE_AA, kShift);
  }
  const auto dot = out_path.rfind('.');
  const std::string ext = dot == std::string::npos ? "" : out_path.substr(dot);
  std::vector<uint8_t> encoded;
  if (ext.empty()) return Fail(ErrorCode::kInvalidArgument, "cannot encode a drawing without an extension (use .png or .jpg): " + out_path);
  const auto written = opencv_codecs::Encode(ext, canvas, encoded);
  if (!written) {
    if (written.error().code == ErrorCode::kUnsupportedFormat) return std::unexpected(written.error());
    return Fail(ErrorCode::kInvalidArgument, "cannot encode a drawing as '" + ext + "': " + written.error().message);
  }
  if (!*written) return Fail(ErrorCode::kInvalidArgument, "cannot encode a drawing as '" + ext + "' (use .png or .jpg): " + out_path);
  return io::WriteFileAtomically(out_path, encoded);
}

}  // namespace oxbow::sift
