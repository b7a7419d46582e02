// The two passes re-sorted only when needed (simulation.sort "when_needed", solvers/mpm_fused.cpp:
// MpmSolver::step_sorted_when_needed): the maths first (within rounding of the two passes sorted
// every substep, with particles outside their bins between sorts), then determinism (bitwise on
// every backend, thread count and vector path), then restarts (an unprimed substep is a fresh
// start from the particles).
#include <gtest/gtest.h>

#include <cmath>

#include "core/exec/simd.hpp"
#include "core/math/bspline.hpp"
#include "io/scene.hpp"
#include "mpm_test_scenes.hpp"
#include "solvers/factory.hpp"
#include "test_util.hpp"

using namespace amalgam;
using namespace amalgam::test;

namespace {
const std::string kLazy = R"(, "sort": "when_needed")";
const std::string kEvery = R"(, "sort": "every_substep")";

// Whether some particle's stencil base lies outside its bin's leaf footprint (it would be in
// another bin if the particles were sorted now).
template <int Order>
bool particles_outside_their_bins(const MpmSolver& s, Real dx) {
  const BinTable& bins = s.bins();
  const Vec3* x = s.particles().vec3(s.attributes().x);
  const Real inv_dx = Real(1) / dx;
  for (std::size_t b = 0; b < bins.count(); ++b)
    for (std::uint32_t q = bins.start[b]; q < bins.start[b + 1]; ++q)
      for (int a = 0; a < 3; ++a) {
        const int d = BSpline<Order>::base(x[q][a] * inv_dx) - bins.leaf[b][a] * kLeafDim;
        if (d < 0 || d > kLeafDim - 1) return true;
      }
  return false;
}
}  // namespace

class LazySortMaths : public ::testing::TestWithParam<std::tuple<std::string, int>> {};

// Over 50 CFL substeps of the falling bodies (three colliders): the particles are re-sorted far
// fewer times than there are substeps, some substeps end with particles outside their bin's leaf
// footprint and no re-sort, and the positions stay within rounding of the run sorted every substep
// (the same dt sequence; the grids differ only in the order each node adds its particles).
TEST_P(LazySortMaths, AgreesWithSortingEverySubstep) {
  const auto [transfer, order] = GetParam();
  MpmSolver every = build_solver(small_scene(transfer, order, "explicit", kEvery));
  MpmSolver lazy = build_solver(small_scene(transfer, order, "explicit", kLazy));
  ASSERT_FALSE(every.sort_when_needed_eligible());
  ASSERT_TRUE(lazy.sort_when_needed_eligible());
  ASSERT_FALSE(lazy.fused_eligible());
  const exec::Space space(exec::Backend::TBB, 2);
  int outside_kept = 0;
  // (At substep 49 of the MLS run a particle reaches the box collider's top face, y = 0.5, and
  // whether it touches is decided by rounding: the runs part by 2.7e-5 m there; up to substep 48
  // they agree to 5e-8 m, as the fused pass does with the two passes.)
  const int steps = 45;
  for (int i = 0; i < steps; ++i) {
    const Real dt = every.stable_dt(space);
    every.step(space, dt);
    const std::uint64_t before = lazy.lazy_resorts();
    lazy.step(space, dt);
    if (i == 0 || lazy.lazy_resorts() != before) continue;  // sorted this substep
    outside_kept += order == 2 ? particles_outside_their_bins<2>(lazy, Real(0.04))
                               : particles_outside_their_bins<3>(lazy, Real(0.04));
  }
  EXPECT_TRUE(lazy.primed());
  const std::vector<Vec3d> xa = every.positions_by_id(), xb = lazy.positions_by_id();
  double dx = 0;
  for (std::size_t i = 0; i < xa.size(); ++i) dx = std::max(dx, (xa[i] - xb[i]).norm());
  std::printf(
      "%s order %d, %d substeps: %llu re-sorts, %d substeps ended with particles outside "
      "their bin; max |x - x'| = %.3g m (dx = 0.04)\n",
      transfer.c_str(), order, steps, static_cast<unsigned long long>(lazy.lazy_resorts()),
      outside_kept, dx);
  EXPECT_GT(outside_kept, 0);
  EXPECT_GT(lazy.lazy_resorts(), 0u);
  EXPECT_LT(lazy.lazy_resorts(), std::uint64_t(steps / 3));
  EXPECT_EQ(lazy.lazy_unfit(), 0u);
  EXPECT_LT(dx, 1e-5 * 0.04);
}

INSTANTIATE_TEST_SUITE_P(Transfers, LazySortMaths,
                         ::testing::Values(std::make_tuple("mls", 2), std::make_tuple("apic", 3),
                                           std::make_tuple("flip", 2)),
                         [](const auto& info) {
                           return std::get<0>(info.param) + "_order" +
                                  std::to_string(std::get<1>(info.param));
                         });

