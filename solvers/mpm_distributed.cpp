// Explicit MPM across MPI ranks (issue 28): MpmSolver::distribute and the distributed phases of
// its step. The grid's leaves (8^3 blocks) are owned by the box of a Zoltan RCB partition of the
// leaf table, weighted by particles per leaf (dist::RcbCuts: any leaf's owner is known on every
// rank); a particle lives only on the owner of its bin's leaf (the leaf of its stencil base).
// Per substep:
//   sort      particles whose leaf another rank owns migrate to it (all attributes, as bytes);
//             repartition when max/mean particles per rank exceeds kImbalance; then the local
//             sort by (leaf, id), the single process's order within a bin.
//   topology  a bin's block reaches its leaf and the +x/+y/+z neighbours: those another rank owns
//             are this rank's ghosts (a one-leaf halo); their owners activate them too.
//   P2G       the blocks of bins that reach ghosts are scattered first and their ghost parts sent
//             to the owners; the colour loop then adds, per colour, the received parts before its
//             own bins' flush: within a colour no two blocks meet, so every node of an owned leaf
//             sums the same blocks in the same colour order as one process (docs/architecture.md).
//   grid      update on owned leaves; the owners' node rows copied into the ghosts, only the nodes
//             G2P reads (the parts of the ghost leaves this rank's blocks reach).
//   G2P       unchanged: every leaf a local bin reads is owned or a ghost.
// Reductions are exact (max of the CFL speeds and the guard's flag); diagnostics, frames and
// checkpoints are computed on rank 0 from the particles gathered in the single process's order
// (gather_particles), so every file is bitwise that of one process.
#include <algorithm>
#include <array>
#include <climits>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <optional>
#include <string>
#include <unordered_map>

#include "core/dist/comm.hpp"
#include "core/errors.hpp"
#include "core/geometry/level_set_collider.hpp"
#include "core/math/bspline.hpp"
#include "solvers/mpm_ranks.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

using mpm_dist::key_leaf;
using mpm_dist::kPeerMargin;
using mpm_dist::leaf_centre;
using mpm_dist::leaf_key;

namespace {
constexpr double kImbalance = 1.25;  // max/mean particles per rank that triggers a repartition
constexpr std::uint64_t kRepartitionGap = 16;  // substeps between repartitions at least

int colour_of(const Vec3i& l) {
  return ((l[0] & 1) << 2) | ((l[1] & 1) << 1) | (l[2] & 1);
}
Vec3i offset_of(int t) {
  return Vec3i((t >> 2) & 1, (t >> 1) & 1, t & 1);
}

// The nodes of a leaf that the parts in `mask` cover (bit t: the part of the block of the bin at
// leaf - offset_of(t), as block_part_nodes: along an axis with t's bit set, the first `order`
// nodes), in leaf offset order. G2P reads exactly these nodes of a ghost leaf.
const std::vector<std::uint16_t>& part_nodes(int order, std::uint32_t mask) {
  static const auto tables = [] {
    std::array<std::array<std::vector<std::uint16_t>, 256>, 2> t;
    for (int o = 2; o <= 3; ++o)
      for (std::uint32_t m = 0; m < 256; ++m)
        for (int i = 0; i < kLeafDim; ++i)
          for (int j = 0; j < kLeafDim; ++j)
            for (int k = 0; k < kLeafDim; ++k) {
              bool in = false;
              for (int q = 0; q < 8 && !in; ++q)
                in = (m >> q & 1) && (!(q >> 2 & 1) || i < o) && (!(q >> 1 & 1) || j < o) &&
                     (!(q & 1) || k < o);
              if (in) t[std::size_t(o - 2)][m].push_back(std::uint16_t(leaf_offset(i, j, k)));
            }
    return t;
  }();
  return tables[std::size_t(order - 2)][mask & 255];
}

template <int Order>
Vec3i leaf_of_order(const Vec3& x, Real inv_dx) {
  Vec3i l;
  for (int a = 0; a < 3; ++a) l[a] = BSpline<Order>::base(x[a] * inv_dx) >> 3;
  return l;
}
}  // namespace

// The nodes of a ghost row: the plan's parts, dilated (re-sorting only when needed) or not.
const std::vector<std::uint16_t>& MpmSolver::Ranks::row_nodes(int order, std::uint32_t mask) {
  return dilated ? dilated_row_nodes(order, mask) : part_nodes(order, mask);
}

Vec3i MpmSolver::Ranks::part_offset(int t) const {
  return dilated ? Vec3i(t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1) : offset_of(t);
}

// The parts of each bin's block in leaves other ranks own (exports, per export bin, and their
// offsets in each rank's send buffer), their heads sent to the owners (exchange_heads).
void MpmSolver::Ranks::plan_exports(const BinTable& bins, int order, int ch) {
  const dist::Comm& comm = dist::Comm::world();
  const int R = comm.size(), me = comm.rank(), parts = dilated ? 27 : 8;
  export_bins.clear();
  export_start.assign(1, 0);
  exports.clear();
  send_reals.assign(std::size_t(R), 0);
  std::vector<std::vector<std::int32_t>> heads(
      static_cast<std::size_t>(R));  // (leaf xyz, t) per part sent
  for (std::size_t b = 0; b < bins.count(); ++b) {
    bool any = false;
    for (int t = 0; t < parts; ++t) {
      const Vec3i l = bins.leaf[b] + part_offset(t);
      const int o = owner(l);
      if (o == me) continue;
      any = true;
      exports.push_back({o, t, send_reals[std::size_t(o)]});
      send_reals[std::size_t(o)] +=
          std::size_t((dilated ? dilated_part_nodes(order, t) : block_part_nodes(order, t)) * ch);
      heads[std::size_t(o)].insert(heads[std::size_t(o)].end(), {l[0], l[1], l[2], t});
    }
    if (any) {
      export_bins.push_back(std::uint32_t(b));
      export_start.push_back(std::uint32_t(exports.size()));
    }
  }
  exchange_heads(heads);
}

// The plan's heads (leaf xyz, part t) to their owners: the parts this rank receives.
void MpmSolver::Ranks::exchange_heads(const std::vector<std::vector<std::int32_t>>& heads) {
  const dist::Comm& comm = dist::Comm::world();
  const int R = comm.size();
  std::vector<std::vector<char>> hb(static_cast<std::size_t>(R));
  for (int q = 0; q < R; ++q) hb[std::size_t(q)] = dist::as_bytes(heads[std::size_t(q)]);
  const std::vector<std::vector<char>> in = comm.alltoall(hb, peers);
  import_leaf.clear(), import_t.clear(), import_rank.clear();
  for (int q = 0; q < R; ++q) {
    const std::vector<std::int32_t> h = dist::from_bytes<std::int32_t>(in[std::size_t(q)]);
    for (std::size_t k = 0; k + 3 < h.size(); k += 4) {
      import_leaf.push_back(Vec3i(h[k], h[k + 1], h[k + 2]));
      import_t.push_back(h[k + 3]);
      import_rank.push_back(q);
    }
  }
}

