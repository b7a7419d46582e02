// Whole substeps (sort, topology, P2G, grid update with colliders, G2P) are bitwise identical on
// Serial, OpenMP and TBB with 1 and 2 threads, for every transfer and both spline orders.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <limits>
#include <random>

#include "core/exec/simd.hpp"
#include "kernels/material_update.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "mpm_test_scenes.hpp"
#include "test_util.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

using namespace amalgam;

using namespace amalgam::test;

class BackendDeterminism : public ::testing::TestWithParam<std::tuple<std::string, int>> {};

TEST_P(BackendDeterminism, TwentySubstepsBitwiseIdentical) {
  const auto [transfer, order] = GetParam();
  const Scene scene = small_scene(transfer, order);
  const std::vector<Real> ref = run_everywhere(scene, 20, [](const MpmSolver&) {});
  // And the state actually changed (the test compares a non-trivial evolution).
  MpmSolver fresh = build_solver(scene);
  // PIC/FLIP of these elastic materials keeps no affine matrix C (MpmSolver::keeps_affine).
  EXPECT_EQ(fresh.attributes().C >= 0, transfer == "mls" || transfer == "apic");
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
  run_everywhere(material_scene(), 30, expect_plastic_flow_and_melting);
}

// FLIP with viscous materials (Newtonian water, melting wax) keeps C, where G2P stores grad v for
// the viscous stress: bitwise too (the elastic FLIP case above runs without C).
TEST(BackendDeterminism, ViscousFlipKeepsTheVelocityGradient) {
  const Scene scene = material_scene(R"(, "transfer": "flip")");
  EXPECT_GE(build_solver(scene).attributes().C, 0);
  run_everywhere(scene, 12, [](const MpmSolver&) {});
}

// Fluids keeping J alone (MpmSolver::keeps_J_only: no F, no material update pass; G2P updates J):
// bitwise on every backend and thread count, two passes and fused, for every transfer; and the
// state changed. A non-integer gamma takes pow (pressure_lanes' other branch).
TEST(BackendDeterminism, FluidsKeepingJBitwiseIdentical) {
  for (const char* transfer : {"mls", "apic", "flip"})
    for (const char* pass : {"", R"(, "transfer_pass": "fused")"})
      for (const char* gamma : {"", R"(, "gamma": 1.5)"}) {
        SCOPED_TRACE(std::string(transfer) + pass + gamma);
        const Scene scene = water_scene(transfer, pass, gamma);
        MpmSolver fresh = build_solver(scene);
        ASSERT_LT(fresh.attributes().F, 0);
        ASSERT_GE(fresh.attributes().J, 0);
        EXPECT_FALSE(fresh.has_material_update());
        const std::vector<Real> ref = run_everywhere(scene, 20, [](const MpmSolver& s) {
          const ParticleSet& ps = s.particles();
          const Real* J = ps.real(s.attributes().J);
          Real lo = 1, hi = 1;
          for (std::size_t i = 0; i < ps.size(); ++i)
            lo = std::min(lo, J[i]), hi = std::max(hi, J[i]);
          EXPECT_LT(lo, Real(0.9999));   // compressed on impact...
          EXPECT_GT(hi, Real(1.00001));  // ... and some expanded
        });
        fresh.sort_particles(exec::Space());
        EXPECT_FALSE(test::bitwise_equal(state_bytes(fresh).data(), ref.data(), ref.size()));
      }
}

