// Particle domains of dynamically enriched MPM (enriched-mpm-invertible-elasticity.txt, Secs.
// 4-6): the connected hexahedral domains, their shared corners, and the solver phases of one
// substep (the kernels are in kernels/particle_domains.hpp):
//   stresses_and_enrichment  P at the clamped F; K(F) <= epsilon marks corners;   (Secs. 5.1-5.3)
//                       particle states
//   particles_to_corners  mass, momentum, force on every corner
//   corners_to_grid     unenriched corners -> transfer points -> binned -> linear scatter
//   (grid update / implicit solve by MpmSolver; enriched corners are extra DOFs) (Sec. 6)
//   grid_to_corners     unenriched corners read the grid; corner collisions     (Sec. 7)
//   corners_to_particles  v (PIC/FLIP), F (eq. 7), positions (eq. 9)
//
// Domains are built from particles on a lattice (jitter 0): a particle at x with lattice spacing
// h owns the box x +- h/2; corners of neighbouring particles of the same object coincide and are
// stored once. Particle order never changes in this method (the corner lists index particles).
// State that a checkpoint must keep: the corner positions (corner_positions()); the adjacency
// is rebuilt from the scene.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "kernels/particle_domains.hpp"
#include "sparse_grid/binning.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

struct DomainSettings {
  bool enabled = false;
  bool enrichment = true;    // dynamic enrichment (Sec. 5); off: domains only
  Real epsilon = Real(0.6);  // enrichment threshold on K(F) (eq. 10)
  Real clamp = Real(0.15);   // smallest principal stretch seen by the stress (Sec. 5.3)
  // Elastic forces are off before this time (s): the body collapses under gravity into a flat
  // configuration and recovers once its strength returns (enriched MPM Fig. 5).
  Real elasticity_from = 0;
  // Transitional and enriched particles integrate their force over 8 Gauss points (the authors'
  // code) instead of eq. 8's single point, which leaves hourglass modes of the enriched corner
  // mesh unresisted (measured in docs/enriched_mpm.md).
  bool gauss_quadrature = true;
};

// Per-particle attributes of the method.
struct DomainAttributes {
  ParticleSet::Id corners = -1, h = -1, state = -1;
  static DomainAttributes add_to(ParticleSet& ps);
};

// Enrichment statistics since the counters were reset (per frame in the runner).
struct DomainCounters {
  std::uint64_t steps = 0;
  double enriched_fraction_sum = 0;  // particles with all corners enriched / particles
  double transitional_fraction_sum = 0;
  double max_enriched_fraction = 0;
  std::size_t last_enriched_corners = 0;
};

class ParticleDomains {
 public:
  ParticleDomains();

  // Domains for particles [first, ps.size()) of one object, sampled on a lattice of spacing h
  // (positions x_p = lo + (i + 1/2) h). Throws InputError if a particle is off the lattice.
  // A surface mesh given with the object (its rest pose) is embedded in the domains (Sec. 4.1):
  // each vertex keeps the domain that contains it (or the nearest within two spacings) and its
  // trilinear coordinates there.
  void add_object(ParticleSet& ps, const DomainAttributes& da, ParticleSet::Id x_id,
                  std::size_t first, Real h, const std::vector<Vec3d>* surface_vertices = nullptr,
                  const std::vector<std::array<std::int32_t, 3>>* surface_triangles = nullptr);
  // The embedded surfaces, deformed with their domains' corners (one mesh for all objects).
  bool has_surface() const { return !surf_tris_.empty(); }
  void surface(const std::int32_t* particle_corners, std::vector<Vec3>& vertices,
               std::vector<std::array<std::uint32_t, 3>>& triangles) const;
  // The velocity of each embedded vertex: that of the particle whose domain holds it.
  void surface_velocity(const Vec3* particle_v, std::vector<Vec3>& velocity) const;

  std::size_t corner_count() const { return corners_.size(); }
  std::size_t point_count() const { return points_.size(); }
  std::size_t enriched_dof_count() const { return enriched_dofs_; }
  const BinTable& bins() const { return bins_; }
  Vec3* corner_positions() { return corners_.vec3(cx_); }
  const Vec3* corner_positions() const { return corners_.vec3(cx_); }
  // Corner masses of the last substep (0: no enabled particle).
  const Real* corner_masses() const { return corners_.real(cm_); }
  const DomainCounters& counters() const { return counters_; }
  void reset_counters() { counters_ = {}; }
  const EnrichmentCounts& last_counts() const { return last_counts_; }

  DomainCornerView corner_view();
  DomainPointView point_view();

