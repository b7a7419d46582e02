// Distributed peridynamics (solvers/pd_distributed.cpp, issue 28) under `mpirun -np R` (ctest
// runs R = 1..4; without MPI, one process). Repartitions are forced every 3 steps
// (AMALGAM_TEST_REPARTITION_EVERY), so particles migrate with their rows many times. Every ghost
// holds its owner's values bitwise after a step; every particle id is owned by exactly one rank;
// a rank holds few ghosts (memory scales); the gathered particles after many steps are bitwise
// those of the single process's solver, which every rank also runs.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <vector>

#include "core/dist/comm.hpp"
#include "dist_test_util.hpp"
#include "solvers/pd_solver.hpp"

using namespace amalgam;

namespace {

constexpr double kLc = 0.01;

// Two brittle blocks flying at each other (they touch, break and bounce) over n x n/2 x n/2
// lattices, with contact and fracture.
PdSolver make_scene(int n, const exec::Space& space, bool plastic = false, bool init = true) {
  PdSettings s;
  s.spacing = Real(kLc);
  s.horizon = Real(3.01 * kLc);
  s.gravity = Vec3::Zero();
  s.compact_fraction = 0;  // the bond layouts stay comparable (compaction changes no bit)
  PdMaterial m;
  m.bulk = Real(1e6), m.shear = Real(6e5), m.density = 1000;
  m.critical_stretch = Real(0.01);
  if (plastic) {  // yields well before it breaks
    m.psi0 = pd_psi0_from_yield_stress(Real(2e4), s.horizon);
    m.critical_stretch = Real(0.05);
  }
  PdSolver solver(s, {m});
  for (int b = 0; b < 2; ++b) {
    std::vector<Vec3> x;
    for (int i = 0; i < n / 2; ++i)
      for (int j = 0; j < n / 2; ++j)
        for (int k = 0; k < n / 2; ++k)
          x.push_back(Vec3(Real(kLc * (i + b * (n / 2 + 1.5))), Real(kLc * j), Real(kLc * k)));
    solver.add_particles(x, Vec3(Real(b ? -6 : 6), 0, 0), Vec3(0, 0, Real(b ? 20 : -20)),
                         x[x.size() / 2], 0, Real(kLc * kLc * kLc));
  }
  if (init) solver.initialize(space);
  return solver;
}

void run(PdSolver& s, const exec::Space& space, int steps) {
  for (int k = 0; k < steps; ++k) s.step(space, s.stable_dt(space));
}

// Every rank's local particles: (global id, owned, x, x_lo, theta, damage) on every rank.
struct Local {
  std::uint64_t gid;
  std::int32_t owned;
  Vec3 x, x_lo;
  Real theta, damage;
};
std::vector<Local> all_locals(const PdSolver& s) {
  const ParticleSet& ps = s.particles();
  const PdAttributes& a = s.attributes();
  const std::vector<std::uint64_t> gid = s.global_ids();
  std::vector<std::uint8_t> own(ps.size(), 0);
  for (std::uint32_t i : s.owned_local()) own[i] = 1;
  std::vector<Local> mine(ps.size());
  for (std::size_t i = 0; i < ps.size(); ++i) {
    std::memset(&mine[i], 0, sizeof(Local));
    mine[i].gid = gid[i], mine[i].owned = own[i];
    mine[i].x = ps.vec3(a.x)[i], mine[i].x_lo = ps.vec3(a.x_lo)[i];
    mine[i].theta = ps.real(a.theta)[i], mine[i].damage = ps.real(a.damage)[i];
  }
  return dist::from_bytes<Local>(dist::Comm::world().allgather(dist::as_bytes(mine), nullptr));
}

}  // namespace

TEST(DistPd, GhostsHoldTheirOwnersValuesBitwise) {
  const exec::Space space;
  PdSolver s = make_scene(16, space);
  s.distribute(space);
  for (int round = 0; round < 3; ++round) {
    run(s, space, 7);
    const std::vector<Local> all = all_locals(s);
    std::map<std::uint64_t, const Local*> owner;
    for (const Local& l : all)
      if (l.owned) owner[l.gid] = &l;
    std::size_t ghosts = 0;
    for (const Local& l : all) {
      if (l.owned) continue;
      ++ghosts;
      ASSERT_TRUE(owner.count(l.gid)) << "ghost " << l.gid << " has no owner";
      const Local& o = *owner[l.gid];
      EXPECT_EQ(std::memcmp(&l.x, &o.x, sizeof(Vec3)), 0) << l.gid;
      EXPECT_EQ(std::memcmp(&l.x_lo, &o.x_lo, sizeof(Vec3)), 0) << l.gid;
      EXPECT_EQ(std::memcmp(&l.theta, &o.theta, sizeof(Real)), 0) << l.gid;
      EXPECT_EQ(std::memcmp(&l.damage, &o.damage, sizeof(Real)), 0) << l.gid;
    }
    if (dist::Comm::world().size() > 1) EXPECT_GT(ghosts, 0u);
  }
}

