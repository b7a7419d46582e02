// A bin's private block of grid nodes for scatter (P2G-like) and gather (G2P-like) kernels.
//
// A bin's particles reach nodes base .. base + Order of their leaf and its +x/+y/+z neighbours,
// so a block of (8 + Order)^3 nodes with node (0,0,0) at the bin leaf's origin holds them all
// (L1-resident). Kernels scatter into the block and flush it into the bin's 8 leaves (nbr8), or
// gather the 8 leaves into the block first. Node (i,j,k) of the block is at ((i B) + j) B + k.
#pragma once

#include <array>
#include <cstdint>
#include <cstring>

#include "core/math/simd4.hpp"
#include "core/math/types.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

// M > 0: a dilated block, M more nodes on every side (node (0,0,0) at the bin leaf's origin - M):
// the fused G2P2G scatter of particles that moved up to M nodes out of their bin's footprint.
// visit / for_each_node / gather4 / flush_add4 are for M = 0.
template <int Order, int CH, int M = 0>
struct GridBlock {
  static constexpr int B = kLeafDim + Order + 2 * M;
  static constexpr int kSize = B * B * B * CH;
  alignas(64) Real data[kSize];
  static int at(int i, int j, int k) { return ((i * B + j) * B + k) * CH; }
  void clear() { std::memset(data, 0, sizeof(data)); }

  // Calls fn(block node pointer, leaf index, offset in leaf) for every node of the block at
  // `data` (this block's or a copy of one), leaf by leaf (t = 0..7: +x, +y, +z neighbours by
  // bit), z fastest.
  template <class P, class Fn>
  static void visit(P* data, const std::array<std::int32_t, 8>& nbr8, Fn&& fn) {
    for (int t = 0; t < 8; ++t) {
      const std::size_t leaf = std::size_t(nbr8[size_t(t)]);
      visit_part(data, t, [&](P* d, int off) { fn(d, leaf, off); });
    }
  }
  // Calls fn(block node pointer, offset in leaf) for the block's nodes in its neighbour leaf t
  // (0..7 as above: 8 nodes a side, Order on a + side), z fastest.
  template <class P, class Fn>
  static void visit_part(P* data, int t, Fn&& fn) {
    const int tx = (t >> 2) & 1, ty = (t >> 1) & 1, tz = t & 1;
    const int ni = tx ? B - kLeafDim : kLeafDim, nj = ty ? B - kLeafDim : kLeafDim,
              nk = tz ? B - kLeafDim : kLeafDim;
    for (int i = 0; i < ni; ++i)
      for (int j = 0; j < nj; ++j)
        for (int k = 0; k < nk; ++k)
          fn(data + at(tx * kLeafDim + i, ty * kLeafDim + j, tz * kLeafDim + k),
             leaf_offset(i, j, k));
  }
  template <class Fn>
  void for_each_node(const std::array<std::int32_t, 8>& nbr8, Fn&& fn) {
    visit(data, nbr8, fn);
  }
  // 4-lane node vectors [leaf][512][4] (the implicit solver's layout): block <- grid (CH == 4).
  void gather4(const std::array<std::int32_t, 8>& nbr8, const Real* grid) {
    for_each_node(nbr8, [grid](Real* d, std::size_t leaf, int off) {
      simd::store4(d, simd::load4(grid + (leaf * kLeafNodes + std::size_t(off)) * 4));
    });
  }
  // grid += block (CH == 4). Race-free when same-colour bins run in parallel.
  void flush_add4(const std::array<std::int32_t, 8>& nbr8, Real* grid) {
    for_each_node(nbr8, [grid](const Real* s, std::size_t leaf, int off) {
      Real* d = grid + (leaf * kLeafNodes + std::size_t(off)) * 4;
      simd::store4(d, simd::load4(d) + simd::load4(s));
    });
  }
};

}  // namespace amalgam
