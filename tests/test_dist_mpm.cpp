// Distributed explicit MPM (solvers/mpm_distributed.cpp, issue 28) under `mpirun -np R` (ctest
// runs R = 1..4; without MPI, one process): every rank also runs the single process's solver on
// the whole scene as the reference. The grid after P2G and the grid update (owned leaves, whose
// sums add other ranks' partial blocks, and the ghosts copied from their owners) is bitwise the
// reference's; migration and repartitioning keep every particle on exactly one rank; the
// particles gathered after many substeps (with forced repartitions) are bitwise the reference's.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "core/dist/comm.hpp"
#include "dist_test_util.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_solver.hpp"
#include "sparse_grid/sparse_grid.hpp"

using namespace amalgam;

namespace {

// `count` random points in the box centre +- half.
std::vector<Vec3> blob(std::mt19937& rng, const Vec3d& centre, const Vec3d& half, int count) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<Vec3> x;
  for (int i = 0; i < count; ++i) {
    Vec3d p;
    for (int a = 0; a < 3; ++a) p[a] = centre[a] + half[a] * u(rng);
    x.push_back(p.cast<Real>());
  }
  return x;
}

// A frictional floor at y = 0.1.
Collider floor() {
  Collider c;
  c.shape = ColliderShape::HalfSpace;
  c.origin = Vec3(0, Real(0.1), 0);
  c.friction = Real(0.3);
  return c;
}

// Two materials (a jelly blob and a snow blob) flying at each other with random affine velocity
// fields over a frictional floor, a sphere collider falling on them.
// sort_when_needed: re-sort only when needed (the default) or every substep.
MpmSolver make_scene(Transfer t, bool sort_when_needed = true, int order = 2) {
  MpmSettings s;
  s.dx = Real(0.04);
  s.transfer = t;
  s.order = order;
  s.sort_when_needed = sort_when_needed;
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  MaterialParams jelly{MaterialModel::FixedCorotated, l.mu, l.lambda, 1000};
  const Lame ls = Lame::from_young_poisson(4e4, 0.2);
  MaterialParams snow{MaterialModel::Snow, ls.mu, ls.lambda, 400};
  Collider ball;
  ball.shape = ColliderShape::Sphere;
  ball.origin = Vec3(Real(0.6), Real(0.8), Real(0.4));
  ball.radius = Real(0.1);
  ball.velocity = Vec3(0, -4, 0);
  ball.boundary = BoundaryType::Slip;
  MpmSolver solver(s, {jelly, snow}, {floor(), ball});
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int m = 0; m < 2; ++m) {
    const std::vector<Vec3> x =
        blob(rng, Vec3d(0.3 + 0.6 * m, 0.4, 0.4), Vec3d(0.2, 0.2, 0.25), 3000);
    solver.add_particles(x, Vec3(Real(m ? -3 : 3), -1, 0), Vec3(0, 0, 4),
                         Vec3(Real(0.3 + 0.6 * m), Real(0.4), Real(0.4)), m, Real(2e-5));
  }
  auto& ps = solver.particles();
  const auto& a = solver.attributes();
  for (std::size_t p = 0; p < ps.size(); ++p)
    ps.vec3(a.v)[p] += Vec3(Real(u(rng)), Real(u(rng)), 0);
  return solver;
}

// Every id on exactly one rank: the ranks' ids together are 0 .. n - 1 once each.
void expect_each_id_once(const MpmSolver& d, std::size_t n) {
  const dist::Comm& comm = dist::Comm::world();
  const ParticleSet& ps = d.particles();
  const std::int32_t* id = ps.int32(d.attributes().id);
  const std::vector<std::int32_t> mine(id, id + ps.size());
  std::vector<std::int32_t> all =
      dist::from_bytes<std::int32_t>(comm.allgather(dist::as_bytes(mine), nullptr));
  ASSERT_EQ(all.size(), n);
  std::vector<int> seen(n, 0);
  for (std::int32_t i : all) {
    ASSERT_GE(i, 0);
    ASSERT_LT(std::size_t(i), n);
    ++seen[std::size_t(i)];
  }
  for (std::size_t i = 0; i < n; ++i) ASSERT_EQ(seen[i], 1) << "particle id " << i;
}

// `steps` substeps of both solvers at the same dt (the exact max over the ranks), every id on
// one rank after each; `fewest`: the fewest particles this rank held.
void step_both(const exec::Space& space, MpmSolver& ref, MpmSolver& d, int steps,
               std::size_t* fewest) {
  const std::size_t n = ref.particles().size();
  for (int step = 0; step < steps; ++step) {
    const Real dt = ref.stable_dt(space);
    ASSERT_EQ(dt, d.stable_dt(space));
    ref.step(space, dt);
    d.step(space, dt);
    expect_each_id_once(d, n);
    *fewest = std::min(*fewest, d.particles().size());
  }
}

// Collective: d's particles gathered on rank 0 are bitwise ref's (none on the other ranks).
void expect_gathered_equal(const MpmSolver& d, const MpmSolver& ref) {
  ParticleSet all;
  d.gather_particles(all);
  test::expect_gathered_bitwise(all, ref.particles());
}

}  // namespace

