// Drawing keypoints over an image, for looking at what the extractor found (uses OpenCV).
#pragma once

#include <string>

#include "sift/base/error.h"
#include "sift/image.h"
#include "sift/types.h"

namespace oxbow::sift {

// Writes `background` (grey, shown in colour) with every keypoint drawn as a circle of radius
// 3 * scale (one descriptor cell; at least 2 px) and a radius line along its orientation, coloured by
// octave. Keypoint coordinates are multiplied by `features_to_background` first (e.g.
// 1 / DecodedImage::scale_to_original when the features are in original-image coordinates).
// The format follows the extension of `out_path` (.png, .jpg, ...). kInvalidArgument when OpenCV
// cannot encode that format, kIoError when the file cannot be written.
[[nodiscard]] Status DrawKeypoints(const GrayImage& background, const FeatureSet& features, double features_to_background,
                                   const std::string& out_path);

}  // namespace oxbow::sift
