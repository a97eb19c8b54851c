#include "eval/plot.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <opencv2/imgproc.hpp>

#include "sift/opencv_codecs.h"

namespace oxbow::eval {
namespace {

// Okabe-Ito palette (distinguishable with colour-vision deficiencies), BGR.
const cv::Scalar kPalette[] = {{178, 114, 0},  {0, 94, 213},   {115, 158, 0}, {167, 121, 204},
                               {66, 228, 240}, {233, 180, 86}, {0, 159, 230}, {0, 0, 0}};
constexpr int kMarginLeft = 80, kMarginRight = 30, kMarginTop = 50, kMarginBottom = 130;

cv::Scalar Colour(size_t i) { return kPalette[i % (sizeof(kPalette) / sizeof(kPalette[0]))]; }

void DrawMarker(cv::Mat& img, cv::Point p, size_t series, const cv::Scalar& colour) {
  const int s = 4;
  switch (series % 4) {
    case 0: cv::circle(img, p, s, colour, cv::FILLED, cv::LINE_AA); break;
    case 1: cv::rectangle(img, p - cv::Point(s, s), p + cv::Point(s, s), colour, cv::FILLED); break;
    case 2: {
      std::vector<cv::Point> tri = {p + cv::Point(0, -s - 1), p + cv::Point(s + 1, s), p + cv::Point(-s - 1, s)};
      cv::fillConvexPoly(img, tri, colour, cv::LINE_AA);
      break;
    }
    default:
      cv::line(img, p - cv::Point(s, s), p + cv::Point(s, s), colour, 2, cv::LINE_AA);
      cv::line(img, p - cv::Point(s, -s), p + cv::Point(s, -s), colour, 2, cv::LINE_AA);
  }
}

std::string FormatTick(double v) {
  char buf[32];
  if (std::fabs(v) >= 1000) {
    std::snprintf(buf, sizeof buf, "%.0fk", v / 1000);
  } else {
    std::snprintf(buf, sizeof buf, "%.2g", v);
  }
  return buf;
}

void PutText(cv::Mat& img, const std::string& text, cv::Point at, double scale = 0.45, int thickness = 1) {
  cv::putText(img, text, at, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(30, 30, 30), thickness, cv::LINE_AA);
}

struct Frame {
  cv::Rect area;
  double x_min, x_max, y_min, y_max;
  bool log_x;
  cv::Point Map(double x, double y) const {
    double fx = log_x ? (std::log10(x) - std::log10(x_min)) / (std::log10(x_max) - std::log10(x_min))
                      : (x - x_min) / (x_max - x_min);
    double fy = (y - y_min) / (y_max - y_min);
    fx = std::clamp(fx, 0.0, 1.0);
    fy = std::clamp(fy, 0.0, 1.0);
    return {area.x + static_cast<int>(fx * area.width), area.y + area.height - static_cast<int>(fy * area.height)};
  }
};

cv::Mat NewCanvas(const ChartOptions& options, Frame* frame) {
  cv::Mat img(options.height_px, options.width_px, CV_8UC3, cv::Scalar(255, 255, 255));
  frame->area = cv::Rect(kMarginLeft, kMarginTop, options.width_px - kMarginLeft - kMarginRight,
                         options.height_px - kMarginTop - kMarginBottom);
  PutText(img, options.title, {kMarginLeft, 30}, 0.6, 1);
  PutText(img, options.x_label, {frame->area.x + frame->area.width / 2 - 40, options.height_px - 15});
  PutText(img, options.y_label, {5, kMarginTop - 10});
  return img;
}

void DrawAxes(cv::Mat& img, const Frame& f, bool x_ticks, const std::vector<double>& x_tick_values = {}) {
  cv::rectangle(img, f.area, cv::Scalar(60, 60, 60), 1);
  for (int i = 0; i <= 5; ++i) {
    const double y = f.y_min + (f.y_max - f.y_min) * i / 5.0;
    const cv::Point p = f.Map(f.x_min, y);
    cv::line(img, p, p + cv::Point(f.area.width, 0), cv::Scalar(225, 225, 225), 1);
    PutText(img, FormatTick(y), p + cv::Point(-45, 5));
  }
  if (!x_ticks) return;
  std::vector<double> xs = x_tick_values;
  if (xs.empty()) {
    for (int i = 0; i <= 5; ++i) {
      xs.push_back(f.log_x ? std::pow(10.0, std::log10(f.x_min) + (std::log10(f.x_max) - std::log10(f.x_min)) * i / 5.0)
                           : f.x_min + (f.x_max - f.x_min) * i / 5.0);
    }
  }
  for (double x : xs) {
    const cv::Point p = f.Map(x, f.y_min);
    cv::line(img, p, p + cv::Point(0, -f.area.height), cv::Scalar(225, 225, 225), 1);
    PutText(img, FormatTick(x), p + cv::Point(-12, 20));
  }
}

void DrawLegend(cv::Mat& img, const Frame& f, const std::vector<std::string>& names, bool at_bottom = false) {
  if (names.empty()) return;
  // An opaque box behind the entries, so the legend stays readable over the data.
  int text_width = 0;
  for (const std::string& name : names) {
    int baseline = 0;
    text_width = std::max(text_width, cv::getTextSize(name, cv::FONT_HERSHEY_SIMPLEX, 0.42, 1, &baseline).width);
  }
  const int box_width = text_width + 30;
  const int box_height = static_cast<int>(names.size()) * 18 + 8;
  const cv::Rect box(f.area.x + f.area.width - box_width - 6,
                     at_bottom ? f.area.y + f.area.height - box_height - 6 : f.area.y + 6, box_width, box_height);
  cv::rectangle(img, box, cv::Scalar(255, 255, 255), cv::FILLED);
  cv::rectangle(img, box, cv::Scalar(160, 160, 160), 1);
  int y = box.y + 12;
  for (size_t i = 0; i < names.size(); ++i) {
    const cv::Point p(box.x + 10, y);
    DrawMarker(img, p, i, Colour(i));
    PutText(img, names[i], p + cv::Point(12, 5), 0.42);
    y += 18;
  }
}

Status Save(const std::string& path, const cv::Mat& img) {
  const auto written = sift::opencv_codecs::Write(path, img);
  if (!written) return Fail(written.error().code == ErrorCode::kUnsupportedFormat ? ErrorCode::kUnsupportedFormat : ErrorCode::kIoError,
                            "cannot write chart '" + path + "': " + written.error().message);
  if (!*written) return Fail(ErrorCode::kIoError, "cannot write chart '" + path + "'");
  return Ok();
}

}  // namespace

Status WriteLineChart(const std::string& png_path, const std::vector<Series>& series, const ChartOptions& options) {
  Frame f{};
  cv::Mat img = NewCanvas(options, &f);
  f.log_x = options.log_x;
  f.x_min = options.x_min;
  f.x_max = options.x_max;
  f.y_min = options.y_min;
  f.y_max = options.y_max;
  if (f.x_min >= f.x_max || f.y_min >= f.y_max) {  // auto range
    double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
    for (const Series& s : series) {
      for (auto [x, y] : s.points) {
        x0 = std::min(x0, x);
        x1 = std::max(x1, x);
        y0 = std::min(y0, y);
        y1 = std::max(y1, y);
      }
    }
    if (!(x0 < x1)) x1 = x0 + 1;
    if (!(y0 < y1)) y1 = y0 + 1;
    if (options.x_min >= options.x_max) { f.x_min = x0; f.x_max = x1; }
    if (options.y_min >= options.y_max) { f.y_min = std::min(0.0, y0); f.y_max = y1 * 1.05; }
  }
  if (f.log_x && f.x_min <= 0) f.log_x = false;
  DrawAxes(img, f, true, options.x_ticks);
  std::vector<std::string> names;
  for (size_t i = 0; i < series.size(); ++i) {
    names.push_back(series[i].name);
    std::vector<cv::Point> pts;
    for (auto [x, y] : series[i].points) pts.push_back(f.Map(x, y));
    if (pts.size() > 1) cv::polylines(img, pts, false, Colour(i), 2, cv::LINE_AA);
    for (const cv::Point& p : pts) DrawMarker(img, p, i, Colour(i));
  }
  DrawLegend(img, f, names, options.legend_at_bottom);
  return Save(png_path, img);
}

Status WriteBarChart(const std::string& png_path, const std::vector<std::string>& categories,
                     const std::vector<std::string>& series_names, const std::vector<std::vector<double>>& values,
                     const ChartOptions& options) {
  Frame f{};
  cv::Mat img = NewCanvas(options, &f);
  f.log_x = false;
  f.x_min = 0;
  f.x_max = 1;
  f.y_min = options.y_min;
  f.y_max = options.y_max > options.y_min ? options.y_max : 1.0;
  DrawAxes(img, f, false);
  const size_t groups = std::max<size_t>(1, categories.size());
  const double group_width = static_cast<double>(f.area.width) / groups;
  const size_t n_series = std::max<size_t>(1, series_names.size());
  const double bar_width = group_width * 0.8 / n_series;
  for (size_t c = 0; c < categories.size(); ++c) {
    for (size_t s = 0; s < values.size() && s < n_series; ++s) {
      if (c >= values[s].size()) continue;
      const int x0 = f.area.x + static_cast<int>(c * group_width + group_width * 0.1 + s * bar_width);
      const cv::Point top = f.Map(0, values[s][c]);
      cv::rectangle(img, cv::Point(x0, top.y), cv::Point(x0 + std::max(1, static_cast<int>(bar_width) - 1),
                                                           f.area.y + f.area.height),
                    Colour(s), cv::FILLED);
    }
    // Category label, rotated by drawing into a temporary image when space is short.
    const std::string& label = categories[c];
    const int cx = f.area.x + static_cast<int>((c + 0.5) * group_width);
    cv::Mat text(20, 160, CV_8UC3, cv::Scalar(255, 255, 255));
    cv::putText(text, label, {2, 14}, cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(30, 30, 30), 1, cv::LINE_AA);
    cv::Mat rotated;
    cv::rotate(text, rotated, cv::ROTATE_90_COUNTERCLOCKWISE);
    const int x = std::clamp(cx - 10, 0, img.cols - rotated.cols);
    const int y = f.area.y + f.area.height + 4;
    const int h = std::min(rotated.rows, img.rows - y);
    if (h > 0) rotated(cv::Rect(0, rotated.rows - h, rotated.cols, h)).copyTo(img(cv::Rect(x, y, rotated.cols, h)));
  }
  DrawLegend(img, f, series_names);
  return Save(png_path, img);
}

}  // namespace oxbow::eval
