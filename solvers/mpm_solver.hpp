// MPM solver (course report Sec. 3.2; MLS-MPM as in A-ULMPM Sec. 5.8), explicit or implicit
// (backward Euler, one Newton step: enriched MPM Sec. 6, A-ULMPM eq. 26). One substep is
// these named phases:
//   sort_particles   stable radix sort by grid leaf, bins           (sparse_grid/binning)
//   update_grid      activate leaves, tables, colours                (sparse_grid)
//   particle_to_grid mass, momentum, stress forces                   (kernels p2g)
//   update_grid_velocities  p/m, gravity, forces -> v*; colliders (explicit)  (kernels grid_update)
//   solve_grid_velocities   implicit only: (M + dt^2 H) v = M v* with the colliders as
//                    constraints, then friction and separation       (solvers/implicit_system)
//   couple_objects   A-ULMPM with several objects: contact through a global grid at the
//                    nodes' positions q_i^{n+1} (eq. 27)                (solvers/object_contact)
//   grid_to_particle v, C, F update, advection                       (kernels g2p)
//   collide_particles  push particles that entered a collider back out  (kernels material_update)
//   update_materials heat sources, return mapping / F reset          (kernels material_update)
// With particle domains (dynamically enriched MPM, settings.domains) a substep is instead
//   mark_enrichment, particles_to_corners, corners_to_grid, update_grid_velocities (+ enriched
//   corners), solve_grid_velocities (grid + enriched corners as extra DOFs), grid_to_corners,
//   corners_to_particles                                              (solvers/particle_domains)
// The time step comes from a CFL condition on particle speed plus the elastic wave speed (the
// wave speed only when explicit), and the explicit viscosity limit dx^2 / (6 nu) when a
// material is viscous (viscosity stays explicit in the implicit integrator).
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/materials/material.hpp"
#include "core/particles/particle_set.hpp"
#include "core/geometry/colliders.hpp"
#include "kernels/implicit_mpm.hpp"
#include "kernels/material_update.hpp"
#include "kernels/mpm_transfers.hpp"
#include "solvers/configuration_maps.hpp"
#include "solvers/implicit_system.hpp"
#include "solvers/object_contact.hpp"
#include "solvers/particle_domains.hpp"
#include "sparse_grid/binning.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

struct MpmSettings {
  Real dx = Real(0.01);
  int order = 2;
  Transfer transfer = Transfer::Mls;
  Real flip_alpha = Real(0.95);
  Vec3 gravity = Vec3(0, Real(-9.81), 0);
  Real cfl = Real(0.5);        // dt <= cfl dx / (max |v_p| + c_max)
  Real max_dt = Real(1e-2);    // upper bound on a substep
  Real max_speed = Real(1e4);  // stability guard: a faster particle is a blow-up (m/s)
  bool implicit = false;       // backward Euler velocity update instead of explicit
  ImplicitSettings solver;     // Krylov solver settings when implicit
  // A-ULMPM: every object keeps its own reference configuration (solvers/configuration_maps.hpp)
  // and the transfers run in the kernels' Lagrangian mode. Explicit only.
  bool configuration_maps = false;
  // A-ULMPM: contact between objects through a global grid (solvers/object_contact.hpp).
  ObjectContactSettings contact;
  // Dynamically enriched MPM: particles carry connected hexahedral domains (explicit or implicit).
  DomainSettings domains;
};

// Implicit solves since the counters were last reset (per frame in the runner).
struct ImplicitCounters {
  std::uint64_t solves = 0, iterations = 0, minres = 0, unconverged = 0;
  int max_iterations = 0;
  double max_residual = 0;
};

struct MpmDiagnostics {
  double kinetic = 0, elastic = 0;
  Vec3d momentum = Vec3d::Zero();
  double max_speed = 0;
  double mass = 0;
};

class MpmSolver {
 public:
  MpmSolver(const MpmSettings& settings, std::vector<MaterialParams> materials,
            std::vector<Collider> colliders, std::vector<HeatSource> heat_sources = {});