// The rest of the plan once the exports, imports, owned leaves and topology are known: the ghost
// rows on both sides (the parts this rank's blocks reach in other ranks' leaves, received; those
// other ranks' blocks reach here, sent; per leaf merged, sorted by key: both sides know them from
// the heads), the interior bins (reaching no ghost) and the grid update's order (the owned leaves
// others read first, their rows travel meanwhile).
void MpmSolver::Ranks::plan_rows(const SparseGrid& grid, const BinTable& bins, int order) {
  const int R = dist::Comm::world().size();
  std::vector<std::vector<std::pair<std::uint64_t, std::uint32_t>>> recv_parts(
      static_cast<std::size_t>(R)),
      send_parts(static_cast<std::size_t>(R));
  for (std::size_t k = 0; k < export_bins.size(); ++k)
    for (std::uint32_t e = export_start[k]; e < export_start[k + 1]; ++e) {
      const Export& x = exports[e];
      recv_parts[std::size_t(x.rank)].push_back(
          {leaf_key(bins.leaf[export_bins[k]] + part_offset(x.t)), 1u << x.t});
    }
  for (std::size_t i = 0; i < import_leaf.size(); ++i)
    send_parts[std::size_t(import_rank[i])].push_back(
        {leaf_key(import_leaf[i]), 1u << import_t[i]});
  auto rows = [&](std::vector<std::vector<std::pair<std::uint64_t, std::uint32_t>>>& parts,
                  std::vector<std::vector<RowPart>>& out, std::vector<std::size_t>& nodes) {
    out.assign(std::size_t(R), {});
    nodes.assign(std::size_t(R), 0);
    for (int q = 0; q < R; ++q) {
      auto& v = parts[std::size_t(q)];
      std::sort(v.begin(), v.end());
      for (std::size_t i = 0; i < v.size();) {
        std::uint32_t mask = 0;
        const std::uint64_t key = v[i].first;
        for (; i < v.size() && v[i].first == key; ++i) mask |= v[i].second;
        const std::int32_t slot = grid.find_leaf(key_leaf(key) * kLeafDim);
        if (slot < 0) throw std::logic_error("MPM halo: a ghost row's leaf is not in the grid");
        out[std::size_t(q)].push_back({std::uint32_t(slot), mask});
        nodes[std::size_t(q)] += row_nodes(order, mask).size();
      }
    }
  };
  rows(recv_parts, rows_recv, rows_recv_nodes);
  rows(send_parts, rows_send, rows_send_nodes);
  interior_bins.clear();
  for (std::size_t b = 0, k = 0; b < bins.count(); ++b) {
    if (k < export_bins.size() && export_bins[k] == b) {
      ++k;
      continue;
    }
    interior_bins.push_back(std::uint32_t(b));
  }
  std::vector<char> read(grid.leaf_coords().size(), 0);
  for (const auto& v : rows_send)
    for (const RowPart& r : v) read[r.slot] = 1;
  update_order.clear();
  for (int first = 1; first >= 0; --first) {
    for (const std::int32_t li : owned_active)
      if (read[std::size_t(li)] == first) update_order.push_back(li);
    if (first) row_leaves = update_order.size();
  }
}

Vec3i MpmSolver::particle_leaf(const Vec3& x) const {
  const Real inv_dx = Real(1) / settings_.dx;
  return settings_.order == 3 ? leaf_of_order<3>(x, inv_dx) : leaf_of_order<2>(x, inv_dx);
}

void MpmSolver::refuse_distributed() const {
  auto refuse = [](const std::string& what) {
    throw InputError("MPM on several MPI ranks: " + what +
                     " not distributed yet (issue 28); run one rank, with --threads for the cores");
  };
  if (implicit_) refuse("implicit integration (simulation.implicit) is");
  // A-ULMPM's PIC/FLIP node positions come from their own pass (p2g_positions), whose ghost sums
  // are not exchanged; MLS and APIC fuse them into the P2G block, which is.
  if (aul_ && settings_.transfer == Transfer::PicFlip && channels_.positions >= 0)
    refuse(
        "A-ULMPM objects with PIC/FLIP transfers (simulation.transfer \"pic\" or \"flip\") and "
        "colliders or contact between objects are");
  if (enriched_) refuse("particle domains (simulation.domains) are");
  // One process would run the fused substep, whose grid sums round otherwise than the two
  // passes' (docs/architecture.md, "The fused substep"): on several ranks the frames would not
  // be the single process's bits. (Variants that fall back to two passes on one process, e.g.
  // sleeping, run distributed as usual; ranks_ is not set yet here.)
  if (fused_eligible()) refuse("the fused G2P2G substep (simulation.transfer_pass \"fused\") is");
}

// Every rank builds the field colliders around the blocks of all ranks' particles: the region
// one process builds, so every query (owned nodes, local particles) finds its voxels built.
void MpmSolver::prepare_colliders_distributed(const exec::Space& space, Real t) {
  bool any = false;
  for (const Collider& c : colliders_) any |= bool(c.field);
  if (!any) return;
  using Key = std::array<std::int64_t, 3>;
  const std::vector<Key> mine =
      collider_blocks(particles_.vec3(attr_.x), particles_.size(), settings_.dx);
  std::vector<Key> all =
      dist::from_bytes<Key>(dist::Comm::world().allgather(dist::as_bytes(mine), nullptr));
  std::sort(all.begin(), all.end());
  all.erase(std::unique(all.begin(), all.end()), all.end());
  prepare_collider_blocks(colliders_, all, settings_.dx, t, space);
}

