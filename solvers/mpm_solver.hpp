// MPM solver (course report Sec. 3.2; MLS-MPM as in A-ULMPM Sec. 5.8): the explicit core, which
// the other MPM variants compose with. One substep, MpmSolver::step():
//   sort_particles   radix sort by grid leaf, then id in a bin; bins (sparse_grid/binning)
//   update_grid      activate leaves, tables, colours                (sparse_grid)
//   particle_to_grid mass, momentum, stress forces                   (kernels p2g)
//   update_grid_velocities  p/m, gravity, forces -> v*; colliders    (kernels grid_update)
//   grid_to_particle v, C, F update, advection                       (kernels g2p)
//   collide_particles  push particles that entered a collider back out  (kernels material_update)
//   update_materials heat sources, return mapping / F reset          (kernels material_update)
// The variants are components with their own files, present only when the scene uses them:
//   MpmImplicit (solvers/mpm_implicit.hpp)  backward Euler: solve_grid_velocities after the grid
//                update (enriched MPM Sec. 6, A-ULMPM eq. 26)
//   MpmAul      (solvers/mpm_aul.hpp)       A-ULMPM: update_configurations instead of sorting
//                (eq. 33), couple_objects after the grid update (eq. 27), F = F_s F_0s (eq. 32)
//   MpmEnriched (solvers/mpm_enriched.hpp)  dynamically enriched MPM: particle domains replace the
//                transfers with their own substep (Algorithm 1)
// The time step comes from a CFL condition on particle speed plus the elastic wave speed (the
// wave speed only when explicit), and the explicit viscosity limit dx^2 / (6 nu) when a
// material is viscous (viscosity stays explicit in the implicit integrator).
#pragma once

#include <algorithm>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/colliders.hpp"
#include "core/materials/material.hpp"
#include "core/particles/particle_set.hpp"
#include "kernels/material_update.hpp"
#include "kernels/mpm_transfers.hpp"
#include "solvers/configuration_maps.hpp"
#include "solvers/implicit_system.hpp"
#include "solvers/mpm_sleep.hpp"
#include "solvers/mpm_sources.hpp"
#include "solvers/object_contact.hpp"
#include "solvers/particle_domains.hpp"
#include "sparse_grid/binning.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

class MpmImplicit;
class MpmAul;
class MpmEnriched;

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
  // Kill regions (solvers/mpm_sources.hpp): particles leaving the box or entering a volume are
  // removed at the end of every substep. Plain MPM (explicit or implicit) only.
  KillSettings kill;
  // Sleeping blocks (solvers/mpm_sleep.hpp). Explicit MLS/APIC only.
  SleepSettings sleep;
  // simulation.transfer_pass "fused": one pass over the particles per substep (G2P2G,
  // solvers/mpm_fused.cpp) where the variant allows it (fused_eligible), else the two passes.
  bool fused = false;
  // simulation.sort "when_needed": the two passes keep the bins of the last sort while every
  // particle's stencil fits its bin's dilated block, and re-sort only when one leaves it
  // (MpmSolver::step_sorted_when_needed, solvers/mpm_fused.cpp) where the variant allows it
  // (sorts_when_needed; on one process or several, solvers/mpm_lazy_distributed.cpp): the
  // default; "every_substep": sort every substep.
  bool sort_when_needed = true;
  // The particles keep F itself (the output asks for it: io/scene.cpp), not only b = F F^T
  // (MpmSolver::keeps_b).
  bool keep_F = false;
};

// Whether a run of these settings takes the fused substep (MpmSolver::step_fused): `fused` asked
// for, and a variant that fuses (explicit, Eulerian, no particle domains nor sleeping, one
// process). Grid-volume output clears `fused` when the scene is read (io/scene.cpp).
bool fuses(const MpmSettings& s, bool distributed);
// Whether a run of these settings takes the two passes re-sorted only when needed: asked for, not
// fused, and a variant that fuses (the same conditions: explicit, Eulerian, no particle domains
// nor sleeping, one process).
bool sorts_when_needed(const MpmSettings& s);

struct MpmDiagnostics {
  double kinetic = 0, elastic = 0;
  Vec3d momentum = Vec3d::Zero();
  double max_speed = 0;
  double mass = 0;
};

