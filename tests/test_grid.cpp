// Sparse grid: binning sorts stably by leaf key and bins match a brute-force grouping; topology
// tables agree with the OpenVDB tree; same-colour bins never share a target leaf.
#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <random>
#include <set>

#include "core/math/bspline.hpp"
#include "sparse_grid/binning.hpp"
#include "sparse_grid/sparse_grid.hpp"
#include "test_util.hpp"
#include "thread_recorder.hpp"

using namespace amalgam;

namespace {
ParticleSet random_particles(size_t n, unsigned seed) {
  ParticleSet ps;
  const auto x = ps.add("x", AttrType::Real, 3);
  const auto id = ps.add("id", AttrType::Int32, 1);
  ps.resize(n);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-0.4, 0.9);
  for (size_t i = 0; i < n; ++i) {
    ps.vec3(x)[i] = Vec3(Real(u(rng)), Real(u(rng) * 0.5), Real(u(rng)));
    ps.int32(id)[i] = std::int32_t(i);
  }
  return ps;
}
}  // namespace

TEST(Binning, SortsStablyAndBinsMatchBruteForce) {
  const Real dx = Real(1.0 / 64);
  for (int order : {2, 3}) {
    ParticleSet ps = random_particles(50000, 11);
    const auto x = ps.id("x"), id = ps.id("id");
    // Brute force: leaf of each original particle.
    std::map<std::tuple<int, int, int>, std::vector<int>> expect;
    for (size_t i = 0; i < ps.size(); ++i) {
      Vec3i l;
      // The kernels compute x * (1/dx): use the same arithmetic.
      for (int a = 0; a < 3; ++a) {
        const Real xs = ps.vec3(x)[i][a] * (Real(1) / dx);
        l[a] = (order == 2 ? BSpline<2>::base(xs) : BSpline<3>::base(xs)) >> 3;
      }
      expect[{l[0], l[1], l[2]}].push_back(int(i));
    }
    ParticleBinning binning;
    BinTable bins;
    exec::Space s(test::parallel_backend(), 2);
    binning.sort_and_bin(s, ps, x, dx, order, bins);
    ASSERT_EQ(bins.count(), expect.size());
    for (size_t b = 0; b < bins.count(); ++b) {
      const auto& want = expect.at({bins.leaf[b][0], bins.leaf[b][1], bins.leaf[b][2]});
      ASSERT_EQ(bins.start[b + 1] - bins.start[b], want.size());
      for (size_t k = 0; k < want.size(); ++k)  // stable: original order kept inside a bin
        ASSERT_EQ(ps.int32(id)[bins.start[b] + k], want[k]);
    }
  }
}

TEST(Binning, IdenticalPermutationOnEveryBackend) {
  std::vector<std::int32_t> ref;
  for (const auto& c : test::all_configs()) {
    ParticleSet ps = random_particles(30000, 4);
    ParticleBinning binning;
    BinTable bins;
    binning.sort_and_bin(exec::Space(c.backend, c.threads), ps, ps.id("x"), Real(0.02), 2, bins);
    const std::int32_t* id = ps.int32(ps.id("id"));
    if (ref.empty()) ref.assign(id, id + ps.size());
    EXPECT_TRUE(test::bitwise_equal(ref.data(), id, ref.size())) << c.name();
  }
}

TEST(Binning, NonFiniteParticleIsReported) {
  ParticleSet ps = random_particles(1000, 5);
  ps.vec3(ps.id("x"))[417][1] = std::numeric_limits<Real>::quiet_NaN();
  ParticleBinning binning;
  BinTable bins;
  try {
    binning.sort_and_bin(exec::Space(), ps, ps.id("x"), Real(0.02), 2, bins);
    FAIL() << "expected an error";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("particle 417"), std::string::npos) << e.what();
  }
}

