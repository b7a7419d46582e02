// Google Benchmark microbenchmarks of the hot kernels of explicit MPM, per backend and thread
// count. Arguments of every transfer benchmark: {backend (0 serial, 1 openmp, 2 tbb, 4 kokkos),
// threads}.
// Items are particles (or grid nodes for the grid update); items/s is the throughput.
// Scene: the standard sphere (solvers/bench_scene) with 2^18 particles at dx chosen for the same
// ~4.2 particles per cell as the 1e6 benchmark.
#include <benchmark/benchmark.h>

#include <cmath>
#include <map>
#include <memory>
#include <random>

#include "core/exec/simd.hpp"
#include "core/materials/material.hpp"
#include "core/math/svd3.hpp"
#include "solvers/bench_scene.hpp"
#include "solvers/pd_bench_block.hpp"
#include "kernels/peak_flops.hpp"
#include "kernels/implicit_mpm.hpp"
#include "kernels/particle_domains.hpp"
#include "solvers/pd_solver.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

using namespace amalgam;

namespace {

constexpr std::size_t kParticles = 1u << 18;

exec::Space space_of(const benchmark::State& st) {
  return exec::Space(static_cast<exec::Backend>(st.range(0)), int(st.range(1)));
}

// Serial, OpenMP and TBB at 1 and 2 threads, and Kokkos (backend 4) when this build has it
// (Debian's Kokkos runs its Serial execution space: 1 thread).
void backend_args(benchmark::internal::Benchmark* b) {
  b->ArgNames({"backend", "threads"});
  b->Args({0, 1})->Args({1, 1})->Args({1, 2})->Args({2, 1})->Args({2, 2});
  if (exec::backend_compiled(exec::Backend::Kokkos)) b->Args({int(exec::Backend::Kokkos), 1});
  b->UseRealTime()->Unit(benchmark::kMillisecond);
}

// A solver after one full substep, sorted and with topology built: ready for P2G/G2P.
// lagrangian: A-ULMPM, one total-Lagrangian object (binned by X^s once; Lagrangian-mode kernels).
std::unique_ptr<MpmSolver> prepared(
    Transfer t, int order, const exec::Space& space, bool lagrangian = false,
    ConfigurationUpdate update = ConfigurationUpdate::TotalLagrangian, int objects = 1,
    std::size_t particles = kParticles, double ppc = 0) {
  BenchSceneOptions o;
  o.objects = objects;
  o.policy.update = update;
  o.policy.epsilon = Real(100);  // adaptive: evaluates the criterion every substep, never resets
  o.particles = particles;
  // Same ppc as 1e6 at dx = 1/128 (about 4.2), or `ppc` particles per cell.
  o.dx = Real(std::cbrt(1e6 / double(particles) * (ppc > 0 ? ppc / 4.19 : 1)) / 128.0);
  o.transfer = t;
  o.order = order;
  o.lagrangian = lagrangian;
  auto s = std::make_unique<MpmSolver>(make_bench_sphere(o));
  s->step(space, Real(1e-4));
  if (lagrangian) {
    s->aul()->update_configurations(space, *s);
  } else {
    s->sort_particles(space);
    s->update_grid(space);
  }
  s->particle_to_grid(space, Real(1e-4));
  s->update_grid_velocities(space, Real(1e-4));
  return s;
}

void set_items(benchmark::State& st, std::size_t per_iter, std::size_t bytes_per_item) {
  st.SetItemsProcessed(std::int64_t(st.iterations()) * std::int64_t(per_iter));
  st.SetBytesProcessed(std::int64_t(st.iterations()) * std::int64_t(per_iter * bytes_per_item));
}

// Bytes of particle state a transfer streams (read + write), per particle.
constexpr std::size_t kP2GBytes = sizeof(Vec3) * 2 + sizeof(Mat3) * 2 + 2 * sizeof(Real) + 4;
constexpr std::size_t kG2PBytes = 2 * (sizeof(Vec3) * 2 + sizeof(Mat3) * 2);

void BM_P2G(benchmark::State& st, Transfer t, int order) {
  const exec::Space space = space_of(st);
  auto s = prepared(t, order, space);
  for (auto _ : st) s->particle_to_grid(space, Real(1e-4));
  set_items(st, kParticles, kP2GBytes);
}

void BM_G2P(benchmark::State& st, Transfer t, int order) {
  const exec::Space space = space_of(st);
  auto s = prepared(t, order, space);
  // dt = 0: particles do not move, so repeated gathers stay inside their bins; the work per
  // particle is the same as with dt > 0.
  for (auto _ : st) s->grid_to_particle(space, Real(0));
  set_items(st, kParticles, kG2PBytes);
}

// The fused G2P2G kernel (solvers/mpm_fused.cpp) alone: gather, particle update and the split
// scatter into the dilated blocks, then their flush into the grid (the leaf lists built by the
// solver's fused substep before the loop), on the standard sphere. dt = 0 as in BM_G2P; compare
// with BM_P2G + BM_G2P of the same transfer and order.
void BM_G2P2G(benchmark::State& st, Transfer t, int order) {
  const exec::Space space = space_of(st);
  BenchSceneOptions o;
  o.particles = kParticles;
  o.dx = Real(std::cbrt(1e6 / double(kParticles)) / 128.0);
  o.transfer = t;
  o.order = order;
  o.fused = true;
  MpmSolver s = make_bench_sphere(o);
  s.step(space, Real(1e-4));  // primes the grid, one fused substep, the next grid flushed
  const MpmGridView g = s.grid_view();
  MpmStepParams prm = s.step_params(0);
  prm.split = true;
  std::vector<Real> blocks(g.nbins * g2p2g_block_reals(order));
  std::vector<std::uint8_t> far(g.nbins);
  for (auto _ : st) g2p2g(space, s.particle_view(), g, prm, nullptr, blocks.data(), far.data());
  st.counters["bins"] = double(g.nbins);
  set_items(st, kParticles, kG2PBytes);
}

// MLS P2G on its two paths: kept bin blocks (every bin scattered in one loop, then summed per
// leaf; what particle_to_grid runs) against the eight colour phases (blocks = null), the same
// bits. On the standard sphere (2^18 particles, ~4.2 per cell) and on one of jelly_drop's size
// (97,336 particles at 8 per cell: ~100 bins, ~12 per colour).
void BM_P2GPath(benchmark::State& st, bool blocks, std::size_t particles, double ppc) {
  const exec::Space space = space_of(st);
  auto s = prepared(Transfer::Mls, 2, space, false, ConfigurationUpdate::TotalLagrangian, 1,
                    particles, ppc);
  const Real dt = Real(1e-4);
  for (auto _ : st) {
    if (blocks) {
      s->particle_to_grid(space, dt);
    } else {
      MpmGridView g = s->grid_view();
      const MpmStepParams prm = s->step_params(dt);
      grid_clear(space, g, prm);
      p2g(space, s->particle_view(), g, prm);
    }
  }
  st.counters["bins"] = double(s->bins().count());
  set_items(st, particles, kP2GBytes);
}

// A-ULMPM: the Lagrangian-mode transfers (stencil at X^s, stress tau F_s^{-T}, F = F_s F_0s),
// the grid update with the rasterised node positions q_i (p2g_positions, for the collider) and
// the per-substep configuration check (eq. 33 criterion; a TL object never re-bins).
void BM_AulP2G(benchmark::State& st, Transfer t) {
  const exec::Space space = space_of(st);
  auto s = prepared(t, 2, space, true);
  for (auto _ : st) s->particle_to_grid(space, Real(1e-4));
  set_items(st, kParticles, kP2GBytes + sizeof(Vec3) + sizeof(Mat3));
}

void BM_AulG2P(benchmark::State& st, Transfer t) {
  const exec::Space space = space_of(st);
  auto s = prepared(t, 2, space, true);
  for (auto _ : st) s->grid_to_particle(space, Real(0));
  set_items(st, kParticles, kG2PBytes + sizeof(Vec3) + 3 * sizeof(Mat3));
}

// Grid update with the floor collider tested at the node positions q_i. For MLS/APIC the q_i come
// out of the momentum P2G (fused, so BM_AulP2G includes them); PIC/FLIP run p2g_positions here.
// Items are particles, to compare with the transfers.
void BM_AulGridUpdate(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared(Transfer::Mls, 2, space, true);
  for (auto _ : st) s->update_grid_velocities(space, Real(1e-4));
  set_items(st, kParticles, sizeof(Vec3) * 2 + sizeof(Mat3) + sizeof(Real));
}

// The adaptive object's per-substep criterion (eq. 33: det F_s per particle, one reduction).
void BM_AulConfigurationCheck(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared(Transfer::Mls, 2, space, true, ConfigurationUpdate::Adaptive);
  for (auto _ : st) s->aul()->update_configurations(space, *s);
  set_items(st, kParticles, sizeof(Mat3));
}

// Contact between objects through the global grid (solvers/object_contact): the sphere split
// into two total-Lagrangian halves touching at x = 0.5 (stick). One iteration = the whole
// couple_objects phase (broad phase, collect, sort the points, activate the global grid,
// scatter, gather); items are particles, to compare with the transfers.
void BM_ObjectContact(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared(Transfer::Mls, 2, space, true, ConfigurationUpdate::TotalLagrangian, 2);
  for (auto _ : st) s->aul()->couple_objects(space, *s, Real(1e-4));
  st.counters["contact_points"] = double(s->aul()->contact_point_count());
  set_items(st, kParticles, 2 * sizeof(Vec3) + sizeof(Real));  // x, v, m of each particle read
}

// Enriched MPM (solvers/particle_domains) on the sphere sampled on a lattice with particle domains
// (about kParticles particles, spacing dx / 2: 8 domains per cell), after two substeps.
std::unique_ptr<MpmSolver> prepared_domains(const exec::Space& space, bool implicit = false) {
  BenchSceneOptions o;
  o.particles = kParticles;
  o.dx = Real(2 * std::cbrt(4.0 / 3.0 * M_PI * 0.027 / double(kParticles)));
  o.domains = true;
  o.implicit = implicit;
  auto s = std::make_unique<MpmSolver>(make_bench_sphere(o));
  for (int k = 0; k < 2; ++k) s->step(space, Real(1e-4));
  return s;
}
// Stress at the clamped F, enrichment marking, particle -> corner gather (mass, momentum, force).
void BM_DomainParticlesToCorners(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared_domains(space);
  const DomainParticleView pv = s->enriched()->particle_view(*s);
  const DomainParams prm = s->enriched()->params(*s, Real(1e-4));
  for (auto _ : st) {
    s->enriched()->domains().stresses_and_enrichment(space, pv, prm, false, true);
    s->enriched()->domains().particles_to_corners(space, pv);
  }
  st.counters["corners"] = double(s->enriched()->domains().corner_count());
  set_items(st, pv.n,
            2 * sizeof(Mat3) + 2 * sizeof(Real) + 8 * 4 + sizeof(Vec3) +
                4);  // F, P, m, V0, corners, h, state
}
// Grid -> corner gather with corner collisions, then corner -> particle (v, F) and advection.
void BM_DomainGridToParticles(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared_domains(space);
  const DomainParticleView pv = s->enriched()->particle_view(*s);
  const DomainParams prm =
      s->enriched()->params(*s, Real(0));  // dt 0: positions stay, state repeatable
  const MpmGridView g = s->grid_view();
  for (auto _ : st) {
    s->enriched()->domains().grid_to_corners(space, g, pv, prm);
    s->enriched()->domains().corners_to_particles(space, pv, prm);
  }
  set_items(st, pv.n,
            8 * 4 + 2 * sizeof(Mat3) + 4 * sizeof(Vec3));  // corners; F r/w; v, x; corner v, x
}
// A whole explicit substep (the two above plus points, sort, topology, scatter, grid update).
void BM_DomainStep(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared_domains(space);
  for (auto _ : st) s->enriched()->step(space, *s, Real(1e-5));
  set_items(st, s->particles().size(),
            s->particles().bytes_per_particle());  // resident particle state
}
// The implicit operator's domain term: grid -> corners -> dF -> dP -> corners -> grid.
void BM_DomainHessianAction(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared_domains(space, true);
  const DomainParticleView pv = s->enriched()->particle_view(*s);
  const DomainParams prm = s->enriched()->params(*s, Real(1e-4));
  s->enriched()->domains().stresses_and_enrichment(space, pv, prm, true, true);
  s->enriched()->domains().particles_to_corners(space, pv);
  s->enriched()->domains().number_enriched_dofs(space);
  const MpmGridView g = s->grid_view();
  const std::size_t ngrid = s->grid().leaf_count() * kLeafNodes * 4;
  const std::size_t ncorner = 4 * s->enriched()->domains().enriched_dof_count() + 4;
  std::vector<Real> du(ngrid, Real(1e-3)), out(ngrid), duc(ncorner, Real(1e-3)), outc(ncorner);
  for (auto _ : st)
    s->enriched()->domains().hessian_action(space, pv, g, s->settings().dx, du.data(), duc.data(),
                                            1, out.data(), outc.data());
  set_items(st, pv.n, 8 * 4 + sizeof(DomainHessian));  // corner ids + the Hessian cache
}

void BM_GridUpdate(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared(Transfer::Mls, 2, space);
  const std::size_t nodes = s->grid().active_leaves().size() * kLeafNodes;
  for (auto _ : st) s->update_grid_velocities(space, Real(1e-4));
  set_items(st, nodes, 16 * 2);
}

void BM_SortAndActivate(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = prepared(Transfer::Mls, 2, space);
  for (auto _ : st) {
    s->sort_particles(space);
    s->update_grid(space);
  }
  set_items(st, kParticles, s->particles().bytes_per_particle());
}

// Implicit integration on the same sphere, stiffened (E = 1e7) and stepped at 10x the explicit
// CFL limit for a realistic system; the system is assembled once, then timed.
struct ImplicitRig {
  std::unique_ptr<MpmSolver> s;
  Real dt = 0;
  std::size_t dofs = 0;  // grid nodes with mass
};
ImplicitRig implicit_rig(const exec::Space& space) {
  BenchSceneOptions o;
  o.particles = kParticles;
  o.dx = Real(std::cbrt(1e6 / double(kParticles)) / 128.0);
  o.youngs_modulus = 1e7;
  ImplicitRig r;
  o.implicit = false;
  const Real dt_explicit = MpmSolver(make_bench_sphere(o)).stable_dt(space);
  o.implicit = true;
  r.s = std::make_unique<MpmSolver>(make_bench_sphere(o));
  r.dt = 10 * dt_explicit;
  r.s->step(space, r.dt);
  r.s->sort_particles(space);
  r.s->update_grid(space);
  r.s->particle_to_grid(space, r.dt);
  r.s->update_grid_velocities(space, r.dt);
  r.s->implicit()->assemble(space, *r.s, r.dt);
  const ImplicitSystem& sys = r.s->implicit()->system();
  for (const auto& b : sys.blocks())
    for (std::uint64_t d = b.first; d < b.first + b.count; ++d)
      r.dofs += r.s->grid().node4(0)[d * 4] > 0;
  return r;
}

// One application of M + dt^2 H (the matrix-free operator: colour gather/scatter per particle).
void BM_ImplicitOperator(benchmark::State& st) {
  const exec::Space space = space_of(st);
  ImplicitRig r = implicit_rig(space);
  ImplicitSystem& sys = r.s->implicit()->system();
  std::vector<Real> out(sys.dof_count() * 4);
  for (auto _ : st) sys.apply(space, r.dt, sys.rhs(), out.data());
  set_items(st, kParticles, sizeof(ParticleHessian) + sizeof(Vec3) + sizeof(Real));  // cache, x, V0
  st.counters["dofs"] = double(r.dofs);
}

// Ten Jacobi-PCG iterations (operator, projections, two dot products, updates; the
// preconditioner is built before timing); items are DOF-iterations, so 1 / (items/s) is the
// time per iteration per DOF.
void BM_CgIteration(benchmark::State& st) {
  const exec::Space space = space_of(st);
  ImplicitRig r = implicit_rig(space);
  ImplicitSystem& sys = r.s->implicit()->system();
  ImplicitSettings cfg;
  cfg.tolerance = 0;  // never converged: exactly max_iterations
  cfg.max_iterations = 10;
  std::vector<Real> guess(sys.solution(), sys.solution() + sys.dof_count() * 4);
  sys.prepare(space, r.dt);
  for (auto _ : st) {
    st.PauseTiming();
    std::copy(guess.begin(), guess.end(), sys.solution());
    st.ResumeTiming();
    sys.solve(space, r.dt, cfg);
  }
  // per DOF-iteration: the CG vectors (x, r, z, p, q, mass, inverse diagonal: 4 lanes each) and
  // the operator's share of the particle Hessian cache
  set_items(st, r.dofs * 10,
            std::size_t(7 * 4 * sizeof(Real) +
                        double(kParticles) / double(r.dofs) *
                            double(sizeof(ParticleHessian) + sizeof(Vec3) + sizeof(Real))));
  st.counters["dofs"] = double(r.dofs);
}

// Per step: DOFs from the grid, contacts, particle Hessian cache (SVD + frame blocks with the
// fix) and the Jacobi diagonal (eqs. 17-19).
void BM_ImplicitAssemble(benchmark::State& st) {
  const exec::Space space = space_of(st);
  ImplicitRig r = implicit_rig(space);
  for (auto _ : st) {
    r.s->implicit()->assemble(space, *r.s, r.dt);
    r.s->implicit()->system().prepare(space, r.dt);
  }
  set_items(st, kParticles,
            sizeof(ParticleHessian) + sizeof(Mat3) + sizeof(Vec3));  // cache written, F, x
}

std::vector<Mat3> random_F(std::size_t n) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.2, 0.2);
  std::vector<Mat3> F(n, Mat3::Identity());
  for (auto& f : F)
    for (int i = 0; i < 9; ++i) f(i) += Real(u(rng));
  return F;
}

