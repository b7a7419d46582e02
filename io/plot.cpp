#include "io/plot.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "core/errors.hpp"
#include "io/font5x7.hpp"

namespace amalgam {

std::map<std::string, std::vector<double>> read_csv_columns(const std::string& text, const std::string& file) {
  std::istringstream in(text);
  std::string line;
  if (!std::getline(in, line) || line.empty()) throw InputError(file + ": empty diagnostics file");
  std::vector<std::string> names;
  {
    std::istringstream h(line);
    std::string name;
    while (std::getline(h, name, ',')) names.push_back(name);
  }
  std::map<std::string, std::vector<double>> cols;
  for (const auto& n : names) cols[n];
  int lineno = 1;
  while (std::getline(in, line)) {
    ++lineno;
    if (line.empty()) continue;
    std::istringstream r(line);
    std::string cell;
    size_t c = 0;
    while (std::getline(r, cell, ',')) {
      if (c >= names.size())
        throw InputError(file + ":" + std::to_string(lineno) + ": more fields than the header's " +
                         std::to_string(names.size()));
      char* end = nullptr;
      const double v = std::strtod(cell.c_str(), &end);
      if (end == cell.c_str() || *end != '\0')
        throw InputError(file + ":" + std::to_string(lineno) + ": field '" + names[c] + "' is not a number: \"" + cell +
                         "\"");
      cols[names[c]].push_back(v);
      ++c;
    }
    if (c != names.size())
      throw InputError(file + ":" + std::to_string(lineno) + ": " + std::to_string(c) + " fields, header has " +
                       std::to_string(names.size()));
  }
  return cols;
}

void draw_text(Image& img, int x, int y, const std::string& text, const Vec3d& color, int scale) {
  for (size_t i = 0; i < text.size(); ++i) {
    const char* g = font::glyph(text[i]);
    for (int r = 0; r < font::kHeight; ++r)
      for (int c = 0; c < font::kWidth; ++c) {
        if (g[r * font::kWidth + c] != '#') continue;
        for (int sy = 0; sy < scale; ++sy)
          for (int sx = 0; sx < scale; ++sx) {
            const int px = x + (int(i) * (font::kWidth + 1) + c) * scale + sx, py = y + r * scale + sy;
            if (px >= 0 && py >= 0 && px < img.width && py < img.height) img.set(px, py, color);
          }
      }
  }
}

namespace {

struct Series {
  std::string name;
  const std::vector<double>* x;
  const std::vector<double>* y;
  Vec3d color;
};

void line(Image& img, double x0, double y0, double x1, double y1, const Vec3d& c) {
  const int n = int(std::ceil(std::max(std::abs(x1 - x0), std::abs(y1 - y0)))) + 1;
  for (int k = 0; k <= n; ++k) {
    const double t = double(k) / n;
    const int px = int(std::lround(x0 + t * (x1 - x0))), py = int(std::lround(y0 + t * (y1 - y0)));
    for (int d = 0; d < 2; ++d)  // 2 px thick
      if (px >= 0 && py + d >= 0 && px < img.width && py + d < img.height) img.set(px, py + d, c);
  }
}

std::string num(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%.3g", v);
  return b;
}

// One panel in the box (x0, y0, w, h): frame, title, axis range labels, series, legend.
void panel(Image& img, int x0, int y0, int w, int h, const std::string& title, const std::string& xlabel,
           const std::vector<Series>& series, bool log_y, bool log_x = false) {
  const Vec3d ink(0.1, 0.1, 0.1), grid(0.85, 0.85, 0.85);
  const int left = x0 + 70, right = x0 + w - 10, top = y0 + 24, bottom = y0 + h - 30;
  draw_text(img, x0 + 8, y0 + 4, title, ink, 2);
  double xmin = 1e300, xmax = -1e300, ymin = 1e300, ymax = -1e300;
  for (const auto& s : series)
    for (size_t i = 0; i < s.x->size() && i < s.y->size(); ++i) {
      const double yv = (*s.y)[i];
      if (!std::isfinite(yv) || (log_y && yv <= 0) || (log_x && !((*s.x)[i] > 0))) continue;
      xmin = std::min(xmin, (*s.x)[i]), xmax = std::max(xmax, (*s.x)[i]);
      ymin = std::min(ymin, yv), ymax = std::max(ymax, yv);
    }
  if (xmin > xmax) {
    draw_text(img, left + 10, top + 10, "NO DATA", ink, 2);
    return;
  }
  if (!log_y) ymin = std::min(ymin, 0.0);
  if (xmax == xmin) xmax = xmin + 1;
  if (ymax == ymin) ymax = ymin + (log_y ? ymin : 1.0);
  auto Y = [&](double v) { return log_y ? std::log10(v) : v; };
  auto X = [&](double v) { return log_x ? std::log10(v) : v; };
  const double ly0 = Y(ymin), ly1 = Y(ymax);
  auto sx = [&](double v) { return left + (X(v) - X(xmin)) / (X(xmax) - X(xmin)) * (right - left); };
  auto sy = [&](double v) { return bottom - (Y(v) - ly0) / (ly1 - ly0) * (bottom - top); };
  for (int k = 0; k <= 4; ++k) {  // horizontal grid lines with labels
    const double yl = ly0 + (ly1 - ly0) * k / 4;
    const int py = int(std::lround(bottom - (bottom - top) * double(k) / 4));
    for (int px = left; px <= right; ++px) img.set(px, py, grid);
    draw_text(img, x0 + 4, py - 3, num(log_y ? std::pow(10.0, yl) : yl), ink);
  }
  for (int px = left; px <= right; ++px) img.set(px, bottom, ink), img.set(px, top, ink);
  for (int py = top; py <= bottom; ++py) img.set(left, py, ink), img.set(right, py, ink);
  if (log_x)  // vertical grid lines at the x samples of the first series, labelled
    for (size_t i = 0; !series.empty() && i < series[0].x->size(); ++i) {
      const double xv = (*series[0].x)[i];
      if (!(xv > xmin && xv < xmax)) continue;
      const int px = int(std::lround(sx(xv)));
      for (int py = top; py <= bottom; ++py) img.set(px, py, grid);
      const std::string l = num(xv);
      draw_text(img, px - int(l.size()) * 3, bottom + 6, l, ink);
    }
  draw_text(img, left, bottom + 6, num(xmin), ink);
  const std::string xm = num(xmax);
  draw_text(img, right - int(xm.size()) * 6, bottom + 6, xm, ink);
  draw_text(img, (left + right) / 2 - int(xlabel.size()) * 3, bottom + 16, xlabel, ink);
  int lx = left + 8;
  for (const auto& s : series) {
    for (size_t i = 1; i < s.x->size() && i < s.y->size(); ++i) {
      const double a = (*s.y)[i - 1], b = (*s.y)[i];
      if (!std::isfinite(a) || !std::isfinite(b) || (log_y && (a <= 0 || b <= 0))) continue;
      line(img, sx((*s.x)[i - 1]), sy(a), sx((*s.x)[i]), sy(b), s.color);
    }
    for (size_t i = 0; log_x && i < s.x->size() && i < s.y->size(); ++i)  // markers at the samples
      if (std::isfinite((*s.y)[i]) && (*s.y)[i] > 0)
        for (int d = -3; d <= 3; ++d) line(img, sx((*s.x)[i]) - 3, sy((*s.y)[i]) + d, sx((*s.x)[i]) + 3, sy((*s.y)[i]) + d, s.color);
    if (s.x->size() == 1 && s.y->size() == 1 && std::isfinite((*s.y)[0]))
      line(img, sx((*s.x)[0]) - 2, sy((*s.y)[0]), sx((*s.x)[0]) + 2, sy((*s.y)[0]), s.color);
    line(img, lx, top + 10, lx + 16, top + 10, s.color);  // legend
    draw_text(img, lx + 20, top + 7, s.name, ink);
    lx += 20 + int(s.name.size()) * 6 + 16;
  }
}

}  // namespace

Image plot_loglog(const std::string& title, const std::vector<LogLogPanel>& panels) {
  static const Vec3d palette[] = {{0.85, 0.2, 0.15}, {0.15, 0.35, 0.85}, {0.1, 0.1, 0.1},
                                  {0.1, 0.6, 0.2},   {0.95, 0.55, 0.1}, {0.55, 0.25, 0.7}};
  Image img;
  img.width = 900;
  img.height = 40 + int(panels.size()) * 340;
  img.rgb.assign(size_t(img.width) * size_t(img.height) * 3, 255);
  draw_text(img, 10, 10, title, Vec3d(0, 0, 0), 2);
  for (size_t k = 0; k < panels.size(); ++k) {
    std::vector<Series> series;
    for (size_t i = 0; i < panels[k].series.size(); ++i) {
      const PlotSeries& s = panels[k].series[i];
      series.push_back({s.name, &s.x, &s.y, palette[i % 6]});
    }
    panel(img, 0, 40 + int(k) * 340, img.width, 340, panels[k].title, panels[k].xlabel, series, true, true);
  }
  return img;
}

Image plot_diagnostics(const std::map<std::string, std::vector<double>>& cols, const std::string& title) {
  auto col = [&](const std::string& n) -> const std::vector<double>& {
    const auto it = cols.find(n);
    if (it == cols.end()) throw InputError("diagnostics: missing column '" + n + "'");
    return it->second;
  };
  // Columns added later (implicit solve time) are optional, so older runs still plot.
  static const std::vector<double> none;
  auto optional_col = [&](const std::string& n) -> const std::vector<double>& {
    const auto it = cols.find(n);
    return it == cols.end() ? none : it->second;
  };
  const std::vector<double>& t = col("time_s");
  const std::vector<double>& frame = col("frame");
  const std::vector<double>& ke = col("kinetic_J");
  const std::vector<double>& ee = col("elastic_J");
  std::vector<double> total;
  total.assign(ke.size(), 0);
  for (size_t i = 0; i < ke.size() && i < ee.size(); ++i) total[i] = ke[i] + ee[i];
  Image img;
  img.width = 900;
  img.height = 40 + 3 * 260;
  img.rgb.assign(size_t(img.width) * size_t(img.height) * 3, 255);
  draw_text(img, 10, 10, title, Vec3d(0, 0, 0), 2);
  const Vec3d red(0.85, 0.2, 0.15), blue(0.15, 0.35, 0.85), green(0.1, 0.6, 0.2), orange(0.95, 0.55, 0.1),
      purple(0.55, 0.25, 0.7), grey(0.45, 0.45, 0.45);
  panel(img, 0, 40, img.width, 260, "ENERGY (J)", "TIME (S)",
        {{"KINETIC", &t, &ke, red}, {"ELASTIC", &t, &ee, blue}, {"KINETIC+ELASTIC", &t, &total, grey}}, false);
  panel(img, 0, 300, img.width, 260, "SUBSTEP DT (S), LOG", "TIME (S)", {{"DT", &t, &col("last_dt_s"), green}}, true);
  panel(img, 0, 560, img.width, 260, "SECONDS PER FRAME", "FRAME",
        {{"P2G", &frame, &col("p2g_s"), red},
         {"G2P", &frame, &col("g2p_s"), blue},
         {"SORT", &frame, &col("sort_s"), green},
         {"GRID", &frame, &col("grid_s"), orange},
         {"SOLVE", &frame, &optional_col("solve_s"), grey},
         {"OTHER", &frame, &col("other_s"), purple}},
        false);
  return img;
}

}  // namespace amalgam
