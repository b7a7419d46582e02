// Peridynamics solver (peridynamics-elastoplastic-fracture.txt): particles with CSR bond
// families, explicit velocity Verlet, gravity, fixed and prescribed-velocity particles,
// colliders (the rigid projectiles of the paper's Fig. 1 and 15) and short-range contact
// between particles that are not bonded, so fragments do not pass through each other.
//
// step() = kick_drift -> move_meshes -> apply_colliders -> compute_dilatation (with the plastic
// return) -> compute_forces (with fracture, and the damage of update_damage in the same pass) ->
// contact_forces -> split_meshes -> compact_bonds -> kick. (move_meshes and split_meshes act on embedded tetrahedral meshes, Sec. 5.2.)
#pragma once

#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/particles/particle_set.hpp"
#include "core/geometry/colliders.hpp"
#include "core/math/expression.hpp"
#include "kernels/peridynamics.hpp"
#include "solvers/pd_crack_mesh.hpp"

namespace amalgam {

struct PdSettings {
  Real spacing = Real(0.01);    // lattice spacing lc of the particles (m)
  Real horizon = Real(0.0301);  // delta (m); 3.01 lc by default
  // PdModel::Lps (LAMMPS peri/lps's model) needs deviatoric Lps and surface_correction off.
  PdModel model = PdModel::Paper;
  PdDeviatoric deviatoric = PdDeviatoric::Paper;
  bool partial_volume = true;      // nu_ij for bonds cut by the horizon
  bool surface_correction = true;  // discrete theta normaliser and shear factor (see PdConstants)
  bool fracture = true;
  PdCriterion criterion =
      PdCriterion::Paper;     // how a bond's stretch is measured (eq. 18 or classical)
  bool contact = true;        // repulsion between unbonded particles closer than contact_distance
  Real contact_distance = 0;  // 0: 0.9 lc
  Real contact_skin = 0;      // Verlet-list skin; 0: 0.5 lc
  Vec3 gravity = Vec3(0, Real(-9.81), 0);
  Real cfl = Real(0.7);  // safety factor on the critical Verlet step (PdSolver::critical_dt)
  Real max_dt = std::numeric_limits<Real>::infinity();
  Real max_speed = Real(1e4);  // stability guard: faster particles stop the run
  // Viscous damping (1/s): each half kick multiplies velocities by exp(-damping dt / 2). For dynamic
  // relaxation to a static state (quasi-static loading); 0 = none (the papers' dynamics).
  Real damping = 0;
  // Bond compaction: once the bonds broken since the last compaction exceed this fraction of the
  // stored ones, they are removed from the CSR arrays (pd_compact_bonds; the run continues
  // bitwise as without). 0 = never. 10 %: measured to pay back within a few steps
  // (docs/benchmarks.md, "Bond compaction").
  Real compact_fraction = Real(0.1);
};

// Particle attributes of a peridynamic body.
struct PdAttributes {
  // x + x_lo is the position, a compensated pair (core/math/types.hpp: add_compensated), so that a
  // body far from the origin keeps the increments dt v below one ulp of x; the bond passes read
  // the displacement (x - x0) + x_lo, whose differences are exact where x's would round.
  ParticleSet::Id x, x_lo, x0, v, acc, volume, material, id, theta, damage;
  ParticleSet::Id fixed;    // int32: 1 = velocity prescribed (fixed_velocity), 0 = free
  ParticleSet::Id fixed_v;  // prescribed velocity
  ParticleSet::Id f_ext;    // external force density (N/m^3), e.g. a traction on an end layer
  static PdAttributes add_to(ParticleSet& ps);
};

struct PdDiagnostics {
  double kinetic = 0;
  Vec3d momentum = Vec3d::Zero();
  double max_speed = 0;
  double max_damage = 0;
  std::uint64_t bonds = 0, intact = 0;  // directed bonds: at the start, and intact now
  std::uint64_t stored = 0;  // directed bonds in the CSR arrays (bonds minus those compacted away)
  std::uint64_t compactions = 0;
};

class PdSolver {
  struct Ranks;  // distributed: the local particles' ids and owners, the ghost plan
  struct BondRec;
  struct LocalEntry;

