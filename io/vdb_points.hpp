// OpenVDB point output: one PointDataGrid named "points" per frame with P (full precision), and
// point attributes v (Vec3s), J (float, det F), material (int32) and id (int32, stable across the
// run). Houdini reads it with a File SOP (and "Convert VDB Points"), as does any OpenVDB-based
// tool; Blender users take the PLY frames. Written under a temporary name and renamed. OpenVDB's
// point tools run under the space's thread limit (exec::with_thread_limit).
#pragma once

#include <string>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "io/writers.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

// `voxel_size` sets the point grid's voxel (the simulation dx is a good choice). Every float
// attribute of `p` (primary and extra) becomes a point attribute of that name.
void write_vdb_points(const std::string& path, const PointFields& p, double voxel_size,
                      const exec::Space& space);

// Grid fields of the last substep as OpenVDB volumes: a FloatGrid "mass" (kg per node) and a
// Vec3SGrid "velocity" (m/s, the updated grid velocity), voxel = node, voxel size dx, over the
// active leaves (nodes with zero mass are left inactive). Houdini reads them with a File SOP.
void write_vdb_grid_fields(const std::string& path, const SparseGrid& grid, double dx,
                           const exec::Space& space);

}  // namespace amalgam