void BM_Svd3(benchmark::State& st) {
  const std::vector<Mat3> F = random_F(4096);
  for (auto _ : st)
    for (const auto& f : F) benchmark::DoNotOptimize(svd3(f));
  set_items(st, F.size(), sizeof(Mat3) * 4);
}

void BM_PolarFast(benchmark::State& st) {
  const std::vector<Mat3> F = random_F(4096);
  for (auto _ : st)
    for (const auto& f : F) benchmark::DoNotOptimize(polar_rotation_fast(f));
  set_items(st, F.size(), sizeof(Mat3) * 2);
}

// The same matrices lanes::kN<Real> at a time, one per vector lane (what P2G runs).
void BM_PolarFastLanes(benchmark::State& st) {
  const std::vector<Mat3> F = random_F(4096);
  constexpr int W = lanes::kN<Real>;
  std::vector<Mat3> R(F.size());
  for (auto _ : st) {
    for (std::size_t i = 0; i < F.size(); i += W) polar_rotation_fast_lanes(&F[i], &R[i], W);
    benchmark::DoNotOptimize(R.data());
  }
  set_items(st, F.size(), sizeof(Mat3) * 2);
}

// Per particle: Kirchhoff stress (what P2G evaluates) plus the state update after G2P (return
// mapping or F reset; nothing for the hyperelastic models). F near I with +-0.3 perturbations,
// so the plastic models mostly project. 2^16 particles in a parallel_for, per backend.
void BM_Material(benchmark::State& st, MaterialModel model) {
  const exec::Space space = space_of(st);
  std::vector<Mat3> F = random_F(1u << 16), out(F.size());
  std::vector<Real> plastic_out(F.size());
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  MaterialParams m{model, l.mu, l.lambda, 1000};
  m.friction_alpha = DruckerPragerT<Real>::friction_alpha(Real(0.5236));
  m.yield_stress = Real(1e3);
  m.hardening_modulus = Real(1e3);
  m.bulk = Real(1e5);
  m.viscosity = Real(1e-3);
  const Mat3 L = Mat3::Identity() * Real(0.1);
  for (auto _ : st) {
    exec::parallel_for(space, "bench.material", exec::Index(F.size()), [&](exec::Index i) {
      Mat3 g = F[size_t(i)];
      Real plastic = m.initial_plastic();
      const Mat3 tau = m.kirchhoff(g, L, plastic, 0);
      m.project(g, plastic, 0);
      out[size_t(i)] = g + tau;
      plastic_out[size_t(i)] = plastic;
    });
    benchmark::DoNotOptimize(out.data());
    benchmark::DoNotOptimize(plastic_out.data());
  }
  set_items(st, F.size(), sizeof(Mat3) * 3);
}

