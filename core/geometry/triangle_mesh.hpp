// Triangle meshes: the watertightness check, the enclosed volume, particle sampling inside a
// closed mesh and a mesh collider's distance field, both through an OpenVDB level set
// (tools::meshToLevelSet, tools::meshToSignedDistanceField) run under the caller's thread limit.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/colliders.hpp"
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
// coordinates. Inside/outside from a level set of voxel size h.
std::vector<Vec3> sample_mesh(const TriangleMesh& m, double h, double jitter, std::uint64_t seed,
                              const exec::Space& space);

// Signed distance field of the mesh (tools::meshToSignedDistanceField, exact distance inside
// and out to `margin` beyond the surface), baked into a dense array of spacing h covering the
// mesh's box plus margin: what a mesh collider samples.
std::shared_ptr<const SdfGrid> bake_sdf(const TriangleMesh& m, double h, double margin,
                                        const exec::Space& space);

}  // namespace amalgam