TEST(DistMpm, HaloSumsEqualTheSingleProcessBitwise) {
  const exec::Space space(exec::Backend::Serial, 1);
  for (Transfer t : {Transfer::Mls, Transfer::Apic, Transfer::PicFlip}) {
    SCOPED_TRACE(transfer_name(t));
    MpmSolver ref = make_scene(t), d = make_scene(t);
    const std::size_t n = ref.particles().size();
    d.distribute(space);
    const GridChannels ch = ref.channels();
    for (int step = 0; step < 12; ++step) {
      const Real dt = ref.stable_dt(space);
      ASSERT_EQ(dt, d.stable_dt(space));  // the exact max over ranks
      for (MpmSolver* s : {&ref, &d}) {
        s->sort_particles(space);
        s->update_grid(space);
        s->particle_to_grid(space, dt);
        s->update_grid_velocities(space, dt);
      }
      // Every node this rank's bins read in G2P (in its own leaves, or in ghost leaves filled by
      // their owners: the parts of the +x/+y/+z neighbour leaves the bins' blocks reach) holds
      // the reference's node rows bit for bit: (m, v) and, PIC/FLIP, (-, dv).
      std::size_t compared = 0;
      const int order = d.settings().order;
      const BinTable& bins = d.bins();
      for (std::size_t b = 0; b < bins.count(); ++b)
        for (int t = 0; t < 8; ++t) {
          const Vec3i c = bins.leaf[b] + Vec3i((t >> 2) & 1, (t >> 1) & 1, t & 1);
          const std::int32_t li = d.grid().find_leaf(c * kLeafDim),
                             lr = ref.grid().find_leaf(c * kLeafDim);
          ASSERT_GE(li, 0);
          ASSERT_GE(lr, 0);
          const int ni = (t >> 2) & 1 ? order : kLeafDim, nj = (t >> 1) & 1 ? order : kLeafDim,
                    nk = t & 1 ? order : kLeafDim;
          for (int set = 0; set < ch.count; ++set)
            for (int i = 0; i < ni; ++i)
              for (int j = 0; j < nj; ++j)
                for (int k = 0; k < nk; ++k) {
                  const std::size_t o = std::size_t(leaf_offset(i, j, k)) * 4;
                  ASSERT_EQ(
                      std::memcmp(d.grid().node4(set) + std::size_t(li) * kLeafNodes * 4 + o,
                                  ref.grid().node4(set) + std::size_t(lr) * kLeafNodes * 4 + o,
                                  4 * sizeof(Real)),
                      0)
                      << "step " << step << ", leaf (" << c.transpose() << "), node " << i << " "
                      << j << " " << k << ", channel set " << set;
                }
          ++compared;
        }
      EXPECT_GT(compared, 0u);
      for (MpmSolver* s : {&ref, &d}) {
        s->grid_to_particle(space, dt);
        s->collide_particles(space, dt);
        if (s->has_material_update()) s->update_materials(space, dt);
        s->restore_clock(s->time() + double(dt), s->step_count() + 1);
      }
      expect_each_id_once(d, n);
    }
  }
}

// Sorted every substep (the plan of every substep) and re-sorted only when needed (the plan kept
// between sorts, solvers/mpm_lazy_distributed.cpp).
TEST(DistMpm, MigrationAndRepartitionKeepEveryParticleOnceAndTheStateBitwise) {
  const dist::Comm& comm = dist::Comm::world();
  for (bool lazy : {false, true}) {
    SCOPED_TRACE(lazy ? "sort when needed" : "sort every substep");
    ::setenv("AMALGAM_TEST_REPARTITION_EVERY", "7", 1);  // forced repartitions with migration
    const exec::Space space(exec::Backend::TBB, 2);      // (OpenMP spins on oversubscribed cores)
    MpmSolver ref = make_scene(Transfer::Mls, lazy), d = make_scene(Transfer::Mls, lazy);
    const std::size_t n = ref.particles().size();
    d.distribute(space);
    ::unsetenv("AMALGAM_TEST_REPARTITION_EVERY");
    expect_each_id_once(d, n);
    std::size_t fewest = n;
    step_both(space, ref, d, 40, &fewest);
    if (comm.size() > 1) EXPECT_LT(fewest, n);            // the particles are split, not replicated
    const std::string summary = d.distributed_summary();  // collective
    if (comm.size() > 1) {
      EXPECT_NE(summary.find(" repartitions"), std::string::npos);
    }
    expect_gathered_equal(d, ref);
  }
}

