// `amalgam run` and `amalgam validate`.
#include <unistd.h>

#include <array>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "apps/commands.hpp"
#include "apps/frame_loop.hpp"
#include "core/dist/comm.hpp"
#include "core/errors.hpp"
#include "core/exec/cpus.hpp"
#include "core/exec/exec.hpp"
#include "io/checkpoint.hpp"
#include "io/scene.hpp"
#include "io/files.hpp"
#include "solvers/estimate.hpp"
#include "solvers/factory.hpp"

namespace amalgam::cli {

namespace {

const char* kRunHelp =
    "usage: amalgam run SCENE.json [--backend serial|openmp|tbb|threads|kokkos] [--threads N] [--out "
    "DIR]\n"
    "                  [--frames N] [--checkpoint-every N] [--resume CHECKPOINT] [--retries N]\n"
    "                  [--preview] [--quiet] [--force] [--sync-output]\n"
    "                  [--parts single|ranks] [--comm-timeout SECONDS]\n"
    "Simulates SCENE and writes DIR/frame_NNNN.ply and DIR/frame_NNNN.vdb (VDB points) with\n"
    "position, velocity, id and the scene's output.attributes per particle (VDB points compact\n"
    "unless output.vdb_points is \"full\"),\n"
    "DIR/diagnostics.csv (energies, momentum, max speed, substeps per frame) and\n"
    "DIR/checkpoint.amck (every N frames, at the last frame, and on SIGINT/SIGTERM).\n"
    "--retries N (default 3): when the stability guard trips, the frame is restarted from its\n"
    "beginning with the CFL number halved, up to N times, before the run stops with exit 1.\n"
    "Before set-up, the run's particles, memory and substeps are estimated from the scene; a\n"
    "scene needing more memory than is available, over 1e6 substeps per frame or over 1e9 in\n"
    "all is refused (exit 3) unless --force.\n"
    "--preview also renders DIR/preview_NNNN.png per frame (point splats; camera from the\n"
    "scene's \"preview\" block or fitted to the objects).\n"
    "Frames are written by a background thread while the next frame simulates (one frame in\n"
    "flight; its OpenVDB work on that one thread); --sync-output writes them on the simulation's\n"
    "threads instead, which wait (the files are the same bytes).\n"
    "--parts ranks (MPI runs): each rank writes its own part of every frame\n"
    "(frame_NNNN.rRRR.ply/.vdb/.pts) and of every checkpoint, and rank 0 a manifest last\n"
    "(frame_NNNN.manifest.json, checkpoint.amck); `amalgam merge DIR` joins them into the files\n"
    "one process writes. Default single: rank 0 gathers the particles and writes one file.\n"
    "--comm-timeout SECONDS (default 600): a rank that waits longer for the others in one MPI\n"
    "exchange names it and the ranks it did not hear from, and ends the job (exit 1).\n"
    "--resume continues a run from a checkpoint of the same scene, bitwise identically to an\n"
    "uninterrupted run (frames may be raised to extend it).\n"
    "Defaults: --backend tbb for MPM scenes, openmp for peridynamics (the faster of the two for\n"
    "each, docs/benchmarks.md; threads: plain std::threads, for ThreadSanitizer runs), --threads =\n"
    "the CPUs this process may run on (its affinity: all cores, or a rank's share under mpirun),\n"
    "--out = the scene's output.directory,\n"
    "--frames = the scene's simulation.frames, --checkpoint-every = output.checkpoint_every.\n";

}  // namespace

// Rows of an existing diagnostics.csv for frames before `first_frame` (kept on resume).
std::vector<std::string> earlier_rows(const std::string& csv, int first_frame) {
  std::vector<std::string> rows;
  std::ifstream in(csv);
  std::string line;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    const int f = std::atoi(line.c_str());
    if (f >= 1 && f < first_frame) rows.push_back(line + "\n");
  }
  return rows;
}

