// `amalgam plot`: the per-frame diagnostics CSV of a run drawn to a PNG (energy, time step,
// time per kernel), so a TD can judge a run without a plotting package.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "io/preview.hpp"

namespace amalgam {

// Columns of a diagnostics CSV by header name. Throws InputError naming the file and line on a
// malformed row.
std::map<std::string, std::vector<double>> read_csv_columns(const std::string& text,
                                                            const std::string& file);

// Three panels: kinetic, elastic and total energy vs time; substep dt vs time; seconds per
// frame in P2G, G2P, sort, grid and other vs frame.
Image plot_diagnostics(const std::map<std::string, std::vector<double>>& cols,
                       const std::string& title);

// Log-log panels stacked vertically (convergence studies): each series a polyline with markers at
// its samples and a legend entry; the x samples of a panel's first series label its x axis.
struct PlotSeries {
  std::string name;
  std::vector<double> x, y;
};
struct LogLogPanel {
  std::string title, xlabel;
  std::vector<PlotSeries> series;
};
Image plot_loglog(const std::string& title, const std::vector<LogLogPanel>& panels);

// Grouped vertical bars (benchmark scaling): one group per entry of `groups`, one bar per
// series inside each group, values[g][s] with optional whiskers low/high (same shape; empty:
// none) and a dashed horizontal reference line (<= 0: none). Linear y axis from 0.
struct BarChart {
  std::string title, ylabel;
  std::vector<std::string> groups, series;
  std::vector<std::vector<double>> values, low, high;
  double reference = 0;
};
Image plot_bars(const BarChart& chart);

// Horizontal stacked bars (time breakdown), one per entry, each normalised to its own total;
// a segment keeps one colour for its label across bars, and each bar lists its segments with
// their shares below it.
struct BreakdownBar {
  std::string label;
  std::vector<std::pair<std::string, double>> segments;  // label, value (> 0)
};
Image plot_breakdown(const std::string& title, const std::vector<BreakdownBar>& bars);

// Text in the 5x7 font, scaled by `scale`, top-left at (x, y).
void draw_text(Image& img, int x, int y, const std::string& text, const Vec3d& color,
               int scale = 1);

}  // namespace amalgam
