// Re-sorting only when needed on several MPI ranks (simulation.sort "when_needed"; one process:
// MpmSolver::step_sorted_when_needed, solvers/mpm_fused.cpp). Between sorts a rank keeps its
// bins, their particles (no migration) and the exchange plan of the last sort:
//   sort      all ranks at once, when a particle of any rank is outside its bin's dilated block
//             (the decision reduced over the ranks); migrate and sort as every substep does
//             (solvers/mpm_distributed.cpp), then this plan: the parts t = 0..26 of each bin's
//             dilated block that fall in leaves other ranks own (the one-leaf halo on every side),
//             the leaves those ranks' blocks reach here, and per owned leaf its parts in bin order
//   P2G       each bin into its dilated block (p2g_dilated, the bins reaching a ghost first); their
//             foreign parts go to the owners, which copy them into blocks of their own; each owned
//             leaf sums its parts in the single process's bin order (sum_dilated_leaves), the
//             source bins' leaf keys: every node adds the same values in the same order
//   grid      update on owned leaves; the owners' node rows (the parts other ranks' blocks reach)
//             copied into the ghosts, as every substep does
//   G2P       the dilated gather (g2p_dilated), far flags per bin
// So a distributed run sorts at the substeps where the single process does, and its frames are
// the single process's bits (tests/dist_mpm_test.sh runs the default, which is this).
#include <algorithm>
#include <cstring>
#include <stdexcept>
#include <string>

#include "core/dist/comm.hpp"
#include "core/math/bspline.hpp"
#include "solvers/mpm_ranks.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

using mpm_dist::leaf_key;

// The view of g over the listed bins only (their neighbour tables, particle ranges and leaves in
// this scratch), no active leaves: p2g_dilated then scatters without summing.
MpmGridView MpmSolver::Ranks::sub_view(const MpmGridView& g,
                                       const std::vector<std::uint32_t>& list) {
  sub_nbr8.resize(list.size()), sub_start.resize(list.size());
  sub_end.resize(list.size()), sub_leaf.resize(list.size());
  sub_nbr27.resize(g.bin_nbr27 ? list.size() : 0);
  for (std::size_t k = 0; k < list.size(); ++k) {
    const std::uint32_t b = list[k];
    sub_nbr8[k] = g.nbr8[b], sub_start[k] = g.bin_start[b];
    sub_end[k] = g.end_of(b), sub_leaf[k] = g.bin_leaf[b];
    if (g.bin_nbr27) sub_nbr27[k] = g.bin_nbr27[b];
  }
  MpmGridView s = g;
  s.nbr8 = sub_nbr8.data(), s.bin_start = sub_start.data();
  s.bin_end = sub_end.data(), s.bin_leaf = sub_leaf.data(), s.nbins = list.size();
  s.bin_nbr27 = g.bin_nbr27 ? sub_nbr27.data() : nullptr;
  s.nactive = 0;
  return s;
}

const std::vector<std::uint16_t>& MpmSolver::Ranks::dilated_row_nodes(int order,
                                                                      std::uint32_t mask) {
  auto& cache = dilated_nodes[std::size_t(order - 2)];
  const auto it = cache.find(mask);
  if (it != cache.end()) return it->second;
  std::vector<char> in(kLeafNodes, 0);
  for (int t = 0; t < 27; ++t) {
    if (!(mask >> t & 1)) continue;
    int n0[3], n1[3];
    dilated_part_range(order, t, n0, n1);
    for (int i = n0[0]; i < n1[0]; ++i)
      for (int j = n0[1]; j < n1[1]; ++j)
        for (int k = n0[2]; k < n1[2]; ++k) in[std::size_t(leaf_offset(i, j, k))] = 1;
  }
  std::vector<std::uint16_t> nodes;
  for (int i = 0; i < kLeafDim; ++i)
    for (int j = 0; j < kLeafDim; ++j)
      for (int k = 0; k < kLeafDim; ++k)
        if (in[std::size_t(leaf_offset(i, j, k))])
          nodes.push_back(std::uint16_t(leaf_offset(i, j, k)));
  return cache.emplace(mask, std::move(nodes)).first->second;
}