// Energies, momentum and speeds of MPM particles: exact sums rounded once (ExactSum), so neither
// the particles' order nor their split over chunks and ranks changes a bit. `over_ranks`: these
// are one rank's particles and the result is every rank's (collective).
MpmDiagnostics mpm_diagnostics(const exec::Space& space, const ParticleSet& particles,
                               const MpmAttributes& attr,
                               const std::vector<MaterialParams>& materials,
                               bool over_ranks = false);

// The channel sets of the grid's node rows ([leaf][512][4] per set) for a run, decided at set-up
// (and again when the run is distributed): set 0 holds (m, p) -> (m, v); PIC/FLIP, particle
// domains and the fused substep's split grid (only when the fused path runs: fuses()) use set 1
// for (-, f) -> (-, dv) or the dt-free force; A-ULMPM with colliders or contact between objects
// rasterises the nodes' current positions q_i into one more set.
struct GridChannels {
  int count = 1;
  int second = -1;     // PIC/FLIP, particle-domain and split layout (kernels grid_update)
  int positions = -1;  // A-ULMPM node positions
  static GridChannels for_run(const MpmSettings& s, bool has_colliders, bool distributed = false);
};

// Which ids add_particles gives: a distributed set-up samples each object in slices, one per
// rank (solvers/factory.cpp): the particles' ids start at next_id() + offset and the object has
// `total` particles over every rank, by which next_id() advances (the defaults: all of the object).
struct IdSlice {
  std::int64_t offset = 0, total = -1;
};

class MpmSolver {
 public:
  MpmSolver(const MpmSettings& settings, std::vector<MaterialParams> materials,
            std::vector<Collider> colliders, std::vector<HeatSource> heat_sources = {});
  ~MpmSolver();
  MpmSolver(MpmSolver&&) noexcept;
  MpmSolver& operator=(MpmSolver&&) noexcept;

  // Writable particles: stable_dt then checks them again in a pass of its own (folded_check).
  ParticleSet& particles() {
    folded_at_ = kNotFolded;
    return particles_;
  }
  const ParticleSet& particles() const { return particles_; }
  const MpmAttributes& attributes() const { return attr_; }
  // Whether particles of these settings and materials carry the affine matrix C
  // (MpmAttributes::C): APIC and MLS transfer it, and a viscous stress reads it as the velocity
  // gradient (MaterialParams::reads_velocity_gradient), which G2P stores there for PIC/FLIP and
  // particle domains too. PIC/FLIP (and particle domains, which transfer by PIC/FLIP) without a
  // viscous material neither read nor write it.
  static bool keeps_affine(const MpmSettings& s, const std::vector<MaterialParams>& materials);
  // Whether particles of these materials carry F's low part F_lo (core/math/types.hpp:
  // add_compensated). Not when every material is a fluid: the material update resets every fluid
  // particle's F to J^{1/3} I and zeroes its low part each substep (WeaklyCompressibleT::reset;
  // kernels/particle_update.hpp), J read from F alone, so the low part is zero whenever G2P adds
  // to F and nothing reads it: without it F takes the same values, bit for bit.
  static bool keeps_F_low_part(const std::vector<MaterialParams>& materials);
  // Whether particles of these settings and materials keep J = det F instead of F: every material
  // a fluid (not melting), explicit, Eulerian, no particle domains. A fluid's stress reads J
  // alone, so F = J^{1/3} I was all it kept (the F reset); G2P updates J <- det(I + dt grad v) J
  // (kernels/mpm_transfers.cpp, g2p_particle) and no material update pass runs: 32 B less per
  // particle than F in float. The output's F of such a particle is J^{1/3} I.
  static bool keeps_J_only(const MpmSettings& s, const std::vector<MaterialParams>& materials);
  // Whether particles of these settings and materials keep b - I of the left Cauchy-Green tensor
  // b = F F^T instead of F and F_lo (MpmAttributes::b; core/math/left_cauchy_green.hpp): explicit,
  // Eulerian, no particle domains, F not kept for the output (MpmSettings::keep_F) and not J alone.
  // Every material is isotropic, so its stress, energy and return mapping read F only through b;
  // b - I keeps a small strain's digits under any rotation, as F + F_lo did: 48 B less per
  // particle in float.
  static bool keeps_b(const MpmSettings& s, const std::vector<MaterialParams>& materials);
  // Gives every particle the attribute `rest` (MpmAttributes::rest), its current position, and
  // every particle added later (emitters) its position at emission. Idempotent.
  void keep_rest_positions();
  const MpmSettings& settings() const { return settings_; }
  const std::vector<MaterialParams>& materials() const { return materials_; }
  // Particle p's mass (not stored: its material's density x its volume0).
  Real particle_mass(std::size_t p) const {
    return materials_[std::size_t(particles_.int32(attr_.material)[p])].mass(
        particles_.real(attr_.volume0)[p]);
  }
  const SparseGrid& grid() const { return grid_; }
  const BinTable& bins() const { return bins_; }
  const GridChannels& channels() const { return channels_; }
  double time() const { return time_; }
  std::uint64_t step_count() const { return steps_; }
  // Sort scratch (keys, permutation, run flags) per particle.
  static constexpr std::size_t binning_bytes_per_particle() {
    return ParticleBinning::kScratchBytesPerParticle;
  }
  // P2G's kept bin blocks (scratch held between substeps; 0 when P2G runs its colour phases).
  std::size_t p2g_block_bytes() const { return p2g_blocks_.size() * sizeof(Real); }

