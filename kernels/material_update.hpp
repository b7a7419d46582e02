// Per-particle material state update after G2P: heat sources raise (or lower) particle
// temperatures, then each particle's material projects its trial F (plastic return mapping,
// fluid F reset, phase change). One parallel_for over particles, no grid access.
//
// Heat sources are regions (a half-space, box or sphere; static or moving like a collider) at a
// temperature T_s with a rate r (1/s): a particle inside relaxes as dT/dt = r (T_s - T),
// integrated exactly over the substep, T <- T_s + (T - T_s) exp(-r dt) (unconditionally
// stable). This is the "heated container bottom" of the enriched-MPM melting bunny (Fig. 11);
// heat conduction between particles is not modelled.
#pragma once

#include "core/exec/exec.hpp"
#include "core/materials/material.hpp"
#include "kernels/colliders.hpp"
#include "kernels/mpm_transfers.hpp"

namespace amalgam {

struct HeatSource {
  Collider region;  // shape and motion; a particle with region.phi(x, t) <= 0 is heated
  Real temperature = 0;
  Real rate = 0;
};

struct MaterialUpdateParams {
  const MaterialParams* materials = nullptr;
  const HeatSource* sources = nullptr;
  int nsources = 0;
  Real dt = 0;
  Real time = 0;  // time at the end of the substep
};

void update_material_state(const exec::Space& space, const MpmParticleView& p, const MaterialUpdateParams& prm);

}  // namespace amalgam
