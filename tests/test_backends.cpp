// Whole substeps (sort, topology, P2G, grid update with colliders, G2P) are bitwise identical on
// Serial, OpenMP and TBB with 1 and 2 threads, for every transfer and both spline orders.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "core/exec/simd.hpp"
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
