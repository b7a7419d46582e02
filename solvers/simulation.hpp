// The seam between a method that advances state and the runner that drives frames, output,
// checkpoints and retries (apps/frame_loop.cpp). Every method (explicit, implicit, A-ULMPM and
// enriched MPM; peridynamics) implements it once; the frame loop knows nothing of any method.
// docs/architecture.md shows where each method's step lives.
//
// What the frame loop does with it, per frame:
//   begin_frame; save_frame_start (for retries); while the frame lasts: stable_dt (also the
//   stability guard, which throws SimulationError), advance; stable_dt on the end state;
//   end_frame (diagnostics row, progress figures); point_fields / surface / grid for output;
//   checkpoint_sections for checkpoints.
// On a SimulationError inside a frame: restore_frame_start, set_cfl(cfl / 2), and again.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "core/errors.hpp"
#include "core/exec/exec.hpp"
#include "core/math/types.hpp"
#include "core/particles/particle_set.hpp"
#include "core/particles/point_fields.hpp"

namespace amalgam {

class SparseGrid;

// A named block of state after the particle attributes in a checkpoint (io/checkpoint.hpp). A
// section whose size is part of the state (peridynamic bonds left after compaction) has `resize`:
// the reader calls it with the size found in the file, and it checks that size and returns where
// to read to.
struct StateSection {
  std::string name;
  char* data = nullptr;
  std::size_t bytes = 0;
  std::function<char*(std::uint64_t)> resize = nullptr;
};

// One value of a frame's diagnostics row (a diagnostics.csv column).
struct Column {
  std::string name;
  double value = 0;
  bool integer = false;  // printed as a whole number
};

// What a simulation reports at the end of a frame.
struct FrameReport {
  std::vector<Column> columns;        // its diagnostics.csv columns, the same names every frame
  double kinetic = 0, max_speed = 0;  // for the progress line
  std::string progress;               // method figures for the progress line ("CG 4.2 it/step")
  std::vector<std::string> warnings;  // printed after the frame ("2 implicit solves stopped ...")
};

class Simulation {
 public:
  virtual ~Simulation() = default;

  // --- What it is.
  // One line for the start of a run: method, particles and the method's key settings.
  virtual std::string describe() const = 0;
  virtual std::size_t particle_count() const = 0;
  // Work done since the start of the run in the unit of the throughput figure (particle-substeps
  // for MPM, directed bond-updates for peridynamics), and that unit's short name.
  virtual double work_done() const = 0;
  virtual const char* work_unit() const = 0;

  // --- Clock and stepping.
  virtual double time() const = 0;
  virtual std::uint64_t step_count() const = 0;
  // Largest stable substep. Also the stability guard: throws SimulationError naming the step,
  // particle and quantity when the state is not finite or a speed is above the limit.
  virtual Real stable_dt(const exec::Space& space) const = 0;
  // One substep of length dt: the method's named phases (its step()).
  virtual void advance(const exec::Space& space, Real dt) = 0;
  virtual Real cfl() const = 0;
  virtual void set_cfl(Real cfl) = 0;

  // --- Retries. The state at the start of the frame, and back to it (clock included).
  virtual void save_frame_start() = 0;
  virtual void restore_frame_start() = 0;

  // --- Per-frame bookkeeping and diagnostics.
  virtual void begin_frame() {}
  // Once, before the first frame is written (after a resume): a distributed run splits its
  // work across the MPI ranks here (collective; solvers/pd_distributed.cpp).
  virtual void begin_run(const exec::Space& space) {}
  // Collective, before checkpoint_sections on a distributed run: the sections' data gathered to
  // rank 0, which writes the file.
  virtual void prepare_checkpoint() {}
  virtual FrameReport end_frame(const exec::Space& space, long long substeps) = 0;
  // The physical state's columns (energies, momentum, speeds; the same names every call), for a
  // diagnostics row and for the samples taken every N substeps (output.every_substeps).
  virtual std::vector<Column> sample(const exec::Space& space) const = 0;
  // Profiler regions grouped into diagnostics columns ("p2g_s"): the column names, and the
  // column of a region label (-1: counted as other).
  virtual std::vector<std::string> profile_columns() const = 0;
  virtual int profile_column(const std::string& label) const = 0;
  // Optional per-substep log (implicit solver statistics): file name, header, and the row of the
  // substep just taken; empty name = none.
  virtual std::string substep_log_name() const { return ""; }
  virtual std::string substep_log_header() const { return ""; }
  virtual std::string substep_log_row(int frame, Real dt) const { return ""; }
  // Lines printed at the end of a run (wall: seconds the run took).
  virtual std::string run_summary(double wall) const { return ""; }

