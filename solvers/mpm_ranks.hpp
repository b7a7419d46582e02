// Private to the distributed MPM files (solvers/mpm_distributed.cpp, solvers/mpm_lazy_distributed.cpp):
// a rank's view of the partition and its exchange plan (MpmSolver::Ranks), and the leaf keys whose
// order is the single process's bin order.
#pragma once

#include <array>
#include <cstdint>
#include <unordered_map>
#include <vector>

#include "core/dist/comm.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {
namespace mpm_dist {

// The exchange peers: the ranks whose cut boxes come within 1.5 leaves of this rank's (node
// units, as the leaf centres). A leaf next to one of this rank's (its bins' +x/+y/+z neighbours,
// a migrating particle's new leaf) has its centre within 1.25 leaves of an own leaf's centre
// (leaf_centre moves centres by under a quarter leaf), so its owner is a peer.
constexpr double kPeerMargin = 1.5 * kLeafDim;

// A leaf coordinate as one 63-bit key whose order is the lexicographic (x, y, z) order of the
// single process's bins (sparse_grid/binning.cpp).
constexpr int kKeyBits = 21;
constexpr std::int64_t kKeyBias = std::int64_t(1) << (kKeyBits - 1);
inline std::uint64_t leaf_key(const Vec3i& l) {
  return (std::uint64_t(l[0] + kKeyBias) << (2 * kKeyBits)) |
         (std::uint64_t(l[1] + kKeyBias) << kKeyBits) | std::uint64_t(l[2] + kKeyBias);
}
inline Vec3i key_leaf(std::uint64_t k) {
  const std::uint64_t mask = (std::uint64_t(1) << kKeyBits) - 1;
  return Vec3i(int(std::int64_t((k >> (2 * kKeyBits)) & mask) - kKeyBias),
               int(std::int64_t((k >> kKeyBits) & mask) - kKeyBias),
               int(std::int64_t(k & mask) - kKeyBias));
}
// The point Zoltan partitions for a leaf: its centre in node units, moved by less than a quarter
// leaf along each axis by a hash of the other two coordinates. RCB splits the points of one cut
// plane between its two sides by weight, but the kept cut (Zoltan_LB_Point_Assign) puts the whole
// plane on one side: with a lattice of leaf centres a rank got 80 % of jelly_drop's particles.
// Moved, the leaves of a plane have different coordinates and the cut falls between them.
inline void leaf_centre(const Vec3i& l, double* c) {
  for (int a = 0; a < 3; ++a) {
    const std::uint32_t h =
        std::uint32_t(l[(a + 1) % 3]) * 73856093u ^ std::uint32_t(l[(a + 2) % 3]) * 19349663u;
    c[a] = (l[a] + 0.5 + 0.25 * double((h >> 8) & 0xFFFF) / 65536.0) * kLeafDim;
  }
}
}  // namespace mpm_dist

