// Dynamically enriched MPM with particle domains (Zhu et al. 2017, "Dynamically enriched MPM for
// invertible elasticity"; docs/architecture.md lists the papers): kernels.
//
// Every particle p owns a hexahedral domain whose 8 corners alpha are shared with its lattice
// neighbours, so the domains form one connected mesh (Sec. 4). Reference domains are lattice
// cells (boxes of edges h), for which the Gauss quadrature of eq. 6 is exact and gives
//   omega_ap = 1/8,   grad_X omega_ap = (s_x / (4 h_x), s_y / (4 h_y), s_z / (4 h_z)),  s in
//   {-1,1}^3
// (domain_reference_weights evaluates eq. 6 for any trilinear hexahedron; tests check both).
// The transfers are two-step, particle <-> corner <-> grid, with linear grid weights omega_i
// (eqs. 2-3):
//   particles_to_corners   m_a = sum_p omega_ap m_p,  p_a = sum_p omega_ap m_p v_p,
//                          f_a = -sum_p V_p^0 P_p grad_X omega_ap                (eqs. 5, 8)
//   points_to_grid         unenriched corners are points scattered with omega_i(x_a), so that
//                          m_i = sum_p omega_ip m_p and f_i = -sum_p V_p^0 P_p grad_X omega_ip
//   grid_to_corners        v_a = sum_i omega_i(x_a) v_i and the FLIP change dv_a     (eq. 9)
//   enriched corners       their own DOFs: v_a = (p_a + dt f_a) / m_a + dt g         (eq. 11)
//   corners_to_particles   v_p = (1 - alpha) sum_a omega_ap v_a + alpha (v_p + sum_a omega_ap
//   dv_a),
//                          F_p += dt sum_a v_a (grad_X omega_ap)^T                   (eq. 7)
//   advect                 x_a += dt v_a (eq. 9; time integration for enriched corners),
//                          x_p = sum_a omega_ap x_a
// Enrichment (Sec. 5.1-5.2): K(F) = 3 / (|F^-1|_F |F|_F) <= epsilon (eq. 10 scaled so that K(I) =
// 1, see enrichment_metric) or a principal stretch at the clamp (flattened or inverted, as the
// authors' code does) marks the particle's 8 corners; a particle is enriched (all 8 corners
// enriched), transitional or unenriched (Fig. 3).
// Inversion (Sec. 5.3, Irving et al. 2004): F = U S V^T with rotations U, V, S clamped below at
// `clamp`, P = U P(S) V^T; K is measured on the clamped S.
// Collisions (Sec. 7): corners that would end inside a collider get the collider's velocity
// projection (so the particles receive the impulse) and are pushed back to its surface.
//
// Every kernel is a gather (corner <- its particles through a CSR adjacency, particle <- its 8
// corners, point <- its grid nodes) or a colour-partitioned block scatter like P2G: results are
// bitwise identical on every backend and thread count.
#pragma once

#include <cstdint>

#include "core/exec/exec.hpp"
#include "core/materials/isotropic.hpp"
#include "core/materials/material.hpp"
#include "core/math/types.hpp"
#include "core/geometry/colliders.hpp"
#include "kernels/mpm_transfers.hpp"

