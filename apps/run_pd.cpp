// `amalgam run` for peridynamics scenes: the same frame loop, outputs and progress as MPM runs,
// with the peridynamic state (damage, dilatation, bonds) in the frames and the diagnostics.
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <sstream>

#include "apps/commands.hpp"
#include "core/errors.hpp"
#include "io/checkpoint.hpp"
#include "io/preview.hpp"
#include "io/scene.hpp"
#include "io/vdb_points.hpp"
#include "io/writers.hpp"

namespace amalgam::cli {

namespace {

PointFields pd_point_fields(const PdSolver& s) {
  const ParticleSet& ps = s.particles();
  const PdAttributes& a = s.attributes();
  PointFields p;
  p.n = ps.size();
  p.x = ps.vec3(a.x);
  p.v = ps.vec3(a.v);
  p.material = ps.int32(a.material);
  p.id = ps.int32(a.id);
  const Real* d = ps.real(a.damage);
  const Real* t = ps.real(a.theta);
  p.primary.emplace_back("damage", std::vector<float>(d, d + p.n));
  p.extra.emplace_back("theta", std::vector<float>(t, t + p.n));
  return p;
}

// Seconds so far in the dilatation (with plasticity), force (with fracture) and contact passes.
struct PdTimes {
  double dilatation = 0, force = 0, contact = 0;
};
PdTimes pd_times(const exec::Profiler& p) {
  PdTimes t;
  for (const auto& r : p.regions()) {
    if (r.label == "pd.dilatation") t.dilatation += r.seconds;
    else if (r.label.rfind("pd.forces", 0) == 0) t.force += r.seconds;  // with pd.forces_rows
    else if (r.label.rfind("pd.contact", 0) == 0 || r.label == "pd.cell_keys") t.contact += r.seconds;
  }
  return t;
}

const char* kCsvHeader =
    "frame,time_s,last_dt_s,substeps,kinetic_J,momentum_x,momentum_y,momentum_z,max_speed_m_s,max_damage,"
    "bonds,intact_bonds,stored_bonds,particles,wall_s,dilatation_s,force_s,contact_s,other_s,rss_mb\n";

}  // namespace

int run_peridynamics(const Scene& scene, const Options& o, const exec::Space& space, exec::Profiler& profiler,
                     const std::string& out_dir) {
  const bool quiet = o.flag("--quiet");
  const bool preview = o.flag("--preview");
  const bool tty = isatty(fileno(stdout));

  const auto t_setup = std::chrono::steady_clock::now();
  PdSolver solver = build_pd_solver(scene);
  solver.initialize(space);
  int checkpoint_every = scene.output.checkpoint_every;
  if (const auto* c = o.get("--checkpoint-every")) checkpoint_every = parse_int("--checkpoint-every", *c, 0, 1000000);
  const std::string checkpoint_path = out_dir + "/checkpoint.amck";
  int first_frame = 1;
  if (const auto* r = o.get("--resume")) {
    first_frame = read_checkpoint(*r, solver, scene.fingerprint).next_frame;
    if (!quiet)
      std::cout << "amalgam: resumed from " << *r << " at t = " << solver.time() << " s, substep "
                << solver.step_count() << ", frame " << first_frame << "\n";
  }
  const std::size_t np = solver.particles().size();
  const PdDiagnostics d0 = solver.diagnostics(space);
  if (!quiet) {
    const double setup = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_setup).count();
    std::cout << "amalgam: scene '" << scene.name << "': peridynamics, " << np << " particles, " << d0.bonds
              << " directed bonds (" << double(d0.bonds) / double(std::max<std::size_t>(1, np))
              << " per particle), spacing " << scene.pd.spacing << " m, horizon " << scene.pd.horizon << " m, deviatoric "
              << pd_deviatoric_name(scene.pd.deviatoric) << ", stable dt " << solver.stable_dt(space) << " s; "
              << scene.frames << " frames at " << scene.fps << " fps, backend " << space.describe() << ", precision "
              << real_name() << " (set-up " << setup << " s)\n"
              << "amalgam: writing to " << out_dir << "/\n";
  }
  auto frame_path = [&](int f, const char* prefix, const char* ext) {
    char name[64];
    std::snprintf(name, sizeof name, "/%s_%04d.%s", prefix, f, ext);
    return out_dir + name;
  };
  const Camera camera = preview_camera(scene);
  const double splat = preview_radius(scene), floor_y = preview_floor(scene);
  auto write_frame = [&](int f) {
    const PointFields p = pd_point_fields(solver);
    if (preview) {
      const float* scalar = scene.preview.color_by == ColorBy::Damage ? p.primary[0].second.data() : nullptr;
      write_png(frame_path(f, "preview", "png"),
                render_points(p.n, p.x, p.v, p.material, scalar, camera, splat, scene.preview.width,
                              scene.preview.height, scene.preview.color_by, floor_y));
    }
    if (scene.output.ply) write_ply_points(frame_path(f, "frame", "ply"), p);
    if (scene.output.vdb_points) write_vdb_points(frame_path(f, "frame", "vdb"), p, double(scene.pd.spacing));
    if (!solver.crack_meshes().empty() && (scene.output.surface_obj || scene.output.surface_ply)) {
      std::vector<Vec3> verts, all_verts;
      std::vector<std::array<std::uint32_t, 3>> tris, all_tris;
      std::vector<std::uint8_t> crack, all_crack;
      for (const PdCrackMesh& m : solver.crack_meshes()) {  // one surface file for all meshes
        m.surface(verts, tris, crack);
        const auto base = std::uint32_t(all_verts.size());
        all_verts.insert(all_verts.end(), verts.begin(), verts.end());
        for (auto t : tris) all_tris.push_back({t[0] + base, t[1] + base, t[2] + base});
        all_crack.insert(all_crack.end(), crack.begin(), crack.end());
      }
      if (scene.output.surface_obj) write_surface_obj(frame_path(f, "surface", "obj"), all_verts, all_tris, all_crack);
      if (scene.output.surface_ply) write_surface_ply(frame_path(f, "surface", "ply"), all_verts, all_tris, all_crack);
    }
  };
  if (first_frame == 1) write_frame(0);