// Whether the ranks sort this substep: `need` (this rank's: not primed, or a far flag of its last
// G2P), or, with colliders (the particle collisions move particles after G2P), a particle
// outside its bin's dilated block now, which the single process's P2G finds (and then sorts):
// the same substeps either way. Collective.
bool MpmSolver::lazy_sort_needed_distributed(const exec::Space& space, bool need) {
  if (!need && !colliders_.empty()) {
    const int order = settings_.order, M = kG2P2GMargin, B = kLeafDim + order + 2 * M;
    const Real inv_dx = Real(1) / settings_.dx;
    const Vec3* x = particles_.vec3(attr_.x);
    const std::uint32_t* start = bins_.start.data();
    const Vec3i* leaf = bins_.leaf.data();
    need = exec::parallel_reduce(
               space, "mpm.lazy_check", exec::Index(bins_.count()), 0,
               [=](exec::Index b, int& out) {
                 const Vec3i origin = leaf[b] * kLeafDim - Vec3i::Constant(M);
                 // as p2g_dilated's scatter and g2p_dilated's flag
                 for (std::uint32_t q = start[b]; q < start[b + 1] && !out; ++q)
                   out = !(order == 3 ? stencil_in_block<3>(x[q], inv_dx, origin, B, nullptr)
                                      : stencil_in_block<2>(x[q], inv_dx, origin, B, nullptr));
               },
               [](int a, int b) { return a | b; }) != 0;
  }
  return dist::Comm::world().max(std::int64_t(need)) > 0;
}

