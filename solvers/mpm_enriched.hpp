// Dynamically enriched MPM (Zhu et al. 2017), a component of MpmSolver (solvers/mpm_solver.hpp):
// particles carry connected hexahedral domains (solvers/particle_domains.hpp) whose shared corners
// keep stretched bodies whole; corners become extra DOFs where the deformation is severe. Its
// substep replaces the explicit MPM transfers (Algorithm 1):
//   stresses_and_enrichment  P at the clamped F, K(F) <= epsilon marks corners     (Secs. 5.1-5.3)
//   particles_to_corners     corner mass, momentum and force
//   corners_to_grid          transfer points, their bins and grid topology, the scatter
//   update_grid_velocities   v* on the grid (explicit colliders), then the enriched corners' own
//   solve                    implicit only: grid + enriched corners as extra DOFs    (eqs. 12-19)
//   grid_to_corners, corners_to_particles   velocities back, F update, advection
//   disable_melted           melted particles leave their domains                    (Sec. 8)
#pragma once

#include <array>
#include <memory>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "solvers/implicit_system.hpp"
#include "solvers/particle_domains.hpp"

namespace amalgam {

class MpmSolver;

class MpmEnriched {
 public:
  explicit MpmEnriched(ParticleSet& particles);
  ~MpmEnriched();

  // Domains for the particles from index `first` on, one object sampled on a lattice of spacing h
  // with jitter 0, optionally with an embedded surface mesh.
  void add_object(MpmSolver& mpm, std::size_t first, Real h,
                  const std::vector<Vec3d>* surface_vertices = nullptr,
                  const std::vector<std::array<std::int32_t, 3>>* surface_triangles = nullptr);
  void step(const exec::Space& space, MpmSolver& mpm, Real dt);
  // The explicit stability limit of the enriched corners (infinity when none).
  Real dt_limit(const exec::Space& space, const MpmSolver& mpm) const;
  // Particles whose domain is disabled (melted) have explicit stresses even in an implicit run.
  bool explicit_stresses() const { return domains_.disabled_count() > 0; }

  DomainParticleView particle_view(MpmSolver& mpm);
  DomainParams params(const MpmSolver& mpm, Real dt) const;
  const ParticleDomains& domains() const { return domains_; }
  ParticleDomains& domains() { return domains_; }
  const DomainAttributes& attributes() const { return dattr_; }

 private:
  void solve_velocities(const exec::Space& space, MpmSolver& mpm, Real dt);
  DomainAttributes dattr_;
  ParticleDomains domains_;
  std::unique_ptr<ImplicitTerm> term_;
};

}  // namespace amalgam
