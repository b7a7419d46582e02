#include "kernels/material_update.hpp"

#include <cmath>

namespace amalgam {

void update_material_state(const exec::Space& space, const MpmParticleView& p, const MaterialUpdateParams& prm) {
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
    if (prm.materials[p.material[i]].project(p.F[i], plastic, temperature) && p.plastic) p.plastic[i] = plastic;
  });
}

}  // namespace amalgam
