// What a scene file says about the physics, once parsed and validated (io/scene.hpp reads it):
// the method and its settings, materials, objects, colliders and the rest. The factory
// (solvers/factory.hpp) builds a Simulation from it; nothing here reads a file.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/colliders.hpp"
#include "core/geometry/tet_mesh.hpp"
#include "core/geometry/triangle_mesh.hpp"
#include "core/math/expression.hpp"
#include "core/materials/material.hpp"
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
  Real radius = 1;                              // sphere, cylinder; torus: major radius
  Real height = 1;                              // cylinder
  Real minor_radius = 0;                        // torus: tube radius
  int axis = 1;                                 // cylinder and torus axis: 0 x, 1 y, 2 z
  int material = 0;
  Vec3 velocity = Vec3::Zero();
  Vec3 angular_velocity = Vec3::Zero();
  // Initial velocity and displacement as functions of the (sampled) position, when given as
  // expressions: the velocity field replaces `velocity`; the displacement moves each particle
  // from its sampled position X to X + u(X) with F = I + grad u (peridynamics: the bonds keep X as
  // their reference, so the body starts strained).
  std::shared_ptr<const VectorField> velocity_field, displacement_field;
  int particles_per_cell = 8;
  Real jitter = Real(0.5);  // fraction of the lattice spacing
  std::uint64_t seed = 1;
  Real temperature = Real(293.15);  // K, initial (used by melting materials)
  // A-ULMPM: the object's own configuration map and its update policy ("configuration" block).
  bool has_configuration = false;
  ConfigurationPolicy configuration;
};

enum class Method { Mpm, Peridynamics };

// Peridynamics: particles whose reference position lies in [min, max] move with `velocity`
// (zero: fixed).
struct PdBoundarySpec {
  Vec3 min, max, velocity;
  // The velocity as expressions of the reference position and time (replaces `velocity`), when
  // given as strings: e.g. a one-period cosine pulse ["0.5*(1-cos(2*pi*min(t,1e-5)/1e-5))", "0", "0"].
  std::shared_ptr<const VectorField> velocity_field;
  bool load = false;  // true: force_density is applied, the velocity is free
  Vec3 force_density = Vec3::Zero();
};
// Peridynamics: a pre-crack, the part inside [min, max] of the plane through point with normal.
struct PdPrecrackSpec {
  Vec3 point, normal, min, max;
};

// A collider as the scene gives it. Mesh colliders keep their rest-pose mesh; the factory bakes it
// into the collider's distance field (build_colliders), and `where` names the scene file and JSON
// path of its "file" key for errors.
struct ColliderSpec : Collider {
  std::shared_ptr<const TriangleMesh> mesh;  // a static or keyframed mesh
  // A sequence of meshes of one topology, or .vdb level sets (one file: static or keyframed),
  // frame k at time k / frame_rate (core/geometry/level_set_collider.hpp).
  std::vector<std::shared_ptr<const TriangleMesh>> mesh_frames;
  std::vector<std::string> vdb_files;
  std::string vdb_grid;  // empty: the first float level set of each file
  double frame_rate = 24;
  std::string where;
};

struct SceneSpec {
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
  std::vector<ColliderSpec> colliders;
  std::vector<HeatSource> heat_sources;
  std::vector<EmitterSpec> emitters;  // MPM (solvers/mpm_sources.hpp)
};

// Samples an object's particles on a jittered lattice of spacing dx / cbrt(ppc), seeded and
// reproducible (meshes through an OpenVDB level set, under the space's thread limit); returns
// positions and sets the volume per particle. `slice`: only that part of the sample, in the same
// order (lattice planes, or a range of a tet mesh's barycentres): the slices of parts 0..P-1 in
// turn are the whole sample (a distributed MPM set-up samples one per rank, solvers/factory.cpp).
std::vector<Vec3> sample_object(const ObjectSpec& obj, Real dx, Real& volume_per_particle,
                                const exec::Space& space = exec::Space(),
                                const LatticeSlice& slice = {});

}  // namespace amalgam