  ParticleSet& particles() { return particles_; }
  const ParticleSet& particles() const { return particles_; }
  const MpmAttributes& attributes() const { return attr_; }
  const MpmSettings& settings() const { return settings_; }
  const std::vector<MaterialParams>& materials() const { return materials_; }
  const SparseGrid& grid() const { return grid_; }
  const BinTable& bins() const { return bins_; }
  double time() const { return time_; }
  std::uint64_t step_count() const { return steps_; }
  // Sort scratch (keys, permutation, run flags) per particle.
  static constexpr std::size_t binning_bytes_per_particle() {
    return ParticleBinning::kScratchBytesPerParticle;
  }

  // Appends particles at `x` with velocity v0 + omega x (x - centre), material index, and mass
  // and volume per particle; F = I, C = affine part of the rigid rotation, plastic state at
  // rest, and the given temperature (K; stored only if a material melts).
  // With configuration maps, the particles form one object with the given update policy.
  void add_particles(const std::vector<Vec3>& x, const Vec3& v0, const Vec3& omega,
                     const Vec3& centre, int material, Real volume_per_particle,
                     Real temperature = 0, const ConfigurationPolicy& policy = {});
  // Particle domains (settings().domains) for the particles from index `first` on, one object
  // sampled on a lattice of spacing h with jitter 0, optionally with an embedded surface mesh.
  void add_particle_domains(
      std::size_t first, Real h, const std::vector<Vec3d>* surface_vertices = nullptr,
      const std::vector<std::array<std::int32_t, 3>>* surface_triangles = nullptr);
  const ParticleDomains& domains() const { return domains_; }
  ParticleDomains& domains() { return domains_; }
  const DomainAttributes& domain_attributes() const { return dattr_; }
  DomainParticleView domain_particle_view();
  DomainParams domain_params(Real dt) const;
  // A-ULMPM configuration maps (settings().configuration_maps): policies and statistics per object.
  const ConfigurationMaps& configuration_maps() const { return maps_; }
  const ConfigurationAttributes& configuration_attributes() const { return cattr_; }

  // Largest stable substep (CFL). Also the stability guard: throws SimulationError naming the
  // step, particle and quantity if any velocity or F is not finite or a speed exceeds max_speed.
  Real stable_dt(const exec::Space& space) const;
  // One explicit substep of length dt.
  void step(const exec::Space& space, Real dt);
  MpmDiagnostics diagnostics(const exec::Space& space) const;
  // Particle positions in the order the particles were added (by stable id; sorting permutes the
  // storage), for comparisons between runs and against a rest shape.
  std::vector<Vec3d> positions_by_id() const;

  // Phases of step(), public so tests and benchmarks can drive them one by one.
  void sort_particles(const exec::Space& space);
  // A-ULMPM: eq. 33 per object, resets of the objects that need one, and re-binning at X^s
  // when a reference changed (sort_particles + update_grid); nothing else while every object
  // keeps its reference (the weights stay valid: what makes TL/A-UL cheaper than Eulerian).
  void update_configurations(const exec::Space& space);
  void update_grid(const exec::Space& space);
  void particle_to_grid(const exec::Space& space, Real dt);
  void update_grid_velocities(const exec::Space& space, Real dt);
  void solve_grid_velocities(const exec::Space& space, Real dt);
  void couple_objects(const exec::Space& space, Real dt);
  void grid_to_particle(const exec::Space& space, Real dt);
  // Whether couple_objects acts (configuration maps, contact mode not none, two objects or more),
  // and the reference nodes whose velocity it changed since the start of the run.
  bool contact_active() const;
  std::uint64_t contact_nodes() const { return contact_nodes_; }
  double contact_seconds() const { return contact_seconds_; }  // wall time in couple_objects
  std::size_t contact_point_count() const {
    return contact_.point_count();
  }  // points of the last substep
  void update_materials(const exec::Space& space, Real dt);
  // The particle-domain substep (enriched MPM Algorithm 1).
  void step_domains(const exec::Space& space, Real dt);
  // Whether update_materials has anything to do (plastic, fluid or melting material, heat source).
  bool has_material_update() const { return material_update_; }

