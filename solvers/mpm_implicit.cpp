#include "solvers/mpm_implicit.hpp"

#include <algorithm>

#include "solvers/mpm_elastic_term.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

namespace {
// Where a node is tested against colliders: its lattice position, or in A-ULMPM its rasterised
// current position q_i (eq. 12) when the grid view carries them.
inline Vec3 node_position(const MpmGridView& g, std::size_t d, const Vec3& lattice) {
  if (!g.q) return lattice;
  const Real* q = g.q + d * 4;
  return q[0] > 0 ? Vec3(q[1] / q[0], q[2] / q[0], q[3] / q[0]) : lattice;
}
}  // namespace

void MpmImplicit::add_collider_constraints(const exec::Space& space, const MpmSolver& mpm,
                                           const MpmGridView& g, Real dt) {
  // Colliders -> constraints (enriched MPM Sec. 7 / Stomakhin et al. 2013, as projections): a
  // node inside a sticky collider takes its velocity; slip fixes the normal velocity; separating
  // only while v* approaches. Friction is applied after the solve from the normal velocity v*
  // had to lose. Detection in parallel, constraints added serially (few nodes).
  contacts_.clear();
  const int ncol = mpm.collider_count();
  if (ncol == 0) return;
  const Real t_end = Real(mpm.time()) + dt, dx = mpm.settings().dx;
  const Collider* cols = mpm.colliders_at(t_end);
  const std::size_t ngrid = mpm.grid().leaf_count() * std::size_t(kLeafNodes);
  in_collider_.assign(ngrid, 0);
  std::uint8_t* flag = in_collider_.data();
  const Real* mass = system_.mass();
  exec::parallel_for(space, "implicit.find_contacts", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t leaf = std::size_t(g.active_leaves[li]);
    const Vec3i node0 = g.leaf_coord[leaf] * kLeafDim;
    for (int i = 0; i < kLeafDim; ++i)
      for (int j = 0; j < kLeafDim; ++j)
        for (int k = 0; k < kLeafDim; ++k) {
          const std::size_t d = leaf * kLeafNodes + std::size_t(leaf_offset(i, j, k));
          if (mass[d] <= 0) continue;
          const Vec3 xi = node_position(g, d, (node0 + Vec3i(i, j, k)).cast<Real>() * dx);
          for (int c = 0; c < ncol; ++c)
            if (cols[c].phi(xi, t_end) <= node_tolerance(xi, dx)) flag[d] = 1;
        }
  });
  const Real* vstar = system_.rhs();
  for (const std::int32_t leaf : mpm.grid().active_leaves()) {
    const Vec3i node0 = g.leaf_coord[leaf] * kLeafDim;
    for (int o = 0; o < kLeafNodes; ++o) {
      const std::size_t d = std::size_t(leaf) * kLeafNodes + std::size_t(o);
      if (!flag[d]) continue;
      const Vec3 xi =
          node_position(g, d, (node0 + Vec3i(o >> 6, (o >> 3) & 7, o & 7)).cast<Real>() * dx);
      const Vec3 vs(vstar[d * 4], vstar[d * 4 + 1], vstar[d * 4 + 2]);
      for (int c = 0; c < ncol; ++c) {
        const Collider& col = cols[c];
        if (col.phi(xi, t_end) > node_tolerance(xi, dx)) continue;
        const Vec3 vc = col.velocity_at(xi, t_end);
        if (col.boundary == BoundaryType::Sticky) {
          system_.fix(d, vc);
          continue;
        }
        const Vec3 n = col.outward_normal(xi, t_end);
        const Real vn = (vs - vc).dot(n);
        if (col.boundary == BoundaryType::Separate && vn >= 0) continue;
        system_.constrain_normal(d, n, n.dot(vc));
        if (col.friction > 0) contacts_.push_back({d, n, vc, std::min(vn, Real(0)), col.friction});
      }
    }
  }
}

