// Frame and diagnostics writers. Every file is written under a temporary name and renamed into
// place, so an interrupted run never leaves a half-written frame.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/particles/point_fields.hpp"
#include "solvers/simulation.hpp"

namespace amalgam {

// Binary little-endian PLY point cloud with x y z, vx vy vz, id, then the attributes of `p` in
// order (float or int properties; Vec3 as name_x name_y name_z, Mat3 as nameRC, e.g. F00 .. F22),
// and, with `material`, a header comment "material_names" (a JSON array); readable by Houdini,
// Blender and ParaView.
void write_ply_points(const std::string& path, const PointFields& p);

// Every triangle mesh Amalgam writes (particle surfaces of output.surfacing, enriched-MPM embedded
// meshes, peridynamic crack surfaces) goes through these two writers; both atomic, read by
// Houdini, Blender and ParaView. The optional arrays of `m` are written when not empty:
// - OBJ: `v x y z`, `vn` normals (faces then `f a//a b//b c//c`), and with `crack` the groups
//   "surface" and "crack" (the triangles with crack[f] = 1). OBJ has no velocity.
// - binary little-endian PLY: vertex x y z [nx ny nz] [vx vy vz] (floats), face
//   `list uchar uint vertex_indices` [uchar crack].
// `what` names the mesh in the file's comment.
void write_mesh_obj(const std::string& path, const SurfaceMesh& m, const std::string& what);
void write_mesh_ply(const std::string& path, const SurfaceMesh& m, const std::string& what);

// Writes `content` to `path` atomically (a new temporary file, then rename: io/files.hpp).
// Throws InputError.
void write_file_atomic(const std::string& path, const std::string& content);

// Resident set size of this process in MB (Linux /proc/self/statm; 0 if unavailable).
double resident_mb();
// A diagnostics.csv header and row from a frame's columns (names in order; whole numbers for
// integer columns, 9 significant digits otherwise).
std::string csv_header(const std::vector<Column>& columns);
std::string csv_row(const std::vector<Column>& columns);

}  // namespace amalgam
