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

// A triangle surface (peridynamic crack meshes): OBJ with the groups "surface" and "crack" (the
// triangles with crack[f] = 1 go to "crack"), or binary PLY with a uchar face property "crack".
// Both atomic; Houdini, Blender and ParaView read them.
void write_surface_obj(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles,
                       const std::vector<std::uint8_t>& crack);
void write_surface_ply(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles,
                       const std::vector<std::uint8_t>& crack);

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
