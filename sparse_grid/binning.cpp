#include "sparse_grid/binning.hpp"

#include <algorithm>
#include <climits>
#include <cmath>
#include <stdexcept>
#include <string>

#include "core/errors.hpp"
#include "core/math/bspline.hpp"

namespace amalgam {
namespace {

constexpr int kDigitBits = 11;
constexpr std::uint32_t kRadix = 1u << kDigitBits;
constexpr exec::Index kSortChunks = 64;  // fixed: the permutation must not depend on threads
// Runs of ascending ids a bin's id order merges (more: the bin is sorted instead).
constexpr int kMaxRuns = 64;

struct LeafBox {
  int lo[3] = {INT_MAX, INT_MAX, INT_MAX};
  int hi[3] = {INT_MIN, INT_MIN, INT_MIN};
  exec::Index first_bad = -1;  // first particle with a non-finite or out-of-range position
};

LeafBox join(LeafBox a, const LeafBox& b) {
  for (int k = 0; k < 3; ++k) {
    a.lo[k] = std::min(a.lo[k], b.lo[k]);
    a.hi[k] = std::max(a.hi[k], b.hi[k]);
  }
  if (a.first_bad < 0 || (b.first_bad >= 0 && b.first_bad < a.first_bad)) a.first_bad = b.first_bad;
  return a;
}

template <int Order>
inline Vec3i leaf_of(const Vec3& x, Real inv_dx) {
  Vec3i l;
  for (int a = 0; a < 3; ++a) l[a] = BSpline<Order>::base(x[a] * inv_dx) >> 3;
  return l;
}

template <int Order>
LeafBox leaf_box(const exec::Space& space, const Vec3* x, exec::Index n, Real inv_dx) {
  // Positions beyond +-2^28 cells would overflow the leaf arithmetic: treat as runaway.
  const Real limit = Real(1 << 28);
  return exec::parallel_reduce(
      space, "bin.leaf_box", n, LeafBox{},
      [=](exec::Index i, LeafBox& acc) {
        const Vec3 xs = x[i] * inv_dx;
        if (!(std::abs(xs[0]) < limit && std::abs(xs[1]) < limit && std::abs(xs[2]) < limit)) {
          if (acc.first_bad < 0) acc.first_bad = i;
          return;
        }
        const Vec3i l = leaf_of<Order>(x[i], inv_dx);
        for (int k = 0; k < 3; ++k) {
          acc.lo[k] = std::min(acc.lo[k], l[k]);
          acc.hi[k] = std::max(acc.hi[k], l[k]);
        }
      },
      join);
}

}  // namespace

void ParticleBinning::sort_and_bin(const exec::Space& space, ParticleSet& ps, ParticleSet::Id x_id,
                                   Real dx, int order, BinTable& bins, ParticleSet::Id id_id) {
  const exec::Index n = exec::Index(ps.size());
  bins.start.assign(1, 0u);
  bins.leaf.clear();
  if (n == 0) return;
  const Real inv_dx = Real(1) / dx;
  const Vec3* x = ps.vec3(x_id);

  const LeafBox box = order == 3   ? leaf_box<3>(space, x, n, inv_dx)
                      : order == 1 ? leaf_box<1>(space, x, n, inv_dx)
                                   : leaf_box<2>(space, x, n, inv_dx);
  if (box.first_bad >= 0) {
    const Vec3 xb = x[box.first_bad];
    throw SimulationError("particle " + std::to_string(box.first_bad) +
                          " has a non-finite or runaway position (" +
                          std::to_string(double(xb[0])) + ", " + std::to_string(double(xb[1])) +
                          ", " + std::to_string(double(xb[2])) + ")");
  }
  const std::int64_t ext[3] = {box.hi[0] - box.lo[0] + 1, box.hi[1] - box.lo[1] + 1,
                               box.hi[2] - box.lo[2] + 1};
  const std::int64_t nkeys = ext[0] * ext[1] * ext[2];
  if (nkeys > (std::int64_t(1) << 32) - 1)
    throw SimulationError("particles span " + std::to_string(ext[0]) + "x" +
                          std::to_string(ext[1]) + "x" + std::to_string(ext[2]) +
                          " leaves, more than a 32-bit key can address");

  // Stable LSD radix sort of (key, index) with a fixed number of chunks.
  int bits = 0;
  while ((std::int64_t(1) << bits) < nkeys) ++bits;
  const int passes = (bits + kDigitBits - 1) / kDigitBits;
  // Keys, their sort's second buffer and the permutation's second buffer are the three words per
  // particle of the set's spare (free until the permute below); the permutation starts in the
  // buffer where an even or odd number of passes leaves it in perm_, which the permute reads.
  perm_.resize(size_t(n));
  if (ParticleSet::spare_words_per_particle() < 3)
    throw std::logic_error("the particle set's spare holds fewer than 3 words per particle");
  std::uint32_t* spare = ps.spare_words();
  std::uint32_t* kin_buf = spare;
  std::uint32_t* kout_buf = spare + n;
  std::uint32_t* pin_buf = (passes % 2 == 0) ? perm_.data() : spare + 2 * n;
  std::uint32_t* pout_buf = (passes % 2 == 0) ? spare + 2 * n : perm_.data();
  {
    std::uint32_t* keys = kin_buf;
    std::uint32_t* perm = pin_buf;
    const int lo0 = box.lo[0], lo1 = box.lo[1], lo2 = box.lo[2];
    const std::int64_t e1 = ext[1], e2 = ext[2];
    auto key_pass = [&](auto order_tag) {
      constexpr int O = decltype(order_tag)::value;
      exec::parallel_for(space, "bin.keys", n, [=](exec::Index i) {
        const Vec3i l = leaf_of<O>(x[i], inv_dx);
        keys[i] =
            std::uint32_t(((std::int64_t(l[0] - lo0) * e1) + (l[1] - lo1)) * e2 + (l[2] - lo2));
        perm[i] = std::uint32_t(i);
      });
    };
    if (order == 3)
      key_pass(std::integral_constant<int, 3>{});
    else if (order == 1)
      key_pass(std::integral_constant<int, 1>{});
    else
      key_pass(std::integral_constant<int, 2>{});
  }

  const exec::Index chunk = (n + kSortChunks - 1) / kSortChunks;
  const exec::Index nchunks = (n + chunk - 1) / chunk;
  hist_.resize(size_t(nchunks) * kRadix);
  for (int pass = 0; pass < passes; ++pass) {
    const int shift = pass * kDigitBits;
    // Digits this pass can take (keys < nkeys): the histogram and its serial prefix cover only
    // these, not all 2^11 (a small grid's sort was dominated by the 64 x 2048 prefix).
    const std::uint32_t ndig =
        std::uint32_t(std::min<std::int64_t>(kRadix, ((nkeys - 1) >> shift) + 1));
    std::uint32_t* hist = hist_.data();
    const std::uint32_t* kin = kin_buf;
    const std::uint32_t* pin = pin_buf;
    std::uint32_t* kout = kout_buf;
    std::uint32_t* pout = pout_buf;
    exec::parallel_for(
        space, "bin.radix_hist", nchunks,
        [=](exec::Index c) {
          std::uint32_t* h = hist + size_t(c) * kRadix;
          std::fill(h, h + ndig, 0u);
          const exec::Index e = std::min(n, (c + 1) * chunk);
          for (exec::Index i = c * chunk; i < e; ++i) ++h[(kin[i] >> shift) & (kRadix - 1)];
        },
        1);
    // Exclusive offsets in (digit, chunk) order: stable.
    std::uint32_t running = 0;
    for (std::uint32_t d = 0; d < ndig; ++d)
      for (exec::Index c = 0; c < nchunks; ++c) {
        std::uint32_t& h = hist[size_t(c) * kRadix + d];
        const std::uint32_t cnt = h;
        h = running;
        running += cnt;
      }
    exec::parallel_for(
        space, "bin.radix_scatter", nchunks,
        [=](exec::Index c) {
          std::uint32_t* h = hist + size_t(c) * kRadix;
          const exec::Index e = std::min(n, (c + 1) * chunk);
          for (exec::Index i = c * chunk; i < e; ++i) {
            const std::uint32_t dst = h[(kin[i] >> shift) & (kRadix - 1)]++;
            kout[dst] = kin[i];
            pout[dst] = pin[i];
          }
        },
        1);
    std::swap(kin_buf, kout_buf);
    std::swap(pin_buf, pout_buf);
  }

  // Bins: runs of equal keys (their numbers in the keys' second buffer, free once sorted).
  const std::uint32_t* keys = kin_buf;
  std::uint32_t* flags = kout_buf;
  const std::uint32_t nbins = exec::parallel_scan<std::uint32_t>(
      space, "bin.find_runs", n,
      [=](exec::Index i) { return (i == 0 || keys[i] != keys[i - 1]) ? 1u : 0u; }, flags);
  bins.start.resize(size_t(nbins) + 1);
  bins.leaf.resize(nbins);
  std::uint32_t* start = bins.start.data();
  Vec3i* leaf = bins.leaf.data();
  const int lo0 = box.lo[0], lo1 = box.lo[1], lo2 = box.lo[2];
  const std::uint32_t e1 = std::uint32_t(ext[1]), e2 = std::uint32_t(ext[2]);
  exec::parallel_for(space, "bin.find_runs", n, [=](exec::Index i) {
    if (i == 0 || keys[i] != keys[i - 1]) {
      const std::uint32_t b = flags[i], k = keys[i];
      start[b] = std::uint32_t(i);
      leaf[b] = Vec3i(int(k / (e1 * e2)) + lo0, int((k / e2) % e1) + lo1, int(k % e2) + lo2);
    }
  });
  start[nbins] = std::uint32_t(n);
  // Canonical order inside each bin: by particle id (the previous order is mostly sorted
  // already, as most particles stay in their bin; ids are unique, so the order is total).
  if (id_id >= 0) {
    const std::int32_t* ids = ps.int32(id_id);
    std::uint32_t* perm = perm_.data();
    exec::parallel_for(space, "bin.order_by_id", exec::Index(nbins), [=](exec::Index b) {
      const auto by_id = [ids](std::uint32_t a, std::uint32_t c) { return ids[a] < ids[c]; };
      // The stable radix sort leaves a bin as the particles of each previous bin in their previous
      // order: a few runs ascending by id (one when no particle arrived). Merge the runs pairwise.
      std::uint32_t* run[kMaxRuns + 1];
      int runs = 0;
      std::uint32_t *p = perm + start[b], *e = perm + start[b + 1];
      run[runs++] = p;
      for (std::uint32_t* q = p + 1; q < e && runs <= kMaxRuns; ++q)
        if (by_id(*q, *(q - 1))) run[runs++] = q;
      if (runs == 1) return;
      if (runs > kMaxRuns) {
        std::sort(p, e, by_id);
        return;
      }
      run[runs] = e;
      for (int width = 1; width < runs; width *= 2)
        for (int r = 0; r + width < runs; r += 2 * width)
          std::inplace_merge(run[r], run[r + width], run[std::min(r + 2 * width, runs)], by_id);
    });
  }
  ps.permute(space, perm_.data());
}

}  // namespace amalgam