void MpmSolver::distribute(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  if (comm.size() == 1 || ranks_) return;
  refuse_distributed();
  auto ranks = std::make_shared<Ranks>();
  std::optional<exec::ScopedRegion> region;  // the set-up's steps, each a profiler region
  region.emplace(space.profiler(), "dist.setup_cut");
  if (const char* e = std::getenv("AMALGAM_TEST_REPARTITION_EVERY"))
    ranks->force_every = std::atoi(e);
  // Each rank sends one slice of the particles to their owners: a fresh set-up's own slice
  // (solvers/factory.cpp) or its slice of a per-rank checkpoint (set_slice_keys), or, when it
  // holds every particle (a checkpoint read whole), the slice [n r / R, n (r + 1) / R) of them.
  // A particle's place in the single process's order (the gathered frames before the first
  // sort): its id in a fresh set-up (ids follow the sampling order), the checkpoint's order keys,
  // or its index in a whole checkpoint.
  const std::uint64_t r = std::uint64_t(comm.rank()), R = std::uint64_t(comm.size());
  const std::size_t n = particles_.size();
  const std::size_t lo = sliced_ ? 0 : std::size_t(n * r / R),
                    hi = sliced_ ? n : std::size_t(n * (r + 1) / R);
  const Vec3* x = particles_.vec3(bin_position());
  const std::int32_t* id = particles_.int32(attr_.id);
  std::int64_t bad = -1;
  for (std::size_t p = lo; p < hi && bad < 0; ++p)
    if (!x[p].allFinite() || x[p].cwiseAbs().maxCoeff() / settings_.dx > Real(1 << 28)) bad = id[p];
  bad = comm.max(bad);
  if (bad >= 0)
    throw SimulationError("particle id " + std::to_string(bad) +
                          " has a non-finite or runaway position at set-up");
  // The leaves and their particle counts, joined over the ranks into one table (the same on
  // every rank), each rank handing Zoltan a slice of it.
  std::vector<std::uint64_t> key(hi - lo);
  for (std::size_t p = lo; p < hi; ++p) key[p - lo] = leaf_key(particle_leaf(x[p]));
  std::vector<std::uint64_t> table;  // (leaf key, particles) pairs, this rank's slice
  {
    std::vector<std::uint64_t> sorted = key;
    std::sort(sorted.begin(), sorted.end());
    for (std::size_t i = 0; i < sorted.size(); ++i) {
      if (i == 0 || sorted[i] != sorted[i - 1]) table.push_back(sorted[i]), table.push_back(0);
      ++table.back();
    }
  }
  std::vector<std::uint64_t> joined =
      dist::from_bytes<std::uint64_t>(comm.allgather(dist::as_bytes(table), nullptr));
  std::vector<std::pair<std::uint64_t, std::uint64_t>> pairs(joined.size() / 2);
  for (std::size_t i = 0; i < pairs.size(); ++i) pairs[i] = {joined[2 * i], joined[2 * i + 1]};
  joined = {};
  std::sort(pairs.begin(), pairs.end());
  std::vector<float> count;
  std::vector<std::uint64_t> unique;
  std::uint64_t total = 0;
  for (std::size_t i = 0; i < pairs.size(); ++i) {
    if (i == 0 || pairs[i].first != pairs[i - 1].first)
      unique.push_back(pairs[i].first), count.push_back(0);
    count.back() += float(pairs[i].second);
    total += pairs[i].second;
  }
  const std::uint64_t m = unique.size();
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  std::vector<float> w;
  for (std::uint64_t i = m * r / R; i < m * (r + 1) / R; ++i) {
    ids.push_back(i);
    double c[3];
    leaf_centre(key_leaf(unique[i]), c);
    xyz.insert(xyz.end(), c, c + 3);
    w.push_back(count[i]);
  }
  ranks->cuts = dist::RcbCuts::partition(ids, xyz, w);
  ranks->peers = ranks->cuts.neighbours(kPeerMargin);
  ranks->last_partition = steps_;
  // Every particle of the slice to its owner (all ranks to all: the set-up's slices are not
  // spatial). A rank's buffer holds its n particles' order keys (16 B each), then each
  // attribute's words for the n particles in turn: packed and unpacked attribute by attribute,
  // in long copies, rather than particle by particle (which cost 1.1 s of 475k particles a rank
  // on the sphere, docs/scaling.md).
  region.reset();
  region.emplace(space.profiler(), "dist.setup_pack");
  const int na = particles_.attribute_count();
  std::vector<std::size_t> wa(static_cast<std::size_t>(na)),
      attr_at(wa.size());  // words, offset (B)
  std::size_t words = 0;
  for (int a = 0; a < na; ++a)
    attr_at[std::size_t(a)] = 16 + 4 * words,
    words += wa[std::size_t(a)] = std::size_t(particles_.words_per_particle(a));
  const std::size_t record = 16 + words * 4;
  std::vector<int> dest(hi - lo);
  std::vector<std::size_t> per_rank(R, 0), at(R, 0);
  {
    std::uint64_t last_key = ~std::uint64_t(0);  // neighbours in the sampling order share leaves
    int last_owner = 0;
    for (std::size_t p = lo; p < hi; ++p) {
      if (key[p - lo] != last_key)
        last_key = key[p - lo], last_owner = ranks->owner(key_leaf(last_key));
      dest[p - lo] = last_owner;
      ++per_rank[std::size_t(last_owner)];
    }
  }
  key = {};
  std::vector<std::vector<char>> send(R);
  for (std::size_t d = 0; d < R; ++d) send[d].resize(per_rank[d] * record);
  for (std::size_t p = lo; p < hi; ++p) {
    const std::size_t d = std::size_t(dest[p - lo]);
    const std::uint64_t order[2] = {!slice_keys_.empty() ? slice_keys_[2 * p]
                                    : sliced_            ? std::uint64_t(id[p])
                                                         : p,
                                    !slice_keys_.empty() ? slice_keys_[2 * p + 1] : 0};
    std::memcpy(send[d].data() + 16 * at[d]++, order, 16);
  }
  for (int a = 0; a < na; ++a) {
    const std::size_t bytes = 4 * wa[std::size_t(a)];
    const char* src = reinterpret_cast<const char*>(particles_.words(a));
    std::vector<char*> out(R);
    for (std::size_t d = 0; d < R; ++d)
      out[d] = send[d].data() + per_rank[d] * attr_at[std::size_t(a)];
    for (std::size_t p = lo; p < hi; ++p) {
      const std::size_t d = std::size_t(dest[p - lo]);
      std::memcpy(out[d], src + p * bytes, bytes);
      out[d] += bytes;
    }
  }
  dest = {};
  slice_keys_ = {};
  region.reset();
  region.emplace(space.profiler(), "dist.setup_alltoall");
  const std::vector<std::vector<char>> in = comm.alltoall(send);
  send = {};
  region.reset();
  region.emplace(space.profiler(), "dist.setup_unpack");
  // Received in rank order; kept in the single process's order, which is the rank order
  // already when each rank's slice is a run of that order (a fresh set-up: ids ascend with the
  // slices; a checkpoint read whole: indices), else found by sorting the keys.
  std::vector<std::size_t> first(R + 1, 0);  // rank q's particles: [first[q], first[q + 1])
  for (std::size_t q = 0; q < R; ++q) {
    if (in[q].size() % record != 0)
      throw std::logic_error("distribute: a received buffer is not whole records");
    first[q + 1] = first[q] + in[q].size() / record;
  }
  const std::size_t N = first[R];
  ranks->presort.resize(2 * N);
  for (std::size_t q = 0; q < R; ++q)
    if (!in[q].empty())
      std::memcpy(ranks->presort.data() + 2 * first[q], in[q].data(),
                  16 * (first[q + 1] - first[q]));
  auto order_of = [&](std::size_t i) {
    return std::array<std::uint64_t, 2>{ranks->presort[2 * i], ranks->presort[2 * i + 1]};
  };
  bool in_order = true;
  for (std::size_t i = 1; i < N && in_order; ++i) in_order = order_of(i - 1) < order_of(i);
  std::vector<std::uint32_t> perm;  // perm[i]: the received particle at place i
  if (!in_order) {
    perm.resize(N);
    for (std::size_t i = 0; i < N; ++i) perm[i] = std::uint32_t(i);
    std::stable_sort(perm.begin(), perm.end(),
                     [&](std::uint32_t a, std::uint32_t b) { return order_of(a) < order_of(b); });
    std::vector<std::uint64_t> sorted(2 * N);
    for (std::size_t i = 0; i < N; ++i)
      sorted[2 * i] = ranks->presort[2 * perm[i]],
                 sorted[2 * i + 1] = ranks->presort[2 * perm[i] + 1];
    ranks->presort = std::move(sorted);
  }
  std::vector<std::uint32_t> from(N);  // the received particle i's rank, when not in order
  if (!in_order)
    for (std::size_t q = 0; q < R; ++q)
      for (std::size_t i = first[q]; i < first[q + 1]; ++i) from[i] = std::uint32_t(q);
  particles_.resize(N);
  for (int a = 0; a < na; ++a) {
    const std::size_t bytes = 4 * wa[std::size_t(a)];
    char* dst = reinterpret_cast<char*>(particles_.words(a));
    auto src = [&](std::size_t q) {
      return in[q].data() + (first[q + 1] - first[q]) * attr_at[std::size_t(a)];
    };
    if (in_order) {
      for (std::size_t q = 0; q < R; ++q)
        if (first[q + 1] > first[q])
          std::memcpy(dst + first[q] * bytes, src(q), (first[q + 1] - first[q]) * bytes);
      continue;
    }
    for (std::size_t i = 0; i < N; ++i) {
      const std::size_t j = perm[i], q = from[j];
      std::memcpy(dst + i * bytes, src(q) + (j - first[q]) * bytes, bytes);
    }
  }
  sliced_ = false;
  ranks->set_up_most = std::uint64_t(comm.max(std::int64_t(hi - lo)));
  ranks->set_up_total = total;
  ranks->balanced =
      double(comm.max(std::int64_t(N))) * double(R) / double(std::max<std::uint64_t>(total, 1));
  ranks_ = std::move(ranks);
  ++state_version_;
}