  // The variants' components, null when the scene does not use them.
  MpmImplicit* implicit() { return implicit_.get(); }
  const MpmImplicit* implicit() const { return implicit_.get(); }
  MpmAul* aul() { return aul_.get(); }
  const MpmAul* aul() const { return aul_.get(); }
  const MpmSleep* sleep() const { return sleep_.get(); }
  MpmEnriched* enriched() { return enriched_.get(); }
  const MpmEnriched* enriched() const { return enriched_.get(); }

  // Appends particles at `x` with velocity v0 + omega x (x - centre), material index, and mass
  // and volume per particle; F = I, C = affine part of the rigid rotation, plastic state at
  // rest, and the given temperature (K; stored only if a material melts).
  // With configuration maps, the particles form one object with the given update policy.
  // `ids`: which of the object's ids (IdSlice, above).
  void add_particles(const std::vector<Vec3>& x, const Vec3& v0, const Vec3& omega,
                     const Vec3& centre, int material, Real volume_per_particle,
                     Real temperature = 0, const ConfigurationPolicy& policy = {},
                     const IdSlice& ids = {});
  // The particles are this rank's slice of a distributed set-up (`distribute` sends each to its
  // owner): of a fresh one (ids ascending in the single process's order), or of a per-rank
  // checkpoint, whose two order keys per particle set_slice_keys gives. Cleared when a checkpoint
  // read whole replaces them.
  void set_sliced(bool sliced) { sliced_ = sliced; }
  bool sliced() const { return sliced_; }
  void set_slice_keys(std::vector<std::uint64_t> keys) { slice_keys_ = std::move(keys); }

  // Emitters (solvers/mpm_sources.hpp), run at the end of every substep. Plain MPM (explicit or
  // implicit) only: throws InputError naming the emitter with A-ULMPM or particle domains.
  void set_emitters(std::vector<EmitterSpec> emitters);
  const std::vector<EmitterSpec>& emitters() const { return emitters_; }
  // The id the next added particle gets (ids are never reused), and the particles emitted and
  // killed so far.
  std::int64_t next_id() const { return next_id_; }
  const SourceCounters& source_counters() const { return sources_; }
  // Restores both after particles were loaded from a checkpoint.
  void restore_sources(std::int64_t next_id, const SourceCounters& c);
  // Emission and kill regions for the substep (t0, t1], as step() runs them after the transfers.
  void emit_and_kill(const exec::Space& space, double t0, double t1);

  // Largest stable substep (CFL). Also the stability guard: throws SimulationError naming the
  // step, particle and quantity if any velocity or F is not finite or a speed exceeds max_speed.
  // Its per-particle part (kernels/stability_check.hpp) comes from the last substep's last
  // particle pass when that pass computed it (folds_check) and the particles have not changed
  // since; otherwise (the first substep, after a restore, emission or kill, a write through
  // particles(), and the variants that do not fold it) from a pass of its own: the same values.
  Real stable_dt(const exec::Space& space) const;
  // Whether the substeps fold the stability check into their last particle pass (G2P with the
  // particle collisions, G2P2G or the material update): one process, no A-ULMPM, particle
  // domains nor sleeping (whose later passes change v or F).
  bool folds_check() const;
  // Whether stable_dt would now take the folded check (tests).
  bool has_folded_check() const { return folded_at_ == state_version_; }
  // One substep of length dt.
  void step(const exec::Space& space, Real dt);
  MpmDiagnostics diagnostics(const exec::Space& space) const;  // every rank's (collective)
  // Particle positions in the order the particles were added (by stable id; sorting permutes the
  // storage), for comparisons between runs and against a rest shape: next_id() entries, NaN for
  // the ids of killed particles.
  std::vector<Vec3d> positions_by_id() const;

