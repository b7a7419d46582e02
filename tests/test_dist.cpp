// The distributed layer (core/dist, issue 28) under `mpirun --oversubscribe -np R` (ctest runs
// R = 1..4; without MPI the same tests run as one rank): Zoltan's RCB gives every item exactly
// one owner, the same on every call, balanced by weight; ghosts receive their owners' bits; the
// collectives are exact.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <numeric>
#include <stdexcept>
#include <vector>

#include "core/dist/comm.hpp"
#include "core/dist/halo.hpp"

using namespace amalgam::dist;

namespace {

constexpr int kSide = 18;  // 18^3 = 5832 lattice points
constexpr std::uint64_t kCount = std::uint64_t(kSide) * kSide * kSide;

// This rank's contiguous slice of `count` ids before partitioning (what a reader of a file would
// have), and their points (point_of(id, p)).
void slice(std::uint64_t& begin, std::uint64_t& end, std::uint64_t count) {
  const Comm& c = Comm::world();
  begin = count * std::uint64_t(c.rank()) / std::uint64_t(c.size());
  end = count * std::uint64_t(c.rank() + 1) / std::uint64_t(c.size());
}
template <class PointOf>
void slice_points(std::uint64_t count, PointOf point_of, std::vector<std::uint64_t>& ids,
                  std::vector<double>& xyz) {
  std::uint64_t b = 0, e = 0;
  slice(b, e, count);
  for (std::uint64_t id = b; id < e; ++id) {
    ids.push_back(id);
    double p[3];
    point_of(id, p);
    xyz.insert(xyz.end(), p, p + 3);
  }
}
void point(std::uint64_t id, double* p) {
  p[0] = double(id % kSide) * 0.01;
  p[1] = double((id / kSide) % kSide) * 0.01;
  p[2] = double(id / (kSide * kSide)) * 0.01 + 10.0;  // away from the origin
}
// Every id's owner, known on every rank.
std::vector<int> all_owners(const std::vector<float>& weight_of_id) {
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  slice_points(kCount, point, ids, xyz);
  std::vector<float> w;
  if (!weight_of_id.empty())
    for (std::uint64_t id : ids) w.push_back(weight_of_id[id]);
  const std::vector<int> mine = partition_rcb(ids, xyz, w);
  std::vector<std::uint64_t> pairs;
  for (std::size_t k = 0; k < ids.size(); ++k) {
    pairs.push_back(ids[k]);
    pairs.push_back(std::uint64_t(mine[k]));
  }
  const std::vector<std::uint64_t> all =
      from_bytes<std::uint64_t>(Comm::world().allgather(as_bytes(pairs), nullptr));
  std::vector<int> owner(kCount, -1);
  for (std::size_t k = 0; k + 1 < all.size(); k += 2) {
    EXPECT_EQ(owner[all[k]], -1) << "item " << all[k] << " listed twice";
    owner[all[k]] = int(all[k + 1]);
  }
  return owner;
}

}  // namespace

TEST(Dist, EveryItemHasExactlyOneOwnerTheSameOnEveryCall) {
  const Comm& c = Comm::world();
  const std::vector<int> a = all_owners({}), b = all_owners({});
  EXPECT_EQ(a, b);
  std::vector<std::uint64_t> count(std::size_t(c.size()), 0);
  for (int o : a) {
    ASSERT_GE(o, 0);
    ASSERT_LT(o, c.size());
    ++count[std::size_t(o)];
  }
  // Balanced: within Zoltan's 5 % tolerance (and a lattice plane's granularity).
  const double mean = double(kCount) / c.size();
  for (std::uint64_t n : count) EXPECT_LE(double(n), 1.08 * mean);
}

TEST(Dist, RcbBalancesTheWeights) {
  const Comm& c = Comm::world();
  std::vector<float> w(kCount);
  for (std::uint64_t id = 0; id < kCount; ++id) w[id] = (id % kSide) < kSide / 3 ? 10.f : 1.f;
  const std::vector<int> owner = all_owners(w);
  std::vector<double> load(std::size_t(c.size()), 0);
  for (std::uint64_t id = 0; id < kCount; ++id) load[std::size_t(owner[id])] += w[id];
  const double mean = std::accumulate(load.begin(), load.end(), 0.0) / c.size();
  for (double l : load) EXPECT_LE(l, 1.10 * mean);
}

