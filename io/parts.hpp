// Per-rank output of a distributed run (issue 28, `amalgam run --parts ranks`; docs/output.md
// "Per-rank output"). Every rank writes its own part of a frame, and rank 0 writes the frame's
// manifest last: the manifest is the commit point (a frame without one is incomplete).
//
//   frame_NNNN.rRRR.ply / .vdb   the rank's points as the scene asks (loadable alone)
//   frame_NNNN.rRRR.pts          the same points exactly (every value as computed, no format
//                                rounding) with their order keys: what `amalgam merge` joins
//   frame_NNNN.manifest.json     frame, time, ranks, and per part its files with particle count,
//                                byte size and FNV-1a 64 checksum; what merge needs to write
//                                (voxel size, VDB precision, formats, material names)
//
// Points part format (little-endian): "AMALGAM-POINTS\n" | u32 version (1) | u32 sizeof(Real)
//   | u64 n | u64 order[2n] | Real x[3n] | Real v[3n] | i32 material[n] | i32 id[n]
//   | u32 attributes | per attribute: u32 name length, name, u32 type, u32 width, values
//   (float n*width, or int32 n) | u64 FNV-1a of every byte before it.
// Joining sorts the points of every part by their order keys (lexicographic), which is the single
// process's order, and writes them with the same writers: the joined files are bitwise the single
// process's (tests/dist_mpm_test.sh, dist_pd_test.sh).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/point_fields.hpp"
#include "io/vdb_points.hpp"

namespace amalgam {

// A file of a part as the manifest lists it.
struct PartFile {
  std::string file;  // name within the run directory
  std::uint64_t bytes = 0, checksum = 0;
};
// The size and FNV-1a 64 checksum of a written file (`dir`/`name`).
PartFile part_file_record(const std::string& dir, const std::string& name);

// Writes a points part (atomic rename); `order`: 2 keys per point.
void write_points_part(const std::string& path, const PointFields& p,
                       const std::vector<std::uint64_t>& order);

struct FrameManifest {
  int frame = 0;
  double time = 0;
  int ranks = 1;
  double voxel_size = 0;
  VdbPrecision vdb_precision = VdbPrecision::Compact;
  bool ply = false, vdb = false;
  std::vector<std::string> material_names;
  std::vector<std::uint64_t> particles;      // per rank
  std::vector<std::vector<PartFile>> files;  // per rank
};
// frame_NNNN.manifest.json in `dir`.
std::string frame_manifest_name(int frame);
void write_frame_manifest(const std::string& dir, const FrameManifest& m);
// Reads and checks a manifest; InputError naming the file and the key.
FrameManifest read_frame_manifest(const std::string& path);
// A rank's list of part files as bytes (for the gather to rank 0) and back.
std::string encode_part_files(std::uint64_t particles, const std::vector<PartFile>& files);
void decode_part_files(const std::string& bytes, std::uint64_t& particles,
                       std::vector<PartFile>& files);

// Joins a complete frame's parts in `dir` into frame_NNNN.ply / .vdb as one process writes
// them; every part is checked against the manifest (size, checksum) first. Returns the paths.
std::vector<std::string> merge_frame(const std::string& dir, const FrameManifest& m,
                                     const exec::Space& space);

}  // namespace amalgam