void MpmImplicit::assemble(const exec::Space& space, MpmSolver& mpm, Real dt) {
  const MpmGridView g = mpm.grid_view_with_positions();
  const std::size_t ngrid = mpm.grid().leaf_count() * std::size_t(kLeafNodes);
  system_.begin(ngrid, mpm.grid().active_leaves());
  system_.finalize();
  grid_velocities_to_dofs(space, g, system_.mass(), system_.rhs());
  std::copy(system_.rhs(), system_.rhs() + ngrid * 4, system_.solution());  // v*, guess below

  add_collider_constraints(space, mpm, g, dt);

  hessians_.resize(mpm.particles().size());
  ImplicitKernelParams kp;
  kp.order = mpm.settings().order;
  kp.transfer = mpm.settings().transfer;
  kp.dx = mpm.settings().dx;
  kp.materials = mpm.materials().data();
  const MpmParticleView pv = mpm.particle_view();
  prepare_particle_hessians(space, pv, kp, settings_.definiteness_fix, hessians_.data());
  elastic_term_ = std::make_unique<MpmElasticTerm>(pv, g, kp, hessians_.data());
  system_.add_term(elastic_term_.get());

  // Initial guess v* - dt M^-1 f^n (the grid velocity before the elastic force, with gravity):
  // the explicit predictor v* itself overshoots by (dt / dt_CFL)^2 wherever the body deforms,
  // so starting from it costs CG many iterations just to undo the explicit step (measured:
  // a stiff armadillo at 28x CFL, 25 -> 7-10 CG iterations per substep in free fall, 60-120 ->
  // 35-58 on the floor; docs/benchmarks.md).
  guess_force_.assign(ngrid * 4, Real(0));
  mpm_cached_elastic_forces(space, pv, g, kp, hessians_.data(), guess_force_.data());
  initial_guess_from_force(space, g, system_.mass(), guess_force_.data(), dt, system_.solution());
}

// Coulomb friction at the contacts: the tangential velocity loses mu times the normal velocity
// the constraint removed (Stomakhin et al. 2013's grid collision, after the solve).
void MpmImplicit::apply_friction(Real* v) const {
  for (const FrictionContact& c : contacts_) {
    Real* vd = v + c.dof * 4;
    const Vec3 vrel = Vec3(vd[0], vd[1], vd[2]) - c.vc;
    const Real vn = vrel.dot(c.n);
    Vec3 vt = vrel - vn * c.n;
    const Real vt_norm = vt.norm();
    if (vt_norm > 0) vt *= std::max(Real(0), vt_norm + c.mu * c.vn_star) / vt_norm;
    const Vec3 out = c.vc + vn * c.n + vt;
    vd[0] = out[0], vd[1] = out[1], vd[2] = out[2];
  }
}

void MpmImplicit::solve_and_count(const exec::Space& space, Real dt) {
  last_solve_ = system_.solve(space, dt, settings_);
  ++counters_.solves;
  counters_.iterations += std::uint64_t(last_solve_.iterations);
  counters_.max_iterations = std::max(counters_.max_iterations, last_solve_.iterations);
  counters_.max_residual = std::max(counters_.max_residual, last_solve_.residual);
  counters_.minres += last_solve_.used_minres ? 1 : 0;
  counters_.unconverged += last_solve_.converged ? 0 : 1;
}

void MpmImplicit::solve_grid_velocities(const exec::Space& space, MpmSolver& mpm, Real dt) {
  assemble(space, mpm, dt);
  solve_and_count(space, dt);
  Real* v = system_.solution();
  apply_friction(v);
  const MpmGridView g = mpm.grid_view_with_positions();
  dofs_to_grid_velocities(space, g, v);
  // Separating nodes left free by the solve may approach a collider now: one more projection.
  grid_apply_colliders(space, g, mpm.step_params(dt));
}

}  // namespace amalgam