// Roofline ceilings. STREAM triad a = b + s c over 3 x 2^24 floats (192 MiB, far beyond the
// caches), bytes counted 3 x 4 per item (no write-allocate, as STREAM counts).
void BM_StreamTriad(benchmark::State& st) {
  const exec::Space space = space_of(st);
  const exec::Index n = exec::Index(1) << 24;
  std::vector<float> a(size_t(n), 0.f), b(size_t(n), 1.f), c(size_t(n), 2.f);
  for (auto _ : st) {
    exec::parallel_for(space, "bench.triad", n,
                       [&](exec::Index i) { a[size_t(i)] = b[size_t(i)] + 0.5f * c[size_t(i)]; });
    benchmark::DoNotOptimize(a.data());
  }
  set_items(st, size_t(n), 12);
}

// Arithmetic peak of the code the kernels run: independent multiply-add chains on the current
// SIMD path's vectors (kernels/peak_flops.cpp, compiled per instruction set; a multiply and a
// separate add: no FMA contraction). Items are flops; one item per core-ns is 1 GFLOP/s. Per
// backend, 1 and 2 threads (each chunk its own chains).
void BM_PeakFlops(benchmark::State& st) {
  const exec::Space space = space_of(st);
  const int chunks = 256, iters = 16384;
  std::vector<Real> sink(static_cast<std::size_t>(chunks));
  double flops = 0;
  for (auto _ : st) {
    flops += peak_flops_run(space, chunks, iters, sink.data());
    benchmark::DoNotOptimize(sink.data());
  }
  st.SetItemsProcessed(std::int64_t(flops));
}