TEST(SparseGrid, TablesMatchTreeAndColoursAreDisjoint) {
  ParticleSet ps = random_particles(40000, 9);
  ParticleBinning binning;
  BinTable bins;
  const exec::Space s;
  SparseGrid grid;
  for (int step = 0; step < 3; ++step) {
    // Move the particles a little each step so topology grows incrementally.
    Vec3* x = ps.vec3(ps.id("x"));
    for (size_t i = 0; i < ps.size(); ++i) x[i][0] += Real(0.05);
    binning.sort_and_bin(s, ps, ps.id("x"), Real(1.0 / 64), 2, bins);
    grid.update_topology(s, bins);
    const auto& lc = grid.leaf_coords();
    for (size_t b = 0; b < bins.count(); ++b)
      for (int t = 0; t < 8; ++t) {
        const Vec3i want = bins.leaf[b] + Vec3i((t >> 2) & 1, (t >> 1) & 1, t & 1);
        const std::int32_t li = grid.nbr8()[b][size_t(t)];
        ASSERT_EQ(lc[size_t(li)], want);
        ASSERT_EQ(grid.find_leaf(want * kLeafDim + Vec3i(3, 5, 7)), li);
      }
    // nbr27 agrees with the coordinates.
    for (size_t li = 0; li < lc.size(); ++li) {
      if (grid.leaf_retired(li)) continue;
      int t = 0;
      for (int a = -1; a <= 1; ++a)
        for (int b = -1; b <= 1; ++b)
          for (int c = -1; c <= 1; ++c, ++t) {
            const std::int32_t n = grid.nbr27()[li][size_t(t)];
            ASSERT_EQ(n, grid.find_leaf((lc[li] + Vec3i(a, b, c)) * kLeafDim));
          }
    }
    // Within one colour no two bins write the same leaf.
    for (int c = 0; c < 8; ++c) {
      std::set<std::int32_t> seen;
      for (auto k = grid.colour_start()[size_t(c)]; k < grid.colour_start()[size_t(c) + 1]; ++k)
        for (auto li : grid.nbr8()[grid.colour_bins()[k]])
          ASSERT_TRUE(seen.insert(li).second) << "colour " << c;
    }
    EXPECT_EQ(grid.colour_start()[8], bins.count());
  }
}

// A body moving through space: leaves it has left are retired after SparseGrid::kRetireAfter
// updates and their slots reused, so the leaf table stops growing once the body's footprint plus
// its recent wake fill it, and the tables stay consistent with the tree throughout.
TEST(SparseGrid, LeavesOfAMovingBodyAreRetiredAndTheirSlotsReused) {
  ParticleSet ps;
  const auto xid = ps.add("x", AttrType::Real, 3);
  ps.resize(20000);
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(0.0, 0.25);
  for (size_t i = 0; i < ps.size(); ++i)
    ps.vec3(xid)[i] = Vec3(Real(u(rng)), Real(u(rng)), Real(u(rng)));
  ParticleBinning binning;
  BinTable bins;
  const exec::Space s;
  SparseGrid grid;
  const Real dx = Real(1.0 / 128);  // leaves of 1/16: the body spans 4-5 leaves per axis
  std::vector<std::size_t> slots;
  std::set<std::int32_t> seen_retired;
  for (int step = 0; step < 400; ++step) {
    // One leaf width every 8 updates along x: 50 leaves of travel, far more than the table.
    Vec3* x = ps.vec3(xid);
    for (size_t i = 0; i < ps.size(); ++i) x[i][0] += Real(1.0 / 16 / 8);
    binning.sort_and_bin(s, ps, xid, dx, 2, bins);
    grid.update_topology(s, bins);
    slots.push_back(grid.leaf_count());
    const auto& lc = grid.leaf_coords();
    for (size_t b = 0; b < bins.count(); ++b)
      for (int t = 0; t < 8; ++t) {
        const std::int32_t li = grid.nbr8()[b][size_t(t)];
        ASSERT_FALSE(grid.leaf_retired(size_t(li)));
        ASSERT_EQ(lc[size_t(li)], bins.leaf[b] + Vec3i((t >> 2) & 1, (t >> 1) & 1, t & 1));
      }
    for (size_t li = 0; li < lc.size(); ++li) {
      if (grid.leaf_retired(li)) {
        seen_retired.insert(std::int32_t(li));
        continue;
      }
      ASSERT_EQ(grid.find_leaf(lc[li] * kLeafDim), std::int32_t(li)) << "step " << step;
      int t = 0;
      for (int a = -1; a <= 1; ++a)
        for (int b = -1; b <= 1; ++b)
          for (int c = -1; c <= 1; ++c, ++t)
            ASSERT_EQ(grid.nbr27()[li][size_t(t)],
                      grid.find_leaf((lc[li] + Vec3i(a, b, c)) * kLeafDim));
    }
  }
  EXPECT_FALSE(seen_retired.empty());
  // Without retirement the table would hold every leaf the body ever touched (> 50 x 6 x 6).
  // With it, it plateaus: the second half of the run adds no slot.
  EXPECT_EQ(slots[199], slots.back());
  EXPECT_LT(slots.back(), std::size_t(4 * grid.active_leaves().size()));
}

