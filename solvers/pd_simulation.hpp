// Peridynamics as a Simulation (solvers/simulation.hpp). The step itself is PdSolver::step()
// (solvers/pd_solver.cpp); this class adds what the frame loop needs: frame-start snapshots for
// retries, diagnostics columns, output fields (damage, dilatation, crack surfaces), checkpoint
// sections (the bond rows left after compaction, per-bond state, crack meshes).
#pragma once

#include <string>
#include <vector>

#include "solvers/pd_solver.hpp"
#include "solvers/simulation.hpp"

namespace amalgam {

class PdSimulation final : public Simulation {
 public:
  // `solver` initialised (PdSolver::initialize); `space` computes the figures of describe().
  PdSimulation(PdSolver solver, const exec::Space& space);
  PdSolver& solver() { return s_; }
  const PdSolver& solver() const { return s_; }

  std::string describe() const override { return description_; }
  std::size_t particle_count() const override { return s_.global_particle_count(); }
  double work_done() const override { return double(s_.bond_updates()); }
  const char* work_unit() const override { return "bond-updates"; }

  double time() const override { return s_.time(); }
  std::uint64_t step_count() const override { return s_.step_count(); }
  Real stable_dt(const exec::Space& space) const override { return s_.stable_dt(space); }
  void advance(const exec::Space& space, Real dt) override { s_.step(space, dt); }
  Real cfl() const override { return s_.settings().cfl; }
  void set_cfl(Real cfl) override { s_.set_cfl(cfl); }

  void begin_run(const exec::Space& space) override { s_.distribute(space); }
  void prepare_checkpoint() override;  // distributed: gathers particles and bond rows
  void save_frame_start() override { s_.save(snapshot_); }
  void restore_frame_start() override { s_.restore(snapshot_); }

  FrameReport end_frame(const exec::Space& space, long long substeps) override;
  std::vector<Column> sample(const exec::Space& space) const override;
  std::vector<std::string> profile_columns() const override;
  int profile_column(const std::string& label) const override;
  std::string run_summary(double wall) const override;

  // Attributes: vonmises (of PdSolver::compute_stress), damage, rest (x0), material, theta.
  PointFields point_fields(const std::vector<std::string>& names,
                           const exec::Space& space) override;
  double point_voxel_size() const override { return double(s_.settings().spacing); }
  bool surface(SurfaceMesh& out) const override;
  const char* surface_pattern() const override { return "surface_%04d"; }

  // Distributed: rank 0's gathered copy of every rank's own particles (what checkpoints write).
  const ParticleSet& particles() const override {
    return s_.distributed() ? gathered_ : s_.particles();
  }
  ParticleSet& particles() override { return s_.distributed() ? gathered_ : s_.particles(); }
  std::vector<StateSection> checkpoint_sections() override;
  std::vector<StateSection> restore_sections() override;
  void before_restore() override;
  void restored(double time, std::uint64_t steps) override;
  // Per-rank output (issue 28): each rank holds its own particles and ghosts (solver-local) and
  // writes its own ones.
  RankPart my_part() const override;
  const ParticleSet& my_particles() const override { return s_.particles(); }
  PointFields my_point_fields(const std::vector<std::string>& names,
                              const exec::Space& space) override;

 private:
  // Every particle in the single process's order: the solver's own on one process; distributed,
  // the own particles of every rank gathered to rank 0 (empty elsewhere), once per state
  // (PdSolver::gather_particles). Collective when distributed: the one place output joins the
  // ranks' particles (per-rank output would replace it).
  const ParticleSet& all_particles() const;
  PointFields fields_of(const ParticleSet& ps, const std::vector<std::string>& names,
                        const exec::Space& space, bool gathered);
  PdSolver s_;
  mutable ParticleSet gathered_;
  mutable std::uint64_t gathered_version_ = ~std::uint64_t(0);
  std::vector<Mat3> stress_;  // output scratch (vonmises)
  // Distributed: the most broken bonds between ranks and contacts between ranks seen at a frame's
  // end (run summary).
  std::uint64_t cross_broken_ = 0, cross_contacts_ = 0;
  PdSolver::Snapshot snapshot_;
  std::string description_;
  // What restore_sections reads into, applied by restored(); on a distributed run also what
  // prepare_checkpoint gathers for checkpoint_sections.
  std::vector<std::uint64_t> offsets_;
  std::vector<std::uint32_t> neighbor_;
  std::vector<Real> plastic_;
  std::vector<std::uint8_t> intact_;
};

}  // namespace amalgam
