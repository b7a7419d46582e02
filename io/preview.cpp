#include "io/preview.hpp"

#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/errors.hpp"
#include "io/writers.hpp"

namespace amalgam {

void Image::set(int x, int y, const Vec3d& c) {
  std::uint8_t* p = rgb.data() + (size_t(y) * size_t(width) + size_t(x)) * 3;
  for (int k = 0; k < 3; ++k) p[k] = std::uint8_t(std::lround(std::clamp(c[k], 0.0, 1.0) * 255.0));
}

Vec3d Image::get(int x, int y) const {
  const std::uint8_t* p = rgb.data() + (size_t(y) * size_t(width) + size_t(x)) * 3;
  return Vec3d(p[0], p[1], p[2]) / 255.0;
}

Camera fit_camera(const Vec3d& lo, const Vec3d& hi, double fov_degrees, double aspect) {
  Camera c;
  c.fov_degrees = fov_degrees;
  c.target = 0.5 * (lo + hi);
  const double radius = 0.5 * (hi - lo).norm();
  const double half = 0.5 * fov_degrees * M_PI / 180.0;
  const double fit = std::min(std::tan(half), std::tan(half) * aspect);  // the narrower field
  const Vec3d dir = Vec3d(0.8, 0.55, 1.5).normalized();
  c.eye = c.target + dir * (radius / std::sin(std::atan(fit)) * 1.05);
  return c;
}

namespace {

// Eight distinct material colours.
Vec3d palette(int i) {
  static const double k[8][3] = {{0.90, 0.45, 0.25}, {0.30, 0.55, 0.90}, {0.45, 0.80, 0.40},
                                 {0.90, 0.80, 0.30}, {0.70, 0.45, 0.85}, {0.35, 0.80, 0.80},
                                 {0.85, 0.40, 0.55}, {0.75, 0.75, 0.75}};
  const int j = ((i % 8) + 8) % 8;
  return Vec3d(k[j][0], k[j][1], k[j][2]);
}

// Blue -> cyan -> yellow -> red for t in [0, 1].
Vec3d ramp(double t) {
  t = std::clamp(t, 0.0, 1.0);
  const Vec3d c0(0.15, 0.25, 0.85), c1(0.2, 0.8, 0.85), c2(0.95, 0.85, 0.25), c3(0.9, 0.2, 0.15);
  if (t < 1.0 / 3) return c0 + (c1 - c0) * (3 * t);
  if (t < 2.0 / 3) return c1 + (c2 - c1) * (3 * t - 1);
  return c2 + (c3 - c2) * (3 * t - 2);
}

}  // namespace

Image render_particles(const ParticleSet& ps, const MpmAttributes& a, const Camera& cam,
                       double radius, int width, int height, ColorBy color_by, double floor_y) {
  std::vector<float> scalar;
  const ParticleSet::Id id = color_by == ColorBy::Temperature ? a.temperature
                             : color_by == ColorBy::Plastic   ? a.plastic
                                                              : -1;
  if (id >= 0) scalar.assign(ps.real(id), ps.real(id) + ps.size());
  return render_points(ps.size(), ps.vec3(a.x), ps.vec3(a.v), ps.int32(a.material),
                       id >= 0 ? scalar.data() : nullptr, cam, radius, width, height, color_by,
                       floor_y);
}

Image render_points(std::size_t n, const Vec3* x, const Vec3* v, const std::int32_t* mat,
                    const float* scalar, const Camera& cam, double radius, int width, int height,
                    ColorBy color_by, double floor_y) {
  Image img;
  img.width = width;
  img.height = height;
  img.rgb.assign(size_t(width) * size_t(height) * 3, 0);
  for (int y = 0; y < height; ++y) {  // background: vertical grey gradient
    const double g = 0.22 + 0.18 * double(y) / double(height);
    for (int x = 0; x < width; ++x) img.set(x, y, Vec3d(g, g, g + 0.02));
  }
  const Vec3d fwd = (cam.target - cam.eye).normalized();
  const Vec3d right = fwd.cross(cam.up).normalized();
  const Vec3d up = right.cross(fwd);
  const double focal = 0.5 * double(height) / std::tan(0.5 * cam.fov_degrees * M_PI / 180.0);
  if (color_by != ColorBy::Speed && color_by != ColorBy::Material && !scalar)
    color_by = ColorBy::Material;
  // Ranges for the colour ramps and the depth cue.
  double smin = std::numeric_limits<double>::max(), smax = -smin, zmin = smin, zmax = -smin;
  for (size_t i = 0; i < n; ++i) {
    const double z = (x[i].cast<double>() - cam.eye).dot(fwd);
    zmin = std::min(zmin, z), zmax = std::max(zmax, z);
    const double s = color_by == ColorBy::Speed ? double(v[i].norm())
                     : scalar                   ? double(scalar[i])
                                                : 0.0;
    smin = std::min(smin, s), smax = std::max(smax, s);
  }
  if (color_by == ColorBy::Speed) smin = 0;
  const double srange = smax > smin ? smax - smin : 1.0, zrange = zmax > zmin ? zmax - zmin : 1.0;
  const Vec3d light =
      Vec3d(-0.4, 0.7, 0.6).normalized();  // camera space: up-left, towards the viewer
  std::vector<float> depth(size_t(width) * size_t(height), std::numeric_limits<float>::max());
  if (std::isfinite(floor_y)) {  // checkered floor, 0.1 m tiles, fading with distance
    for (int py = 0; py < height; ++py)
      for (int px = 0; px < width; ++px) {
        const Vec3d dir = fwd + ((px + 0.5 - 0.5 * width) / focal) * right -
                          ((py + 0.5 - 0.5 * height) / focal) * up;
        if (std::abs(dir[1]) < 1e-12) continue;
        const double t = (floor_y - cam.eye[1]) / dir[1];
        if (t <= 0) continue;
        const Vec3d q = cam.eye + t * dir;
        const bool odd = (long(std::floor(q[0] / 0.1)) + long(std::floor(q[2] / 0.1))) & 1;
        const double fade = std::exp(-0.15 * t);
        const double g = (odd ? 0.55 : 0.68) * fade + 0.3 * (1 - fade);
        img.set(px, py, Vec3d(g, g, g));
        depth[size_t(py) * size_t(width) + size_t(px)] = float(t);  // dir . fwd = 1: t is the depth
      }
  }
  for (size_t i = 0; i < n; ++i) {
    const Vec3d p = x[i].cast<double>() - cam.eye;
    const double z = p.dot(fwd);
    if (z <= radius) continue;
    const double sx = 0.5 * width + focal * p.dot(right) / z,
                 sy = 0.5 * height - focal * p.dot(up) / z;
    const double r = std::max(0.75, focal * radius / z);
    const int x0 = std::max(0, int(std::floor(sx - r))),
              x1 = std::min(width - 1, int(std::ceil(sx + r)));
    const int y0 = std::max(0, int(std::floor(sy - r))),
              y1 = std::min(height - 1, int(std::ceil(sy + r)));
    if (x0 > x1 || y0 > y1) continue;
    Vec3d base;
    switch (color_by) {
      case ColorBy::Material:
        base = palette(mat[i]);
        break;
      case ColorBy::Speed:
        base = ramp((double(v[i].norm()) - smin) / srange);
        break;
      default:
        base = ramp((double(scalar[i]) - smin) / srange);
        break;
    }
    const double cue = 1.0 - 0.45 * (z - zmin) / zrange;
    for (int py = y0; py <= y1; ++py)
      for (int px = x0; px <= x1; ++px) {
        const double dx = (px + 0.5 - sx) / r, dy = (py + 0.5 - sy) / r, d2 = dx * dx + dy * dy;
        if (d2 > 1) continue;
        const double nz = std::sqrt(1 - d2);
        const float zd = float(z - radius * nz);
        float& zb = depth[size_t(py) * size_t(width) + size_t(px)];
        if (zd >= zb) continue;
        zb = zd;
        const Vec3d nrm(dx, -dy, nz);  // camera space, z towards the viewer
        const double shade = 0.3 + 0.7 * std::max(0.0, nrm.dot(light));
        img.set(px, py, base * (shade * cue));
      }
  }
  return img;
}

namespace {
void put_be32(std::string& s, std::uint32_t v) {
  for (int k = 3; k >= 0; --k) s.push_back(char((v >> (8 * k)) & 0xff));
}
void chunk(std::string& out, const char* type, const std::string& data) {
  put_be32(out, std::uint32_t(data.size()));
  const std::string body = std::string(type, 4) + data;
  out += body;
  put_be32(out,
           std::uint32_t(crc32(0, reinterpret_cast<const Bytef*>(body.data()), uInt(body.size()))));
}
}  // namespace

std::string encode_png(const Image& img) {
  std::string raw;
  raw.reserve(size_t(img.height) * (size_t(img.width) * 3 + 1));
  for (int y = 0; y < img.height; ++y) {
    raw.push_back(0);  // filter: none
    raw.append(reinterpret_cast<const char*>(img.rgb.data()) + size_t(y) * size_t(img.width) * 3,
               size_t(img.width) * 3);
  }
  uLongf len = compressBound(uLong(raw.size()));
  std::string z(len, '\0');
  if (compress2(reinterpret_cast<Bytef*>(z.data()), &len,
                reinterpret_cast<const Bytef*>(raw.data()), uLong(raw.size()), 6) != Z_OK)
    throw InputError("PNG: zlib compression failed");
  z.resize(len);
  std::string out("\x89PNG\r\n\x1a\n", 8);
  std::string ihdr;
  put_be32(ihdr, std::uint32_t(img.width));
  put_be32(ihdr, std::uint32_t(img.height));
  ihdr += std::string("\x08\x02\x00\x00\x00", 5);  // 8 bits, RGB, deflate, no filter, no interlace
  chunk(out, "IHDR", ihdr);
  chunk(out, "IDAT", z);
  chunk(out, "IEND", "");
  return out;
}

void write_png(const std::string& path, const Image& img) {
  write_file_atomic(path, encode_png(img));
}

}  // namespace amalgam
