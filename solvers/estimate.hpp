// What a run will cost, from the scene alone (no sampling, no voxelising): particles, grid
// leaves or bonds, resident memory and substeps. `amalgam validate` prints it and `amalgam run`
// checks it before allocating anything, so an absurd scene (a box of 10^9 particles, a step of
// 10^-12 s, a frame of 10^9 s) is refused in a moment with the number that crossed the limit,
// instead of failing hours or gigabytes later.
#pragma once

#include <string>

#include "solvers/scene_spec.hpp"

namespace amalgam {

struct RunEstimate {
  double particles = 0;    // from each object's shape and lattice (curved shapes: by volume)
  double grid_leaves = 0;  // MPM: 8^3-node leaves around the objects at the start
  double bonds = 0;        // peridynamics: directed bonds (lattice neighbours in the horizon)
  double bins = 0;         // MPM: the sort's bins (leaves holding particles) at the start
  double bytes = 0;        // resident memory of the state (particles, grid or bonds, snapshot)
  double block_bytes = 0;  // MPM: P2G's blocks kept between substeps, one per bin (in bytes)
  double bond_bytes = 0;   // peridynamics: the bonds' part of bytes (split across MPI ranks)
  double dt = 0;           // the first substep's stable step (s)
  double substeps_per_frame = 0;
  double substeps = 0;  // the whole run
};

// Limits a run must stay under unless forced (`amalgam run --force`).
constexpr double kMaxSubstepsPerFrame = 1e6;
constexpr double kMaxSubsteps = 1e9;

// Throws InputError when the scene cannot be run at all whatever the machine (an object beyond
// the grid's index range, a collider field over its sample limit, a step that is not a normal
// number in the build's precision, initial speeds above the stability limit).
// `rest_positions`: the output asks for MPM's `rest` attribute (12 B per particle in float).
// `ranks`: MPI ranks of the run (a fused MPM scene runs two passes on several, without the split
// grid set). The layout (attributes, grid sets) is that of a solver of the scene's settings.
RunEstimate estimate_run(const SceneSpec& scene, bool rest_positions = false, int ranks = 1);

// One line for people: "9.7e4 particles, 120 leaves, 47 MB, 61 substeps per frame (dt 6.8e-4 s),
// 2928 substeps".
std::string describe(const RunEstimate& e);

// Empty when the run fits: else what crossed which limit (memory against `available_bytes`, 0 =
// unknown, not checked; substeps against the limits above), one sentence per limit.
std::string over_limits(const RunEstimate& e, double available_bytes);

}  // namespace amalgam
