// Implicit MPM (backward Euler, one Newton step: enriched MPM Sec. 6, A-ULMPM eq. 26), a component
// of MpmSolver (solvers/mpm_solver.hpp). In the substep it replaces the explicit grid velocities
// by the solve of (M + dt^2 H) v = M v*, after the grid update:
//   assemble   grid DOFs, v* and its mass, the colliders as constraints, the particles' elastic
//              Hessians, and the initial guess v* - dt M^-1 f^n
//   solve      matrix-free Jacobi-preconditioned CG (MINRES fallback)    (solvers/implicit_system)
//   friction   Coulomb friction at the contacts, from the normal velocity the constraint removed
//   back       velocities to the grid, one more collider projection for separating nodes
// The enriched step (solvers/mpm_enriched.cpp) solves with its corners as extra DOFs through the
// same collider constraints, counters and friction.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "core/exec/exec.hpp"
#include "kernels/implicit_mpm.hpp"
#include "kernels/mpm_transfers.hpp"
#include "solvers/implicit_system.hpp"

namespace amalgam {

class MpmSolver;

// Implicit solves since the counters were last reset (per frame in the runner).
struct ImplicitCounters {
  std::uint64_t solves = 0, iterations = 0, minres = 0, unconverged = 0;
  int max_iterations = 0;
  double max_residual = 0;
};

class MpmImplicit {
 public:
  explicit MpmImplicit(const ImplicitSettings& settings) : settings_(settings) {}

  // The implicit grid velocities of the substep (after MpmSolver::update_grid_velocities).
  void solve_grid_velocities(const exec::Space& space, MpmSolver& mpm, Real dt);
  // Sets up the system for the current grid (mass, v*, constraints, Hessian cache, elastic term)
  // without solving: what solve_grid_velocities does before its solve (tests, benchmarks).
  void assemble(const exec::Space& space, MpmSolver& mpm, Real dt);

  // Pieces the enriched step shares. Colliders -> constraints on the grid DOFs of `g`.
  void add_collider_constraints(const exec::Space& space, const MpmSolver& mpm,
                                const MpmGridView& g, Real dt);
  // Solves the assembled system and adds the solve to the counters.
  void solve_and_count(const exec::Space& space, Real dt);
  // Coulomb friction at the contacts found by add_collider_constraints.
  void apply_friction(Real* v) const;

  ImplicitSystem& system() { return system_; }
  const ImplicitSystem& system() const { return system_; }
  const SolveStats& last_solve() const { return last_solve_; }
  const ImplicitCounters& counters() const { return counters_; }
  void reset_counters() { counters_ = {}; }

 private:
  ImplicitSettings settings_;
  ImplicitSystem system_;
  std::vector<ParticleHessian> hessians_;
  std::vector<Real> guess_force_;
  std::unique_ptr<ImplicitTerm> elastic_term_;
  struct FrictionContact {
    std::uint64_t dof;
    Vec3 n, vc;
    Real vn_star, mu;
  };
  std::vector<FrictionContact> contacts_;
  std::vector<std::uint8_t> in_collider_;
  SolveStats last_solve_;
  ImplicitCounters counters_;
};

}  // namespace amalgam