volatile std::sig_atomic_t g_signal = 0;
extern "C" void on_signal(int sig) {
  g_signal = sig;
}

// During set-up (reading, sampling, voxelising, baking) nothing has been written and there is no
// state worth keeping: a signal ends the process at once, with a message (async-signal-safe).
extern "C" void on_signal_during_setup(int sig) {
  const char msg[] = "\namalgam: interrupted during set-up: no frame or checkpoint was written\n";
  (void)!::write(2, msg, sizeof msg - 1);
  ::_exit(128 + sig);
}

std::string format_seconds(double s) {
  char buf[64];
  if (s < 0 || !std::isfinite(s)) return "?";
  if (s < 60)
    std::snprintf(buf, sizeof buf, "%.0fs", s);
  else if (s < 3600)
    std::snprintf(buf, sizeof buf, "%dm%02ds", int(s) / 60, int(s) % 60);
  else
    std::snprintf(buf, sizeof buf, "%dh%02dm", int(s) / 3600, (int(s) % 3600) / 60);
  return buf;
}

namespace {

// The run's cost from the scene alone (solvers/estimate.hpp), errors naming the scene file.
RunEstimate estimate_of(const Scene& scene) {
  try {
    const auto& a = scene.output.attributes;
    return estimate_run(scene, std::find(a.begin(), a.end(), "rest") != a.end(),
                        dist::Comm::world().size());
  } catch (const InputError& e) {
    throw InputError(scene.file + ": " + e.what());
  }
}

// The default backend is the one measured fastest for the method on the reference machine
// (docs/benchmarks.md, "All four scenes"): TBB for MPM (its idle workers leave the cores to the
// output thread; OpenMP's spin at every pass's end), OpenMP for peridynamics. Every backend gives
// the same bits.
exec::Backend default_backend(Method m) {
  return m == Method::Peridynamics ? exec::Backend::OpenMP : exec::Backend::TBB;
}

// --backend when given (a usage error before the scene is read), else none.
std::optional<exec::Backend> chosen_backend(const Options& o) {
  if (const auto* s = o.get("--backend")) return exec::parse_backend(*s);
  return std::nullopt;
}

exec::Space make_space(const Options& o, exec::Backend b, exec::Profiler* prof) {
  const int usable = exec::usable_threads();
  int threads = usable;
  if (const auto* s = o.get("--threads")) threads = parse_int("--threads", *s, 1, 4096);
  // More threads than the CPUs this process may use (e.g. a rank that mpirun bound to one core,
  // its default for up to 2 ranks) share those CPUs: say so, with the launch that fixes it.
  if (threads > usable && b != exec::Backend::Serial) {
    const dist::Comm& comm = dist::Comm::world();
    std::ostringstream w;  // one write, so the ranks' lines do not interleave
    w << "amalgam: warning: " << threads << " threads but "
      << (comm.size() > 1 ? "MPI rank " + std::to_string(comm.rank()) : "this process")
      << " may run on " << usable << " CPU" << (usable == 1 ? "" : "s")
      << " (its affinity mask); the threads will share " << (usable == 1 ? "it" : "them")
      << (comm.size() > 1 ? ". Start the ranks with `mpirun --map-by slot:PE=" +
                                std::to_string(threads) + "` or `--bind-to none`"
                          : "")
      << "\n";
    const std::string line = w.str();
    std::fwrite(line.data(), 1, line.size(), stderr);
  }
  return exec::Space(b, threads, prof);
}

}  // namespace

