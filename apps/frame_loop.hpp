// The one frame loop of `amalgam run`, for every method (solvers/simulation.hpp): substeps of a
// frame split evenly under the stable step, the stability guard on each substep's start and on
// the frame's end state, retries of a failed frame from its start with the CFL number halved,
// frame output (PLY, VDB points, grid volumes, surfaces, previews), diagnostics.csv, the
// optional per-substep log, periodic and final checkpoints and one on SIGINT/SIGTERM, and the
// progress line with throughput and ETA.
#pragma once

#include <cstdint>
#include <string>

#include "core/exec/exec.hpp"
#include "io/scene.hpp"
#include "solvers/simulation.hpp"

namespace amalgam::cli {

struct RunSettings {
  std::string out_dir;
  int first_frame = 1;       // 1, or the checkpoint's next frame on resume
  bool resumed = false;      // from a checkpoint: frames before first_frame are written already
  int resume_retries = 0;    // retries frame first_frame had had when the checkpoint was taken
  int checkpoint_every = 0;  // frames; 0 = only at the end and on a signal
  int max_retries = 3;
  bool quiet = false, preview = false;
  bool sync_output = false;  // --sync-output: frames written on the simulation's thread
  bool rank_parts = false;   // --parts ranks: every rank writes its part of frames/checkpoints
};

// Runs frames first_frame..scene.frames of `sim`; returns the exit code (0, or 128 + signal).
// Installs the SIGINT/SIGTERM handler that checkpoints mid-frame (after set-up's, apps/run.cpp).
// Throws SimulationError when a frame fails after every retry, InputError when output fails.
int run_frames(Simulation& sim, const Scene& scene, const RunSettings& rs, const exec::Space& space,
               const exec::Profiler& profiler);

}  // namespace amalgam::cli
