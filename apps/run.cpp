// `amalgam run` and `amalgam validate`.
#include <unistd.h>

#include <array>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <stdexcept>

#include "apps/commands.hpp"
#include "core/errors.hpp"
#include "core/exec/exec.hpp"
#include "io/checkpoint.hpp"
#include "io/preview.hpp"
#include "io/scene.hpp"
#include "io/vdb_points.hpp"
#include "io/writers.hpp"

namespace amalgam::cli {

namespace {

const char* kRunHelp =
    "usage: amalgam run SCENE.json [--backend serial|openmp|tbb|threads|kokkos] [--threads N] [--out "
    "DIR]\n"
    "                  [--frames N] [--checkpoint-every N] [--resume CHECKPOINT] [--retries N]\n"
    "                  [--preview] [--quiet]\n"
    "Simulates SCENE and writes DIR/frame_NNNN.ply and DIR/frame_NNNN.vdb (VDB points) with\n"
    "position, velocity, J, material and id per particle,\n"
    "DIR/diagnostics.csv (energies, momentum, max speed, substeps per frame) and\n"
    "DIR/checkpoint.amck (every N frames, at the last frame, and on SIGINT/SIGTERM).\n"
    "--retries N (default 3): when the stability guard trips, the frame is restarted from its\n"
    "beginning with the CFL number halved, up to N times, before the run stops with exit 1.\n"
    "--preview also renders DIR/preview_NNNN.png per frame (point splats; camera from the\n"
    "scene's \"preview\" block or fitted to the objects).\n"
    "--resume continues a run from a checkpoint of the same scene, bitwise identically to an\n"
    "uninterrupted run (frames may be raised to extend it).\n"
    "Defaults: --backend openmp (threads: plain std::threads, for ThreadSanitizer runs), --threads "
    "=\n"
    "all cores, --out = the scene's output.directory,\n"
    "--frames = the scene's simulation.frames, --checkpoint-every = output.checkpoint_every.\n";

// Profiler seconds so far in the groups of the CSV columns: p2g, g2p, sort, grid.
std::array<double, 5> kernel_groups(const exec::Profiler& p) {
  std::array<double, 5> g{};
  for (const auto& r : p.regions()) {
    // Particle domains: particle -> corner -> grid is the P2G side, grid -> corner -> particle
    // (with the corner collisions and the advection) the G2P side.
    if (r.label == "mpm.p2g" || r.label == "domain.p2c" || r.label == "domain.points_to_grid" ||
        r.label == "domain.stress")
      g[0] += r.seconds;
    else if (r.label == "mpm.g2p" || r.label == "domain.grid_to_corners" || r.label == "domain.c2p" ||
             r.label == "domain.collide_corners" || r.label.rfind("domain.advect", 0) == 0)
      g[1] += r.seconds;
    else if (r.label.rfind("bin.", 0) == 0 || r.label == "particles.permute")
      g[2] += r.seconds;
    else if (r.label.rfind("grid.", 0) == 0 || r.label == "mpm.grid_clear" ||
             r.label == "mpm.grid_update")
      g[3] += r.seconds;
    else if (r.label.rfind("implicit.", 0) == 0)
      g[4] += r.seconds;
  }
  return g;
}

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

exec::Space make_space(const Options& o, exec::Profiler* prof) {
  exec::Backend b = exec::Backend::OpenMP;
  if (const auto* s = o.get("--backend")) b = exec::parse_backend(*s);
  int threads = exec::hardware_threads();
  if (const auto* s = o.get("--threads")) threads = parse_int("--threads", *s, 1, 4096);
  return exec::Space(b, threads, prof);
}

}  // namespace

int run_command(const std::vector<std::string>& args) {
  Options o;
  try {
    o = parse_options(args,
                      {"--backend", "--threads", "--out", "--frames", "--checkpoint-every",
                       "--resume", "--retries"},
                      {"--quiet", "--help", "--preview"});
    if (o.flag("--help")) {
      std::cout << kRunHelp;
      return kOk;
    }
    if (o.positional.size() != 1) throw std::invalid_argument("expected exactly one scene file");
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam run: " << e.what() << "\n" << kRunHelp;
    return kUsage;
  }
  exec::Profiler profiler;
  try {
    const exec::Space space = make_space(o, &profiler);
    Scene scene = load_scene(o.positional[0]);
    if (const auto* f = o.get("--frames")) scene.frames = parse_int("--frames", *f, 1, 1000000);
    const std::string out_dir = o.get("--out") ? *o.get("--out") : scene.output.directory;
    const bool quiet = o.flag("--quiet");
    std::error_code ec;
    std::filesystem::create_directories(out_dir, ec);
    if (ec) throw InputError(out_dir + ": cannot create output directory: " + ec.message());
    if (scene.method == Method::Peridynamics)
      return run_peridynamics(scene, o, space, profiler, out_dir);

    int checkpoint_every = scene.output.checkpoint_every;
    if (const auto* c = o.get("--checkpoint-every"))
      checkpoint_every = parse_int("--checkpoint-every", *c, 0, 1000000);
    const std::string checkpoint_path = out_dir + "/checkpoint.amck";

    MpmSolver solver = build_solver(scene);
    int first_frame = 1;
    if (const auto* r = o.get("--resume")) {
      first_frame = read_checkpoint(*r, solver, scene.fingerprint).next_frame;
      if (!quiet)
        std::cout << "amalgam: resumed from " << *r << " at t = " << solver.time() << " s, substep "
                  << solver.step_count() << ", frame " << first_frame << "\n";
    }
    const size_t np = solver.particles().size();
    if (!quiet)
      std::cout << "amalgam: scene '" << scene.name << "': " << np
                << " particles, dx = " << scene.mpm.dx << ", transfer "
                << transfer_name(scene.mpm.transfer) << ", " << scene.frames << " frames at "
                << scene.fps << " fps, backend " << space.describe() << ", precision "
                << real_name() << "\n"
                << "amalgam: writing to " << out_dir << "/\n";
    auto frame_path = [&](int f, const char* ext) {
      char name[64];
      std::snprintf(name, sizeof name, "/frame_%04d.%s", f, ext);
      return out_dir + name;
    };
    const bool preview = o.flag("--preview");
    const Camera camera = preview_camera(scene);
    const double splat = preview_radius(scene), floor_y = preview_floor(scene);
    std::vector<Vec3> surf_vertices;
    std::vector<std::array<std::uint32_t, 3>> surf_triangles;
    std::vector<std::uint8_t> surf_crack;
    auto write_frame = [&](int f) {
      // Enriched MPM: the meshes embedded in the particle domains, deformed (Sec. 4.1).
      if (solver.domains().has_surface() && (scene.output.surface_obj || scene.output.surface_ply)) {
        solver.domains().surface(solver.particles().int32(solver.domain_attributes().corners), surf_vertices,
                                 surf_triangles);
        surf_crack.assign(surf_triangles.size(), 0);
        char name[64];
        for (const char* ext : {"obj", "ply"}) {
          if (!(ext[0] == 'o' ? scene.output.surface_obj : scene.output.surface_ply)) continue;
          std::snprintf(name, sizeof name, "/frame_%04d_surface.%s", f, ext);
          if (ext[0] == 'o') write_surface_obj(out_dir + name, surf_vertices, surf_triangles, surf_crack);
          else write_surface_ply(out_dir + name, surf_vertices, surf_triangles, surf_crack);
        }
      }
      if (preview)
        write_png(frame_path(f, "png").replace(frame_path(f, "png").rfind("frame_"), 6, "preview_"),
                  render_particles(solver.particles(), solver.attributes(), camera, splat,
                                   scene.preview.width, scene.preview.height,
                                   scene.preview.color_by, floor_y));
      if (scene.output.ply)
        write_ply_points(frame_path(f, "ply"), solver.particles(), solver.attributes());
      if (scene.output.vdb_points)
        write_vdb_points(frame_path(f, "vdb"), solver.particles(), solver.attributes(),
                         double(scene.mpm.dx));
      if (scene.output.grid_volumes && f > 0)  // the grid exists once a substep ran
        write_vdb_grid_fields(frame_path(f, "grid.vdb"), solver.grid(), double(scene.mpm.dx));
    };
    if (first_frame == 1) write_frame(0);

    const std::string csv_path = out_dir + "/diagnostics.csv";
    std::vector<std::string> csv_rows;
    if (first_frame > 1) csv_rows = earlier_rows(csv_path, first_frame);
    // Implicit runs: one row per substep (CG iterations, residual), appended frame by frame; on
    // resume the rows of substeps before the checkpoint are kept.
    const std::string steps_path = out_dir + "/implicit_steps.csv";
    const bool step_log = scene.mpm.implicit && scene.output.diagnostics_csv;
    std::string step_rows;
    if (step_log) {
      std::string kept = "frame,step,time_s,dt_s,iterations,relative_residual,converged,minres\n";
      if (solver.step_count() > 0) {
        std::ifstream in(steps_path);
        std::string line;
        std::getline(in, line);
        while (std::getline(in, line)) {
          const size_t comma = line.find(',');
          if (comma != std::string::npos &&
              std::strtoull(line.c_str() + comma + 1, nullptr, 10) < solver.step_count())
            kept += line + "\n";
        }
      }
      write_file_atomic(steps_path, kept);
    }
    auto flush_steps = [&]() {
      if (step_rows.empty()) return;
      std::ofstream app(steps_path, std::ios::app);
      app << step_rows;
      if (!app) throw InputError(steps_path + ": cannot append implicit solver statistics");
      step_rows.clear();
    };
    g_signal = 0;
    std::signal(SIGINT, on_signal);
    std::signal(SIGTERM, on_signal);

    const int max_retries =
        o.get("--retries") ? parse_int("--retries", *o.get("--retries"), 0, 10) : 3;
    const Real cfl0 = scene.mpm.cfl;
    MpmSolver::Snapshot snapshot;
    const bool tty = isatty(fileno(stdout));
    const auto t_start = std::chrono::steady_clock::now();
    long long total_substeps = 0;
    std::array<double, 5> groups_before = kernel_groups(profiler);
    double wall_before = 0;
    double enriched_sum = 0, enriched_max = 0;  // particle domains: enriched particle fraction
    for (int f = first_frame; f <= scene.frames; ++f) {
      const double t_frame_end = double(f) / scene.fps;
      long long substeps = 0;
      Real dt = 0;
      // Adaptive retry: the frame's starting state, restored if the stability guard trips.
      const double t_frame_start = solver.time();
      const std::uint64_t steps_frame_start = solver.step_count();
      if (max_retries > 0) solver.save(snapshot);
      solver.reset_implicit_counters();
      solver.domains().reset_counters();
      for (int attempt = 0;; ++attempt) {
        try {
          // Tolerance covers the rounding of dt to Real; it is far below any physical substep.
          while (solver.time() < t_frame_end - 1e-7 / scene.fps) {
            // Split what is left of the frame evenly into CFL-stable substeps (no sliver at the
            // end).
            const double remaining = t_frame_end - solver.time();
            const double n_left = std::ceil(remaining / double(solver.stable_dt(space)));
            dt = Real(remaining / std::max(1.0, n_left));
            solver.step(space, dt);
            ++substeps;
            if (step_log) {
              const SolveStats& ls = solver.last_solve();
              char row[160];
              std::snprintf(row, sizeof row, "%d,%llu,%.9g,%.9g,%d,%.4g,%d,%d\n", f,
                            (unsigned long long)(solver.step_count() - 1), solver.time(),
                            double(dt), ls.iterations, ls.residual, ls.converged ? 1 : 0,
                            ls.used_minres ? 1 : 0);
              step_rows += row;
            }
            if (g_signal) {  // interrupted: save the exact state mid-frame and stop
              const int sig = g_signal;
              write_checkpoint(checkpoint_path, solver, f, scene.fingerprint);
              flush_steps();
              if (tty && !quiet) std::cout << "\n";
              std::cerr << "amalgam: " << (sig == SIGINT ? "SIGINT" : "SIGTERM")
                        << " received: checkpoint written to " << checkpoint_path
                        << " (t = " << solver.time() << " s, frame " << f
                        << " in progress); continue with --resume " << checkpoint_path << "\n";
              return 128 + sig;
            }
          }
          // The guard runs on a substep's starting state, so a blow-up in the frame's last
          // substep would otherwise surface in the next frame, whose retries cannot undo it:
          // check the end state here, before the frame is written.
          (void)solver.stable_dt(space);
          break;
        } catch (const SimulationError& e) {
          if (attempt >= max_retries) throw;
          const Real cfl = cfl0 * Real(std::pow(0.5, attempt + 1));
          if (tty && !quiet) std::cout << "\n";
          std::cerr << "amalgam: warning: frame " << f << ": " << e.what()
                    << "\namalgam: retrying frame " << f << " from its start with cfl = " << cfl
                    << " (retry " << attempt + 1 << " of " << max_retries << ")\n";
          solver.restore(snapshot);
          solver.restore_clock(t_frame_start, steps_frame_start);
          solver.set_cfl(cfl);
          solver.reset_implicit_counters();
          solver.domains().reset_counters();
          step_rows.clear();
          substeps = 0;
        }
      }
      solver.set_cfl(cfl0);
      total_substeps += substeps;
      flush_steps();
      const MpmDiagnostics d = solver.diagnostics(space);
      write_frame(f);
      const double wall =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();
      DiagnosticsRow row{f, solver.time(), double(dt), wall, substeps, d, np};
      const std::array<double, 5> groups = kernel_groups(profiler);
      row.p2g_s = groups[0] - groups_before[0];
      row.g2p_s = groups[1] - groups_before[1];
      row.sort_s = groups[2] - groups_before[2];
      row.grid_s = groups[3] - groups_before[3];
      row.solve_s = groups[4] - groups_before[4];
      if (scene.mpm.domains.enabled) {
        const DomainCounters& dc = solver.domains().counters();
        row.enriched_fraction = dc.steps ? dc.enriched_fraction_sum / double(dc.steps) : 0.0;
        row.transitional_fraction = dc.steps ? dc.transitional_fraction_sum / double(dc.steps) : 0.0;
        row.max_enriched_fraction = dc.max_enriched_fraction;
        row.enriched_corners = dc.last_enriched_corners;
        enriched_sum += row.enriched_fraction;
        enriched_max = std::max(enriched_max, dc.max_enriched_fraction);
      }
      row.other_s = std::max(0.0, (wall - wall_before) - row.p2g_s - row.g2p_s - row.sort_s -
                                      row.grid_s - row.solve_s);
      const ImplicitCounters& ic = solver.implicit_counters();
      row.cg_iterations = (long long)ic.iterations;
      row.cg_max_iterations = ic.max_iterations;
      row.cg_max_residual = ic.max_residual;
      row.cg_unconverged = (long long)ic.unconverged;
      if (ic.unconverged > 0)
        std::cerr << (tty && !quiet ? "\n" : "") << "amalgam: warning: frame " << f << ": "
                  << ic.unconverged << " implicit solve(s) stopped at max_iterations = "
                  << scene.mpm.solver.max_iterations << " (worst relative residual "
                  << ic.max_residual
                  << "); raise simulation.implicit.max_iterations or lower max_dt\n";
      row.leaves = solver.grid().leaf_count();
      row.active_leaves = solver.grid().active_leaves().size();
      row.rss_mb = resident_mb();
      groups_before = groups;
      wall_before = wall;
      csv_rows.push_back(diagnostics_csv_line(row));
      if (scene.output.diagnostics_csv) {
        std::string csv = diagnostics_csv_header();
        for (const auto& r : csv_rows) csv += r;
        write_file_atomic(csv_path, csv);
      }
      if ((checkpoint_every > 0 && f % checkpoint_every == 0) || f == scene.frames)
        write_checkpoint(checkpoint_path, solver, f + 1, scene.fingerprint);
      if (!quiet) {
        const int done = f - first_frame + 1;
        const double eta = wall / done * (scene.frames - f);
        const double rate = double(np) * double(total_substeps) / std::max(wall, 1e-9);
        char cg[64] = "";
        if (scene.mpm.implicit)
          std::snprintf(cg, sizeof cg, "  CG %.1f it/step",
                        double(row.cg_iterations) / double(std::max(1LL, substeps)));
        char line[320];
        std::snprintf(line, sizeof line,
                      "frame %d/%d  t=%.4fs  substeps=%lld  dt=%.2e  KE=%.4g J  max|v|=%.3g m/s%s  "
                      "%.2fM p-steps/s  "
                      "elapsed %s  ETA %s",
                      f, scene.frames, solver.time(), substeps, double(dt), d.kinetic, d.max_speed,
                      cg, rate * 1e-6, format_seconds(wall).c_str(), format_seconds(eta).c_str());
        if (tty)
          std::cout << "\r" << line << "\033[K" << std::flush;
        else
          std::cout << line << "\n";
      }
    }
    const double wall =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();
    if (!quiet) {
      if (tty) std::cout << "\n";
      std::cout << "amalgam: done: " << scene.frames - first_frame + 1 << " frames, "
                << total_substeps << " substeps in " << format_seconds(wall) << " (" << wall
                << " s), " << double(np) * double(total_substeps) / wall * 1e-6
                << "M particle-substeps/s\n"
                << "amalgam: per-kernel time:\n"
                << profiler.report(wall);
      // A-ULMPM: configuration resets per object and the time they (and the re-binning they
      // force) took, against the whole run.
      const ConfigurationMaps& maps = solver.configuration_maps();
      for (int k = 0; k < maps.object_count(); ++k) {
        const ConfigurationStats& st = maps.stats(k);
        std::cout << "amalgam: object " << k << " ("
                  << configuration_update_name(maps.policy(k).update) << "): " << st.updates
                  << " configuration updates in " << st.steps << " substeps, " << st.update_seconds
                  << " s updating (" << 100.0 * st.update_seconds / wall << " % of the run)\n";
      }
      if (scene.mpm.domains.enabled)
        std::cout << "amalgam: particle domains: " << solver.domains().corner_count() << " corners; enriched "
                  << "particles " << 100.0 * enriched_sum / double(std::max(1, scene.frames - first_frame + 1))
                  << " % on average over frames, at most " << 100.0 * enriched_max << " % in a substep"
                  << (scene.mpm.domains.enrichment ? "" : " (enrichment off)") << "\n";
      if (solver.contact_active())
        std::cout << "amalgam: contact between objects (" << object_contact_mode_name(scene.mpm.contact.mode)
                  << ", friction " << scene.mpm.contact.friction << "): " << solver.contact_nodes()
                  << " reference-node velocity corrections, " << solver.contact_seconds() << " s ("
                  << 100.0 * solver.contact_seconds() / wall << " % of the run)\n";
    }
    return kOk;
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << e.what() << "\n";
    return kBadInput;
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam run: " << e.what() << "\n";
    return kUsage;
  } catch (const SimulationError& e) {
    std::cerr
        << "amalgam: simulation failed: " << e.what() << "\n"
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
    size_t n = 0;
    for (const auto& obj : scene.objects) {
      Real vol = 0;
      n += sample_object(obj, scene.mpm.dx, vol).size();
    }
    std::cout << args[0] << ": ok: " << scene.objects.size() << " objects, " << n << " particles, "
              << scene.materials.size() << " materials, " << scene.colliders.size()
              << " colliders, " << scene.frames << " frames\n";
    return kOk;
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << e.what() << "\n";
    return kBadInput;
  }
}

}  // namespace amalgam::cli
