// Backward-Euler velocity solve linearised with one Newton step (enriched MPM Sec. 6, eq. 12;
// A-ULMPM eq. 26; Stomakhin et al. 2013):
//   (I + dt^2 M^{-1} H) v = v*   solved in its symmetric, mass-weighted form   (M + dt^2 H) v = M v*
// matrix-free, over every active DOF: grid nodes with mass, then any extra DOF sets a method
// registers (the enriched particle-domain corners), stacked in one vector of 4 lanes per DOF
// (x, y, z, unused), like the grid's node rows (docs/architecture.md, "The grid"). H is the sum of registered terms (the particles' elastic
// energy for MPM; a method adds its own coupling); each term adds scale * H du and its diagonal.
//
// Solvers: Jacobi-preconditioned conjugate gradients (preconditioner diag(M + dt^2 H), eqs.
// 17-19) and preconditioned MINRES (Paige & Saunders 1975) for indefinite systems; CG switches to
// MINRES when it meets a direction of non-positive curvature (only possible without the
// definiteness fix). Stopping test, CG: the velocity error estimated by the preconditioned
// residual z = D^-1 r, ||z||_M <= tolerance max(||v*||_M, ||v0||_M) (D the Jacobi diagonal,
// ||.||_M the mass-weighted norm); MINRES: ||r||_{D^-1} <= tolerance ||M v*||_{D^-1} (its
// recurrence only knows that norm). Or the iteration limit.
//
// Boundary conditions are projections inside the solve (Baraff & Witkin 1998 filtered PCG):
// a fixed DOF has its velocity prescribed, a normal constraint prescribes n . v; the residual and
// search directions are kept in the free subspace. DOFs without mass are excluded.
//
// All vector operations are parallel over blocks of at most 512 DOFs with fixed chunking, and
// reductions combine in a fixed order, so solves are bitwise identical across backends and
// thread counts.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/math/types.hpp"

namespace amalgam {

enum class KrylovMethod { Cg, Minres };
const char* krylov_name(KrylovMethod m);

struct ImplicitSettings {
  double tolerance = 1e-4;  // relative velocity error (CG) / relative residual (MINRES)
  int max_iterations = 200;
  KrylovMethod method = KrylovMethod::Cg;
  bool definiteness_fix = true;  // Teran et al. 2005 (enriched MPM eq. 16)
};

struct SolveStats {
  int iterations = 0;
  double residual = 0;  // final relative residual
  bool converged = false;
  bool used_minres = false;
};

// A stiffness term over the stacked DOF vector (4 lanes per DOF).
class ImplicitTerm {
 public:
  virtual ~ImplicitTerm() = default;
  // out += scale * H du
  virtual void add_hessian_action(const exec::Space& space, const Real* du, Real scale,
                                  Real* out) const = 0;
  // diag += scale * diag(H)
  virtual void add_hessian_diagonal(const exec::Space& space, Real scale, Real* diag) const = 0;
};

class ImplicitSystem {
 public:
  // Starts a new layout: the grid owns DOFs [0, grid_dofs), of which the leaves in `grid_leaves`
  // (DOFs 512 leaf .. 512 leaf + 511) are in use.
  void begin(std::size_t grid_dofs, const std::vector<std::int32_t>& grid_leaves);
  // Registers an extra DOF set after the grid (and earlier sets); returns its first DOF index.
  std::size_t add_dof_set(std::size_t count);
  // Allocates the vectors of the layout (zeroed); terms and constraints are cleared.
  void finalize();

  std::size_t dof_count() const { return ndof_; }
  Real* mass() { return mass_.data(); }   // 1 per DOF; <= 0 excludes the DOF
  Real* rhs() { return vstar_.data(); }   // v*, 4 lanes per DOF
  Real* solution() { return x_.data(); }  // v: initial guess in, solution out
  const Real* solution() const { return x_.data(); }
  void add_term(const ImplicitTerm* term) {
    terms_.push_back(term);
    preconditioner_dt_ = -1;
  }

  // Constraints (call after finalize, before solve; one per DOF, later calls combine):
  void fix(std::size_t dof, const Vec3& v);                        // v prescribed
  void constrain_normal(std::size_t dof, const Vec3& n, Real vn);  // n . v = vn (n unit)
  std::size_t constraint_count() const { return con_dof_.size(); }

  // out = (M + dt^2 H) v (no projection). For tests and benchmarks.
  void apply(const exec::Space& space, Real dt, const Real* v, Real* out) const;
  // Builds the Jacobi preconditioner for dt (eq. 17) unless it is current; solve() calls it.
  void prepare(const exec::Space& space, Real dt);
  // Solves for solution() from rhs(); the initial guess is solution() (e.g. v*).
  SolveStats solve(const exec::Space& space, Real dt, const ImplicitSettings& settings);

  // The blocks vector kernels iterate: first DOF and count (<= 512).
  struct Block {
    std::uint64_t first;
    std::uint32_t count;
  };
  const std::vector<Block>& blocks() const { return blocks_; }

 private:
  std::size_t ndof_ = 0, grid_dofs_ = 0;
  std::vector<Block> blocks_;
  std::vector<const ImplicitTerm*> terms_;
  std::vector<Real> mass_, vstar_, x_, inv_diag_;
  std::vector<Real> r_, z_, p_, q_;                    // CG
  std::vector<Real> m_r1_, m_r2_, m_w_, m_w1_, m_w2_;  // MINRES extras
  std::vector<std::uint64_t> con_dof_;
  std::vector<Mat3> con_P_;              // projector onto the free directions
  std::vector<Vec3> con_val_;            // the prescribed part of v
  std::vector<std::int32_t> con_index_;  // per DOF, index into the constraint list or -1
  Real preconditioner_dt_ = -1;          // dt the preconditioner was built for (-1: stale)

  void project(const exec::Space& space, Real* v) const;
  void apply_preconditioner(const exec::Space& space, const Real* r, Real* z) const;
  double dot(const exec::Space& space, const Real* a, const Real* b) const;
  struct Dots {
    double rz = 0, mzz = 0;  // r . z and sum m |z|^2
  };
  Dots dots(const exec::Space& space, const Real* r, const Real* z) const;
  double mass_norm2(const exec::Space& space, const Real* v) const;  // sum m |v|^2
  void build_preconditioner(const exec::Space& space, Real dt);
  SolveStats minres(const exec::Space& space, Real dt, const ImplicitSettings& s, double bnorm,
                    int used);
};

}  // namespace amalgam
