// Scene files (JSON; docs/scenes.md documents every key): parsing with strict validation.
// Unknown keys, wrong types and out-of-range values are InputErrors naming the file and the JSON
// path (e.g. "drop.json: /colliders/0/friction: expected a number >= 0, got -1").
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "io/preview.hpp"
#include "io/surfacing.hpp"
#include "io/vdb_points.hpp"
#include "solvers/scene_spec.hpp"

namespace amalgam {

struct OutputSpec {
  std::string directory = "out";
  bool ply = true;
  bool vdb_points = true;
  VdbPrecision vdb_precision = VdbPrecision::Compact;  // output.vdb_points: "full" or "compact"
  // Attributes written beyond P, v and id (output.attributes, point_attribute_names()), checked
  // against the method; none when the scene gives none (frames then carry P, v and id only).
  std::vector<std::string> attributes;
  bool diagnostics_csv = true;
  bool grid_volumes = false;  // frame_NNNN_grid.vdb: node mass and velocity
  int checkpoint_every = 10;  // frames; 0 = only on SIGINT/SIGTERM
  // Samples every N substeps (0: none): samples.csv rows and, with ply / vdb_points, the points
  // in samples/points_sNNNNNNNNNN.* (N counts the run's substeps, so a resumed run takes the same).
  long long every_substeps = 0;
  // Peridynamic tet_mesh objects: the surface with crack faces per frame (frame_NNNN_surface.*).
  bool surface_obj = true, surface_ply = false;
  // Particle surfaces (output.surfacing; off by default): surfacing_NNNN.vdb and, with a mesh,
  // surfacing_NNNN.obj / .ply (io/surfacing.hpp). voxel_size is resolved (dx / 2 when not given).
  SurfacingSpec surfacing;
};

// A parsed scene: the physics (SceneSpec, what the factory builds a Simulation from), plus what
// only the runner reads: file, name, output and preview settings, and the fingerprint.
struct Scene : SceneSpec {
  std::string file;
  std::string name;
  OutputSpec output;
  PreviewSpec preview;
  // Hash of everything that determines the simulated state (not output, frames, name,
  // description): a checkpoint only resumes a scene with the same fingerprint.
  std::uint64_t fingerprint = 0;
};

// Most frames a run may have (simulation.frames, --frames).
constexpr int kMaxFrames = 1000000;

// Most retries of a frame (--retries).
constexpr int kMaxRetries = 10;

// Largest scene file read (a scene is a few kB of JSON; meshes are separate files).
constexpr std::uint64_t kMaxSceneBytes = 64ull << 20;

// Whether `name` is an output attribute the scene's method has (point_attribute_names()).
bool attribute_available(const SceneSpec& scene, const std::string& name);

// Reads and validates a scene file (meshes are loaded and checked too). Throws InputError.
// Warnings (e.g. an open mesh allowed with allow_open) go to std::cerr.
Scene load_scene(const std::string& path);
// Same, from JSON text (`file` is used in messages and to resolve relative mesh paths).
Scene parse_scene(const std::string& text, const std::string& file);

// The preview camera: the scene's, or fitted to the objects' bounds (widened for material that
// spreads) and the floor below them.
Camera preview_camera(const Scene& scene);
// Splat radius for previews: 0.6 particle spacings of the densest object.
double preview_radius(const Scene& scene);
// The particle lattice spacing surfacing sizes its spheres by: the peridynamic spacing, or for MPM
// dx / cbrt(particles_per_cell) of the object with the fewest particles per cell (the widest
// spacing, so that no object's spheres leave gaps).
double particle_spacing(const Scene& scene);
// Height of the highest upward-facing half-space collider (the floor), or NaN.
double preview_floor(const Scene& scene);

}  // namespace amalgam