TEST(Dist, GhostsReceiveTheirOwnersBits) {
  const Comm& c = Comm::world();
  const std::vector<int> owner = all_owners({});
  // Local layout: owned and ghost items sorted by global id (as the distributed solvers keep
  // them); ghosts: every item within 3 lattice spacings of an owned one.
  std::vector<char> want(kCount, 0);
  for (std::uint64_t id = 0; id < kCount; ++id) {
    if (owner[id] != c.rank()) continue;
    const int i = int(id % kSide), j = int((id / kSide) % kSide), k = int(id / (kSide * kSide));
    for (int a = std::max(0, i - 3); a <= std::min(kSide - 1, i + 3); ++a)
      for (int b = std::max(0, j - 3); b <= std::min(kSide - 1, j + 3); ++b)
        for (int d = std::max(0, k - 3); d <= std::min(kSide - 1, k + 3); ++d)
          want[std::uint64_t(a) + std::uint64_t(b) * kSide + std::uint64_t(d) * kSide * kSide] = 1;
  }
  std::vector<std::uint64_t> local, owned, ghost;
  std::vector<std::uint32_t> owned_slot, ghost_slot;
  for (std::uint64_t id = 0; id < kCount; ++id)
    if (want[id]) {
      (owner[id] == c.rank() ? owned : ghost).push_back(id);
      (owner[id] == c.rank() ? owned_slot : ghost_slot).push_back(std::uint32_t(local.size()));
      local.push_back(id);
    }
  const HaloPlan plan(owned, owned_slot, ghost, ghost_slot,
                      [&](std::uint64_t id) { return owner[id]; });
  EXPECT_EQ(plan.ghosts(), ghost.size());
  if (c.size() == 1) {
    EXPECT_EQ(ghost.size(), 0u);
  }
  struct Rec {  // no padding: memcmp compares values only
    double x[3];
    double s;
  };
  std::vector<Rec> v(local.size());
  auto value = [](std::uint64_t id) {  // bit patterns that differ from any neighbour's
    Rec r;
    point(id, r.x);
    r.x[0] = std::sin(double(id)) * 1e-7 + r.x[0];
    r.s = std::cos(double(id) * 0.37);
    return r;
  };
  for (std::size_t k = 0; k < local.size(); ++k) {
    const bool mine = owner[local[k]] == c.rank();
    v[k] = mine ? value(local[k]) : Rec{{-1, -1, -1}, -1};
  }
  plan.exchange(v.data());
  for (std::size_t k = 0; k < local.size(); ++k) {
    const Rec want_rec = value(local[k]);
    ASSERT_EQ(std::memcmp(&v[k], &want_rec, sizeof(Rec)), 0) << "item " << local[k];
  }
}

