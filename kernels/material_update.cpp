#include "kernels/material_update.hpp"

#include <algorithm>
#include <cmath>

#include "core/exec/simd.hpp"
#include "core/math/lanes.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "core/math/svd3.hpp"
#include "kernels/particle_update.hpp"

namespace amalgam {

// The kernels, once per instruction set (core/exec/simd.hpp): the return mappings' SVDs take
// 4, 8 or 16 particles per vector (baseline, AVX2, AVX-512).
namespace AMALGAM_ISA {

void update_material_state(const exec::Space& space, const MpmParticleView& p,
                           const MaterialUpdateParams& prm) {
  // Groups of kN consecutive particles (update_material_group: their SVDs at once).
  constexpr int kN = lanes::kN<Real>;
  const exec::Index n = exec::Index(p.n), groups = (n + kN - 1) / kN;
  if (!prm.check) {
    exec::parallel_for(space, "mpm.material_update", groups, [&](exec::Index g) {
      const exec::Index i0 = g * kN;
      update_material_group(p, prm, i0, std::min(n, i0 + kN));
    });
    return;
  }
  // The substep's last particle pass: with the stability check of the updated particles.
  *prm.check = exec::parallel_reduce(
      space, "mpm.material_update", groups, StabilityCheck{},
      [&](exec::Index g, StabilityCheck& acc) {
        const exec::Index i0 = g * kN, i1 = std::min(n, i0 + kN);
        update_material_group(p, prm, i0, i1);
        check_particles(acc, i0, i1, p, prm.check_limits);
      },
      merge_checks);
}

void collide_particles(const exec::Space& space, const MpmParticleView& p,
                       const Collider* colliders, int n, Real time) {
  // Chunks of kCollideChunk particles, each with the colliders outer (collide_range).
  const exec::Index chunks = (exec::Index(p.n) + kCollideChunk - 1) / kCollideChunk;
  const MpmParticleView pv = p;
  exec::parallel_for(space, "mpm.collide_particles", chunks, [=](exec::Index k) {
    const exec::Index i0 = k * kCollideChunk, i1 = std::min(exec::Index(pv.n), i0 + kCollideChunk);
    collide_range(pv, colliders, n, i0, i1, time);
  });
}

void energy_densities(const MpmParticleView& p, const MaterialParams* mats, std::size_t q0,
                      std::size_t q1, Real* e) {
  // Groups of kN: each one-material run of a group takes its energies at once
  // (MaterialParams::energy_lanes, bitwise energy() per particle whatever the runs).
  constexpr int kN = lanes::kN<Real>;
  for (std::size_t g0 = q0; g0 < q1; g0 += kN) {
    const std::size_t g1 = std::min(q1, g0 + kN);
    Real* out = e + (g0 - q0);
    if (p.J) {  // the fluid's energy density of J (energy(F) is that of det F)
      for (std::size_t i = g0; i < g1; ++i)
        out[i - g0] = mats[p.material[i]].fluid().energy_of_J(p.J[i]);
      continue;
    }
    if (!p.b && !p.F) {  // no deformation kept (not a state the solver builds): no energy
      std::fill(out, out + (g1 - g0), Real(0));
      continue;
    }
    Real pl[kN] = {}, tp[kN] = {};
    for (std::size_t i = g0; i < g1; ++i) {
      if (p.plastic) pl[i - g0] = p.plastic[i];
      if (p.temperature) tp[i - g0] = p.temperature[i];
    }
    Mat3 Fb[kN];  // b - I: its Cholesky factor stands in for F (isotropic energies)
    if (p.b) b_factor_lanes(p.b + g0, int(g1 - g0), Fb);
    const Mat3* F = p.b ? Fb : p.F + g0;  // particle i's at F + (i - g0)
    for (std::size_t r0 = g0, r1; r0 < g1; r0 = r1) {
      for (r1 = r0 + 1; r1 < g1 && p.material[r1] == p.material[r0];) ++r1;
      mats[p.material[r0]].energy_lanes(F + (r0 - g0), pl + (r0 - g0), tp + (r0 - g0),
                                        out + (r0 - g0), int(r1 - r0));
    }
  }
}

extern const MaterialKernelTable material_kernels;
const MaterialKernelTable material_kernels = {&update_material_state, &collide_particles,
                                              &energy_densities};

}  // namespace AMALGAM_ISA
}  // namespace amalgam
