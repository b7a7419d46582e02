// Peridynamics peer benchmark (docs/benchmarks.md "Peridynamics: LAMMPS peer"): the same bar as
// bench/pd_peer.py gives LAMMPS (pair_style peri/lps): nx x ny x nz particles on a simple-cubic
// lattice of spacing lc, horizon 3.015 lc, K and G of glass, density 2200. The first three layers
// start at v0 along x; the wave's arrival at the far end is the first time the mean x velocity of
// the last layer exceeds 10 % of v0. Prints one key = value per line, which the script parses:
//   arrival_s, steps, dt_s, bonds (directed), seconds_per_step (median of --repeats timed blocks
//   of the run after the arrival), bond_updates_per_s.
//
// amalgam_pd_wave --nx 100 --ny 10 --nz 10 --dt 5e-7 --backend openmp --threads 2
//                 [--form paper|lps] [--correction 0|1] [--steps N] [--timing-steps M --repeats R [--profile]]
//                 [--simd baseline|avx2|avx512|auto]
// With --timing-steps it also prints cpu_seconds_per_step (the process's CPU time over the timed
// steps, every thread's: less distorted than wall time by other processes on a shared machine).
// --simd-paths baseline,avx2,avx512: the timed blocks alternate the paths in one process (each
// repeat runs every path once, the first path rotating), on the same block, and print per path
// seconds_per_step[P] and cpu_seconds_per_step[P] (medians over the repeats) and ratio[P] (the
// median over repeats of that repeat's first path's time over P's).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/exec/simd.hpp"
#include "solvers/pd_solver.hpp"

using namespace amalgam;

namespace {

struct Options {
  int nx = 100, ny = 10, nz = 10;
  double lc = 0.01, dt = 5e-7, v0 = 1.0;
  std::string backend = "serial", form = "paper", simd, simd_paths;
  int threads = 1, steps = 0, timing_steps = 0, repeats = 3;
  bool correction = true;
  bool profile = false;  // --profile: per-region times of the timed steps
};

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> const char* {
      if (i + 1 >= argc) throw std::invalid_argument("missing value after " + a);
      return argv[++i];
    };
    if (a == "--nx")
      o.nx = std::atoi(next());
    else if (a == "--ny")
      o.ny = std::atoi(next());
    else if (a == "--nz")
      o.nz = std::atoi(next());
    else if (a == "--lc")
      o.lc = std::atof(next());
    else if (a == "--dt")
      o.dt = std::atof(next());
    else if (a == "--v0")
      o.v0 = std::atof(next());
    else if (a == "--backend")
      o.backend = next();
    else if (a == "--threads")
      o.threads = std::atoi(next());
    else if (a == "--form")
      o.form = next();
    else if (a == "--correction")
      o.correction = std::atoi(next()) != 0;
    else if (a == "--steps")
      o.steps = std::atoi(next());
    else if (a == "--timing-steps")
      o.timing_steps = std::atoi(next());
    else if (a == "--repeats")
      o.repeats = std::atoi(next());
    else if (a == "--profile")
      o.profile = true;
    else if (a == "--simd")
      o.simd = next();
    else if (a == "--simd-paths")
      o.simd_paths = next();
    else
      throw std::invalid_argument("unknown option " + a);
  }
  if (o.nx < 8 || o.ny < 1 || o.nz < 1 || !(o.dt > 0) || o.threads < 1 || o.repeats < 1)
    throw std::invalid_argument("bad sizes, dt, threads or repeats");
  if (o.form != "paper" && o.form != "lps") throw std::invalid_argument("--form is paper or lps");
  return o;
}

}  // namespace

