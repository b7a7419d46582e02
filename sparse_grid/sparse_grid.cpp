// The only grid translation unit that sees OpenVDB.
#include "sparse_grid/sparse_grid.hpp"

#include <openvdb/openvdb.h>

#include <algorithm>
#include <functional>

namespace amalgam {

namespace {
// OpenVDB's Tree::clear() (also its destructor) frees the nodes in a parallel loop on TBB's
// default arena, outside the run's thread limit (docs/architecture.md, "Determinism"). The table has a
// few thousand leaves: free them here one by one, so clear() finds only an empty root.
void clear_serially(openvdb::Int32Tree& tree) {
  std::vector<openvdb::Int32Tree::LeafNodeType*> leaves;
  tree.stealNodes(leaves);
  for (auto* l : leaves) delete l;
  std::vector<openvdb::Int32Tree::RootNodeType::ChildNodeType*> upper;
  tree.stealNodes(upper);
  for (auto* n : upper) delete n;
  tree.clear();
}
}  // namespace

struct SparseGrid::Tree {
  openvdb::Int32Tree tree{-1};
  openvdb::tree::ValueAccessor<openvdb::Int32Tree> acc{tree};
  ~Tree() {
    acc.clear();
    clear_serially(tree);
  }
};

SparseGrid::SparseGrid() : tree_(std::make_unique<Tree>()) {
  node4_.resize(1);
}
SparseGrid::~SparseGrid() = default;
SparseGrid::SparseGrid(SparseGrid&&) noexcept = default;
SparseGrid& SparseGrid::operator=(SparseGrid&&) noexcept = default;

void SparseGrid::set_node4_channels(int count) {
  node4_.resize(size_t(count));
  grow_channels();
}

std::size_t SparseGrid::bytes_per_leaf() const {
  // channel data + OpenVDB index leaf (512 int32 + masks) + tables
  return node4_.size() * 4 * kLeafNodes * sizeof(Real) + kLeafNodes * 4 + 128 + 27 * 4 +
         sizeof(Vec3i);
}

void SparseGrid::grow_channels() {
  const size_t need = leaf_coord_.size() * kLeafNodes;
  for (auto& c : node4_)
    if (c.size() < need * 4) c.resize(std::max(need * 4, c.size() * 3 / 2));
}

std::int32_t SparseGrid::touch_leaf(const Vec3i& lc) {
  const openvdb::Coord origin(lc[0] * kLeafDim, lc[1] * kLeafDim, lc[2] * kLeafDim);
  if (const auto* leaf = tree_->acc.probeConstLeaf(origin)) return leaf->getFirstValue();
  std::int32_t idx;
  if (!free_.empty()) {  // reuse the lowest retired slot
    idx = free_.back();
    free_.pop_back();
    leaf_coord_[size_t(idx)] = lc;
    leaf_idle_[size_t(idx)] = 0;
  } else {
    idx = std::int32_t(leaf_coord_.size());
    leaf_coord_.push_back(lc);
    leaf_idle_.push_back(0);
  }
  auto* leaf = tree_->acc.touchLeaf(origin);
  leaf->fill(idx, true);
  nbr27_stale_ = true;
  return idx;
}

std::int32_t SparseGrid::find_leaf(const Vec3i& node) const {
  const openvdb::Coord ijk(node[0], node[1], node[2]);
  const auto* leaf = tree_->tree.probeConstLeaf(ijk);
  return leaf ? leaf->getFirstValue() : -1;
}

void SparseGrid::clear_topology() {
  tree_->acc.clear();
  clear_serially(tree_->tree);
  leaf_coord_.clear();
  leaf_idle_.clear();
  free_.clear();
  nbr27_stale_ = true;
  ++rebuilds_;
}

void SparseGrid::retire_idle_leaves() {
  using Leaf = openvdb::Int32Tree::LeafNodeType;
  const std::size_t before = free_.size();
  for (std::size_t li = 0; li < leaf_idle_.size(); ++li) {
    if (leaf_idle_[li] == kRetired || leaf_idle_[li] < kRetireAfter) continue;
    const Vec3i o = leaf_coord_[li] * kLeafDim;
    delete tree_->tree.stealNode<Leaf>(openvdb::Coord(o[0], o[1], o[2]), -1, false);
    leaf_idle_[li] = kRetired;
    free_.push_back(std::int32_t(li));
  }
  if (free_.size() == before) return;
  tree_->acc.clear();
  std::sort(free_.begin(), free_.end(), std::greater<std::int32_t>());
  nbr27_stale_ = true;
}

void SparseGrid::update_topology(const exec::Space& space, const BinTable& bins,
                                 const std::vector<Vec3i>* extra, std::uint32_t age) {
  age = std::min(std::max<std::uint32_t>(age, 1), kRetireAfter);
  exec::ScopedRegion region(space.profiler(), "grid.topology");
  const size_t nb = bins.count();
  auto build = [&] {
    nbr8_.resize(nb);
    for (auto& idle : leaf_idle_)  // `age` more substeps unused, unless a bin touches it below
      if (idle != kRetired) idle = std::min(idle + age, kRetireAfter);
    for (size_t b = 0; b < nb; ++b) {
      const Vec3i l = bins.leaf[b];
      for (int t = 0; t < 8; ++t) {
        const std::int32_t li = touch_leaf(l + Vec3i((t >> 2) & 1, (t >> 1) & 1, t & 1));
        nbr8_[b][size_t(t)] = li;
        leaf_idle_[size_t(li)] = 0;
      }
    }
    if (extra)
      for (const Vec3i& l : *extra) leaf_idle_[size_t(touch_leaf(l))] = 0;
  };
  build();
  const size_t used = size_t(std::count(leaf_idle_.begin(), leaf_idle_.end(), 0u));
  // Compact (rebuild indices in bin order) once fewer than a quarter of the slots are in use: the
  // body shrank a lot. Retirement keeps the table near what is in use otherwise, and a moving
  // body's wake (up to 2 kRetireAfter updates) does not trigger it.
  if (used * 4 < leaf_coord_.size()) {
    clear_topology();
    build();
  }
  if ((aged_ += age) >= kRetireAfter) aged_ = 0, retire_idle_leaves();
  grow_channels();

  active_.clear();
  for (size_t i = 0; i < leaf_idle_.size(); ++i)
    if (leaf_idle_[i] == 0) active_.push_back(std::int32_t(i));

  // Colour lists: parity of the bin's leaf coordinate, bins in key order within a colour.
  std::array<std::uint32_t, 9> count{};
  auto colour = [](const Vec3i& l) { return ((l[0] & 1) << 2) | ((l[1] & 1) << 1) | (l[2] & 1); };
  for (size_t b = 0; b < nb; ++b) ++count[size_t(colour(bins.leaf[b])) + 1];
  for (int c = 0; c < 8; ++c) count[size_t(c) + 1] += count[size_t(c)];
  colour_start_ = count;
  colour_bins_.resize(nb);
  for (size_t b = 0; b < nb; ++b)
    colour_bins_[count[size_t(colour(bins.leaf[b]))]++] = std::uint32_t(b);
  // The reverse of nbr8 by colour: leaf nbr8[b][t] is reached by bin b, the only bin of b's colour
  // that reaches it (the 8 bins reaching a leaf sit at its coordinate minus t: 8 parities).
  leaf_bins_.resize(leaf_coord_.size());
  for (const std::int32_t li : active_) leaf_bins_[size_t(li)].fill(-1);
  for (size_t b = 0; b < nb; ++b)
    for (int t = 0; t < 8; ++t)
      leaf_bins_[size_t(nbr8_[b][size_t(t)])][size_t(colour(bins.leaf[b]))] = std::int32_t(b);

  if (nbr27_stale_) {
    nbr27_.resize(leaf_coord_.size());
    for (size_t li = 0; li < leaf_coord_.size(); ++li) {
      if (leaf_idle_[li] == kRetired) {
        nbr27_[li].fill(-1);
        continue;
      }
      int t = 0;
      for (int dx = -1; dx <= 1; ++dx)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dz = -1; dz <= 1; ++dz, ++t) {
            const Vec3i n = (leaf_coord_[li] + Vec3i(dx, dy, dz)) * kLeafDim;
            const auto* leaf = tree_->acc.probeConstLeaf(openvdb::Coord(n[0], n[1], n[2]));
            nbr27_[li][size_t(t)] = leaf ? leaf->getFirstValue() : -1;
          }
    }
    nbr27_stale_ = false;
  }
}

}  // namespace amalgam