int run_command(const std::vector<std::string>& args) {
  Options o;
  try {
    o = parse_options(args,
                      {"--backend", "--threads", "--out", "--frames", "--checkpoint-every",
                       "--resume", "--retries", "--comm-timeout", "--parts"},
                      {"--quiet", "--help", "--preview", "--force", "--sync-output"});
    if (o.flag("--help")) {
      std::cout << kRunHelp;
      return kOk;
    }
    if (o.positional.size() != 1) throw std::invalid_argument("expected exactly one scene file");
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam run: " << printable(e.what()) << "\n" << kRunHelp;
    return kUsage;
  }
  // The set-up's phases are profiler regions "setup.*" (the run's set-up summary, frame_loop.cpp):
  // the process's start up to main (dynamic loading) and MPI's initialisation first.
  exec::Profiler profiler;
  if (g_age_at_main >= 0) profiler.add("setup.start", g_age_at_main);
  if (dist::Comm::world().size() > 1)
    profiler.add("setup.mpi_init", dist::Comm::world().init_seconds());
  std::signal(SIGINT, on_signal_during_setup);
  std::signal(SIGTERM, on_signal_during_setup);
  try {
    const std::optional<exec::Backend> backend = chosen_backend(o);
    set_phase("reading scene file " + o.positional[0]);
    const auto t_read = std::chrono::steady_clock::now();
    Scene scene = load_scene(o.positional[0]);
    const exec::Space space =
        make_space(o, backend.value_or(default_backend(scene.method)), &profiler);
    if (const auto* f = o.get("--frames")) scene.frames = parse_int("--frames", *f, 1, kMaxFrames);
    RunSettings rs;
    rs.out_dir = o.get("--out") ? *o.get("--out") : scene.output.directory;
    rs.quiet = o.flag("--quiet") || !dist::Comm::world().root();  // rank 0 speaks for a job
    // Distributed runs (issue 28): peridynamics splits its bonds across the ranks
    // (solvers/pd_distributed.cpp), explicit MPM its leaves and particles
    // (solvers/mpm_distributed.cpp); what is not distributed yet is refused by begin_run.
    if (const auto* t = o.get("--comm-timeout"))
      dist::Comm::world().set_timeout(double(parse_int("--comm-timeout", *t, 1, 1000000000)));
    if (const auto* p = o.get("--parts")) {
      if (*p != "single" && *p != "ranks")
        throw std::invalid_argument("--parts: expected single or ranks, got '" + *p + "'");
      rs.rank_parts = *p == "ranks";
    }
    rs.preview = o.flag("--preview");
    rs.sync_output = o.flag("--sync-output");
    rs.checkpoint_every = scene.output.checkpoint_every;
    if (const auto* c = o.get("--checkpoint-every"))
      rs.checkpoint_every = parse_int("--checkpoint-every", *c, 0, 1000000);
    rs.max_retries =
        o.get("--retries") ? parse_int("--retries", *o.get("--retries"), 0, kMaxRetries) : 3;
    // What the run will cost, before anything is allocated: a scene past the machine's memory
    // or the substep limits is refused unless --force.
    set_phase("estimating scene " + scene.file);
    const RunEstimate estimate = estimate_of(scene);
    profiler.add("setup.read_scene",
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t_read).count());
    if (!rs.quiet) std::cout << "amalgam: expected: " << describe(estimate) << "\n";
    // On several ranks the memory is this machine's ranks' share: explicit MPM splits its state
    // and samples its set-up in slices (solvers/factory.cpp); peridynamics holds every
    // particle's per-particle data on every rank but builds only its own particles' bond rows
    // (solvers/pd_distributed.cpp: the bonds split across the ranks); particle domains set up the
    // whole scene on every rank.
    RunEstimate here = estimate;
    if (const dist::Comm& comm = dist::Comm::world(); comm.size() > 1) {
      const double mine = double(comm.node_ranks()), all = double(comm.size());
      if (scene.method == Method::Peridynamics)
        here.bytes = mine * (estimate.bytes - estimate.bond_bytes + estimate.bond_bytes / all);
      else
        here.bytes *= scene.mpm.domains.enabled ? mine : mine / all;
    }
    std::string over = over_limits(here, double(available_memory_bytes()));
    if (!over.empty() && here.bytes != estimate.bytes)
      over += " (the share of this machine's " + std::to_string(dist::Comm::world().node_ranks()) +
              " of " + std::to_string(dist::Comm::world().size()) + " ranks)";
    if (!over.empty() && !o.flag("--force"))
      throw InputError(scene.file + ": " + over + " (--force runs it anyway)");
    std::error_code ec;
    std::filesystem::create_directories(rs.out_dir, ec);
    if (ec) throw InputError(rs.out_dir + ": cannot create output directory: " + ec.message());

    const auto t_setup = std::chrono::steady_clock::now();
    set_phase("setting up scene " + scene.file);
    std::unique_ptr<Simulation> sim;
    try {
      sim = make_simulation(scene, space);
    } catch (const InputError& e) {  // set-up's findings name a JSON path: add the file
      throw InputError(e.what()[0] == '/' ? scene.file + ": " + e.what() : e.what());
    }
    // Rest positions (output.attributes "rest") are the set-up's, also when resuming.
    const auto& attrs = scene.output.attributes;
    if (std::find(attrs.begin(), attrs.end(), "rest") != attrs.end()) sim->keep_rest_positions();
    // Fault injection for tests/interrupt_points_test.sh: a SIGINT at the end of set-up.
    if (std::getenv("AMALGAM_TEST_SIGINT_IN_SETUP")) std::raise(SIGINT);
    if (const auto* r = o.get("--resume")) {
      set_phase("reading checkpoint " + *r);
      exec::ScopedRegion region(&profiler, "setup.read_checkpoint");
      const CheckpointState st = read_checkpoint(*r, *sim, scene.fingerprint);
      rs.first_frame = st.next_frame;
      rs.resumed = true;
      rs.resume_retries = std::min(st.retries, rs.max_retries);
      if (rs.first_frame > scene.frames) {
        std::cout << "amalgam: nothing to run: the checkpoint " << printable(*r)
                  << " is past the last frame (" << scene.frames
                  << "); raise --frames to extend the run\n";
        return kOk;
      }
      if (!rs.quiet)
        std::cout << "amalgam: resumed from " << *r << " at t = " << sim->time() << " s, substep "
                  << sim->step_count() << ", frame " << rs.first_frame << "\n";
    }
    const double setup =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t_setup).count();
    if (!rs.quiet)
      std::cout << "amalgam: scene '" << scene.name << "': " << sim->describe() << "; "
                << scene.frames << " frames at " << scene.fps << " fps, backend "
                << space.describe() << ", precision " << real_name() << " (set-up "
                << format_seconds(setup) << ")\n"
                << "amalgam: writing to " << rs.out_dir << "/\n";
    set_phase("running scene " + scene.file);
    return run_frames(*sim, scene, rs, space, profiler);
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << printable(e.what()) << "\n";
    return kBadInput;
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam run: " << printable(e.what()) << "\n";
    return kUsage;
  } catch (const SimulationError& e) {
    std::cerr
        << "amalgam: simulation failed: " << printable(e.what()) << "\n"
        << "amalgam: the last good checkpoint (if any was written) is in the output directory\n";
    return kSimulationFailed;
  }
}

int validate_command(const std::vector<std::string>& args) {
  if (args.size() != 1 || args[0] == "--help") {
    std::cout << "usage: amalgam validate SCENE.json\nChecks a scene file without running it.\n";
    return args.size() == 1 ? kOk : kUsage;
  }
  try {
    const Scene scene = load_scene(args[0]);
    const RunEstimate e = estimate_of(scene);
    const std::string over = over_limits(e, double(available_memory_bytes()));
    if (!over.empty())
      throw InputError(scene.file + ": " + over + " (`amalgam run --force` runs it anyway)");
    std::cout << printable(args[0]) << ": ok: " << scene.objects.size() << " objects, "
              << scene.materials.size() << " materials, " << scene.colliders.size()
              << " colliders, " << scene.frames << " frames; expected: " << describe(e) << "\n";
    return kOk;
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << printable(e.what()) << "\n";
    return kBadInput;
  }
}

}  // namespace amalgam::cli
