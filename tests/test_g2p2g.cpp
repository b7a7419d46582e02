// The fused substep (G2P2G, solvers/mpm_fused.cpp): the maths first (it agrees with the two
// passes up to rounding, conserves momentum), then determinism (bitwise on every backend, thread
// count and vector path), then its fallback and its frame-start priming.
#include <gtest/gtest.h>

#include <cmath>

#include "core/exec/simd.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "test_util.hpp"

using namespace amalgam;

namespace {
// A box and a sphere of two elastic materials thrown at three colliders (as test_backends).
Scene scene_of(const std::string& transfer, int order, const std::string& pass,
               bool colliders = true, const std::string& gravity = "[0, -9.81, 0]") {
  std::string text = R"({
    "simulation": {"dx": 0.04, "order": )" +
                     std::to_string(order) + R"(, "transfer": ")" + transfer +
                     R"(", "frames": 1, "max_dt": 4e-3, "transfer_pass": ")" + pass +
                     R"(", "gravity": )" + gravity + R"(},
    "materials": {"a": {"model": "fixed_corotated", "density": 1000, "youngs_modulus": 2e4, "poisson_ratio": 0.3},
                  "b": {"model": "neo_hookean", "density": 500, "youngs_modulus": 1e4, "poisson_ratio": 0.2}},
    "objects": [
      {"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.6, 0.6, 0.5], "material": "a", "velocity": [0, -2, 0],
       "angular_velocity": [1, 2, 3]},
      {"shape": "sphere", "center": [0.5, 0.8, 0.45], "radius": 0.12, "material": "b", "velocity": [0.5, -3, 0]}])";
  if (colliders)
    text += R"(,
    "colliders": [
      {"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "separate", "friction": 0.3},
      {"type": "sphere", "center": [0.45, 0.2, 0.4], "radius": 0.1, "boundary": "sticky", "velocity": [0, 0.5, 0]},
      {"type": "box", "center": [0.7, 0.3, 0.4], "half_extent": [0.05, 0.2, 0.3], "boundary": "slip"}])";
  return parse_scene(text + "}", "inline.json");
}

// Snow, sand, metal, water and melting wax under a heat source, on a sticky floor.
Scene materials_scene() {
  return parse_scene(R"({
    "simulation": {"dx": 0.04, "frames": 1, "transfer_pass": "fused"},
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
    "colliders": [{"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "sticky"}],
    "heat_sources": [{"type": "half_space", "point": [0, 0.3, 0], "normal": [0, 1, 0], "temperature": 400, "rate": 200}]
  })",
                     "inline.json");
}

std::vector<Real> state_of(const MpmSolver& s) {
  std::vector<Real> out;
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  for (auto id : {a.x, a.x_lo, a.v, a.C, a.F, a.F_lo, a.plastic, a.temperature})
    if (id >= 0) out.insert(out.end(), ps.real(id), ps.real(id) + ps.size() * size_t(ps.width(id)));
  return out;
}

// Velocities by particle id (the storage is sorted by leaf).
std::vector<Vec3d> velocities_by_id(const MpmSolver& s) {
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  std::vector<Vec3d> v(ps.size());
  for (std::size_t p = 0; p < ps.size(); ++p)
    v[std::size_t(ps.int32(a.id)[p])] = ps.vec3(a.v)[p].cast<double>();
  return v;
}

Vec3d momentum(const MpmSolver& s) {
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  Vec3d P = Vec3d::Zero();
  for (std::size_t p = 0; p < ps.size(); ++p)
    P += double(s.materials()[std::size_t(ps.int32(a.material)[p])].mass(ps.real(a.volume0)[p])) *
         ps.vec3(a.v)[p].cast<double>();
  return P;
}

// The same dt sequence for both runs: the CFL steps of the two-pass run.
void run_pair(MpmSolver& two, MpmSolver& fused, int steps, const exec::Space& space) {
  for (int i = 0; i < steps; ++i) {
    const Real dt = two.stable_dt(space);
    two.step(space, dt);
    fused.step(space, dt);
  }
}
}  // namespace

class G2P2GMaths : public ::testing::TestWithParam<std::tuple<std::string, int>> {};

