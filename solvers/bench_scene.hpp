// The standard benchmark scene of issue 2: N particles uniform in a sphere (centre 0.5, radius
// 0.3, dx = 1/128 gives ~4.2 particles per cell at N = 1e6), fixed-corotated jelly, spinning
// slowly above a floor, explicit MLS-MPM with quadratic B-splines. Seeded and reproducible.
#pragma once

#include <memory>
#include <optional>

#include "solvers/mpm_solver.hpp"

namespace amalgam {

struct BenchSceneOptions {
  std::size_t particles = 1000000;
  Real dx = Real(1.0 / 128.0);
  Transfer transfer = Transfer::Mls;
  int order = 2;
  bool implicit = false;  // backward Euler (CG) instead of explicit
  double youngs_modulus = 1e5;
  // A-ULMPM: the sphere as one object with this configuration policy (Lagrangian-mode kernels)
  bool lagrangian = false;
  ConfigurationPolicy policy{ConfigurationUpdate::TotalLagrangian};
  // A-ULMPM only: 2 splits the sphere at x = 0.5 into two objects in contact (same particles).
  int objects = 1;
  // Enriched MPM: the sphere sampled on a lattice (about `particles` points) with particle
  // domains (PIC/FLIP on linear weights; `transfer` and `order` unused); enrichment on.
  bool domains = false;
  bool fused = false;  // simulation.transfer_pass "fused" (G2P2G)
  // simulation.sort "when_needed" (the two passes re-sort only when a particle leaves its bin's
  // dilated block); the scene's default.
  bool sort_when_needed = MpmSettings().sort_when_needed;
  // The sphere's material (`amalgam bench --like SCENE`: the scene's first object's); unset, the
  // fixed-corotated jelly of youngs_modulus, Poisson 0.3, density 1000.
  std::optional<MaterialParams> material;
  Real temperature = 0;  // the particles' initial temperature, K (--like: the object's)
};

MpmSolver make_bench_sphere(const BenchSceneOptions& o);

}  // namespace amalgam
