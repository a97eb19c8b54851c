// Small PNG charts for evaluation reports (line charts and grouped bar charts), drawn with OpenCV so the
// reports need nothing beyond the project's own dependencies. Colours are paired with distinct marker
// shapes / hatching-free labels so a chart stays readable without colour.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::eval {

struct Series {
  std::string name;
  std::vector<std::pair<double, double>> points;  // (x, y)
};

struct ChartOptions {
  std::string title;
  std::string x_label;
  std::string y_label;
  double x_min = 0, x_max = 1;  // axis ranges; ignored (auto) when min >= max
  double y_min = 0, y_max = 1;
  bool log_x = false;           // logarithmic x axis (for vocabulary sizes); x values must be > 0
  std::vector<double> x_ticks = {};  // x positions of the tick labels (e.g. the measured sizes); empty: 6 even steps
  bool legend_at_bottom = false;  // legend in the bottom-right corner instead of the top-right
  int width_px = 900;
  int height_px = 600;
};

// Line chart, one polyline with markers per series, legend top-right. Writes a PNG.
[[nodiscard]] Status WriteLineChart(const std::string& png_path, const std::vector<Series>& series,
                                    const ChartOptions& options);

// Grouped bar chart: categories along x (labels rotated when many), one bar per series in each group.
// values[s][c] is series s at category c. Writes a PNG.
[[nodiscard]] Status WriteBarChart(const std::string& png_path, const std::vector<std::string>& categories,
                                   const std::vector<std::string>& series_names,
                                   const std::vector<std::vector<double>>& values, const ChartOptions& options);

}  // namespace oxbow::eval
