#include "kernels/object_contact.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/math/bspline.hpp"
#include "kernels/grid_block.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

const char* object_contact_mode_name(ObjectContactMode m) {
  switch (m) {
    case ObjectContactMode::None:
      return "none";
    case ObjectContactMode::Stick:
      return "stick";
    case ObjectContactMode::Separate:
      return "separate";
  }
  return "?";
}

namespace {
// The contact point of reference node o of a leaf: q_i^{n+1} = q_i^n + dt v_i^{n+1} (eq. 27).
inline Vec3 point_position(const Real* n, const Real* qn, Real dt) {
  return Vec3(qn[1], qn[2], qn[3]) / qn[0] + dt * Vec3(n[1], n[2], n[3]);
}
}  // namespace

ContactBoxes contact_boxes(const exec::Space& space, const MpmGridView& ref, const Real* q,
                           const std::int32_t* leaf_object, int objects, Real dt) {
  ContactBoxes init;
  init.n = std::min(objects, ContactBoxes::kMax);
  for (int k = 0; k < init.n; ++k) {
    init.lo[k] = Vec3::Constant(std::numeric_limits<Real>::max());
    init.hi[k] = Vec3::Constant(std::numeric_limits<Real>::lowest());
  }
  return exec::parallel_reduce(
      space, "contact.boxes", exec::Index(ref.nactive), init,
      [&](exec::Index li, ContactBoxes& acc) {
        const std::int32_t leaf = ref.active_leaves[li];
        const int k = leaf_object[leaf];
        const Real* a = ref.a + std::size_t(leaf) * kLeafNodes * 4;
        const Real* ql = q + std::size_t(leaf) * kLeafNodes * 4;
        for (int o = 0; o < kLeafNodes; ++o) {
          if (!(a[o * 4] > 0)) continue;
          const Vec3 x = point_position(a + o * 4, ql + o * 4, dt);
          acc.lo[k] = acc.lo[k].cwiseMin(x);
          acc.hi[k] = acc.hi[k].cwiseMax(x);
        }
      },
      [](ContactBoxes x, const ContactBoxes& y) {
        for (int k = 0; k < x.n; ++k) {
          x.lo[k] = x.lo[k].cwiseMin(y.lo[k]);
          x.hi[k] = x.hi[k].cwiseMax(y.hi[k]);
        }
        return x;
      });
}

void contact_count_points(const exec::Space& space, const MpmGridView& ref, const Real* q,
                          const std::int32_t* leaf_object, const ContactBoxes& boxes, Real margin,
                          Real dt, std::uint32_t* count) {
  exec::parallel_for(space, "contact.count", exec::Index(ref.nactive), [&](exec::Index li) {
    const std::int32_t leaf = ref.active_leaves[li];
    const int k = leaf_object[leaf];
    const Real* a = ref.a + std::size_t(leaf) * kLeafNodes * 4;
    const Real* ql = q + std::size_t(leaf) * kLeafNodes * 4;
    std::uint32_t c = 0;
    for (int o = 0; o < kLeafNodes; ++o)
      if (a[o * 4] > 0 && boxes.near_other(point_position(a + o * 4, ql + o * 4, dt), k, margin))
        ++c;
    count[li] = c;
  });
}

void contact_collect_points(const exec::Space& space, const MpmGridView& ref, const Real* q,
                            const std::int32_t* leaf_object, const ContactBoxes& boxes, Real margin,
                            Real dt, const std::uint32_t* start, const ContactPointView& out) {
  exec::parallel_for(space, "contact.collect", exec::Index(ref.nactive), [&](exec::Index li) {
    const std::int32_t leaf = ref.active_leaves[li];
    const int k = leaf_object[leaf];
    const Real* a = ref.a + std::size_t(leaf) * kLeafNodes * 4;
    const Real* ql = q + std::size_t(leaf) * kLeafNodes * 4;
    std::size_t p = start[li];
    for (int o = 0; o < kLeafNodes; ++o) {
      const Real* n = a + o * 4;
      if (!(n[0] > 0)) continue;
      const Vec3 x = point_position(n, ql + o * 4, dt);
      if (!boxes.near_other(x, k, margin)) continue;
      out.x[p] = x;
      out.v[p] = Vec3(n[1], n[2], n[3]);
      out.m[p] = n[0];
      out.object[p] = k;
      out.leaf[p] = leaf;
      out.offset[p] = o;
      ++p;
    }
  });
}

