#include "solvers/bench_scene.hpp"

#include <cmath>
#include <random>

#include "core/geometry/lattice.hpp"
#include "solvers/mpm_enriched.hpp"

namespace amalgam {

MpmSolver make_bench_sphere(const BenchSceneOptions& o) {
  MpmSettings s;
  s.dx = o.dx;
  s.order = o.order;
  s.transfer = o.transfer;
  s.fused = o.fused;
  s.sort_when_needed = o.sort_when_needed;
  s.implicit = o.implicit;
  s.configuration_maps = o.lagrangian;
  s.domains.enabled = o.domains;
  MaterialParams m;
  if (o.material) {
    m = *o.material;
  } else {
    const Lame l = Lame::from_young_poisson(o.youngs_modulus, 0.3);
    m.mu = l.mu;
    m.lambda = l.lambda;
    m.density = 1000;
  }
  Collider floor;
  floor.origin = Vec3(0, Real(0.15), 0);
  floor.normal = Vec3::UnitY();
  floor.friction = Real(0.2);
  MpmSolver solver(s, {m}, {floor});
  const double r = 0.3;
  const Vec3 v0(0, Real(-1), 0), omega(0, Real(2), Real(1)), centre = Vec3::Constant(Real(0.5));
  if (o.domains) {  // a lattice of spacing h with about o.particles points inside the sphere
    const double h = std::cbrt(4.0 / 3.0 * M_PI * r * r * r / double(o.particles));
    const long long n = (long long)std::ceil(2 * r / h), dims[3] = {n, n, n};
    const std::vector<Vec3> x = sample_lattice(
        Vec3d::Constant(0.5 - r), dims, h, 0.0, 1,
        [&](const Vec3d& p) { return (p - Vec3d::Constant(0.5)).squaredNorm() <= r * r; });
    solver.add_particles(x, v0, omega, centre, 0, Real(h * h * h));
    solver.enriched()->add_object(solver, 0, Real(h));
    return solver;
  }
  std::mt19937_64 rng(12345);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<Vec3> x;
  x.reserve(o.particles);
  while (x.size() < o.particles) {
    const Vec3d p(u(rng), u(rng), u(rng));
    if (p.squaredNorm() <= 1.0) x.push_back((Vec3d::Constant(0.5) + r * p).cast<Real>());
  }
  const Real vol = Real(4.0 / 3.0 * M_PI * r * r * r / double(o.particles));
  if (o.lagrangian && o.objects == 2) {
    std::vector<Vec3> halves[2];
    for (const Vec3& p : x) halves[p[0] < Real(0.5) ? 0 : 1].push_back(p);
    for (const auto& h : halves)
      solver.add_particles(h, v0, omega, centre, 0, vol, o.temperature, o.policy);
  } else {
    solver.add_particles(x, v0, omega, centre, 0, vol, o.temperature, o.policy);
  }
  return solver;
}

}  // namespace amalgam