// RcbCuts::neighbours is symmetric and holds the owner of every point next to an owned one, and
// the all-to-all among those peers delivers exactly what each peer sent (and refuses bytes for a
// rank that is not a peer, before sending anything).
TEST(Dist, NeighbourPeersAreSymmetricCompleteAndExchange) {
  const Comm& c = Comm::world();
  // A bar of 64 x 4 x 4 points: RCB cuts it into slabs, so on 3 and 4 ranks the end slabs are
  // not each other's peers.
  constexpr std::uint64_t kBar = 64 * 4 * 4;
  auto bar_point = [](std::uint64_t id, double* p) {
    p[0] = double(id % 64) * 0.01;
    p[1] = double((id / 64) % 4) * 0.01;
    p[2] = double(id / 256) * 0.01;
  };
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  slice_points(kBar, bar_point, ids, xyz);
  const RcbCuts cuts = RcbCuts::partition(ids, xyz, {});
  const std::vector<int> peers = cuts.neighbours(0.015);  // 1.5 lattice steps
  if (c.size() == 1) {
    EXPECT_TRUE(peers.empty());
  }
  std::vector<char> is_peer(std::size_t(c.size()), 0);
  for (int r : peers) {
    EXPECT_NE(r, c.rank());
    is_peer[std::size_t(r)] = 1;
  }
  // Symmetric: every rank's list, on every rank.
  std::vector<std::size_t> sizes;
  const std::vector<int> all = from_bytes<int>(c.allgather(as_bytes(peers), &sizes));
  std::size_t at = 0;
  for (int q = 0; q < c.size(); ++q) {
    const std::size_t n = sizes[std::size_t(q)] / sizeof(int);
    for (std::size_t k = 0; k < n; ++k)
      if (all[at + k] == c.rank()) {
        EXPECT_TRUE(is_peer[std::size_t(q)]) << "rank " << q;
      }
    bool lists_me = false;
    for (std::size_t k = 0; k < n; ++k) lists_me |= all[at + k] == c.rank();
    if (is_peer[std::size_t(q)]) {
      EXPECT_TRUE(lists_me) << "rank " << q;
    }
    at += n;
  }
  // Complete: the owner of every lattice point next to one this rank owns is a peer.
  for (std::uint64_t id = 0; id < kBar; ++id) {
    double p[3];
    bar_point(id, p);
    if (cuts.owner(p) != c.rank()) continue;
    for (int d = 0; d < 27; ++d) {
      const double q[3] = {p[0] + 0.01 * (d % 3 - 1), p[1] + 0.01 * (d / 3 % 3 - 1),
                           p[2] + 0.01 * (d / 9 - 1)};
      const int o = cuts.owner(q);
      EXPECT_TRUE(o == c.rank() || is_peer[std::size_t(o)]) << "owner " << o;
    }
  }
  // The exchange: to each peer its rank and ours, repeated by the peer's number + 1.
  std::vector<std::vector<char>> send(std::size_t(c.size()));
  for (int r : peers)
    send[std::size_t(r)] = as_bytes(std::vector<int>(std::size_t(r + 1), c.rank() * 100 + r));
  const std::vector<std::vector<char>> got = c.alltoall(send, peers);
  for (int q = 0; q < c.size(); ++q) {
    if (q == c.rank()) continue;
    const std::vector<int> v = from_bytes<int>(got[std::size_t(q)]);
    if (is_peer[std::size_t(q)])
      EXPECT_EQ(v, std::vector<int>(std::size_t(c.rank() + 1), q * 100 + c.rank()));
    else
      EXPECT_TRUE(v.empty());
  }
  if (c.size() >= 3) {  // some rank (an end slab) has a rank that is not its peer
    EXPECT_GT(c.sum(std::uint64_t(peers.size() + 1 < std::size_t(c.size()))), 0u);
  }
  for (int q = 0; q < c.size(); ++q)
    if (q != c.rank() && !is_peer[std::size_t(q)]) {
      std::vector<std::vector<char>> bad(std::size_t(c.size()));
      bad[std::size_t(q)] = {'x'};
      EXPECT_THROW(c.alltoall(bad, peers), std::logic_error);
    }
}

TEST(Dist, CollectivesAreExact) {
  const Comm& c = Comm::world();
  EXPECT_EQ(c.max(double(c.rank()) + 0.5), double(c.size() - 1) + 0.5);
  EXPECT_EQ(c.min(double(c.rank()) * 1e-300), 0.0);
  EXPECT_EQ(c.sum(std::uint64_t(1) << 40), std::uint64_t(c.size()) << 40);
  std::vector<std::size_t> sizes;
  const std::vector<int> mine(std::size_t(c.rank() + 1), c.rank());
  const std::vector<int> all = from_bytes<int>(c.gather(as_bytes(mine), &sizes));
  if (c.root()) {
    std::vector<int> want;
    for (int r = 0; r < c.size(); ++r) want.insert(want.end(), std::size_t(r + 1), r);
    EXPECT_EQ(all, want);
  } else {
    EXPECT_TRUE(all.empty());
  }
  std::vector<char> b = c.root() ? std::vector<char>{'a', 'm', 'g'} : std::vector<char>{};
  c.broadcast(b);
  EXPECT_EQ(std::string(b.begin(), b.end()), "amg");
}

// Non-root ranks print their failures only, with the rank.
class FailurePrinter : public ::testing::EmptyTestEventListener {
  void OnTestPartResult(const ::testing::TestPartResult& r) override {
    if (r.failed())
      std::fprintf(stderr, "rank %d: %s:%d: %s\n", Comm::world().rank(),
                   r.file_name() ? r.file_name() : "?", r.line_number(), r.summary());
  }
};

int main(int argc, char** argv) {
  Session session(&argc, &argv);
  ::testing::InitGoogleTest(&argc, argv);
  // Only rank 0 prints the per-test lines; the other ranks print their failures.
  if (!Comm::world().root()) {
    auto& listeners = ::testing::UnitTest::GetInstance()->listeners();
    delete listeners.Release(listeners.default_result_printer());
    listeners.Append(new FailurePrinter);
  }
  const int rc = RUN_ALL_TESTS();
  // A failure on any rank fails the run on every rank.
  return Comm::world().max(std::int64_t(rc)) != 0 ? 1 : 0;
}
