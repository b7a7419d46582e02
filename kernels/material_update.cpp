#include "kernels/material_update.hpp"

#include <algorithm>
#include <cmath>

#include "core/exec/simd.hpp"
#include "core/math/lanes.hpp"
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

extern const MaterialKernelTable material_kernels;
const MaterialKernelTable material_kernels = {&update_material_state, &collide_particles};

}  // namespace AMALGAM_ISA
}  // namespace amalgam
