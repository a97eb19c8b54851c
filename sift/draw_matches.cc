#include "sift/draw_matches.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>  // the IMREAD_ flags only; the library is loaded by opencv_codecs.cc
#include <opencv2/imgproc.hpp>

#include "sift/opencv_codecs.h"

namespace oxbow::sift {
namespace {

Result<cv::Mat> ReadColour(const std::string& path) {
  if (!std::filesystem::exists(path)) return Fail(ErrorCode::kNotFound, "no such image file: " + path);
  auto image = opencv_codecs::Read(path, cv::IMREAD_COLOR);  // applies the EXIF orientation
  if (!image) {
    if (image.error().code == ErrorCode::kUnsupportedFormat) return std::unexpected(image.error());
    return Fail(ErrorCode::kInvalidImage, "cannot decode " + path + ": " + image.error().message);
  }
  if (image->empty()) return Fail(ErrorCode::kInvalidImage, "cannot decode " + path);
  return image;
}

}  // namespace

Status DrawMatchesToFile(const std::string& query_image_path, const std::string& db_image_path,
                         const MatchDrawing& drawing, const std::string& output_path) {
  for (const Match& m : drawing.matches) {
    if (m.query_index >= drawing.query.size() || m.db_index >= drawing.db.size()) {
      return Fail(ErrorCode::kInvalidArgument, "DrawMatchesToFile: a match index is out of range");
    }
  }
  for (uint32_t i : drawing.inliers) {
    if (i >= drawing.matches.size()) return Fail(ErrorCode::kInvalidArgument, "DrawMatchesToFile: an inlier index is out of range");
  }
  auto query = ReadColour(query_image_path);
  if (!query) return std::unexpected(query.error());
  auto db = ReadColour(db_image_path);
  if (!db) return std::unexpected(db.error());

  const int width = query->cols + db->cols;
  const int height = std::max(query->rows, db->rows);
  cv::Mat canvas(height, width, CV_8UC3, cv::Scalar(0, 0, 0));
  query->copyTo(canvas(cv::Rect(0, 0, query->cols, query->rows)));
  db->copyTo(canvas(cv::Rect(query->cols, 0, db->cols, db->rows)));
  const cv::Point2f offset(static_cast<float>(query->cols), 0);
  const int thickness = std::max(1, std::max(width, height) / 1200);

  std::vector<uint8_t> is_inlier(drawing.matches.size(), 0);
  for (uint32_t i : drawing.inliers) is_inlier[i] = 1;
  auto draw_match = [&](size_t i, const cv::Scalar& colour) {
    const Keypoint& a = drawing.query[drawing.matches[i].query_index];
    const Keypoint& b = drawing.db[drawing.matches[i].db_index];
    const cv::Point2f pa(a.x, a.y), pb = cv::Point2f(b.x, b.y) + offset;
    cv::line(canvas, pa, pb, colour, thickness, cv::LINE_AA);
    cv::circle(canvas, pa, 2 * thickness + 1, colour, thickness, cv::LINE_AA);
    cv::circle(canvas, pb, 2 * thickness + 1, colour, thickness, cv::LINE_AA);
  };
  // Rejected matches first so that inliers stay visible on top.
  for (size_t i = 0; i < drawing.matches.size(); ++i) {
    if (!is_inlier[i]) draw_match(i, cv::Scalar(0, 0, 255));
  }
  for (size_t i = 0; i < drawing.matches.size(); ++i) {
    if (is_inlier[i]) draw_match(i, cv::Scalar(0, 200, 0));
  }

  const auto& r = drawing.query_region;
  if (drawing.db_from_query && drawing.db_from_query->allFinite()) {
    cv::rectangle(canvas, cv::Point2f(r[0], r[1]), cv::Point2f(r[2], r[3]), cv::Scalar(0, 255, 255), thickness, cv::LINE_AA);
    std::vector<cv::Point> quad;
    for (auto [x, y] : {std::pair{r[0], r[1]}, {r[2], r[1]}, {r[2], r[3]}, {r[0], r[3]}}) {
      const Eigen::Vector3d p = *drawing.db_from_query * Eigen::Vector3d(x, y, 1);
      if (!(p.z() > 1e-12)) {
        quad.clear();
        break;
      }
      const double px = p.x() / p.z() + offset.x, py = p.y() / p.z();
      if (std::abs(px) > 1e6 || std::abs(py) > 1e6) {
        quad.clear();
        break;
      }
      quad.emplace_back(static_cast<int>(std::lround(px)), static_cast<int>(std::lround(py)));
    }
    if (quad.size() == 4) cv::polylines(canvas, quad, true, cv::Scalar(0, 255, 255), 2 * thickness, cv::LINE_AA);
  }
  if (drawing.db_region) {
    const auto& b = *drawing.db_region;
    cv::rectangle(canvas, cv::Point2f(b[0], b[1]) + offset, cv::Point2f(b[2], b[3]) + offset, cv::Scalar(255, 128, 0),
                  thickness, cv::LINE_AA);
  }

  const auto written = opencv_codecs::Write(output_path, canvas);
  if (!written) {
    if (written.error().code == ErrorCode::kUnsupportedFormat) return std::unexpected(written.error());
    return Fail(ErrorCode::kIoError, "cannot write " + output_path + ": " + written.error().message);
  }
  if (!*written) return Fail(ErrorCode::kIoError, "cannot write " + output_path + " (unknown extension or unwritable path)");
  return Ok();
}

}  // namespace oxbow::sift