// Particles whose leaf another rank owns go to it: every attribute's words, particle by particle.
void MpmSolver::migrate(const exec::Space& space, bool anywhere) {
  exec::ScopedRegion region(space.profiler(), "dist.migrate");
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  const std::size_t n = particles_.size();
  const Vec3* x = particles_.vec3(bin_position());
  // Each particle's leaf in parallel (with the first bad position). While the particles are in
  // the bins of the last sort (bins_match), a particle still in its bin's leaf stays (that leaf
  // is this rank's); only the others (about 1 % a substep on the sphere) look their owner up,
  // serially, and only the leavers are packed and refilled. Otherwise every particle looks up.
  rk.migrate_leaf.resize(n);
  rk.migrate_dest.resize(n);
  Vec3i* lf = rk.migrate_leaf.data();
  int* dst = rk.migrate_dest.data();
  const Real dx = settings_.dx;
  const int me = comm.rank();
  const bool by_bin = !anywhere && rk.bins_match && !bins_.start.empty() && bins_.start.back() <= n;
  const std::size_t nb = by_bin ? bins_.count() : 0, tail = by_bin ? bins_.start.back() : 0;
  constexpr std::size_t kChunk = 4096;  // the particles after the bins (emitted), per task
  const std::uint32_t* bstart = bins_.start.data();
  const Vec3i* bleaf = bins_.leaf.data();
  const std::int64_t bad = exec::parallel_reduce(
      space, "dist.migrate_leaves", exec::Index(nb + (n - tail + kChunk - 1) / kChunk),
      std::int64_t(-1),
      [=](exec::Index i, std::int64_t& first) {
        const bool bin = std::size_t(i) < nb;
        const std::size_t p0 = bin ? bstart[i] : tail + (std::size_t(i) - nb) * kChunk,
                          p1 = bin ? bstart[i + 1] : std::min(n, p0 + kChunk);
        for (std::size_t p = p0; p < p1; ++p) {
          if (!x[p].allFinite() || x[p].cwiseAbs().maxCoeff() / dx > Real(1 << 28)) {
            if (first < 0 || std::int64_t(p) < first) first = std::int64_t(p);
            continue;
          }
          lf[p] = particle_leaf(x[p]);
          dst[p] = bin && lf[p] == bleaf[i] ? me : -1;
        }
      },
      [](std::int64_t a, std::int64_t b) { return a < 0 ? b : (b < 0 ? a : std::min(a, b)); });
  rk.bins_match = false;  // the leavers' slots are refilled below
  std::vector<char> is_peer(std::size_t(comm.size()), char(anywhere));
  for (int q : rk.peers) is_peer[std::size_t(q)] = 1;
  is_peer[std::size_t(me)] = 1;
  Vec3i last(INT_MIN, 0, 0);
  int last_owner = 0;
  bool far = false;  // a particle for a rank that is not a peer (moved more than a leaf)
  std::vector<std::uint32_t>& movers = rk.migrate_movers;  // the leavers, increasing
  movers.clear();
  for (std::size_t p = 0; p < n && bad < 0; ++p) {
    if (dst[p] == me) continue;
    if (lf[p] != last) last = lf[p], last_owner = rk.owner(lf[p]), far |= !is_peer[last_owner];
    dst[p] = last_owner;
    if (last_owner != me) movers.push_back(std::uint32_t(p));
  }
  // One collective for three: status 2 a bad position somewhere, 1 a particle for a non-peer;
  // and the particles per rank before migrating, which sort_distributed's repartition test uses
  // (migration keeps the total; the largest rank is that of the substep before, give or take
  // the few leavers) instead of two reductions of its own.
  const std::vector<std::int64_t> all = dist::from_bytes<std::int64_t>(
      comm.allgather(dist::as_bytes(std::vector<std::int64_t>{bad >= 0 ? 2
                                                              : far    ? 1
                                                                       : 0,
                                                              std::int64_t(n)}),
                     nullptr));
  std::int64_t status = 0;
  rk.count_most = 0, rk.count_total = 0;
  for (std::size_t q = 0; q + 1 < all.size(); q += 2) {
    status = std::max(status, all[q]);
    rk.count_most = std::max(rk.count_most, all[q + 1]);
    rk.count_total += all[q + 1];
  }
  if (status == 2)
    throw SimulationError(bad >= 0 ? "step " + std::to_string(steps_) + ": particle id " +
                                         std::to_string(particles_.int32(attr_.id)[bad]) +
                                         " (rank " + std::to_string(comm.rank()) +
                                         ") has a non-finite or runaway position"
                                   : "step " + std::to_string(steps_) +
                                         ": a particle on another rank has a non-finite or "
                                         "runaway position");
  const int na = particles_.attribute_count();
  std::size_t words = 0;
  for (int a = 0; a < na; ++a) words += std::size_t(particles_.words_per_particle(a));
  std::vector<std::vector<char>> send(static_cast<std::size_t>(comm.size()));
  for (const std::uint32_t p : movers) {
    std::vector<char>& out = send[std::size_t(dst[p])];
    for (int a = 0; a < na; ++a) {
      const std::size_t wa = std::size_t(particles_.words_per_particle(a));
      const char* src = reinterpret_cast<const char*>(particles_.words(a) + p * wa);
      out.insert(out.end(), src, src + wa * 4);
    }
  }
  const std::vector<std::vector<char>> in =
      status == 1 || anywhere ? comm.alltoall(send) : comm.alltoall(send, rk.peers);
  // The leavers' slots are filled from the end (a few copies, not a gather of every particle):
  // the order changes, but the sort that follows puts the particles in (leaf, id) order, which
  // does not depend on the order they come in.
  if (!movers.empty()) {
    std::size_t m = n;
    for (std::size_t k = movers.size(); k-- > 0;) {
      const std::size_t p = movers[k];
      --m;
      if (p != m)
        for (int a = 0; a < na; ++a) {
          const std::size_t wa = std::size_t(particles_.words_per_particle(a));
          std::memcpy(particles_.words(a) + p * wa, particles_.words(a) + m * wa, wa * 4);
        }
    }
    particles_.resize(m);
  }
  std::size_t arriving = 0;
  for (const auto& b : in) arriving += b.size() / (words * 4);
  if (arriving == 0) return;
  std::size_t at = particles_.size();
  particles_.resize(at + arriving);
  for (const auto& b : in)
    for (std::size_t off = 0; off < b.size(); ++at)
      for (int a = 0; a < na; ++a) {
        const std::size_t wa = std::size_t(particles_.words_per_particle(a));
        std::memcpy(particles_.words(a) + at * wa, b.data() + off, wa * 4);
        off += wa * 4;
      }
}