// Peridynamics: a 40^3 lattice block (64 000 particles, delta = 3.015 lc: 122 bonds in the bulk,
// 7.2 M directed bonds), stretched 0.1 % and sheared so every bond carries a force; plastic and
// fracture enabled (thresholds not reached) so the kernels run their full paths. Items are
// directed bonds (each visited from both ends, as LAMMPS counts them).
// Built once (on every core: set-up is bitwise the same on every backend), copied per benchmark
// run: the surface-correction constants of 64 000 particles take seconds.
std::unique_ptr<PdSolver> pd_block(const exec::Space&) {
  static const std::unique_ptr<PdSolver> proto =
      make_bench_pd_block(40, exec::Space(exec::Backend::OpenMP, exec::hardware_threads()));
  return std::make_unique<PdSolver>(*proto);
}

void BM_PdBuildBonds(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block(exec::Space());
  const ParticleSet& ps = s->particles();
  PdBonds b;
  for (auto _ : st)
    pd_build_bonds(space, ps.vec3(s->attributes().x0), ps.real(s->attributes().volume),
                   ps.int32(s->attributes().material), ps.size(), s->params(), true, b);
  set_items(st, s->bonds().size(),
            sizeof(std::uint32_t) + sizeof(std::uint64_t) + 4 * sizeof(Real) + 1);
}

