// `amalgam bench`: the 1e6-particle sphere on each backend and thread count; one line per run.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <iostream>
#include <sstream>

#include "apps/commands.hpp"
#include "core/exec/exec.hpp"
#include "core/exec/simd.hpp"
#include "core/errors.hpp"
#include "solvers/bench_scene.hpp"
#include "io/scene.hpp"
#include "solvers/mpm_implicit.hpp"

namespace amalgam::cli {

namespace {
const char* kBenchHelp =
    "usage: amalgam bench [--particles N] [--steps S] [--reps R] [--threads LIST] [--backends LIST]\n"
    "                     [--transfer mls|apic|flip|pic] [--transfer-pass fused|two_pass]\n"
    "                     [--sort every_substep|when_needed] [--implicit [--dt SECONDS]]\n"
    "                     [--like SCENE]\n"
    "Runs the standard sphere scene (N particles, default 1e6, dx = 1/128, MLS, fixed corotated)\n"
    "for S timed substeps (default 10) after 2 warm-up substeps, R times (default 3), on each\n"
    "backend (default serial,openmp,tbb) and thread count (default 1,2), and prints one line per\n"
    "run with the median (min, max) particle-substeps per second and per-kernel ns per particle.\n"
    "--transfer-pass fused: one pass over the particles per substep (G2P2G; g2p2g_ns).\n"
    "--sort (default: the scene default, simulation.sort): when_needed re-sorts the two passes'\n"
    "particles only when one leaves its bin's dilated block; resorts= counts the timed substeps\n"
    "that re-sorted, sort_unfit= those that sorted because the blocks exceeded their budget\n"
    "(also printed for the fused pass, which always re-sorts when needed).\n"
    "--implicit: the same sphere stiffened to E = 1e7 with the implicit integrator, dx scaled so\n"
    "particles per cell stay those of 1e6 at 1/128, dt = 10x the explicit CFL step of that\n"
    "resolution (or --dt); adds CG iterations per substep (mean, max) and the solve's share.\n"
    "--like SCENE: the sphere made like an MPM scene's first object: its material (at the\n"
    "object's temperature), particles per cell (dx from them and N), and the scene's transfer,\n"
    "order, transfer_pass and sort (options given beside it win); dt = min(1e-4 s, the scene\n"
    "settings' CFL step at the start). The scene's rate against this one is what the scene adds\n"
    "to its material's cost (docs/benchmarks.md, \"All four scenes\").\n"
    "\n"
    "usage: amalgam bench --report DIR [--scale X] [--reps R] [--steps S] [--warmup W]\n"
    "                     [--threads LIST] [--backends LIST] [--cases LIST] [--compare CSV]\n"
    "                     [--commit TEXT]\n"
    "Runs the standard cases (explicit MPM with each transfer, implicit MPM, A-ULMPM, enriched\n"
    "MPM, peridynamics) on every backend and thread count: W warm-up steps (default 2), then R\n"
    "repetitions (default 5) of S steps (default 8; 4 for implicit and peridynamics), interleaved\n"
    "across configurations. Writes DIR/results.csv, DIR/kernels.csv, DIR/report.md (medians,\n"
    "min/max, spread, speed-up, parallel efficiency, bytes per item, per-kernel breakdown, STREAM\n"
    "bandwidth) and DIR/scaling.png, DIR/breakdown.png. --scale multiplies every case's size\n"
    "(1: 2^18-particle spheres, a 40^3 peridynamics block). --compare CSV adds a repeatability\n"
    "section against an earlier run's results.csv. scripts/bench_report.sh regenerates\n"
    "docs/bench_report/ (two runs, the second compared with the first).\n";

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) out.push_back(item);
  return out;
}
// "threads=N", N the threads the run used: an execution space caps a request at what it has
// (Debian's Kokkos runs only Serial: core/exec/exec.hpp), and then the request follows, so a
// capped run is not read as a 2-thread figure.
std::string threads_field(exec::Backend backend, int requested) {
  const int ran = exec::Space(backend, requested).threads();
  std::string f = "threads=" + std::to_string(ran);
  if (ran != requested) f += " threads_requested=" + std::to_string(requested);
  return f;
}

const char* sort_name(bool when_needed) {
  return when_needed ? "when_needed" : "every_substep";
}
double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

