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

// Text in the 5x7 font, scaled by `scale`, top-left at (x, y).
void draw_text(Image& img, int x, int y, const std::string& text, const Vec3d& color, int scale = 1);

}  // namespace amalgam