void BM_PdDilatation(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block(space);
  for (auto _ : st) s->compute_dilatation(space);
  // per bond streamed: neighbour index, length, omega, shear_omega, volume, plastic, intact; +
  // the neighbour's position and reference position (gathered, mostly cache hits)
  set_items(st, s->bonds().size(), sizeof(std::uint32_t) + 5 * sizeof(Real) + 1 + 2 * sizeof(Vec3));
}

void BM_PdForces(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block(space);
  s->compute_dilatation(space);
  for (auto _ : st) s->compute_forces(space);  // with the damage (issue 31: fused)
  // per bond streamed: neighbour, length, omega, shear_omega, volume, plastic, their mirrors of
  // the reverse bond (omega_r, shear_omega_r, plastic_r), intact; + x, x0 and the 16-byte
  // per-particle coefficients of j (gathered)
  set_items(st, s->bonds().size(),
            sizeof(std::uint32_t) + 8 * sizeof(Real) + 1 + 2 * sizeof(Vec3) + 4 * sizeof(Real));
}

// The damage pass on its own (pd_damage; a step before issue 31 ran it after the force pass,
// which now does its work while each row's flags are in cache): what the fusion saves.
void BM_PdDamage(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block(space);
  for (auto _ : st) s->update_damage(space);
  set_items(st, s->bonds().size(), 1);  // per bond: its intact flag
}

