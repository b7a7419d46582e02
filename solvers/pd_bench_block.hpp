// The peridynamics benchmark block (amalgam bench --report, the microbenchmarks).
#pragma once

#include <memory>

#include "core/exec/exec.hpp"
#include "solvers/pd_solver.hpp"

namespace amalgam {

// Peridynamics: an n^3 simple-cubic block of spacing 0.01 (n = 40: 64 000 particles; delta =
// 3.015 lc: 122 bonds in the bulk, 7.2 M directed bonds), glass-like moduli, plastic and
// fracture enabled with thresholds not reached, no particle contact; initialised on `space`,
// then stretched 0.1 % and sheared so every bond carries a force.
std::unique_ptr<PdSolver> make_bench_pd_block(int n, const exec::Space& space);

}  // namespace amalgam
