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
std::map<std::string, std::vector<double>> read_csv_columns(const std::string& text, const std::string& file);

// Three panels: kinetic, elastic and total energy vs time; substep dt vs time; seconds per
// frame in P2G, G2P, sort, grid and other vs frame.
Image plot_diagnostics(const std::map<std::string, std::vector<double>>& cols, const std::string& title);

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

// Text in the 5x7 font, scaled by `scale`, top-left at (x, y).
void draw_text(Image& img, int x, int y, const std::string& text, const Vec3d& color, int scale = 1);

}  // namespace amalgam
