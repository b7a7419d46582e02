// OpenVDB point output: one PointDataGrid named "points" per frame with P, v (Vec3s) and id
// (int32, stable across the run), then the attributes output.attributes asks for, typed: float
// attributes as float, `rest` as Vec3s, `F` as Mat3s, `material` as int32 with the material names
// as the grid's string metadata "material_names" (a JSON array, index = material). Houdini reads
// it with a File SOP (and "Convert VDB Points"), as does any OpenVDB-based tool; Blender users take
// the PLY frames. Written under a temporary name and renamed. OpenVDB's point tools run under the
// space's thread limit (exec::with_thread_limit). docs/output.md has sizes and error bounds.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "io/writers.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

// Full: positions as float offsets within their voxel (NullCodec) and every attribute exact, as
// OpenVDB's default file compression leaves them.
// Compact: positions as 16-bit fixed point within their voxel (FixedPointCodec<false,
// PositionRange>: truncated, so each axis reads back up to voxel/65535 low, plus float rounding);
// v and the bounded scalars (J, Jp, damage, theta, temperature, enrichment) as half floats
// (TruncateCodec, relative error <= 2^-11); vonmises (Pa: past half's 65504), rest and F as
// floats; every array Blosc-compressed (io::COMPRESS_BLOSC) and arrays of one value collapsed
// (points::compactAttributes).
enum class VdbPrecision { Full, Compact };
const char* vdb_precision_name(VdbPrecision p);

// `voxel_size` sets the point grid's voxel (the simulation dx, or the peridynamic spacing).
void write_vdb_points(const std::string& path, const PointFields& p, double voxel_size,
                      VdbPrecision precision, const exec::Space& space);

// Grid fields of the last substep as OpenVDB volumes: a FloatGrid "mass" (kg per node) and a
// Vec3SGrid "velocity" (m/s, the updated grid velocity), voxel = node, voxel size dx, over the
// active leaves (nodes with zero mass are left inactive). Houdini reads them with a File SOP.
void write_vdb_grid_fields(const std::string& path, const SparseGrid& grid, double dx,
                           const exec::Space& space);

// The same in two steps, for asynchronous output (apps/frame_loop.cpp): the grid's nodes with mass
// copied out (index space, mass, velocity as floats), then written from that copy, byte for byte
// the file write_vdb_grid_fields writes.
struct GridNodes {
  double dx = 0;
  std::vector<std::array<int, 3>> ijk;
  std::vector<float> mass;
  std::vector<std::array<float, 3>> velocity;
};
GridNodes grid_nodes(const SparseGrid& grid, double dx);
void write_vdb_grid_nodes(const std::string& path, const GridNodes& g, const exec::Space& space);

}  // namespace amalgam
