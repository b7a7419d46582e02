// Loading by prescribed boundary velocities that change in time (issue 27, docs/scenes.md
// `boundary_conditions`): expressions of the position and t.
//
// Peridynamics: the end layer of a glass bar is driven by a one-period cosine velocity pulse
// V(t) = V0 (1 - cos(2 pi min(t, T) / T)) / 2. The driven layer moves by exactly V0 T / 2 (the
// drift uses the velocity at each step's midpoint), and the pulse travels down the bar at the
// bar speed sqrt(E / rho) with the driven amplitude (a 1-D bar: particle velocity = driving
// velocity behind the front).
//
// MPM: a region larger than a jelly block prescribes v = (0.2 sin(10 t), x t, 0) on its grid
// nodes. B-splines reproduce linear fields, so every particle's velocity after a substep is the
// field at its position and the substep's end time; explicit and implicit alike.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "core/errors.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "solvers/pd_solver.hpp"

using namespace amalgam;

namespace {

std::shared_ptr<const VectorField> field(const char* x, const char* y, const char* z) {
  auto f = std::make_shared<VectorField>();
  f->c[0] = Expression::parse(x), f->c[1] = Expression::parse(y), f->c[2] = Expression::parse(z);
  f->where = "test";
  return f;
}

struct Pulse {
  double end_displacement = 0;  // of the driven layer, after the pulse
  double transit = 0;           // time between the two sensors' V0/2 crossings
  double peak = 0;              // largest x velocity at the far sensor
  double velocity_error = 0;    // largest |v - V(t)| on the driven layer at a step's end
};

// Sensors: the mean x velocity over the cross-sections at lattice columns 15 and 45 (0.3 m
// apart, away from the driven end's horizon and before the far end's reflection returns).
Pulse drive_bar(bool driven_in_time) {
  const int nx = 60, ny = 4, nz = 4, sensors[2] = {15, 45};
  const double lc = 0.01, V0 = 0.5, T = 4e-5;
  PdSettings st;
  st.spacing = Real(lc);
  st.horizon = Real(3.015 * lc);
  st.gravity = Vec3::Zero();
  st.fracture = false;
  PdMaterial glass;
  glass.bulk = Real(48e9);
  glass.shear = Real(28.8e9);
  glass.density = 2200;
  PdSolver solver(st, {glass});
  std::vector<Vec3> x;
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) x.push_back(Vec3(Real(lc * a), Real(lc * b), Real(lc * c)));
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(lc * lc * lc));
  const char* pulse = driven_in_time ? "0.5*0.5*(1-cos(2*pi*min(t,4e-5)/4e-5))" : "0";
  solver.prescribe_velocity(Vec3(Real(-lc / 2), -1, -1), Vec3(Real(lc / 2), 1, 1),
                            field(pulse, "0", "0"));
  const exec::Space space(exec::Backend::Serial, 1);
  solver.initialize(space);
  const Vec3* v = solver.particles().vec3(solver.attributes().v);
  const Vec3* px = solver.particles().vec3(solver.attributes().x);
  const Vec3* lo = solver.particles().vec3(solver.attributes().x_lo);
  auto sensor_velocity = [&](int column) {
    double sum = 0;
    for (int k = 0; k < ny * nz; ++k) sum += double(v[std::size_t(column * ny * nz + k)][0]);
    return sum / (ny * nz);
  };
  auto V = [&](double t) { return V0 * 0.5 * (1 - std::cos(2 * M_PI * std::min(t, T) / T)); };
  Pulse r;
  const Real dt = Real(2e-7);
  double t_prev = 0, v_prev[2] = {0, 0}, t_half[2] = {-1, -1};
  for (int step = 1; step <= 600; ++step) {
    solver.step(space, dt);
    const double t = solver.time();
    r.velocity_error = std::max(r.velocity_error, std::abs(double(v[0][0]) - V(t)));
    for (int k = 0; k < 2; ++k) {
      const double vs = sensor_velocity(sensors[k]);
      if (k == 1) r.peak = std::max(r.peak, vs);
      if (t_half[k] < 0 && vs >= V0 / 2 && v_prev[k] < V0 / 2)
        t_half[k] = t_prev + (V0 / 2 - v_prev[k]) / (vs - v_prev[k]) * (t - t_prev);
      v_prev[k] = vs;
    }
    t_prev = t;
  }
  r.end_displacement = double(px[0][0]) + double(lo[0][0]);
  r.transit = t_half[1] - t_half[0];
  return r;
}

std::string region_scene(const std::string& integrator, bool maps = false) {
  return R"J({
  "simulation": {"dx": 0.05, "frames": 1, "gravity": [0, 0, 0], "integrator": ")J" +
         integrator + R"J("},
  "materials": {"jelly": {"density": 1000, "youngs_modulus": 1e4}},
  "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "jelly")J" +
         std::string(maps ? R"J(, "configuration": {"update": "adaptive"})J" : "") + R"J(}],
  "boundary_conditions": [{"min": [0.1, 0.1, 0.1], "max": [0.9, 0.9, 0.9],
                           "velocity": ["0.2*sin(10*t)", "x*t", 0]}]
})J";
}

}  // namespace

