// Visualisation of matches between two images: both images side by side (query left, db right), inlier
// matches as green lines, other tentative matches as red lines, and the region of the db image that the
// query maps onto (the projected query region as a yellow quadrilateral, its clipped bounding box in blue).
// Used by `oxbow match --draw`. Not on any hot path; OpenCV is used only inside the .cc.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>

#include <Eigen/Core>

#include "sift/base/error.h"
#include "sift/match.h"
#include "sift/types.h"

namespace oxbow::sift {

struct MatchDrawing {
  std::span<const Keypoint> query;     // keypoints in query-image pixels (as extracted from the file)
  std::span<const Keypoint> db;        // keypoints in db-image pixels
  std::span<const Match> matches;      // tentative matches (indices into query / db)
  std::span<const uint32_t> inliers;   // indices into `matches` drawn green; the rest red
  // When set: the query region (x1,y1,x2,y2, query pixels) is mapped through this 3x3 transform and
  // outlined in the db image (yellow), together with `db_region` (blue) when that is set too.
  std::optional<Eigen::Matrix3d> db_from_query;
  std::array<float, 4> query_region = {0, 0, 0, 0};
  std::optional<std::array<float, 4>> db_region;
};

// Reads both images in colour (EXIF orientation applied, as the extractor does), draws `drawing` and
// writes the picture to `output_path` (format from its extension, e.g. .png or .jpg).
// Errors: kNotFound / kInvalidImage when an input cannot be read, kIoError when the output cannot be
// written, kInvalidArgument for a match index out of range. Thread-safe.
[[nodiscard]] Status DrawMatchesToFile(const std::string& query_image_path, const std::string& db_image_path,
                                       const MatchDrawing& drawing, const std::string& output_path);

}  // namespace oxbow::sift