  // --- Output.
  // The point fields with the attributes `names` (core/particles/point_fields.hpp), in that
  // order; the scene reader lets through only names the method has. Computed on `space`
  // (stresses).
  virtual PointFields point_fields(const std::vector<std::string>& names,
                                   const exec::Space& space) = 0;
  // Keeps every particle's current position as its rest position (attribute `rest`, carried by
  // each particle; particles made later keep theirs): called after set-up and before a
  // checkpoint is read. Methods that hold a reference position (peridynamics: x0) need not.
  virtual void keep_rest_positions() {}
  virtual double point_voxel_size() const = 0;  // the VDB point grid's voxel (dx, or the spacing)
  // A surface mesh written per frame (false: none; with per-vertex velocity, and crack faces for
  // peridynamics), and its file name pattern without extension (printf with the frame number).
  virtual bool surface(SurfaceMesh& out) const { return false; }
  virtual const char* surface_pattern() const { return "surface_%04d"; }
  // The background grid of the last substep (grid volumes), when the method has one.
  virtual const SparseGrid* grid() const { return nullptr; }

  // --- Checkpoints (io/checkpoint.hpp): the particles, the sections after them, and a hook
  // called once the particles and sections were read, with the clock (throws InputError without
  // the file name when what was read is inconsistent).
  virtual const ParticleSet& particles() const = 0;
  virtual ParticleSet& particles() = 0;
  virtual std::vector<StateSection> checkpoint_sections() = 0;
  virtual std::vector<StateSection> restore_sections() { return checkpoint_sections(); }
  // The most particles a checkpoint of this run can hold: the count it starts with unless
  // particles are emitted or removed (a checkpoint's other count is then refused).
  virtual std::size_t max_particle_count() const { return particles().size(); }
  // Distributed runs: which slice of a per-rank checkpoint this rank reads (io/checkpoint.cpp
  // read_checkpoint: the parts q with q % parts == part, then `distribute` sends each particle to
  // its owner); parts = 1 reads it whole. A set-up that holds only a slice of the scene's
  // particles (solvers/factory.cpp) counts them all in set_up_particle_count.
  struct Slice {
    int part = 0, parts = 1;
  };
  virtual Slice checkpoint_slice() const { return {}; }
  virtual std::uint64_t set_up_particle_count() const { return particles().size(); }
  // Before a checkpoint is read, on every path, while particles() still holds the set-up's.
  virtual void before_checkpoint_read() {}
  // Before a checkpoint is read whole into particles(): they are sized to set_up_particle_count.
  virtual void before_restore() {}
  // The checkpoint had no optional attribute `name` that particles() carries (`rest`: the output
  // asked for it after the checkpoint was written): fill it, before restored(). Collective.
  virtual void fill_absent_attribute(const std::string& name) {
    throw InputError("checkpoint has no particle attribute '" + name + "'");
  }
  // Before restored(), when a slice was read: its rows' order keys (two per particle, the
  // single process's order) and the checkpoint's particle count over every rank.
  virtual void restoring_slice(std::vector<std::uint64_t> /*keys*/, std::uint64_t /*total*/) {}
  virtual bool variable_particle_count() const { return false; }
  virtual void restored(double time, std::uint64_t steps) = 0;

  // --- Per-rank output (issue 28, `amalgam run --parts ranks`; apps/frame_loop.cpp, io/parts.hpp).
  // This rank's part of the particles: the rows of my_particles() / my_point_fields() it owns
  // (`all`: every row) and, per kept row, two order keys whose lexicographic order over every
  // rank's parts is the single process's particle order, so joined parts are bitwise one
  // process's files. One process: every row, keyed by its index. A method whose ranks hold only
  // their own particles (distributed MPM) returns them whole; one whose ranks hold every particle
  // (peridynamics today) names its owned rows.
  struct RankPart {
    bool all = true;
    std::vector<std::uint32_t> rows;   // the kept rows when !all, increasing
    std::vector<std::uint64_t> order;  // 2 per kept row
  };
  virtual RankPart my_part() const {
    RankPart r;
    r.order.resize(2 * particles().size());
    for (std::size_t i = 0; i < particles().size(); ++i) r.order[2 * i] = i, r.order[2 * i + 1] = 0;
    return r;
  }
  virtual const ParticleSet& my_particles() const { return particles(); }
  virtual PointFields my_point_fields(const std::vector<std::string>& names,
                                      const exec::Space& space) {
    return point_fields(names, space);
  }
  // Collective, before checkpoint_sections when every rank writes its own part: what rank 0's part
  // needs beyond its particles (peridynamics: the bond rows gathered; MPM: nothing).
  virtual void prepare_checkpoint_part() { prepare_checkpoint(); }
};

}  // namespace amalgam