// Bond compaction (issue 5: "periodic compaction of broken bonds if it pays"): the dilatation +
// force passes of the block with a fraction of its bonds broken (pairs chosen by a hash, both
// directions), left in the CSR arrays (args: compacted 0) or removed by pd_compact_bonds first
// (compacted 1). Items are the directed bonds of the *unbroken* block, so items/s compare the
// same physical work. BM_PdCompact times the compaction itself.
std::unique_ptr<PdSolver> pd_block_broken(int percent) {
  auto s = pd_block(exec::Space());
  PdBonds& b = s->bonds();
  for (std::size_t i = 0; i < b.particles(); ++i)
    for (std::uint64_t k = b.offsets[i]; k < b.offsets[i + 1]; ++k) {
      const std::uint32_t j = b.neighbor[k];
      if (j < i) continue;
      std::uint64_t h = (std::uint64_t(i) << 32 | j) * 0x9E3779B97F4A7C15ull;
      h ^= h >> 29;
      if (h % 100 < std::uint64_t(percent)) b.intact[k] = b.intact[b.reverse[k]] = 0;
    }
  return s;
}

void BM_PdBrokenStep(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block_broken(int(st.range(2)));
  const std::size_t all = s->bonds().size();
  if (st.range(3)) pd_compact_bonds(space, s->bonds());
  for (auto _ : st) {
    s->compute_dilatation(space);
    s->compute_forces(space);
  }
  set_items(st, all, 0);
  st.counters["stored_bonds"] = double(s->bonds().size());
}