  // Phases of step(), public so tests, benchmarks and the components can drive them one by one.
  void sort_particles(const exec::Space& space);
  void update_grid(const exec::Space& space);
  void particle_to_grid(const exec::Space& space, Real dt);
  void update_grid_velocities(const exec::Space& space, Real dt);
  void grid_to_particle(const exec::Space& space, Real dt);
  void collide_particles(const exec::Space& space, Real dt);
  void update_materials(const exec::Space& space, Real dt);
  // Whether update_materials has anything to do (plastic, fluid or melting material, heat source).
  bool has_material_update() const { return material_update_; }
  // The fused substep (G2P2G, solvers/mpm_fused.cpp): settings().fused and a variant that fuses
  // (explicit, Eulerian, one process, no sleeping); the grid then carries the next substep's
  // split scatter from one substep to the next ("primed"), until unprime(): a frame's start, a
  // restore, a changed particle set. The two passes re-sorted only when needed keep their bins
  // and topology while primed, with the same resets.
  bool fused_eligible() const;
  bool primed() const { return primed_; }
  void unprime() { primed_ = false; }
  // Fused substeps that re-sorted the particles (one left its bin's dilated block: the split P2G
  // of the re-sorted particles instead of the flush) and that ran two passes (the dilated blocks
  // over their memory budget).
  std::uint64_t fused_fallbacks() const { return fused_fallbacks_; }
  std::uint64_t fused_unfused() const { return fused_unfused_; }
  // The two passes re-sorted only when needed (settings().sort_when_needed, sorts_when_needed):
  // the bins and the grid's topology are kept while primed() (the same resets as the fused
  // grid's). Substeps that re-sorted because a particle had left its bin's dilated block (after
  // G2P, or found in P2G), and substeps that ran the sort-every-substep passes (the dilated
  // blocks over their memory budget).
  bool sort_when_needed_eligible() const;
  std::uint64_t lazy_resorts() const { return lazy_resorts_; }
  // The bytes of P2G blocks a run of `particles` keeps at most (solvers/estimate.cpp counts
  // them): the two passes' (8 + order)^3-node blocks, and the dilated blocks of the fused pass
  // and of re-sorting only when needed. Over them the solver runs without the blocks.
  static std::size_t p2g_blocks_budget(std::size_t particles) {
    return std::max(std::size_t(16) << 20, std::size_t(64) * particles);
  }
  static std::size_t dilated_blocks_budget(std::size_t particles) {
    return std::max(std::size_t(64) << 20, std::size_t(192) * particles);
  }
  std::uint64_t lazy_unfit() const { return lazy_unfit_; }

  // The whole evolving state (particles, and the domain corners' positions), to retry a frame.
  struct Snapshot {
    ParticleSet::Snapshot particles;
    std::vector<Vec3> corners;
    std::int64_t next_id = 0;
    SourceCounters sources;
    // Distributed: the bins of the particles' order (gather_particles).
    BinTable bins;
    bool sorted = false;
    std::vector<std::uint64_t> presort;
  };
  void save(Snapshot& s) const;
  void restore(const Snapshot& s);
  // CFL number used by stable_dt (lowered while retrying a failed frame).
  void set_cfl(Real cfl) { settings_.cfl = cfl; }
  // Restores the clock after particles were loaded from a checkpoint.
  void restore_clock(double time, std::uint64_t steps);