// After a sort: the dilated blocks' exchange plan (see the top of this file) and the grid's
// topology, the leaves the local blocks reach and those other ranks' blocks reach here.
void MpmSolver::update_grid_lazy_distributed(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  const int me = comm.rank(), order = settings_.order;
  const int ch = p2g_channels(settings_.transfer, false);
  exec::ScopedRegion region(space.profiler(), "dist.plan");
  rk.dilated = true;
  const std::size_t nb = bins_.count();
  rk.plan_exports(bins_, order, ch);
  dilated_extra_leaves(fused_extra_);  // the - side leaves the blocks reach
  fused_extra_.insert(fused_extra_.end(), rk.import_leaf.begin(), rk.import_leaf.end());
  grid_.update_topology(space, bins_, &fused_extra_, topology_age());
  fused_nbr27_.resize(nb);
  for (std::size_t b = 0; b < nb; ++b)
    fused_nbr27_[b] = grid_.nbr27()[std::size_t(grid_.nbr8()[b][0])];
  // Owned active leaves, and their index among them.
  const auto& coords = grid_.leaf_coords();
  rk.owned_active.clear();
  fused_slot_.assign(grid_.leaf_count(), -1);
  for (std::int32_t li : grid_.active_leaves())
    if (rk.owner(coords[std::size_t(li)]) == me) {
      fused_slot_[std::size_t(li)] = std::int32_t(rk.owned_active.size());
      rk.owned_active.push_back(li);
    }
  rk.plan_rows(grid_, bins_, order);  // the ghost rows, the interior bins, the update order
  // Block slots: the export bins', then the interior bins' (the order P2G scatters them), then
  // one per source bin of the imports (a bin's parts arrive together).
  std::vector<std::uint32_t> bin_slot(nb);
  for (std::size_t k = 0; k < rk.export_bins.size(); ++k)
    bin_slot[rk.export_bins[k]] = std::uint32_t(k);
  for (std::size_t k = 0; k < rk.interior_bins.size(); ++k)
    bin_slot[rk.interior_bins[k]] = std::uint32_t(rk.export_bins.size() + k);
  rk.lazy_imports.clear();
  std::uint32_t slot = std::uint32_t(nb);
  std::uint64_t last_source = ~std::uint64_t(0);
  int last_rank = -1;
  // Per owned leaf, its parts as (source bin's leaf key, slot << 5 | t): sorted by key, the single
  // process's bin order (one bin per leaf, sparse_grid/binning.hpp).
  std::vector<std::pair<std::uint64_t, std::uint32_t>> parts;
  std::vector<std::uint32_t> parts_leaf;
  for (std::size_t b = 0; b < nb; ++b)
    for (int t = 0; t < 27; ++t) {
      const std::int32_t li = fused_nbr27_[b][std::size_t(t)];
      if (li < 0 || fused_slot_[std::size_t(li)] < 0) continue;
      parts.push_back({leaf_key(bins_.leaf[b]), bin_slot[b] << 5 | std::uint32_t(t)});
      parts_leaf.push_back(std::uint32_t(fused_slot_[std::size_t(li)]));
    }
  for (std::size_t i = 0; i < rk.import_leaf.size(); ++i) {
    const int t = rk.import_t[i];
    const std::uint64_t source = leaf_key(rk.import_leaf[i] - rk.part_offset(t));
    if (source != last_source || rk.import_rank[i] != last_rank) ++slot;
    last_source = source, last_rank = rk.import_rank[i];
    const std::int32_t li = grid_.find_leaf(rk.import_leaf[i] * kLeafDim);
    if (li < 0 || fused_slot_[std::size_t(li)] < 0)
      throw std::logic_error("MPM halo: an imported part's leaf is not an owned leaf here");
    rk.lazy_imports.push_back({rk.import_rank[i], t, li, slot - 1});
    parts.push_back({source, (slot - 1) << 5 | std::uint32_t(t)});
    parts_leaf.push_back(std::uint32_t(fused_slot_[std::size_t(li)]));
  }
  rk.lazy_slots = slot;
  const std::size_t nowned = rk.owned_active.size();
  rk.sum_start.assign(nowned + 1, 0);
  for (std::uint32_t l : parts_leaf) ++rk.sum_start[l + 1];
  for (std::size_t l = 0; l < nowned; ++l) rk.sum_start[l + 1] += rk.sum_start[l];
  std::vector<std::pair<std::uint64_t, std::uint32_t>> by_leaf(parts.size());
  {
    std::vector<std::uint32_t> at(rk.sum_start.begin(), rk.sum_start.end() - 1);
    for (std::size_t i = 0; i < parts.size(); ++i) by_leaf[at[parts_leaf[i]]++] = parts[i];
  }
  rk.sum_items.resize(by_leaf.size());
  for (std::size_t l = 0; l < nowned; ++l) {
    auto* first = by_leaf.data() + rk.sum_start[l];
    auto* last = by_leaf.data() + rk.sum_start[l + 1];
    std::sort(first, last);
    for (auto* p = first; p != last; ++p) rk.sum_items[std::size_t(p - by_leaf.data())] = p->second;
  }
  rk.no_target.assign(std::max(rk.export_bins.size(), rk.interior_bins.size()) * 27, -1);
  const std::size_t reals = rk.lazy_slots * dilated_block_reals(order, ch);
  if (p2g_blocks_.size() < reals) p2g_blocks_.resize(reals);
  std::size_t ghosts = 0;
  for (const auto& v : rk.rows_recv) ghosts += v.size();
  rk.halo_leaves = ghosts;
  rk.halo_parts = rk.exports.size();
}