struct MpmSolver::Ranks {
  dist::RcbCuts cuts;
  std::unordered_map<std::uint64_t, int> owner_cache;  // leaf key -> rank, for these cuts
  std::vector<int> peers;                              // cuts.neighbours(kPeerMargin)
  std::vector<Vec3i> migrate_leaf;  // migrate's scratch: each particle's leaf and rank
  std::vector<int> migrate_dest;
  std::vector<std::uint32_t> migrate_movers;
  bool bins_match = false;  // the particles are in the order of bins_ (the last sort)
  std::int64_t count_most = 0, count_total = 0;  // particles per rank before the last migrate
  std::vector<Vec3i> last_bin_leaves;
  std::uint64_t sorts = 0, same_bin_leaves = 0;
  std::uint64_t last_partition = 0;  // step of the last (re)partition
  std::uint64_t repartitions = 0;
  double balanced = 1;  // max/mean particles per rank right after the last partition
  // Set-up: the most particles a rank held before distribute, of how many (the summary).
  std::uint64_t set_up_most = 0, set_up_total = 0;
  int force_every = 0;  // test hook: repartition every N substeps
  // Until the first sort the particles are in the order they had on one process (frame 0, or
  // the checkpoint's): two keys per particle whose order is that one (its index there, or a
  // per-rank checkpoint's order keys). After it, (bin leaf, id) is that order.
  bool sorted = false;
  std::vector<std::uint64_t> presort;
  // This substep's exchange plan.
  std::vector<std::uint32_t> export_bins;  // local bins whose block reaches a ghost
  struct Export {
    int rank;
    int t;
    std::size_t offset;  // in Reals, in the send buffer of `rank`
  };
  std::vector<std::uint32_t> export_start;  // per export bin: its exports
  std::vector<Export> exports;
  std::vector<std::size_t> send_reals;  // per rank
  std::vector<Vec3i> import_leaf;       // received parts: target leaf, block neighbour t, rank
  std::vector<int> import_t, import_rank;
  std::vector<std::vector<char>> received;
  std::vector<P2GImport> imports;
  std::array<std::uint32_t, 9> import_colour_start{};
  // The export bins' P2G blocks, kept for the colour loop's flush (scattered once): per bin its
  // slot in `kept` or -1.
  std::vector<Real> kept;
  std::vector<std::int32_t> kept_slot;
  std::vector<std::int32_t> owned_active;
  // The ghost node rows, by peer rank: (local leaf slot, mask of the block parts t = 1..7 read
  // there), sorted by leaf key on both sides: what this rank sends (its leaves others read) and
  // receives (its ghost leaves). Both sides know them from the plan's heads.
  struct RowPart {
    std::uint32_t slot;
    std::uint32_t mask;
  };
  std::vector<std::vector<RowPart>> rows_send, rows_recv;
  std::vector<std::size_t> rows_send_nodes, rows_recv_nodes;  // per rank
  // Overlap (the exchanges travel while the interior works): the bins that reach no ghost leaf,
  // scattered into `kept` while the partial sums travel and gathered (G2P) while the node rows
  // do; the owned leaves whose rows others read first in the grid update's order.
  std::vector<std::uint32_t> interior_bins;
  std::vector<std::int32_t> update_order;
  std::size_t row_leaves = 0;  // update_order[0, row_leaves): leaves in some rows_send
  std::vector<std::vector<char>> p2g_out, rows_out;  // alive until their exchange starts again
  dist::Comm::Pending p2g_pending, rows_pending;
  std::vector<Real*> row_channels;  // the node4 arrays whose rows start_ghost_rows sent
  bool g2p_interior_done = false;   // update_grid_velocities_distributed gathered interior_bins
  // G2P over a subset of the bins (g2p_bins): their neighbour tables, particle ranges, leaves.
  std::vector<std::array<std::int32_t, 8>> sub_nbr8;
  std::vector<std::uint32_t> sub_start, sub_end;
  std::vector<Vec3i> sub_leaf;
  std::uint64_t halo_leaves = 0, halo_parts = 0;  // per substep, this rank (for the summary)

  // Re-sorting only when needed (solvers/mpm_lazy_distributed.cpp): the plan above is then
  // built for the dilated blocks at each sort and kept until the next. exports' t and the row
  // masks' bits are parts 0..26 of a dilated block (copy_dilated_part), not 0..7.
  bool dilated = false;
  struct Import {
    int rank;
    int t;
    std::int32_t leaf;   // the target leaf (this rank's), grid slot
    std::uint32_t slot;  // the block slot it is copied into (one per source bin)
  };
  std::vector<Import> lazy_imports;  // in the order the ranks send them
  std::size_t lazy_slots = 0;        // block slots: local bins, then one per source bin
  std::vector<std::uint32_t> sum_start, sum_items;  // per owned active leaf: parts in bin order
  std::vector<std::int32_t> no_target;              // all -1: p2g_dilated scatters without summing
  std::vector<std::uint8_t> sub_far;
  std::vector<std::array<std::int32_t, 27>> sub_nbr27;
  std::unordered_map<std::uint32_t, std::vector<std::uint16_t>> dilated_nodes[2];
  // The nodes of a leaf that the dilated parts in `mask` cover, in leaf offset order.
  const std::vector<std::uint16_t>& dilated_row_nodes(int order, std::uint32_t mask);
  // The plan's exports and heads to their owners (import_leaf, import_t, import_rank), and its rows,
  // interior bins and update order (solvers/mpm_distributed.cpp).
  void plan_exports(const BinTable& bins, int order, int ch);
  void exchange_heads(const std::vector<std::vector<std::int32_t>>& heads);
  Vec3i part_offset(int t) const;  // part t's leaf from its bin's (dilated: 27 parts, else 8)
  void plan_rows(const SparseGrid& grid, const BinTable& bins, int order);
  // The view of g over the listed bins (in the sub_ scratch), no active leaves.
  MpmGridView sub_view(const MpmGridView& g, const std::vector<std::uint32_t>& list);
  // The nodes of a ghost row's parts `mask`: dilated_row_nodes or the +x/+y/+z parts'.
  const std::vector<std::uint16_t>& row_nodes(int order, std::uint32_t mask);

  int owner(const Vec3i& l) {
    const std::uint64_t k = mpm_dist::leaf_key(l);
    const auto it = owner_cache.find(k);
    if (it != owner_cache.end()) return it->second;
    double c[3];
    mpm_dist::leaf_centre(l, c);
    const int r = cuts.owner(c);
    owner_cache.emplace(k, r);
    return r;
  }
};

}  // namespace amalgam