void BM_PdCompact(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block_broken(int(st.range(2)));
  const PdBonds full = s->bonds();
  for (auto _ : st) {
    st.PauseTiming();
    s->bonds() = full;
    st.ResumeTiming();
    pd_compact_bonds(space, s->bonds());
  }
  set_items(st, full.size(), 0);
}

void broken_args(benchmark::internal::Benchmark* b, bool both) {
  b->ArgNames({"backend", "threads", "broken_pct", "compacted"});
  for (int pct : {0, 25, 50, 75, 90})
    for (int c = 0; c <= (both ? 1 : 0); ++c) {
      b->Args({0, 1, pct, both ? c : 1});
      b->Args({1, 2, pct, both ? c : 1});
    }
  b->UseRealTime()->Unit(benchmark::kMillisecond);
}

void BM_PdContact(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block(space);
  std::vector<Vec3> f(s->particles().size());
  PdContactList list;
  pd_build_contact_list(space, s->particles().vec3(s->attributes().x), s->particles().size(),
                        Real(0.014), list);
  for (auto _ : st)
    pd_contact_forces(space, s->view(), s->bonds(), s->params(), Real(0.009), list, f.data());
  set_items(st, s->particles().size(), 2 * sizeof(Vec3));
}

void BM_PdContactList(benchmark::State& st) {
  const exec::Space space = space_of(st);
  auto s = pd_block(space);
  PdContactList list;
  for (auto _ : st)
    pd_build_contact_list(space, s->particles().vec3(s->attributes().x), s->particles().size(),
                          Real(0.014), list);
  set_items(st, s->particles().size(), sizeof(Vec3));
}

}  // namespace

