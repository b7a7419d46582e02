#include "apps/frame_loop.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <iterator>
#include <memory>

#include "apps/commands.hpp"
#include "core/dist/comm.hpp"
#include "core/errors.hpp"
#include "core/exec/background.hpp"
#include "io/checkpoint.hpp"
#include "io/files.hpp"
#include "io/parts.hpp"
#include "io/preview.hpp"
#include "io/surfacing.hpp"
#include "io/vdb_points.hpp"
#include "io/writers.hpp"

namespace amalgam::cli {

namespace {

std::string numbered(const std::string& dir, const char* pattern, int frame, const char* ext) {
  char name[96];
  std::snprintf(name, sizeof name, pattern, frame);
  return dir + "/" + name + "." + ext;
}

// The float attribute a preview colours by (null: by material).
const char* preview_attribute(ColorBy c) {
  switch (c) {
    case ColorBy::Temperature:
      return "temperature";
    case ColorBy::Plastic:
      return "Jp";
    case ColorBy::Damage:
      return "damage";
    default:
      return nullptr;
  }
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Shared files (gathered frames, the single-file checkpoint, diagnostics, samples) are written by
// MPI rank 0 only: it holds what the collectives joined (the gathered particles, the exact sums
// of every rank's diagnostics), and the other ranks take part in the collectives alone.
bool writes_files() {
  return dist::Comm::world().root();
}

// The frame files of the simulation's current state. write(f) copies what frame f writes (the
// point fields, the preview's attribute, the grid's nodes, the surface mesh) into a snapshot on
// the simulation's thread; the files are written from it by the output worker: in the background
// while the next frame simulates (asynchronous output, the default), or at once (--sync-output).
// At most one frame is in flight: write(f + 1) waits for frame f's files. A checkpoint never
// claims a frame that is not on disk: one written at frame f's end is staged in a temporary file
// before write(f) and renamed into place by the writer once frame f's files are (write's `then`),
// and wait() is called before the checkpoints written outside that order (an interrupt's, --parts
// ranks). A write error in the background is rethrown by the next write or wait, naming the file;
// the checkpoint it would have committed is then removed.
class FrameWriter {
 public:
  FrameWriter(Simulation& sim, const Scene& scene, const RunSettings& rs, const exec::Space& space)
      : sim_(sim),
        scene_(scene),
        rs_(rs),
        space_(space),
        camera_(preview_camera(scene)),
        splat_(preview_radius(scene)),
        floor_y_(preview_floor(scene)),
        spacing_(particle_spacing(scene)),
        parts_(rs.rank_parts),
        async_(!rs.sync_output && (writes_files() || parts_)),
        // The writer's OpenVDB work runs on its own thread alone (an arena of one), beside the
        // simulation's --threads; synchronous output uses the simulation's space, as it waits.
        writer_space_(async_ ? exec::Space(exec::Backend::Serial, 1) : space),
        worker_(async_) {
    // Test hook (tests/async_interrupt_test.sh): the writer sleeps this long before each frame,
    // so a frame is certainly in flight when the test's injected SIGINT arrives.
    if (const char* d = std::getenv("AMALGAM_TEST_WRITE_DELAY_MS")) delay_ms_ = std::atoi(d);
  }

  // `then` runs after frame f's files are written (on the writer's thread when asynchronous).
  void write(int f, std::function<void()> then = {}) {
    commit();  // --parts ranks: frame f - 1's manifest, once every rank's part is on disk
    // The whole frame's points (gathered to rank 0 on a distributed MPM run): for the point files
    // of a single-file run, and for what is computed from every point (previews, surfacing).
    // A run that writes none of them (output.ply and output.vdb_points false, no preview, no
    // surfacing) neither copies nor gathers them: on 2 ranks the sphere's frame 0 gather of
    // 948,690 particles was a third of the set-up's difference to one process (docs/scaling.md).
    const OutputSpec& out = scene_.output;
    const bool point_files = !parts_ && (out.ply || out.vdb_points);
    const bool whole = point_files || rs_.preview || out.surfacing.enabled;
    PointFields p = whole ? point_fields() : PointFields();  // collective when distributed
    // Grid volumes: collective when distributed (every rank's owned leaves gathered to rank 0).
    // The grid exists once a substep ran.
    const SparseGrid* grid = scene_.output.grid_volumes && f > 0 ? sim_.grid() : nullptr;
    std::shared_ptr<PartSnapshot> part;
    if (parts_) part = part_snapshot();
    if (!writes_files() && !parts_) {
      if (then) then();
      return;
    }
    const auto t0 = std::chrono::steady_clock::now();
    std::shared_ptr<Snapshot> s;
    if (writes_files()) {
      s = std::make_shared<Snapshot>(std::move(p));
      if (rs_.preview) {
        const char* attr = preview_attribute(scene_.preview.color_by);
        if (const std::vector<float>* a = attr ? s->points.fields.find(attr) : nullptr)
          s->preview_scalar = *a;
        else if (attr && has_attribute(attr))  // the preview's attribute when frames lack it
          s->preview_scalar = *sim_.point_fields({attr}, space_).find(attr);
      }
      if (grid) s->grid = std::make_unique<GridNodes>(grid_nodes(*grid, sim_.point_voxel_size()));
      s->has_mesh = (out.surface_obj || out.surface_ply) && sim_.surface(s->mesh);
    }
    if (parts_) pending_ = {f, sim_.time()};
    waited_ += seconds_since(t0);  // the copy is the simulation's share of asynchronous output
    const auto t1 = std::chrono::steady_clock::now();
    worker_.submit([this, f, s, part, then = std::move(then)] {
      if (s) write_snapshot(f, *s);
      if (part) write_part(f, *part);
      if (then) then();
    });
    waited_ += seconds_since(t1);
  }
  // Waits for the frame in flight; rethrows its write error. --parts ranks: collective, and the
  // frame's manifest is written (rank 0) once every rank's part is on disk.
  void wait() {
    drain();
    commit();
  }
  // The point files (PLY, VDB points, as the output asks) at `base` + extension, OpenVDB under
  // `space`'s thread limit; returns their paths.
  std::vector<std::string> write_points(const std::string& base, const PointFields& p,
                                        const exec::Space& space) const {
    std::vector<std::string> paths;
    if (!writes_files()) return paths;
    if (scene_.output.ply) {
      paths.push_back(base + "ply");
      write_ply_points(paths.back(), p);
    }
    if (scene_.output.vdb_points) {
      paths.push_back(base + "vdb");
      write_vdb_points(paths.back(), p, sim_.point_voxel_size(), scene_.output.vdb_precision,
                       space);
    }
    return paths;
  }
  // The point fields with the scene's output.attributes.
  PointFields point_fields() const {
    PointFields p = sim_.point_fields(scene_.output.attributes, space_);
    p.material_names = scene_.material_names;
    return p;
  }
  // "amalgam: output: ..." for the end of a run: bytes, the writer's seconds and rate, and the
  // seconds the simulation spent on output (copying and waiting; with synchronous output, all).
  std::string summary() {
    if (parts_) {  // every rank wrote: the bytes summed, the slowest rank's seconds
      const dist::Comm& comm = dist::Comm::world();
      bytes_ = double(comm.sum(std::uint64_t(bytes_)));
      written_s_ = comm.max(written_s_);
      waited_ = comm.max(waited_);
    }
    if (!writes_files() || frames_ == 0) return "";
    char line[320];
    std::snprintf(line, sizeof line,
                  "amalgam: output (%s%s): %d frames, %.1f MB in %.3f s of writing (%.1f MB/s); "
                  "simulation held %.3f s\n",
                  async_ ? "asynchronous" : "synchronous", parts_ ? ", a part per rank" : "",
                  frames_, bytes_ * 1e-6, written_s_, bytes_ * 1e-6 / std::max(written_s_, 1e-9),
                  async_ ? waited_ : written_s_);
    return line;
  }

 private:
  struct Snapshot {
    explicit Snapshot(PointFields p) : points(std::move(p)) {}
    PointSnapshot points;
    std::vector<float> preview_scalar;  // empty: coloured by material
    std::unique_ptr<GridNodes> grid;
    bool has_mesh = false;
    SurfaceMesh mesh;
  };

  // --parts ranks: this rank's points (Simulation::my_part) and their order keys.
  struct PartSnapshot {
    explicit PartSnapshot(PointFields p) : points(std::move(p)) {}
    PointSnapshot points;
    std::vector<std::uint64_t> order;
  };
  std::shared_ptr<PartSnapshot> part_snapshot() {
    PointFields p = sim_.my_point_fields(scene_.output.attributes, space_);
    p.material_names = scene_.material_names;
    Simulation::RankPart rp = sim_.my_part();
    std::shared_ptr<PartSnapshot> s;
    if (rp.all) {
      s = std::make_shared<PartSnapshot>(std::move(p));
    } else {  // the owned rows of a set every rank holds whole
      std::vector<Vec3> x, v;
      std::vector<std::int32_t> material, id;
      PointFields q;
      q.n = rp.rows.size();
      q.material_names = p.material_names;
      for (const PointAttribute& a : p.attributes) q.attributes.push_back({a.name, a.type, {}, {}});
      for (std::uint32_t i : rp.rows) {
        x.push_back(p.x[i]), v.push_back(p.v[i]);
        material.push_back(p.material[i]), id.push_back(p.id[i]);
        for (std::size_t k = 0; k < p.attributes.size(); ++k) {
          const PointAttribute& a = p.attributes[k];
          const std::size_t w = std::size_t(a.width());
          if (a.type == PointAttribute::Type::Int)
            q.attributes[k].i.push_back(a.i[i]);
          else
            q.attributes[k].f.insert(q.attributes[k].f.end(), a.f.begin() + std::ptrdiff_t(w * i),
                                     a.f.begin() + std::ptrdiff_t(w * i + w));
        }
      }
      q.x = x.data(), q.v = v.data(), q.material = material.data(), q.id = id.data();
      s = std::make_shared<PartSnapshot>(std::move(q));  // copies x, v, material, id
    }
    s->order = std::move(rp.order);
    return s;
  }
  // This rank's part of frame f: its point files and the exact points (.pts) merge joins.
  void write_part(int f, const PartSnapshot& s) {
    if (delay_ms_ > 0 && !writes_files()) ::usleep(useconds_t(delay_ms_) * 1000);
    const auto t0 = std::chrono::steady_clock::now();
    char base[64];
    std::snprintf(base, sizeof base, "frame_%04d.r%03d.", f, dist::Comm::world().rank());
    const PointFields& p = s.points.fields;
    std::vector<std::string> names;
    if (scene_.output.ply) {
      names.push_back(std::string(base) + "ply");
      write_ply_points(rs_.out_dir + "/" + names.back(), p);
    }
    if (scene_.output.vdb_points) {
      names.push_back(std::string(base) + "vdb");
      write_vdb_points(rs_.out_dir + "/" + names.back(), p, sim_.point_voxel_size(),
                       scene_.output.vdb_precision, writer_space_);
    }
    names.push_back(std::string(base) + "pts");
    write_points_part(rs_.out_dir + "/" + names.back(), p, s.order);
    pending_files_.clear();
    for (const std::string& n : names) {
      pending_files_.push_back(part_file_record(rs_.out_dir, n));
      bytes_ += double(pending_files_.back().bytes);
    }
    pending_particles_ = p.n;
    written_s_ += seconds_since(t0);
    if (!writes_files()) ++frames_;
  }
  void drain() {
    const auto t0 = std::chrono::steady_clock::now();
    worker_.wait();
    waited_ += seconds_since(t0);
  }
  // --parts ranks, collective: the pending frame's part lists gathered to rank 0, which writes
  // the manifest (the frame's commit point) and removes parts a run on more ranks left there.
  void commit() {
    if (!parts_) return;
    drain();
    if (pending_.frame < 0) return;
    const dist::Comm& comm = dist::Comm::world();
    const std::string mine = encode_part_files(pending_particles_, pending_files_);
    std::vector<std::size_t> sizes;
    const std::vector<char> all = comm.gather(std::vector<char>(mine.begin(), mine.end()), &sizes);
    const int f = pending_.frame;
    if (comm.root()) {
      FrameManifest m;
      m.frame = f;
      m.time = pending_.time;
      m.ranks = comm.size();
      m.voxel_size = sim_.point_voxel_size();
      m.vdb_precision = scene_.output.vdb_precision;
      m.ply = scene_.output.ply;
      m.vdb = scene_.output.vdb_points;
      m.material_names = scene_.material_names;
      std::size_t at = 0;
      for (int r = 0; r < comm.size(); ++r) {
        std::uint64_t n = 0;
        std::vector<PartFile> files;
        decode_part_files(std::string(all.data() + at, sizes[std::size_t(r)]), n, files);
        at += sizes[std::size_t(r)];
        m.particles.push_back(n);
        m.files.push_back(std::move(files));
      }
      write_frame_manifest(rs_.out_dir, m);
      for (int r = comm.size();; ++r) {  // parts of an earlier run on more ranks
        bool any = false;
        for (const char* ext : {"ply", "vdb", "pts"}) {
          char name[64];
          std::snprintf(name, sizeof name, "/frame_%04d.r%03d.%s", f, r, ext);
          std::error_code ec;
          any = std::filesystem::remove(rs_.out_dir + name, ec) || any;
        }
        if (!any) break;
      }
    }
    pending_ = {};
  }

  // Frame f's files from its snapshot (on the worker's thread when asynchronous).
  void write_snapshot(int f, const Snapshot& s) {
    if (delay_ms_ > 0) ::usleep(useconds_t(delay_ms_) * 1000);
    const auto t0 = std::chrono::steady_clock::now();
    const PointFields& p = s.points.fields;
    const OutputSpec& out = scene_.output;
    std::vector<std::string> paths;
    if (rs_.preview) {
      paths.push_back(numbered(rs_.out_dir, "preview_%04d", f, "png"));
      write_png(paths.back(),
                render_points(p.n, p.x, p.v, p.material,
                              s.preview_scalar.empty() ? nullptr : s.preview_scalar.data(), camera_,
                              splat_, scene_.preview.width, scene_.preview.height,
                              scene_.preview.color_by, floor_y_));
    }
    if (!parts_)  // --parts ranks: every rank writes its own part (write_part)
      for (std::string& path :
           write_points(numbered(rs_.out_dir, "frame_%04d", f, ""), p, writer_space_))
        paths.push_back(std::move(path));
    if (out.surfacing.enabled) {  // surfacing_NNNN.vdb (+ .obj / .ply): io/surfacing.hpp
      std::string base = numbered(rs_.out_dir, "surfacing_%04d", f, "");
      base.pop_back();  // the "." before the (empty) extension
      write_surfacing(base, p, spacing_, out.surfacing, writer_space_);
      for (const char* ext : {".vdb", ".obj", ".ply"}) paths.push_back(base + ext);
    }
    if (s.grid) {
      paths.push_back(numbered(rs_.out_dir, "frame_%04d", f, "grid.vdb"));
      write_vdb_grid_nodes(paths.back(), *s.grid, writer_space_);
    }
    if (s.has_mesh) {
      const char* what =
          s.mesh.crack.empty() ? "embedded surface mesh" : "surface with crack faces (group crack)";
      if (out.surface_obj) {
        paths.push_back(numbered(rs_.out_dir, sim_.surface_pattern(), f, "obj"));
        write_mesh_obj(paths.back(), s.mesh, what);
      }
      if (out.surface_ply) {
        paths.push_back(numbered(rs_.out_dir, sim_.surface_pattern(), f, "ply"));
        write_mesh_ply(paths.back(), s.mesh, what);
      }
    }
    std::error_code ec;
    if (!parts_)  // a manifest left by an earlier run with --parts ranks no longer applies
      std::filesystem::remove(rs_.out_dir + "/" + frame_manifest_name(f), ec);
    for (const std::string& path : paths) {
      const std::uintmax_t b = std::filesystem::file_size(path, ec);
      if (!ec) bytes_ += double(b);
    }
    written_s_ += seconds_since(t0);
    ++frames_;
  }

  // Whether the method has attribute `name` (the scene reader's check).
  bool has_attribute(const char* name) const { return attribute_available(scene_, name); }

  Simulation& sim_;
  const Scene& scene_;
  const RunSettings& rs_;
  const exec::Space& space_;
  const Camera camera_;
  const double splat_, floor_y_, spacing_;
  const bool parts_;  // --parts ranks
  const bool async_;
  const exec::Space writer_space_;
  // Written by the worker's thread, read after wait() (summary): the worker's mutex orders them.
  double bytes_ = 0, written_s_ = 0;
  int frames_ = 0, delay_ms_ = 0;
  double waited_ = 0;  // the simulation thread's
  // --parts ranks: the frame whose part is written or in flight and has no manifest yet (frame
  // -1: none), and its part's files (set by the worker, read after drain()).
  struct Pending {
    int frame = -1;
    double time = 0;
  } pending_;
  std::uint64_t pending_particles_ = 0;
  std::vector<PartFile> pending_files_;
  exec::BackgroundWorker worker_;  // last: destroyed (joined) first
};

// A per-substep CSV whose second column is a step number: its header and, on resume, the rows
// of the file at `path` whose step is below `limit` (the rest belong to substeps taken again).
std::string rows_before(const std::string& path, const std::string& header, std::uint64_t limit) {
  std::string kept = header;
  std::ifstream in(path);
  std::string line;
  std::getline(in, line);
  while (std::getline(in, line)) {
    const std::size_t comma = line.find(',');
    if (comma != std::string::npos && std::strtoull(line.c_str() + comma + 1, nullptr, 10) < limit)
      kept += line + "\n";
  }
  return kept;
}

// The optional per-substep log (Simulation::substep_log_name): rows appended frame by frame; on
// resume the rows of substeps before the checkpoint are kept.
class SubstepLog {
 public:
  SubstepLog(const Simulation& sim, const Scene& scene, const RunSettings& rs) : sim_(sim) {
    const std::string name = sim.substep_log_name();
    if (name.empty() || !scene.output.diagnostics_csv || !writes_files()) return;
    path_ = rs.out_dir + "/" + name;
    write_file_atomic(path_, sim.step_count() > 0
                                 ? rows_before(path_, sim.substep_log_header(), sim.step_count())
                                 : sim.substep_log_header());
  }
  void add(int frame, Real dt) {
    if (!path_.empty()) rows_ += sim_.substep_log_row(frame, dt);
  }
  void discard() { rows_.clear(); }
  void flush() {
    if (rows_.empty()) return;
    append_to_file(path_, rows_);
    rows_.clear();
  }

 private:
  const Simulation& sim_;
  std::string path_, rows_;
};

// Samples every N substeps (output.every_substeps), N counting the run's substeps: a
// samples.csv row (frame, step = substeps taken, time, dt, the simulation's state columns) and
// the point files samples/points_sNNNNNNNNNN.ply / .vdb. A frame's samples are kept with it: a
// retried or interrupted frame's rows and files are removed with it, and a resumed run first
// removes what lies past its checkpoint (left by a killed process), so it writes them again as
// the uninterrupted run did.
class SampleWriter {
 public:
  SampleWriter(const Simulation& sim, const Scene& scene, const RunSettings& rs,
               const exec::Space& space, const FrameWriter& frames)
      : sim_(sim), space_(space), frames_(frames), every_(scene.output.every_substeps) {
    if (every_ <= 0) return;
    std::string header = "frame,step,time_s,dt_s";
    for (const Column& c : sim.sample(space))
      header += "," + c.name;  // collective when distributed
    header += "\n";
    if (!writes_files()) return;
    dir_ = rs.out_dir + "/samples";
    std::filesystem::create_directories(dir_);
    const std::uint64_t done = sim.step_count();
    for (const auto& e : std::filesystem::directory_iterator(dir_)) {
      const std::string name = e.path().filename().string();
      unsigned long long step = 0;
      if (std::sscanf(name.c_str(), "points_s%llu.", &step) == 1 && step > done)
        std::filesystem::remove(e.path());
    }
    csv_ = rs.out_dir + "/samples.csv";
    write_file_atomic(csv_, done > 0 ? rows_before(csv_, header, done + 1) : header);
  }
  void after_substep(int frame, Real dt) {
    if (every_ <= 0 || sim_.step_count() % std::uint64_t(every_) != 0) return;
    std::vector<Column> cols = {{"frame", double(frame), true},
                                {"step", double(sim_.step_count()), true},
                                {"time_s", sim_.time()},
                                {"dt_s", double(dt)}};
    const std::vector<Column> state = sim_.sample(space_);
    cols.insert(cols.end(), state.begin(), state.end());
    rows_ += csv_row(cols);
    char base[64];
    std::snprintf(base, sizeof base, "/points_s%010llu.", (unsigned long long)sim_.step_count());
    for (std::string& f : frames_.write_points(dir_ + base, frames_.point_fields(), space_))
      written_.push_back(std::move(f));
  }
  void discard() {
    rows_.clear();
    for (const std::string& f : written_) std::filesystem::remove(f);
    written_.clear();
  }
  void flush() {
    if (!rows_.empty() && writes_files()) append_to_file(csv_, rows_);
    rows_.clear();
    written_.clear();
  }

 private:
  const Simulation& sim_;
  const exec::Space& space_;
  const FrameWriter& frames_;
  const long long every_;
  std::string dir_, csv_, rows_;
  std::vector<std::string> written_;
};

// Profiler seconds so far per profile column of the simulation.
std::vector<double> profile_seconds(const Simulation& sim, const exec::Profiler& p,
                                    std::size_t ncols) {
  std::vector<double> s(ncols, 0.0);
  for (const auto& r : p.regions()) {
    const int c = sim.profile_column(r.label);
    if (c >= 0 && std::size_t(c) < ncols) s[std::size_t(c)] += r.seconds;
  }
  return s;
}

// Collective: what the job's communication cost each rank over the run (set-up included), per
// substep, as the mean and the most over the ranks (dist::Comm::traffic); empty on one rank.
// `loop_exchange`: this rank's seconds in exchanges during the frame loop, so that each rank's
// work (the loop minus them) shows whether the ranks wait for uneven work or for messages.
std::string communication_summary(double wall, long long substeps, double loop_exchange) {
  const dist::Comm& comm = dist::Comm::world();
  if (comm.size() == 1) return "";
  const dist::Comm::Traffic t = comm.traffic();
  const std::vector<double> mine = {double(t.bytes), double(t.messages), double(t.calls), t.seconds,
                                    wall - loop_exchange};
  constexpr std::size_t K = 5;
  const std::vector<double> all =
      dist::from_bytes<double>(comm.allgather(dist::as_bytes(mine), nullptr));
  const std::size_t R = std::size_t(comm.size());
  double mean[K] = {0, 0, 0, 0, 0}, most[K] = {0, 0, 0, 0, 0};
  double least = all[4];
  for (std::size_t r = 0; r < R; ++r)
    for (std::size_t k = 0; k < K; ++k) {
      mean[k] += all[K * r + k] / double(R);
      most[k] = std::max(most[k], all[K * r + k]);
      if (k == 4) least = std::min(least, all[K * r + k]);
    }
  const double n = double(std::max(1LL, substeps));
  char line[400];
  std::snprintf(line, sizeof line,
                "amalgam: communication per rank and substep (mean / most of %zu ranks): %.1f / "
                "%.1f kB sent in %.1f / %.1f messages, %.1f / %.1f calls; in exchanges %.3g / "
                "%.3g s of %.3g s (%.1f %% / %.1f %%, waiting for slower ranks included)\n",
                R, mean[0] / n * 1e-3, most[0] / n * 1e-3, mean[1] / n, most[1] / n, mean[2] / n,
                most[2] / n, mean[3], most[3], wall, 100 * mean[3] / wall, 100 * most[3] / wall);
  char work[200];
  std::snprintf(work, sizeof work,
                "amalgam: work per rank (the frame loop minus its exchanges): least %.3g / mean "
                "%.3g / most %.3g s, max/mean %.3f\n",
                least, mean[4], most[4], mean[4] > 0 ? most[4] / mean[4] : 1.0);
  return std::string(line) + work;
}

// Collective: where the set-up went, from the process's start to the frame loop, per phase (the
// profiler's "setup.*" regions; on several ranks the least / most of the ranks, each phase's own
// extremes): `age_at_loop` is the process's age when the loop began (process_age_seconds), so the
// phases plus "other" (what no region covers: option parsing, the colliders, the solver's
// construction) make it up.
std::string setup_summary(const exec::Profiler& profiler, double age_at_loop, double cpu_at_loop) {
  static const char* const kPhases[] = {
      "setup.start",           "setup.mpi_init",  "setup.read_scene",
      "setup.read_checkpoint", "setup.sample",    "setup.slice_ids",
      "setup.particles",       "setup.begin_run", "setup.frame0"};
  constexpr std::size_t K = std::size(kPhases) + 3;  // + other, total, CPU
  std::vector<double> mine(K, 0.0);
  double covered = 0;
  for (std::size_t k = 0; k + 3 < K; ++k) covered += mine[k] = profiler.seconds(kPhases[k]);
  mine[K - 3] = std::max(0.0, age_at_loop - covered);
  mine[K - 2] = age_at_loop;
  mine[K - 1] = cpu_at_loop;
  const dist::Comm& comm = dist::Comm::world();
  const std::vector<double> all =
      comm.size() > 1 ? dist::from_bytes<double>(comm.allgather(dist::as_bytes(mine), nullptr))
                      : mine;
  const std::size_t R = all.size() / K;
  if (age_at_loop < 0) return "";
  auto range = [&](std::size_t k) {
    double lo = all[k], hi = all[k];
    for (std::size_t r = 1; r < R; ++r)
      lo = std::min(lo, all[K * r + k]), hi = std::max(hi, all[K * r + k]);
    char b[64];
    if (R == 1)
      std::snprintf(b, sizeof b, "%.3f", lo);
    else
      std::snprintf(b, sizeof b, "%.3f / %.3f", lo, hi);
    return std::string(b);
  };
  std::string line = "amalgam: set-up, process start to frame loop (s";
  line += R > 1 ? "; least / most of " + std::to_string(R) + " ranks): " : "): ";
  line += range(K - 2) + " (CPU " + range(K - 1) + ") =";
  for (std::size_t k = 0; k + 2 < K; ++k) {
    double hi = 0;
    for (std::size_t r = 0; r < R; ++r) hi = std::max(hi, all[K * r + k]);
    if (hi <= 0) continue;
    line += std::string(" ") + (k + 3 < K ? kPhases[k] + 6 : "other") + " " + range(k) + ",";
  }
  line.back() = '\n';
  return line;
}

}  // namespace

int run_frames(Simulation& sim, const Scene& scene, const RunSettings& rs, const exec::Space& space,
               const exec::Profiler& profiler) {
  const std::string checkpoint_path = rs.out_dir + "/checkpoint.amck";
  const bool tty = isatty(fileno(stdout));
  g_signal = 0;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  const dist::Comm& comm = dist::Comm::world();
  {
    exec::ScopedRegion region(space.profiler(), "setup.begin_run");
    sim.begin_run(space);  // a distributed run splits its work here
  }
  FrameWriter frames(sim, scene, rs, space);
  // Frame 0 is the initial state; a resumed run never rewrites a frame its checkpoint has passed
  // (resuming inside frame 1 used to write frame 0 again from the mid-frame state).
  if (!rs.resumed) {
    exec::ScopedRegion region(space.profiler(), "setup.frame0");
    frames.write(0);
  }

  const std::string csv_path = rs.out_dir + "/diagnostics.csv";
  std::vector<std::string> csv_rows;
  if (rs.first_frame > 1) csv_rows = earlier_rows(csv_path, rs.first_frame);
  SubstepLog steps_log(sim, scene, rs);
  SampleWriter samples(sim, scene, rs, space, frames);

  // Checkpoints: one file written by rank 0 from the gathered state, or (--parts ranks) a part per
  // rank and rank 0's manifest after every part is on disk (io/checkpoint.hpp). Collective.
  std::uint64_t generation = 0;  // of the parts: one more than any part already in out_dir
  if (rs.rank_parts) {
    std::vector<std::uint64_t> g = {comm.root() ? last_checkpoint_generation(rs.out_dir) : 0};
    std::vector<char> b = dist::as_bytes(g);
    comm.broadcast(b);
    generation = dist::from_bytes<std::uint64_t>(b).at(0);
  }
  auto checkpoint = [&](int next_frame, int retries) {
    if (!rs.rank_parts) {
      sim.prepare_checkpoint();
      if (writes_files()) {
        write_checkpoint(checkpoint_path, sim, next_frame, scene.fingerprint, retries);
        remove_stale_checkpoint_parts(rs.out_dir, 0);  // parts of an earlier --parts ranks run
      }
      return;
    }
    sim.prepare_checkpoint_part();
    const CheckpointPartRecord mine = write_checkpoint_part(
        rs.out_dir, ++generation, comm.rank(), sim, next_frame, scene.fingerprint, retries, space);
    // Fault injection (tests/dist_faults_test.sh): "RANK:GEN": MPI rank RANK kills itself once
    // its part of checkpoint generation GEN is on disk, before the manifest names it.
    if (const char* k = std::getenv("AMALGAM_TEST_KILL_IN_CHECKPOINT"))
      if (std::atoi(k) == comm.rank() && std::strchr(k, ':') &&
          std::strtoull(std::strchr(k, ':') + 1, nullptr, 10) == generation)
        std::raise(SIGKILL);
    const std::vector<char> all = comm.gather(
        dist::as_bytes(std::vector<std::uint64_t>{mine.particles, mine.bytes, mine.checksum}),
        nullptr);
    if (!comm.root()) return;
    const std::vector<std::uint64_t> v = dist::from_bytes<std::uint64_t>(all);
    std::vector<CheckpointPartRecord> parts(std::size_t(comm.size()));
    for (std::size_t r = 0; r < parts.size(); ++r)
      parts[r] = {checkpoint_part_name(generation, int(r)), v[3 * r], v[3 * r + 1], v[3 * r + 2]};
    write_checkpoint_manifest(checkpoint_path, generation, parts);  // the commit point
    remove_stale_checkpoint_parts(rs.out_dir, generation);
  };

  // Fault injection for the interrupt tests (tests/interrupt_points_test.sh): act as if SIGINT
  // arrived during the N-th substep this process takes (retried substeps count too).
  const char* inject = std::getenv("AMALGAM_TEST_SIGINT_AT_SUBSTEP");
  const long long sigint_at = inject ? std::atoll(inject) : 0;
  // Fault injection for tests/dist_faults_test.sh: "RANK:N[:kill]": at its N-th substep, MPI rank
  // RANK stops answering (sleeps; the others' --comm-timeout ends the job) or, with ":kill",
  // kills itself with SIGKILL (the launcher ends the job).
  int stall_rank = -1;
  long long stall_at = 0;
  bool stall_kill = false;
  if (const char* s = std::getenv("AMALGAM_TEST_STALL_RANK")) {
    stall_rank = std::atoi(s);
    const char* c = std::strchr(s, ':');
    stall_at = c ? std::atoll(c + 1) : 0;
    stall_kill = std::strstr(s, ":kill") != nullptr;
  }
  long long advanced = 0;
  const Real cfl0 = sim.cfl();
  const std::vector<std::string> profile_names = sim.profile_columns();
  const auto t_start = std::chrono::steady_clock::now();
  const double age_at_loop = process_age_seconds();
  const double cpu_at_loop = process_cpu_seconds();
  const double exchange_start = comm.traffic().seconds;
  const double work0 = sim.work_done();
  long long total_substeps = 0;
  std::vector<double> profile_before = profile_seconds(sim, profiler, profile_names.size());
  double wall_before = 0;
  for (int f = rs.first_frame; f <= scene.frames; ++f) {
    const double t_frame_end = double(f) / scene.fps;
    long long substeps = 0;
    Real dt = 0;
    set_phase("simulating frame " + std::to_string(f) + " of " + scene.file);
    sim.begin_frame();
    {  // for retries, and for a checkpoint on SIGINT/SIGTERM
      exec::ScopedRegion region(space.profiler(), "frame.snapshot");
      sim.save_frame_start();
    }
    // A run resumed inside a retried frame continues that frame at its retry's CFL number.
    const int first_attempt = f == rs.first_frame ? rs.resume_retries : 0;
    if (first_attempt > 0) sim.set_cfl(cfl0 * Real(std::pow(0.5, first_attempt)));
    for (int attempt = first_attempt;; ++attempt) {
      try {
        // Tolerance covers the rounding of dt to Real; it is far below any physical substep.
        while (sim.time() < t_frame_end - 1e-7 / scene.fps) {
          // On several ranks the signal counts once any rank has it, so all stop at this substep.
          const int signalled = comm.size() > 1 ? int(comm.max(std::int64_t(g_signal))) : g_signal;
          if (signalled) {
            // Interrupted: the checkpoint holds the state at the start of this frame and the
            // retries it has had, so the resumed run computes the frame again exactly as the
            // uninterrupted run did (a retry after the interrupt included); frames before it are
            // written and are never written again.
            const int sig = signalled;
            sim.restore_frame_start();
            steps_log.discard();
            samples.discard();
            frames.wait();  // the frame in flight is on disk before the checkpoint claims it
            checkpoint(f, attempt);
            if (tty && !rs.quiet) std::cout << "\n";
            if (comm.root())
              std::cerr << "amalgam: " << (sig == SIGINT ? "SIGINT" : "SIGTERM")
                        << " received: checkpoint written to " << checkpoint_path << " (frame "
                        << f - 1 << " complete; frame " << f
                        << " starts again from t = " << sim.time() << " s); continue with --resume "
                        << checkpoint_path << "\n";
            // Every rank leaves only once rank 0's checkpoint is on disk: a rank returning
            // 128 + sig ends the job (apps/main.cpp), which would otherwise kill rank 0 while it
            // still waits for its frame in flight or writes the checkpoint. (Should rank 0 fail
            // to write it, its own error ends the job and releases the others.)
            if (comm.size() > 1) comm.barrier();
            return 128 + sig;
          }
          // Split what is left of the frame evenly into stable substeps (no sliver at the end).
          const double remaining = t_frame_end - sim.time();
          const double n_left = std::ceil(remaining / double(sim.stable_dt(space)));
          dt = Real(remaining / std::max(1.0, n_left));
          sim.advance(space, dt);
          if (++advanced == sigint_at) g_signal = SIGINT;
          if (advanced == stall_at && comm.rank() == stall_rank) {
            if (stall_kill) std::raise(SIGKILL);
            for (;;) ::sleep(1);
          }
          ++substeps;
          steps_log.add(f, dt);
          samples.after_substep(f, dt);
        }
        // The guard runs on a substep's starting state, so a blow-up in the frame's last substep
        // would otherwise surface in the next frame, whose retries cannot undo it: check the end
        // state here, before the frame is written.
        (void)sim.stable_dt(space);
        break;
      } catch (const SimulationError& e) {
        if (attempt >= rs.max_retries) throw;
        const Real cfl = cfl0 * Real(std::pow(0.5, attempt + 1));
        if (tty && !rs.quiet) std::cout << "\n";
        if (comm.root())
          std::cerr << "amalgam: warning: frame " << f << ": " << e.what()
                    << "\namalgam: retrying frame " << f << " from its start with cfl = " << cfl
                    << " (retry " << attempt + 1 << " of " << rs.max_retries << ")\n";
        sim.restore_frame_start();
        sim.set_cfl(cfl);
        steps_log.discard();
        samples.discard();
        substeps = 0;
      }
    }
    sim.set_cfl(cfl0);
    total_substeps += substeps;
    steps_log.flush();
    samples.flush();
    const FrameReport report = sim.end_frame(space, substeps);
    const double wall = seconds_since(t_start);
    for (const std::string& w : report.warnings)
      if (comm.root())
        std::cerr << (tty && !rs.quiet ? "\n" : "") << "amalgam: warning: frame " << f << ": " << w
                  << "\n";

    // diagnostics.csv: frame, clock, the simulation's columns, wall time split by kernel group;
    // written before the frame's checkpoint can be committed (a resumed run keeps the rows before
    // its checkpoint's frame). The frame's hand-over to the writer counts in the next row.
    std::vector<Column> cols = {{"frame", double(f), true},
                                {"time_s", sim.time()},
                                {"last_dt_s", double(dt)},
                                {"substeps", double(substeps), true}};
    cols.insert(cols.end(), report.columns.begin(), report.columns.end());
    cols.push_back({"wall_s", wall});
    const std::vector<double> profile_now = profile_seconds(sim, profiler, profile_names.size());
    double grouped = 0;
    for (std::size_t k = 0; k < profile_names.size(); ++k) {
      cols.push_back({profile_names[k], profile_now[k] - profile_before[k]});
      grouped += profile_now[k] - profile_before[k];
    }
    cols.push_back({"other_s", std::max(0.0, (wall - wall_before) - grouped)});
    cols.push_back({"rss_mb", resident_mb()});
    profile_before = profile_now;
    wall_before = wall;
    csv_rows.push_back(csv_row(cols));
    if (scene.output.diagnostics_csv && writes_files()) {
      std::string csv = csv_header(cols);
      for (const auto& r : csv_rows) csv += r;
      write_file_atomic(csv_path, csv);
    }
    const bool checkpoint_now =
        (rs.checkpoint_every > 0 && f % rs.checkpoint_every == 0) || f == scene.frames;
    // The single-file checkpoint of frame f's end is streamed to a temporary file now and
    // renamed into place by the output writer after frame f's files (FrameWriter): the
    // simulation does not wait for the frame in flight.
    std::shared_ptr<TempFile> staged;
    if (checkpoint_now && !rs.rank_parts) {
      exec::ScopedRegion region(space.profiler(), "frame.checkpoint");
      sim.prepare_checkpoint();  // collective: the particles gathered to rank 0
      try {
        if (writes_files())
          staged = stage_checkpoint(checkpoint_path, sim, f + 1, scene.fingerprint);
      } catch (const InputError&) {
        frames.wait();  // a frame's write error first: it is the cause (a full disk, say)
        throw;
      }
    }
    std::function<void()> commit_checkpoint;
    if (staged)
      commit_checkpoint = [staged, &rs] {
        ::futimens(staged->fd(), nullptr);  // its time: after the frames it claims
        staged->commit();
        remove_stale_checkpoint_parts(rs.out_dir, 0);  // parts of an earlier --parts ranks run
      };
    frames.write(f, std::move(commit_checkpoint));
    if (checkpoint_now && rs.rank_parts) {
      exec::ScopedRegion region(space.profiler(), "frame.checkpoint");
      frames.wait();  // frames up to f are on disk before the checkpoint claims them
      checkpoint(f + 1, 0);
    }
    if (!rs.quiet) {
      const int done = f - rs.first_frame + 1;
      const double eta = wall / done * (scene.frames - f);
      const double rate = (sim.work_done() - work0) / std::max(wall, 1e-9);
      char line[400];
      std::snprintf(
          line, sizeof line,
          "frame %d/%d  t=%.4fs  substeps=%lld  dt=%.2e  KE=%.4g J  max|v|=%.3g m/s%s%s  %.2fM %s/s  "
          "elapsed %s  ETA %s",
          f, scene.frames, sim.time(), substeps, double(dt), report.kinetic, report.max_speed,
          report.progress.empty() ? "" : "  ", report.progress.c_str(), rate * 1e-6,
          sim.work_unit(), format_seconds(wall).c_str(), format_seconds(eta).c_str());
      if (tty)
        std::cout << "\r" << line << "\033[K" << std::flush;
      else
        std::cout << line << "\n";
    }
  }
  frames.wait();
  const double wall = seconds_since(t_start);
  const std::string summary =
      sim.run_summary(wall) + frames.summary() +
      communication_summary(wall, total_substeps, comm.traffic().seconds - exchange_start) +
      setup_summary(profiler, age_at_loop, cpu_at_loop);
  if (!rs.quiet) {
    if (tty) std::cout << "\n";
    std::cout << "amalgam: done: " << scene.frames - rs.first_frame + 1 << " frames, "
              << total_substeps << " substeps in " << format_seconds(wall) << " (" << wall
              << " s), " << (sim.work_done() - work0) / wall * 1e-6 << "M " << sim.work_unit()
              << "/s\n"
              << "amalgam: per-kernel time:\n"
              << profiler.report(wall) << summary;
  }
  // Diagnosis of distributed runs: every other rank's per-kernel table too, after rank 0's.
  if (comm.size() > 1 && !comm.root() && std::getenv("AMALGAM_RANK_PROFILE"))
    std::cout << "amalgam: rank " << comm.rank() << " per-kernel time:\n" << profiler.report(wall);
  return kOk;
}

}  // namespace amalgam::cli
