// Block-sparse MPM grid backed by a persistent OpenVDB tree (docs/architecture.md, "The grid").
//
// Blocks are OpenVDB leaves of 8^3 nodes; node (i,j,k) lives in leaf (i>>3, j>>3, k>>3) at offset
// ((i&7)<<6) | ((j&7)<<3) | (k&7) (z fastest, as OpenVDB). The tree is an index grid: every voxel
// of a leaf stores that leaf's index in the flat leaf table, so kernels never touch the tree and
// node data lives in leaf-indexed side arrays:
//   node4(a)   [leaf][512][4]  AoS channels for transfers (mass + momentum, later velocity)
// (SoA [leaf][512] channels for implicit-solver vectors belong here too, added with their solver.)
// Topology per substep: for each bin, its leaf and the +x/+y/+z neighbours (the stencil reaches
// at most base+3 <= 10 < 16). Only new leaves are created (serially), existing leaf indices stay
// put. Leaves no bin has touched for kRetireAfter substeps (topology updates weighted by their
// `age`) are retired (checked every kRetireAfter substeps): removed from the tree, their table slots kept for the next new leaves
// (lowest slot first), so a moving body's table stays at the size of what it occupies instead
// of growing with everywhere it has been. When fewer than a quarter of the slots are in use the
// table is rebuilt compactly in bin order.
// Tables: nbr8[bin][8] (the 8 leaves a bin scatters to), nbr27[leaf][27] (grid stencils, -1 for
// absent), active leaves (those some bin touches), and bins grouped by the parity colour of their
// leaf coordinate: same-colour bins' 8-leaf footprints never overlap, so each colour's bins can
// scatter in parallel without atomics, deterministically; leaf_bins[leaf][colour], the bin of each
// colour that reaches a leaf, lets P2G sum kept bin blocks per leaf in the same colour order.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/memory/huge_pages.hpp"
#include "core/math/types.hpp"
#include "sparse_grid/binning.hpp"

namespace amalgam {

constexpr int kLeafDim = 8;
constexpr int kLeafNodes = 512;

inline int leaf_offset(int i, int j, int k) {
  return (i << 6) | (j << 3) | k;
}

class SparseGrid {
 public:
  SparseGrid();
  ~SparseGrid();
  SparseGrid(const SparseGrid&) = delete;
  SparseGrid& operator=(const SparseGrid&) = delete;
  SparseGrid(SparseGrid&&) noexcept;
  SparseGrid& operator=(SparseGrid&&) noexcept;

  // Number of AoS node4 channel sets to maintain (each 4 Reals per node).
  void set_node4_channels(int count);

  // Activates the leaves the bins' stencils reach and rebuilds tables. Serial by design
  // (OpenVDB topology edits are not thread-safe); only new leaves are created.
  // `extra`: more leaves to activate though no bin here reaches them (a distributed run's leaves
  // that only other ranks' particles reach: solvers/mpm_distributed.cpp). `age`: the substeps
  // since the previous update (a caller that re-sorts only when needed updates every 11-40
  // substeps): leaves retire after kRetireAfter substeps unused, not kRetireAfter updates.
  void update_topology(const exec::Space& space, const BinTable& bins,
                       const std::vector<Vec3i>* extra = nullptr, std::uint32_t age = 1);

  static constexpr std::uint32_t kRetireAfter = 32;
  // Slots of the leaf table (live leaves and retired slots awaiting reuse): the size of every
  // leaf-indexed array.
  std::size_t leaf_count() const { return leaf_coord_.size(); }
  // A retired slot: no leaf of the tree maps to it (its coordinates and nbr27 row are stale / -1).
  bool leaf_retired(std::size_t li) const { return leaf_idle_[li] == kRetired; }
  const std::vector<Vec3i>& leaf_coords() const { return leaf_coord_; }
  const std::vector<std::int32_t>& active_leaves() const { return active_; }
  const std::vector<std::array<std::int32_t, 8>>& nbr8() const { return nbr8_; }
  const std::vector<std::array<std::int32_t, 27>>& nbr27() const { return nbr27_; }
  // Bins of colour c are colour_bins()[colour_start()[c] .. colour_start()[c+1]).
  const std::vector<std::uint32_t>& colour_bins() const { return colour_bins_; }
  const std::array<std::uint32_t, 9>& colour_start() const { return colour_start_; }
  // Per leaf slot (active leaves only), the bin of each colour c whose 8-leaf footprint (nbr8)
  // holds the leaf, or -1: a leaf's P2G sum over bins in colour order, without the colour phases.
  const std::vector<std::array<std::int32_t, 8>>& leaf_bins() const { return leaf_bins_; }
  // Leaf index containing node (i,j,k), or -1 (tree lookup: for tests and setup, not kernels).
  std::int32_t find_leaf(const Vec3i& node) const;

  Real* node4(int set) { return node4_[size_t(set)].data(); }
  const Real* node4(int set) const { return node4_[size_t(set)].data(); }
  std::size_t bytes_per_leaf() const;
  std::uint64_t topology_rebuilds() const { return rebuilds_; }

 private:
  struct Tree;  // OpenVDB tree and accessor, only seen by sparse_grid.cpp
  std::unique_ptr<Tree> tree_;
  std::vector<Vec3i> leaf_coord_;
  std::vector<std::int32_t> active_;
  static constexpr std::uint32_t kRetired = ~std::uint32_t(0);
  // Per slot: substeps since a bin last touched the leaf (0: in use this update, i.e. active),
  // or kRetired.
  std::vector<std::uint32_t> leaf_idle_;
  std::vector<std::int32_t> free_;  // retired slots, highest first (reuse takes the lowest)
  std::uint64_t aged_ = 0;          // substeps since the last retirement check
  std::vector<std::array<std::int32_t, 8>> nbr8_;
  std::vector<std::array<std::int32_t, 27>> nbr27_;
  std::vector<std::uint32_t> colour_bins_;
  std::array<std::uint32_t, 9> colour_start_{};
  std::vector<std::array<std::int32_t, 8>> leaf_bins_;
  std::vector<HugePageVector<Real>> node4_;  // (transparent huge pages: core/memory)
  std::uint64_t rebuilds_ = 0;
  bool nbr27_stale_ = true;

  std::int32_t touch_leaf(const Vec3i& lc);
  void clear_topology();
  void retire_idle_leaves();
  void grow_channels();
};

}  // namespace amalgam