// --like SCENE: so made like the MPM scene's first object (material, particles per cell) and its
// transfer settings; returns "SCENE (material NAME, PPC per cell)". Throws InputError (an
// unreadable scene, or one that is not MPM or has no object).
std::string like_scene(const std::string& path, BenchSceneOptions& so) {
  const Scene scene = load_scene(path);
  if (scene.method != Method::Mpm || scene.objects.empty())
    throw InputError(path + ": --like needs an MPM scene with at least one object");
  const ObjectSpec& obj = scene.objects.front();
  const MpmSettings& s = scene.mpm;
  so.transfer = s.transfer;
  so.order = s.order;
  so.fused = s.fused;
  so.sort_when_needed = s.sort_when_needed;
  so.material = scene.materials.at(std::size_t(obj.material));
  so.temperature = obj.temperature;
  const double r = 0.3, ppc = obj.particles_per_cell;  // the sphere's radius (bench_scene.cpp)
  so.dx = Real(std::cbrt(ppc * 4.0 / 3.0 * M_PI * r * r * r / double(so.particles)));
  const std::string name = std::size_t(obj.material) < scene.material_names.size()
                               ? scene.material_names[std::size_t(obj.material)]
                               : std::to_string(obj.material);
  return path + " (material " + name + ", " + std::to_string(obj.particles_per_cell) + " per cell)";
}

// The implicit integrator on the stiff sphere: CG iterations per substep and where time goes.
int implicit_bench(BenchSceneOptions so, int steps, int reps, const std::vector<int>& threads,
                   const std::vector<exec::Backend>& backends, double fixed_dt) {
  so.dx = Real(std::cbrt(1e6 / double(so.particles)) / 128.0);
  so.youngs_modulus = 1e7;
  so.implicit = false;
  const Real dt_cfl = make_bench_sphere(so).stable_dt(exec::Space());
  so.implicit = true;
  const Real dt = fixed_dt > 0 ? Real(fixed_dt) : 10 * dt_cfl;
  std::cout << "# amalgam bench --implicit: sphere, " << so.particles << " particles, dx=" << so.dx
            << ", E=1e7, transfer=" << transfer_name(so.transfer) << ", precision=" << real_name()
            << ", simd=" << exec::simd_path_name(exec::simd_path()) << ", dt=" << dt << " ("
            << dt / dt_cfl << "x explicit CFL), " << steps << " substeps x " << reps
            << " reps (median, [min, max])\n";
  for (const auto backend : backends) {
    for (const int t : threads) {
      if (backend == exec::Backend::Serial && t != 1) continue;
      std::vector<double> rate;
      exec::Profiler prof;
      double mean_it = 0;
      int max_it = 0;
      std::uint64_t applications = 0;
      for (int r = 0; r < reps; ++r) {
        MpmSolver solver = make_bench_sphere(so);
        exec::Space warm(backend, t);
        for (int s = 0; s < 2; ++s) solver.step(warm, dt);
        solver.implicit()->reset_counters();
        exec::Profiler run_prof;
        exec::Space space(backend, t, &run_prof);
        const auto t0 = std::chrono::steady_clock::now();
        for (int s = 0; s < steps; ++s) solver.step(space, dt);
        const double sec =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        rate.push_back(double(so.particles) * steps / sec);
        if (r == reps / 2) {
          prof = run_prof;
          const ImplicitCounters& c = solver.implicit()->counters();
          mean_it = double(c.iterations) / double(c.solves);
          max_it = c.max_iterations;
          applications = c.iterations + c.solves;  // + the initial residual
        }
      }
      const double per = 1e9 / (double(so.particles) * steps);
      double solve = 0;
      for (const auto& r : prof.regions())
        if (r.label.rfind("implicit.", 0) == 0) solve += r.seconds;
      const double op =
          prof.seconds("implicit.hessian_action") + prof.seconds("implicit.apply_mass");
      char line[512];
      std::snprintf(
          line, sizeof line,
          "backend=%s %s particles=%zu particle_substeps_per_s=%.4g min=%.4g max=%.4g "
          "cg_iterations_mean=%.1f cg_iterations_max=%d solve_ns=%.1f operator_ns_per_application=%.1f "
          "p2g_ns=%.1f g2p_ns=%.1f",
          exec::backend_name(backend), threads_field(backend, t).c_str(), so.particles,
          median(rate), *std::min_element(rate.begin(), rate.end()),
          *std::max_element(rate.begin(), rate.end()), mean_it, max_it, solve * per,
          op * 1e9 / (double(so.particles) * double(std::max<std::uint64_t>(1, applications))),
          prof.seconds("mpm.p2g") * per, prof.seconds("mpm.g2p") * per);
      std::cout << line << std::endl;
    }
  }
  return kOk;
}

}  // namespace