int main(int argc, char** argv) try {
  const Options o = parse(argc, argv);
  if (!o.simd.empty()) exec::set_simd_path(exec::parse_simd_path(o.simd));
  const exec::Space space(exec::parse_backend(o.backend), o.threads);
  PdSettings s;
  s.spacing = Real(o.lc);
  s.horizon = Real(3.015 * o.lc);
  s.deviatoric = o.form == "paper" ? PdDeviatoric::Paper : PdDeviatoric::Lps;
  s.surface_correction = o.correction;
  s.partial_volume = true;
  s.fracture = false;
  s.contact = false;
  s.gravity = Vec3::Zero();
  PdMaterial glass;
  glass.bulk = Real(48e9);
  glass.shear = Real(28.8e9);
  glass.density = 2200;
  PdSolver solver(s, {glass});
  std::vector<Vec3> x;
  for (int i = 0; i < o.nx; ++i)
    for (int j = 0; j < o.ny; ++j)
      for (int k = 0; k < o.nz; ++k)
        x.push_back((o.lc * Vec3d(i, j, k)).cast<Real>());  // LAMMPS's sc sites
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(o.lc * o.lc * o.lc));
  const auto t_setup = std::chrono::steady_clock::now();
  solver.initialize(space);
  const double setup_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t_setup).count();
  Vec3* v = solver.particles().vec3(solver.attributes().v);
  std::vector<std::size_t> far;
  for (std::size_t i = 0; i < x.size(); ++i) {
    if (double(x[i][0]) < 2.5 * o.lc) v[i] = Vec3(Real(o.v0), 0, 0);
    if (double(x[i][0]) > (o.nx - 1.5) * o.lc) far.push_back(i);
  }
  const Real dt = Real(o.dt);
  const int max_steps = o.steps > 0 ? o.steps : int(4.0 * o.nx * o.lc / 5000.0 / o.dt) + 10;
  double arrival = -1;
  int step = 0;
  for (; step < max_steps && arrival < 0; ++step) {
    solver.step(space, dt);
    double vx = 0;
    for (std::size_t i : far) vx += double(v[i][0]);
    vx /= double(far.size());
    if (vx > 0.1 * o.v0) arrival = double(step + 1) * o.dt;
  }
  std::printf(
      "simd = %s\nparticles = %zu\nbonds = %zu\ndt_s = %.6g\nsetup_s = %.4f\narrival_s = "
      "%.6g\nsteps = %d\n",
      exec::simd_path_name(exec::simd_path()), x.size(), solver.bonds().size(), o.dt, setup_s,
      arrival, step);
  if (o.timing_steps > 0 && !o.simd_paths.empty()) {
    std::vector<exec::SimdPath> paths;
    for (std::size_t b = 0; b <= o.simd_paths.size();) {
      std::size_t e = o.simd_paths.find(',', b);
      if (e == std::string::npos) e = o.simd_paths.size();
      paths.push_back(exec::parse_simd_path(o.simd_paths.substr(b, e - b)));
      b = e + 1;
    }
    const std::size_t np = paths.size();
    std::vector<std::vector<double>> wall(np), cpu(np), ratio(np);
    for (int r = 0; r < o.repeats; ++r) {
      for (std::size_t q = 0; q < np; ++q) {
        const std::size_t i = (q + std::size_t(r)) % np;
        exec::set_simd_path(paths[i]);
        const std::clock_t c0 = std::clock();
        const auto t0 = std::chrono::steady_clock::now();
        for (int k = 0; k < o.timing_steps; ++k) solver.step(space, dt);
        wall[i].push_back(
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() /
            o.timing_steps);
        cpu[i].push_back(double(std::clock() - c0) / CLOCKS_PER_SEC / o.timing_steps);
      }
      for (std::size_t i = 0; i < np; ++i) ratio[i].push_back(wall[0].back() / wall[i].back());
    }
    auto median = [](std::vector<double> v) {
      std::sort(v.begin(), v.end());
      return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
    };
    for (std::size_t i = 0; i < np; ++i) {
      const char* name = exec::simd_path_name(paths[i]);
      std::printf(
          "seconds_per_step[%s] = %.6g\ncpu_seconds_per_step[%s] = %.6g\nratio[%s] = %.4f\n"
          "bond_updates_per_s[%s] = %.4g\n",
          name, median(wall[i]), name, median(cpu[i]), name, median(ratio[i]), name,
          double(solver.bonds().size()) / median(wall[i]));
    }
  } else if (o.timing_steps > 0) {
    exec::Profiler profiler;  // --profile: per-region times of the timed steps
    exec::Space timed = space;
    if (o.profile) timed.set_profiler(&profiler);
    std::vector<double> per_step;
    const std::clock_t c0 = std::clock();
    for (int r = 0; r < o.repeats; ++r) {
      const auto t0 = std::chrono::steady_clock::now();
      for (int k = 0; k < o.timing_steps; ++k) solver.step(timed, dt);
      per_step.push_back(
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() /
          o.timing_steps);
    }
    const double cpu = double(std::clock() - c0) / CLOCKS_PER_SEC / (o.repeats * o.timing_steps);
    std::sort(per_step.begin(), per_step.end());
    const double med = per_step[per_step.size() / 2];
    std::printf(
        "seconds_per_step = %.6g\nseconds_per_step_min = %.6g\nseconds_per_step_max = %.6g\n"
        "bond_updates_per_s = %.4g\ncpu_seconds_per_step = %.6g\n",
        med, per_step.front(), per_step.back(), double(solver.bonds().size()) / med, cpu);
    if (o.profile) std::printf("%s", profiler.report().c_str());
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "amalgam_pd_wave: %s\n", e.what());
  return 2;
}