 public:
  PdSolver(const PdSettings& settings, std::vector<PdMaterial> materials,
           std::vector<Collider> colliders = {});

  // Adds particles of one material with a velocity v + omega x (x - centre) and a volume each.
  void add_particles(const std::vector<Vec3>& x, const Vec3& v, const Vec3& omega,
                     const Vec3& centre, int material, Real volume);
  // Same with a volume per particle (tetrahedron barycentres).
  void add_particles(const std::vector<Vec3>& x, const std::vector<Real>& volume, const Vec3& v,
                     const Vec3& omega, const Vec3& centre, int material);
  // Prescribes the velocity of the particles inside the box [lo, hi] (at their reference
  // position): zero velocity fixes them.
  void prescribe_velocity(const Vec3& lo, const Vec3& hi, const Vec3& velocity);
  // The same with the velocity a function of the reference position X and the time t
  // (`where` names it in errors): each step moves the particles with v(X, t + dt/2), the
  // midpoint of the drift, and ends with v(X, t + dt).
  void prescribe_velocity(const Vec3& lo, const Vec3& hi,
                          std::shared_ptr<const VectorField> velocity);
  // Adds an external force density (N/m^3) on the particles inside [lo, hi] (reference
  // positions), for the whole run: a traction T on an end layer of thickness h is T / h.
  void apply_force_density(const Vec3& lo, const Vec3& hi, const Vec3& force_density);
  // A pre-crack: bonds whose reference segment crosses the plane through `point` with normal `n`
  // at a point inside the box [lo, hi] are broken when the solver is initialised (the paper's
  // Fig. 17 sheet "with initial cracks").
  void add_precrack(const Vec3& point, const Vec3& n, const Vec3& lo, const Vec3& hi);
  // Embeds a tetrahedral mesh whose tetrahedron t is particle first_particle + t (the particles
  // added from its barycentres): it follows the particles and splits along crack faces (Sec. 5.2).
  void add_crack_mesh(const std::vector<Vec3d>& nodes,
                      const std::vector<std::array<std::int32_t, 4>>& tets,
                      std::uint32_t first_particle);
  std::vector<PdCrackMesh>& crack_meshes() { return meshes_; }
  const std::vector<PdCrackMesh>& crack_meshes() const { return meshes_; }
  // Builds the bond families and the model constants from the current positions (the reference
  // configuration) and the initial forces. Called once, after the particles are added.
  void initialize(const exec::Space& space);
  // The same on several MPI ranks (collective; one rank: initialize()), and distributed (see
  // distribute()) without the whole bond list: every rank holds every particle's per-particle
  // data (set up alike, as added) but builds the bond rows, the per-bond arrays and the constants
  // that need a row only for the particles it owns (and, for the surface correction's shared
  // fits, the first particle of each of its families elsewhere; DistStats::rows_built); the
  // ghosts' constants and the mirrored per-bond values come from their owners. Bitwise the
  // whole set-up followed by distribute() (solvers/pd_distributed.cpp).
  void initialize_distributed(const exec::Space& space);

  void step(const exec::Space& space, Real dt);
  // min(max_dt, cfl * the critical Verlet step (computed once: it depends on the reference
  // configuration only), cfl * spacing / fastest particle). Also the stability guard: throws
  // SimulationError naming the step and particle when a velocity or position is not finite or a
  // speed exceeds max_speed.
  Real stable_dt(const exec::Space& space) const;