// The material update takes a group's SVDs and the fluid resets' cube roots a vector of
// particles at a time (update_material_group): on every path and configuration each particle
// gets bitwise what its own MaterialParams::project gives, in groups mixing water, snow, sand
// and a melting solid (lanes melted and not), with J far from 1, negative, huge (std::cbrt's
// fallback) and NaN among them; the low parts of the projected F are cleared.
TEST(SimdPaths, MaterialUpdateIsEachParticlesProjection) {
  SimdGuard guard;
  std::vector<MaterialParams> mats(4);
  mats[0].model = MaterialModel::Fluid, mats[0].bulk = Real(2e5), mats[0].viscosity = Real(0.01);
  mats[1].model = MaterialModel::Snow, mats[1].mu = Real(4e4), mats[1].lambda = Real(6e4);
  mats[2].model = MaterialModel::DruckerPrager, mats[2].mu = Real(4e4), mats[2].lambda = Real(6e4);
  mats[2].friction_alpha = Real(0.4);
  mats[3].mu = Real(4e4), mats[3].lambda = Real(6e4), mats[3].melting = true;
  mats[3].melting_point = 300, mats[3].liquid_bulk = Real(1e4);
  const std::size_t n = 1003;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  std::vector<Mat3> F(n), F_lo(n);
  std::vector<Real> plastic(n), temperature(n);
  std::vector<std::int32_t> material(n);
  std::vector<Vec3> x(n, Vec3::Zero()), v(n, Vec3::Zero());
  for (std::size_t i = 0; i < n;) {  // runs of 1-12 particles of one material
    const int m = int(rng() % 4), len = 1 + int(rng() % 12);
    for (int k = 0; k < len && i < n; ++k, ++i) material[i] = m;
  }
  for (std::size_t i = 0; i < n; ++i) {
    F[i] = Mat3::Identity();
    for (int e = 0; e < 9; ++e) F[i](e) += Real(u(rng));
    if (i % 17 == 0) F[i] *= Real(4);          // J far above 1
    if (i % 23 == 0) F[i].col(0) *= Real(-1);  // inverted: J < 0, clamped
    if (i % 101 == 0) F[i] *= Real(1e11);      // J ~ 1e33: std::cbrt's range
    if (i == 500) F[i](1, 1) = std::numeric_limits<Real>::quiet_NaN();
    F_lo[i] = Mat3::Constant(Real(1e-9));
    plastic[i] = mats[std::size_t(material[i])].initial_plastic();
    temperature[i] = Real(300 + 10 * u(rng));  // the melting solid: some lanes melted
  }
  // The reference: one particle at a time.
  std::vector<Mat3> F_ref = F, lo_ref = F_lo;
  std::vector<Real> pl_ref = plastic;
  int resets = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const MaterialParams& m = mats[std::size_t(material[i])];
    resets += m.project_is_reset(temperature[i]);
    if (m.project(F_ref[i], pl_ref[i], temperature[i])) lo_ref[i].setZero();
  }
  EXPECT_GT(resets, 200);
  std::vector<Real> volume(n, Real(1e-6));
  for (const exec::SimdPath path : exec::supported_simd_paths()) {
    exec::set_simd_path(path);
    for (const Config& c : all_configs()) {
      SCOPED_TRACE(std::string(exec::simd_path_name(path)) + " " + c.name());
      std::vector<Mat3> F2 = F, lo2 = F_lo;
      std::vector<Real> pl2 = plastic, t2 = temperature;
      MpmParticleView p{x.data(), v.data(), nullptr, F2.data(), volume.data(), material.data(), n};
      p.F_lo = lo2.data(), p.plastic = pl2.data(), p.temperature = t2.data();
      MaterialUpdateParams prm;
      prm.materials = mats.data(), prm.dt = Real(1e-4);
      update_material_state(exec::Space(c.backend, c.threads), p, prm);
      for (std::size_t i = 0; i < n; ++i) {
        ASSERT_TRUE(bitwise_equal(F2[i].data(), F_ref[i].data(), 9)) << "particle " << i;
        ASSERT_TRUE(bitwise_equal(lo2[i].data(), lo_ref[i].data(), 9)) << "particle " << i;
        ASSERT_TRUE(bitwise_equal(&pl2[i], &pl_ref[i], 1)) << "particle " << i;
      }
    }
  }
}

// Run-time vector width (core/exec/simd.hpp): the kernels compiled for AVX2 and AVX-512 give
// the baseline's state bit for bit, on Serial and on 2 TBB threads. Paths this CPU (or build)
// lacks are skipped, saying so (expect_same_on_every_path, mpm_test_scenes.hpp).
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
  expect_same_on_every_path(water_scene("apic"), 20);
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