namespace amalgam {

// Particle states (attribute "domain_state").
enum DomainState : std::int32_t {
  kDomainDisabled = -1,
  kUnenriched = 0,
  kTransitional = 1,
  kEnriched = 2
};

struct DomainParticleView {
  Vec3* x;
  Vec3* v;
  Mat3* F;
  const Real* volume0;  // mass: MaterialParams::mass(volume0) of the particle's material
  const std::int32_t* material;
  const std::int32_t*
      corners;          // 8 per particle; slot a = 4 bx + 2 by + bz, corner at X_p + (b - 1/2) h
  const Vec3* h;        // reference domain edges
  std::int32_t* state;  // DomainState
  std::size_t n;
  const MaterialParams* materials = nullptr;  // indexed by material (the mass, density x volume0)
  const Real* plastic = nullptr;
  const Real* temperature = nullptr;
  // Disabled particles: their velocity gradient (viscous stress); null when no material is
  // viscous (MpmSolver::keeps_affine), as nothing then reads it.
  Mat3* C = nullptr;
  // The low parts of x and F (core/math/types.hpp: add_compensated): disabled particles advance
  // x + x_lo; a domain particle's position is its corners' mean (x_lo = 0).
  Vec3* x_lo = nullptr;
  Mat3* F_lo = nullptr;
};

struct DomainCornerView {
  Vec3* x;
  Real* m;
  Vec3* p;   // momentum
  Vec3* f;   // elastic force
  Vec3* v;   // v^{n+1}
  Vec3* dv;  // v^{n+1} - v^n (FLIP)
  std::int32_t* enriched;
  const std::uint32_t* adj_start;  // n + 1: corner -> its particles
  const std::uint32_t* adj;        // (particle << 3) | slot
  std::size_t n;
};

// Transfer points, binned by grid leaf (linear stencils): the unenriched corners, and the
// particles whose domain is disabled (Sec. 8: they transfer as plain MPM points).
struct DomainPointView {
  Vec3* x;
  Real* m;
  Vec3* p;
  Vec3* f;
  std::int32_t* corner;  // source: corner index, or -(particle + 1) for a disabled particle
  std::size_t n;
  Mat3* stress = nullptr;  // disabled particles: V0 tau (zero for corners)
};

struct DomainParams {
  Real dx = Real(0.01);
  Real dt = Real(1e-4);
  Real flip_alpha = Real(0.95);
  Real epsilon = Real(0.6);  // enrichment threshold on K(F) (eq. 10)
  bool enrichment = true;
  Real clamp = Real(0.15);  // smallest principal stretch the stress sees (inversion handling)
  bool elastic = true;      // false: no elastic stress (strength switched off, Fig. 5)
  Vec3 gravity = Vec3(0, Real(-9.81), 0);
  Real time = 0;  // start of the substep
  const MaterialParams* materials = nullptr;
  const Collider* colliders = nullptr;
  int ncolliders = 0;
};

// grad_X omega_ap of a box domain with edges h (closed form of eq. 6).
inline Vec3 box_corner_gradient(int slot, const Vec3& h) {
  return Vec3(((slot >> 2) & 1 ? Real(1) : Real(-1)) / (4 * h[0]),
              ((slot >> 1) & 1 ? Real(1) : Real(-1)) / (4 * h[1]),
              (slot & 1 ? Real(1) : Real(-1)) / (4 * h[2]));
}
inline Vec3 box_corner_offset(int slot, const Vec3& h) {
  return Vec3(((slot >> 2) & 1 ? Real(0.5) : Real(-0.5)) * h[0],
              ((slot >> 1) & 1 ? Real(0.5) : Real(-0.5)) * h[1],
              (slot & 1 ? Real(0.5) : Real(-0.5)) * h[2]);
}

// grad_X N_slot at Gauss point g (of the 2x2x2 rule, xi = +-1/sqrt(3), g = 4 gx + 2 gy + gz) of a
// box domain with edges h: (s_x / h_x) (1 + s_y xi_y)(1 + s_z xi_z) / 4 and cyclic.
inline Vec3 box_gauss_gradient(int slot, int g, const Vec3& h) {
  const Real r = Real(0.57735026918962576);
  Vec3 t, s;
  for (int k = 0; k < 3; ++k) {
    s[k] = (slot >> (2 - k)) & 1 ? Real(1) : Real(-1);
    t[k] = (1 + s[k] * ((g >> (2 - k)) & 1 ? r : -r)) / 2;
  }
  return Vec3(s[0] / h[0] * t[1] * t[2], s[1] / h[1] * t[0] * t[2], s[2] / h[2] * t[0] * t[1]);
}

// Eq. 6 by 2x2x2 Gauss quadrature for the trilinear hexahedron with reference corners X[slot]:
// omega[a] = (1/V) int N_a dX, grad[a] = (1/V) int grad_X N_a dX; returns the volume V.
Real domain_reference_weights(const Vec3 X[8], Real omega[8], Vec3 grad[8]);

// Enrichment metric K(F) (eq. 10) of singular values s (already clamped), scaled by the
// dimension: as printed, 1 / (|F^-1|_F |F|_F) is at most 1/3 in 3D (F = I gives 1/3), so the
// paper's epsilon = 0.6 would enrich every particle at rest; the paper describes K as ranging
// from 0 to 1 with 1 the best condition, which 3 / (|F^-1|_F |F|_F) does (1 exactly for scaled
// rotations). Uniaxial stretch 3x (or 1/3) gives K = 0.62, 4x 0.48.
inline Real enrichment_metric(const Vec3& s) {
  const Real a = s.squaredNorm(), b = (s.cwiseInverse()).squaredNorm();
  return Real(3) / std::sqrt(a * b);
}

// Elastic Hessian of a particle in the SVD frame of its clamped F (implicit solves).
struct DomainHessian {
  Mat3 U, V;
  SvdFrameHessian<Real> h;
  Real V0;
  // V0 dP for an increment dF (eq. 16: the fix, when made, is in h).
  Mat3 stress_differential(const Mat3& dF) const {
    return V0 * (U * h.apply(U.transpose() * dF * V) * V.transpose());
  }
};

// Eight-point quadrature of the transitional and enriched particles (the authors' code: their
// enriched corners are FE nodes, and the one-point rule of eq. 8 would leave the domain mesh's
// hourglass modes without stiffness). Per listed particle, per Gauss point g: the stress at
// F_g = sum_a x_a (grad_X N_a(xi_g))^T, and the Hessian cache for implicit solves.
struct DomainQuadrature {
  const std::int32_t* index = nullptr;  // per particle: its entry in the list, or -1 (one point)
  const std::uint32_t* particles = nullptr;
  std::size_t n = 0;
  Mat3* piola = nullptr;          // 8 per entry
  DomainHessian* hess = nullptr;  // 8 per entry (V0 / 8 each), implicit only
  Mat3* scratch = nullptr;        // 8 per entry (Hessian action)
};

// First Piola stress of every enabled particle at its clamped F (Sec. 5.3), optionally the
// Hessian cache (made positive semi-definite when psd: eqs. 16, 19), the smallest clamped
// principal stretch smin, and the enrichment criterion (eq. 10; never when !prm.enrichment):
// state 3 for a particle that meets it, 0 otherwise (domain_mark_enrichment finishes the states).
void domain_stresses(const exec::Space& space, const DomainParticleView& p, const DomainParams& prm,
                     Mat3* piola, DomainHessian* hess, bool psd, Real* smin);
// Corners of the marked particles become enriched; particle states from their corners. Returns
// the number of particles in each state and of enriched corners.
struct EnrichmentCounts {
  std::size_t unenriched = 0, transitional = 0, enriched = 0, corners = 0;
};
EnrichmentCounts domain_mark_enrichment(const exec::Space& space, const DomainParticleView& p,
                                        const DomainCornerView& c);
// Stresses (and Hessians, when q.hess) at the Gauss points of the listed particles, from the
// corner positions (after domain_mark_enrichment decided the states).
void domain_quadrature_stresses(const exec::Space& space, const DomainParticleView& p,
                                const DomainCornerView& c, const DomainParams& prm,
                                const DomainQuadrature& q, bool psd);
// Corner mass, momentum and force from their particles (gather); the listed particles' forces
// from their eight Gauss points.
void domain_particles_to_corners(const exec::Space& space, const DomainParticleView& p,
                                 const DomainCornerView& c, const Mat3* piola,
                                 const DomainQuadrature& q);
// Deterministic compaction of the unenriched corners with mass into points: start[a] = index of
// corner a's point (exclusive scan of the flags), returns the count; then collect.
std::size_t domain_point_offsets(const exec::Space& space, const DomainCornerView& c,
                                 std::uint32_t* start);
void domain_collect_points(const exec::Space& space, const DomainCornerView& c,
                           const std::uint32_t* start, const DomainPointView& out);
// Scatter of the binned points with linear weights: g.a = (m, p), g.b = (-, f) (the PIC/FLIP
// layout grid_update expects). Clears the active leaves first.
void domain_points_to_grid(const exec::Space& space, const DomainPointView& pts,
                           const MpmGridView& g, Real dx);
// After grid_update: v and dv of the points' corners from g.a (m, v) and g.b (-, dv); disabled
// particles' points update their particle as plain PIC/FLIP MPM (v, C = grad v, F, x, collider
// push-out).
void domain_grid_to_corners(const exec::Space& space, const DomainPointView& pts,
                            const MpmGridView& g, Real dx, const DomainCornerView& c,
                            const DomainParticleView& p, const DomainParams& prm);
// Disabled particles as transfer points after the corners' (offsets, then collect at base).
std::size_t domain_particle_point_offsets(const exec::Space& space, const DomainParticleView& p,
                                          std::uint32_t* start);
void domain_collect_particle_points(const exec::Space& space, const DomainParticleView& p,
                                    const DomainParams& prm, const std::uint32_t* start,
                                    std::size_t base, const DomainPointView& out);
// Disables the domains of melted particles (Sec. 8, Fig. 11: topology may change where the
// material melts); returns the number of disabled particles.
std::size_t domain_disable_melted(const exec::Space& space, const DomainParticleView& p,
                                  const MaterialParams* materials);
// Explicit update of the enriched corners (their own DOFs): v = (p + dt f) / m + dt g.
void domain_update_enriched_corners(const exec::Space& space, const DomainCornerView& c,
                                    const DomainParams& prm);
// Collider velocity projection at the corners' end-of-step positions x + dt v (Sec. 7).
void domain_collide_corners(const exec::Space& space, const DomainCornerView& c,
                            const DomainParams& prm);
// Particle velocity (PIC/FLIP) and F (eq. 7) from the corners.
void domain_corners_to_particles(const exec::Space& space, const DomainParticleView& p,
                                 const DomainCornerView& c, const DomainParams& prm);
// x_a += dt v_a (pushed out of non-sticky colliders), then x_p = sum_a omega_ap x_a.
void domain_advect(const exec::Space& space, const DomainParticleView& p, const DomainCornerView& c,
                   const DomainParams& prm);

// Implicit solve (Sec. 6): the Hessian action on stacked velocity increments. `du_grid` is the
// grid part ([leaf][512][4]), `du_corner` the enriched corners' part (4 lanes per DOF, indexed by
// dof[a] >= 0). The kernels go grid -> points (gather), enriched DOFs -> corners, corners ->
// particles (dF), particles -> corners (V0 dP grad omega), points -> grid (scatter).
// Corner increments: du_c[a] for every corner with mass.
void domain_corner_increments(const exec::Space& space, const DomainPointView& pts,
                              const MpmGridView& g, Real dx, const Real* du_grid,
                              const DomainCornerView& c, const std::int32_t* dof,
                              const Real* du_corner, Vec3* du_c);
// Corner forces of the increments: df_c[a] = sum_p V0 dP_p grad omega_ap with dF_p = sum_a du_c[a]
// grad^T.
// Listed particles: per Gauss point (q.scratch).
void domain_corner_hessian_forces(const exec::Space& space, const DomainParticleView& p,
                                  const DomainCornerView& c, const DomainHessian* hess,
                                  const DomainQuadrature& q, const Vec3* du_c, Mat3* scratch,
                                  Vec3* df_c);
// out_grid += scale * sum over unenriched points of omega_i df_c (scatter; 4 lanes, lane 3
// untouched); out_corner[dof[a]] += scale * df_c[a] for enriched corners.
void domain_forces_to_dofs(const exec::Space& space, const DomainPointView& pts,
                           const MpmGridView& g, Real dx, const DomainCornerView& c,
                           const std::int32_t* dof, const Vec3* df_c, Real scale, Real* out_grid,
                           Real* out_corner);
// Jacobi diagonal: diag_grid += scale * sum over unenriched points of omega_i^2 d_c (the corner
// diagonal pushed with squared weights, cross-corner terms dropped), diag_corner[dof] += scale d_c.
void domain_diagonal_to_dofs(const exec::Space& space, const DomainPointView& pts,
                             const MpmGridView& g, Real dx, const DomainCornerView& c,
                             const std::int32_t* dof, const Vec3* d_c, Real scale, Real* diag_grid,
                             Real* diag_corner);
// Per-corner diagonal of the corner-level Hessian (eq. 18 with the frame of eq. 19):
// d_c[a] = sum_p V0 (grad omega_ap (x) e_k) : dP/dF : (grad omega_ap (x) e_k), k = x, y, z.
void domain_corner_hessian_diagonal(const exec::Space& space, const DomainParticleView& p,
                                    const DomainCornerView& c, const DomainHessian* hess,
                                    const DomainQuadrature& q, Vec3* d_c);

}  // namespace amalgam
