// Contact between A-ULMPM objects through the global grid (kernels/object_contact.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "core/errors.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "test_util.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

using namespace amalgam;

namespace {

// Two soft cubes (0.1 m, total Lagrangian) flying at each other at +-v without gravity.
Scene head_on(const std::string& contact, double v = 0.5) {
  const std::string text = R"({
    "simulation": {"dx": 0.02, "frames": 1, "gravity": [0, 0, 0], "cfl": 0.4)" +
                           (contact.empty() ? std::string() : ", \"contact\": " + contact) + R"(},
    "materials": {"rubber": {"model": "neo_hookean", "density": 1000, "youngs_modulus": 2e4, "poisson_ratio": 0.3}},
    "objects": [{"shape": "box", "min": [0.3, 0.45, 0.45], "max": [0.4, 0.55, 0.55], "material": "rubber",
                 "jitter": 0, "velocity": [)" +
                           std::to_string(v) + R"(, 0, 0],
                 "configuration": {"update": "total_lagrangian"}},
                {"shape": "box", "min": [0.46, 0.45, 0.45], "max": [0.56, 0.55, 0.55], "material": "rubber",
                 "jitter": 0, "velocity": [)" +
                           std::to_string(-v) + R"(, 0, 0],
                 "configuration": {"update": "total_lagrangian"}}]})";
  return parse_scene(text, "head_on.json");
}

struct Bodies {
  double xa = 0, xb = 0, va = 0, vb = 0;  // centroids and mean x-velocities of objects 0 and 1
  double px = 0, ma = 0, mb = 0;          // total x-momentum, masses
  double min_gap = 1e30;                  // smallest x gap between the bodies' particles
};

Bodies measure(const MpmSolver& s) {
  const auto& ps = s.particles();
  const Vec3* x = ps.vec3(s.attributes().x);
  const Vec3* v = ps.vec3(s.attributes().v);
  const std::int32_t* k = ps.int32(s.aul()->attributes().object);
  Bodies b;
  double amax = -1e30, bmin = 1e30;
  for (size_t p = 0; p < ps.size(); ++p) {
    const double mp = double(s.particle_mass(p));
    b.px += mp * double(v[p][0]);
    if (k[p] == 0) {
      b.xa += mp * double(x[p][0]), b.va += mp * double(v[p][0]), b.ma += mp;
      amax = std::max(amax, double(x[p][0]));
    } else {
      b.xb += mp * double(x[p][0]), b.vb += mp * double(v[p][0]), b.mb += mp;
      bmin = std::min(bmin, double(x[p][0]));
    }
  }
  b.xa /= b.ma, b.va /= b.ma, b.xb /= b.mb, b.vb /= b.mb;
  b.min_gap = bmin - amax;
  return b;
}

}  // namespace

// Without contact the cubes pass through each other; with it they meet and never overlap, stick
// (rebounding only through their own elasticity) or separate (Bardenhagen contact) with a
// restitution, and the total momentum stays zero. Explicit and semi-implicit (eq. 26).
TEST(ObjectContact, HeadOnCubesCollideInsteadOfPassingThrough) {
  const exec::Space space(test::parallel_backend(), 2);
  struct Case {
    const char* mode;
    double v0;
    const char* integrator;
  };
  for (const Case c : {Case{"none", 0.5, "explicit"}, Case{"stick", 0.5, "explicit"},
                       Case{"separate", 0.5, "explicit"}, Case{"stick", 2.0, "explicit"},
                       Case{"separate", 2.0, "explicit"}, Case{"separate", 0.5, "implicit"}}) {
    MpmSolver s = build_solver(head_on(
        std::string("{\"mode\": \"") + c.mode + "\"}, \"integrator\": \"" + c.integrator + "\"",
        c.v0));
    const Bodies b0 = measure(s);
    const double p0 = b0.ma * c.v0;  // |p| of one body
    double t = 0, min_gap = 1e30, max_px = 0;
    while (t < 0.5 / (c.v0 + 0.5)) {
      const Real dt = std::min(s.stable_dt(space), Real(2e-3));
      s.step(space, dt);
      t += double(dt);
      const Bodies b = measure(s);
      min_gap = std::min(min_gap, b.min_gap);
      max_px = std::max(max_px, std::abs(b.px));
    }
    const Bodies b = measure(s);
    std::printf(
        "%-8s v0 %.1f %-8s: centroids %.4f %.4f, velocities %+.4f %+.4f, min gap %+.4f m, "
        "max |p_x| / p0 %.1e, contact nodes %llu\n",
        c.mode, c.v0, c.integrator, b.xa, b.xb, b.va, b.vb, min_gap, max_px / p0,
        (unsigned long long)s.aul()->contact_nodes());
    const std::string what =
        std::string(c.mode) + " " + c.integrator + " v0 " + std::to_string(c.v0);
    if (std::string(c.mode) == "none") {
      EXPECT_LT(min_gap, -0.15) << "without contact the cubes must pass through each other";
      EXPECT_EQ(s.aul()->contact_nodes(), 0u);
      continue;
    }
    EXPECT_GT(min_gap, 0.0) << what << ": the cubes' particles overlapped";
    EXPECT_LT(b.xa, b.xb - 0.1) << what;
    EXPECT_LT(max_px / p0, 1e-4) << what << ": momentum not conserved";
    EXPECT_LT(b.va, 0.0) << what << ": object 0 must move back after the impact";
    EXPECT_GT(b.vb, 0.0) << what;
    if (std::string(c.mode) == "separate") {
      EXPECT_GT(-b.va / c.v0, 0.4) << what << ": restitution";
    }
  }
}