  // Sums exact until one rounding (ExactSum), over the own particles; collective when
  // distributed: every rank gets every rank's diagnostics.
  PdDiagnostics diagnostics(const exec::Space& space) const;
  double time() const { return time_; }
  void restore_clock(double time, std::uint64_t steps) {
    time_ = time;
    steps_ = steps;
  }
  // The whole evolving state (particles, per-bond state, crack meshes, counters and clock), to
  // retry a frame from its start. The bond layout is not copied: save() arms the snapshot, and
  // the first compaction after it keeps the layout it replaces there (9 bytes per bond per frame
  // instead of the ~46 of the whole PdBonds). The snapshot must outlive the solver's steps until
  // the next save(). Restoring drops the contact list (rebuilt at the next contact pass).
  struct Snapshot {
    ParticleSet::Snapshot particles;
    std::vector<Real> plastic, plastic_r;
    std::vector<std::uint8_t> intact;
    PdBonds layout;  // the bonds as saved, when a compaction replaced them since
    bool layout_saved = false;
    std::vector<PdCrackMesh> meshes;
    std::uint64_t intact_count = 0, meshes_intact = 0, kept_broken = 0, compactions = 0,
                  bond_updates = 0;
    double time = 0;
    std::uint64_t steps = 0;
    // Distributed: the local layout (particles, constants, ghost plan) of the frame start.
    std::shared_ptr<const Ranks> ranks;
    PdConstants constants;
  };
  void save(Snapshot& s);
  void restore(Snapshot& s);
  std::uint64_t step_count() const { return steps_; }
  const PdSettings& settings() const { return settings_; }
  // CFL number used by stable_dt (lowered while retrying a failed frame).
  void set_cfl(Real cfl) { settings_.cfl = cfl; }
  ParticleSet& particles() { return particles_; }
  const ParticleSet& particles() const { return particles_; }
  const PdAttributes& attributes() const { return attr_; }
  const PdBonds& bonds() const { return bonds_; }
  PdBonds& bonds() { return bonds_; }
  const std::vector<PdMaterial>& materials() const { return materials_; }
  // The model parameters with `materials` pointing at this solver's materials (bound on each
  // call, so a copied solver never points into its source).
  PdParams params() const {
    PdParams p = params_;
    p.materials = materials_.data();
    p.plastic = false;
    for (const PdMaterial& m : materials_)
      p.plastic |= m.psi0 < std::numeric_limits<Real>::infinity();
    return p;
  }
  const PdConstants& constants() const { return constants_; }
  PdView view();
  // Force densities of the last step (N/m^3), and the stress of each particle recomputed now.
  const std::vector<Vec3>& forces() const { return force_; }
  std::uint64_t contact_list_builds() const { return contact_builds_; }
  void compute_stress(const exec::Space& space, std::vector<Mat3>& stress);

  // Phases of step(), public for tests.
  void kick_drift(const exec::Space& space, Real dt);
  void apply_colliders(const exec::Space& space, Real t);
  void compute_dilatation(const exec::Space& space);
  void compute_forces(const exec::Space& space);  // also the damage (update_damage's work)
  void contact_forces(const exec::Space& space);
  void update_damage(const exec::Space& space);
  void move_meshes(Real dt);
  void split_meshes();
  void compact_bonds(const exec::Space& space);
  void kick(const exec::Space& space, Real dt);

  // Directed bonds processed by the dilatation and force passes since initialize() (the stored
  // bonds, summed over steps): the numerator of bond-updates/s.
  std::uint64_t bond_updates() const { return bond_updates_; }
  // A checkpoint's bond rows and per-bond state (see read_checkpoint): restricts the bonds built
  // from the reference configuration to the given rows and takes the state. Returns false
  // (nothing changed) when the rows are not a subset of this solver's bonds.
  bool restore_bonds(const std::vector<std::uint64_t>& offsets,
                     const std::vector<std::uint32_t>& neighbor, const std::vector<Real>& plastic,
                     const std::vector<std::uint8_t>& intact);
  // Distributed (collective): a whole checkpoint (`all`: every particle in global id order, and
  // the global bond rows) into this rank's local particles and own rows, then re-ghosted. False on
  // every rank (nothing usable) when some rank's rows are not a subset of its bonds.
  bool restore_distributed(const exec::Space& space, const ParticleSet& all,
                           const std::vector<std::uint64_t>& offsets,
                           const std::vector<std::uint32_t>& neighbor,
                           const std::vector<Real>& plastic,
                           const std::vector<std::uint8_t>& intact);

