// Error types of the engine. Every message names what failed and where (file, JSON path,
// step, particle), so the CLI can print it and exit non-zero.
#pragma once

#include <stdexcept>
#include <string>

namespace amalgam {

// Bad input: scene files, meshes, command-line values.
struct InputError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// The simulation reached a state it cannot continue from (NaN/inf, runaway velocity).
struct SimulationError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

}  // namespace amalgam