// Fused and two-pass substeps compute the same particle updates from grids that differ only by
// rounding (the force's dt applied at the node; the blocks summed in another order).
TEST_P(G2P2GMaths, AgreesWithTheTwoPassesUpToRounding) {
  const auto [transfer, order] = GetParam();
  MpmSolver two = build_solver(scene_of(transfer, order, "two_pass"));
  MpmSolver fused = build_solver(scene_of(transfer, order, "fused"));
  ASSERT_TRUE(fused.fused_eligible());
  ASSERT_FALSE(two.fused_eligible());
  const exec::Space space;
  run_pair(two, fused, 8, space);
  EXPECT_TRUE(fused.primed());
  const std::vector<Vec3d> xa = two.positions_by_id(), xb = fused.positions_by_id();
  const std::vector<Vec3d> va = velocities_by_id(two), vb = velocities_by_id(fused);
  double dx = 0, dv = 0, vmax = 0;
  for (std::size_t i = 0; i < xa.size(); ++i) {
    dx = std::max(dx, (xa[i] - xb[i]).norm());
    dv = std::max(dv, (va[i] - vb[i]).norm());
    vmax = std::max(vmax, va[i].norm());
  }
  std::printf("%s order %d: max |x - x'| = %.3g m (dx = 0.04), max |v - v'| = %.3g of %.3g m/s\n",
              transfer.c_str(), order, dx, dv, vmax);
  EXPECT_LT(dx, 1e-5 * 0.04);
  EXPECT_LT(dv, 1e-4 * vmax);
  EXPECT_GT(dv, 0);  // the grids do differ by rounding (the dt-free scatter)
  EXPECT_EQ(fused.fused_unfused(), 0u);
}

// Without gravity and colliders, the split P2G, the grid update and G2P conserve the particles'
// momentum (MLS, APIC: the affine transfer), as the two passes do.
TEST_P(G2P2GMaths, ConservesMomentumWithoutExternalForces) {
  const auto [transfer, order] = GetParam();
  if (transfer == "flip" || transfer == "pic") GTEST_SKIP() << "FLIP's blend does not conserve";
  MpmSolver s = build_solver(scene_of(transfer, order, "fused", false, "[0, 0, 0]"));
  const exec::Space space;
  const Vec3d P0 = momentum(s);
  double speed = 0;
  for (int i = 0; i < 10; ++i) {
    s.step(space, s.stable_dt(space));
    speed = std::max(speed, s.diagnostics(space).max_speed);
  }
  const Vec3d P1 = momentum(s);
  double mass = 0;
  {
    const auto& ps = s.particles();
    const auto& a = s.attributes();
    for (std::size_t p = 0; p < ps.size(); ++p)
      mass +=
          double(s.materials()[std::size_t(ps.int32(a.material)[p])].mass(ps.real(a.volume0)[p]));
  }
  std::printf("momentum drift %.3g of m |v|max = %.3g\n", (P1 - P0).norm(), mass * speed);
  EXPECT_LT((P1 - P0).norm(), 1e-5 * mass * speed);
}

INSTANTIATE_TEST_SUITE_P(Transfers, G2P2GMaths,
                         ::testing::Combine(::testing::Values("mls", "apic", "flip"),
                                            ::testing::Values(2, 3)),
                         [](const auto& info) {
                           return std::get<0>(info.param) + "_order" +
                                  std::to_string(std::get<1>(info.param));
                         });

namespace {
// `steps` CFL substeps of `scene` on every backend configuration: bitwise the serial run's.
std::vector<Real> bitwise_everywhere(const Scene& scene, int steps) {
  std::vector<Real> ref;
  for (const auto& c : test::all_configs()) {
    MpmSolver s = build_solver(scene);
    const exec::Space space(c.backend, c.threads);
    for (int i = 0; i < steps; ++i) s.step(space, s.stable_dt(space));
    EXPECT_TRUE(s.primed());
    const std::vector<Real> st = state_of(s);
    if (ref.empty()) {
      ref = st;
      continue;
    }
    EXPECT_EQ(st.size(), ref.size());
    if (st.size() == ref.size()) {
      EXPECT_TRUE(test::bitwise_equal(st.data(), ref.data(), st.size())) << c.name();
    }
  }
  return ref;
}
}  // namespace

TEST(G2P2GDeterminism, EveryTransferAndOrderBitwiseOnEveryBackend) {
  for (const char* transfer : {"mls", "apic", "flip"})
    for (int order : {2, 3}) {
      SCOPED_TRACE(std::string(transfer) + " order " + std::to_string(order));
      bitwise_everywhere(scene_of(transfer, order, "fused"), 16);
    }
}

