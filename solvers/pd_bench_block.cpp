#include "solvers/pd_bench_block.hpp"

#include <vector>

namespace amalgam {

std::unique_ptr<PdSolver> make_bench_pd_block(int n, const exec::Space& space) {
  PdMaterial m;
  m.bulk = Real(3.3e7);
  m.shear = Real(2e7);
  m.density = 2200;
  m.psi0 = pd_psi0_from_yield_stress(Real(1e9), Real(0.03015));
  m.plastic_cap = Real(0.2);
  m.critical_stretch = Real(0.05);
  PdSettings ps;
  ps.spacing = Real(0.01);
  ps.horizon = Real(0.03015);
  ps.contact = false;
  auto s = std::make_unique<PdSolver>(ps, std::vector<PdMaterial>{m});
  std::vector<Vec3> x;
  x.reserve(std::size_t(n) * std::size_t(n) * std::size_t(n));
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k)
        x.push_back(Vec3(Real(0.01 * (i + 0.5)), Real(0.01 * (j + 0.5)), Real(0.01 * (k + 0.5))));
  s->add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(1e-6));
  s->initialize(space);
  Vec3* px = s->particles().vec3(s->attributes().x);
  for (std::size_t i = 0; i < s->particles().size(); ++i)
    px[i] += Vec3(Real(1e-3) * px[i][0] + Real(5e-4) * px[i][1], 0, 0);
  return s;
}

}  // namespace amalgam