  // --- Distributed runs (solvers/mpm_distributed.cpp, issue 28). Collective: keeps on this rank
  // only the particles of the leaves it owns (Zoltan RCB of the leaves weighted by particles);
  // throws InputError naming a feature that does not run distributed yet. One rank: nothing.
  void distribute(const exec::Space& space);
  bool distributed() const { return ranks_ != nullptr; }
  // Collective: every rank's particles on rank 0 in the single process's order (`out` holds
  // them there, no particle elsewhere): for frames, diagnostics and checkpoints.
  void gather_particles(ParticleSet& out) const;
  // Collective: the node rows (m, v) of every rank's owned active leaves into `out` on rank 0 (a
  // fresh grid: those leaves active, nothing elsewhere), for grid volumes.
  void gather_grid(SparseGrid& out) const;
  // Two keys per local particle whose lexicographic order over every rank is the order
  // gather_particles gives (one process: the index).
  std::vector<std::uint64_t> order_keys() const;
  // Changes whenever the particles may have changed (a substep, a restore, distribute).
  std::uint64_t state_version() const { return state_version_; }
  // Collective: ranks, repartitions, imbalance and halo of the last substep, for the run summary.
  std::string distributed_summary() const;
  std::size_t owned_active_leaves() const;  // distributed: the active leaves this rank owns

  MpmParticleView particle_view();
  MpmGridView grid_view();
  // grid_view() plus, in A-ULMPM with colliders, the rasterised node positions q_i of this
  // substep (valid after update_grid_velocities).
  MpmGridView grid_view_with_positions();
  bool fused_positions()
      const;  // q_i come out of the momentum P2G (MLS/APIC) instead of p2g_positions
  bool positions_needed() const;  // q_i are rasterised this substep (colliders or contact)
  MpmStepParams step_params(Real dt) const;
  // Colliders with keyframed poses evaluated at time t (the kernels see rigid poses only).
  const Collider* colliders_at(Real t) const;
  int collider_count() const { return int(colliders_.size()); }
  const std::vector<Collider>& colliders() const { return colliders_; }