void MpmSolver::repartition() {
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  // This rank's leaves (every particle of a leaf is on its owner after migration) and counts.
  std::unordered_map<std::uint64_t, float> count;
  std::vector<std::uint64_t> keys;
  const Vec3* x = particles_.vec3(bin_position());
  for (std::size_t p = 0; p < particles_.size(); ++p) {
    const std::uint64_t k = leaf_key(particle_leaf(x[p]));
    if (count[k]++ == 0) keys.push_back(k);
  }
  std::sort(keys.begin(), keys.end());
  // Global ids: this rank's leaves after those of the ranks before it.
  const std::vector<std::uint64_t> counts = dist::from_bytes<std::uint64_t>(
      comm.allgather(dist::as_bytes(std::vector<std::uint64_t>{keys.size()}), nullptr));
  std::uint64_t first = 0;
  for (int q = 0; q < comm.rank(); ++q) first += counts[std::size_t(q)];
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  std::vector<float> w;
  for (std::size_t i = 0; i < keys.size(); ++i) {
    ids.push_back(first + i);
    double c[3];
    leaf_centre(key_leaf(keys[i]), c);
    xyz.insert(xyz.end(), c, c + 3);
    w.push_back(count[keys[i]]);
  }
  rk.cuts = dist::RcbCuts::partition(ids, xyz, w);
  rk.peers = rk.cuts.neighbours(kPeerMargin);
  rk.owner_cache.clear();
  rk.last_partition = steps_;
  ++rk.repartitions;
}

void MpmSolver::sort_distributed(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  migrate(space, false);
  // Repartition when the work (particles) is unbalanced; results do not depend on the partition.
  // The counts are those migrate gathered (before it moved the leavers).
  const double most = double(rk.count_most), mean = double(rk.count_total) / comm.size();
  const bool forced = rk.force_every > 0 && steps_ % std::uint64_t(rk.force_every) == 0 &&
                      steps_ > rk.last_partition;
  // A leaf is the partition's grain: when the best cut of the leaves leaves some imbalance, wait
  // until it grows by a tenth before cutting again.
  const double imbalance = mean > 0 ? most / mean : 1.0;
  if (forced || (imbalance > kImbalance && imbalance > 1.1 * rk.balanced &&
                 steps_ >= rk.last_partition + kRepartitionGap)) {
    repartition();
    migrate(space, true);
    const std::int64_t now = std::int64_t(particles_.size());
    rk.balanced = double(comm.max(now)) / mean;
  }
  binning_.sort_and_bin(space, particles_, bin_position(), settings_.dx, settings_.order, bins_,
                        attr_.id);
  rk.bins_match = true;
  // How often the plan could be kept (its heads depend on the bins' leaves only): substeps whose
  // bin leaves are those of the last one, for the summary.
  ++rk.sorts;
  if (bins_.leaf == rk.last_bin_leaves) ++rk.same_bin_leaves;
  rk.last_bin_leaves = bins_.leaf;
  rk.sorted = true;
  rk.presort.clear();
}

// Which parts of which local blocks go to which rank, which parts come in, the owned leaves and
// the halo: then the grid's topology with the leaves only other ranks' blocks reach.
void MpmSolver::update_grid_distributed(const exec::Space& space) {
  Ranks& rk = *ranks_;
  const int order = settings_.order;
  const int ch = settings_.transfer == Transfer::PicFlip || fused_positions() ? 8 : 4;
  exec::ScopedRegion region(space.profiler(), "dist.plan");
  rk.dilated = false;
  rk.plan_exports(bins_, order, ch);
  std::vector<std::uint64_t> ghost_keys;  // the leaves this rank's blocks reach on other ranks
  for (std::size_t k = 0; k < rk.export_bins.size(); ++k)
    for (std::uint32_t e = rk.export_start[k]; e < rk.export_start[k + 1]; ++e)
      ghost_keys.push_back(
          leaf_key(bins_.leaf[rk.export_bins[k]] + rk.part_offset(rk.exports[e].t)));
  grid_.update_topology(space, bins_, &rk.import_leaf);
  // Owned active leaves: the active ones that are no ghost.
  std::sort(ghost_keys.begin(), ghost_keys.end());
  ghost_keys.erase(std::unique(ghost_keys.begin(), ghost_keys.end()), ghost_keys.end());
  rk.owned_active.clear();
  const auto& coords = grid_.leaf_coords();
  for (std::int32_t li : grid_.active_leaves()) {
    const std::uint64_t k = leaf_key(coords[std::size_t(li)]);
    if (std::binary_search(ghost_keys.begin(), ghost_keys.end(), k)) continue;
    rk.owned_active.push_back(li);
  }
  rk.plan_rows(grid_, bins_, order);
  rk.halo_leaves = ghost_keys.size();
  rk.halo_parts = rk.exports.size();
  if (sleep_)
    sleep_->decide(space, particles_, attr_, bins_, settings_.dx, time_, colliders_at(Real(time_)),
                   int(colliders_.size()), emitters_, true);
}

