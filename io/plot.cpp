#include "io/plot.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "core/errors.hpp"
#include "io/font5x7.hpp"

namespace amalgam {

std::map<std::string, std::vector<double>> read_csv_columns(const std::string& text,
                                                            const std::string& file) {
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
        throw InputError(file + ":" + std::to_string(lineno) + ": field '" + names[c] +
                         "' is not a number: \"" + cell + "\"");
      cols[names[c]].push_back(v);
      ++c;
    }
    if (c != names.size())
      throw InputError(file + ":" + std::to_string(lineno) + ": " + std::to_string(c) +
                       " fields, header has " + std::to_string(names.size()));
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
            const int px = x + (int(i) * (font::kWidth + 1) + c) * scale + sx,
                      py = y + r * scale + sy;
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
void panel(Image& img, int x0, int y0, int w, int h, const std::string& title,
           const std::string& xlabel, const std::vector<Series>& series, bool log_y,
           bool log_x = false) {
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
  auto sx = [&](double v) {
    return left + (X(v) - X(xmin)) / (X(xmax) - X(xmin)) * (right - left);
  };
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
        for (int d = -3; d <= 3; ++d)
          line(img, sx((*s.x)[i]) - 3, sy((*s.y)[i]) + d, sx((*s.x)[i]) + 3, sy((*s.y)[i]) + d,
               s.color);
    if (s.x->size() == 1 && s.y->size() == 1 && std::isfinite((*s.y)[0]))
      line(img, sx((*s.x)[0]) - 2, sy((*s.y)[0]), sx((*s.x)[0]) + 2, sy((*s.y)[0]), s.color);
    line(img, lx, top + 10, lx + 16, top + 10, s.color);  // legend
    draw_text(img, lx + 20, top + 7, s.name, ink);
    lx += 20 + int(s.name.size()) * 6 + 16;
  }
}

}  // namespace

namespace {
const Vec3d kPalette[] = {{0.85, 0.2, 0.15}, {0.15, 0.35, 0.85}, {0.1, 0.6, 0.2},
                          {0.95, 0.55, 0.1}, {0.55, 0.25, 0.7},  {0.1, 0.65, 0.7},
                          {0.35, 0.2, 0.1},  {0.75, 0.5, 0.3},   {0.9, 0.4, 0.7},
                          {0.4, 0.4, 0.1},   {0.25, 0.25, 0.45}, {0.5, 0.8, 0.4}};
constexpr int kPaletteSize = int(sizeof kPalette / sizeof kPalette[0]);

Image blank(int w, int h) {
  Image img;
  img.width = w, img.height = h;
  img.rgb.assign(size_t(w) * size_t(h) * 3, 255);
  return img;
}

void fill(Image& img, int x0, int y0, int x1, int y1, const Vec3d& c) {
  for (int y = std::max(0, std::min(y0, y1)); y <= std::min(img.height - 1, std::max(y0, y1)); ++y)
    for (int x = std::max(0, std::min(x0, x1)); x <= std::min(img.width - 1, std::max(x0, x1)); ++x)
      img.set(x, y, c);
}
}  // namespace

Image plot_bars(const BarChart& chart) {
  const Vec3d ink(0.1, 0.1, 0.1), grid(0.85, 0.85, 0.85);
  const int ng = int(chart.groups.size()), ns = int(chart.series.size());
  const int width = std::max(900, 120 + ng * (ns * 16 + 30)), height = 520;
  Image img = blank(width, height);
  draw_text(img, 10, 10, chart.title, ink, 2);
  const int left = 70, right = width - 20, top = 70, bottom = height - 60;
  double ymax = chart.reference;
  for (int g = 0; g < ng; ++g)
    for (int k = 0; k < ns; ++k) {
      if (size_t(k) < chart.values[g].size()) ymax = std::max(ymax, chart.values[g][k]);
      if (size_t(g) < chart.high.size() && size_t(k) < chart.high[g].size())
        ymax = std::max(ymax, chart.high[g][k]);
    }
  if (!(ymax > 0)) ymax = 1;
  ymax *= 1.08;
  auto sy = [&](double v) { return int(std::lround(bottom - v / ymax * (bottom - top))); };
  for (int k = 0; k <= 5; ++k) {
    const double v = ymax * k / 5;
    const int py = sy(v);
    for (int px = left; px <= right; ++px) img.set(px, py, grid);
    draw_text(img, 6, py - 3, num(v), ink);
  }
  draw_text(img, 6, top - 16, chart.ylabel, ink);
  for (int px = left; px <= right; ++px) img.set(px, bottom, ink);
  for (int py = top; py <= bottom; ++py) img.set(left, py, ink);
  int lx = left;  // legend
  for (int k = 0; k < ns; ++k) {
    fill(img, lx, 40, lx + 12, 50, kPalette[k % kPaletteSize]);
    draw_text(img, lx + 16, 42, chart.series[size_t(k)], ink);
    lx += 16 + int(chart.series[size_t(k)].size()) * 6 + 18;
  }
  const double gw = double(right - left) / std::max(1, ng);
  const int bw = std::max(4, std::min(24, int((gw - 20) / std::max(1, ns))));
  for (int g = 0; g < ng; ++g) {
    const int gx = int(left + g * gw + (gw - bw * ns) / 2);
    for (int k = 0; k < ns && size_t(k) < chart.values[g].size(); ++k) {
      const double v = chart.values[g][k];
      if (!std::isfinite(v)) continue;
      const int x0 = gx + k * bw, x1 = x0 + bw - 3;
      fill(img, x0, sy(v), x1, bottom - 1, kPalette[k % kPaletteSize]);
      if (size_t(g) < chart.low.size() && size_t(k) < chart.low[g].size() &&
          size_t(g) < chart.high.size() && size_t(k) < chart.high[g].size()) {
        const int xm = (x0 + x1) / 2, ylo = sy(chart.low[g][k]), yhi = sy(chart.high[g][k]);
        fill(img, xm, yhi, xm, ylo, ink);
        fill(img, xm - 3, yhi, xm + 3, yhi, ink);
        fill(img, xm - 3, ylo, xm + 3, ylo, ink);
      }
    }
    const std::string& name = chart.groups[size_t(g)];
    draw_text(img, int(left + g * gw + gw / 2) - int(name.size()) * 3, bottom + 8 + (g % 2) * 12,
              name, ink);
  }
  if (chart.reference > 0) {
    const int py = sy(chart.reference);
    for (int px = left; px <= right; px += 8)
      fill(img, px, py, std::min(right, px + 4), py + 1, ink);
  }
  return img;
}