  g_signal = 0;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  const std::string csv_path = out_dir + "/diagnostics.csv";
  std::string csv = kCsvHeader;
  if (first_frame > 1)
    for (const std::string& row : earlier_rows(csv_path, first_frame)) csv += row;
  const auto t_start = std::chrono::steady_clock::now();
  long long total_substeps = 0;
  const std::uint64_t updates0 = solver.bond_updates();
  PdTimes before = pd_times(profiler);
  double wall_before = 0;
  for (int f = first_frame; f <= scene.frames; ++f) {
    const double t_frame_end = double(f) / scene.fps;
    long long substeps = 0;
    Real dt = 0;
    while (solver.time() < t_frame_end - 1e-7 / scene.fps) {
      const double remaining = t_frame_end - solver.time();
      const double n_left = std::ceil(remaining / double(solver.stable_dt(space)));
      dt = Real(remaining / std::max(1.0, n_left));
      solver.step(space, dt);
      ++substeps;
      if (g_signal) {  // interrupted: save the exact state mid-frame and stop
        const int sig = g_signal;
        write_checkpoint(checkpoint_path, solver, f, scene.fingerprint);
        if (tty && !quiet) std::cout << "\n";
        std::cerr << "amalgam: " << (sig == SIGINT ? "SIGINT" : "SIGTERM") << " received: checkpoint written to "
                  << checkpoint_path << " (t = " << solver.time() << " s, frame " << f
                  << " in progress); continue with --resume " << checkpoint_path << "\n";
        return 128 + sig;
      }
    }
    solver.stable_dt(space);  // the stability guard on the frame's final state
    total_substeps += substeps;
    const PdDiagnostics d = solver.diagnostics(space);
    write_frame(f);
    const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();
    const PdTimes now = pd_times(profiler);
    std::ostringstream row;
    row.precision(9);
    const double dil = now.dilatation - before.dilatation, frc = now.force - before.force,
                 con = now.contact - before.contact;
    row << f << ',' << solver.time() << ',' << dt << ',' << substeps << ',' << d.kinetic << ',' << d.momentum[0] << ','
        << d.momentum[1] << ',' << d.momentum[2] << ',' << d.max_speed << ',' << d.max_damage << ',' << d.bonds << ','
        << d.intact << ',' << d.stored << ',' << np << ',' << wall << ',' << dil << ',' << frc << ',' << con << ','
        << std::max(0.0, wall - wall_before - dil - frc - con) << ',' << resident_mb() << '\n';
    csv += row.str();
    before = now;
    wall_before = wall;
    if (scene.output.diagnostics_csv) write_file_atomic(csv_path, csv);
    if ((checkpoint_every > 0 && f % checkpoint_every == 0) || f == scene.frames)
      write_checkpoint(checkpoint_path, solver, f + 1, scene.fingerprint);
    if (!quiet) {
      const double eta = wall / (f - first_frame + 1) * (scene.frames - f);
      const double rate = double(solver.bond_updates() - updates0) / std::max(wall, 1e-9);
      char line[320];
      std::snprintf(line, sizeof line,
                    "frame %d/%d  t=%.4fs  substeps=%lld  dt=%.2e  KE=%.4g J  max|v|=%.3g m/s  broken %.2f%%  "
                    "%.1fM bond-updates/s  elapsed %s  ETA %s",
                    f, scene.frames, solver.time(), substeps, double(dt), d.kinetic, d.max_speed,
                    100.0 * double(d.bonds - d.intact) / double(std::max<std::uint64_t>(1, d.bonds)), rate * 1e-6,
                    format_seconds(wall).c_str(), format_seconds(eta).c_str());
      if (tty) std::cout << "\r" << line << "\033[K" << std::flush;
      else std::cout << line << "\n";
    }
  }
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();
  if (!quiet) {
    if (tty) std::cout << "\n";
    std::cout << "amalgam: done: " << scene.frames - first_frame + 1 << " frames, " << total_substeps << " substeps in "
              << format_seconds(wall) << " (" << wall << " s), "
              << double(solver.bond_updates() - updates0) / wall * 1e-6 << "M directed bond-updates/s (stored bonds; "
              << solver.diagnostics(space).compactions << " compactions)\n"
              << "amalgam: per-kernel time:\n"
              << profiler.report(wall);
  }
  return kOk;
}

}  // namespace amalgam::cli