// A caller that updates the topology only every few substeps (re-sorting only when needed) passes
// the substeps since its last update: a leaf unused for kRetireAfter to 2 kRetireAfter substeps
// is retired, however few updates that took (4 of age 16); updates of age 1 keep it for as many
// updates.
TEST(SparseGrid, LeavesRetireAfterSubstepsNotUpdates) {
  const exec::Space s;
  BinTable here, there;
  here.start = {0, 1};
  here.leaf = {Vec3i(0, 0, 0)};
  there.start = {0, 1};
  there.leaf = {Vec3i(10, 0, 0)};
  for (std::uint32_t age : {std::uint32_t(1), SparseGrid::kRetireAfter / 2}) {
    SCOPED_TRACE(age);
    SparseGrid grid;
    grid.update_topology(s, here, nullptr, age);
    const std::int32_t li = grid.find_leaf(Vec3i(0, 0, 0));
    ASSERT_GE(li, 0);
    int updates = 0;
    while (!grid.leaf_retired(std::size_t(li)) && updates < 100) {
      grid.update_topology(s, there, nullptr, age);
      ++updates;
    }
    // (retirement is checked every kRetireAfter substeps: a leaf goes within twice that)
    EXPECT_GE(std::uint32_t(updates) * age, SparseGrid::kRetireAfter);
    EXPECT_LE(std::uint32_t(updates) * age, 2 * SparseGrid::kRetireAfter);
    EXPECT_LT(grid.find_leaf(Vec3i(0, 0, 0)), 0);
  }
}

// The grid's OpenVDB tree is freed on the calling thread: OpenVDB's Tree::clear() (and the tree's
// destructor) would free its nodes in a parallel loop on TBB's default arena, where a worker
// joins outside the run's thread limit. Destroying grids of ~4 000 leaves takes no TBB worker.
TEST(SparseGrid, FreeingTheTreeTakesNoLibraryThread) {
  ParticleSet ps;
  const auto xid = ps.add("x", AttrType::Real, 3);
  const int n = 16;  // one particle per leaf, n^3 leaves (each touching 8 leaves: (n+1)^3)
  ps.resize(size_t(n * n * n));
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k)
        ps.vec3(xid)[size_t((i * n + j) * n + k)] =
            Vec3(Real(i + 0.5), Real(j + 0.5), Real(k + 0.5)) / Real(16);
  ParticleBinning binning;
  BinTable bins;
  const exec::Space s;
  test::WorkerRecorder rec;
  for (int rep = 0; rep < 10; ++rep) {
    SparseGrid grid;
    binning.sort_and_bin(s, ps, xid, Real(1.0 / 128), 2, bins);
    grid.update_topology(s, bins);
    ASSERT_GE(grid.leaf_count(), size_t(n * n * n));
  }
  EXPECT_EQ(rec.workers(), 0u);
}