  const SolveStats& last_solve() const { return last_solve_; }
  const ImplicitCounters& implicit_counters() const { return counters_; }
  void reset_implicit_counters() { counters_ = {}; }
  // The implicit system of the last solve (tests, benchmarks).
  ImplicitSystem& implicit_system() { return implicit_; }
  const ImplicitSystem& implicit_system() const { return implicit_; }
  // Sets up the implicit system for the current grid (mass, v*, constraints, Hessian cache,
  // elastic term) without solving: what solve_grid_velocities does before its solve.
  void assemble_implicit(const exec::Space& space, Real dt);

  // The whole evolving state (particles, and the domain corners' positions), to retry a frame.
  struct Snapshot {
    ParticleSet::Snapshot particles;
    std::vector<Vec3> corners;
  };
  void save(Snapshot& s) const;
  void restore(const Snapshot& s);
  // CFL number used by stable_dt (lowered while retrying a failed frame).
  void set_cfl(Real cfl) { settings_.cfl = cfl; }
  // Restores the clock after particles were loaded from a checkpoint.
  void restore_clock(double time, std::uint64_t steps) {
    time_ = time;
    steps_ = steps;
    bins_valid_ = false;  // particles may have been replaced: re-bin before the next transfer
  }

  MpmParticleView particle_view();
  MpmGridView grid_view();
  // grid_view() plus, in A-ULMPM with colliders, the rasterised node positions q_i of this
  // substep (valid after update_grid_velocities).
  MpmGridView grid_view_with_positions();
  bool fused_positions()
      const;  // q_i come out of the momentum P2G (MLS/APIC) instead of p2g_positions
  bool positions_needed() const;  // q_i are rasterised this substep (colliders or contact)
  MpmStepParams step_params(Real dt) const;

 private:
  MpmSettings settings_;
  std::vector<MaterialParams> materials_;
  std::vector<Collider> colliders_;
  std::vector<HeatSource> heat_sources_;
  // Colliders with keyframed poses evaluated at the end of the current substep (refreshed when
  // the time changes); empty when no collider is keyframed.
  mutable std::vector<Collider> posed_colliders_;
  mutable Real posed_time_ = Real(-1);
  const Collider* colliders_at(Real t) const;
  Real max_wave_speed_ = 0;
  Real max_kinematic_viscosity_ = 0;
  bool hardening_ = false;  // some material's wave speed depends on its plastic state
  bool material_update_ = false;
  ParticleSet particles_;
  MpmAttributes attr_;
  ConfigurationAttributes cattr_;
  ConfigurationMaps maps_;
  std::vector<std::uint8_t> reset_flags_;
  bool bins_valid_ = false;  // Lagrangian mode: bins and topology match X^s
  int positions_set_ =
      -1;  // node4 set of the rasterised node positions (Lagrangian + colliders/contact)
  ObjectContact contact_;
  DomainAttributes dattr_;
  ParticleDomains domains_;
  std::unique_ptr<ImplicitTerm> domain_term_;
  void add_collider_constraints(const exec::Space& space, const MpmGridView& g, Real dt);
  void apply_friction(Real* v) const;
  void solve_and_count(const exec::Space& space, Real dt);
  void solve_domain_velocities(const exec::Space& space, Real dt);
  std::uint64_t contact_nodes_ = 0;
  double contact_seconds_ = 0;
  ParticleBinning binning_;
  BinTable bins_;
  SparseGrid grid_;
  double time_ = 0;
  std::uint64_t steps_ = 0;
  // Implicit integration state (reused between steps).
  ImplicitSystem implicit_;
  std::vector<ParticleHessian> hessians_;
  std::vector<Real> guess_force_;
  std::unique_ptr<ImplicitTerm> elastic_term_;
  struct FrictionContact {
    std::uint64_t dof;
    Vec3 n, vc;
    Real vn_star, mu;
  };
  std::vector<FrictionContact> contacts_;
  std::vector<std::uint8_t> in_collider_;
  SolveStats last_solve_;
  ImplicitCounters counters_;
};

}  // namespace amalgam
