// Preview images without a 3D package: software point splatting of the particles with a
// z-buffer, per-pixel sphere shading and depth cueing, written as PNG (zlib from Debian).
// The camera comes from the scene ("preview" block) or is fitted once from the scene's object
// bounds and floor, so it does not move between frames (and a resumed run renders the same
// images).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/math/types.hpp"
#include "core/particles/particle_set.hpp"

namespace amalgam {

struct Camera {
  Vec3d eye = Vec3d(2, 1.5, 3), target = Vec3d::Zero(), up = Vec3d::UnitY();
  double fov_degrees = 35;
};

enum class ColorBy { Material, Speed, Temperature, Plastic, Damage };

struct PreviewSpec {
  bool camera_given = false;
  Camera camera;
  int width = 640, height = 480;
  ColorBy color_by = ColorBy::Material;
};

struct Image {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgb;  // row-major, top row first
  void set(int x, int y, const Vec3d& c);
  Vec3d get(int x, int y) const;
};

// Camera looking at the box [lo, hi] from the front-right-above so that the whole box fits.
Camera fit_camera(const Vec3d& lo, const Vec3d& hi, double fov_degrees, double aspect);

// Renders each particle as a shaded sphere of `radius` metres (colour by material index, speed,
// temperature or plastic state; missing attributes fall back to material), over a checkered
// floor at height floor_y (NaN: none).
Image render_particles(const ParticleSet& ps, const MpmAttributes& a, const Camera& cam,
                       double radius, int width, int height, ColorBy color_by, double floor_y);
// Same for any solver's points; `scalar` (may be null: colour by material) colours Temperature,
// Plastic and Damage.
Image render_points(std::size_t n, const Vec3* x, const Vec3* v, const std::int32_t* material,
                    const float* scalar, const Camera& cam, double radius, int width, int height,
                    ColorBy color_by, double floor_y);

// Encodes an RGB PNG (8 bits per channel), written atomically. Throws InputError on failure.
void write_png(const std::string& path, const Image& img);
std::string encode_png(const Image& img);

}  // namespace amalgam