Image plot_breakdown(const std::string& title, const std::vector<BreakdownBar>& bars) {
  const Vec3d ink(0.1, 0.1, 0.1);
  std::vector<std::string> labels;  // colour of a segment label: order of first appearance
  auto colour = [&](const std::string& l) {
    if (l == "other") return Vec3d(0.72, 0.72, 0.72);
    auto it = std::find(labels.begin(), labels.end(), l);
    if (it == labels.end()) it = labels.insert(labels.end(), l);
    return kPalette[(it - labels.begin()) % kPaletteSize];
  };
  const int width = 1100, row = 72, left = 10, right = width - 10;
  Image img = blank(width, 40 + row * int(bars.size()));
  draw_text(img, 10, 10, title, ink, 2);
  for (size_t b = 0; b < bars.size(); ++b) {
    const int y = 40 + int(b) * row;
    draw_text(img, left, y, bars[b].label, ink);
    double total = 0;
    for (const auto& s : bars[b].segments) total += std::max(0.0, s.second);
    if (!(total > 0)) continue;
    double acc = 0;
    int lx = left, ly = y + 36;
    for (const auto& s : bars[b].segments) {
      const Vec3d c = colour(s.first);
      const int x0 = left + int(std::lround(acc / total * (right - left)));
      acc += std::max(0.0, s.second);
      const int x1 = left + int(std::lround(acc / total * (right - left)));
      if (x1 > x0) fill(img, x0, y + 12, x1 - 1, y + 30, c);
      const std::string text = s.first + " " + num(100 * s.second / total) + "%";
      const int w = 16 + int(text.size()) * 6 + 12;
      if (lx + w > right) lx = left, ly += 11;
      fill(img, lx, ly, lx + 10, ly + 7, c);
      draw_text(img, lx + 14, ly, text, ink);
      lx += w;
    }
  }
  return img;
}

Image plot_loglog(const std::string& title, const std::vector<LogLogPanel>& panels) {
  static const Vec3d palette[] = {{0.85, 0.2, 0.15}, {0.15, 0.35, 0.85}, {0.1, 0.1, 0.1},
                                  {0.1, 0.6, 0.2},   {0.95, 0.55, 0.1},  {0.55, 0.25, 0.7}};
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
    panel(img, 0, 40 + int(k) * 340, img.width, 340, panels[k].title, panels[k].xlabel, series,
          true, true);
  }
  return img;
}

Image plot_diagnostics(const std::map<std::string, std::vector<double>>& cols,
                       const std::string& title) {
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
  const Vec3d red(0.85, 0.2, 0.15), blue(0.15, 0.35, 0.85), green(0.1, 0.6, 0.2),
      orange(0.95, 0.55, 0.1), purple(0.55, 0.25, 0.7), grey(0.45, 0.45, 0.45);
  panel(img, 0, 40, img.width, 260, "ENERGY (J)", "TIME (S)",
        {{"KINETIC", &t, &ke, red},
         {"ELASTIC", &t, &ee, blue},
         {"KINETIC+ELASTIC", &t, &total, grey}},
        false);
  panel(img, 0, 300, img.width, 260, "SUBSTEP DT (S), LOG", "TIME (S)",
        {{"DT", &t, &col("last_dt_s"), green}}, true);
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