TEST(LazySortDeterminism, EveryTransferAndOrderBitwiseOnEveryBackend) {
  for (const char* transfer : {"mls", "apic", "flip"})
    for (int order : {2, 3}) {
      SCOPED_TRACE(std::string(transfer) + " order " + std::to_string(order));
      run_everywhere(small_scene(transfer, order, "explicit", kLazy), 30, [](const MpmSolver& s) {
        EXPECT_TRUE(s.primed());
        EXPECT_GT(s.lazy_resorts(), 0u);
      });
    }
}

// Every material with state, a heat source and a keyframed mesh collider pushing particles.
TEST(LazySortDeterminism, MaterialsWithStateBitwiseOnEveryBackend) {
  run_everywhere(material_scene(kLazy), 24, [](const MpmSolver& s) {
    EXPECT_TRUE(s.sort_when_needed_eligible());
    expect_plastic_flow_and_melting(s);
  });
}

// The AVX2 and AVX-512 builds of the dilated kernels give the baseline's bits (Serial, 2 TBB).
TEST(LazySortDeterminism, BitwiseOnEverySimdPath) {
  expect_bitwise_on_every_simd_path(kLazy, 20);
}

// A substep longer than the CFL step moves particles past the dilated blocks' margin: the next
// substep re-sorts, which is exactly what an unprimed substep does, bitwise on every backend.
TEST(LazySortRestart, AParticlePastTheMarginResortsLikeAnUnprimedStart) {
  const Scene scene = small_scene("mls", 2, "explicit", kLazy);
  auto run = [&](bool unprime_after_long_step, const exec::Space& sp) {
    MpmSolver s = build_solver(scene);
    for (int i = 0; i < 6; ++i) {
      s.step(sp, (i == 2 ? Real(20) : Real(1)) * s.stable_dt(sp));  // substep 2: 20 CFL steps
      if (unprime_after_long_step && i == 2) s.unprime();
    }
    if (!unprime_after_long_step) EXPECT_GT(s.lazy_resorts(), 0u);
    return state_bytes(s);
  };
  const std::vector<Real> a = run(false, exec::Space()), b = run(true, exec::Space());
  ASSERT_EQ(a.size(), b.size());
  EXPECT_TRUE(bitwise_equal(a.data(), b.data(), a.size()));
  for (const auto& c : all_configs()) {
    const std::vector<Real> s = run(false, exec::Space(c.backend, c.threads));
    EXPECT_TRUE(bitwise_equal(s.data(), a.data(), a.size())) << c.name();
  }
}

// A frame's start unprimes the bins (a checkpoint holds particles only): a run unprimed at a
// substep is bitwise a fresh solver started from that substep's particles and clock, and
// different from the run that kept its bins (the bins' order is part of the rounding).
TEST(LazySortRestart, UnprimedStartIsAFreshStartFromTheParticles) {
  expect_unprimed_start_is_a_fresh_start(small_scene("apic", 2, "explicit", kLazy), 8);
}

// A particle moved out of its bin's dilated block after G2P (as a particle collision may push it):
// P2G finds it, re-sorts and scatters again, which is what a substep starting with a sort
// computes (the run unprimed there), bitwise on every backend.
TEST(LazySortRestart, AParticleMovedAfterG2PIsFoundByP2G) {
  const Scene scene = small_scene("mls", 2, "explicit", kLazy);
  auto run = [&](bool unprime_after_move, const exec::Space& sp) {
    MpmSolver s = build_solver(scene);
    s.step(sp, s.stable_dt(sp));
    s.step(sp, s.stable_dt(sp));
    // Particle 0 of bin 0 three nodes below the bin's footprint in x: outside its dilated block.
    const std::uint32_t q = s.bins().start[0];
    Vec3* x = s.particles().vec3(s.attributes().x);
    x[q][0] = Real(s.bins().leaf[0][0] * kLeafDim - 3) * Real(0.04);
    if (unprime_after_move) s.unprime();
    const std::uint64_t before = s.lazy_resorts();
    s.step(sp, s.stable_dt(sp));
    if (!unprime_after_move) EXPECT_EQ(s.lazy_resorts(), before + 1);  // found by P2G
    for (int i = 0; i < 3; ++i) s.step(sp, s.stable_dt(sp));
    return state_bytes(s);
  };
  const std::vector<Real> a = run(false, exec::Space()), b = run(true, exec::Space());
  ASSERT_EQ(a.size(), b.size());
  EXPECT_TRUE(bitwise_equal(a.data(), b.data(), a.size()));
  for (const auto& c : all_configs()) {
    const std::vector<Real> s = run(false, exec::Space(c.backend, c.threads));
    EXPECT_TRUE(bitwise_equal(s.data(), a.data(), a.size())) << c.name();
  }
}