  // Distributed runs (issue 28; solvers/pd_distributed.cpp). Collective: every rank calls it
  // with the same solver (set up alike on every rank, with the whole state; a no-op after
  // initialize_distributed, which gives the same layout without the whole bond list). Zoltan's RCB splits
  // the particles by reference position, weighted by bonds, and keeps its cuts; afterwards each
  // rank holds only its own particles and their ghosts (the bond neighbours of its rows and the
  // particles within contact reach), in the order of their global ids, with the CSR rows of its
  // own particles referring to local indices. Each step copies the owners' positions, dilatation
  // and damage into the ghosts point to point; the contact list's rebuild re-ghosts (and, when the
  // bond work is imbalanced or forced, repartitions with migration). Bitwise the single process
  // on every rank count. One rank: nothing changes. Refused (InputError) with embedded tet meshes,
  // which are not distributed yet.
  void distribute(const exec::Space& space);
  bool distributed() const { return ranks_ != nullptr; }
  // Collective: the bond rows of all ranks in the global layout, on rank 0 (others: empty).
  void gather_bonds(std::vector<std::uint64_t>& offsets, std::vector<std::uint32_t>& neighbor,
                    std::vector<Real>& plastic, std::vector<std::uint8_t>& intact) const;
  // Output accessors (distributed; one process: the solver's own particles):
  //  gather_particles: collective; every rank's own particles on rank 0 in the single process's
  //    order (global id), every attribute; empty on the other ranks.
  //  gather_owned: collective; per-particle records (`bytes` each, indexed by local index) of the
  //    own particles, on rank 0 in global id order.
  //  owned_local / global_ids: this rank's own particles (local indices) and every local
  //    particle's global id (per-rank output writes these).
  void gather_particles(ParticleSet& out) const;
  std::vector<char> gather_owned(const void* data, std::size_t bytes) const;
  std::vector<std::uint32_t> owned_local() const;
  std::vector<std::uint64_t> global_ids() const;
  std::size_t global_particle_count() const;
  // Rank-local counts made global (integer sums: exact).
  std::uint64_t global_sum(std::uint64_t v) const;
  // Distributed counters (this rank): ghost traffic of the last step, time in the exchanges.
  struct DistStats {
    std::uint64_t owned = 0, ghosts = 0;  // local particles now
    std::uint64_t reghosts = 0, repartitions = 0;
    double imbalance = 1;  // max / mean bond work per rank, at the last cut
    std::uint64_t step_bytes = 0, step_messages = 0;  // halo traffic sent in the last step
    double comm_seconds = 0;  // in the halo exchanges and re-ghosting, summed
    // initialize_distributed: bond rows this rank built (its own particles' and, of those, the
    // family representatives owned elsewhere, family_rows), the surface correction's families it
    // fitted (each family is fitted on one rank; initialize(): all of them), and its set-up's
    // seconds.
    std::uint64_t rows_built = 0, family_rows = 0, families_fitted = 0;
    double setup_seconds = 0;
  };
  const DistStats& dist_stats() const { return dist_stats_; }
  // This rank's own rows' broken bonds to ghosts, and its own particles in contact (closer than
  // the contact distance, no intact bond) with ghosts now: what shows that fracture and contact
  // cross rank boundaries (tests). Local: no communication; zeros on one process.
  struct CrossRank {
    std::uint64_t broken = 0, contacts = 0;
  };
  CrossRank cross_rank() const;
  // Increments with every change of the state (a step, a restore): caches of gathered output.
  std::uint64_t state_version() const { return version_; }
  std::uint64_t compactions() const { return compactions_; }