 private:
  friend class MpmAul;
  friend class MpmEnriched;
  struct Ranks;  // solvers/mpm_distributed.cpp
  std::shared_ptr<Ranks> ranks_;
  std::uint64_t state_version_ = 0;
  Vec3i particle_leaf(const Vec3& x) const;  // the leaf of the particle's bin
  ParticleSet::Id bin_position() const;      // where particles are binned: x, A-ULMPM's X^s
  // Distributed A-ULMPM contact: the active leaves this rank owns, the owner of any leaf, and
  // the owners' node rows (m, v; PIC/FLIP's dv) copied into the ghosts again.
  const std::vector<std::int32_t>& owned_leaf_list() const;
  int leaf_owner(const Vec3i& leaf) const;
  // The ranks this rank exchanges with every substep (RcbCuts::neighbours of its cut box).
  const std::vector<int>& exchange_peers() const;
  void exchange_ghost_rows(const exec::Space& space);  // start_ghost_rows, finish_ghost_rows
  // Field colliders built around every rank's particles (collective), as on one process.
  void prepare_colliders_distributed(const exec::Space& space, Real t);
  void refuse_distributed() const;
  // anywhere: after a repartition particles may go to any rank; otherwise only to the peers.
  void migrate(const exec::Space& space, bool anywhere);
  void repartition();
  void sort_distributed(const exec::Space& space);
  void update_grid_distributed(const exec::Space& space);
  void particle_to_grid_distributed(const exec::Space& space, Real dt);
  void update_grid_velocities_distributed(const exec::Space& space, Real dt);
  void grid_to_particle_distributed(const exec::Space& space, Real dt);
  void g2p_bins(const exec::Space& space, const std::vector<std::uint32_t>& bins, Real dt);
  void update_owned_leaves_rows_first(const exec::Space& space, MpmGridView g,
                                      const MpmStepParams& prm);
  void start_ghost_rows(const exec::Space& space);
  void finish_ghost_rows(const exec::Space& space);
  void keep_owned_emitted(const exec::Space& space, std::size_t first);
  void compact_bins(const std::vector<std::uint32_t>& kept);
  void save_distributed(Snapshot& s) const;
  void restore_distributed(const Snapshot& s);
  MpmSettings settings_;
  std::vector<MaterialParams> materials_;
  std::vector<Collider> colliders_;
  std::vector<HeatSource> heat_sources_;
  // Colliders with keyframed poses evaluated at the end of the current substep (refreshed when
  // the time changes); empty when no collider is keyframed.
  mutable std::vector<Collider> posed_colliders_;
  mutable Real posed_time_ = Real(-1);
  Real max_wave_speed_ = 0;
  Real max_kinematic_viscosity_ = 0;
  bool hardening_ = false;  // some material's wave speed depends on its plastic state
  bool material_update_ = false;
  ParticleSet particles_;
  MpmAttributes attr_;
  GridChannels channels_;
  ParticleBinning binning_;
  BinTable bins_;
  SparseGrid grid_;
  double time_ = 0;
  std::uint64_t steps_ = 0;
  std::vector<EmitterSpec> emitters_;
  std::int64_t next_id_ = 0;
  bool sliced_ = false;                    // set_sliced
  std::vector<std::uint64_t> slice_keys_;  // set_slice_keys
  SourceCounters sources_;
  std::vector<Vec3> emitted_x_;      // emission scratch
  std::vector<std::uint8_t> keep_;   // kill scratch: survivor flags
  std::vector<std::uint32_t> kept_;  // kill scratch: survivor indices
  // P2G scratch: one block per bin (MpmGridView::blocks), within max(the minimum, the bytes per
  // particle below); over it P2G runs its colour phases (the same bits).
  std::vector<Real> p2g_blocks_;
  Real* p2g_blocks_for(std::size_t nbins, bool fused);
  // The fused substep (solvers/mpm_fused.cpp).
  void step_fused(const exec::Space& space, Real dt);
  MaterialUpdateParams material_params(Real dt) const;  // update_materials' parameters
  // The stability check folded into the substep's last particle pass (folds_check): its value,
  // the state_version_ it holds for (kNotFolded: none), and whether this substep computed it.
  static constexpr std::uint64_t kNotFolded = ~std::uint64_t(0);
  StabilityCheck folded_;
  std::uint64_t folded_at_ = kNotFolded;
  bool fold_pending_ = false;
  StabilityLimits check_limits() const;
  // G2P's parameters when the check folds: the particle collisions in G2P, and the check there
  // unless the material update runs after it.
  MpmStepParams g2p_params(MpmStepParams prm);
  // After G2P: the particle collisions (when G2P did not run them) and the material update
  // (with the check when it folds).
  void after_g2p(const exec::Space& space, Real dt);
  void prime_grid(const exec::Space& space);          // the split P2G of the sorted particles
  void flush_fused_blocks(const exec::Space& space);  // the dilated blocks into the grid
  void update_grid_fused(const exec::Space& space);   // topology + tables of the sorted bins
  void step_sorted_when_needed(const exec::Space& space, Real dt);  // the two passes, lazy sort
  // ... on several ranks (solvers/mpm_lazy_distributed.cpp): the collective sort decision, the
  // dilated blocks' plan after a sort, P2G, and the grid update with G2P.
  bool lazy_sort_needed_distributed(const exec::Space& space, bool need);
  void update_grid_lazy_distributed(const exec::Space& space);
  void p2g_lazy_distributed(const exec::Space& space, Real dt);
  void g2p_lazy_distributed(const exec::Space& space, Real dt);
  std::vector<std::uint8_t> lazy_far_;  // per bin: a particle left its dilated block (G2P, P2G)
  std::uint64_t lazy_resorts_ = 0, lazy_unfit_ = 0;
  bool primed_ = false;
  std::uint64_t fused_fallbacks_ = 0, fused_unfused_ = 0;
  std::vector<Vec3i> fused_extra_;  // the leaves the dilated blocks reach beyond nbr8
  std::vector<std::array<std::int32_t, 27>> fused_nbr27_;  // per bin: MpmGridView::bin_nbr27
  std::vector<std::uint8_t> fused_far_;     // per bin: a particle left its dilated block
  std::vector<std::int32_t> fused_slot_;    // per leaf slot: its index among the active leaves
  std::vector<std::int32_t> fused_target_;  // per (bin, t): the active leaf index or -1
  std::vector<std::uint32_t> fused_start_, fused_items_;  // per active leaf: its blocks' parts
  std::vector<std::uint32_t> fused_slot_cursor_;
  // The substeps since the last topology update of the kept bins (SparseGrid::update_topology's
  // age: leaves retire after that many substeps unused, not that many sorts).
  std::uint32_t topology_age();
  void dilated_extra_leaves(std::vector<Vec3i>& out) const;
  std::uint64_t topology_step_ = 0;
  std::unique_ptr<MpmSleep> sleep_;
  std::unique_ptr<MpmImplicit> implicit_;
  std::unique_ptr<MpmAul> aul_;
  std::unique_ptr<MpmEnriched> enriched_;
};

}  // namespace amalgam
