#include "kernels/material_update.hpp"

#include <algorithm>
#include <cmath>

#include "core/exec/simd.hpp"
#include "core/math/lanes.hpp"
#include "core/math/svd3.hpp"

namespace amalgam {

// The kernels, once per instruction set (core/exec/simd.hpp): the return mappings' SVDs take
// 4, 8 or 16 particles per vector (baseline, AVX2, AVX-512).
namespace AMALGAM_ISA {

void update_material_state(const exec::Space& space, const MpmParticleView& p,
                           const MaterialUpdateParams& prm) {
  // Groups of kN consecutive particles: the SVDs that the plastic return mappings start from are
  // computed for the whole group at once, one particle per vector lane (svd3_lanes, bitwise each
  // particle's svd3); everything else is per particle.
  constexpr int kN = lanes::kN<Real>;
  const exec::Index n = exec::Index(p.n), groups = (n + kN - 1) / kN;
  exec::parallel_for(space, "mpm.material_update", groups, [&](exec::Index g) {
    const exec::Index i0 = g * kN, i1 = std::min(n, i0 + kN);
    Real temperature[kN];
    Mat3 F[kN];
    int lane_of[kN], m = 0;
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
      const bool svd = prm.materials[p.material[i]].project_takes_svd(ti);
      lane_of[i - i0] = svd ? m : -1;
      if (svd) F[m++] = p.F[i];
    }
    Svd3<Real> d[kN];
    if (m > 0) svd3_lanes(F, m, d);
    for (exec::Index i = i0; i < i1; ++i) {
      const MaterialParams& mat = prm.materials[p.material[i]];
      const int l = lane_of[i - i0];
      Real plastic = p.plastic ? p.plastic[i] : Real(0);
      if (l >= 0 ? mat.project(p.F[i], plastic, d[l])
                 : mat.project(p.F[i], plastic, temperature[i - i0])) {
        if (p.plastic) p.plastic[i] = plastic;
        if (p.F_lo) p.F_lo[i].setZero();  // the projected F is new: no low part carries over
      }
    }
  });
}

namespace {
// What collide_particles does to particle i inside collider c (phi < 0).
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
constexpr exec::Index kCollideChunk = 256;
}  // namespace

void collide_particles(const exec::Space& space, const MpmParticleView& p,
                       const Collider* colliders, int n, Real time) {
  // Each particle meets the colliders in their order, as before; the loops are interchanged
  // within a chunk of particles (colliders outer), so a half-space's test is one tight loop with
  // its plane hoisted: phi = (x - c) . n, exactly Collider::phi's expression. Most particles are
  // outside every collider and never reach collide_one.
  const exec::Index chunks = (exec::Index(p.n) + kCollideChunk - 1) / kCollideChunk;
  const MpmParticleView pv = p;
  exec::parallel_for(space, "mpm.collide_particles", chunks, [=](exec::Index k) {
    const exec::Index i0 = k * kCollideChunk, i1 = std::min(exec::Index(pv.n), i0 + kCollideChunk);
    for (int c = 0; c < n; ++c) {
      const Collider& col = colliders[c];
      if (time > col.until) continue;  // released: phi is kReleased everywhere
      if (col.shape == ColliderShape::HalfSpace) {
        const Vec3 o = col.origin + time * col.velocity, nrm = col.normal;
        Real phi[kCollideChunk];  // a branch-free loop the compiler vectorises, then the few inside
        for (exec::Index i = i0; i < i1; ++i) phi[i - i0] = (pv.x[i] - o).dot(nrm);
        for (exec::Index i = i0; i < i1; ++i)
          if (phi[i - i0] < 0) collide_one(pv, col, i, phi[i - i0], time);
        continue;
      }
      for (exec::Index i = i0; i < i1; ++i) {
        const Real phi = col.phi(pv.x[i], time);
        if (phi < 0) collide_one(pv, col, i, phi, time);
      }
    }
  });
}

extern const MaterialKernelTable material_kernels;
const MaterialKernelTable material_kernels = {&update_material_state, &collide_particles};

}  // namespace AMALGAM_ISA
}  // namespace amalgam