void MpmSolver::particle_to_grid_distributed(const exec::Space& space, Real dt) {
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  const int R = comm.size(), order = settings_.order;
  MpmGridView g = grid_view();
  const MpmStepParams prm = step_params(dt);
  grid_clear(space, g, prm);
  if (fused_positions()) {  // A-ULMPM: (m, m q) in lanes 4..7 of the blocks, as on one process
    g.q_out = grid_.node4(channels_.positions);
    clear_node4(space, g, g.q_out);
  }
  // The blocks of the bins whose parts other ranks' leaves receive, scattered first: their parts
  // sent, the blocks kept for the colour loop's flush.
  const int ch = settings_.transfer == Transfer::PicFlip || fused_positions() ? 8 : 4;
  std::vector<std::vector<char>>& send = rk.p2g_out;
  send.resize(std::size_t(R));
  for (int q = 0; q < R; ++q)
    send[std::size_t(q)].resize(rk.send_reals[std::size_t(q)] * sizeof(Real));
  const std::size_t block_reals = p2g_block_reals(order, ch);
  // While the parts travel, the interior bins' blocks are scattered and kept too (up to
  // kKeptInterior bytes of blocks), so that the colour loop after the receive only flushes: a
  // rank with few exports no longer waits idle for its neighbour's (measured: the rank on the +
  // side of the cut has almost none and waited ~25 % of its P2G). Each block is what the colour
  // loop would scatter, flushed in the same colour order: the sums are unchanged.
  constexpr std::size_t kKeptInterior = std::size_t(256) << 20;
  const std::size_t ninterior =
      std::min(rk.interior_bins.size(), kKeptInterior / (block_reals * sizeof(Real)));
  const std::size_t nexport = rk.export_bins.size();
  rk.kept.resize((nexport + ninterior) * block_reals);
  rk.kept_slot.assign(bins_.count(), -1);
  for (std::size_t k = 0; k < nexport; ++k) rk.kept_slot[rk.export_bins[k]] = std::int32_t(k);
  for (std::size_t k = 0; k < ninterior; ++k)
    rk.kept_slot[rk.interior_bins[k]] = std::int32_t(nexport + k);
  const MpmParticleView pv = particle_view();
  p2g_blocks(space, pv, g, prm, rk.export_bins.data(), nexport, rk.kept.data(),
             [&](std::size_t k, const Real* block, int) {
               for (std::uint32_t e = rk.export_start[k]; e < rk.export_start[k + 1]; ++e) {
                 const Ranks::Export& x = rk.exports[e];
                 Real* out = reinterpret_cast<Real*>(send[std::size_t(x.rank)].data()) + x.offset;
                 copy_block_part(block, order, ch, x.t, out);
               }
             });
  // Both sides know the sizes from the plan's heads: point to point, no sizes round.
  std::vector<std::size_t> expect(std::size_t(R), 0);
  for (std::size_t i = 0; i < rk.import_t.size(); ++i)
    expect[std::size_t(rk.import_rank[i])] +=
        std::size_t(block_part_nodes(order, rk.import_t[i]) * ch) * sizeof(Real);
  comm.exchange_start(rk.p2g_pending, send, expect);
  p2g_blocks(space, pv, g, prm, rk.interior_bins.data(), ninterior,
             rk.kept.data() + nexport * block_reals, [](std::size_t, const Real*, int) {});
  {
    exec::ScopedRegion region(space.profiler(), "dist.p2g_exchange");
    rk.received = comm.exchange_finish(rk.p2g_pending);
  }
  // The received parts by colour of the block they come from (the bin leaf = leaf - t).
  std::vector<P2GImport> by_rank;
  std::array<std::uint32_t, 9> count{};
  std::vector<std::size_t> at(std::size_t(R), 0);
  std::vector<int> colour(rk.import_leaf.size());
  for (std::size_t i = 0; i < rk.import_leaf.size(); ++i) {
    const int q = rk.import_rank[i], t = rk.import_t[i];
    const Real* data =
        reinterpret_cast<const Real*>(rk.received[std::size_t(q)].data()) + at[std::size_t(q)];
    at[std::size_t(q)] += std::size_t(block_part_nodes(order, t) * ch);
    if (at[std::size_t(q)] * sizeof(Real) > rk.received[std::size_t(q)].size())
      throw std::runtime_error("MPM halo: rank " + std::to_string(q) +
                               " sent too few partial sums");
    by_rank.push_back({grid_.find_leaf(rk.import_leaf[i] * kLeafDim), t, data});
    colour[i] = colour_of(rk.import_leaf[i] - offset_of(t));
    ++count[std::size_t(colour[i]) + 1];
  }
  for (int c = 0; c < 8; ++c) count[std::size_t(c) + 1] += count[std::size_t(c)];
  rk.import_colour_start = count;
  rk.imports.resize(by_rank.size());
  for (std::size_t i = 0; i < by_rank.size(); ++i)
    rk.imports[count[std::size_t(colour[i])]++] = by_rank[i];
  g.imports = rk.imports.data();
  g.import_colour_start = rk.import_colour_start.data();
  g.kept_slot = rk.kept_slot.data();
  g.kept = rk.kept.data();
  p2g(space, pv, g, prm);
}

void MpmSolver::update_grid_velocities_distributed(const exec::Space& space, Real dt) {
  Ranks& rk = *ranks_;
  MpmGridView g = grid_view_with_positions();  // A-ULMPM: colliders at the nodes' q_i
  const MpmStepParams prm = step_params(dt);
  rk.g2p_interior_done = false;
  // Overlapped: the owned leaves others read are updated first and their rows sent; while they
  // travel the other leaves are updated and the interior bins (which read owned leaves only)
  // gathered: G2P per bin is independent of the others, so the particles end bitwise the same,
  // and the ghosts hold their rows when this returns, as before. grid_to_particle_distributed
  // then gathers the bins that read ghosts. Not with sleeping blocks (their nodes are pinned
  // after the whole update) nor A-ULMPM (the objects' coupling runs on the whole grid, ghosts
  // included, before G2P): those exchange after the whole update.
  if (!sleep_ && !aul_) {
    update_owned_leaves_rows_first(space, g, prm);
    g2p_bins(space, rk.interior_bins, dt);
    rk.g2p_interior_done = true;
    finish_ghost_rows(space);
    return;
  }
  g.active_leaves = rk.owned_active.data();
  g.nactive = rk.owned_active.size();
  grid_update(space, g, prm);
  if (sleep_) sleep_->pin_nodes(space, grid_, bins_, grid_.node4(0));  // own leaves: owned
  exchange_ghost_rows(space);
}