namespace {
// A 0.1 m block (object 1) slides at 1 m/s along a slab (object 0) held by a sticky floor.
Scene sliding_block(const std::string& contact) {
  const std::string text = R"({
    "simulation": {"dx": 0.02, "frames": 1, "cfl": 0.4, "contact": )" +
                           contact + R"(},
    "materials": {"rubber": {"model": "neo_hookean", "density": 1000, "youngs_modulus": 2e5, "poisson_ratio": 0.3}},
    "objects": [{"shape": "box", "min": [0.2, 0.1, 0.4], "max": [0.8, 0.2, 0.6], "material": "rubber",
                 "jitter": 0, "configuration": {"update": "total_lagrangian"}},
                {"shape": "box", "min": [0.3, 0.215, 0.45], "max": [0.4, 0.315, 0.55], "material": "rubber",
                 "jitter": 0, "velocity": [1, 0, 0], "configuration": {"update": "total_lagrangian"}}],
    "colliders": [{"type": "half_space", "point": [0, 0.1, 0], "normal": [0, 1, 0], "boundary": "sticky"}]})";
  return parse_scene(text, "slide.json");
}
}  // namespace

// Coulomb friction between objects: the block lands on the slab and decelerates at mu g (the
// slab is held by the floor); without friction it keeps its speed.
TEST(ObjectContact, SlidingBlockDeceleratesAtMuG) {
  const exec::Space space(test::parallel_backend(), 2);
  for (const double mu : {0.0, 0.2, 0.5}) {
    MpmSolver s = build_solver(
        sliding_block("{\"mode\": \"separate\", \"friction\": " + std::to_string(mu) + "}"));
    double t = 0;
    std::vector<double> ts, vs;
    while (t < 0.16) {
      const Real dt = s.stable_dt(space);
      s.step(space, dt);
      t += double(dt);
      const Bodies b = measure(s);
      ts.push_back(t), vs.push_back(b.vb);
    }
    // least-squares slope of v(t) over [0.05, 0.15] s
    double st = 0, sv = 0, stt = 0, stv = 0, n = 0;
    for (size_t i = 0; i < ts.size(); ++i)
      if (ts[i] >= 0.05 && ts[i] <= 0.15)
        st += ts[i], sv += vs[i], stt += ts[i] * ts[i], stv += ts[i] * vs[i], ++n;
    const double slope = (n * stv - st * sv) / (n * stt - st * st);
    std::printf(
        "mu %.1f: v(%.2f s) %.4f, deceleration over [0.05, 0.15] s %.3f m/s^2 (mu g = %.3f)\n", mu,
        ts.back(), vs.back(), -slope, mu * 9.81);
    // Measured: 0.021 (mu 0), 1.942 (mu 0.2: 1 % under mu g), 4.484 (mu 0.5: 9 % under).
    EXPECT_NEAR(-slope, mu * 9.81, 0.05 + 0.12 * mu * 9.81) << "mu " << mu;
  }
}