// The permutation gathers every attribute through one spare of a Vec3's width: a Vec3 is gathered
// into it and swapped, a Mat3 a Vec3-wide group at a time (each group copied back in the pass
// that gathers the next), scalars and other widths (5, 11 words: one word at a time) gathered and
// copied back. After permutations and a
// compaction every attribute holds exactly its own values (a spare handed from one attribute to
// the next must not leak values, a group copied back must not overwrite a value still to read).
TEST(ParticleSet, PermuteThroughSparesKeepsEveryAttribute) {
  ParticleSet ps;
  const auto a1 = ps.add("a1", AttrType::Int32, 1), v1 = ps.add("v1", AttrType::Real, 3),
             m = ps.add("m", AttrType::Real, 9), v2 = ps.add("v2", AttrType::Real, 3),
             a2 = ps.add("a2", AttrType::Int32, 1), a5 = ps.add("a5", AttrType::Int32, 5),
             a11 = ps.add("a11", AttrType::Int32, 11);  // wider than the spare, not a multiple
  const std::size_t n = 5000;
  ps.resize(n);
  auto value = [](std::size_t p, int attr, int k) { return Real(p * 100 + attr * 10 + k); };
  for (std::size_t p = 0; p < n; ++p) {
    ps.int32(a1)[p] = std::int32_t(p);
    ps.int32(a2)[p] = std::int32_t(7 * p);
    for (int k = 0; k < 5; ++k) ps.int32(a5)[p * 5 + std::size_t(k)] = std::int32_t(p * 5 + k);
    for (int k = 0; k < 11; ++k) ps.int32(a11)[p * 11 + std::size_t(k)] = std::int32_t(p * 11 + k);
    for (int k = 0; k < 3; ++k) ps.vec3(v1)[p][k] = value(p, 1, k);
    for (int k = 0; k < 3; ++k) ps.vec3(v2)[p][k] = value(p, 2, k);
    for (int k = 0; k < 9; ++k) ps.real(m)[p * 9 + std::size_t(k)] = value(p, 3, k);
  }
  const int w = int(sizeof(Real) / 4);
  EXPECT_EQ(ps.state_bytes_per_particle(), std::size_t(4 * (18 + 15 * w)));
  EXPECT_EQ(ps.bytes_per_particle(), ps.state_bytes_per_particle() + std::size_t(4 * 3 * w));
  std::mt19937 rng(3);
  std::vector<std::uint32_t> order(n);  // order[i]: the original particle now at i
  for (std::size_t i = 0; i < n; ++i) order[i] = std::uint32_t(i);
  exec::Space s(test::parallel_backend(), 2);
  for (int round = 0; round < 3; ++round) {
    std::vector<std::uint32_t> perm(n);
    for (std::size_t i = 0; i < n; ++i) perm[i] = std::uint32_t(i);
    std::shuffle(perm.begin(), perm.end(), rng);
    ps.permute(s, perm.data());
    std::vector<std::uint32_t> next(n);
    for (std::size_t i = 0; i < n; ++i) next[i] = order[perm[i]];
    order = next;
  }
  std::vector<std::uint32_t> keep;
  for (std::uint32_t i = 0; i < n; i += 3) keep.push_back(i);
  ps.compact(s, keep.data(), keep.size());
  ASSERT_EQ(ps.size(), keep.size());
  for (std::size_t i = 0; i < keep.size(); ++i) {
    const std::size_t p = order[keep[i]];
    ASSERT_EQ(ps.int32(a1)[i], std::int32_t(p));
    ASSERT_EQ(ps.int32(a2)[i], std::int32_t(7 * p));
    for (int k = 0; k < 5; ++k)
      ASSERT_EQ(ps.int32(a5)[i * 5 + std::size_t(k)], std::int32_t(p * 5 + std::size_t(k)));
    for (int k = 0; k < 11; ++k)
      ASSERT_EQ(ps.int32(a11)[i * 11 + std::size_t(k)], std::int32_t(p * 11 + std::size_t(k)));
    for (int k = 0; k < 3; ++k) ASSERT_EQ(ps.vec3(v1)[i][k], value(p, 1, k));
    for (int k = 0; k < 3; ++k) ASSERT_EQ(ps.vec3(v2)[i][k], value(p, 2, k));
    for (int k = 0; k < 9; ++k) ASSERT_EQ(ps.real(m)[i * 9 + std::size_t(k)], value(p, 3, k));
  }
}

// With ids, a bin's particles are in id order whatever order they came in: after a sort, random
// moves (a bin then holds runs of ascending ids from several previous bins, which the sort
// merges) and a shuffle (many runs: sorted outright), every bin holds its particles by id.
TEST(Binning, BinsAreInIdOrderAfterMovesAndShuffles) {
  const Real dx = Real(1.0 / 64);
  ParticleSet ps = random_particles(40000, 5);
  const auto x = ps.id("x"), id = ps.id("id");
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> step(-2.5 * double(dx), 2.5 * double(dx));
  ParticleBinning binning;
  BinTable bins;
  exec::Space s(test::parallel_backend(), 2);
  for (int round = 0; round < 4; ++round) {
    if (round == 3) {  // shuffled storage order
      std::vector<std::uint32_t> perm(ps.size());
      for (std::size_t i = 0; i < perm.size(); ++i) perm[i] = std::uint32_t(i);
      std::shuffle(perm.begin(), perm.end(), rng);
      ps.permute(s, perm.data());
    }
    binning.sort_and_bin(s, ps, x, dx, 2, bins, id);
    std::map<std::tuple<int, int, int>, std::vector<int>> expect;
    for (size_t i = 0; i < ps.size(); ++i) {
      Vec3i l;
      for (int a = 0; a < 3; ++a) l[a] = BSpline<2>::base(ps.vec3(x)[i][a] * (Real(1) / dx)) >> 3;
      expect[{l[0], l[1], l[2]}].push_back(ps.int32(id)[i]);
    }
    ASSERT_EQ(bins.count(), expect.size());
    for (size_t b = 0; b < bins.count(); ++b) {
      std::vector<int> want = expect.at({bins.leaf[b][0], bins.leaf[b][1], bins.leaf[b][2]});
      std::sort(want.begin(), want.end());
      ASSERT_EQ(bins.start[b + 1] - bins.start[b], want.size());
      for (size_t k = 0; k < want.size(); ++k) ASSERT_EQ(ps.int32(id)[bins.start[b] + k], want[k]);
    }
    for (size_t i = 0; i < ps.size(); ++i)  // then move every particle a little
      for (int a = 0; a < 3; ++a) ps.vec3(x)[i][a] += Real(step(rng));
  }
}