 private:
  PdSettings settings_;
  std::vector<PdMaterial> materials_;
  std::vector<Collider> colliders_;
  ParticleSet particles_;
  PdAttributes attr_;
  PdBonds bonds_;
  PdConstants constants_;
  PdContactList contact_list_;
  std::uint64_t contact_builds_ = 0;
  PdParams params_;
  // The largest stable velocity-Verlet step at the start, 2 / omega_max: omega_max^2 is the
  // largest eigenvalue of rho^-1 K, K the stiffness of the linearised peridynamic forces, found
  // by 40 power iterations on finite differences of the forces (a probe displacement of 3e-3 lc,
  // elastic, no fracture), with a 10 % margin. Silling & Askari's bound (2005, eq. 34) and
  // Gershgorin's bound on the state-based forces were 2.6x and 3.5-4.5x below the measured
  // critical step of a corrected 8^3 block, i.e. that many more steps for nothing.
  // start (distributed): the power iteration's start vector per local particle (the single
  // process's draw); the ordered sums of its last iteration are gathered on rank 0.
  Real critical_dt(const exec::Space& space, const std::vector<Vec3>* start = nullptr);
  // The power iteration's start vector of every particle (fixed ones zero; a fixed seed).
  std::vector<Vec3> probe_start() const;
  std::vector<Vec3> force_;
  PdScratch scratch_;    // the passes' per-particle records, reused every step
  std::vector<Real> q_;  // consistent term per particle (PdView::q), recomputed every step
  struct Precrack {
    Vec3 point, n, lo, hi;
  };
  std::vector<Precrack> precracks_;
  // Prescribed velocities that change with time: the field and the particles it drives.
  struct Drive {
    std::shared_ptr<const VectorField> v;
    std::vector<std::uint32_t> particles;
    Vec3 lo, hi;  // the box (reference positions): a distributed run re-selects its particles
  };
  std::vector<Drive> drives_;
  void drive_velocities(const exec::Space& space, double t);
  // Distributed: which particles this rank owns and the plan copying owners' values to the rest.
  std::shared_ptr<const Ranks> ranks_;
  mutable DistStats dist_stats_;
  std::uint64_t version_ = 0;
  std::uint64_t global_stored_ = 0;  // distributed: stored bonds summed over the ranks
  // The local particles rebuilt (re-ghosting, with migration when repartitioning): see
  // pd_distributed.cpp. Then the contact list is rebuilt.
  // keep (optional, per bond): the own rows' bonds that stay (a checkpoint's restriction).
  void relocal(const exec::Space& space, bool repartition,
               const std::vector<std::uint8_t>* keep = nullptr);
  // bond_plan: the bond halo also without plastic materials (the set-up's mirrored values).
  void assemble_local(const exec::Space& space, std::vector<LocalEntry>& entries,
                      std::shared_ptr<Ranks> ranks, bool bond_plan = false);
  // Distributed set-up: the far ends' omega and shear_omega of the own rows' bonds (from this
  // rank's rows, else from the owners' through the bond halo); every ghost's constants.
  void mirror_distributed();
  // Pre-cracks break the bonds of `b` (row q is particle rows[q]; null: q) crossing them.
  void apply_precracks(const exec::Space& space, PdBonds& b, const std::uint32_t* rows);
  // Distributed: the ghosts' positions before the bond passes (or a re-ghost when the contact
  // list is rebuilt or a repartition is due).
  void exchange_positions(const exec::Space& space);
  void build_contact_list(const exec::Space& space);
  void select_drives();
  void pack_record(std::vector<char>& b, std::size_t i) const;
  BondRec bond_record(std::uint64_t k, std::uint64_t neighbour_gid) const;
  // Distributed plastic materials: the far ends' plastic extensions of bonds to ghosts.
  void share_plastic();
  // Owners' values of a per-particle array into the ghosts (no-op on one process).
  void share_bytes(void* data, std::size_t bytes) const;
  template <class T>
  void share(T* data) const {
    if (ranks_) share_bytes(data, sizeof(T));
  }
  std::vector<PdCrackMesh> meshes_;
  std::uint64_t intact_ = 0,
                meshes_intact_ = 0;  // intact directed bonds: now, and when the meshes last split
  std::uint64_t bonds_initial_ = 0;  // directed bonds at initialize()
  std::uint64_t kept_broken_ =
      0;  // broken bonds the last compaction kept (short ones, for contact)
  std::uint64_t compactions_ = 0, bond_updates_ = 0;
  // The snapshot of the frame start, given the layout a compaction replaces. Not carried by a
  // copy or a move: a copied solver must not write into the original's snapshot (save() arms).
  struct ArmedSnapshot {
    Snapshot* p = nullptr;
    ArmedSnapshot() = default;
    ArmedSnapshot(const ArmedSnapshot&) {}
    ArmedSnapshot& operator=(const ArmedSnapshot&) {
      p = nullptr;
      return *this;
    }
  } armed_;
  Real contact_distance() const;
  double contact_reach() const;  // solvers/pd_distributed.cpp
  void keep_within_contact_reach(const Vec3* x, std::size_t n, const double* lo, const double* hi,
                                 std::vector<std::uint8_t>& keep) const;
  Real crit_dt_ = 0;  // critical Verlet step of the reference configuration (critical_dt)
  double time_ = 0;
  std::uint64_t steps_ = 0;
  bool initialized_ = false;
};

}  // namespace amalgam
