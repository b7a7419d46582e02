// Render-ready surfaces from particles (issue 29): a narrow-band level set built with OpenVDB's
// own point rasterisers, optionally filtered, written as one VDB file with the grids `surface`
// (level set), `density` (fog volume) and `v` (velocity), and optionally a triangle mesh (OBJ or
// binary PLY, io/writers.hpp's mesh writer) with per-vertex normals (and velocity in PLY). Every OpenVDB tool call runs inside
// exec::with_thread_limit; files are written to a new temporary file and renamed, the VDB file with
// the UUID derived from its bytes (io/vdb_file.hpp), so identical input writes identical files.
//
// Particle radius: every particle gets the radius of the sphere of its rest volume on the
// sampling lattice, r = radius_scale * cbrt(3 V / (4 pi)) with V = h^3 (h = the lattice spacing,
// dx / cbrt(particles_per_cell)), i.e. r = 0.620 h * radius_scale. One radius for all particles
// (the per-particle volume is not in the frame files `amalgam surface` reads). The default
// radius_scale, 0.9 for smooth and 0.8 for spheres (r = h / 2: after the closing the union's
// surface lies about r beyond the outermost particles, where their lattice cells end), was chosen
// by measurement on lattice balls of radius 8 h and 10 h (tests/test_surfacing.cpp; the numbers
// are in docs/scenes.md).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/point_fields.hpp"

namespace amalgam {

enum class SurfacingMethod {
  Smooth,   // points::rasterizeSmoothSpheres (Zhu & Bridson 2005 averaged positions)
  Spheres,  // points::rasterizeSpheres (union of spheres)
};
enum class SurfaceFilter { Dilate, Smooth, Erode };  // tools::LevelSetFilter passes, one voxel each
enum class SurfaceMeshFormat { None, Obj, Ply };

struct SurfacingSpec {
  bool enabled = false;  // output.surfacing given (in a scene)
  SurfacingMethod method = SurfacingMethod::Smooth;
  double voxel_size = 0;    // metres; 0: half the simulation dx (resolved by the caller)
  double radius_scale = 0;  // multiplies r = cbrt(3 h^3 / (4 pi)); 0: the method's default
  std::vector<SurfaceFilter> filters;
  bool grid_surface = true, grid_density = true, grid_velocity = true;  // grids written
  SurfaceMeshFormat mesh = SurfaceMeshFormat::None;
  double adaptivity = 0;                // tools::volumeToMesh adaptivity, [0, 1]
  std::vector<std::int32_t> materials;  // material indices surfaced; empty: every particle
};

// Names as in scenes and on the command line; InputError-free: return false on an unknown name.
bool parse_surfacing_method(const std::string& name, SurfacingMethod& out);
bool parse_surface_filter(const std::string& name, SurfaceFilter& out);
bool parse_surface_mesh(const std::string& name, SurfaceMeshFormat& out);

// The filters when none are given: none for smooth; a closing (dilate, erode) for spheres, whose
// union at radius 0.62 h leaves gaps of 0.25 h at the lattice's cell centres.
std::vector<SurfaceFilter> default_surface_filters(SurfacingMethod m);

// The particle radius of the spec for lattice spacing h.
double surfacing_radius(const SurfacingSpec& s, double spacing);

struct SurfacingStats {
  std::size_t particles = 0;      // surfaced (after the material selection)
  std::size_t active_voxels = 0;  // of the level set
  std::size_t vertices = 0, triangles = 0;
  std::vector<std::string> files;  // written
};

// Surfaces the particles of `p` (lattice spacing `spacing`; `s.voxel_size` must be > 0) and
// writes base + ".vdb" and, as s.mesh asks, base + ".obj" or ".ply". An empty selection writes
// valid empty grids (and an empty mesh). Throws InputError naming the file on failure.
SurfacingStats write_surfacing(const std::string& base, const PointFields& p, double spacing,
                               const SurfacingSpec& s, const exec::Space& space);

// The same from a VDB points file written by a run (frame_NNNN.vdb: the grid "points" with P, v
// and material). A spacing or s.voxel_size <= 0 is taken as half the points' voxel size (the
// run's dx for MPM: right for 8 particles per cell). Throws InputError naming the file when it
// cannot be read or lacks P and v.
SurfacingStats surface_vdb_points_file(const std::string& input, const std::string& base,
                                       double spacing, const SurfacingSpec& s,
                                       const exec::Space& space);

}  // namespace amalgam
