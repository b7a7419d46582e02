// Preview images and diagnostics plots: the PNG encoder round-trips (chunk CRCs, inflated pixel
// rows), the splat renderer puts a particle where the camera looks and keeps the nearer of two,
// and the CSV reader names the file and line of a malformed row.
#include <gtest/gtest.h>
#include <zlib.h>

#include <cstring>

#include "core/errors.hpp"
#include "io/plot.hpp"
#include "io/preview.hpp"

using namespace amalgam;

namespace {
std::uint32_t be32(const std::string& s, size_t at) {
  return (std::uint32_t(std::uint8_t(s[at])) << 24) |
         (std::uint32_t(std::uint8_t(s[at + 1])) << 16) |
         (std::uint32_t(std::uint8_t(s[at + 2])) << 8) | std::uint32_t(std::uint8_t(s[at + 3]));
}

// Decodes the PNG subset encode_png writes (RGB8, filter 0) back to pixels.
Image decode(const std::string& png) {
  EXPECT_EQ(png.substr(0, 8), std::string("\x89PNG\r\n\x1a\n", 8));
  Image img;
  std::string idat;
  size_t at = 8;
  while (at + 12 <= png.size()) {
    const std::uint32_t len = be32(png, at);
    const std::string type = png.substr(at + 4, 4);
    const std::string body = png.substr(at + 4, 4 + len);
    EXPECT_EQ(
        be32(png, at + 8 + len),
        std::uint32_t(crc32(0, reinterpret_cast<const Bytef*>(body.data()), uInt(body.size()))))
        << type;
    if (type == "IHDR") {
      img.width = int(be32(png, at + 8));
      img.height = int(be32(png, at + 12));
    } else if (type == "IDAT") {
      idat += png.substr(at + 8, len);
    }
    at += 12 + len;
  }
  std::string raw(size_t(img.height) * (size_t(img.width) * 3 + 1), '\0');
  uLongf n = uLongf(raw.size());
  EXPECT_EQ(uncompress(reinterpret_cast<Bytef*>(raw.data()), &n,
                       reinterpret_cast<const Bytef*>(idat.data()), uLong(idat.size())),
            Z_OK);
  img.rgb.resize(size_t(img.width) * size_t(img.height) * 3);
  for (int y = 0; y < img.height; ++y) {
    EXPECT_EQ(raw[size_t(y) * (size_t(img.width) * 3 + 1)], 0);
    std::memcpy(img.rgb.data() + size_t(y) * size_t(img.width) * 3,
                raw.data() + size_t(y) * (size_t(img.width) * 3 + 1) + 1, size_t(img.width) * 3);
  }
  return img;
}

ParticleSet particles(const std::vector<Vec3>& x, const std::vector<int>& material,
                      MpmAttributes& a) {
  ParticleSet ps;
  a = MpmAttributes::add_to(ps);
  ps.resize(x.size());
  for (size_t i = 0; i < x.size(); ++i) {
    ps.vec3(a.x)[i] = x[i];
    ps.int32(a.material)[i] = material[i];
  }
  return ps;
}
}  // namespace

TEST(Preview, PngRoundTrip) {
  Image img;
  img.width = 7;
  img.height = 5;
  img.rgb.resize(7 * 5 * 3);
  for (size_t i = 0; i < img.rgb.size(); ++i) img.rgb[i] = std::uint8_t(i * 37 + 11);
  const Image back = decode(encode_png(img));
  EXPECT_EQ(back.width, 7);
  EXPECT_EQ(back.height, 5);
  EXPECT_EQ(back.rgb, img.rgb);
}