// Re-sorting only when needed on R ranks: every rank re-sorts at the substeps where the single
// process does (the decision is reduced), between sorts no particle migrates and each owned node
// sums its own and the other ranks' dilated-block parts in the single process's bin order: after
// 40 substeps (MLS, APIC cubic, FLIP; a ball collider pushing particles) the gathered particles
// are the single process's bits.
TEST(DistMpm, SortWhenNeededResortsWhereOneProcessDoesAndStaysBitwise) {
  const exec::Space space(exec::Backend::TBB, 2);
  for (Transfer t : {Transfer::Mls, Transfer::Apic, Transfer::PicFlip}) {
    SCOPED_TRACE(transfer_name(t));
    const int order = t == Transfer::Apic ? 3 : 2;
    MpmSolver ref = make_scene(t, true, order), d = make_scene(t, true, order);
    const std::size_t n = ref.particles().size();
    d.distribute(space);
    ASSERT_TRUE(d.sort_when_needed_eligible());
    std::size_t fewest = n;
    for (int step = 0; step < 40; ++step) {
      step_both(space, ref, d, 1, &fewest);
      ASSERT_EQ(d.lazy_resorts(), ref.lazy_resorts()) << "substep " << step;
    }
    EXPECT_GT(ref.lazy_resorts(), 0u);
    EXPECT_LT(ref.lazy_resorts(), 20u);
    expect_gathered_equal(d, ref);
  }
}

// A particle moved out of its bin's dilated block between substeps (as a particle collision may
// push one after G2P, whose far flags then miss it): the single process finds it in P2G and
// re-sorts; the ranks find it before P2G (MpmSolver::lazy_sort_needed_distributed), re-sort at
// the same substep and stay bitwise.
TEST(DistMpm, SortWhenNeededFindsAParticleMovedAfterG2P) {
  const exec::Space space(exec::Backend::TBB, 2);
  MpmSolver ref = make_scene(Transfer::Mls), d = make_scene(Transfer::Mls);
  d.distribute(space);
  std::size_t fewest = ref.particles().size();
  step_both(space, ref, d, 4, &fewest);
  const std::uint64_t before = ref.lazy_resorts();
  for (MpmSolver* s : {&ref, &d}) {  // particle id 17, wherever it is, 10 dx along +x
    ParticleSet& ps = s->particles();
    const std::int32_t* id = ps.int32(s->attributes().id);
    for (std::size_t p = 0; p < ps.size(); ++p)
      if (id[p] == 17) ps.vec3(s->attributes().x)[p] += Vec3(Real(0.4), 0, 0);
  }
  step_both(space, ref, d, 1, &fewest);
  EXPECT_EQ(ref.lazy_resorts(), before + 1);  // found by the single process's P2G
  EXPECT_EQ(d.lazy_resorts(), ref.lazy_resorts());
  step_both(space, ref, d, 3, &fewest);
  expect_gathered_equal(d, ref);
}

namespace {
// A-ULMPM: two jelly blobs with their own configuration maps (adaptive with a tight criterion,
// and Eulerian) thrown at each other over a floor, contact between them (separate, friction).
MpmSolver make_aul_scene() {
  MpmSettings s;
  s.dx = Real(0.04);
  s.configuration_maps = true;
  s.contact.mode = ObjectContactMode::Separate;
  s.contact.friction = Real(0.3);
  const Lame l = Lame::from_young_poisson(1e4, 0.3);
  const MaterialParams jelly{MaterialModel::NeoHookean, l.mu, l.lambda, 1000};
  MpmSolver solver(s, {jelly}, {floor()});
  std::mt19937 rng(11);
  for (int m = 0; m < 2; ++m) {
    const std::vector<Vec3> x =
        blob(rng, Vec3d(0.35 + 0.5 * m, 0.35, 0.4), Vec3d(0.15, 0.15, 0.2), 2500);
    ConfigurationPolicy policy;
    policy.update = m ? ConfigurationUpdate::Eulerian : ConfigurationUpdate::Adaptive;
    policy.epsilon = Real(0.02);
    policy.eta = Real(0.05);
    solver.add_particles(x, Vec3(Real(m ? -3 : 3), -1, 0), Vec3(0, 0, 4),
                         Vec3(Real(0.35 + 0.5 * m), Real(0.35), Real(0.4)), 0, Real(2e-5), 0,
                         policy);
  }
  return solver;
}
}  // namespace

// Distributed A-ULMPM: the reset decisions, the Lagrangian P2G with the fused node positions and
// the contact between the objects across ranks give the single process's particles bit for bit.
TEST(DistMpm, AulConfigurationsAndContactBitwise) {
  const exec::Space space(exec::Backend::Serial, 1);
  MpmSolver ref = make_aul_scene(), d = make_aul_scene();
  const std::size_t n = ref.particles().size();
  d.distribute(space);
  std::size_t fewest = n;
  step_both(space, ref, d, 40, &fewest);
  // The adaptive object reset, the objects touched, alike on every rank count.
  EXPECT_GT(ref.aul()->maps().stats(0).updates, 0u);
  EXPECT_EQ(d.aul()->maps().stats(0).updates, ref.aul()->maps().stats(0).updates);
  EXPECT_GT(ref.aul()->contact_nodes(), 0u);
  EXPECT_EQ(d.aul()->contact_nodes(), ref.aul()->contact_nodes());
  expect_gathered_equal(d, ref);
}

int main(int argc, char** argv) {
  return test::run_tests_on_every_rank(argc, argv);
}