// P2G between sorts: the export bins' blocks first, their foreign parts sent; the interior bins'
// while they travel; the received parts into their slots; each owned leaf summed in bin order.
void MpmSolver::p2g_lazy_distributed(const exec::Space& space, Real dt) {
  const dist::Comm& comm = dist::Comm::world();
  Ranks& rk = *ranks_;
  const int R = comm.size(), order = settings_.order;
  const int ch = p2g_channels(settings_.transfer, false);
  const std::size_t stride = dilated_block_reals(order, ch);
  const MpmParticleView pv = particle_view();
  const MpmGridView g = grid_view();
  const MpmStepParams prm = step_params(dt);
  Real* blocks = p2g_blocks_.data();
  auto scatter = [&](const std::vector<std::uint32_t>& list, Real* at) {
    const MpmGridView s = rk.sub_view(g, list);
    rk.sub_far.assign(list.size(), 0);
    p2g_dilated(space, pv, s, prm, at, nullptr, nullptr, rk.no_target.data(), rk.sub_far.data());
    if (std::any_of(rk.sub_far.begin(), rk.sub_far.end(), [](std::uint8_t f) { return f; }))
      throw std::logic_error("MPM halo: a particle outside its block after the sort decision");
  };
  scatter(rk.export_bins, blocks);
  std::vector<std::vector<char>>& send = rk.p2g_out;
  send.resize(std::size_t(R));
  for (int q = 0; q < R; ++q)
    send[std::size_t(q)].resize(rk.send_reals[std::size_t(q)] * sizeof(Real));
  for (std::size_t k = 0; k < rk.export_bins.size(); ++k)
    for (std::uint32_t e = rk.export_start[k]; e < rk.export_start[k + 1]; ++e) {
      const Ranks::Export& x = rk.exports[e];
      Real* out = reinterpret_cast<Real*>(send[std::size_t(x.rank)].data()) + x.offset;
      copy_dilated_part(blocks + k * stride, order, ch, x.t, out, false);
    }
  std::vector<std::size_t> expect(std::size_t(R), 0);
  for (const Ranks::Import& i : rk.lazy_imports)
    expect[std::size_t(i.rank)] += std::size_t(dilated_part_nodes(order, i.t) * ch) * sizeof(Real);
  comm.exchange_start(rk.p2g_pending, send, expect);
  scatter(rk.interior_bins, blocks + rk.export_bins.size() * stride);
  {
    exec::ScopedRegion region(space.profiler(), "dist.p2g_exchange");
    rk.received = comm.exchange_finish(rk.p2g_pending);
  }
  std::vector<std::size_t> at(std::size_t(R), 0);
  for (const Ranks::Import& i : rk.lazy_imports) {
    const std::size_t n = std::size_t(dilated_part_nodes(order, i.t) * ch);
    std::vector<char>& buf = rk.received[std::size_t(i.rank)];
    if ((at[std::size_t(i.rank)] + n) * sizeof(Real) > buf.size())
      throw std::runtime_error("MPM halo: rank " + std::to_string(i.rank) +
                               " sent too few partial sums");
    copy_dilated_part(blocks + std::size_t(i.slot) * stride, order, ch, i.t,
                      reinterpret_cast<Real*>(buf.data()) + at[std::size_t(i.rank)], true);
    at[std::size_t(i.rank)] += n;
  }
  MpmGridView sums = g;
  sums.active_leaves = rk.owned_active.data();
  sums.nactive = rk.owned_active.size();
  sum_dilated_leaves(space, sums, order, ch, blocks, rk.sum_start.data(), rk.sum_items.data());
}

// The grid update on the owned leaves (those others read first, their rows sent), the dilated G2P
// of the interior bins while the rows travel, then of the bins reading ghosts; far flags per bin.
void MpmSolver::g2p_lazy_distributed(const exec::Space& space, Real dt) {
  Ranks& rk = *ranks_;
  const MpmStepParams prm = step_params(dt);
  update_owned_leaves_rows_first(space, grid_view(), prm);
  lazy_far_.assign(bins_.count(), 0);
  auto gather = [&](const std::vector<std::uint32_t>& list) {
    const MpmGridView s = rk.sub_view(grid_view(), list);
    rk.sub_far.assign(list.size(), 0);
    g2p_dilated(space, particle_view(), s, prm, rk.sub_far.data());
    for (std::size_t k = 0; k < list.size(); ++k) lazy_far_[list[k]] = rk.sub_far[k];
  };
  gather(rk.interior_bins);
  finish_ghost_rows(space);
  gather(rk.export_bins);
}

}  // namespace amalgam
