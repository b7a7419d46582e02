#include "solvers/bench_suite.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>

#include "solvers/bench_scene.hpp"
#include "solvers/pd_bench_block.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

namespace amalgam {

namespace {

// The standard sphere (solvers/bench_scene) at 2^18 x scale particles with the ~4.2 particles per
// cell of the 1e6 sphere at dx = 1/128.
BenchSceneOptions sphere(double scale) {
  BenchSceneOptions o;
  o.particles = std::size_t(std::max(4096.0, std::round(262144.0 * scale)));
  o.dx = Real(std::cbrt(1e6 / double(o.particles)) / 128.0);
  return o;
}

double mpm_bytes(const MpmSolver& s) {
  return double(s.particles().bytes_per_particle() + MpmSolver::binning_bytes_per_particle()) +
         double(s.grid().bytes_per_leaf()) * double(s.grid().leaf_count()) /
             double(s.particles().size());
}

BenchInstance mpm_instance(MpmSolver&& solver, Real dt) {
  auto s = std::make_shared<MpmSolver>(std::move(solver));
  BenchInstance b;
  b.dt = dt;
  b.step = [s, dt](const exec::Space& space) { s->step(space, dt); };
  b.items = double(s->particles().size());
  b.owner = s;
  b.extra = [s] {
    const ImplicitCounters c = s->implicit() ? s->implicit()->counters() : ImplicitCounters();
    std::string out;
    if (c.solves > 0) {
      char buf[96];
      std::snprintf(buf, sizeof buf, "cg_iterations_mean=%.1f cg_iterations_max=%d",
                    double(c.iterations) / double(c.solves), c.max_iterations);
      out = buf;
    }
    if (s->enriched()) {
      char buf[64];
      std::snprintf(buf, sizeof buf, "%senriched_fraction=%.3f", out.empty() ? "" : " ",
                    s->enriched()->domains().counters().max_enriched_fraction);
      out += buf;
    }
    return out;
  };
  b.reset_extra = [s] {
    if (s->implicit()) s->implicit()->reset_counters();
    if (s->enriched()) s->enriched()->domains().reset_counters();
  };
  return b;
}

// Builds the sphere, runs two warm-up substeps (grid allocated, caches warm) and measures the
// bytes after them, when the grid has its working size.
BenchInstance mpm_case(const BenchSceneOptions& o, const exec::Space& space, Real dt) {
  MpmSolver solver = make_bench_sphere(o);
  for (int k = 0; k < 2; ++k) solver.step(space, dt);
  const double bytes = mpm_bytes(solver);
  BenchInstance b = mpm_instance(std::move(solver), dt);
  b.bytes_per_item = bytes;
  return b;
}

BenchCase transfer_case(const char* name, const char* method, Transfer t, int order) {
  return {name, method, "particle-substeps/s",
          "spinning jelly sphere over a floor, 2^18 particles, ~4.2 per cell, dt 1e-4 s",
          [t, order](double scale, const exec::Space& space) {
            BenchSceneOptions o = sphere(scale);
            o.transfer = t;
            o.order = order;
            return mpm_case(o, space, Real(1e-4));
          }};
}

}  // namespace

std::vector<BenchCase> standard_bench_cases() {
  std::vector<BenchCase> out;
  out.push_back(transfer_case("mpm_mls", "explicit MPM, MLS, quadratic", Transfer::Mls, 2));
  out.push_back(transfer_case("mpm_apic", "explicit MPM, APIC, quadratic", Transfer::Apic, 2));
  out.push_back(
      transfer_case("mpm_flip", "explicit MPM, PIC/FLIP 0.95, quadratic", Transfer::PicFlip, 2));
  out.push_back(transfer_case("mpm_mls_cubic", "explicit MPM, MLS, cubic", Transfer::Mls, 3));
  out.push_back({"mpm_implicit", "implicit MPM (backward Euler, Jacobi CG), MLS",
                 "particle-substeps/s",
                 "the sphere stiffened to E = 1e7, 2^16 particles, dt = 10x the explicit CFL step",
                 [](double scale, const exec::Space& space) {
                   BenchSceneOptions o = sphere(scale / 4);
                   o.youngs_modulus = 1e7;
                   const Real dt = 10 * make_bench_sphere(o).stable_dt(space);
                   o.implicit = true;
                   return mpm_case(o, space, dt);
                 }});
  out.push_back({"aulmpm_tl", "A-ULMPM, total Lagrangian, MLS", "particle-substeps/s",
                 "the sphere as one total-Lagrangian object, 2^18 particles, dt 1e-4 s",
                 [](double scale, const exec::Space& space) {
                   BenchSceneOptions o = sphere(scale);
                   o.lagrangian = true;
                   return mpm_case(o, space, Real(1e-4));
                 }});
  out.push_back({"enriched_mpm", "enriched MPM (particle domains), explicit, FLIP",
                 "particle-substeps/s",
                 "the sphere on a lattice with connected domains, 2^16 particles, dt 1e-5 s",
                 [](double scale, const exec::Space& space) {
                   BenchSceneOptions o = sphere(scale / 4);
                   o.domains = true;
                   return mpm_case(o, space, Real(1e-5));
                 }});
  out.push_back(
      {"peridynamics", "peridynamics, state-based, plastic + fracture on", "bond-updates/s",
       "40^3 lattice block (64 000 particles, 7.2 M directed bonds), delta = 3.015 lc",
       [](double scale, const exec::Space& space) {
         const int n = std::max(12, int(std::lround(40 * std::cbrt(scale))));
         // One block per size, copied per configuration (its set-up takes seconds).
         static std::map<int, std::shared_ptr<const PdSolver>> built;
         if (!built.count(n)) built[n] = make_bench_pd_block(n, space);
         auto s = std::make_shared<PdSolver>(*built[n]);
         const Real dt = s->stable_dt(space);
         BenchInstance b;
         b.dt = dt;
         b.step = [s, dt](const exec::Space& sp) { s->step(sp, dt); };
         b.items = double(s->bonds().size());
         const PdBonds& bo = s->bonds();
         b.bytes_per_item =
             double(sizeof(std::uint32_t) + sizeof(std::uint64_t) + 5 * sizeof(Real) + 1) +
             double(bo.offsets.size() * sizeof(std::uint64_t) +
                    s->particles().size() * s->particles().bytes_per_particle()) /
                 double(bo.size());
         b.extra = [] { return std::string(); };
         b.reset_extra = [] {};
         b.owner = s;
         return b;
       }});
  return out;
}

}  // namespace amalgam
