// Triangle meshes: the watertightness check, the enclosed volume, particle sampling inside a
// closed mesh through an OpenVDB level set (tools::meshToLevelSet) run under the caller's thread
// limit. A mesh collider's field: core/geometry/level_set_collider.hpp.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/colliders.hpp"
#include "core/geometry/lattice.hpp"
#include "core/math/types.hpp"

namespace amalgam {

struct TriangleMesh {
  std::vector<Vec3d> vertices;
  std::vector<std::array<std::int32_t, 3>> triangles;  // polygons are fan-triangulated
};

struct MeshCheck {
  std::size_t boundary_edges = 0;     // edges used by one triangle
  std::size_t nonmanifold_edges = 0;  // edges used by more than two triangles
  bool watertight() const { return boundary_edges == 0 && nonmanifold_edges == 0; }
};
MeshCheck check_mesh(const TriangleMesh& m);

// Signed enclosed volume (divergence theorem; positive for outward-oriented triangles).
double enclosed_volume(const TriangleMesh& m);

// Lattice points of spacing h (jittered by jitter * h, seeded) inside the mesh, in the mesh's
// coordinates. Inside/outside from a level set of voxel size h. `slice`: that part of the lattice
// only (core/geometry/lattice.hpp; the level set is still built over the whole mesh).
std::vector<Vec3> sample_mesh(const TriangleMesh& m, double h, double jitter, std::uint64_t seed,
                              const exec::Space& space, const LatticeSlice& slice = {});

// Bounding box of the vertices.
void mesh_bounds(const TriangleMesh& m, Vec3d& lo, Vec3d& hi);

// A closed unit sphere: an octahedron subdivided `levels` times (8 * 4^levels triangles, wound
// outward), vertices on the sphere. For tests and benchmarks of mesh colliders.
TriangleMesh unit_sphere_mesh(int levels);
// Grid and level-set indices are 32-bit: |x| / h must stay below 2^30 (InputError naming `what`).
constexpr double kMaxGridIndex = 1073741824.0;
void check_grid_range(const Vec3d& lo, const Vec3d& hi, double h, const std::string& what);

}  // namespace amalgam