TEST(DistPd, EveryParticleOwnedOnceAfterMigration) {
  const exec::Space space;
  PdSolver s = make_scene(16, space);
  const std::size_t n = s.particles().size();
  s.distribute(space);
  run(s, space, 20);
  const std::vector<Local> all = all_locals(s);
  std::vector<int> count(n, 0);
  for (const Local& l : all)
    if (l.owned) ++count[l.gid];
  for (std::size_t i = 0; i < n; ++i) EXPECT_EQ(count[i], 1) << "particle " << i;
  if (dist::Comm::world().size() > 1) EXPECT_GE(s.dist_stats().repartitions, 5u);
}

TEST(DistPd, MemoryPerRankScales) {
  const exec::Space space;
  PdSolver s = make_scene(24, space);  // two 12^3 blocks
  const std::size_t n = s.particles().size();
  s.distribute(space);
  run(s, space, 5);
  const dist::Comm& comm = dist::Comm::world();
  const std::size_t local = s.particles().size(), own = s.owned_local().size();
  std::printf("rank %d: %zu own, %zu ghosts of %zu particles\n", comm.rank(), own, local - own, n);
  if (comm.size() >= 4) {
    EXPECT_LT(double(local), 0.6 * double(n)) << "rank " << comm.rank();
    EXPECT_LT(double(local - own), double(n) / 2) << "ghosts on rank " << comm.rank();
  }
  EXPECT_EQ(comm.sum(std::uint64_t(own)), n);
}

template <class T>
void expect_same(const std::vector<T>& a, const std::vector<T>& b, const char* what) {
  ASSERT_EQ(a.size(), b.size()) << what;
  if (!a.empty())
    EXPECT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(T)), 0)
        << what << " on rank " << dist::Comm::world().rank();
}

// initialize_distributed builds the bond rows of the own particles only (plus, per family, the
// row of its first member when another rank owns it: the shared fit's bond vectors), and its
// local state is bitwise the whole set-up's then distribute()'s: particles, every per-bond array,
// the constants of own particles and ghosts, the critical step. Elastic with a pre-crack, and
// plastic.
class DistPdSetUp : public ::testing::TestWithParam<bool> {};

