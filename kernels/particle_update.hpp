// The per-particle bodies of the material update and the particle collisions
// (kernels/material_update.cpp), shared with the fused G2P2G (kernels/mpm_transfers.cpp), which
// runs them on a bin's particles between its gather and its scatter. Included by files compiled
// once per instruction set (core/exec/simd.hpp): the functions live in that set's namespace.
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/exec/simd.hpp"
#include "core/math/lanes.hpp"
#include "core/math/svd3.hpp"
#include "kernels/material_update.hpp"

namespace amalgam {
namespace AMALGAM_ISA {

// Material update of particles [i0, i1), at most lanes::kN of them: heat sources, then each
// particle's projection; the SVDs that the plastic return mappings start from, and the cube
// roots of the fluid's F reset, are computed for the group at once, one particle per vector lane
// (svd3_lanes, detail::cube_root_lanes: bitwise each particle's svd3 and cube_root).
inline void update_material_group(const MpmParticleView& p, const MaterialUpdateParams& prm,
                                  exec::Index i0, exec::Index i1) {
  constexpr int kN = lanes::kN<Real>;
  Real temperature[kN], J[kN], root[kN];
  Mat3 F[kN];
  // Particles keeping b - I (MpmParticleView::b): its Cholesky factor stands in for F (every
  // material is isotropic); a projection writes back the new F's F F^T - I.
  Mat3 Fb[kN];
  if (p.b) b_factor_lanes(p.b + i0, int(i1 - i0), Fb);
  auto F_of = [&](exec::Index i) -> Mat3& { return p.b ? Fb[i - i0] : p.F[i]; };
  int lane_of[kN], m = 0, r = 0;
  for (exec::Index i = i0; i < i1; ++i) {
    Real& ti = temperature[i - i0];
    ti = p.temperature ? p.temperature[i] : Real(0);
    if (p.temperature && prm.nsources > 0) {
      for (int s = 0; s < prm.nsources; ++s) {
        const HeatSource& h = prm.sources[s];
        if (h.region.phi(p.x[i], prm.time) <= 0)
          ti = h.temperature + (ti - h.temperature) * std::exp(-h.rate * prm.dt);
      }
      p.temperature[i] = ti;
    }
    const MaterialParams& mat = prm.materials[p.material[i]];
    if (mat.project_is_reset(ti)) {  // WeaklyCompressibleT::reset: its J here, its root below
      lane_of[i - i0] = kN + r;
      J[r++] = WeaklyCompressibleT<Real>::reset_J(F_of(i));
      continue;
    }
    const bool svd = mat.project_takes_svd(ti);
    lane_of[i - i0] = svd ? m : -1;
    if (svd) F[m++] = F_of(i);
  }
  Svd3<Real> d[kN];
  if (m > 0) svd3_lanes(F, m, d);
  if (r > 0) detail::cube_root_lanes(J, root, r);
  for (exec::Index i = i0; i < i1; ++i) {
    const MaterialParams& mat = prm.materials[p.material[i]];
    const int l = lane_of[i - i0];
    if (l >= kN) {  // the fluid's reset, F <- J^{1/3} I
      if (p.b) {
        const Real s = root[l - kN] * root[l - kN] - 1;  // b - I = (J^{2/3} - 1) I
        p.b[i] = SymDev{{s, s, s, 0, 0, 0}};
        continue;
      }
      p.F[i] = root[l - kN] * Mat3::Identity();
      if (p.F_lo) p.F_lo[i].setZero();
      continue;
    }
    Real plastic = p.plastic ? p.plastic[i] : Real(0);
    Mat3& Fi = F_of(i);
    if (l >= 0 ? mat.project(Fi, plastic, d[l]) : mat.project(Fi, plastic, temperature[i - i0])) {
      if (p.plastic) p.plastic[i] = plastic;
      if (p.F_lo) p.F_lo[i].setZero();  // the projected F is new: no low part carries over
      if (p.b) p.b[i] = b_from_F<Real>(Fi.cast<double>());
    }
  }
}

// What the particle collisions do to particle i inside collider c (phi < 0).
inline void collide_one(const MpmParticleView& p, const Collider& c, exec::Index i, Real phi,
                        Real time) {
  if (c.boundary == BoundaryType::Sticky) {  // a grip holds what it holds
    p.v[i] = c.velocity_at(p.x[i], time);
    return;
  }
  const Vec3 nrm = c.outward_normal(p.x[i], time);
  if (p.x_lo)
    add_compensated(p.x[i], p.x_lo[i], Vec3(-phi * nrm));
  else
    p.x[i] -= phi * nrm;
  c.project(p.x[i], time, p.v[i]);
}

// Particle i against every collider, in their order (collide_particles' result for it).
inline void collide_particle(const MpmParticleView& p, const Collider* colliders, int n,
                             exec::Index i, Real time) {
  for (int c = 0; c < n; ++c) {
    const Collider& col = colliders[c];
    if (time > col.until) continue;  // released: phi is kReleased everywhere
    const Real phi = col.phi(p.x[i], time);
    if (phi < 0) collide_one(p, col, i, phi, time);
  }
}

// The box of positions x[i0 .. i1) (a NaN coordinate is left out: its phi is never < 0).
inline void position_box(const Vec3* x, exec::Index i0, exec::Index i1, Vec3& lo, Vec3& hi) {
  lo = Vec3::Constant(std::numeric_limits<Real>::infinity());
  hi = -lo;
  for (exec::Index i = i0; i < i1; ++i)
    for (int a = 0; a < 3; ++a) {
      lo[a] = x[i][a] < lo[a] ? x[i][a] : lo[a];
      hi[a] = x[i][a] > hi[a] ? x[i][a] : hi[a];
    }
}

// Particles [i0, i1) against every collider, each particle meeting them in their order
// (collide_particle's result for each): the loops interchanged (colliders outer), in chunks of
// kCollideChunk particles, so that a half-space's test is one tight loop with its plane hoisted:
// phi = (x - c) . n, exactly Collider::phi's expression. Most particles are outside every collider
// and never reach collide_one; a collider the chunk's box of positions lies clear of
// (Collider::phi_at_least > 0: no particle's phi below 0) is skipped for the chunk, and the box is
// taken again after a collider moved some of them.
constexpr exec::Index kCollideChunk = 256;
inline void collide_range(const MpmParticleView& p, const Collider* colliders, int n,
                          exec::Index i0, exec::Index i1, Real time) {
  for (exec::Index c0 = i0; c0 < i1; c0 += kCollideChunk) {
    const exec::Index c1 = std::min(i1, c0 + kCollideChunk);
    Vec3 lo, hi;
    bool boxed = false;
    for (int c = 0; c < n; ++c) {
      const Collider& col = colliders[c];
      if (time > col.until) continue;  // released: phi is kReleased everywhere
      if (!boxed) position_box(p.x, c0, c1, lo, hi), boxed = true;
      if (col.phi_at_least(lo, hi, time) > 0) continue;
      bool moved = false;
      if (col.shape == ColliderShape::HalfSpace) {
        const Vec3 o = col.origin + time * col.velocity, nrm = col.normal;
        Real phi[kCollideChunk];  // a branch-free loop the compiler vectorises, then the few inside
        for (exec::Index i = c0; i < c1; ++i) phi[i - c0] = (p.x[i] - o).dot(nrm);
        for (exec::Index i = c0; i < c1; ++i)
          if (phi[i - c0] < 0) collide_one(p, col, i, phi[i - c0], time), moved = true;
      } else {
        for (exec::Index i = c0; i < c1; ++i) {
          const Real phi = col.phi(p.x[i], time);
          if (phi < 0) collide_one(p, col, i, phi, time), moved = true;
        }
      }
      boxed = !moved;
    }
  }
}

}  // namespace AMALGAM_ISA
}  // namespace amalgam
