// Whole substeps (sort, topology, P2G, grid update with colliders, G2P) are bitwise identical on
// Serial, OpenMP and TBB with 1 and 2 threads, for every transfer and both spline orders.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "core/exec/simd.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "test_util.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

using namespace amalgam;

namespace {
Scene small_scene(const std::string& transfer, int order,
                  const std::string& integrator = "explicit") {
  const std::string text = R"({
    "simulation": {"dx": 0.04, "order": )" +
                           std::to_string(order) + R"(, "transfer": ")" + transfer +
                           R"(", "frames": 1, "integrator": ")" + integrator +
                           R"(", "max_dt": 4e-3},
    "materials": {"a": {"model": "fixed_corotated", "density": 1000, "youngs_modulus": 2e4, "poisson_ratio": 0.3},
                  "b": {"model": "neo_hookean", "density": 500, "youngs_modulus": 1e4, "poisson_ratio": 0.2}},
    "objects": [
      {"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.6, 0.6, 0.5], "material": "a", "velocity": [0, -2, 0],
       "angular_velocity": [1, 2, 3]},
      {"shape": "sphere", "center": [0.5, 0.8, 0.45], "radius": 0.12, "material": "b", "velocity": [0.5, -3, 0]}],
    "colliders": [
      {"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "separate", "friction": 0.3},
      {"type": "sphere", "center": [0.45, 0.2, 0.4], "radius": 0.1, "boundary": "sticky", "velocity": [0, 0.5, 0]},
      {"type": "box", "center": [0.7, 0.3, 0.4], "half_extent": [0.05, 0.2, 0.3], "boundary": "slip"}]
  })";
  return parse_scene(text, "inline.json");
}

std::vector<Real> state_bytes(const MpmSolver& s) {
  std::vector<Real> out;
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  for (auto id : {a.x, a.v, a.C, a.F, a.plastic, a.temperature})
    if (id >= 0) out.insert(out.end(), ps.real(id), ps.real(id) + ps.size() * size_t(ps.width(id)));
  return out;
}

// Every material model with state (return mappings, F reset, melting under a heat source), the
// particle collision pass and a keyframed mesh collider (a cube sweeping through the snow).
Scene material_scene() {
  const std::string cube =
      (std::filesystem::temp_directory_path() / "amalgam_backend_cube.obj").string();
  {
    std::ofstream f(cube);
    for (int i = 0; i < 8; ++i)
      f << "v " << ((i & 1) ? 0.06 : -0.06) << " " << ((i & 2) ? 0.06 : -0.06) << " "
        << ((i & 4) ? 0.06 : -0.06) << "\n";
    f << "f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n";
  }
  const std::string text = R"({
    "simulation": {"dx": 0.04, "frames": 1},
    "materials": {
      "snow": {"model": "snow", "density": 400, "youngs_modulus": 1.4e5, "poisson_ratio": 0.2},
      "sand": {"model": "drucker_prager", "density": 2200, "youngs_modulus": 3.5e5, "friction_angle": 30, "cohesion": 10},
      "metal": {"model": "von_mises", "density": 2700, "youngs_modulus": 1e6, "yield_stress": 2e3, "hardening_modulus": 1e4},
      "water": {"model": "fluid", "density": 1000, "bulk_modulus": 1e5, "viscosity": 0.1},
      "wax": {"model": "neo_hookean", "density": 900, "youngs_modulus": 5e4,
              "melting": {"temperature": 320, "bulk_modulus": 5e4, "viscosity": 1}}},
    "objects": [
      {"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.5, 0.5, 0.5], "material": "snow", "velocity": [0, -3, 0]},
      {"shape": "box", "min": [0.55, 0.3, 0.3], "max": [0.7, 0.45, 0.5], "material": "sand", "velocity": [0, -2, 0]},
      {"shape": "sphere", "center": [0.4, 0.7, 0.4], "radius": 0.08, "material": "metal", "velocity": [0, -4, 0]},
      {"shape": "box", "min": [0.6, 0.55, 0.3], "max": [0.75, 0.7, 0.45], "material": "water", "velocity": [0, -1, 0]},
      {"shape": "box", "min": [0.2, 0.26, 0.6], "max": [0.4, 0.4, 0.75], "material": "wax", "temperature": 300}],
    "colliders": [{"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "sticky"},
                  {"type": "mesh", "file": ")" +
                           cube + R"(", "translate": [0.25, 0.4, 0.4], "boundary": "separate",
                   "friction": 0.5, "keyframes": [{"time": 0}, {"time": 0.05, "translate": [0.3, 0, 0], "rotate_degrees": [0, 0, 60]}]}],
    "heat_sources": [{"type": "half_space", "point": [0, 0.3, 0], "normal": [0, 1, 0], "temperature": 400, "rate": 200}]
  })";
  return parse_scene(text, "inline.json");
}
}  // namespace

