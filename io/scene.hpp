// Scene files (JSON; docs/scenes.md documents every key): parsing with strict validation.
// Unknown keys, wrong types and out-of-range values are InputErrors naming the file and the JSON
// path (e.g. "drop.json: /colliders/0/friction: expected a number >= 0, got -1").
#pragma once

#include <string>
#include <vector>

#include <memory>

#include "core/materials/material.hpp"
#include "io/mesh.hpp"
#include "io/tetmesh.hpp"
#include "io/preview.hpp"
#include "kernels/colliders.hpp"
#include "solvers/mpm_solver.hpp"
#include "solvers/pd_solver.hpp"

namespace amalgam {

enum class ObjectShape { Box, Sphere, Cylinder, Torus, Mesh, TetMesh };

struct ObjectSpec {
  ObjectShape shape = ObjectShape::Box;
  std::shared_ptr<const TriangleMesh> mesh;  // Mesh: loaded, scaled and translated
  std::shared_ptr<const TetMesh> tets;       // TetMesh (peridynamics): one particle per tetrahedron
  Vec3 min = Vec3::Zero(), max = Vec3::Ones();  // box
  Vec3 center = Vec3::Zero();                   // sphere (and rotation centre of both)
  Real radius = 1;        // sphere, cylinder; torus: major radius
  Real height = 1;        // cylinder
  Real minor_radius = 0;  // torus: tube radius
  int axis = 1;           // cylinder and torus axis: 0 x, 1 y, 2 z
  int material = 0;
  Vec3 velocity = Vec3::Zero();
  Vec3 angular_velocity = Vec3::Zero();
  int particles_per_cell = 8;
  Real jitter = Real(0.5);  // fraction of the lattice spacing
  std::uint64_t seed = 1;
  Real temperature = Real(293.15);  // K, initial (used by melting materials)
  // A-ULMPM: the object's own configuration map and its update policy ("configuration" block).
  bool has_configuration = false;
  ConfigurationPolicy configuration;
};

struct OutputSpec {
  std::string directory = "out";
  bool ply = true;
  bool vdb_points = true;
  bool diagnostics_csv = true;
  bool grid_volumes = false;  // frame_NNNN_grid.vdb: node mass and velocity
  int checkpoint_every = 10;  // frames; 0 = only on SIGINT/SIGTERM
  // Peridynamic tet_mesh objects: the surface with crack faces per frame (frame_NNNN_surface.*).
  bool surface_obj = true, surface_ply = false;
};

enum class Method { Mpm, Peridynamics };

// Peridynamics: particles whose reference position lies in [min, max] move with `velocity`
// (zero: fixed).
struct PdBoundarySpec {
  Vec3 min, max, velocity;
  bool load = false;  // true: force_density is applied, the velocity is free
  Vec3 force_density = Vec3::Zero();
};
// Peridynamics: a pre-crack, the part inside [min, max] of the plane through point with normal.
struct PdPrecrackSpec {
  Vec3 point, normal, min, max;
};

struct Scene {
  std::string file;
  std::string name;
  Method method = Method::Mpm;
  MpmSettings mpm;  // dx, fps, max_dt and gravity are shared by both methods
  PdSettings pd;
  std::vector<PdMaterial> pd_materials;  // parallel to materials (peridynamics scenes)
  std::vector<PdBoundarySpec> pd_boundaries;
  std::vector<PdPrecrackSpec> pd_precracks;
  int frames = 48;
  double fps = 24;
  std::vector<std::string> material_names;
  std::vector<MaterialParams> materials;
  std::vector<ObjectSpec> objects;
  std::vector<Collider> colliders;
  std::vector<HeatSource> heat_sources;
  OutputSpec output;
  PreviewSpec preview;
  // Hash of everything that determines the simulated state (not output, frames, name,
  // description): a checkpoint only resumes a scene with the same fingerprint.
  std::uint64_t fingerprint = 0;
};

// Reads and validates a scene file (meshes are loaded and checked too). Throws InputError.
// Warnings (e.g. an open mesh allowed with allow_open) go to std::cerr.
Scene load_scene(const std::string& path);
// Same, from JSON text (`file` is used in messages and to resolve relative mesh paths).
Scene parse_scene(const std::string& text, const std::string& file);

// Samples an object's particles on a jittered lattice of spacing dx / cbrt(ppc), seeded and
// reproducible; returns positions and sets the volume per particle.
std::vector<Vec3> sample_object(const ObjectSpec& obj, Real dx, Real& volume_per_particle);

// The preview camera: the scene's, or fitted to the objects' bounds (widened for material that
// spreads) and the floor below them.
Camera preview_camera(const Scene& scene);
// Splat radius for previews: 0.6 particle spacings of the densest object.
double preview_radius(const Scene& scene);
// Height of the highest upward-facing half-space collider (the floor), or NaN.
double preview_floor(const Scene& scene);

// Builds a solver from a scene and fills its particles.
MpmSolver build_solver(const Scene& scene);
// Peridynamics scenes: the solver with its particles and boundary sets, not yet initialised.
PdSolver build_pd_solver(const Scene& scene);

}  // namespace amalgam