TEST(G2P2GDeterminism, MaterialsWithStateBitwiseOnEveryBackend) {
  const std::vector<Real> ref = bitwise_everywhere(materials_scene(), 24);
  // ... and the same as the two passes' particle updates would give on the fused grids: the
  // material update ran (plastic flow, melting) inside the fused pass.
  MpmSolver s = build_solver(materials_scene());
  const exec::Space space;
  for (int i = 0; i < 24; ++i) s.step(space, s.stable_dt(space));
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  int plastic = 0, melted = 0;
  for (size_t p = 0; p < ps.size(); ++p) {
    const MaterialParams& m = s.materials()[size_t(ps.int32(a.material)[p])];
    plastic += m.has_plastic_state() && ps.real(a.plastic)[p] != m.initial_plastic();
    melted += ps.real(a.temperature)[p] >= 320;
  }
  EXPECT_GT(plastic, 10);
  EXPECT_GT(melted, 10);
}

TEST(G2P2GDeterminism, BitwiseOnEverySimdPath) {
  struct Guard {
    exec::SimdPath saved = exec::simd_path();
    ~Guard() { exec::set_simd_path(saved); }
  } guard;
  for (const Scene& scene : {scene_of("mls", 2, "fused"), scene_of("apic", 3, "fused"),
                             scene_of("flip", 2, "fused"), materials_scene()}) {
    std::vector<Real> ref;
    for (const exec::SimdPath path :
         {exec::SimdPath::Baseline, exec::SimdPath::Avx2, exec::SimdPath::Avx512}) {
      if (!exec::simd_path_supported(path)) {
        std::printf("SIMD path %s: skipped\n", exec::simd_path_name(path));
        continue;
      }
      exec::set_simd_path(path);
      for (const exec::Space& space : {exec::Space(), exec::Space(exec::Backend::TBB, 2)}) {
        MpmSolver s = build_solver(scene);
        for (int i = 0; i < 12; ++i) s.step(space, s.stable_dt(space));
        const std::vector<Real> st = state_of(s);
        if (ref.empty()) {
          ref = st;
          continue;
        }
        ASSERT_EQ(st.size(), ref.size());
        EXPECT_TRUE(test::bitwise_equal(st.data(), ref.data(), st.size()))
            << exec::simd_path_name(path) << " on " << space.describe();
      }
    }
  }
}

// A substep longer than the CFL step moves particles past the dilated blocks' margin: the fused
// substep falls back to the split P2G of the re-sorted particles, which is exactly what an
// unprimed substep starts with, and stays bitwise on every backend.
TEST(G2P2GFallback, AParticlePastTheMarginRescattersLikeAPrimedStart) {
  const Scene scene = scene_of("mls", 2, "fused");
  const exec::Space space;
  auto run = [&](bool unprime_after_fallback, const exec::Space& sp) {
    MpmSolver s = build_solver(scene);
    for (int i = 0; i < 6; ++i) {
      const std::uint64_t before = s.fused_fallbacks();
      s.step(sp, (i == 2 ? Real(20) : Real(1)) * s.stable_dt(sp));  // substep 2: 20 CFL steps
      if (unprime_after_fallback && s.fused_fallbacks() > before) s.unprime();
    }
    EXPECT_GT(s.fused_fallbacks(), 0u);
    return state_of(s);
  };
  const std::vector<Real> a = run(false, space), b = run(true, space);
  ASSERT_EQ(a.size(), b.size());
  EXPECT_TRUE(test::bitwise_equal(a.data(), b.data(), a.size()));
  for (const auto& c : test::all_configs()) {
    const std::vector<Real> s = run(false, exec::Space(c.backend, c.threads));
    EXPECT_TRUE(test::bitwise_equal(s.data(), a.data(), a.size())) << c.name();
  }
}

// A frame's start unprimes the grid (the checkpoint holds particles only): a run that unprimes at
// a substep is bitwise a fresh solver started from that substep's particles.
TEST(G2P2GFallback, UnprimedStartIsAFreshStartFromTheParticles) {
  const Scene scene = scene_of("apic", 2, "fused");
  const exec::Space space(exec::Backend::TBB, 2);
  MpmSolver a = build_solver(scene);
  for (int i = 0; i < 4; ++i) a.step(space, a.stable_dt(space));
  MpmSolver::Snapshot snap;
  a.save(snap);
  MpmSolver b = build_solver(scene);
  b.restore(snap);
  b.restore_clock(a.time(), a.step_count());
  a.unprime();
  for (int i = 0; i < 4; ++i) {
    const Real dt = a.stable_dt(space);
    a.step(space, dt);
    b.step(space, dt);
  }
  const std::vector<Real> sa = state_of(a), sb = state_of(b);
  ASSERT_EQ(sa.size(), sb.size());
  EXPECT_TRUE(test::bitwise_equal(sa.data(), sb.data(), sa.size()));
}