TEST_P(DistPdSetUp, BuildsOnlyTheRowsItNeedsBitwiseTheWholeSetUp) {
  const exec::Space space;
  PdSolver ref = make_scene(16, space, GetParam(), false);
  if (!GetParam())
    ref.add_precrack(Vec3(Real(0.035), 0, 0), Vec3(1, 0, 0), Vec3::Constant(-1), Vec3::Constant(1));
  PdSolver s = ref;
  const std::uint64_t n = ref.particles().size();
  ref.initialize(space);
  ref.distribute(space);
  s.initialize_distributed(space);
  const dist::Comm& comm = dist::Comm::world();
  const PdSolver::DistStats& st = s.dist_stats();
  std::printf(
      "rank %d: %llu families fitted; %llu bond rows built for %llu own particles (%llu "
      "family rows) of %llu\n",
      comm.rank(), (unsigned long long)st.families_fitted, (unsigned long long)st.rows_built,
      (unsigned long long)st.owned, (unsigned long long)st.family_rows, (unsigned long long)n);
  if (comm.size() > 1) {
    EXPECT_EQ(st.rows_built, st.owned + st.family_rows) << "rank " << comm.rank();
    // Rows of families' first members owned elsewhere (one per family held here and elsewhere,
    // or fitted here for other ranks): on this small block, most of whose families are surface
    // ones, under half the own rows.
    EXPECT_LT(double(st.family_rows), 0.5 * double(st.owned)) << "rank " << comm.rank();
    EXPECT_LT(double(st.rows_built), 0.8 * double(n)) << "rank " << comm.rank();
  }
  if (comm.size() > 1) EXPECT_EQ(comm.sum(st.owned), n);
  // Each family of the surface correction is fitted on one rank only, at most the mean a rank.
  const std::uint64_t families = ref.dist_stats().families_fitted;
  EXPECT_EQ(comm.sum(st.families_fitted), families) << "rank " << comm.rank();
  const std::int64_t R = comm.size();
  EXPECT_LE(comm.max(std::int64_t(st.families_fitted)), (std::int64_t(families) + R - 1) / R)
      << "rank " << comm.rank();
  ASSERT_EQ(s.particles().size(), ref.particles().size()) << "rank " << comm.rank();
  EXPECT_EQ(s.global_ids(), ref.global_ids());
  for (int a = 0; a < ref.particles().attribute_count(); ++a) {
    const std::size_t w = std::size_t(ref.particles().words_per_particle(a));
    EXPECT_EQ(std::memcmp(s.particles().words(a), ref.particles().words(a),
                          ref.particles().size() * w * 4),
              0)
        << ref.particles().name(a) << " on rank " << comm.rank();
  }
  const PdBonds &b = s.bonds(), &r = ref.bonds();
  expect_same(b.offsets, r.offsets, "offsets");
  expect_same(b.neighbor, r.neighbor, "neighbor");
  expect_same(b.reverse, r.reverse, "reverse");
  expect_same(b.length, r.length, "length");
  expect_same(b.omega, r.omega, "omega");
  expect_same(b.shear_omega, r.shear_omega, "shear_omega");
  expect_same(b.volume, r.volume, "volume");
  expect_same(b.plastic, r.plastic, "plastic");
  expect_same(b.intact, r.intact, "intact");
  expect_same(b.omega_r, r.omega_r, "omega_r");
  expect_same(b.shear_omega_r, r.shear_omega_r, "shear_omega_r");
  expect_same(b.plastic_r, r.plastic_r, "plastic_r");
  expect_same(b.lane, r.lane, "lane");
  expect_same(b.dense, r.dense, "dense");
  const PdConstants &c = s.constants(), &rc = ref.constants();
  expect_same(c.m, rc.m, "m");
  expect_same(c.a, rc.a, "a");
  expect_same(c.b, rc.b, "b");
  expect_same(c.kappa, rc.kappa, "kappa");
  expect_same(c.bonds0, rc.bonds0, "bonds0");
  expect_same(c.fitted, rc.fitted, "fitted");
  if (!GetParam())  // the pre-crack broke bonds
    EXPECT_GT(s.global_sum(std::uint64_t(std::count(b.intact.begin(), b.intact.end(), 0))), 0u);
  EXPECT_EQ(s.stable_dt(space), ref.stable_dt(space));
  EXPECT_EQ(s.diagnostics(space).bonds, ref.diagnostics(space).bonds);
  run(ref, space, 10);
  run(s, space, 10);
  ParticleSet a, ra;
  s.gather_particles(a);
  ref.gather_particles(ra);
  test::expect_gathered_bitwise(a, ra);
}

INSTANTIATE_TEST_SUITE_P(ElasticAndPlastic, DistPdSetUp, ::testing::Bool());

class DistPdBitwise : public ::testing::TestWithParam<bool> {};

TEST_P(DistPdBitwise, GatheredStateIsTheSingleProcessBitwise) {
  const exec::Space space;
  PdSolver ref = make_scene(16, space, GetParam());
  PdSolver s = ref;
  s.distribute(space);
  for (int k = 0; k < 40; ++k) {
    const Real dt = ref.stable_dt(space);
    EXPECT_EQ(s.stable_dt(space), dt);
    ref.step(space, dt);
    s.step(space, dt);
  }
  EXPECT_LT(ref.diagnostics(space).intact, ref.diagnostics(space).bonds);  // bonds broke
  if (GetParam()) {  // plastic: bonds yielded, and their state is the single process's
    std::size_t yielded = 0;
    for (Real e : ref.bonds().plastic) yielded += e != 0;
    EXPECT_GT(yielded, 0u);
    std::vector<std::uint64_t> off;
    std::vector<std::uint32_t> nb;
    std::vector<Real> pl;
    std::vector<std::uint8_t> in;
    s.gather_bonds(off, nb, pl, in);
    if (dist::Comm::world().root()) {
      EXPECT_EQ(off, ref.bonds().offsets);
      EXPECT_EQ(nb, ref.bonds().neighbor);
      EXPECT_EQ(std::memcmp(pl.data(), ref.bonds().plastic.data(), pl.size() * sizeof(Real)), 0);
      EXPECT_EQ(in, ref.bonds().intact);
    }
  }
  ParticleSet all;
  s.gather_particles(all);
  test::expect_gathered_bitwise(all, ref.particles());
}

INSTANTIATE_TEST_SUITE_P(ElasticAndPlastic, DistPdBitwise, ::testing::Bool());

int main(int argc, char** argv) {
  setenv("AMALGAM_TEST_REPARTITION_EVERY", "3", 1);  // before the first step reads it
  return test::run_tests_on_every_rank(argc, argv);
}