// The grid update of the owned leaves others read first, their node rows then sent
// (start_ghost_rows), then of the other owned leaves: the caller gathers its interior bins while
// the rows travel, then finish_ghost_rows.
void MpmSolver::update_owned_leaves_rows_first(const exec::Space& space, MpmGridView g,
                                               const MpmStepParams& prm) {
  Ranks& rk = *ranks_;
  g.active_leaves = rk.update_order.data();
  g.nactive = rk.row_leaves;
  grid_update(space, g, prm);
  start_ghost_rows(space);
  g.active_leaves = rk.update_order.data() + rk.row_leaves;
  g.nactive = rk.update_order.size() - rk.row_leaves;
  grid_update(space, g, prm);
}

void MpmSolver::grid_to_particle_distributed(const exec::Space& space, Real dt) {
  Ranks& rk = *ranks_;
  if (rk.g2p_interior_done)
    g2p_bins(space, rk.export_bins, dt);
  else
    g2p(space, particle_view(), grid_view(), step_params(dt));
  rk.g2p_interior_done = false;
  if (sleep_) sleep_->rest(space, particles_, attr_, dt);
}

// G2P of the listed bins only: the kernel over a view of their neighbour tables, particle ranges
// and leaves.
void MpmSolver::g2p_bins(const exec::Space& space, const std::vector<std::uint32_t>& list,
                         Real dt) {
  g2p(space, particle_view(), ranks_->sub_view(grid_view(), list), step_params(dt));
}

// Owners' node rows (m, v) (and PIC/FLIP's (-, dv)) into the ghosts, the nodes G2P reads only
// (the parts of the ghost leaves this rank's blocks reach), point to point: both sides know the
// nodes from the plan. Bytes moved, never combined: a ghost node holds its owner's bits.
// start_ghost_rows sends this rank's rows (of leaves already updated) and posts the receives;
// finish_ghost_rows waits for the receives and stores them in the ghost leaves.
void MpmSolver::start_ghost_rows(const exec::Space& space) {
  exec::ScopedRegion region(space.profiler(), "dist.halo_send");
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  const std::size_t R = std::size_t(comm.size());
  std::vector<Real*>& channel = rk.row_channels;  // finish_ghost_rows stores into the same
  channel.assign(1, grid_.node4(0));
  if (channels_.second >= 0) channel.push_back(grid_.node4(channels_.second));
  const std::size_t node_bytes = 4 * sizeof(Real) * channel.size();
  std::vector<std::vector<char>>& out = rk.rows_out;
  out.resize(R);
  std::vector<std::size_t> expect(R);
  for (std::size_t q = 0; q < R; ++q) {
    expect[q] = rk.rows_recv_nodes[q] * node_bytes;
    out[q].resize(rk.rows_send_nodes[q] * node_bytes);
    Real* o = reinterpret_cast<Real*>(out[q].data());
    for (const Ranks::RowPart& r : rk.rows_send[q])
      for (const Real* c : channel)
        for (std::uint16_t n : rk.row_nodes(settings_.order, r.mask)) {
          std::memcpy(o, c + (std::size_t(r.slot) * kLeafNodes + n) * 4, 4 * sizeof(Real));
          o += 4;
        }
  }
  comm.exchange_start(rk.rows_pending, out, expect);
}

void MpmSolver::exchange_ghost_rows(const exec::Space& space) {
  start_ghost_rows(space);
  finish_ghost_rows(space);
}

void MpmSolver::finish_ghost_rows(const exec::Space& space) {
  exec::ScopedRegion region(space.profiler(), "dist.halo");
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  const std::size_t R = std::size_t(comm.size());
  const std::vector<Real*>& channel = rk.row_channels;
  const std::size_t node_bytes = 4 * sizeof(Real) * channel.size();
  const std::vector<std::vector<char>> in = comm.exchange_finish(rk.rows_pending);
  for (std::size_t q = 0; q < R; ++q) {
    const std::size_t expect = rk.rows_recv_nodes[q] * node_bytes;
    if (in[q].size() != expect)
      throw std::runtime_error("MPM halo: rank " + std::to_string(q) + " sent " +
                               std::to_string(in[q].size()) + " bytes of node rows, expected " +
                               std::to_string(expect));
    const Real* i = reinterpret_cast<const Real*>(in[q].data());
    for (const Ranks::RowPart& r : rk.rows_recv[q])
      for (Real* c : channel)
        for (std::uint16_t n : rk.row_nodes(settings_.order, r.mask)) {
          std::memcpy(c + (std::size_t(r.slot) * kLeafNodes + n) * 4, i, 4 * sizeof(Real));
          i += 4;
        }
  }
}

const std::vector<std::int32_t>& MpmSolver::owned_leaf_list() const {
  return ranks_->owned_active;
}
int MpmSolver::leaf_owner(const Vec3i& leaf) const {
  return ranks_->owner(leaf);
}
const std::vector<int>& MpmSolver::exchange_peers() const {
  return ranks_->peers;
}

std::vector<std::uint64_t> MpmSolver::order_keys() const {
  const std::size_t n = particles_.size();
  std::vector<std::uint64_t> order(2 * n);
  if (!ranks_) {
    for (std::size_t p = 0; p < n; ++p) order[2 * p] = p, order[2 * p + 1] = 0;
    return order;
  }
  const Ranks& rk = *ranks_;
  // Each particle's place in the single process's order: (bin leaf, id) once sorted, the
  // one-process index before.
  const std::int32_t* id = particles_.int32(attr_.id);
  if (rk.sorted) {
    for (std::size_t b = 0; b < bins_.count(); ++b)
      for (std::uint32_t p = bins_.start[b]; p < bins_.start[b + 1]; ++p)
        order[2 * p] = leaf_key(bins_.leaf[b]), order[2 * p + 1] = std::uint64_t(id[p]);
    // Particles emitted after the sort follow every sorted one, by id (emission order).
    for (std::size_t p = bins_.start.empty() ? 0 : bins_.start.back(); p < n; ++p)
      order[2 * p] = ~std::uint64_t(0), order[2 * p + 1] = std::uint64_t(id[p]);
  } else {
    std::copy(rk.presort.begin(), rk.presort.end(), order.begin());
  }
  return order;
}

