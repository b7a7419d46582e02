// Transfers: P2G conserves mass and linear momentum (APIC/MLS: angular momentum too, including the
// stress term); P2G -> G2P round trip conserves them on the particles; every transfer kernel is
// bitwise identical on all backends.
#include <gtest/gtest.h>

#include <random>

#include "core/exec/simd.hpp"
#include "solvers/mpm_simulation.hpp"
#include "solvers/mpm_solver.hpp"
#include "sparse_grid/sparse_grid.hpp"
#include "half_space.hpp"
#include "test_util.hpp"

using namespace amalgam;

namespace {

MpmSolver make_blob(Transfer t, int order, Real dt_stress_scale = 1,
                    std::vector<Collider> colliders = {}, const Vec3& gravity = Vec3::Zero()) {
  MpmSettings s;
  s.dx = Real(0.05);
  s.order = order;
  s.transfer = t;
  s.gravity = gravity;
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  MaterialParams m{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  MpmSolver solver(s, {m}, std::move(colliders));
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<Vec3> x;
  for (int i = 0; i < 6000; ++i)
    x.push_back(Vec3(Real(0.5 + 0.25 * u(rng)), Real(0.5 + 0.2 * u(rng)), Real(0.3 * u(rng))));
  solver.add_particles(x, Vec3(Real(0.3), Real(-0.2), Real(0.1)), Vec3(1, 2, 3),
                       Vec3::Constant(Real(0.5)), 0, Real(1e-5));
  // Random affine velocity fields and deformations so every term is exercised.
  auto& ps = solver.particles();
  const auto& a = solver.attributes();
  for (size_t p = 0; p < ps.size(); ++p) {
    Eigen::Matrix3d Fr = Eigen::Matrix3d::Identity();
    for (int k = 0; k < 9; ++k) {
      if (a.C >= 0) ps.mat3(a.C)[p](k) += Real(0.5 * u(rng));  // PIC/FLIP: no C
      Fr(k) += 0.1 * u(rng) * double(dt_stress_scale);
    }
    if (a.F >= 0)
      ps.mat3(a.F)[p] = Fr.cast<Real>();
    else
      ps.sym_dev(a.b)[p] = b_from_F<Real>(Fr);
    ps.vec3(a.v)[p] += Vec3(Real(u(rng)), Real(u(rng)), Real(u(rng)));
  }
  return solver;
}

struct Moments {
  double m = 0;
  Vec3d p = Vec3d::Zero(), L = Vec3d::Zero();
};

Moments grid_moments(const MpmSolver& s) {
  Moments r;
  const auto& g = s.grid();
  const Real* a = g.node4(0);
  for (auto li : g.active_leaves())
    for (int o = 0; o < kLeafNodes; ++o) {
      const Real* n = a + (size_t(li) * kLeafNodes + size_t(o)) * 4;
      const Vec3i node =
          g.leaf_coords()[size_t(li)] * kLeafDim + Vec3i(o >> 6, (o >> 3) & 7, o & 7);
      const Vec3d xi = node.cast<double>() * double(s.settings().dx);
      const Vec3d pi(n[1], n[2], n[3]);
      r.m += n[0];
      r.p += pi;
      r.L += xi.cross(pi);
    }
  return r;
}

// Particle angular momentum including the affine part: x_p x m v_p + m D_p eps:(C_p)
// (Jiang et al. 2015), D_p = dx^2 / Dinv_scale.
Moments particle_moments(const MpmSolver& s, bool affine) {
  Moments r;
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  const double D =
      double(s.settings().dx) * double(s.settings().dx) / (s.settings().order == 2 ? 4.0 : 3.0);
  for (size_t p = 0; p < ps.size(); ++p) {
    const double m = s.particle_mass(p);
    const Vec3d x = ps.vec3(a.x)[p].cast<double>(), v = ps.vec3(a.v)[p].cast<double>();
    const Mat3d C = a.C >= 0 ? Mat3d(ps.mat3(a.C)[p].cast<double>()) : Mat3d(Mat3d::Zero());
    r.m += m;
    r.p += m * v;
    r.L += x.cross(m * v);
    if (affine) r.L += m * D * Vec3d(C(2, 1) - C(1, 2), C(0, 2) - C(2, 0), C(1, 0) - C(0, 1));
  }
  return r;
}

void expect_close(const Vec3d& a, const Vec3d& b, double tol, const char* what) {
  EXPECT_LT((a - b).norm(), tol * (1 + b.norm()))
      << what << ": " << a.transpose() << " vs " << b.transpose();
}

const double kTol = sizeof(Real) == 4 ? 2e-5 : 1e-11;

}  // namespace

class TransferConservation : public ::testing::TestWithParam<std::tuple<Transfer, int>> {};

TEST_P(TransferConservation, P2GConservesMassMomentumAndAngularMomentum) {
  const auto [transfer, order] = GetParam();
  MpmSolver s = make_blob(transfer, order);
  const exec::Space space(test::parallel_backend(), 2);
  const bool affine = transfer != Transfer::PicFlip;
  const Moments before = particle_moments(s, affine);
  s.sort_particles(space);
  s.update_grid(space);
  // With dt > 0 the MLS/APIC stress terms enter the momentum: they must sum to zero, and their
  // torque too, because tau = P F^T is symmetric for isotropic materials.
  s.particle_to_grid(space, Real(1e-4));
  const Moments g = grid_moments(s);
  EXPECT_NEAR(g.m, before.m, kTol * before.m);
  if (transfer != Transfer::PicFlip) {
    expect_close(g.p, before.p, kTol * 10, "linear momentum");
    expect_close(g.L, before.L, kTol * 50, "angular momentum");
  } else {
    expect_close(g.p, before.p, kTol * 10, "linear momentum");  // force kept in channel b
  }
}

TEST_P(TransferConservation, RoundTripConservesOnParticles) {
  const auto [transfer, order] = GetParam();
  MpmSolver s = make_blob(transfer, order);
  const exec::Space space(exec::Backend::TBB, 2);
  const bool affine = transfer != Transfer::PicFlip;
  const Moments before = particle_moments(s, affine);
  // dt = 0: no forces, no motion; a pure transfer P2G -> grid velocities -> G2P.
  s.sort_particles(space);
  s.update_grid(space);
  s.particle_to_grid(space, 0);
  s.update_grid_velocities(space, 0);
  s.grid_to_particle(space, 0);
  const Moments after = particle_moments(s, affine);
  EXPECT_NEAR(after.m, before.m, kTol * before.m);
  if (transfer == Transfer::PicFlip) {
    // FLIP keeps v_p + (0 increment); PIC part alone would conserve momentum but not L.
    expect_close(after.p, before.p, kTol * 10, "linear momentum");
  } else {
    expect_close(after.p, before.p, kTol * 10, "linear momentum");
    expect_close(after.L, before.L, kTol * 50, "angular momentum");
  }
}

// Every transfer with quadratic and cubic B-splines, named "mls_order2" and so on.
static auto transfers_and_orders() {
  return ::testing::Combine(::testing::Values(Transfer::PicFlip, Transfer::Apic, Transfer::Mls),
                            ::testing::Values(2, 3));
}
static std::string transfer_order_name(
    const ::testing::TestParamInfo<std::tuple<Transfer, int>>& info) {
  return std::string(transfer_name(std::get<0>(info.param))) + "_order" +
         std::to_string(std::get<1>(info.param));
}

INSTANTIATE_TEST_SUITE_P(AllTransfers, TransferConservation, transfers_and_orders(),
                         transfer_order_name);

TEST(TransferPIC, PurePicConservesLinearMomentum) {
  MpmSolver s = make_blob(Transfer::PicFlip, 2);
  const Moments before = particle_moments(s, false);
  const exec::Space space;
  s.sort_particles(space);
  s.update_grid(space);
  s.particle_to_grid(space, 0);
  s.update_grid_velocities(space, 0);
  // alpha = 0 gives PIC: v_p = sum w v_i.
  auto prm = s.step_params(0);
  prm.flip_alpha = 0;
  g2p(space, s.particle_view(), s.grid_view(), prm);
  const Moments after = particle_moments(s, false);
  expect_close(after.p, before.p, kTol * 10, "PIC linear momentum");
}

// P2G with kept bin blocks (one scatter loop, then each leaf sums its blocks in colour order)
// gives the colour phases' grid bit for bit: every transfer, both orders, every backend/thread
// count. The sums' order is what is tested: adding a leaf's blocks in any other order than by
// colour changes low bits of this blob's nodes (checked by reversing it).
class P2GBlocks : public ::testing::TestWithParam<std::tuple<Transfer, int>> {};

TEST_P(P2GBlocks, KeptBlocksSumLikeTheColourPhases) {
  const auto [transfer, order] = GetParam();
  for (const auto& c : test::all_configs()) {
    MpmSolver s = make_blob(transfer, order);
    const exec::Space space(c.backend, c.threads);
    s.sort_particles(space);
    s.update_grid(space);
    const size_t nflt = s.grid().leaf_count() * kLeafNodes * 4;
    auto grids = [&] {
      std::vector<Real> r(s.grid().node4(0), s.grid().node4(0) + nflt);
      const int second = s.channels().second;
      if (second >= 0) r.insert(r.end(), s.grid().node4(second), s.grid().node4(second) + nflt);
      return r;
    };
    s.particle_to_grid(space, Real(1e-3));  // the solver's path: kept blocks
    const std::vector<Real> blocks = grids();
    ASSERT_GT(s.p2g_block_bytes(), 0u);
    MpmGridView g = s.grid_view();
    ASSERT_NE(g.leaf_bins, nullptr);
    g.blocks = nullptr;  // the colour phases
    const MpmStepParams prm = s.step_params(Real(1e-3));
    grid_clear(space, g, prm);
    p2g(space, s.particle_view(), g, prm);
    const std::vector<Real> phases = grids();
    ASSERT_EQ(blocks.size(), phases.size());
    EXPECT_TRUE(test::bitwise_equal(blocks.data(), phases.data(), blocks.size())) << c.name();
  }
}

INSTANTIATE_TEST_SUITE_P(AllTransfers, P2GBlocks, transfers_and_orders(), transfer_order_name);

// The grid update (kernels/mpm_transfers.cpp: whole nodes in vectors, then the colliders of the
// leaves they may reach) is at every node the scalar update, bit for bit, on every SIMD path and
// backend: v = p / m + dt g (+ (dt / m) f), then each collider projected at the node's position
// where m > 0, and v = 0 where m <= 0; PIC/FLIP's second channel dv = v - p / m (0 where m <= 0).
// Three modes: MLS (no force), PIC/FLIP (force and dv), and MLS's split grid of the fused pass
// (force, no dv). The blob straddles a floor and a wall, so leaves with and without colliders
// are both exercised.
TEST(GridUpdate, EveryNodeIsTheScalarUpdateOnEveryPath) {
  const std::vector<Collider> colliders = {
      test::half_space(Vec3(0, Real(0.42), 0), Vec3::UnitY(), BoundaryType::Separate, Real(0.3)),
      test::half_space(Vec3(Real(0.33), 0, 0), Vec3::UnitX(), BoundaryType::Slip, 0)};
  const Real dt = Real(1e-3);
  const exec::SimdPath saved = exec::simd_path();
  for (const Transfer t : {Transfer::Mls, Transfer::PicFlip})
    for (const bool split : {false, true}) {
      if (t == Transfer::PicFlip && split) continue;  // PIC/FLIP's b is its force already
      MpmSolver s = make_blob(t, 2, 1, colliders, Vec3(Real(0.3), Real(-9.81), Real(0.2)));
      const exec::Space serial;
      s.sort_particles(serial);
      s.update_grid(serial);
      s.particle_to_grid(serial, dt);
      MpmGridView g = s.grid_view();
      MpmStepParams prm = s.step_params(dt);
      const std::size_t nflt = s.grid().leaf_count() * kLeafNodes * 4;
      std::vector<Real> split_force;
      std::mt19937 rng(5);
      std::uniform_real_distribution<double> u(-1.0, 1.0);
      if (split) {  // the fused pass's stress force, without dt
        prm.split = true;
        split_force.resize(nflt);
        for (Real& f : split_force) f = Real(50 * u(rng));
        g.b = split_force.data();
      }
      const bool flip = t == Transfer::PicFlip, force = flip || split;
      ASSERT_EQ(force, g.b != nullptr);
      // Nodes with m <= 0 besides the empty ones: -0 and a negative mass.
      const auto& leaves = s.grid().active_leaves();
      ASSERT_GT(leaves.size(), 2u);
      g.a[std::size_t(leaves[1]) * kLeafNodes * 4 + 4 * 7] = Real(-0.0);
      g.a[std::size_t(leaves[2]) * kLeafNodes * 4 + 4 * 9] = Real(-1);
      const std::vector<Real> a0(g.a, g.a + nflt);
      const std::vector<Real> b0 = force ? std::vector<Real>(g.b, g.b + nflt) : std::vector<Real>();
      std::vector<Real> ra = a0, rb = b0;
      int near = 0, reached = 0;
      for (const auto li : leaves)
        for (int o = 0; o < kLeafNodes; ++o) {
          const std::size_t at = (std::size_t(li) * kLeafNodes + std::size_t(o)) * 4;
          Real* n = ra.data() + at;
          if (n[0] <= 0) {
            n[1] = n[2] = n[3] = 0;
            if (flip) rb[at + 1] = rb[at + 2] = rb[at + 3] = 0;
            continue;
          }
          const Real inv = Real(1) / n[0];
          Vec3 v_old, v;
          for (int c = 0; c < 3; ++c) {
            v_old[c] = n[1 + c] * inv;
            v[c] = v_old[c] + dt * prm.gravity[c];
            if (force) v[c] = v[c] + (dt * inv) * rb[at + 1 + std::size_t(c)];
          }
          const Vec3i node = s.grid().leaf_coords()[std::size_t(li)] * kLeafDim +
                             Vec3i(o >> 6, (o >> 3) & 7, o & 7);
          const Vec3 xi = node.cast<Real>() * prm.dx;
          const Vec3 before = v;
          for (const Collider& c : colliders) {
            near += c.phi(xi, prm.time + dt) <= node_tolerance(xi, prm.dx);
            c.project(xi, prm.time + dt, v, node_tolerance(xi, prm.dx));
          }
          reached += v != before;
          for (int c = 0; c < 3; ++c) {
            n[1 + c] = v[c];
            if (flip) rb[at + 1 + std::size_t(c)] = v[c] - v_old[c];
          }
        }
      EXPECT_GT(reached, 0) << "the colliders change some nodes' velocities";
      EXPECT_GT(near, 0);
      for (const exec::SimdPath path :
           {exec::SimdPath::Baseline, exec::SimdPath::Avx2, exec::SimdPath::Avx512}) {
        if (!exec::simd_path_supported(path)) continue;
        exec::set_simd_path(path);
        for (const auto& c : test::all_configs()) {
          std::copy(a0.begin(), a0.end(), g.a);
          if (force) std::copy(b0.begin(), b0.end(), g.b);
          grid_update(exec::Space(c.backend, c.threads), g, prm);
          const std::string what = std::string(transfer_name(t)) + (split ? " split " : " ") +
                                   exec::simd_path_name(path) + " " + c.name();
          EXPECT_TRUE(test::bitwise_equal(g.a, ra.data(), nflt)) << what;
          if (force) EXPECT_TRUE(test::bitwise_equal(g.b, rb.data(), nflt)) << what;
        }
      }
      exec::set_simd_path(saved);
    }
}

// Each kernel separately, on every backend/thread count, bitwise against Serial.
class KernelDeterminism : public ::testing::TestWithParam<Transfer> {};

TEST_P(KernelDeterminism, P2GGridUpdateG2PBitwiseAcrossBackends) {
  std::vector<Real> ref_grid_p2g, ref_grid_upd, ref_particles;
  for (const auto& c : test::all_configs()) {
    MpmSolver s = make_blob(GetParam(), 2);
    const exec::Space space(c.backend, c.threads);
    s.sort_particles(space);
    s.update_grid(space);
    s.particle_to_grid(space, Real(1e-3));
    const size_t nflt = s.grid().leaf_count() * kLeafNodes * 4;
    std::vector<Real> grid(s.grid().node4(0), s.grid().node4(0) + nflt);
    s.update_grid_velocities(space, Real(1e-3));
    std::vector<Real> upd(s.grid().node4(0), s.grid().node4(0) + nflt);
    s.grid_to_particle(space, Real(1e-3));
    const auto& ps = s.particles();
    std::vector<Real> parts;
    for (auto id :
         {s.attributes().x, s.attributes().v, s.attributes().C, s.attributes().F, s.attributes().b})
      if (id >= 0)  // PIC/FLIP keeps no C
        parts.insert(parts.end(), ps.real(id), ps.real(id) + ps.size() * size_t(ps.width(id)));
    if (ref_grid_p2g.empty()) {
      ref_grid_p2g = grid;
      ref_grid_upd = upd;
      ref_particles = parts;
      continue;
    }
    ASSERT_EQ(grid.size(), ref_grid_p2g.size());
    EXPECT_TRUE(test::bitwise_equal(grid.data(), ref_grid_p2g.data(), grid.size()))
        << "p2g " << c.name();
    EXPECT_TRUE(test::bitwise_equal(upd.data(), ref_grid_upd.data(), upd.size()))
        << "grid update " << c.name();
    EXPECT_TRUE(test::bitwise_equal(parts.data(), ref_particles.data(), parts.size()))
        << "g2p " << c.name();
  }
}

INSTANTIATE_TEST_SUITE_P(AllTransfers, KernelDeterminism,
                         ::testing::Values(Transfer::PicFlip, Transfer::Apic, Transfer::Mls),
                         [](const auto& info) { return std::string(transfer_name(info.param)); });

// F's low part exists only where a particle's F accumulates over substeps: a run whose materials
// are all fluids resets every particle's F to J^{1/3} I, low part zero, each substep, so keeps
// none (36 B less per particle in float) and takes the same values bit for bit. Checked against
// the same water run made to keep F_lo by a second material no particle uses, over APIC and MLS
// (implicit: an explicit all-fluid run keeps no F at all, FluidJ below).
TEST(FLowPart, KeptOnlyWhereAMaterialIsNotAFluid) {
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  const MaterialParams elastic{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  MaterialParams water{MaterialModel::Fluid, 0, 0, 1000};
  water.bulk = Real(2e5), water.viscosity = Real(0.01);
  MaterialParams wax = elastic;  // a solid that melts still accumulates F below its melting point
  wax.melting = true, wax.melting_point = 320, wax.liquid_bulk = Real(1e4);
  MpmSettings plain;  // implicit: F kept (an explicit all-fluid run keeps J alone)
  plain.implicit = true;
  auto keeps = [&](const std::vector<MaterialParams>& m) {
    EXPECT_EQ(MpmSolver::keeps_F_low_part(m), MpmSolver(plain, m, {}).attributes().F_lo >= 0);
    return MpmSolver::keeps_F_low_part(m);
  };
  EXPECT_FALSE(keeps({water}));
  EXPECT_FALSE(keeps({water, water}));
  EXPECT_TRUE(keeps({elastic}));
  EXPECT_TRUE(keeps({water, elastic}));
  EXPECT_TRUE(keeps({wax}));
  EXPECT_EQ(MpmSolver(plain, {water, elastic}, {}).particles().bytes_per_particle() -
                MpmSolver(plain, {water}, {}).particles().bytes_per_particle(),
            9 * sizeof(Real));

  const exec::Space space(exec::Backend::TBB, 2);
  for (const Transfer t : {Transfer::Apic, Transfer::Mls}) {
    MpmSettings s;
    s.dx = Real(0.05), s.transfer = t, s.implicit = true;
    s.gravity = Vec3(0, Real(-9.8), 0);
    MpmSolver lean(s, {water}, {}), kept(s, {water, elastic}, {});
    ASSERT_LT(lean.attributes().F_lo, 0);
    ASSERT_GE(kept.attributes().F_lo, 0);
    std::mt19937 rng(5);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    std::vector<Vec3> x;
    for (int i = 0; i < 4000; ++i)
      x.push_back(Vec3(Real(0.5 + 0.2 * u(rng)), Real(0.5 + 0.15 * u(rng)), Real(0.2 * u(rng))));
    for (MpmSolver* m : {&lean, &kept})
      m->add_particles(x, Vec3(Real(0.3), Real(-0.2), Real(0.1)), Vec3(1, 2, 3),
                       Vec3::Constant(Real(0.5)), 0, Real(1e-5));
    for (int k = 0; k < 40; ++k) {  // water at 2e5 Pa: ~1e-4 s is stable at dx = 0.05
      lean.step(space, Real(1e-4));
      kept.step(space, Real(1e-4));
    }
    const std::size_t n = lean.particles().size();
    ASSERT_EQ(kept.particles().size(), n);
    for (const char* name : {"x", "x_lo", "v", "C", "F"}) {
      const ParticleSet &pa = lean.particles(), &pb = kept.particles();
      EXPECT_TRUE(test::bitwise_equal(pa.real(pa.id(name)), pb.real(pb.id(name)),
                                      n * std::size_t(pa.width(pa.id(name)))))
          << name << ", " << transfer_name(t);
    }
    // kept's low parts: every entry zero after the last substep's reset.
    const Mat3* lo = kept.particles().mat3(kept.attributes().F_lo);
    for (std::size_t i = 0; i < n; ++i) ASSERT_TRUE(lo[i].isZero(0)) << i;
    // ... and the values moved: the test compares something.
    EXPECT_NE(lean.particles().vec3(lean.attributes().x)[0], x[0]);
  }
}

// A run whose materials are all fluids (explicit, Eulerian, no particle domains) keeps J alone:
// no F, no F_lo (68 B less per particle in float), no material update pass; G2P takes
// J <- det(I + dt grad v) J. Against the same water made to keep F (the F reset to J^{1/3} I each
// substep) by a second material no particle uses: the same motion to rounding, over APIC, MLS and
// FLIP, the two passes and fused.
TEST(FluidJ, KeptInsteadOfFWhereEveryMaterialIsAFluid) {
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  const MaterialParams elastic{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  MaterialParams water{MaterialModel::Fluid, 0, 0, 1000};
  water.bulk = Real(2e5), water.viscosity = Real(0.01);
  MaterialParams oil = water;
  oil.density = 800, oil.gamma = Real(1.5);
  MaterialParams molten = water;
  molten.melting = true;
  auto only_J = [](const MpmSettings& s, const std::vector<MaterialParams>& m) {
    const MpmSolver solver(s, m, {});
    const bool J = solver.attributes().J >= 0;
    EXPECT_EQ(J, solver.attributes().F < 0 && solver.attributes().b < 0);
    EXPECT_EQ(J, MpmSolver::keeps_J_only(s, m));
    if (J) EXPECT_FALSE(solver.has_material_update());
    return J;
  };
  const MpmSettings plain;
  MpmSettings implicit, aul;
  implicit.implicit = true;
  aul.configuration_maps = true;
  EXPECT_TRUE(only_J(plain, {water}));
  EXPECT_TRUE(only_J(plain, {water, oil}));
  EXPECT_FALSE(only_J(plain, {water, elastic}));
  EXPECT_FALSE(only_J(plain, {molten}));
  EXPECT_FALSE(only_J(implicit, {water}));
  EXPECT_FALSE(only_J(aul, {water}));
  MpmSettings with_F;  // a solid beside the fluid keeps F + F_lo (or b - I: MpmSolver::keeps_b)
  with_F.keep_F = true;
  EXPECT_EQ(MpmSolver(with_F, {water, elastic}, {}).particles().bytes_per_particle() -
                MpmSolver(plain, {water}, {}).particles().bytes_per_particle(),
            17 * sizeof(Real));
  EXPECT_EQ(MpmSolver(plain, {water, elastic}, {}).particles().bytes_per_particle() -
                MpmSolver(plain, {water}, {}).particles().bytes_per_particle(),
            5 * sizeof(Real));

  const exec::Space space(exec::Backend::TBB, 2);
  for (const Transfer t : {Transfer::Apic, Transfer::Mls, Transfer::PicFlip})
    for (const bool fused : {false, true}) {
      SCOPED_TRACE(std::string(transfer_name(t)) + (fused ? " fused" : " two passes"));
      MpmSettings s;
      s.dx = Real(0.05), s.transfer = t, s.fused = fused;
      s.gravity = Vec3(0, Real(-9.8), 0);
      s.keep_F = true;  // kept: F itself, not b (MpmSolver::keeps_b)
      MpmSolver lean(s, {water, oil}, {}), kept(s, {water, oil, elastic}, {});
      ASSERT_GE(lean.attributes().J, 0);
      ASSERT_GE(kept.attributes().F, 0);
      std::mt19937 rng(5);
      std::uniform_real_distribution<double> u(-1.0, 1.0);
      std::vector<Vec3> x, y;
      for (int i = 0; i < 4000; ++i) {
        x.push_back(Vec3(Real(0.5 + 0.2 * u(rng)), Real(0.5 + 0.15 * u(rng)), Real(0.2 * u(rng))));
        y.push_back(x.back() + Vec3(Real(0.5), 0, 0));
      }
      for (MpmSolver* m : {&lean, &kept}) {
        m->add_particles(x, Vec3(Real(0.3), Real(-0.2), Real(0.1)), Vec3(1, 2, 3),
                         Vec3::Constant(Real(0.5)), 0, Real(1e-5));
        m->add_particles(y, Vec3(Real(-0.3), Real(-0.1), Real(0.2)), Vec3(-2, 1, 0),
                         Vec3(Real(1), Real(0.5), 0), 1, Real(1e-5));
      }
      for (int k = 0; k < 200; ++k) {  // water at 2e5 Pa: ~1e-4 s is stable at dx = 0.05
        lean.step(space, Real(1e-4));
        kept.step(space, Real(1e-4));
      }
      const ParticleSet &pa = lean.particles(), &pb = kept.particles();
      const std::size_t n = pa.size();
      ASSERT_EQ(pb.size(), n);
      const Vec3 *xa = pa.vec3(lean.attributes().x), *xb = pb.vec3(kept.attributes().x);
      const Real* Ja = pa.real(lean.attributes().J);
      const Mat3* Fb = pb.mat3(kept.attributes().F);
      const std::int32_t *ida = pa.int32(lean.attributes().id),
                         *idb = pb.int32(kept.attributes().id);
      std::vector<std::size_t> at(n);  // the runs may have sorted their particles differently
      for (std::size_t i = 0; i < n; ++i) at[std::size_t(idb[i])] = i;
      double dx_most = 0, dJ_most = 0, J_lo = 1, J_hi = 1;
      for (std::size_t i = 0; i < n; ++i) {
        const std::size_t k = at[std::size_t(ida[i])];
        dx_most = std::max(dx_most, double((xa[i] - xb[k]).norm()));
        dJ_most = std::max(dJ_most, std::abs(double(Ja[i]) - double(Fb[k].determinant())));
        J_lo = std::min(J_lo, double(Ja[i])), J_hi = std::max(J_hi, double(Ja[i]));
      }
      std::printf("%s%s: max |x_J - x_F| = %.3g dx, max |J - det F| = %.3g, J in [%.6f, %.6f]\n",
                  transfer_name(t), fused ? " fused" : "", dx_most / 0.05, dJ_most, J_lo, J_hi);
      EXPECT_GT(J_hi - J_lo, 1e-3);  // the fluids compressed and expanded: J did change
      EXPECT_LT(dx_most, 1e-4 * 0.05);
      EXPECT_LT(dJ_most, 1e-4);
    }
}

// The paths around a run keeping J alone, against the same water made to keep F by an unused
// elastic material: an inviscid PIC/FLIP run (no C either), and APIC with sleeping blocks (a
// still pool falls asleep while two blobs of water collide above it). The motion, the output's F
// (J^{1/3} I), J and von Mises (zero: the pressure is isotropic), and the elastic energy
// (WeaklyCompressibleT::energy_of_J against energy(F)) agree to rounding.
TEST(FluidJ, OutputsEnergyInviscidFlipAndSleepAsTheRunKeepingF) {
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  const MaterialParams elastic{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  MaterialParams water{MaterialModel::Fluid, 0, 0, 1000};
  water.bulk = Real(2e5);
  const exec::Space space(exec::Backend::TBB, 2);
  for (const Transfer t : {Transfer::PicFlip, Transfer::Apic}) {
    const bool sleep = t == Transfer::Apic;
    SCOPED_TRACE(transfer_name(t));
    MpmSettings s;
    s.dx = Real(0.05), s.transfer = t, s.gravity = Vec3::Zero();
    s.sleep.enabled = sleep;
    s.sleep.time = Real(0.005);
    s.keep_F = true;  // kept: F itself, not b (MpmSolver::keeps_b)
    MpmSolver lean(s, {water}, {}), kept(s, {water, elastic}, {});
    ASSERT_GE(lean.attributes().J, 0);
    ASSERT_GE(kept.attributes().F, 0);
    EXPECT_EQ(lean.attributes().C >= 0, t == Transfer::Apic);  // inviscid PIC/FLIP: no C
    std::mt19937 rng(9);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    // The pool in the leaves (0.4 m) of y = 0, the blobs two leaves above: the pool sleeps.
    std::vector<Vec3> pool, left, right;
    for (int i = 0; i < 3000; ++i)
      pool.push_back(Vec3(Real(0.2 + 0.6 * u(rng)), Real(0.1 + 0.2 * u(rng)), Real(0.3 * u(rng))));
    for (int i = 0; i < 400; ++i) {
      left.push_back(Vec3(Real(0.2 + 0.1 * u(rng)), Real(1.25 + 0.1 * u(rng)), Real(0.1 * u(rng))));
      right.push_back(left.back() + Vec3(Real(0.2), 0, 0));
    }
    for (MpmSolver* m : {&lean, &kept}) {
      m->add_particles(pool, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(1e-5));
      m->add_particles(left, Vec3(Real(3), 0, 0), Vec3::Zero(), Vec3::Zero(), 0, Real(1e-5));
      m->add_particles(right, Vec3(Real(-3), 0, 0), Vec3::Zero(), Vec3::Zero(), 0, Real(1e-5));
    }
    for (int k = 0; k < 300; ++k) {
      lean.step(space, Real(1e-4));
      kept.step(space, Real(1e-4));
    }
    if (sleep) {
      ASSERT_TRUE(lean.sleep() && kept.sleep());
      const std::size_t asleep = lean.sleep()->sleeping(lean.particles());
      std::printf("%zu of %zu particles asleep\n", asleep, lean.particles().size());
      EXPECT_EQ(asleep, pool.size());  // the pool, and no blob particle
      EXPECT_EQ(asleep, kept.sleep()->sleeping(kept.particles()));
    }
    const ParticleSet &pa = lean.particles(), &pb = kept.particles();
    const std::size_t n = pa.size();
    ASSERT_EQ(pb.size(), n);
    const std::int32_t *ida = pa.int32(lean.attributes().id), *idb = pb.int32(kept.attributes().id);
    std::vector<std::size_t> at(n);
    for (std::size_t i = 0; i < n; ++i) at[std::size_t(idb[i])] = i;
    const Vec3 *xa = pa.vec3(lean.attributes().x), *xb = pb.vec3(kept.attributes().x);
    const PointFields fa = mpm_point_fields(pa, lean.attributes(), lean.materials(),
                                            {"F", "J", "vonmises"}, space),
                      fb = mpm_point_fields(pb, kept.attributes(), kept.materials(),
                                            {"F", "J", "vonmises"}, space);
    ASSERT_EQ(fa.attributes.size(), 3u);
    ASSERT_EQ(fb.attributes.size(), 3u);
    double dx_most = 0, dF_most = 0, dJ_most = 0, J_lo = 1, J_hi = 1, vm_most = 0;
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t k = at[std::size_t(ida[i])];
      dx_most = std::max(dx_most, double((xa[i] - xb[k]).norm()));
      for (int e = 0; e < 9; ++e)
        dF_most = std::max(dF_most, std::abs(double(fa.attributes[0].f[9 * i + std::size_t(e)]) -
                                             double(fb.attributes[0].f[9 * k + std::size_t(e)])));
      const double Ja = fa.attributes[1].f[i];
      dJ_most = std::max(dJ_most, std::abs(Ja - double(fb.attributes[1].f[k])));
      J_lo = std::min(J_lo, Ja), J_hi = std::max(J_hi, Ja);
      // F = J^{1/3} I: off-diagonal zero, the diagonal's cube J.
      const float* F = &fa.attributes[0].f[9 * i];
      EXPECT_EQ(F[1], 0.0f);
      EXPECT_EQ(F[0], F[4]);
      EXPECT_NEAR(double(F[0]) * F[0] * F[0], Ja, 4e-7 * Ja);
      EXPECT_EQ(fa.attributes[2].f[i], 0.0f);
      vm_most = std::max(vm_most, double(std::abs(fb.attributes[2].f[k])));
    }
    const MpmDiagnostics da = lean.diagnostics(space), db = kept.diagnostics(space);
    std::printf(
        "%s: max |x_J - x_F| = %.3g dx, |F| %.3g, |J| %.3g, J in [%.6f, %.6f], von Mises "
        "of the F run <= %.3g Pa, elastic energy %.6g J vs %.6g J\n",
        transfer_name(t), dx_most / 0.05, dF_most, dJ_most, J_lo, J_hi, vm_most, da.elastic,
        db.elastic);
    EXPECT_GT(J_hi - J_lo, 1e-3);
    EXPECT_LT(dx_most, 1e-4 * 0.05);
    EXPECT_LT(dF_most, 1e-4);
    EXPECT_LT(dJ_most, 1e-4);
    EXPECT_LT(vm_most, 1e-3 * water.bulk);  // the F run's isotropic stress, to rounding
    EXPECT_GT(da.elastic, 0);
    EXPECT_NEAR(da.elastic, db.elastic, 1e-3 * db.elastic);
    EXPECT_NEAR(da.kinetic, db.kinetic, 1e-4 * db.kinetic);
  }
}

// C (the affine matrix) exists only where it is read: APIC and MLS transfer it, a viscous stress
// reads it as the velocity gradient; PIC/FLIP (and particle domains, which transfer by PIC/FLIP)
// of materials without viscosity keep none: 9 Reals less per particle.
TEST(AffineMatrix, KeptOnlyWhereTheTransferOrAViscousStressReadsIt) {
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  const MaterialParams elastic{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  MaterialParams damped = elastic;
  damped.viscosity = Real(0.5);  // Kelvin-Voigt
  MaterialParams wax = elastic;  // melts into a viscous liquid
  wax.melting = true;
  wax.melting_point = 320;
  wax.liquid_bulk = Real(1e4);
  MaterialParams dry_wax = wax;  // ... or an inviscid one
  dry_wax.liquid_viscosity = 0;
  wax.liquid_viscosity = 1;
  auto keeps = [](Transfer t, const MaterialParams& m, bool domains = false) {
    MpmSettings s;
    s.transfer = t;
    s.domains.enabled = domains;
    EXPECT_EQ(MpmSolver::keeps_affine(s, {m}), MpmSolver(s, {m}, {}).attributes().C >= 0);
    return MpmSolver::keeps_affine(s, {m});
  };
  EXPECT_TRUE(keeps(Transfer::Mls, elastic));
  EXPECT_TRUE(keeps(Transfer::Apic, elastic));
  EXPECT_FALSE(keeps(Transfer::PicFlip, elastic));
  EXPECT_TRUE(keeps(Transfer::PicFlip, damped));
  EXPECT_TRUE(keeps(Transfer::PicFlip, wax));
  EXPECT_FALSE(keeps(Transfer::PicFlip, dry_wax));
  EXPECT_FALSE(keeps(Transfer::Mls, dry_wax, true));  // domains: PIC/FLIP whatever the transfer
  EXPECT_TRUE(keeps(Transfer::Mls, wax, true));
  MpmSettings s;
  s.transfer = Transfer::PicFlip;
  const MpmSolver flip(s, {elastic}, {});
  s.transfer = Transfer::Apic;
  const MpmSolver apic(s, {elastic}, {});
  EXPECT_EQ(flip.particles().find("C"), -1);
  EXPECT_GE(apic.particles().find("C"), 0);
  EXPECT_EQ(apic.particles().bytes_per_particle() - flip.particles().bytes_per_particle(),
            9 * sizeof(Real));
}

// Particles keep b - I of b = F F^T (MpmSolver::keeps_b) unless the run is implicit, A-ULMPM, has
// particle domains, keeps J alone or outputs F (MpmSettings::keep_F): 24 B instead of F + F_lo's
// 72 in float.
TEST(LeftCauchyGreen, KeptWhereNothingReadsFItself) {
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  const MaterialParams elastic{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  MaterialParams water{MaterialModel::Fluid, 0, 0, 1000};
  water.bulk = Real(2e5);
  auto keeps = [](MpmSettings s, std::vector<MaterialParams> m) {
    const MpmSolver solver(s, m, {});
    const MpmAttributes& a = solver.attributes();
    EXPECT_EQ(MpmSolver::keeps_b(s, m), a.b >= 0);
    EXPECT_EQ(a.b >= 0, a.F < 0 && a.F_lo < 0 && a.J < 0);
    return a.b >= 0;
  };
  MpmSettings s;
  EXPECT_TRUE(keeps(s, {elastic}));
  EXPECT_TRUE(keeps(s, {elastic, water}));
  EXPECT_FALSE(keeps(s, {water}));  // J alone
  MpmSettings f = s;
  f.keep_F = true;
  EXPECT_FALSE(keeps(f, {elastic}));
  MpmSettings imp = s;
  imp.implicit = true;
  EXPECT_FALSE(keeps(imp, {elastic}));
  MpmSettings aul = s;
  aul.configuration_maps = true;
  EXPECT_FALSE(keeps(aul, {elastic}));
  MpmSettings dom = s;
  dom.domains.enabled = true;
  EXPECT_FALSE(keeps(dom, {elastic}));
  EXPECT_EQ(MpmSolver(f, {elastic}, {}).particles().bytes_per_particle() -
                MpmSolver(s, {elastic}, {}).particles().bytes_per_particle(),
            12 * sizeof(Real));  // F + F_lo: 18 Reals; b - I: 6
}

// A run keeping b - I against the same run keeping F + F_lo (MpmSettings::keep_F), for every
// material model (snow's and sand's return mappings, von Mises, a fluid beside a solid, whose F
// reset writes b, a melting solid), every transfer, two passes and fused: the same motion and
// energies to rounding (the materials read F only through b: Materials.EveryModelReadsFOnlyThroughB),
// and the output's J and von Mises stress alike.
TEST(LeftCauchyGreen, RunsAsTheRunKeepingF) {
  const Lame l = Lame::from_young_poisson(2e4, 0.3);
  const exec::Space space(exec::Backend::TBB, 2);
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k)
    for (const Transfer t : {Transfer::Mls, Transfer::Apic, Transfer::PicFlip}) {
      const MaterialModel model = MaterialModel(k);
      const bool fused = k % 2 == 1;
      SCOPED_TRACE(std::string(material_model_name(model)) + ", " + transfer_name(t) +
                   (fused ? ", fused" : ""));
      MaterialParams m{model, l.mu, l.lambda, 1000};
      m.bulk = Real(2e4);
      m.friction_alpha = Real(0.3);
      m.yield_stress = Real(300);
      m.viscosity = t == Transfer::PicFlip ? Real(0) : Real(0.05);
      const MaterialParams solid{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
      // A fluid needs a solid beside it, else the run keeps J alone; a solid melts at 300 K.
      std::vector<MaterialParams> mats{m, solid};
      if (model == MaterialModel::NeoHookean)
        mats[0].melting = true, mats[0].melting_point = 300, mats[0].liquid_bulk = Real(2e4);
      MpmSettings s;
      s.dx = Real(0.05), s.transfer = t, s.fused = fused;
      s.gravity = Vec3(0, Real(-9.8), 0);
      MpmSettings sf = s;
      sf.keep_F = true;
      MpmSolver bb(s, mats, {}), ff(sf, mats, {});
      ASSERT_GE(bb.attributes().b, 0);
      ASSERT_GE(ff.attributes().F, 0);
      std::mt19937 rng(5);
      std::uniform_real_distribution<double> u(-1.0, 1.0);
      std::vector<Vec3> x, y;
      for (int i = 0; i < 3000; ++i) {
        x.push_back(Vec3(Real(0.5 + 0.2 * u(rng)), Real(0.5 + 0.15 * u(rng)), Real(0.2 * u(rng))));
        y.push_back(x.back() + Vec3(Real(0.45), 0, 0));
      }
      for (MpmSolver* r : {&bb, &ff}) {
        // Colliding, spinning bodies: shear, compression, rotation (and, for the plastic models,
        // return mappings that move).
        r->add_particles(x, Vec3(Real(1.5), Real(-0.2), 0), Vec3(3, 2, 5),
                         Vec3::Constant(Real(0.5)), 0, Real(1e-5),
                         Real(t == Transfer::Apic ? 320 : 280));
        r->add_particles(y, Vec3(Real(-1.5), 0, 0), Vec3(-2, 1, 0), Vec3(Real(0.95), Real(0.5), 0),
                         1, Real(1e-5));
      }
      for (int n = 0; n < 150; ++n) {
        const Real dt = std::min(bb.stable_dt(space), Real(2e-4));
        bb.step(space, dt);
        ff.step(space, dt);
      }
      const ParticleSet &pa = bb.particles(), &pb = ff.particles();
      const std::size_t n = pa.size();
      ASSERT_EQ(pb.size(), n);
      const std::int32_t *ida = pa.int32(bb.attributes().id), *idb = pb.int32(ff.attributes().id);
      std::vector<std::size_t> at(n);
      for (std::size_t i = 0; i < n; ++i) at[std::size_t(idb[i])] = i;
      const Vec3 *xa = pa.vec3(bb.attributes().x), *xb = pb.vec3(ff.attributes().x);
      const PointFields fa = mpm_point_fields(pa, bb.attributes(), bb.materials(),
                                              {"J", "vonmises"}, space),
                        fb = mpm_point_fields(pb, ff.attributes(), ff.materials(),
                                              {"J", "vonmises"}, space);
      double dx_most = 0, dJ_most = 0, J_lo = 1, J_hi = 1, dvm_most = 0, vm_most = 0;
      for (std::size_t i = 0; i < n; ++i) {
        const std::size_t j = at[std::size_t(ida[i])];
        dx_most = std::max(dx_most, double((xa[i] - xb[j]).norm()));
        const double Ja = fa.attributes[0].f[i];
        dJ_most = std::max(dJ_most, std::abs(Ja - double(fb.attributes[0].f[j])));
        J_lo = std::min(J_lo, Ja), J_hi = std::max(J_hi, Ja);
        dvm_most = std::max(
            dvm_most, std::abs(double(fa.attributes[1].f[i]) - double(fb.attributes[1].f[j])));
        vm_most = std::max(vm_most, double(fb.attributes[1].f[j]));
      }
      const MpmDiagnostics da = bb.diagnostics(space), db = ff.diagnostics(space);
      std::printf(
          "%s %s%s: max |x_b - x_F| = %.3g dx, |J| %.3g, J in [%.4f, %.4f], von Mises "
          "%.3g of %.3g Pa, elastic energy %.6g vs %.6g J\n",
          material_model_name(model), transfer_name(t), fused ? " fused" : "", dx_most / 0.05,
          dJ_most, J_lo, J_hi, dvm_most, vm_most, da.elastic, db.elastic);
      EXPECT_GT(J_hi - J_lo, 1e-3);  // the bodies deformed
      EXPECT_LT(dx_most, 2e-4 * 0.05);
      EXPECT_LT(dJ_most, 2e-4);
      EXPECT_LT(dvm_most, 2e-3 * vm_most + 1e-3);
      EXPECT_NEAR(da.elastic, db.elastic, 2e-3 * db.elastic + 1e-9);
      EXPECT_NEAR(da.kinetic, db.kinetic, 1e-4 * db.kinetic);
    }
}
