// Kernels of the implicit (backward Euler, one Newton step) MPM velocity update: the action of
// the elastic Hessian on grid velocity increments, its diagonal, and elastic forces at a grid
// displacement (enriched MPM Sec. 6, eqs. 14-19; A-ULMPM eqs. 24-26; Stomakhin et al. 2013).
//
// With grid displacement u, F_p(u) = (I + sum_j u_j g_jp^T) F_p and E(u) = sum_p V_p^0 Psi(F_p(u)):
//   force      f_i = -dE/du_i = -sum_p V_p^0 P(F_p) F_p^T g_ip
//   Hessian    (H du)_i = sum_p V_p^0 A_p F_p^T g_ip,  A_p = d^2 Psi/dF dF : (sum_j du_j g_jp^T F_p)  (eq. 15)
// where g_ip is the gradient the transfer uses: grad w_ip (PIC/FLIP, APIC), or MLS-MPM's
// w_ip D_p^{-1} (x_i - x_p), which makes these the exact derivatives of the discrete energy each
// scheme integrates. Per particle the Hessian is cached in the SVD frame of F = U S V^T once per
// step; since F V = U S, with Ghat = U^T grad(du) U and R = frame(Ghat S):
//   V_p^0 A_p F_p^T = V_p^0 U (R S) U^T          (no V needed; eq. 16 with the fix applied to R)
// A-ULMPM (p.X_ref set): stencils at X^s, g_ip = (F^{sn})^{-T} g^s_ip (see implicit_mpm.cpp).
// Vectors are 4 lanes per grid node, [leaf][512][4] (lane 3 unused), like the transfer channels.
// The action is one pass per colour: each bin gathers du from its 8 leaves, computes its
// particles' contributions into a private block and adds it into its 8 leaves of `out`. Same-
// colour bins never share a leaf, so it is race-free and bitwise deterministic like P2G.
#pragma once

#include "core/exec/exec.hpp"
#include "core/materials/isotropic.hpp"
#include "core/materials/material.hpp"
#include "kernels/mpm_transfers.hpp"

namespace amalgam {

// Elastic Hessian of one particle in the SVD frame of its F, scaled by nothing (V_p^0 apart).
struct ParticleHessian {
  Mat3 U;
  Vec3 sigma;
  SvdFrameHessian<Real> h;
  Real V0;
  Vec3 tau;  // principal Kirchhoff stresses p_i sigma_i: tau = P F^T = U diag(tau) U^T
};

// The part of MpmStepParams these kernels use.
struct ImplicitKernelParams {
  int order = 2;
  Transfer transfer = Transfer::Mls;  // selects g_ip: MLS weights or B-spline gradients
  Real dx = Real(0.01);
  const MaterialParams* materials = nullptr;
};

// One SVD per particle: U, sigma, the frame Hessian (made positive semi-definite if `psd`).
void prepare_particle_hessians(const exec::Space& space, const MpmParticleView& p,
                               const ImplicitKernelParams& prm, bool psd, ParticleHessian* out);

// out += scale * H du over the grid (both [leaf][512][4]).
void mpm_hessian_action(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                        const ImplicitKernelParams& prm, const ParticleHessian* hess,
                        const Real* du, Real scale, Real* out);

// diag += scale * diag(H) (per node and axis; eq. 18 with the fix of eq. 19 if the cache has it).
void mpm_hessian_diagonal(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                          const ImplicitKernelParams& prm, const ParticleHessian* hess, Real scale,
                          Real* diag);

// f += elastic force at grid displacement u (u == nullptr: zero displacement), recomputing
// P(F_p(u)) from the materials. For finite-difference checks of the Hessian and for solvers that
// need the force apart from the transfer.
void mpm_elastic_forces(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                        const ImplicitKernelParams& prm, const Real* u, Real* f);

// f += elastic force at zero displacement from the cached stresses (no SVD): what the implicit
// solver subtracts from v* for its initial guess.
void mpm_cached_elastic_forces(const exec::Space& space, const MpmParticleView& p,
                               const MpmGridView& g, const ImplicitKernelParams& prm,
                               const ParticleHessian* hess, Real* f);

// Per-particle pieces, pure (no grid), for tests:
// V_p^0 A_p F_p^T for a velocity-increment gradient grad_du.
inline Mat3 particle_stress_differential(const ParticleHessian& ph, const Mat3& grad_du) {
  const Mat3 M = (ph.U.transpose() * grad_du * ph.U) * ph.sigma.asDiagonal();
  const Mat3 R = ph.h.apply(M);
  return ph.V0 * (ph.U * (R * ph.sigma.asDiagonal()) * ph.U.transpose());
}
ParticleHessian particle_hessian(const MaterialParams& m, const Mat3& F, Real plastic,
                                 Real temperature, Real V0, bool psd);

}  // namespace amalgam

namespace amalgam {

// Grid -> implicit DOFs: mass (1 per node) and velocity (4 lanes) from the transfer channel
// a = (m, v) after the explicit grid update, for the active leaves (DOF = 512 leaf + offset).
void grid_velocities_to_dofs(const exec::Space& space, const MpmGridView& g, Real* mass, Real* v);
// v -= dt f / m on the active leaves' nodes with mass (the implicit solve's initial guess).
void initial_guess_from_force(const exec::Space& space, const MpmGridView& g, const Real* mass,
                              const Real* f, Real dt, Real* v);
// DOFs -> grid: a's velocity lanes <- v; PIC/FLIP's b (v_new - v_old) shifts by the same change.
void dofs_to_grid_velocities(const exec::Space& space, const MpmGridView& g, const Real* v);

}  // namespace amalgam
