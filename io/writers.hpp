// Frame and diagnostics writers. Every file is written under a temporary name and renamed into
// place, so an interrupted run never leaves a half-written frame.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "core/particles/particle_set.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

// What a frame writer needs of any solver's particles: positions, velocities, material and a
// stable id, plus named float attributes, `primary` written before material and id, `extra`
// after them (the PLY property order; VDB points keep the names).
struct PointFields {
  std::size_t n = 0;
  const Vec3* x = nullptr;
  const Vec3* v = nullptr;
  const std::int32_t* material = nullptr;
  const std::int32_t* id = nullptr;
  std::vector<std::pair<std::string, std::vector<float>>> primary, extra;
};
// MPM particles: primary J (= det F); extra plastic and temperature when the scene has them, and
// enrichment (the domain state) with particle domains.
PointFields mpm_point_fields(const ParticleSet& ps, const MpmAttributes& a);

// Binary little-endian PLY point cloud with x y z, vx vy vz, the primary attributes, material, id
// and the extra attributes (MPM: x y z vx vy vz J material id [plastic] [temperature]), readable
// by Houdini, Blender and ParaView.
void write_ply_points(const std::string& path, const PointFields& p);
inline void write_ply_points(const std::string& path, const ParticleSet& ps, const MpmAttributes& a) {
  write_ply_points(path, mpm_point_fields(ps, a));
}

// A triangle surface (peridynamic crack meshes): OBJ with the groups "surface" and "crack" (the
// triangles with crack[f] = 1 go to "crack"), or binary PLY with a uchar face property "crack".
// Both atomic; Houdini, Blender and ParaView read them.
void write_surface_obj(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles, const std::vector<std::uint8_t>& crack);
void write_surface_ply(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles, const std::vector<std::uint8_t>& crack);

// Writes `content` to `path` atomically (temporary file, then rename). Throws InputError.
void write_file_atomic(const std::string& path, const std::string& content);
// Renames a finished temporary file onto `path` (removing it on failure). Throws InputError.
void commit_temporary(const std::string& tmp, const std::string& path);

struct DiagnosticsRow {
  int frame;
  double time, dt, wall_seconds;
  long long substeps;
  MpmDiagnostics d;
  std::size_t particles;
  // Seconds spent this frame in P2G, G2P, sorting (keys, radix sort, permutation, bins),
  // grid (topology, clear, update) and everything else (CFL check, diagnostics, output).
  double p2g_s = 0, g2p_s = 0, sort_s = 0, grid_s = 0, other_s = 0;
  // Implicit integration: seconds in the solve (Hessian cache, operator, CG), CG iterations this
  // frame (total and the most in one substep), the worst final relative residual and the number
  // of substeps whose solve stopped at the iteration limit. Zero when explicit.
  double solve_s = 0;
  long long cg_iterations = 0, cg_unconverged = 0;
  int cg_max_iterations = 0;
  double cg_max_residual = 0;
  // Memory: grid leaves allocated and active this frame, resident set size of the process (MB).
  std::size_t leaves = 0, active_leaves = 0;
  double rss_mb = 0;
  // Particle domains (enriched MPM): mean fraction of enriched and transitional particles over
  // the frame's substeps, the largest enriched fraction in one substep, enriched corners at the
  // last substep. Zero without domains.
  double enriched_fraction = 0, transitional_fraction = 0, max_enriched_fraction = 0;
  std::size_t enriched_corners = 0;
};
// Resident set size of this process in MB (Linux /proc/self/statm; 0 if unavailable).
double resident_mb();
std::string diagnostics_csv_header();
std::string diagnostics_csv_line(const DiagnosticsRow& r);

}  // namespace amalgam
