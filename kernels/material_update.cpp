#include "kernels/material_update.hpp"

#include <cmath>

namespace amalgam {

void update_material_state(const exec::Space& space, const MpmParticleView& p,
                           const MaterialUpdateParams& prm) {
  exec::parallel_for(space, "mpm.material_update", exec::Index(p.n), [&](exec::Index i) {
    Real temperature = p.temperature ? p.temperature[i] : Real(0);
    if (p.temperature && prm.nsources > 0) {
      for (int s = 0; s < prm.nsources; ++s) {
        const HeatSource& h = prm.sources[s];
        if (h.region.phi(p.x[i], prm.time) <= 0)
          temperature = h.temperature + (temperature - h.temperature) * std::exp(-h.rate * prm.dt);
      }
      p.temperature[i] = temperature;
    }
    Real plastic = p.plastic ? p.plastic[i] : Real(0);
    if (prm.materials[p.material[i]].project(p.F[i], plastic, temperature)) {
      if (p.plastic) p.plastic[i] = plastic;
      if (p.F_lo) p.F_lo[i].setZero();  // the projected F is new: no low part carries over
    }
  });
}

void collide_particles(const exec::Space& space, const MpmParticleView& p,
                       const Collider* colliders, int n, Real time) {
  exec::parallel_for(space, "mpm.collide_particles", exec::Index(p.n), [&](exec::Index i) {
    for (int c = 0; c < n; ++c) {
      const Real phi = colliders[c].phi(p.x[i], time);
      if (phi >= 0) continue;
      if (colliders[c].boundary == BoundaryType::Sticky) {  // a grip holds what it holds
        p.v[i] = colliders[c].velocity_at(p.x[i], time);
        continue;
      }
      const Vec3 nrm = colliders[c].outward_normal(p.x[i], time);
      if (p.x_lo)
        add_compensated(p.x[i], p.x_lo[i], Vec3(-phi * nrm));
      else
        p.x[i] -= phi * nrm;
      colliders[c].project(p.x[i], time, p.v[i]);
    }
  });
}

}  // namespace amalgam