BENCHMARK_CAPTURE(BM_P2G, mls_quadratic, Transfer::Mls, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2G, apic_quadratic, Transfer::Apic, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2G, flip_quadratic, Transfer::PicFlip, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2G, mls_cubic, Transfer::Mls, 3)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2GPath, sphere_blocks, true, kParticles, 0)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2GPath, sphere_colours, false, kParticles, 0)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2GPath, jelly_blocks, true, 97336, 8)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_P2GPath, jelly_colours, false, 97336, 8)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P, mls_quadratic, Transfer::Mls, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P, apic_quadratic, Transfer::Apic, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P, flip_quadratic, Transfer::PicFlip, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P, mls_cubic, Transfer::Mls, 3)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P2G, mls_quadratic, Transfer::Mls, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P2G, apic_quadratic, Transfer::Apic, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P2G, flip_quadratic, Transfer::PicFlip, 2)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_G2P2G, mls_cubic, Transfer::Mls, 3)->Apply(backend_args);
BENCHMARK(BM_GridUpdate)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_AulP2G, mls_quadratic, Transfer::Mls)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_AulP2G, flip_quadratic, Transfer::PicFlip)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_AulG2P, mls_quadratic, Transfer::Mls)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_AulG2P, flip_quadratic, Transfer::PicFlip)->Apply(backend_args);
BENCHMARK(BM_AulGridUpdate)->Apply(backend_args);
BENCHMARK(BM_AulConfigurationCheck)->Apply(backend_args);
BENCHMARK(BM_ObjectContact)->Apply(backend_args);
BENCHMARK(BM_DomainParticlesToCorners)->Apply(backend_args);
BENCHMARK(BM_DomainGridToParticles)->Apply(backend_args);
BENCHMARK(BM_DomainStep)->Apply(backend_args);
BENCHMARK(BM_DomainHessianAction)->Apply(backend_args);
BENCHMARK(BM_ImplicitOperator)->Apply(backend_args);
BENCHMARK(BM_CgIteration)->Apply(backend_args);
BENCHMARK(BM_ImplicitAssemble)->Apply(backend_args);
BENCHMARK(BM_SortAndActivate)->Apply(backend_args);
BENCHMARK(BM_StreamTriad)->Apply(backend_args);
BENCHMARK(BM_PeakFlops)->Apply(backend_args);
BENCHMARK(BM_Svd3)->Unit(benchmark::kNanosecond);
BENCHMARK(BM_PolarFast)->Unit(benchmark::kNanosecond);
BENCHMARK(BM_PolarFastLanes)->Unit(benchmark::kNanosecond);
BENCHMARK_CAPTURE(BM_Material, fixed_corotated, MaterialModel::FixedCorotated)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_Material, neo_hookean, MaterialModel::NeoHookean)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_Material, stvk_hencky, MaterialModel::StvkHencky)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_Material, snow, MaterialModel::Snow)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_Material, drucker_prager, MaterialModel::DruckerPrager)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_Material, von_mises, MaterialModel::VonMises)->Apply(backend_args);
BENCHMARK_CAPTURE(BM_Material, fluid, MaterialModel::Fluid)->Apply(backend_args);

BENCHMARK(BM_PdBuildBonds)->Apply(backend_args);
BENCHMARK(BM_PdDilatation)->Apply(backend_args);
BENCHMARK(BM_PdForces)->Apply(backend_args);
BENCHMARK(BM_PdDamage)->Apply(backend_args);
BENCHMARK(BM_PdContact)->Apply(backend_args);
BENCHMARK(BM_PdBrokenStep)->Apply([](benchmark::internal::Benchmark* b) { broken_args(b, true); });
BENCHMARK(BM_PdCompact)->Apply([](benchmark::internal::Benchmark* b) { broken_args(b, false); });
BENCHMARK(BM_PdContactList)->Apply(backend_args);

// BENCHMARK_MAIN with the SIMD path of the transfer kernels in the context (AMALGAM_SIMD forces one).
int main(int argc, char** argv) {
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::AddCustomContext("simd_path", amalgam::exec::simd_description());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