  // Phases (see the header comment).
  // Stresses at the clamped F (and the Hessian cache when `hessians`), the enrichment criterion,
  // corner flags and particle states; the enrichment counters.
  // gauss_quadrature: transitional and enriched particles by 8 Gauss points (DomainSettings).
  void stresses_and_enrichment(const exec::Space& space, const DomainParticleView& p,
                               const DomainParams& prm, bool hessians, bool psd,
                               bool gauss_quadrature = true);
  // Corner mass, momentum and force.
  void particles_to_corners(const exec::Space& space, const DomainParticleView& p);
  // Explicit stability of the enriched corners (FE nodes of the domain mesh), from the last
  // substep's states and clamped stretches: min over transitional/enriched particles of
  // cfl s_min^2 h / c (infinity if none).
  Real enriched_dt_limit(const exec::Space& space, const std::int32_t* state, const Vec3* h,
                         Real cfl, Real wave_speed) const;
  // Transfer points, their bins, the grid topology, and the scatter into the grid's node4 sets
  // 0 = (m, p) and 1 = (-, f) (views of the grid are valid from here: make_grid_view with bins()).
  // Disabled particles join the points (plain MPM, their stress from prm.materials).
  void corners_to_grid(const exec::Space& space, const DomainParticleView& p,
                       const DomainParams& prm, SparseGrid& grid, Real dx);
  // Compact DOF indices of the enriched corners with mass (after particles_to_corners).
  std::size_t number_enriched_dofs(const exec::Space& space);
  const std::int32_t* enriched_dof() const { return dof_.data(); }
  // Explicit velocity of the enriched corners (their own DOFs; eq. 13 on a corner).
  void update_enriched_corners(const exec::Space& space, const DomainParams& prm);
  // Implicit: mass and v* of the enriched DOFs into the stacked vectors (1 and 4 lanes per DOF),
  // and their solved velocity back (dv = v - v^n).
  void enriched_to_dofs(const exec::Space& space, Real* mass, Real* v);
  void dofs_to_enriched(const exec::Space& space, const Real* v);
  void grid_to_corners(const exec::Space& space, const MpmGridView& g, const DomainParticleView& p,
                       const DomainParams& prm);
  // Disables the domains of melted particles (Sec. 8, Fig. 11); returns how many are disabled.
  std::size_t disable_melted(const exec::Space& space, const DomainParticleView& p,
                             const MaterialParams* materials);
  std::size_t disabled_count() const { return disabled_; }
  void corners_to_particles(const exec::Space& space, const DomainParticleView& p,
                            const DomainParams& prm);

  // Implicit solve pieces (valid after particles_to_corners with hessians, corners_to_grid and
  // number_enriched_dofs); they use scratch buffers, hence non-const.
  const DomainHessian* hessians() const { return hess_.data(); }
  void hessian_action(const exec::Space& space, const DomainParticleView& p, const MpmGridView& g,
                      Real dx, const Real* du_grid, const Real* du_corner, Real scale,
                      Real* out_grid, Real* out_corner);
  void hessian_diagonal(const exec::Space& space, const DomainParticleView& p, const MpmGridView& g,
                        Real dx, Real scale, Real* diag_grid, Real* diag_corner);

 private:
  ParticleSet corners_;
  ParticleSet::Id cx_, cm_, cp_, cf_, cv_, cdv_, cenr_;
  ParticleSet points_;
  ParticleSet::Id px_, pm_, pp_, pf_, pcorner_, pstress_;
  std::size_t disabled_ = 0;  // particles whose domain is disabled (melted)
  std::vector<std::uint32_t> particle_start_;
  std::vector<std::uint32_t> adj_start_, adj_;
  std::vector<std::uint32_t> point_start_;
  std::vector<std::int32_t> dof_;
  std::vector<std::uint32_t> dof_scan_;  // scratch of number_enriched_dofs
  std::size_t enriched_dofs_ = 0;
  std::vector<Mat3> piola_;
  std::vector<Real> smin_;  // smallest clamped principal stretch per particle
  // Eight-point quadrature of the transitional and enriched particles: per particle its entry or
  // -1, the list, and 8 stresses / Hessians / action scratch per entry.
  std::vector<std::int32_t> quad_index_;
  std::vector<std::uint32_t> quad_list_, quad_scan_;
  std::vector<Mat3> quad_piola_, quad_scratch_;
  std::vector<DomainHessian> quad_hess_;
  bool quad_hessians_ = false;
  DomainQuadrature quadrature_view();
  std::vector<DomainHessian> hess_;
  std::vector<Vec3> du_c_, df_c_;  // Hessian action scratch
  std::vector<Mat3> dP_;
  std::vector<std::int32_t> surf_particle_;  // embedded vertices: domain and trilinear coordinates
  std::vector<Vec3> surf_xi_;
  std::vector<std::array<std::uint32_t, 3>> surf_tris_;
  ParticleBinning binning_;
  BinTable bins_;
  DomainCounters counters_;
  EnrichmentCounts last_counts_;
};

}  // namespace amalgam