// Runs `steps` CFL substeps of the scene on every backend configuration, expects the state to be
// bitwise identical to the first (serial) run, and returns that reference solver's state.
template <class OnReference>
std::vector<Real> run_everywhere(const Scene& scene, int steps, OnReference on_reference) {
  std::vector<Real> ref;
  for (const auto& c : test::all_configs()) {
    MpmSolver s = build_solver(scene);
    const exec::Space space(c.backend, c.threads);
    for (int i = 0; i < steps; ++i) s.step(space, s.stable_dt(space));
    const std::vector<Real> st = state_bytes(s);
    if (ref.empty()) {
      ref = st;
      on_reference(s);
      continue;
    }
    EXPECT_EQ(st.size(), ref.size());
    if (st.size() == ref.size()) {
      EXPECT_TRUE(test::bitwise_equal(st.data(), ref.data(), st.size())) << c.name();
    }
  }
  return ref;
}

class BackendDeterminism : public ::testing::TestWithParam<std::tuple<std::string, int>> {};

TEST_P(BackendDeterminism, TwentySubstepsBitwiseIdentical) {
  const auto [transfer, order] = GetParam();
  const Scene scene = small_scene(transfer, order);
  const std::vector<Real> ref = run_everywhere(scene, 20, [](const MpmSolver&) {});
  // And the state actually changed (the test compares a non-trivial evolution).
  MpmSolver fresh = build_solver(scene);
  fresh.sort_particles(exec::Space());
  EXPECT_FALSE(test::bitwise_equal(state_bytes(fresh).data(), ref.data(), ref.size()));
}

INSTANTIATE_TEST_SUITE_P(Transfers, BackendDeterminism,
                         ::testing::Combine(::testing::Values("mls", "apic", "flip", "pic"),
                                            ::testing::Values(2, 3)),
                         [](const auto& info) {
                           return std::get<0>(info.param) + "_order" +
                                  std::to_string(std::get<1>(info.param));
                         });

// The implicit integrator: Hessian cache, matrix-free action and diagonal (colour scatter), CG
// dot products and updates, constraint projections from all three boundary types, friction.
TEST(BackendDeterminism, ImplicitBitwiseIdentical) {
  for (const char* transfer : {"mls", "flip"}) {
    int iterations = 0;
    run_everywhere(small_scene(transfer, 2, "implicit"), 12, [&](const MpmSolver& s) {
      iterations = int(s.implicit()->counters().iterations);
      EXPECT_GT(s.implicit()->system().constraint_count(), 0u);  // colliders were in the solve
    });
    std::printf("%s: %d CG iterations in 12 steps\n", transfer, iterations);
    EXPECT_GT(iterations, 24) << transfer;  // real solves, not v* handed back
  }
}

TEST(BackendDeterminism, MaterialsWithStateBitwiseIdentical) {
  run_everywhere(material_scene(), 30, [](const MpmSolver& s) {
    // Non-trivial: some snow, sand and metal projected, some wax melted.
    const auto& ps = s.particles();
    const auto& a = s.attributes();
    int plastic = 0, melted = 0;
    for (size_t p = 0; p < ps.size(); ++p) {
      const MaterialParams& m = s.materials()[size_t(ps.int32(a.material)[p])];
      plastic += m.has_plastic_state() && ps.real(a.plastic)[p] != m.initial_plastic();
      melted += ps.real(a.temperature)[p] >= 320;
    }
    std::printf("particles with plastic flow: %d, melted: %d of %zu\n", plastic, melted, ps.size());
    EXPECT_GT(plastic, 10);
    EXPECT_GT(melted, 10);
  });
}