int bench_command(const std::vector<std::string>& args) {
  BenchSceneOptions so;
  int steps = 10, reps = 3;
  std::vector<int> threads = {1, 2};
  std::vector<exec::Backend> backends = exec::available_backends();
  bool implicit = false;
  double fixed_dt = 0;
  std::string like;  // --like: like_scene's description, for the header line
  try {
    const Options o =
        parse_options(args,
                      {"--particles", "--steps", "--reps", "--threads", "--backends", "--transfer",
                       "--dt", "--transfer-pass", "--sort", "--report", "--scale", "--warmup",
                       "--cases", "--compare", "--commit", "--like"},
                      {"--help", "--implicit"});
    if (o.flag("--help")) {
      std::cout << kBenchHelp;
      return kOk;
    }
    if (o.get("--report")) {
      for (const char* k :
           {"--particles", "--transfer", "--dt", "--transfer-pass", "--sort", "--like"})
        if (o.get(k)) throw std::invalid_argument(std::string(k) + " does not apply to --report");
      if (o.flag("--implicit"))
        throw std::invalid_argument("--implicit does not apply to --report");
      if (!o.positional.empty())
        throw std::invalid_argument("unexpected argument " + o.positional[0]);
      try {
        return bench_report(o);
      } catch (const InputError& e) {
        std::cerr << "amalgam bench: " << e.what() << "\n";
        return kBadInput;
      }
    }
    for (const char* k : {"--scale", "--warmup", "--cases", "--compare", "--commit"})
      if (o.get(k)) throw std::invalid_argument(std::string(k) + " needs --report");
    if (!o.positional.empty())
      throw std::invalid_argument("unexpected argument " + o.positional[0]);
    if (auto* v = o.get("--particles"))
      so.particles = size_t(parse_int("--particles", *v, 1000, 200000000));
    if (auto* v = o.get("--like")) {
      if (o.flag("--implicit")) throw std::invalid_argument("--like does not apply to --implicit");
      try {
        like = like_scene(*v, so);
      } catch (const InputError& e) {
        std::cerr << "amalgam bench: " << e.what() << "\n";
        return kBadInput;
      }
    }
    if (auto* v = o.get("--steps")) steps = parse_int("--steps", *v, 1, 100000);
    if (auto* v = o.get("--reps")) reps = parse_int("--reps", *v, 1, 1000);
    if (auto* v = o.get("--threads")) {
      threads.clear();
      for (const auto& t : split(*v)) threads.push_back(parse_int("--threads", t, 1, 4096));
    }
    if (auto* v = o.get("--backends")) {
      backends.clear();
      for (const auto& b : split(*v)) backends.push_back(exec::parse_backend(b));
    }
    if (auto* v = o.get("--transfer")) {
      if (*v == "mls")
        so.transfer = Transfer::Mls;
      else if (*v == "apic")
        so.transfer = Transfer::Apic;
      else if (*v == "flip" || *v == "pic")
        so.transfer = Transfer::PicFlip;
      else
        throw std::invalid_argument("--transfer expects mls, apic, flip or pic, got '" + *v + "'");
    }
    if (auto* v = o.get("--transfer-pass")) {
      if (*v != "fused" && *v != "two_pass")
        throw std::invalid_argument("--transfer-pass expects fused or two_pass, got '" + *v + "'");
      so.fused = *v == "fused";
    }
    if (auto* v = o.get("--sort")) {
      if (*v != "every_substep" && *v != "when_needed")
        throw std::invalid_argument("--sort expects every_substep or when_needed, got '" + *v +
                                    "'");
      so.sort_when_needed = *v == "when_needed";
    }
    implicit = o.flag("--implicit");
    if (auto* v = o.get("--dt")) {
      if (!implicit) throw std::invalid_argument("--dt needs --implicit");
      fixed_dt = parse_double("--dt", *v, 1e-9, 1.0);
    }
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam bench: " << e.what() << "\n" << kBenchHelp;
    return kUsage;
  }
  if (implicit) return implicit_bench(so, steps, reps, threads, backends, fixed_dt);
  std::cout << "# amalgam bench: sphere, " << so.particles << " particles, dx=1/"
            << int(std::lround(1 / so.dx)) << ", transfer=" << transfer_name(so.transfer)
            << ", transfer_pass=" << (so.fused ? "fused" : "two_pass")
            << ", sort=" << sort_name(so.sort_when_needed) << ", precision=" << real_name()
            << ", simd=" << exec::simd_description() << ", " << steps << " substeps x " << reps
            << " reps (median, [min, max])";
  Real dt = Real(1e-4);
  if (!like.empty()) {
    dt = std::min(dt, make_bench_sphere(so).stable_dt(exec::Space()));
    std::cout << ", like=" << like << ", order=" << so.order << ", dt=" << dt;
  }
  std::cout << "\n";
  for (const auto backend : backends) {
    for (const int t : threads) {
      if (backend == exec::Backend::Serial && t != 1) continue;
      std::vector<double> rate;
      exec::Profiler prof;
      std::size_t leaves = 0, particle_bytes = 0, leaf_bytes = 0, block_bytes = 0;
      bool sort_when_needed = false, lazy = false;
      std::uint64_t resorts = 0, unfit = 0;  // in the timed substeps
      for (int r = 0; r < reps; ++r) {
        MpmSolver solver = make_bench_sphere(so);
        exec::Space warm(backend, t);
        for (int s = 0; s < 2; ++s) solver.step(warm, dt);
        exec::Profiler run_prof;
        exec::Space space(backend, t, &run_prof);
        // Re-sorts of the lazy two passes or of the fused pass (the fused pass always re-sorts
        // only when needed), and substeps whose dilated blocks exceeded their budget.
        auto counts = [&] {
          return solver.fused_eligible()
                     ? std::make_pair(solver.fused_fallbacks(), solver.fused_unfused())
                     : std::make_pair(solver.lazy_resorts(), solver.lazy_unfit());
        };
        const auto c0 = counts();
        const auto t0 = std::chrono::steady_clock::now();
        for (int s = 0; s < steps; ++s) solver.step(space, dt);
        const double sec =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        rate.push_back(double(so.particles) * steps / sec);
        if (r == reps / 2) prof = run_prof;
        sort_when_needed = solver.settings().sort_when_needed;
        lazy = solver.fused_eligible() || solver.sort_when_needed_eligible();
        resorts = counts().first - c0.first;
        unfit = counts().second - c0.second;
        leaves = solver.grid().active_leaves().size();
        particle_bytes =
            solver.particles().bytes_per_particle() + solver.binning_bytes_per_particle();
        leaf_bytes = solver.grid().bytes_per_leaf();
        block_bytes = solver.p2g_block_bytes();
      }
      const double per = 1e9 / (double(so.particles) * steps);
      auto ns = [&](std::initializer_list<const char*> labels) {
        double s = 0;
        for (auto* l : labels) s += prof.seconds(l);
        return s * per;
      };
      char lazy_counts[96] = "";
      if (lazy)
        std::snprintf(lazy_counts, sizeof lazy_counts, " resorts=%llu sort_unfit=%llu",
                      (unsigned long long)resorts, (unsigned long long)unfit);
      char line[1024];
      std::snprintf(
          line, sizeof line,
          "backend=%s %s particles=%zu sort=%s%s particle_substeps_per_s=%.4g min=%.4g "
          "max=%.4g p2g_ns=%.1f g2p_ns=%.1f g2p2g_ns=%.1f sort_ns=%.1f topology_ns=%.1f grid_ns=%.1f leaves=%zu "
          "bytes_per_particle=%zu bytes_per_node=%.1f p2g_block_bytes_per_particle=%.1f simd=%s",
          exec::backend_name(backend), threads_field(backend, t).c_str(), so.particles,
          sort_name(sort_when_needed), lazy_counts, median(rate),
          *std::min_element(rate.begin(), rate.end()), *std::max_element(rate.begin(), rate.end()),
          ns({"mpm.p2g"}), ns({"mpm.g2p"}), ns({"mpm.g2p2g", "mpm.g2p2g_flush"}),
          ns({"bin.leaf_box", "bin.keys", "bin.radix_hist", "bin.radix_scatter",
              "particles.permute", "bin.find_runs"}),
          ns({"grid.topology"}), ns({"mpm.grid_clear", "mpm.grid_update"}), leaves, particle_bytes,
          double(leaf_bytes) / 512.0, double(block_bytes) / double(so.particles),
          exec::simd_path_name(exec::simd_path()));
      std::cout << line << std::endl;
    }
  }
  return kOk;
}

}  // namespace amalgam::cli