// Contact is deterministic: every backend and thread count gives the serial run bit for bit
// (FLIP, whose v_new - v_old lanes the contact also corrects, and MLS; cubes spinning into each
// other so that friction acts).
TEST(ObjectContact, BitwiseIdenticalOnEveryBackend) {
  for (const char* transfer : {"flip", "mls"}) {
    const std::string text = std::string(R"({
      "simulation": {"dx": 0.02, "frames": 1, "gravity": [0, 0, 0], "transfer": ")") +
                             transfer + R"(",
                     "contact": {"mode": "separate", "friction": 0.4}},
      "materials": {"rubber": {"model": "neo_hookean", "density": 1000, "youngs_modulus": 2e4, "poisson_ratio": 0.3}},
      "objects": [{"shape": "box", "min": [0.3, 0.45, 0.45], "max": [0.4, 0.55, 0.55], "material": "rubber",
                   "velocity": [1, 0, 0], "angular_velocity": [3, 0, 0], "configuration": {"update": "total_lagrangian"}},
                  {"shape": "sphere", "center": [0.48, 0.5, 0.5], "radius": 0.05, "material": "rubber",
                   "velocity": [-1, 0.2, 0], "configuration": {"update": "adaptive", "epsilon": 0.01, "eta": 0.05}}]})";
    const Scene scene = parse_scene(text, "bitwise_contact.json");
    std::vector<Real> ref;
    std::uint64_t ref_nodes = 0;
    for (const auto& c : test::all_configs()) {
      MpmSolver s = build_solver(scene);
      const exec::Space space(c.backend, c.threads);
      for (int i = 0; i < 30; ++i) s.step(space, s.stable_dt(space));
      const auto& ps = s.particles();
      std::vector<Real> st;
      for (auto id : {s.attributes().x, s.attributes().v, s.attributes().C, s.attributes().F})
        if (id >= 0)  // flip keeps no C
          st.insert(st.end(), ps.real(id), ps.real(id) + ps.size() * size_t(ps.width(id)));
      if (ref.empty()) {
        ref = st;
        ref_nodes = s.aul()->contact_nodes();
        std::printf("%s: %llu contact node corrections in 30 substeps\n", transfer,
                    (unsigned long long)ref_nodes);
        EXPECT_GT(ref_nodes, 100u) << "the test must exercise contact";
        continue;
      }
      ASSERT_EQ(st.size(), ref.size());
      EXPECT_TRUE(test::bitwise_equal(st.data(), ref.data(), st.size()))
          << transfer << " " << c.name();
      EXPECT_EQ(s.aul()->contact_nodes(), ref_nodes) << transfer << " " << c.name();
    }
  }
}

// The scene file's contact block: modes, friction only with separate, MPM with maps only.
TEST(ObjectContact, SceneKeys) {
  EXPECT_EQ(head_on("").mpm.contact.mode, ObjectContactMode::Stick);
  const Scene sep = head_on(R"({"mode": "separate", "friction": 0.3})");
  EXPECT_EQ(sep.mpm.contact.mode, ObjectContactMode::Separate);
  EXPECT_FLOAT_EQ(float(sep.mpm.contact.friction), 0.3f);
  EXPECT_EQ(head_on(R"({"mode": "none"})").mpm.contact.mode, ObjectContactMode::None);
  EXPECT_THROW(head_on(R"({"mode": "glue"})"), InputError);
  EXPECT_THROW(head_on(R"({"mode": "stick", "friction": 0.3})"), InputError);
  EXPECT_THROW(head_on(R"({"friction": -1, "mode": "separate"})"), InputError);
}

// Objects keep their references in lanes 2048 cells apart along x: an object 2048 cells to the
// left of another lands in the other's lane. That is an error naming both, with or without
// contact (sharing reference nodes would couple them at their reference positions).
TEST(ObjectContact, ObjectsSharingALaneAreAnError) {
  for (const char* mode : {"stick", "none"}) {
    const std::string text = std::string(R"({
      "simulation": {"dx": 0.01, "frames": 1, "contact": {"mode": ")") +
                             mode + R"("}},
      "materials": {"rubber": {"model": "neo_hookean", "density": 1000, "youngs_modulus": 2e4, "poisson_ratio": 0.3}},
      "objects": [{"shape": "box", "min": [0.5, 0.5, 0.5], "max": [0.6, 0.6, 0.6], "material": "rubber",
                   "configuration": {"update": "total_lagrangian"}},
                  {"shape": "box", "min": [-19.96, 0.5, 0.5], "max": [-19.86, 0.6, 0.6], "material": "rubber",
                   "configuration": {"update": "total_lagrangian"}}]})";
    MpmSolver s = build_solver(parse_scene(text, "lanes.json"));
    const exec::Space space(exec::Backend::Serial, 1);
    try {
      s.step(space, Real(1e-4));
      ADD_FAILURE() << mode << ": expected a SimulationError";
    } catch (const SimulationError& e) {
      EXPECT_NE(std::string(e.what()).find("objects 0 and 1 reach the same reference-grid leaf"),
                std::string::npos)
          << e.what();
    }
  }
}
