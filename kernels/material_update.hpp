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
#include "core/geometry/colliders.hpp"
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
  // When set, *check = the stability check of every particle after the update (the material
  // update is then the substep's last particle pass), with check_limits.
  StabilityCheck* check = nullptr;
  StabilityLimits check_limits;
};

void update_material_state(const exec::Space& space, const MpmParticleView& p,
                           const MaterialUpdateParams& prm);

// Particle-level collision after advection: grid-based colliders stop a particle only once all
// its stencil nodes are inside, so particles sink up to 1.5 cells into walls (measured: the
// hydrostatic column widened by 12 % and lost 20 % of its height). A particle found inside a
// slip or separating collider at the end of the substep is moved back to its surface along the
// collider normal and its velocity projected like a grid node's (with friction). A sticky
// collider holds the particles inside it where they are, moving with it (a grip pulling a bar's
// end would otherwise push that end out through its nearest face every substep).
void collide_particles(const exec::Space& space, const MpmParticleView& p,
                       const Collider* colliders, int n, Real time);

// The elastic energy density psi(F) of particles [q0, q1) of p (q1 - q0 <= kEnergyBatch), into
// e[0 .. q1 - q0): of J where the particles keep J alone, else of F or of b's Cholesky factor
// (every material isotropic), with the plastic and temperature fields where present. Bitwise
// MaterialParams::energy per particle on every vector width (the diagnostics' energies:
// solvers/mpm_solver.cpp, mpm_diagnostics).
constexpr int kEnergyBatch = 64;
void energy_densities(const MpmParticleView& p, const MaterialParams* mats, std::size_t q0,
                      std::size_t q1, Real* e);

// The kernels above for one instruction set (core/exec/simd.hpp; kernels/simd_dispatch.cpp
// calls the table of exec::simd_path()).
struct MaterialKernelTable {
  void (*update_material_state)(const exec::Space&, const MpmParticleView&,
                                const MaterialUpdateParams&);
  void (*collide_particles)(const exec::Space&, const MpmParticleView&, const Collider*, int, Real);
  void (*energy_densities)(const MpmParticleView&, const MaterialParams*, std::size_t, std::size_t,
                           Real*);
};

}  // namespace amalgam
