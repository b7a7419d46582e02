// Collider fields (ColliderField, core/geometry/colliders.hpp) over OpenVDB grids:
//  - a triangle mesh (static or keyframed rigid) sampled lazily into a sparse level set of voxel h,
//    only in the blocks the material reaches (plus a halo), extended as it moves;
//  - a .vdb level set read from a file (static or keyframed rigid);
//  - a sequence of level sets, one per frame: .vdb files (optional velocity grid `v`) or meshes of
//    one topology (vertex velocities by central differences), linear in time between the two
//    frames bracketing t (Houdini's "Animated (Deforming)" collider), loaded two at a time.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/geometry/colliders.hpp"
#include "core/geometry/triangle_mesh.hpp"

namespace amalgam {

// Exact distance to the surface within this many voxels of it (both sides); beyond, +-band * h.
constexpr double kLevelSetBand = 4.0;

// A mesh collider's field, voxel size h, built where prepare() asks.
std::shared_ptr<ColliderField> make_mesh_field(std::shared_ptr<const TriangleMesh> mesh, double h);

// Meshes of one topology, frame k at time k / rate; voxel size h.
std::shared_ptr<ColliderField> make_mesh_sequence_field(
    std::vector<std::shared_ptr<const TriangleMesh>> frames, double rate, double h);

// .vdb level sets: one file (static) or frame k = files[k] at time k / rate. `grid`: the grid's
// name, empty for the first float level set of each file. Velocity from a grid named `v` when
// a file has one, else v = -(dphi/dt) n.
std::shared_ptr<ColliderField> make_vdb_field(std::vector<std::string> files, std::string grid,
                                              double rate);

// "" when `path` opens and holds a float level-set grid (named `grid`, or any when empty);
// otherwise why not. Reads headers and metadata only.
std::string check_level_set_file(const std::string& path, const std::string& grid);

}  // namespace amalgam

namespace amalgam {

// Before a substep's kernels query the colliders at time t: makes every field collider valid
// around the material, the 8 dx blocks holding a point of x[0, n) widened by a halo of 4 dx (the
// transfer stencil's nodes, a substep's motion and the trilinear support), so the built region
// follows the material. Serial over the points; the blocks are computed in parallel.
void prepare_colliders(std::vector<Collider>& colliders, const Vec3* x, std::size_t n, Real dx,
                       Real t, const exec::Space& space);
// Its two halves: the 8 dx blocks holding a point (sorted, unique), and the colliders prepared
// around given blocks (distributed MPM joins every rank's blocks in between, so each rank builds
// the single process's region; every voxel is a pure function of the collider and its index).
std::vector<std::array<std::int64_t, 3>> collider_blocks(const Vec3* x, std::size_t n, Real dx);
void prepare_collider_blocks(std::vector<Collider>& colliders,
                             const std::vector<std::array<std::int64_t, 3>>& keys, Real dx, Real t,
                             const exec::Space& space);

}  // namespace amalgam
