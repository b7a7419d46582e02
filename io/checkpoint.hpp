// Checkpoints: the complete state needed to continue a run bitwise-identically.
//
// The state is the particle attributes plus the clock (time, substep count), the frame being
// computed and the sections each method adds (Simulation::checkpoint_sections): MPM rebuilds its
// grid from the particles every substep and no node value depends on the leaf table's history, so
// it adds only the particle-domain corners; peridynamics adds its bond layout (the rows left after
// compaction: offsets and neighbours) and per-bond state, the per-bond constants being rebuilt
// from the reference positions, deterministically, and restricted to the stored rows. Format (little-endian), version 3:
//   "AMALGAM-CKPT\n" (13 bytes) | u32 version | u32 sizeof(Real) | u64 scene fingerprint
//   | f64 time | u64 steps | i32 next_frame | i32 retries (version 3) | u64 particles
//   | u32 attributes
//   | per attribute: u32 name length, name, u32 type, u32 width, u32 words/particle, words
//   | u32 sections | per section: u32 name length, name, u64 bytes, bytes   (version 2 and 3)
//   | u64 FNV-1a checksum of every byte before it
// Version 1 files (no sections) and version 2 (no retries: 0) are still read. `retries` is how
// many times the frame in progress was restarted with a halved CFL number before the interrupt
// (0 at a frame's end), so a resumed run continues at that frame's CFL number.
// Written to a temporary name and renamed. Reading checks magic, version, precision, scene,
// attribute layout, sizes and checksum, each failure an InputError naming the file.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/hash.hpp"
#include "io/files.hpp"
#include "solvers/simulation.hpp"

namespace amalgam {

struct CheckpointState {
  double time = 0;
  std::uint64_t steps = 0;
  int next_frame = 1;  // the frame the run continues with
  int retries = 0;     // retries of frame next_frame so far (interrupted mid-frame)
  // Optional particle attributes (`rest`) this run carries and the file did not: filled by
  // Simulation::fill_absent_attribute before Simulation::restored.
  std::vector<std::string> absent;
};

// Writes the simulation's particles and state sections (Simulation::checkpoint_sections),
// streamed to a temporary file beside `path` and renamed into place.
void write_checkpoint(const std::string& path, Simulation& sim, int next_frame,
                      std::uint64_t scene_fingerprint, int retries = 0);
// The same bytes in a temporary file beside `path`, not yet in place: its commit() renames it (the
// checkpoint's commit point; the frame loop commits once the frames it claims are on disk), and
// destroyed uncommitted it is removed. The state may change as soon as this returns.
std::unique_ptr<TempFile> stage_checkpoint(const std::string& path, Simulation& sim, int next_frame,
                                           std::uint64_t scene_fingerprint, int retries = 0);
// Loads particles, sections and clock into `sim`, built from the same scene (peridynamics:
// initialised); returns the state. A section or bond list that does not fit the scene is an
// InputError naming the file.
CheckpointState read_checkpoint(const std::string& path, Simulation& sim,
                                std::uint64_t scene_fingerprint);

// Per-rank checkpoints (issue 28, `amalgam run --parts ranks`; docs/reliability.md). Every rank
// writes its part, checkpoint.gGGGGGG.rRRR.amck: a version-7 checkpoint of its own particles
// (Simulation::my_part) whose first section, dist.order, holds their order keys; rank 0's part
// also holds the method's sections (counters, bonds, ...). Rank 0 then writes the manifest
// (JSON, at the checkpoint's usual path, atomic rename): the commit point. Parts carry a
// generation number, so a crash while a checkpoint is written leaves the previous generation,
// which the old manifest names, whole. read_checkpoint reads a manifest by joining its parts
// (join_checkpoint) into the bytes the single process writes, in the single process's order: a
// resume on any rank count is bitwise the uninterrupted run. Every part is checked against the
// manifest (size, checksum) and against rank 0's part; a failure names the file and the rank.
struct CheckpointPartRecord {
  std::string file;  // name in the checkpoint's directory
  std::uint64_t particles = 0, bytes = 0, checksum = 0;
};
CheckpointPartRecord write_checkpoint_part(const std::string& dir, std::uint64_t generation,
                                           int rank, Simulation& sim, int next_frame,
                                           std::uint64_t scene_fingerprint, int retries,
                                           const exec::Space& space);
void write_checkpoint_manifest(const std::string& path, std::uint64_t generation,
                               const std::vector<CheckpointPartRecord>& parts);
// checkpoint.gGGGGGG.rRRR.amck
std::string checkpoint_part_name(std::uint64_t generation, int rank);
// Removes checkpoint.g*.r*.amck parts of other generations than `generation` from `dir`.
void remove_stale_checkpoint_parts(const std::string& dir, std::uint64_t generation);
// The highest generation of the parts in `dir` (0: none).
std::uint64_t last_checkpoint_generation(const std::string& dir);
// Whether `path` is a manifest (JSON) rather than a single-file checkpoint.
bool is_checkpoint_manifest(const std::string& path);
// A manifest's parts joined into a single-file checkpoint's bytes (InputError naming file, rank).
// With slice.parts > 1, only the parts q with q % parts == part give particles (rank 0's part is
// read for the header and the method's sections in any case): `keys` receives their order keys
// (two per particle, in the joined order) and `total` the particle count of every part (the
// manifest's); a distributed run reads its checkpoint this way, each rank a slice
// (Simulation::checkpoint_slice).
struct JoinSlice {
  int part = 0, parts = 1;
};
std::string join_checkpoint(const std::string& manifest_path, const JoinSlice& slice = {},
                            std::vector<std::uint64_t>* keys = nullptr,
                            std::uint64_t* total = nullptr);

}  // namespace amalgam