// Run-time vector width (core/exec/simd.hpp): the kernels compiled for AVX2 and AVX-512 give
// the baseline's state bit for bit, on Serial and on 2 TBB threads. Paths this CPU (or build)
// lacks are skipped, saying so.
namespace {
struct SimdGuard {  // restores the path a test found
  exec::SimdPath saved = exec::simd_path();
  ~SimdGuard() { exec::set_simd_path(saved); }
};

// The state after `steps` substeps of `scene` on every supported path and two configurations,
// compared with the baseline path on Serial.
void expect_same_on_every_path(const Scene& scene, int steps) {
  SimdGuard guard;
  std::vector<Real> ref;
  for (const exec::SimdPath path :
       {exec::SimdPath::Baseline, exec::SimdPath::Avx2, exec::SimdPath::Avx512}) {
    if (!exec::simd_path_supported(path)) {
      std::printf("SIMD path %s: skipped (%s)\n", exec::simd_path_name(path),
                  exec::simd_path_compiled(path) ? "this CPU lacks it" : "not in this build");
      continue;
    }
    exec::set_simd_path(path);
    for (const exec::Space& space : {exec::Space(), exec::Space(exec::Backend::TBB, 2)}) {
      MpmSolver s = build_solver(scene);
      for (int i = 0; i < steps; ++i) s.step(space, s.stable_dt(space));
      const std::vector<Real> st = state_bytes(s);
      if (ref.empty()) {
        ref = st;
        continue;
      }
      ASSERT_EQ(st.size(), ref.size());
      EXPECT_TRUE(test::bitwise_equal(st.data(), ref.data(), st.size()))
          << exec::simd_path_name(path) << " on " << space.describe();
    }
    if (path != exec::SimdPath::Baseline)
      std::printf("SIMD path %s: bitwise the baseline's\n", exec::simd_path_name(path));
  }
}
}  // namespace

TEST(SimdPaths, EveryTransferAndOrderBitwiseOnEveryPath) {
  if (exec::supported_simd_paths().size() < 2)
    GTEST_SKIP() << "only the baseline path runs here: " << exec::simd_description();
  for (const char* transfer : {"mls", "apic", "flip"})
    for (int order : {2, 3}) {
      SCOPED_TRACE(std::string(transfer) + " order " + std::to_string(order));
      expect_same_on_every_path(small_scene(transfer, order), 10);
    }
}

TEST(SimdPaths, MaterialsAndImplicitBitwiseOnEveryPath) {
  if (exec::supported_simd_paths().size() < 2)
    GTEST_SKIP() << "only the baseline path runs here: " << exec::simd_description();
  expect_same_on_every_path(material_scene(), 20);
  expect_same_on_every_path(small_scene("mls", 2, "implicit"), 6);
}

TEST(SimdPaths, ParseOverrideAndDescribe) {
  SimdGuard guard;
  EXPECT_EQ(exec::parse_simd_path("baseline"), exec::SimdPath::Baseline);
  EXPECT_EQ(exec::parse_simd_path("AUTO"), exec::best_simd_path());
  EXPECT_EQ(exec::supported_simd_paths().front(), exec::SimdPath::Baseline);
  try {
    exec::parse_simd_path("sse9");
    ADD_FAILURE() << "an unknown path was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("unknown SIMD path 'sse9'"), std::string::npos);
  }
  for (const exec::SimdPath p : {exec::SimdPath::Avx2, exec::SimdPath::Avx512}) {
    if (exec::simd_path_supported(p)) {
      exec::set_simd_path(p);
      EXPECT_EQ(exec::simd_path(), p);
      EXPECT_EQ(exec::simd_description().rfind(exec::simd_path_name(p), 0), 0u);
    } else {
      EXPECT_THROW(exec::set_simd_path(p), std::invalid_argument);
    }
  }
  exec::set_simd_path(exec::SimdPath::Baseline);
  EXPECT_EQ(exec::simd_description().rfind("baseline", 0), 0u);
}