void contact_scatter(const exec::Space& space, const ContactPointView& pts,
                     const MpmGridView& global, const ObjectContactParams& prm) {
  using Blk = GridBlock<2, 8>;
  const Real inv_dx = Real(1) / prm.dx;
  exec::parallel_for(space, "contact.clear", exec::Index(global.nactive), [&](exec::Index i) {
    const std::size_t leaf = std::size_t(global.active_leaves[i]);
    std::fill(global.a + leaf * kLeafNodes * 4, global.a + (leaf + 1) * kLeafNodes * 4, Real(0));
    std::fill(global.b + leaf * kLeafNodes * 4, global.b + (leaf + 1) * kLeafNodes * 4, Real(0));
  });
  for (int c = 0; c < 8; ++c) {
    const std::uint32_t c0 = global.colour_start[c], c1 = global.colour_start[c + 1];
    exec::parallel_for(
        space, "contact.scatter", exec::Index(c1 - c0),
        [&](exec::Index ci) {
          const std::uint32_t b = global.colour_bins[c0 + std::uint32_t(ci)];
          Blk blk;
          blk.clear();
          const Vec3i origin = global.bin_leaf[b] * kLeafDim;
          for (std::uint32_t p = global.bin_start[b]; p < global.bin_start[b + 1]; ++p) {
            const Stencil<2> st = Stencil<2>::at(pts.x[p], inv_dx);
            const Vec3i l = st.base - origin;
            const Real m = pts.m[p], k = Real(pts.object[p]);
            const Real lanes[6] = {m,     m * pts.v[p][0], m * pts.v[p][1], m * pts.v[p][2],
                                   m * k, m * k * k};
            for (int i = 0; i < 3; ++i)
              for (int j = 0; j < 3; ++j)
                for (int kk = 0; kk < 3; ++kk) {
                  const Real w = st.weight(i, j, kk);
                  Real* d = blk.data + Blk::at(l[0] + i, l[1] + j, l[2] + kk);
                  for (int ch = 0; ch < 6; ++ch) d[ch] += w * lanes[ch];
                }
          }
          blk.for_each_node(global.nbr8[b], [&](Real* s, std::size_t leaf, int off) {
            Real* da = global.a + (leaf * kLeafNodes + std::size_t(off)) * 4;
            Real* db = global.b + (leaf * kLeafNodes + std::size_t(off)) * 4;
            for (int ch = 0; ch < 4; ++ch) da[ch] += s[ch];
            db[0] += s[4];
            db[1] += s[5];
          });
        },
        1);
  }
}

std::size_t contact_gather(const exec::Space& space, const ContactPointView& pts,
                           const MpmGridView& global, const MpmGridView& ref,
                           const ObjectContactParams& prm) {
  using Blk = GridBlock<2, 8>;
  const Real inv_dx = Real(1) / prm.dx;
  const bool separate = prm.mode == ObjectContactMode::Separate;
  return exec::parallel_reduce(
      space, "contact.gather", exec::Index(global.nbins), std::size_t(0),
      [&](exec::Index bi, std::size_t& changed) {
        const std::size_t b = std::size_t(bi);
        Blk blk;
        blk.for_each_node(global.nbr8[b], [&](Real* d, std::size_t leaf, int off) {
          const Real* sa = global.a + (leaf * kLeafNodes + std::size_t(off)) * 4;
          const Real* sb = global.b + (leaf * kLeafNodes + std::size_t(off)) * 4;
          d[0] = sa[0], d[1] = sa[1], d[2] = sa[2], d[3] = sa[3];
          d[4] = sb[0], d[5] = sb[1], d[6] = d[7] = 0;  // K, S
        });
        const Vec3i origin = global.bin_leaf[b] * kLeafDim;
        for (std::uint32_t p = global.bin_start[b]; p < global.bin_start[b + 1]; ++p) {
          if (pts.leaf[p] < 0) continue;  // distributed: another rank's reference node
          const Stencil<2> st = Stencil<2>::at(pts.x[p], inv_dx);
          const Vec3i l = st.base - origin;
          const Real k = Real(pts.object[p]);
          // At q_i: M = sum w M_I, c = sum over the other objects j of w m_j (k_j - k) and
          // D = sum w m_j (k_j - k)^2 (both from K_I and S_I); f = c^2 / (D M) is the others'
          // share of the mass there, exactly when one other object is near, a lower bound else.
          Real sM = 0, c = 0, D = 0;
          Vec3 sP = Vec3::Zero(), gc = Vec3::Zero();
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
              for (int kk = 0; kk < 3; ++kk) {
                const Real* d = blk.data + Blk::at(l[0] + i, l[1] + j, l[2] + kk);
                const Real w = st.weight(i, j, kk);
                const Real others = d[4] - k * d[0];  // sum over other objects of m (k_j - k)
                sM += w * d[0];
                sP += w * Vec3(d[1], d[2], d[3]);
                c += w * others;
                D += w * (d[5] - 2 * k * d[4] + k * k * d[0]);
                gc += others * st.gradient(i, j, kk);
              }
          if (!(sM > 0) || !(D > 0) || c * c < prm.shared_fraction * D * sM) continue;
          const Vec3 V = sP / sM;  // centre-of-mass velocity at q_i
          const Vec3 v = pts.v[p];
          Vec3 vnew = V;
          if (separate) {
            const Real gn = gc.norm();
            if (!(gn > 0)) continue;
            const Vec3 n = (c > 0 ? Real(1) : Real(-1)) * gc / gn;
            const Vec3 dv = v - V;
            const Real vn = dv.dot(n);
            if (vn <= 0) continue;  // separating: free
            const Vec3 dvt = dv - vn * n;
            const Real t = dvt.norm();
            const Real scale = t > 0 ? std::max(Real(0), t - prm.friction * vn) / t : Real(0);
            vnew = V + scale * dvt;
          }
          const std::size_t d = std::size_t(pts.leaf[p]) * kLeafNodes + std::size_t(pts.offset[p]);
          Real* a = ref.a + d * 4;
          for (int ch = 0; ch < 3; ++ch) a[1 + ch] = vnew[ch];
          if (ref.b) {
            Real* bb = ref.b + d * 4;
            for (int ch = 0; ch < 3; ++ch) bb[1 + ch] += vnew[ch] - v[ch];
          }
          ++changed;
        }
      },
      [](std::size_t x, std::size_t y) { return x + y; });
}

}  // namespace amalgam