TEST(Preview, SplatLandsWhereTheCameraLooksAndNearerWins) {
  MpmAttributes a;
  Camera cam;
  cam.eye = Vec3d(0, 0, 5);
  cam.target = Vec3d::Zero();
  // Material 0 at the target, material 1 nearer the camera but off to the right.
  const ParticleSet one = particles({Vec3(0, 0, 0)}, {0}, a);
  const Image img = render_particles(one, a, cam, 0.2, 64, 48, ColorBy::Material, std::nan(""));
  const Vec3d centre = img.get(32, 24), corner = img.get(1, 1);
  EXPECT_GT((centre - corner).norm(), 0.2);
  EXPECT_GT(centre[0], centre[2]);  // material 0 is orange
  // Two particles on the line of sight: the nearer (material 1, blue) hides the other.
  const ParticleSet two = particles({Vec3(0, 0, 0), Vec3(0, 0, 1)}, {0, 1}, a);
  const Vec3d front =
      render_particles(two, a, cam, 0.2, 64, 48, ColorBy::Material, std::nan("")).get(32, 24);
  EXPECT_GT(front[2], front[0]);
  // Same result when the nearer one comes first in memory.
  const ParticleSet swapped = particles({Vec3(0, 0, 1), Vec3(0, 0, 0)}, {1, 0}, a);
  EXPECT_EQ(
      render_particles(swapped, a, cam, 0.2, 64, 48, ColorBy::Material, std::nan("")).get(32, 24),
      front);
}

TEST(Preview, FittedCameraSeesTheWholeBox) {
  const Camera cam = fit_camera(Vec3d(0, 0, 0), Vec3d(1, 0.5, 2), 35, 4.0 / 3.0);
  MpmAttributes a;
  std::vector<Vec3> corners;
  for (int i = 0; i < 8; ++i)
    corners.push_back(Vec3(Real(i & 1), Real(0.5 * ((i >> 1) & 1)), Real(2 * ((i >> 2) & 1))));
  const ParticleSet ps = particles(corners, std::vector<int>(8, 2), a);
  const Image img = render_particles(ps, a, cam, 0.02, 160, 120, ColorBy::Material, std::nan(""));
  // Every corner's splat is inside the frame: count distinctly coloured (green) pixel clusters.
  int green = 0;
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x) green += img.get(x, y)[1] > img.get(x, y)[0] + 0.1;
  EXPECT_GE(green, 8);
  for (int x = 0; x < img.width; ++x) {  // and none is clipped at the border
    EXPECT_FALSE(img.get(x, 0)[1] > img.get(x, 0)[0] + 0.1);
    EXPECT_FALSE(img.get(x, img.height - 1)[1] > img.get(x, img.height - 1)[0] + 0.1);
  }
}

TEST(Plot, CsvErrorsNameFileAndLine) {
  const auto cols = read_csv_columns("frame,time_s\n1,0.5\n2,1.0\n", "d.csv");
  EXPECT_EQ(cols.at("time_s"), (std::vector<double>{0.5, 1.0}));
  try {
    read_csv_columns("frame,time_s\n1,0.5\n2,abc\n", "d.csv");
    FAIL();
  } catch (const InputError& e) {
    EXPECT_STREQ(e.what(), "d.csv:3: field 'time_s' is not a number: \"abc\"");
  }
  EXPECT_THROW(read_csv_columns("frame,time_s\n1\n", "d.csv"), InputError);
  EXPECT_THROW(read_csv_columns("", "d.csv"), InputError);
}

TEST(Plot, DrawsEveryPanel) {
  std::map<std::string, std::vector<double>> cols;
  for (const char* k : {"frame", "time_s", "kinetic_J", "elastic_J", "last_dt_s", "p2g_s", "g2p_s",
                        "sort_s", "grid_s", "other_s"})
    cols[k] = {};
  for (int f = 1; f <= 10; ++f) {
    cols["frame"].push_back(f);
    cols["time_s"].push_back(f / 24.0);
    cols["kinetic_J"].push_back(10.0 / f);
    cols["elastic_J"].push_back(f);
    cols["last_dt_s"].push_back(1e-4 * f);
    for (const char* k : {"p2g_s", "g2p_s", "sort_s", "grid_s", "other_s"})
      cols[k].push_back(0.1 * f);
  }
  const Image img = plot_diagnostics(cols, "TEST");
  // Each of the three panels has coloured (non-grey) pixels: the series were drawn.
  for (int p = 0; p < 3; ++p) {
    int coloured = 0;
    for (int y = 40 + 260 * p + 30; y < 40 + 260 * (p + 1) - 30; ++y)
      for (int x = 80; x < img.width - 20; ++x) {
        const Vec3d c = img.get(x, y);
        coloured += c.maxCoeff() - c.minCoeff() > 0.3;
      }
    EXPECT_GT(coloured, 100) << "panel " << p;
  }
  cols.erase("p2g_s");
  EXPECT_THROW(plot_diagnostics(cols, "TEST"), InputError);
}
