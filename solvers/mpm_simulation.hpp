// MPM as a Simulation (solvers/simulation.hpp): every MPM variant (explicit, implicit, A-ULMPM,
// enriched) behind the one interface the frame loop drives. The step itself is MpmSolver::step()
// (solvers/mpm_solver.cpp); this class adds what the frame loop needs: frame-start snapshots for
// retries, diagnostics columns, output fields, checkpoint sections.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "solvers/mpm_solver.hpp"
#include "solvers/simulation.hpp"

namespace amalgam {

// MPM particles for the frame writers with the attributes `names` (point_attribute_names()): F,
// J = det F, Jp (the plastic scalar), vonmises (of the elastic Cauchy stress), rest (the
// attribute MpmAttributes::rest), material, temperature, enrichment (the domain state). A
// name the particles lack (no plastic state, no temperature) throws std::logic_error: the scene
// reader refuses it first. Stresses are computed on `space`.
PointFields mpm_point_fields(const ParticleSet& ps, const MpmAttributes& a,
                             const std::vector<MaterialParams>& materials,
                             const std::vector<std::string>& names, const exec::Space& space);

class MpmSimulation final : public Simulation {
 public:
  explicit MpmSimulation(MpmSolver solver);
  MpmSolver& solver() { return s_; }
  const MpmSolver& solver() const { return s_; }

  std::string describe() const override;
  std::size_t particle_count() const override { return s_.particles().size(); }
  double work_done() const override {
    return double(s_.particles().size()) * double(s_.step_count());
  }
  const char* work_unit() const override { return "p-steps"; }

  double time() const override { return s_.time(); }
  std::uint64_t step_count() const override { return s_.step_count(); }
  Real stable_dt(const exec::Space& space) const override { return s_.stable_dt(space); }
  void advance(const exec::Space& space, Real dt) override { s_.step(space, dt); }
  Real cfl() const override { return s_.settings().cfl; }
  void set_cfl(Real cfl) override { s_.set_cfl(cfl); }

  void save_frame_start() override;
  void restore_frame_start() override;

  void begin_frame() override;
  FrameReport end_frame(const exec::Space& space, long long substeps) override;
  std::vector<Column> sample(const exec::Space& space) const override;
  std::vector<std::string> profile_columns() const override;
  int profile_column(const std::string& label) const override;
  std::string substep_log_name() const override;
  std::string substep_log_header() const override;
  std::string substep_log_row(int frame, Real dt) const override;
  std::string run_summary(double wall) const override;

  PointFields point_fields(const std::vector<std::string>& names,
                           const exec::Space& space) override {
    return mpm_point_fields(all_particles(), s_.attributes(), s_.materials(), names, space);
  }
  // Distributed (solvers/mpm_distributed.cpp): the particles are split across the ranks here.
  void begin_run(const exec::Space& space) override { s_.distribute(space); }
  void prepare_checkpoint() override { (void)all_particles(); }
  void keep_rest_positions() override { s_.keep_rest_positions(); }
  void before_checkpoint_read() override;
  void fill_absent_attribute(const std::string& name) override;
  double point_voxel_size() const override { return double(s_.settings().dx); }
  bool surface(SurfaceMesh& out) const override;
  const char* surface_pattern() const override { return "frame_%04d_surface"; }
  // Distributed (collective): every rank's owned leaves gathered into a grid on rank 0.
  const SparseGrid* grid() const override;

  // Distributed: rank 0's gathered copy of every rank's particles (what checkpoints write).
  const ParticleSet& particles() const override {
    return s_.distributed() ? gathered_ : s_.particles();
  }
  ParticleSet& particles() override { return s_.distributed() ? gathered_ : s_.particles(); }
  std::vector<StateSection> checkpoint_sections() override;
  std::vector<StateSection> restore_sections() override;
  std::size_t max_particle_count() const override { return max_particles_; }
  // A distributed set-up (solvers/factory.cpp) reads a per-rank checkpoint in slices, one per
  // rank, and a single-file one whole.
  Slice checkpoint_slice() const override;
  std::uint64_t set_up_particle_count() const override {
    return s_.sliced() ? std::uint64_t(s_.next_id()) : s_.particles().size();
  }
  void before_restore() override;
  void restoring_slice(std::vector<std::uint64_t> keys, std::uint64_t total) override;
  bool variable_particle_count() const override {
    return !s_.emitters().empty() || s_.settings().kill.enabled();
  }
  void restored(double time, std::uint64_t steps) override;

  // Per-rank output: a rank's own particles, keyed by their place in the single process's order.
  RankPart my_part() const override;
  const ParticleSet& my_particles() const override { return s_.particles(); }
  PointFields my_point_fields(const std::vector<std::string>& names,
                              const exec::Space& space) override {
    return mpm_point_fields(s_.particles(), s_.attributes(), s_.materials(), names, space);
  }
  void prepare_checkpoint_part() override {}

 private:
  // Every particle, in the single process's order: the solver's own on one process; distributed,
  // gathered to rank 0 (empty elsewhere) once per state. Collective when distributed. The one
  // place a distributed run joins its particles (`--parts ranks` output does without it).
  const ParticleSet& all_particles() const;
  MpmSolver s_;
  mutable ParticleSet gathered_;
  mutable std::uint64_t gathered_version_ = ~std::uint64_t(0);
  mutable std::unique_ptr<SparseGrid> gathered_grid_;
  mutable std::uint64_t gathered_grid_version_ = ~std::uint64_t(0);
  MpmSolver::Snapshot snapshot_;
  struct RestById {
    std::int32_t id;
    Vec3 x;
  };
  std::vector<RestById> setup_rest_;  // before_checkpoint_read, for fill_absent_attribute
  bool setup_sliced_ = false;
  double frame_time_ = 0;
  std::uint64_t frame_steps_ = 0;
  // Emitters and kill regions: the counters at the frame's start, the bound on the particle count
  // (the initial particles plus what the emitters can emit), and the checkpointed state
  // (next particle id, emitted, killed).
  SourceCounters frame_sources_;
  std::size_t max_particles_ = 0;
  std::int64_t initial_particles_ = 0, emitted_bound_ = 0;
  std::int64_t source_state_[3] = {0, 0, 0};
  std::int64_t slice_total_ = -1;  // restoring_slice: the checkpoint's count over every rank
  void check_slice_ids(std::int64_t limit) const;
  // Particle domains: enriched particle fraction, summed over the frames of this run and its
  // largest value in one substep.
  double enriched_sum_ = 0, enriched_max_ = 0;
  int frames_ = 0;
};

}  // namespace amalgam