TEST(Loading, PdPulseDrivenInTimeTravelsAtTheBarSpeed) {
  const Pulse p = drive_bar(true);
  const double c = std::sqrt(72e9 / 2200), expected = 0.3 / c;
  std::printf(
      "pulse: end displacement %.6e m (exact %.6e), transit %.4e s (0.3 m / c = %.4e, %+.2f %%), "
      "peak %.4f m/s of 0.5, driven velocity error %.2e m/s\n",
      p.end_displacement, 0.5 * 4e-5 / 2, p.transit, expected, 100 * (p.transit / expected - 1),
      p.peak, p.velocity_error);
  EXPECT_NEAR(p.end_displacement, 0.5 * 4e-5 / 2, 1e-4 * 0.5 * 4e-5 / 2);
  EXPECT_LT(p.velocity_error, 1e-6);
  EXPECT_NEAR(p.transit / expected, 1, 0.03);
  EXPECT_NEAR(p.peak, 0.5, 0.05);
  // The same bar with a constant zero drive stays at rest: the pulse above is the drive's.
  const Pulse still = drive_bar(false);
  EXPECT_LT(still.peak, 0.01 * 0.5);  // the free surfaces' own small initial forces
  EXPECT_EQ(still.end_displacement, 0);
}

TEST(Loading, MpmRegionPrescribesGridVelocitiesInSpaceAndTime) {
  for (const char* variant : {"explicit", "implicit", "explicit A-ULMPM"}) {
    const std::string name = variant;
    const std::string integrator = name.substr(0, name.find(' '));
    MpmSolver s = build_solver(parse_scene(region_scene(integrator, name != integrator), "r.json"));
    const exec::Space space(exec::Backend::Serial, 1);
    double worst = 0;
    const Vec3 *x = nullptr, *v = nullptr;
    for (int step = 0; step < 40; ++step) {
      s.step(space, Real(2e-3));
      const double t = s.time();
      x = s.particles().vec3(s.attributes().x);  // the sort swaps buffers every substep
      v = s.particles().vec3(s.attributes().v);
      for (std::size_t p = 0; p < s.particles().size(); ++p) {
        worst = std::max(worst, std::abs(double(v[p][0]) - 0.2 * std::sin(10 * t)));
        worst = std::max(worst, std::abs(double(v[p][2])));
      }
    }
    // v_y = x t: particles inside a sticky region take its velocity at their new position
    // (collide_particles, after G2P).
    double worst_y = 0;
    const double t = s.time();
    for (std::size_t p = 0; p < s.particles().size(); ++p)
      worst_y = std::max(worst_y, std::abs(double(v[p][1]) - double(x[p][0]) * t));
    EXPECT_LT(worst, 1e-6) << variant;
    EXPECT_LT(worst_y, 1e-5) << variant;
  }
}

TEST(Loading, BoundaryExpressionErrorsNameTheKey) {
  const std::string pd = R"({
  "simulation": {"method": "peridynamics", "dx": 0.02},
  "materials": {"glass": {"model": "peridynamic", "density": 2200, "youngs_modulus": 1e9}},
  "objects": [{"shape": "box", "min": [0,0,0], "max": [0.2,0.06,0.06], "material": "glass"}],
  "boundary_conditions": [{"min": [0,0,0], "max": [0.01,0.06,0.06], "velocity": [V, 0, 0]}]
})";
  auto with = [&](const std::string& v) {
    std::string s = pd;
    return s.replace(s.find("V,"), 1, v);
  };
  // Not finite at t = 0 on a driven particle: an input error at set-up.
  try {
    build_pd_solver(parse_scene(with("\"log(t)\""), "b.json"));
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("b.json: /boundary_conditions/0/velocity/0: \"log(t)\""),
              std::string::npos)
        << e.what();
  }
  // Not finite later: the run stops with the condition, the time and the position named.
  PdSolver s = build_pd_solver(parse_scene(with("\"sqrt(1e-6-t)\""), "b.json"));
  const exec::Space space(exec::Backend::Serial, 1);
  s.initialize(space);
  try {
    for (int k = 0; k < 20; ++k) s.step(space, Real(1e-7));
    FAIL();
  } catch (const SimulationError& e) {
    EXPECT_NE(
        std::string(e.what()).find("/boundary_conditions/0/velocity/0: \"sqrt(1e-6-t)\" gives"),
        std::string::npos)
        << e.what();
  }
  // An MPM region's field that is not finite at a corner at t = 0.
  const std::string mpm = region_scene("explicit");
  std::string bad = mpm;
  bad.replace(bad.find("\"0.2*sin(10*t)\""), 15, "\"sqrt(0.2-x)\"");
  try {
    build_solver(parse_scene(bad, "r.json"));
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("r.json: /boundary_conditions/0/velocity/0"),
              std::string::npos)
        << e.what();
  }
}
