// The standard scenes of the benchmark report (`amalgam bench --report`, docs/bench_report/):
// one case per method family, each a solver ready to step plus how to count its work.
// Explicit MPM with each transfer scheme, implicit MPM, A-ULMPM (total Lagrangian), enriched MPM
// (particle domains) and peridynamics. Sizes scale with one factor so a quick run and the
// committed report use the same scenes.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"

namespace amalgam {

// A built scene: step() advances one substep (MPM) or one Verlet step (peridynamics) with the
// case's fixed time step. Items are particles (particle-substeps) or directed bonds
// (bond-updates: every bond i->j and j->i, as LAMMPS counts them).
struct BenchInstance {
  std::function<void(const exec::Space&)> step;
  double items = 0;           // per step
  double bytes_per_item = 0;  // resident state of the solver per item (particle or bond)
  double dt = 0;
  // Method-specific figures since the last reset, as "key=value" pairs (e.g. CG iterations).
  std::function<std::string()> extra;
  std::function<void()> reset_extra;
  std::shared_ptr<void> owner;  // keeps the solver alive
};

struct BenchCase {
  std::string name;    // e.g. "mpm_mls"
  std::string method;  // e.g. "explicit MPM, MLS, quadratic"
  std::string unit;    // "particle-substeps/s" or "bond-updates/s"
  std::string scene;   // one line: what is simulated, how many items
  // Builds the case at `scale` (1 = the report's size); `space` may be used for set-up.
  std::function<BenchInstance(double scale, const exec::Space& space)> make;
};

// Every standard case, in report order.
std::vector<BenchCase> standard_bench_cases();

}  // namespace amalgam