void MpmSolver::gather_particles(ParticleSet& out) const {
  if (!ranks_) {
    out = particles_;
    return;
  }
  const dist::Comm& comm = dist::Comm::world();
  const std::size_t n = particles_.size();
  const std::vector<std::uint64_t> order = order_keys();
  const int na = particles_.attribute_count();
  std::size_t words = 0;
  for (int a = 0; a < na; ++a) words += std::size_t(particles_.words_per_particle(a));
  std::vector<char> mine(n * words * 4);
  {
    char* o = mine.data();
    for (std::size_t p = 0; p < n; ++p)
      for (int a = 0; a < na; ++a) {
        const std::size_t wa = std::size_t(particles_.words_per_particle(a));
        std::memcpy(o, particles_.words(a) + p * wa, wa * 4);
        o += wa * 4;
      }
  }
  const std::vector<char> all_order = comm.gather(dist::as_bytes(order), nullptr);
  const std::vector<char> all = comm.gather(mine, nullptr);
  out = particles_;
  out.resize(0);
  if (!comm.root()) return;
  const std::vector<std::uint64_t> keys = dist::from_bytes<std::uint64_t>(all_order);
  const std::size_t total = keys.size() / 2;
  if (all.size() != total * words * 4) throw std::runtime_error("gather_particles: sizes disagree");
  std::vector<std::uint32_t> perm(total);
  for (std::size_t i = 0; i < total; ++i) perm[i] = std::uint32_t(i);
  std::sort(perm.begin(), perm.end(), [&](std::uint32_t a, std::uint32_t b) {
    return keys[2 * a] != keys[2 * b] ? keys[2 * a] < keys[2 * b]
                                      : keys[2 * a + 1] < keys[2 * b + 1];
  });
  out.resize(total);
  for (std::size_t i = 0; i < total; ++i) {
    const char* src = all.data() + std::size_t(perm[i]) * words * 4;
    for (int a = 0; a < na; ++a) {
      const std::size_t wa = std::size_t(out.words_per_particle(a));
      std::memcpy(out.words(a) + i * wa, src, wa * 4);
      src += wa * 4;
    }
  }
}

void MpmSolver::gather_grid(SparseGrid& out) const {
  const dist::Comm& comm = dist::Comm::world();
  const std::size_t row = std::size_t(kLeafNodes) * 4;
  std::vector<std::int32_t> coords;
  std::vector<Real> rows;
  const auto& lc = grid_.leaf_coords();
  for (const std::int32_t li : ranks_->owned_active) {
    const Vec3i& l = lc[std::size_t(li)];
    coords.insert(coords.end(), {l[0], l[1], l[2]});
    const Real* a = grid_.node4(0) + std::size_t(li) * row;
    rows.insert(rows.end(), a, a + row);
  }
  const std::vector<std::int32_t> all_coords =
      dist::from_bytes<std::int32_t>(comm.gather(dist::as_bytes(coords), nullptr));
  const std::vector<Real> all_rows =
      dist::from_bytes<Real>(comm.gather(dist::as_bytes(rows), nullptr));
  out.set_node4_channels(1);
  if (!comm.root()) return;
  std::vector<Vec3i> leaves;
  for (std::size_t i = 0; i + 2 < all_coords.size(); i += 3)
    leaves.push_back(Vec3i(all_coords[i], all_coords[i + 1], all_coords[i + 2]));
  out.update_topology(exec::Space(), BinTable{}, &leaves);
  for (std::size_t i = 0; i < leaves.size(); ++i)
    std::memcpy(out.node4(0) + std::size_t(out.find_leaf(leaves[i] * kLeafDim)) * row,
                all_rows.data() + i * row, row * sizeof(Real));
}

// Emitted particles [first, size) were added on every rank: each keeps those in its own leaves.
void MpmSolver::keep_owned_emitted(const exec::Space& space, std::size_t first) {
  const int me = dist::Comm::world().rank();
  const Vec3* x = particles_.vec3(bin_position());
  std::vector<std::uint32_t> keep(first);
  for (std::size_t p = 0; p < first; ++p) keep[p] = std::uint32_t(p);
  for (std::size_t p = first; p < particles_.size(); ++p)
    if (x[p].allFinite() && ranks_->owner(particle_leaf(x[p])) == me)
      keep.push_back(std::uint32_t(p));
  if (keep.size() < particles_.size()) particles_.compact(space, keep.data(), keep.size());
}

// A stable compaction kept the particles `kept` (increasing): the bins of the last sort, which
// give the gathered order, follow them.
void MpmSolver::compact_bins(const std::vector<std::uint32_t>& kept) {
  for (std::uint32_t& s : bins_.start)
    s = std::uint32_t(std::lower_bound(kept.begin(), kept.end(), s) - kept.begin());
}

void MpmSolver::save_distributed(Snapshot& s) const {
  s.bins = bins_;
  s.sorted = ranks_->sorted;
  s.presort = ranks_->presort;
}
void MpmSolver::restore_distributed(const Snapshot& s) {
  bins_ = s.bins;
  ranks_->bins_match = false;  // the first migrate after a restore looks every owner up
  ranks_->sorted = s.sorted;
  ranks_->presort = s.presort;
}

std::size_t MpmSolver::owned_active_leaves() const {
  return ranks_ ? ranks_->owned_active.size() : grid_.active_leaves().size();
}

std::string MpmSolver::distributed_summary() const {
  if (!ranks_) return "";
  const dist::Comm& comm = dist::Comm::world();
  const std::int64_t mine = std::int64_t(particles_.size());
  const double most = double(comm.max(mine)),
               mean = double(comm.sum(std::uint64_t(mine))) / comm.size();
  const Ranks& rk = *ranks_;
  const std::uint64_t halo = comm.sum(rk.halo_leaves), parts = comm.sum(rk.halo_parts);
  // The halo's bytes of the last substep, summed over the ranks: partial sums and node rows.
  std::uint64_t sums = 0, rows = 0;
  for (std::size_t q = 0; q < rk.send_reals.size(); ++q) sums += rk.send_reals[q] * sizeof(Real);
  const std::uint64_t row_bytes = 4 * sizeof(Real) * (channels_.second >= 0 ? 2 : 1);
  for (std::size_t q = 0; q < rk.rows_send_nodes.size(); ++q)
    rows += rk.rows_send_nodes[q] * row_bytes;
  sums = comm.sum(sums), rows = comm.sum(rows);
  const std::uint64_t sorts = comm.sum(rk.sorts), same = comm.sum(rk.same_bin_leaves);
  return "amalgam: distributed MPM on " + std::to_string(comm.size()) +
         " ranks: " + std::to_string(rk.repartitions) + " repartitions, particles max/mean " +
         std::to_string(mean > 0 ? most / mean : 1.0) + "; last substep: " + std::to_string(halo) +
         " ghost leaves, " + std::to_string(parts) + " partial blocks sent, halo " +
         std::to_string(sums / 1000) + " kB of partial sums + " + std::to_string(rows / 1000) +
         " kB of node rows (all ranks); a rank's bin leaves as in its previous substep in " +
         std::to_string(sorts ? 100 * same / sorts : 0) + " % of its substeps; set-up: at most " +
         std::to_string(rk.set_up_most) + " of " + std::to_string(rk.set_up_total) +
         " particles on a rank\n";
}

}  // namespace amalgam
