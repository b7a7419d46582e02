// Checkpoints: the complete state needed to continue a run bitwise-identically.
//
// The grid is rebuilt from the particles every substep and no node value depends on the leaf
// table's history, so the state is the particle attributes plus the clock (time, substep count)
// and the frame being computed; peridynamics adds its bond layout (the rows left after compaction:
// offsets and neighbours) and per-bond state; the per-bond constants are rebuilt from the
// reference positions, deterministically, and restricted to the stored rows. Format (little-endian), version 2:
//   "AMALGAM-CKPT\n" (13 bytes) | u32 version | u32 sizeof(Real) | u64 scene fingerprint
//   | f64 time | u64 steps | i32 next_frame | u64 particles | u32 attributes
//   | per attribute: u32 name length, name, u32 type, u32 width, u32 words/particle, words
//   | u32 sections | per section: u32 name length, name, u64 bytes, bytes   (version 2 only)
//   | u64 FNV-1a checksum of every byte before it
// Version 1 files (no sections) are still read.
// Written to a temporary name and renamed. Reading checks magic, version, precision, scene,
// attribute layout, sizes and checksum, each failure an InputError naming the file.
#pragma once

#include <cstdint>
#include <string>

#include "core/hash.hpp"
#include "solvers/mpm_solver.hpp"
#include "solvers/pd_solver.hpp"

namespace amalgam {

struct CheckpointState {
  double time = 0;
  std::uint64_t steps = 0;
  int next_frame = 1;  // the frame the run continues with
};

void write_checkpoint(const std::string& path, const MpmSolver& solver, int next_frame,
                      std::uint64_t scene_fingerprint);
// Loads particles and clock into `solver` (built from the same scene); returns the state.
CheckpointState read_checkpoint(const std::string& path, MpmSolver& solver, std::uint64_t scene_fingerprint);

// Peridynamics: particles, clock, the bond rows (compacted or not), the bonds' plastic extensions
// and intact flags, and embedded crack meshes (vertex positions, split tetrahedra, crack faces).
// Reading needs an initialised solver of the same scene; a bond list that is not a subset of its
// bonds is an InputError.
void write_checkpoint(const std::string& path, const PdSolver& solver, int next_frame,
                      std::uint64_t scene_fingerprint);
CheckpointState read_checkpoint(const std::string& path, PdSolver& solver, std::uint64_t scene_fingerprint);

}  // namespace amalgam
