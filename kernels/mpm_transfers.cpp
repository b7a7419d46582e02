#include "kernels/mpm_transfers.hpp"

#include <algorithm>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

#if defined(__AVX512F__)
#include <immintrin.h>
#endif

#include "core/exec/simd.hpp"
#include "core/math/bspline.hpp"
#include "core/math/lanes.hpp"
#include "core/math/simd4.hpp"
#include "kernels/grid_block.hpp"
#include "kernels/particle_update.hpp"
#include "sparse_grid/sparse_grid.hpp"

namespace amalgam {

const char* transfer_name(Transfer t) {
  switch (t) {
    case Transfer::PicFlip:
      return "pic_flip";
    case Transfer::Apic:
      return "apic";
    case Transfer::Mls:
      return "mls";
  }
  return "?";
}

MpmGridView make_grid_view(const SparseGrid& grid, const BinTable& bins, Real* a, Real* b) {
  MpmGridView g;
  g.a = a;
  g.b = b;
  g.nbr8 = grid.nbr8().data();
  g.bin_start = bins.start.data();
  g.bin_leaf = bins.leaf.data();
  g.nbins = bins.count();
  g.colour_bins = grid.colour_bins().data();
  g.colour_start = grid.colour_start().data();
  g.active_leaves = grid.active_leaves().data();
  g.nactive = grid.active_leaves().size();
  g.leaf_coord = grid.leaf_coords().data();
  g.leaf_bins = grid.leaf_bins().data();
  return g;
}

// The kernels, once per instruction set (core/exec/simd.hpp: AMALGAM_ISA is isa_baseline,
// isa_avx2 or isa_avx512).
namespace AMALGAM_ISA {

namespace {

// Private scatter/gather block of (8 + Order)^3 nodes x CH channels (kernels/grid_block.hpp).
template <int Order, int CH>
using Block = GridBlock<Order, CH>;

constexpr int channels_of(Transfer t) {
  return t == Transfer::PicFlip ? 8 : 4;
}

// How many of the particles q0, q0 + 1, ... (at most W, none from q1 on) share q0's material.
template <int W>
inline int one_material_run(const std::int32_t* material, std::uint32_t q0, std::uint32_t q1) {
  const int most = int(std::min<std::uint32_t>(W, q1 - q0));
  int n = 1;
  while (n < most && material[q0 + std::uint32_t(n)] == material[q0]) ++n;
  return n;
}

#if defined(__AVX512F__) && !defined(AMALGAM_REAL_DOUBLE)  // float only: 16 floats
// P2G's nodes k = 0 .. N-1 of one (i, j) row at once on AVX-512 (float, CH = 4, N <= 4): the
// block's row holds them contiguously, 4N floats, one 16-lane register with the lanes past 4N
// masked off. Lane 4k + c computes exactly what node k's lane c computes in the 4-lane loop (the
// same multiplies and adds in the same order, no contraction), so the bits are those of every
// other path; what changes is the instruction count: one masked load, add and store per row
// instead of N of each.
struct NodeRows16 {
  __m512 wz, dwz, z;  // (w_k), (dw_k), zk[k] per 4 lanes
  __mmask16 mask;
};
inline __m512 quads16(const simd::V4* q, int n) {
  __m512 r = _mm512_setzero_ps();
  if (n > 0) r = _mm512_insertf32x4(r, (__m128)q[0], 0);
  if (n > 1) r = _mm512_insertf32x4(r, (__m128)q[1], 1);
  if (n > 2) r = _mm512_insertf32x4(r, (__m128)q[2], 2);
  if (n > 3) r = _mm512_insertf32x4(r, (__m128)q[3], 3);
  return r;
}
// The 4 lanes in every quad (the masked form: GCC 12's unmasked one warns of its undefined source).
inline __m512 bcast16(__m128 q) {
  return _mm512_maskz_broadcast_f32x4(__mmask16(0xFFFF), q);
}
inline __m512 splat_quads16(const Real* s, int n) {
  simd::V4 q[4];
  for (int k = 0; k < n; ++k) q[k] = simd::V4{s[k], s[k], s[k], s[k]};
  return quads16(q, n);
}
#endif

// One row of a block's stencil, nodes k = 0 .. N-1 of (i, j): L = N * CH contiguous Reals, held
// in the path's widest vectors (AVX-512 float: 16 lanes, the last masked; AVX float: 8 lanes and a
// 4-lane tail; otherwise 4-lane V4s). G2P accumulates whole rows lane by lane (lane 4q + c is
// quad q's channel c), every lane with the same multiplies and adds on every path, so the bits
// are the paths' common ones and only the instruction count differs.
template <int L>
struct RowLanes {
  static_assert(L % 4 == 0, "whole 4-lane quads");
#if !defined(AMALGAM_REAL_DOUBLE)
  static constexpr int W = lanes::kN<Real>;  // the path's particle lanes: 4, 8 or 16 floats
#else
  static constexpr int W = 4;
#endif
  // simd::V4 where 4 wide (the double build's: two SSE2 halves without AVX).
  using VW = std::conditional_t<W == 4, simd::V4, lanes::V<Real>>;
  static constexpr int C = L / W, kTail = L % W;  // full vectors, then kTail (< W) lanes
  static constexpr int kTailV = kTail == 0 ? 0 : 1;
  // AVX-512: the tail is one masked 16-lane vector; AVX: a V4 (L % 8 is 0 or 4).
  static_assert(W != 8 || kTail % 4 == 0, "AVX tail: one V4");
  VW v[C + (W == 16 ? kTailV : 0)];
  simd::V4 t[W == 8 ? kTailV : 0];

  static RowLanes load(const Real* p) {
    RowLanes r;
    for (int c = 0; c < C; ++c) {
      if constexpr (W == 4)
        r.v[c] = simd::load4(p + c * W);
      else
        std::memcpy(static_cast<void*>(&r.v[c]), p + c * W, sizeof(VW));
    }
    if constexpr (kTail > 0) {
#if defined(__AVX512F__) && !defined(AMALGAM_REAL_DOUBLE)
      r.v[C] = (VW)_mm512_maskz_loadu_ps(__mmask16((1u << kTail) - 1u), p + C * W);
#else
      r.t[0] = simd::load4(p + C * W);
#endif
    }
    return r;
  }
  // *this = s r, and *this += s r (a multiply, then an add, per lane).
  void set_scaled(Real s, const RowLanes& r) {
    for (int c = 0; c < C + (W == 16 ? kTailV : 0); ++c) v[c] = s * r.v[c];
    if constexpr (W == 8 && kTail > 0) t[0] = s * r.t[0];
  }
  void add_scaled(Real s, const RowLanes& r) {
    for (int c = 0; c < C + (W == 16 ? kTailV : 0); ++c) v[c] += s * r.v[c];
    if constexpr (W == 8 && kTail > 0) t[0] += s * r.t[0];
  }
#if !defined(AMALGAM_REAL_DOUBLE)
  // For P2G's rows (AVX and baseline paths only): the row whose quad k is q[k] (k < L / 4), the
  // row with every quad q, its store and its update.
  static RowLanes from_quads(const simd::V4* q) {
    static_assert(L > 0 && (W == 4 || W == 8), "AVX-512's P2G rows are NodeRows16");
    RowLanes r;
    if constexpr (W == 4) {
      for (int c = 0; c < C; ++c) r.v[c] = q[c];
    } else {
      for (int c = 0; c < C; ++c)
        r.v[c] = __builtin_shufflevector(q[2 * c], q[2 * c + 1], 0, 1, 2, 3, 4, 5, 6, 7);
      if constexpr (kTail > 0) r.t[0] = q[2 * C];
    }
    return r;
  }
  void store(Real* p) const {
    static_assert(L > 0 && (W == 4 || W == 8), "AVX-512's P2G rows are NodeRows16");
    for (int c = 0; c < C; ++c) {
      if constexpr (W == 4)
        simd::store4(p + c * W, v[c]);
      else
        std::memcpy(p + c * W, static_cast<const void*>(&v[c]), sizeof(VW));
    }
    if constexpr (kTail > 0) simd::store4(p + C * W, t[0]);
  }
  static RowLanes splat_quad(simd::V4 q) {
    static_assert(L > 0 && (W == 4 || W == 8), "AVX-512's P2G rows are NodeRows16");
    RowLanes r;
    for (int c = 0; c < C; ++c) {
      if constexpr (W == 4)
        r.v[c] = q;
      else
        r.v[c] = __builtin_shufflevector(q, q, 0, 1, 2, 3, 0, 1, 2, 3);
    }
    if constexpr (W == 8 && kTail > 0) r.t[0] = q;
    return r;
  }
  // P2G's row of (mass, momentum), lane by lane: *this += (wij wz) (a + z), less (wz g0 + dwz g1)
  // first when Grad: per lane exactly the node-by-node loop's operations (p2g_particle).
  template <bool Grad>
  void add_momentum(Real wij, const RowLanes& wz, const RowLanes& z, const RowLanes& a,
                    const RowLanes& dwz, const RowLanes& g0, const RowLanes& g1) {
    auto lane = [wij](auto& acc, const auto& wz_, const auto& z_, const auto& a_, const auto& dwz_,
                      const auto& g0_, const auto& g1_) {
      auto mom = (wij * wz_) * (a_ + z_);
      if constexpr (Grad) mom = mom - (wz_ * g0_ + dwz_ * g1_);
      acc = acc + mom;
    };
    static_assert(L > 0 && (W == 4 || W == 8), "AVX-512's P2G rows are NodeRows16");
    for (int c = 0; c < C; ++c) lane(v[c], wz.v[c], z.v[c], a.v[c], dwz.v[c], g0.v[c], g1.v[c]);
    if constexpr (W == 8 && kTail > 0)
      lane(t[0], wz.t[0], z.t[0], a.t[0], dwz.t[0], g0.t[0], g1.t[0]);
  }
#endif
  // Lanes 4q .. 4q + 3.
  simd::V4 quad(int q) const {
    const int c = (4 * q) / W, e = (4 * q) % W;
    if constexpr (W == 4) {
      return v[q];
    } else {
      if (W == 8 && c == C) return t[0];
      return simd::V4{v[c][e], v[c][e + 1], v[c][e + 2], v[c][e + 3]};
    }
  }
};

// Per-particle P2G contribution into a block whose node (0,0,0) is `origin` (pure: no grid).
// P (A-ULMPM, MLS/APIC only, CH = 8): lanes 4-7 also receive the node-position scatter of
// p2g_positions, w (m, m (xq + Fq o)) with the same stencil (xq = x_p, Fq = F_s; o = X_i - X_p).
// S (split, dt-free; CH = 8): the stress force goes into lanes 4-7 for every transfer, without
// its dt (the fused G2P2G scatters before the next dt is known; grid_update adds dt f / m).
// M: the block's margin (GridBlock), origin being the bin leaf's origin - M.
// flatten: every small Eigen operation inside is inlined; GCC's unit-growth limits otherwise
// leave some out of line as the file grows (measured: G2P 12 % slower).
template <int Order, Transfer T, int CH, bool P = false, bool S = false, int M = 0>
__attribute__((flatten)) inline void p2g_particle(GridBlock<Order, CH, M>& blk, const Vec3i& origin,
                                                  const Vec3& x, const Vec3& v, const Mat3& C,
                                                  const Mat3& tau, Real m, Real V0, Real dx,
                                                  Real inv_dx, Real dt,
                                                  const Vec3& xq = Vec3::Zero(),
                                                  const Mat3& Fq = Mat3::Zero()) {
  static_assert(!P || (CH == 8 && T != Transfer::PicFlip && !S),
                "fused positions: MLS/APIC with an 8-lane block");
  static_assert(!S || CH == 8, "split force: an 8-lane block");
  const Stencil<Order> st = Stencil<Order>::at(x, inv_dx);
  const Vec3i l = st.base - origin;
  constexpr int N = Stencil<Order>::kN;
  // One separable form for the three transfers, per node (i, j, k) with o = x_i - x_p:
  //   (m, p)_i += w (m, m v + A o) - (0, G grad w)      and, PIC/FLIP only, f_i = -G grad w
  //   MLS:      A = m C - dt V0 D^{-1} tau, G = 0   (stress folded into the affine term)
  //   APIC:     A = m C,                   G = dt V0 tau
  //   PIC/FLIP: A = 0,                     G = V0 tau (force kept apart: FLIP needs v_old)
  // Split (S): A = m C (MLS, APIC) and the force apart, f_i = -w Sf o (MLS, Sf = V0 D^{-1} tau)
  // or -G grad w (APIC, G = V0 tau), as PIC/FLIP's.
  // A o = A.col(0) o0[i] + A.col(1) o1[j] + A.col(2) o2[k], and with
  // grad w_ijk = (dwx_i wy_j wz_k, wx_i dwy_j wz_k, wx_i wy_j dwz_k),
  // G grad w = wz_k g0_ij + dwz_k g1_ij, g0_ij = G.col(0) dwx_i wy_j + G.col(1) wx_i dwy_j,
  // g1_ij = G.col(2) wx_i wy_j: a few 4-lane multiply-adds per node, no 3x3 product.
  constexpr bool kGrad = (T != Transfer::Mls);
  constexpr bool kAffineForce = S && T == Transfer::Mls;
  Mat3 A, G, Sf;
  if constexpr (T == Transfer::Mls) {
    const Real Dinv = BSpline<Order>::kDinvScale * inv_dx * inv_dx;
    if constexpr (S) {
      A = m * C;
      Sf = (V0 * Dinv) * tau;
    } else {
      A = m * C - (dt * V0 * Dinv) * tau;
    }
    G.setZero();
  } else if constexpr (T == Transfer::Apic) {
    A = m * C;
    G = S ? Mat3(V0 * tau) : Mat3((dt * V0) * tau);
  } else {
    A.setZero();
    G = V0 * tau;
  }
  // Node rows are 4-lane vectors (simd::V4); every lane op is the scalar op of the same lane.
  using simd::V4;
  const V4 em{m, 0, 0, 0}, mv = simd::row4(0, m * v);
  const V4 a0 = simd::col4(A, 0), a1 = simd::col4(A, 1), a2 = simd::col4(A, 2);
  V4 zk[N];  // (m, A.col(2) o2[k])
  for (int k = 0; k < N; ++k) zk[k] = em + a2 * ((Real(k) - st.fx[2]) * dx);
  // Positions (P): the same separable affine form with v -> xq and A -> m Fq, no stress term;
  // split MLS: the force's affine form Sf o in the same lanes.
  Mat3 Aq;
  if constexpr (kAffineForce)
    Aq = Sf;
  else
    Aq = m * Fq;
  const V4 mq = kAffineForce ? V4{} : simd::row4(0, m * xq);
  const V4 q0 = simd::col4(Aq, 0), q1 = simd::col4(Aq, 1), q2 = simd::col4(Aq, 2);
  V4 qk[N] = {};
  if constexpr (P)
    for (int k = 0; k < N; ++k) qk[k] = em + q2 * ((Real(k) - st.fx[2]) * dx);
  if constexpr (kAffineForce)
    for (int k = 0; k < N; ++k) qk[k] = q2 * ((Real(k) - st.fx[2]) * dx);
  const V4 g0c = simd::col4(G, 0), g1c = simd::col4(G, 1), g2c = simd::col4(G, 2);
#if defined(__AVX512F__) && !defined(AMALGAM_REAL_DOUBLE)
  constexpr bool kRows16 =
      CH == 4 && N <= 4 && !P && !S && (T == Transfer::Mls || T == Transfer::Apic);
  if constexpr (kRows16) {
    NodeRows16 nr;
    nr.wz = splat_quads16(st.w[2], N);
    nr.dwz = splat_quads16(st.dw[2], N);
    nr.z = quads16(zk, N);
    nr.mask = __mmask16((1u << (4 * N)) - 1u);
    const __m512 mv16 = bcast16((__m128)mv);
    const __m512 a0_16 = bcast16((__m128)a0);
    const __m512 a1_16 = bcast16((__m128)a1);
    for (int i = 0; i < N; ++i) {
      const Real oi = (Real(i) - st.fx[0]) * dx;
      const __m512 ai = _mm512_add_ps(mv16, _mm512_mul_ps(a0_16, _mm512_set1_ps(oi)));
      for (int j = 0; j < N; ++j) {
        const Real oj = (Real(j) - st.fx[1]) * dx;
        const __m512 aij = _mm512_add_ps(ai, _mm512_mul_ps(a1_16, _mm512_set1_ps(oj)));
        const Real wx = st.w[0][i], wy = st.w[1][j], wij = wx * wy;
        Real* row = blk.data + GridBlock<Order, CH, M>::at(l[0] + i, l[1] + j, l[2]);
        const __m512 w = _mm512_mul_ps(_mm512_set1_ps(wij), nr.wz);
        __m512 mom = _mm512_mul_ps(w, _mm512_add_ps(aij, nr.z));
        if constexpr (kGrad) {
          const V4 g0 = g0c * (st.dw[0][i] * wy) + g1c * (wx * st.dw[1][j]);
          const V4 g1 = g2c * wij;
          const __m512 t = _mm512_add_ps(_mm512_mul_ps(nr.wz, bcast16((__m128)g0)),
                                         _mm512_mul_ps(nr.dwz, bcast16((__m128)g1)));
          mom = _mm512_sub_ps(mom, t);
        }
        _mm512_mask_storeu_ps(row, nr.mask,
                              _mm512_add_ps(_mm512_maskz_loadu_ps(nr.mask, row), mom));
      }
    }
    return;
  }
#endif
#if !defined(AMALGAM_REAL_DOUBLE)
  // The same rows on the AVX and baseline paths, in RowLanes (8 + 4 lanes on AVX, V4s on the
  // baseline): lane 4k + c computes exactly what node k's lane c computes in the loop below, so
  // every path gives the same bits; a row takes one load, add and store per vector. (AVX-512
  // keeps NodeRows16 above: this code built for 16 lanes ran P2G 3.3x slower, measured.)
  constexpr bool kRows =
      lanes::kN<Real> != 16 && CH == 4 && !P && !S && (T == Transfer::Mls || T == Transfer::Apic);
  if constexpr (kRows) {
    using Row = RowLanes<N * CH>;
    V4 wq[N], dwq[N];
    for (int k = 0; k < N; ++k) {
      wq[k] = V4{} + st.w[2][k];
      dwq[k] = V4{} + st.dw[2][k];
    }
    const Row wz = Row::from_quads(wq), dwz = Row::from_quads(dwq), z = Row::from_quads(zk);
    for (int i = 0; i < N; ++i) {
      const Real oi = (Real(i) - st.fx[0]) * dx;
      const V4 ai = mv + a0 * oi;
      for (int j = 0; j < N; ++j) {
        const Real oj = (Real(j) - st.fx[1]) * dx;
        const V4 aij = ai + a1 * oj;
        const Real wx = st.w[0][i], wy = st.w[1][j], wij = wx * wy;
        Row g0{}, g1{};
        if constexpr (kGrad) {
          g0 = Row::splat_quad(g0c * (st.dw[0][i] * wy) + g1c * (wx * st.dw[1][j]));
          g1 = Row::splat_quad(g2c * wij);
        }
        Real* row = blk.data + GridBlock<Order, CH, M>::at(l[0] + i, l[1] + j, l[2]);
        Row r = Row::load(row);
        r.template add_momentum<kGrad>(wij, wz, z, Row::splat_quad(aij), dwz, g0, g1);
        r.store(row);
      }
    }
    return;
  }
#endif
  for (int i = 0; i < N; ++i) {
    const Real oi = (Real(i) - st.fx[0]) * dx;
    const V4 ai = mv + a0 * oi;
    const V4 qi = mq + q0 * oi;
    for (int j = 0; j < N; ++j) {
      const Real oj = (Real(j) - st.fx[1]) * dx;
      const V4 aij = ai + a1 * oj;
      const V4 qij = qi + q1 * oj;
      const Real wx = st.w[0][i], wy = st.w[1][j], wij = wx * wy;
      V4 g0{}, g1{};
      if constexpr (kGrad) {
        g0 = g0c * (st.dw[0][i] * wy) + g1c * (wx * st.dw[1][j]);
        g1 = g2c * wij;
      }
      Real* row = blk.data + GridBlock<Order, CH, M>::at(l[0] + i, l[1] + j, l[2]);
      for (int k = 0; k < N; ++k) {
        const Real w = wij * st.w[2][k], wz = st.w[2][k], dwz = st.dw[2][k];
        Real* r = row + k * CH;
        const V4 mom = w * (aij + zk[k]);
        if constexpr (P) simd::store4(r + 4, simd::load4(r + 4) + w * (qij + qk[k]));
        if constexpr (T == Transfer::Mls) {
          simd::store4(r, simd::load4(r) + mom);
          if constexpr (S) simd::store4(r + 4, simd::load4(r + 4) - w * (qij + qk[k]));
        } else if constexpr (T == Transfer::Apic && !S) {
          simd::store4(r, simd::load4(r) + (mom - (wz * g0 + dwz * g1)));
        } else {
          simd::store4(r, simd::load4(r) + mom);
          simd::store4(r + 4, simd::load4(r + 4) - (wz * g0 + dwz * g1));
        }
      }
    }
  }
}

// Particle q's C for p2g_particle: PIC/FLIP's scatter has no affine term (and its particles may
// have no C), so it gets zeros.
template <Transfer T>
inline const Mat3& affine(const MpmParticleView& p, std::uint32_t q, const Mat3* zero) {
  if constexpr (T == Transfer::PicFlip)
    return zero[0];
  else
    return p.C[q];
}

// Scatters particles [q0, q1) into `blk` (node (0,0,0) at `origin`). Particles in batches of up
// to W of one material: their stresses at once (one per vector lane, the values of one at a time:
// MaterialParams::kirchhoff_lanes), then their scatter. A dilated block (M > 0: the fused G2P2G
// and the two passes between sorts) skips a particle whose stencil leaves it and returns false;
// `reach` (optional, M > 0): the block nodes the scattered stencils reached, lo x, y, z and hi x, y,
// z inclusive (B and -1 when none), found from the stencil bases the inside test computes anyway.
template <int Order, Transfer T, bool L, bool P, bool S = false, int CH, int M>
inline bool scatter_range(GridBlock<Order, CH, M>& blk, const Vec3i& origin, std::uint32_t q_begin,
                          std::uint32_t q1, const MpmParticleView& p, const MpmStepParams& prm,
                          std::array<std::int8_t, 6>* reach = nullptr) {
  const Real dx = prm.dx, inv_dx = Real(1) / prm.dx, dt = prm.dt;
  constexpr int W = lanes::kN<Real>;
  constexpr int kB = GridBlock<Order, CH, M>::B;
  bool inside = true;
  int lo[3] = {kB, kB, kB}, hi[3] = {-1, -1, -1};
  // Without C (PIC/FLIP of materials without viscosity, MpmSolver::keeps_affine) the stress reads
  // no velocity gradient: zeros stand in for it, and PIC/FLIP's scatter has no affine term.
  Mat3 zero[W];
  if (T == Transfer::PicFlip || !p.C)
    for (int l = 0; l < W; ++l) zero[l].setZero();
  for (std::uint32_t q0 = q_begin; q0 < q1;) {
    const int n = one_material_run<W>(p.material, q0, q1);
    Real plastic[W], temperature[W];
    Mat3 tau[W], Lv[W], Fs_inv[W];
    for (int l = 0; l < n; ++l) {
      const std::uint32_t q = q0 + std::uint32_t(l);
      plastic[l] = p.plastic ? p.plastic[q] : Real(0);
      temperature[l] = p.temperature ? p.temperature[q] : Real(0);
      if constexpr (L) {
        // A-ULMPM eq. 20: P^0 (F^{0s})^T = tau (F^{sn})^{-T}; the material sees the spatial
        // velocity gradient grad_s v (F^{sn})^{-1}.
        Fs_inv[l] = p.F_s[q].inverse();
        Lv[l] = p.C ? Mat3(p.C[q] * Fs_inv[l]) : zero[l];
      }
    }
    const MaterialParams& mat = prm.materials[p.material[q0]];
    if (!L && p.J) {  // the particles keep J alone (MpmParticleView::J): every material a fluid
      mat.fluid_kirchhoff_lanes(p.J + q0, p.C ? p.C + q0 : zero, tau, n);
    } else if (!L && p.b) {  // b - I: its Cholesky factor stands in for F (isotropic materials)
      mat.kirchhoff_lanes_b(p.b + q0, p.C ? p.C + q0 : zero, plastic, temperature, tau, n);
    } else {
      mat.kirchhoff_lanes(p.F + q0, L ? Lv : p.C ? p.C + q0 : zero, plastic, temperature, tau, n);
    }
    for (int l = 0; l < n; ++l) {
      const std::uint32_t q = q0 + std::uint32_t(l);
      if constexpr (M > 0) {  // the stencil's nodes base .. base + Order inside the block?
        int d[3];
        if (!stencil_in_block<Order>(p.x[q], inv_dx, origin, kB, d)) {
          inside = false;
          continue;
        }
        for (int a = 0; a < 3; ++a) {
          lo[a] = std::min(lo[a], d[a]);
          hi[a] = std::max(hi[a], d[a] + Order);
        }
      }
      if constexpr (!L) {
        p2g_particle<Order, T, CH, false, S, M>(blk, origin, p.x[q], p.v[q], affine<T>(p, q, zero),
                                                tau[l], mat.mass(p.volume0[q]), p.volume0[q], dx,
                                                inv_dx, dt);
      } else {
        p2g_particle<Order, T, CH, P>(blk, origin, p.X_ref[q], p.v[q], affine<T>(p, q, zero),
                                      tau[l] * Fs_inv[l].transpose(), mat.mass(p.volume0[q]),
                                      p.volume0[q], dx, inv_dx, dt, p.x[q], p.F_s[q]);
      }
    }
    q0 += std::uint32_t(n);
  }
  if (reach)
    for (int a = 0; a < 3; ++a) {
      (*reach)[std::size_t(a)] = std::int8_t(lo[a]);
      (*reach)[std::size_t(a) + 3] = std::int8_t(hi[a]);
    }
  return inside;
}

// Scatters bin b's particles into its zeroed block (P2G of one bin, before the flush).
template <int Order, Transfer T, bool L, bool P, bool S = false, int CH>
inline void scatter_bin(Block<Order, CH>& blk, std::uint32_t b, const MpmParticleView& p,
                        const MpmGridView& g, const MpmStepParams& prm) {
  std::memset(blk.data, 0, sizeof(blk.data));
  scatter_range<Order, T, L, P, S>(blk, g.bin_leaf[b] * kLeafDim, g.bin_start[b], g.end_of(b), p,
                                   prm);
}

// Distributed P2G: adds the partial blocks other ranks computed for this rank's leaves, those
// of colour c (at most one per leaf: a colour's blocks do not overlap), into a and `second`.
template <int CH>
void add_imports(const exec::Space& space, const MpmGridView& g, int order, int c, Real* second) {
  if (!g.imports) return;
  const std::uint32_t i0 = g.import_colour_start[c], i1 = g.import_colour_start[c + 1];
  exec::parallel_for(space, "mpm.p2g_imports", exec::Index(i1 - i0), [&](exec::Index ii) {
    const P2GImport& im = g.imports[i0 + std::uint32_t(ii)];
    const int t = im.t, ni = (t >> 2) & 1 ? order : kLeafDim, nj = (t >> 1) & 1 ? order : kLeafDim,
              nk = t & 1 ? order : kLeafDim;
    const Real* s = im.data;
    for (int i = 0; i < ni; ++i)
      for (int j = 0; j < nj; ++j)
        for (int k = 0; k < nk; ++k, s += CH) {
          const std::size_t n =
              (std::size_t(im.leaf) * kLeafNodes + std::size_t(leaf_offset(i, j, k))) * 4;
          simd::store4(g.a + n, simd::load4(g.a + n) + simd::load4(s));
          if constexpr (CH == 8)
            simd::store4(second + n, simd::load4(second + n) + simd::load4(s + 4));
        }
  });
}

// Scatters bins[k] (bin k when bins is null), k < nbins, each into its block at
// keep + k * kSize, handed to take(k, block, CH) first when there is a take, then done(k). Each
// bin on one thread, the bins balanced over the threads (no colour phases: a bin writes only its
// block).
template <int Order, Transfer T, bool L, bool P, bool S = false, class Done>
void scatter_blocks(const exec::Space& space, const char* label, const MpmParticleView& p,
                    const MpmGridView& g, const MpmStepParams& prm, const std::uint32_t* bins,
                    std::size_t nbins, Real* keep,
                    const std::function<void(std::size_t, const Real*, int)>* take, Done&& done) {
  constexpr int CH = P || S ? 8 : channels_of(T);
  using Blk = Block<Order, CH>;
  exec::parallel_for(
      space, label, exec::Index(nbins),
      [&](exec::Index k) {
        Blk blk;
        scatter_bin<Order, T, L, P, S>(blk, bins ? bins[k] : std::uint32_t(k), p, g, prm);
        if (take) (*take)(std::size_t(k), blk.data, CH);
        std::memcpy(keep + std::size_t(k) * Blk::kSize, blk.data, sizeof(blk.data));
        done(std::size_t(k));
      },
      1);
}

// Leaf `leaf` += the kept blocks (g.blocks) that reach it: leaf_bins lists the bin of each colour
// that reaches the leaf, and its part is added in colour order, as the colour phases add them.
// a gets lanes 0-3, `second` lanes 4-7 (CH == 8).
template <int Order, int CH>
void sum_leaf(const MpmGridView& g, std::size_t leaf, Real* second) {
  using Blk = Block<Order, CH>;
  const Vec3i lc = g.leaf_coord[leaf];
  Real* la = g.a + leaf * kLeafNodes * 4;
  Real* lb = CH == 8 ? second + leaf * kLeafNodes * 4 : nullptr;
  for (int c = 0; c < 8; ++c) {
    const std::int32_t b = g.leaf_bins[leaf][size_t(c)];
    if (b < 0) continue;
    const Vec3i d = lc - g.bin_leaf[b];  // the leaf is the bin's neighbour t
    const int t = (d[0] << 2) | (d[1] << 1) | d[2];
    Blk::visit_part(g.blocks + std::size_t(b) * Blk::kSize, t, [&](const Real* s, int off) {
      Real* n = la + off * 4;
      simd::store4(n, simd::load4(n) + simd::load4(s));
      if constexpr (CH == 8)
        simd::store4(lb + off * 4, simd::load4(lb + off * 4) + simd::load4(s + 4));
    });
  }
}

// One-process P2G on kept blocks: every bin scattered in one loop; each active leaf summed by the
// thread that completes the last block reaching it (a countdown per leaf, whose release/acquire
// makes the other threads' blocks visible), so the sums run inside the same loop while the blocks
// are still in cache (a leaf's blocks come from bins at most one x-slab of keys apart). Whoever
// sums a leaf, it adds the blocks in colour order: the same bits on any thread count.
template <int Order, Transfer T, bool L, bool P, int CH, bool S = false>
void p2g_kept_blocks(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                     const MpmStepParams& prm, Real* second) {
  std::size_t slots = 0;
  for (std::size_t li = 0; li < g.nactive; ++li)
    slots = std::max(slots, std::size_t(g.active_leaves[li]) + 1);
  exec::Countdowns pending(slots);
  for (std::size_t li = 0; li < g.nactive; ++li) {
    const std::size_t leaf = std::size_t(g.active_leaves[li]);
    int n = 0;
    for (const std::int32_t b : g.leaf_bins[leaf]) n += b >= 0;
    pending.set(leaf, n);
  }
  auto done = [&](std::size_t b) {
    for (const std::int32_t leaf : g.nbr8[b])
      if (pending.arrive(std::size_t(leaf))) sum_leaf<Order, CH>(g, std::size_t(leaf), second);
  };
  scatter_blocks<Order, T, L, P, S>(space, "mpm.p2g", p, g, prm, nullptr, g.nbins, g.blocks,
                                    nullptr, done);
}

// S: the split (dt-free) scatter of the fused G2P2G's priming (p2g_particle), 8 lanes.
template <int Order, Transfer T, bool L, bool P = false, bool S = false>
void p2g_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
              const MpmStepParams& prm) {
  constexpr int CH = P || S ? 8 : channels_of(T);
  using Blk = Block<Order, CH>;
  Real* second = P ? g.q_out : g.b;
  if (g.blocks && g.leaf_bins && !g.imports && !g.kept_slot) {
    p2g_kept_blocks<Order, T, L, P, CH, S>(space, p, g, prm, second);
    return;
  }
  for (int c = 0; c < 8; ++c) {
    // Other ranks' partial blocks of this colour first (their leaves and this colour's local
    // blocks are disjoint, so the order within a colour does not matter).
    add_imports<CH>(space, g, Order, c, second);
    const std::uint32_t c0 = g.colour_start[c], c1 = g.colour_start[c + 1];
    exec::parallel_for(
        space, "mpm.p2g", exec::Index(c1 - c0),
        [&](exec::Index ci) {
          const std::uint32_t b = g.colour_bins[c0 + std::uint32_t(ci)];
          // Flush into the 8 target leaves; P: (m, m q) into q_out, PIC/FLIP: the force lanes into b
          // (their lane 0 is 0, so b's stays 0).
          auto flush = [&](const Real* s, std::size_t leaf, int off) {
            const std::size_t n = (leaf * kLeafNodes + std::size_t(off)) * 4;
            simd::store4(g.a + n, simd::load4(g.a + n) + simd::load4(s));
            if constexpr (CH == 8)
              simd::store4(second + n, simd::load4(second + n) + simd::load4(s + 4));
          };
          if (g.kept_slot && g.kept_slot[b] >= 0) {  // scattered by p2g_blocks already
            Blk::visit(g.kept + std::size_t(g.kept_slot[b]) * Blk::kSize, g.nbr8[b], flush);
            return;
          }
          Blk blk;
          scatter_bin<Order, T, L, P, S>(blk, b, p, g, prm);
          blk.for_each_node(g.nbr8[b], flush);
        },
        1);
  }
}

// Distributed P2G: the blocks of the listed bins, each handed to `take` (on the exec threads).
// L, P as p2g_impl: the Lagrangian mode (A-ULMPM) and its fused node positions (8 lanes).
template <int Order, Transfer T, bool L = false, bool P = false>
void p2g_blocks_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                     const MpmStepParams& prm, const std::uint32_t* bins, std::size_t nbins,
                     Real* keep, const std::function<void(std::size_t, const Real*, int)>& take) {
  scatter_blocks<Order, T, L, P>(space, "mpm.p2g_exports", p, g, prm, bins, nbins, keep, &take,
                                 [](std::size_t) {});
}

// A 3x3 matrix held as 4-lane columns (_, M(0, a), M(1, a), M(2, a)) -> its 9 column-major
// entries (Eigen's order): two V4 and the last entry, by shuffles rather than a trip through
// memory entry by entry.
struct Flat9 {
  simd::V4 a, b;
  Real c;
};
inline Flat9 flat9(const simd::V4* col) {
#if defined(AMALGAM_REAL_DOUBLE) && !defined(__AVX__)  // V4: two SSE2 halves (core/math/simd4.hpp)
  return {simd::V4{col[0][1], col[0][2], col[0][3], col[1][1]},
          simd::V4{col[1][2], col[1][3], col[2][1], col[2][2]}, col[2][3]};
#else
  return {__builtin_shufflevector(col[0], col[1], 1, 2, 3, 5),
          __builtin_shufflevector(col[1], col[2], 2, 3, 5, 6), col[2][3]};
#endif
}

#if !(defined(AMALGAM_REAL_DOUBLE) && !defined(__AVX__))
// Row r of a matrix held as 4-lane columns, as such a column: (_, M(r, 0), M(r, 1), M(r, 2)),
// i.e. column r of its transpose.
template <int r>
inline simd::V4 row4_of(const simd::V4* col) {
  const simd::V4 t = __builtin_shufflevector(col[0], col[1], 0, r + 1, r + 5, 0);
  return __builtin_shufflevector(t, col[2], 0, 1, 2, r + 5);
}
#endif

// advance_b (core/math/left_cauchy_green.hpp: b <- (I + G) b (I + G)^T) with G = dt grad v given
// as 4-lane columns (column k is dt Gcol[k], row r in lane r + 1): the same operations in the same
// order, on columns, so the same bits as the scalar form.
#if defined(__AVX512F__) && !defined(AMALGAM_REAL_DOUBLE)
// AVX-512: the three columns side by side in one 16-lane register, entry (r, c) in lane
// 4 c + r + 1 (lanes 0, 4, 8 and 12-15 unused), each factor of the scalar form's products one
// permute of G, D or Q: ~35 instructions where the 4-lane columns take ~75 (9 broadcasts of D,
// 9 of G's entries, the transpose's shuffles). Every entry is the same sums in the same order
// (per lane; no contraction in this file's variants), so the same bits.
// P16(v, ...): lane k of the result is lane (k-th index) of v (constant indices: GCC and clang).
#define AMALGAM_P16(v, ...) __builtin_shufflevector(v, v, __VA_ARGS__)
inline void advance_b_columns(SymDev& bd, const simd::V4* Gcol, Real dt) {
  typedef float V8 __attribute__((vector_size(32)));
  typedef float V16 __attribute__((vector_size(64)));
  Real* d = bd.e;
  const V8 g01 = __builtin_shufflevector(Gcol[0], Gcol[1], 0, 1, 2, 3, 4, 5, 6, 7);
  const V8 g22 = __builtin_shufflevector(Gcol[2], Gcol[2], 0, 1, 2, 3, 0, 1, 2, 3);
  const V16 g =
      dt * __builtin_shufflevector(g01, g22, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  const V16 dz = V16(_mm512_maskz_loadu_ps(0x3f, d));  // D's six entries, lanes 0-5
  // Column k in every column's place, (r, c) <- (r, k):
#define AMALGAM_COL(k)                                                                             \
  0, 4 * k + 1, 4 * k + 2, 4 * k + 3, 0, 4 * k + 1, 4 * k + 2, 4 * k + 3, 0, 4 * k + 1, 4 * k + 2, \
      4 * k + 3, 0, 0, 0, 0
  // Q = G + G D: Q(r, c) = G(r, c) + ((G(r, 0) D(0, c) + G(r, 1) D(1, c)) + G(r, 2) D(2, c)),
  // D(k, c) in every row of column c taken from dz (D(r, c) is entry sym_index(r, c)).
  const V16 Q = g + ((AMALGAM_P16(g, AMALGAM_COL(0)) *
                          AMALGAM_P16(dz, 0, 0, 0, 0, 0, 3, 3, 3, 0, 4, 4, 4, 0, 0, 0, 0) +
                      AMALGAM_P16(g, AMALGAM_COL(1)) *
                          AMALGAM_P16(dz, 0, 3, 3, 3, 0, 1, 1, 1, 0, 5, 5, 5, 0, 0, 0, 0)) +
                     AMALGAM_P16(g, AMALGAM_COL(2)) *
                         AMALGAM_P16(dz, 0, 4, 4, 4, 0, 5, 5, 5, 0, 2, 2, 2, 0, 0, 0, 0));
  // Q G^T: (Q(r, 0) G(c, 0) + Q(r, 1) G(c, 1)) + Q(r, 2) G(c, 2), G(c, k) at (r, c).
  const V16 QG = (AMALGAM_P16(Q, AMALGAM_COL(0)) *
                      AMALGAM_P16(g, 0, 1, 1, 1, 0, 2, 2, 2, 0, 3, 3, 3, 0, 0, 0, 0) +
                  AMALGAM_P16(Q, AMALGAM_COL(1)) *
                      AMALGAM_P16(g, 0, 5, 5, 5, 0, 6, 6, 6, 0, 7, 7, 7, 0, 0, 0, 0)) +
                 AMALGAM_P16(Q, AMALGAM_COL(2)) *
                     AMALGAM_P16(g, 0, 9, 9, 9, 0, 10, 10, 10, 0, 11, 11, 11, 0, 0, 0, 0);
#undef AMALGAM_COL
  // (Q + Q^T) + Q G^T, Q^T: (r, c) <- (c, r).
  const V16 M = (Q + AMALGAM_P16(Q, 0, 1, 5, 9, 0, 2, 6, 10, 0, 3, 7, 11, 0, 0, 0, 0)) + QG;
  // D's entries in SymDev's order: M(0, 0), M(1, 1), M(2, 2), M(0, 1), M(0, 2), M(1, 2).
  const V16 m = AMALGAM_P16(M, 1, 6, 11, 5, 9, 10, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
  _mm512_mask_storeu_ps(d, 0x3f, __m512(dz + m));
}
#undef AMALGAM_P16
#else
inline void advance_b_columns(SymDev& bd, const simd::V4* Gcol, Real dt) {
  using simd::V4;
  Real* d = bd.e;
  const Real D[3][3] = {{d[0], d[3], d[4]}, {d[3], d[1], d[5]}, {d[4], d[5], d[2]}};
  V4 g[3], Q[3], QG[3];
  for (int k = 0; k < 3; ++k) g[k] = dt * Gcol[k];
  for (int c = 0; c < 3; ++c)  // Q = G + G D, column c
    Q[c] = g[c] + ((g[0] * D[0][c] + g[1] * D[1][c]) + g[2] * D[2][c]);
  for (int c = 0; c < 3; ++c)  // Q G^T, column c: sum over k of Q's column k times G(c, k)
    QG[c] = (Q[0] * g[0][c + 1] + Q[1] * g[1][c + 1]) + Q[2] * g[2][c + 1];
#if defined(AMALGAM_REAL_DOUBLE) && !defined(__AVX__)  // V4: two SSE2 halves (core/math/simd4.hpp)
  constexpr int rs[6] = {0, 1, 2, 0, 0, 1}, cs[6] = {0, 1, 2, 1, 2, 2};
  for (int e = 0; e < 6; ++e) {
    const int r = rs[e], c = cs[e];
    d[e] += (Q[c][r + 1] + Q[r][c + 1]) + QG[c][r + 1];
  }
#else
  // M = (Q + Q^T) + Q G^T in columns (Q^T by shuffles), then D's entries 0-3 as one 4-lane add:
  // each entry the same sums as the scalar form, without 27 lane extracts.
  const V4 M[3] = {(Q[0] + row4_of<0>(Q)) + QG[0], (Q[1] + row4_of<1>(Q)) + QG[1],
                   (Q[2] + row4_of<2>(Q)) + QG[2]};
  const V4 m03 = __builtin_shufflevector(__builtin_shufflevector(M[0], M[1], 1, 6, 5, 5), M[2], 0,
                                         1, 7, 2);  // M(0,0), M(1,1), M(2,2), M(0,1)
  simd::store4(d, simd::load4(d) + m03);
  d[4] += M[2][1], d[5] += M[2][2];
#endif
}
#endif

// Per-particle G2P (pure: reads a block of node velocities, updates the particle).
// L (Lagrangian mode): the stencil sits at the reference position xs and F_s, F_0s are updated
// (eqs. 30, 32); otherwise xs is x itself and F <- (I + dt grad v) F, or, where the particles keep
// J alone (F null), J <- det(I + dt grad v) J. flatten: as p2g_particle.
// C: APIC/MLS's affine matrix (never null); PIC/FLIP stores grad v in it when the particles
// keep one (a viscous stress reads it), else C is null and nothing is stored.
template <int Order, Transfer T, int CH, bool L, int M = 0>
__attribute__((flatten)) inline void g2p_particle(const GridBlock<Order, CH, M>& blk,
                                                  const Vec3i& origin, const Vec3& xs, Vec3& x,
                                                  Vec3* x_lo, Vec3& v, Mat3* C, Mat3* Fp,
                                                  Mat3* F_lo, Real* J, SymDev* bd, Mat3* Fs,
                                                  const Mat3* F0s, Real dx, Real inv_dx, Real dt,
                                                  Real alpha) {
  const Stencil<Order> st = Stencil<Order>::at(xs, inv_dx);
  const Vec3i l = st.base - origin;
  constexpr int N = Stencil<Order>::kN;
  // Hierarchical sums over j, then i, of whole stencil rows (RowLanes: node k's 4 or 8 lanes, the
  // grid's (m, v) rows, side by side), then over k of their nodes' quads. One order on every path.
  constexpr bool kB = (T != Transfer::PicFlip), kGrad = (T != Transfer::Mls),
                 kFlip = (T == Transfer::PicFlip);
  using simd::V4;
  using Row = RowLanes<N * CH>;
  // Sums over (i, j) of a row's lanes: w_i w_j r, i w_i w_j r, w_i j w_j r, dw_i w_j r, w_i dw_j r.
  Row P{}, Pi{}, Pj{}, Pd0{}, Pd1{};
  for (int i = 0; i < N; ++i) {
    Row Q{}, Qj{}, Qd{};  // over j of row (i, j): w_j r, j w_j r, dw_j r
    for (int j = 0; j < N; ++j) {
      const Row r = Row::load(blk.data + GridBlock<Order, CH, M>::at(l[0] + i, l[1] + j, l[2]));
      const Real wy = st.w[1][j];
      if (j == 0) {
        Q.set_scaled(wy, r);
        if constexpr (kGrad) Qd.set_scaled(st.dw[1][j], r);
      } else {
        Q.add_scaled(wy, r);
        if constexpr (kGrad) Qd.add_scaled(st.dw[1][j], r);
        if constexpr (kB) {  // the j = 0 term is +-0
          if (j == 1)
            Qj.set_scaled(wy, r);
          else
            Qj.add_scaled(Real(j) * wy, r);
        }
      }
    }
    const Real wx = st.w[0][i], dwx = st.dw[0][i];
    if (i == 0) {
      P.set_scaled(wx, Q);
      if constexpr (kB) Pj.set_scaled(wx, Qj);
      if constexpr (kGrad) Pd0.set_scaled(dwx, Q), Pd1.set_scaled(wx, Qd);
    } else {
      P.add_scaled(wx, Q);
      if constexpr (kB) {
        if (i == 1)
          Pi.set_scaled(wx, Q);
        else
          Pi.add_scaled(Real(i) * wx, Q);
        Pj.add_scaled(wx, Qj);
      }
      if constexpr (kGrad) Pd0.add_scaled(dwx, Q), Pd1.add_scaled(wx, Qd);
    }
  }
  // Then over k, node k's quads (CH = 8: quad 2k is (m, v), 2k + 1 PIC/FLIP's (-, dv)):
  //   S = sum w v;  S_a = sum w v idx_a  ->  B.col(a) = sum w v o_a = dx (S_a - fx_a S)  (MLS, APIC)
  //   D_a = sum v dw/dx_a                ->  grad v = [D_0 D_1 D_2]                  (APIC, PIC/FLIP)
  //   dV = sum w dv                                                                  (FLIP)
  constexpr int QK = CH / 4;
  V4 S = st.w[2][0] * P.quad(0), Si{}, Sj{}, Sk{}, D0{}, D1{}, D2{}, dV{};
  if constexpr (kB) Si = st.w[2][0] * Pi.quad(0), Sj = st.w[2][0] * Pj.quad(0);
  if constexpr (kGrad) {
    D0 = st.w[2][0] * Pd0.quad(0), D1 = st.w[2][0] * Pd1.quad(0);
    D2 = st.dw[2][0] * P.quad(0);
  }
  if constexpr (kFlip) dV = st.w[2][0] * P.quad(1);
  for (int k = 1; k < N; ++k) {
    const Real wz = st.w[2][k];
    const V4 pk = P.quad(QK * k);
    S += wz * pk;
    if constexpr (kB) {
      Si += wz * Pi.quad(QK * k), Sj += wz * Pj.quad(QK * k);
      if (k == 1)
        Sk = wz * pk;
      else
        Sk += (Real(k) * wz) * pk;
    }
    if constexpr (kGrad) {
      D0 += wz * Pd0.quad(QK * k), D1 += wz * Pd1.quad(QK * k);
      D2 += st.dw[2][k] * pk;
    }
    if constexpr (kFlip) dV += wz * P.quad(QK * k + 1);
  }
  // Lane 0 summed the nodes' masses (unused); velocity component c is lane c + 1, and the
  // matrices below are 4-lane columns with row c in lane c + 1.
  const Vec3 v_pic(S[1], S[2], S[3]);
  const Vec3 dv(dV[1], dV[2], dV[3]);
  V4 Ccol[3], Gcol[3];  // C and grad v
  if constexpr (T == Transfer::PicFlip) {
    v = alpha * (v + dv) + (1 - alpha) * v_pic;
    Ccol[0] = Gcol[0] = D0, Ccol[1] = Gcol[1] = D1, Ccol[2] = Gcol[2] = D2;  // C kept for viscosity
  } else {
    // B.col(a) = dx (S_a - fx_a S), C = D^{-1} B.
    const Real s = BSpline<Order>::kDinvScale * inv_dx * inv_dx;
    const V4* Sa[3] = {&Si, &Sj, &Sk};
    for (int a = 0; a < 3; ++a) Ccol[a] = s * (dx * (*Sa[a] - st.fx[a] * S));
    if constexpr (T == Transfer::Mls) {
      for (int a = 0; a < 3; ++a) Gcol[a] = Ccol[a];  // A-ULMPM Sec. 5.8: grad v_p = C_p
    } else {
      Gcol[0] = D0, Gcol[1] = D1, Gcol[2] = D2;
    }
    v = v_pic;
  }
  if (T != Transfer::PicFlip || C) {
    const Flat9 c9 = flat9(Ccol);
    simd::store4(C->data(), c9.a), simd::store4(C->data() + 4, c9.b), C->data()[8] = c9.c;
  }
  if constexpr (L) {
    Mat3 grad_v;
    for (int a = 0; a < 3; ++a)
      for (int c = 0; c < 3; ++c) grad_v(c, a) = Gcol[a][c + 1];
    *Fs += dt * grad_v;  // A-ULMPM eq. 30: F^{s(n+1)} = F^{sn} + dt grad_s v
    *Fp = *Fs * *F0s;    // eq. 32: F^{0(n+1)} = F^{s(n+1)} F^{0s}
  } else if (J) {        // det of F <- (I + dt grad v) F, F itself not kept
    Real a[3][3];
    for (int c = 0; c < 3; ++c)
      for (int k = 0; k < 3; ++k) a[c][k] = dt * Gcol[k][c + 1];
    *J = WeaklyCompressibleT<Real>::advance_J(*J, a);
  } else if (bd) {  // b <- (I + dt grad v) b (I + dt grad v)^T, F itself not kept
    advance_b_columns(*bd, Gcol, dt);
  } else {
    Mat3& F = *Fp;
    // F <- F + dt (grad v) F: the increment's column j is dt sum_a g_a F(a, j), on 4-lane
    // columns. It is added to F itself (compensated when F has a low part): forming
    // I + dt grad v first would round 1 + dt g to float's uneven spacing around 1 (6e-8 below,
    // 1.2e-7 above), a bias towards compression in every small increment (issue 27).
    V4 dcol[3];
    for (int j = 0; j < 3; ++j)
      dcol[j] = dt * (Gcol[0] * F(0, j) + Gcol[1] * F(1, j) + Gcol[2] * F(2, j));
    const Flat9 d = flat9(dcol);  // dF's entries, column-major, as F's
    const V4 d4[2] = {d.a, d.b};
    Real* h = F.data();
    if (F_lo) {  // add_compensated on lanes: entries 0-3 and 4-7, then 8
      Real* lo = F_lo->data();
      for (int e = 0; e < 2; ++e) {
        const V4 hv = simd::load4(h + 4 * e), b = simd::load4(lo + 4 * e) + d4[e];
        const V4 sv = hv + b, bb = sv - hv;
        simd::store4(lo + 4 * e, (hv - (sv - bb)) + (b - bb));
        simd::store4(h + 4 * e, sv);
      }
      add_compensated(h[8], lo[8], d.c);
    } else {
      for (int e = 0; e < 2; ++e) simd::store4(h + 4 * e, simd::load4(h + 4 * e) + d4[e]);
      h[8] += d.c;
    }
  }
  if (x_lo)  // eq. 28: x += dt v
    add_compensated(x, *x_lo, Vec3(dt * v_pic));
  else
    x += dt * v_pic;
}

// Bin b's node rows into its gather block: (m, v_new) and, CH = 8, PIC/FLIP's (-, dv) beside them.
template <int Order, int CH>
inline void gather_bin(Block<Order, CH>& blk, const MpmGridView& g, std::size_t b) {
  blk.for_each_node(g.nbr8[b], [&](Real* d, std::size_t leaf, int off) {
    const std::size_t n = (leaf * kLeafNodes + std::size_t(off)) * 4;
    simd::store4(d, simd::load4(g.a + n));
    if constexpr (CH == 8) simd::store4(d + 4, simd::load4(g.b + n));
  });
}

// Bin b's dilated block (node (0,0,0) at the bin leaf's origin - M) from the 27 leaves around the
// bin's leaf (g.bin_nbr27[b]); a missing leaf's nodes are zero (no mass: no particle's stencil
// reaches them).
template <int Order, int CH, int M>
inline void gather_dilated(GridBlock<Order, CH, M>& blk, const MpmGridView& g, std::size_t b) {
  using Blk = GridBlock<Order, CH, M>;
  int leaf_d[Blk::B], off[Blk::B];  // per axis: block node i -> leaf -1/0/+1, offset in it
  for (int i = 0; i < Blk::B; ++i) {
    const int a = i - M;
    leaf_d[i] = a < 0 ? -1 : a / kLeafDim;
    off[i] = a - leaf_d[i] * kLeafDim;
  }
  const std::array<std::int32_t, 27>& n27 = g.bin_nbr27[b];
  // A block row (i, j) meets the leaves -1, 0, +1 along z in three runs of nodes, each contiguous
  // in its leaf (leaf_offset: z fastest) and in the block: one copy per run, of a length known at
  // compile time (M, kLeafDim, Order + M nodes), so the copies are inline moves rather than
  // ~430 library calls a bin of 1 to 8 nodes each (within noise on the bench: docs/benchmarks.md).
  auto run = [&](auto r_c, Real* row, int t0, int oi, int oj) {
    constexpr int r = decltype(r_c)::value;
    constexpr int k0 = r == 0 ? 0 : r == 1 ? M : M + kLeafDim;
    constexpr int n = (r == 0 ? M : r == 1 ? M + kLeafDim : Blk::B) - k0;
    if constexpr (n > 0) {
      Real* d = row + k0 * CH;
      const std::int32_t leaf = n27[std::size_t(t0 + r)];
      if (leaf < 0) {
        std::memset(d, 0, sizeof(Real) * std::size_t(n * CH));
        return;
      }
      constexpr int ok = r == 0 ? kLeafDim - M : 0;  // the run's first offset along z in its leaf
      const std::size_t e =
          (std::size_t(leaf) * kLeafNodes + std::size_t(leaf_offset(oi, oj, ok))) * 4;
      if constexpr (CH == 4) {
        std::memcpy(d, g.a + e, sizeof(Real) * std::size_t(4 * n));
      } else {
        for (int k = 0; k < n; ++k) {
          simd::store4(d + 8 * k, simd::load4(g.a + e + 4 * std::size_t(k)));
          simd::store4(d + 8 * k + 4, simd::load4(g.b + e + 4 * std::size_t(k)));
        }
      }
    }
  };
  for (int i = 0; i < Blk::B; ++i)
    for (int j = 0; j < Blk::B; ++j) {
      const int t0 = (leaf_d[i] + 1) * 9 + (leaf_d[j] + 1) * 3;
      Real* row = blk.data + Blk::at(i, j, 0);
      run(std::integral_constant<int, 0>{}, row, t0, off[i], off[j]);
      run(std::integral_constant<int, 1>{}, row, t0, off[i], off[j]);
      run(std::integral_constant<int, 2>{}, row, t0, off[i], off[j]);
    }
}

// body(b, acc) for every bin b: acc is null, or (prm.check) the partial stability check the body
// adds its particles to, reduced into *prm.check (the same value in any order: stability_check.hpp).
template <class Body>
void for_bins(const exec::Space& space, const char* label, std::size_t nbins,
              const MpmStepParams& prm, Body&& body) {
  if (!prm.check) {
    exec::parallel_for(
        space, label, exec::Index(nbins), [&](exec::Index b) { body(b, nullptr); }, 1);
    return;
  }
  *prm.check = exec::parallel_reduce(
      space, label, exec::Index(nbins), StabilityCheck{},
      [&](exec::Index b, StabilityCheck& acc) { body(b, &acc); }, merge_checks, 1);
}

// The end of a bin's particle update in g2p and g2p_dilated: the particle collisions
// (prm.collide) and the stability check (acc).
inline void finish_bin(const MpmParticleView& p, const MpmStepParams& prm, std::uint32_t q0,
                       std::uint32_t q1, StabilityCheck* acc) {
  if (prm.collide && prm.ncolliders > 0)
    collide_range(p, prm.colliders, prm.ncolliders, q0, q1, prm.time + prm.dt);
  if (acc) check_particles(*acc, q0, q1, p, prm.check_limits);
}

template <int Order, Transfer T, bool L>
void g2p_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
              const MpmStepParams& prm) {
  constexpr int CH = (T == Transfer::PicFlip) ? 8 : 4;  // (m, v_new) (+ (-, dv)): the grid's rows
  using Blk = Block<Order, CH>;
  const Real dx = prm.dx, inv_dx = Real(1) / prm.dx, dt = prm.dt, alpha = prm.flip_alpha;
  auto lo = [](auto* a, std::uint32_t q) { return a ? a + q : nullptr; };
  for_bins(space, "mpm.g2p", g.nbins, prm, [&](exec::Index bi, StabilityCheck* acc) {
    const std::size_t b = std::size_t(bi);
    Blk blk;
    gather_bin(blk, g, b);
    const Vec3i origin = g.bin_leaf[b] * kLeafDim;
    const std::uint32_t q0 = g.bin_start[b], q1 = g.end_of(b);
    for (std::uint32_t q = q0; q < q1; ++q) {
      if constexpr (L)
        g2p_particle<Order, T, CH, true>(blk, origin, p.X_ref[q], p.x[q], lo(p.x_lo, q), p.v[q],
                                         lo(p.C, q), p.F + q, nullptr, nullptr, nullptr, p.F_s + q,
                                         p.F_0s + q, dx, inv_dx, dt, alpha);
      else
        g2p_particle<Order, T, CH, false>(blk, origin, p.x[q], p.x[q], lo(p.x_lo, q), p.v[q],
                                          lo(p.C, q), lo(p.F, q), lo(p.F_lo, q), lo(p.J, q),
                                          lo(p.b, q), nullptr, nullptr, dx, inv_dx, dt, alpha);
    }
    finish_bin(p, prm, q0, q1, acc);
  });
}

// The fused G2P2G (Wang et al. 2020): per bin, one pass over its particles' data: gather from
// the grid and update each particle (g2p_particle), the particle collisions (collide_particle),
// the material update (update_material_group), then the split (dt-free) scatter of the updated
// particles into the bin's dilated block (margin kG2P2GMargin: the particles moved) at
// blocks + b * g2p2g_block_reals(Order). far[b] = 1 when a particle left the dilated block
// (skipped: the caller falls back to a plain P2G). Every particle's updates are those of
// g2p, collide_particles and update_material_state, in that order: the same bits.
template <int Order, Transfer T>
void g2p2g_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                const MpmStepParams& prm, const MaterialUpdateParams* mu, Real* blocks,
                std::uint8_t* far) {
  constexpr int CH = channels_of(T), M = kG2P2GMargin;
  using Out = GridBlock<Order, 8, M>;
  const Real dx = prm.dx, inv_dx = Real(1) / prm.dx, dt = prm.dt, alpha = prm.flip_alpha;
  const Real t_end = prm.time + prm.dt;
  constexpr int kN = lanes::kN<Real>;
  auto lo = [](auto* a, std::uint32_t q) { return a ? a + q : nullptr; };
  for_bins(space, "mpm.g2p2g", g.nbins, prm, [&](exec::Index bi, StabilityCheck* acc) {
    const std::size_t b = std::size_t(bi);
    const Vec3i origin = g.bin_leaf[b] * kLeafDim;
    const std::uint32_t q0 = g.bin_start[b], q1 = g.end_of(b);
    {  // the particles moved up to M nodes since the bins were sorted: a dilated gather
      GridBlock<Order, CH, M> in;
      gather_dilated(in, g, b);
      const Vec3i in_origin = origin - Vec3i::Constant(M);
      for (std::uint32_t q = q0; q < q1; ++q)
        g2p_particle<Order, T, CH, false>(in, in_origin, p.x[q], p.x[q], lo(p.x_lo, q), p.v[q],
                                          lo(p.C, q), lo(p.F, q), lo(p.F_lo, q), lo(p.J, q),
                                          lo(p.b, q), nullptr, nullptr, dx, inv_dx, dt, alpha);
    }
    if (prm.ncolliders > 0) collide_range(p, prm.colliders, prm.ncolliders, q0, q1, t_end);
    for (std::uint32_t q = q0; mu && q < q1; q += kN)
      update_material_group(p, *mu, q, std::min(q1, q + kN));
    if (acc) check_particles(*acc, q0, q1, p, prm.check_limits);
    Out out;
    out.clear();
    far[b] = !scatter_range<Order, T, false, false, true>(out, origin - Vec3i::Constant(M), q0, q1,
                                                          p, prm);
    std::memcpy(blocks + b * std::size_t(Out::kSize), out.data, sizeof(out.data));
  });
}

// Active leaf li of g = the parts of the dilated blocks (CH lanes, margin kG2P2GMargin) listed for
// it (items[start[li] .. start[li + 1]): bin << 5 | t, the leaf at the bin's leaf + (t / 9 - 1,
// t / 3 % 3 - 1, t % 3 - 1)), in list order: lanes 0-3 into a, 4-7 (CH = 8) into b. The leaf is
// overwritten (no grid_clear needed), and its sum is the same whichever thread computes it.
// box (optional): per bin, the block nodes its particles' stencils reached (lo x, y, z, hi x, y, z,
// inclusive); the rest of its block is zero and is not added.
template <int Order, int CH>
void sum_dilated_leaf(const MpmGridView& g, std::size_t li, const Real* blocks,
                      const std::uint32_t* start, const std::uint32_t* items,
                      const std::array<std::int8_t, 6>* box = nullptr) {
  constexpr int M = kG2P2GMargin;
  using Blk = GridBlock<Order, CH, M>;
  const std::size_t leaf = std::size_t(g.active_leaves[li]);
  Real* la = g.a + leaf * kLeafNodes * 4;
  Real* lb = CH == 8 ? g.b + leaf * kLeafNodes * 4 : nullptr;
  std::memset(la, 0, kLeafNodes * 4 * sizeof(Real));
  if constexpr (CH == 8) std::memset(lb, 0, kLeafNodes * 4 * sizeof(Real));
  for (std::uint32_t k = start[li]; k < start[li + 1]; ++k) {
    const Real* blk = blocks + std::size_t(items[k] >> 5) * std::size_t(Blk::kSize);
    const int t = int(items[k] & 31u);
    const int d[3] = {t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1};
    int n0[3], n1[3];  // the leaf's nodes n0 <= n < n1 inside the block (block node d 8 + n + M)
    bool empty = false;
    for (int a = 0; a < 3; ++a) {
      n0[a] = std::max(0, -d[a] * kLeafDim - M);
      n1[a] = std::min(kLeafDim, Blk::B - d[a] * kLeafDim - M);
      if (box) {
        const std::array<std::int8_t, 6>& bx = box[items[k] >> 5];
        n0[a] = std::max(n0[a], int(bx[std::size_t(a)]) - d[a] * kLeafDim - M);
        n1[a] = std::min(n1[a], int(bx[std::size_t(a) + 3]) + 1 - d[a] * kLeafDim - M);
      }
      empty |= n0[a] >= n1[a];
    }
    if (empty) continue;
    for (int i = n0[0]; i < n1[0]; ++i)
      for (int j = n0[1]; j < n1[1]; ++j)
        for (int k2 = n0[2]; k2 < n1[2]; ++k2) {
          const Real* s = blk + Blk::at(d[0] * kLeafDim + i + M, d[1] * kLeafDim + j + M,
                                        d[2] * kLeafDim + k2 + M);
          const int o = leaf_offset(i, j, k2) * 4;
          simd::store4(la + o, simd::load4(la + o) + simd::load4(s));
          if constexpr (CH == 8) simd::store4(lb + o, simd::load4(lb + o) + simd::load4(s + 4));
        }
  }
}

// Every active leaf li < g.nactive of g = the CH-lane dilated blocks listed for it (the two passes'
// lanes between sorts; a distributed run's owned leaves, with other ranks' parts in import slots).
// (The fused pass's flush, g2p2g_flush, is this with its 8 lanes.)
template <int Order, int CH>
void sum_dilated_leaves_impl(const exec::Space& space, const MpmGridView& g, const Real* blocks,
                             const std::uint32_t* start, const std::uint32_t* items,
                             const char* region = "mpm.p2g_sum") {
  exec::parallel_for(space, region, exec::Index(g.nactive), [&](exec::Index li) {
    sum_dilated_leaf<Order, CH>(g, std::size_t(li), blocks, start, items);
  });
}

// The two passes between sorts (MpmSolver's lazy sort): P2G of each bin into its dilated block
// (CH = the two passes' lanes: 4, PIC/FLIP 8), all bins in one balanced loop; each active leaf is
// summed (sum_dilated_leaf, the blocks in bin order) by the thread that completes the last block
// reaching it (a countdown per active leaf, release / acquire), while the blocks are hot.
// target[b * 27 + t]: the active index of the leaf at bin b's leaf + offset t, or -1. far[b] = 1
// when a particle of bin b lies outside its dilated block (not scattered: the caller re-sorts).
template <int Order, Transfer T>
void p2g_dilated_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                      const MpmStepParams& prm, Real* blocks, const std::uint32_t* start,
                      const std::uint32_t* items, const std::int32_t* target, std::uint8_t* far) {
  constexpr int CH = channels_of(T), M = kG2P2GMargin;
  using Blk = GridBlock<Order, CH, M>;
  exec::Countdowns pending(std::max<std::size_t>(g.nactive, 1));
  for (std::size_t li = 0; li < g.nactive; ++li) {
    const int n = int(start[li + 1] - start[li]);
    pending.set(li, n);
    if (n == 0) sum_dilated_leaf<Order, CH>(g, li, blocks, start, items);  // zeroes it
  }
  // Per bin, the block nodes its particles reach: between sorts mostly the bin's own footprint,
  // so the margin's slabs (zero) are not added into the leaves.
  std::vector<std::array<std::int8_t, 6>> box(g.nbins);
  exec::parallel_for(
      space, "mpm.p2g", exec::Index(g.nbins),
      [&](exec::Index bi) {
        const std::size_t b = std::size_t(bi);
        Blk blk;
        blk.clear();
        const Vec3i origin = g.bin_leaf[b] * kLeafDim - Vec3i::Constant(M);
        // (a particle outside the block is neither scattered nor in the box: far, re-sorted)
        far[b] = !scatter_range<Order, T, false, false>(blk, origin, g.bin_start[b], g.end_of(b), p,
                                                        prm, &box[b]);
        std::memcpy(blocks + b * std::size_t(Blk::kSize), blk.data, sizeof(blk.data));
        for (int t = 0; t < 27; ++t) {
          const std::int32_t li = target[b * 27 + std::size_t(t)];
          if (li >= 0 && pending.arrive(std::size_t(li)))
            sum_dilated_leaf<Order, CH>(g, std::size_t(li), blocks, start, items, box.data());
        }
      },
      1);
}

// G2P between sorts: each bin gathers its dilated block from the 27 leaves around its leaf
// (gather_dilated) and updates its particles as g2p does (g2p_particle: the same bits for the same
// grid); far[b] = 1 when a particle of bin b ends outside the bin's dilated block.
template <int Order, Transfer T>
void g2p_dilated_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                      const MpmStepParams& prm, std::uint8_t* far) {
  constexpr int CH = channels_of(T), M = kG2P2GMargin;
  using Blk = GridBlock<Order, CH, M>;
  const Real dx = prm.dx, inv_dx = Real(1) / prm.dx, dt = prm.dt, alpha = prm.flip_alpha;
  auto lo = [](auto* a, std::uint32_t q) { return a ? a + q : nullptr; };
  for_bins(space, "mpm.g2p", g.nbins, prm, [&](exec::Index bi, StabilityCheck* acc) {
    const std::size_t b = std::size_t(bi);
    Blk in;
    gather_dilated(in, g, b);
    const Vec3i origin = g.bin_leaf[b] * kLeafDim - Vec3i::Constant(M);
    bool out = false;
    const std::uint32_t q0 = g.bin_start[b], q1 = g.end_of(b);
    for (std::uint32_t q = q0; q < q1; ++q) {
      g2p_particle<Order, T, CH, false>(in, origin, p.x[q], p.x[q], lo(p.x_lo, q), p.v[q],
                                        lo(p.C, q), lo(p.F, q), lo(p.F_lo, q), lo(p.J, q),
                                        lo(p.b, q), nullptr, nullptr, dx, inv_dx, dt, alpha);
      out |= !stencil_in_block<Order>(p.x[q], inv_dx, origin, Blk::B, nullptr);
    }
    far[b] = out;  // before the collisions: P2G finds a particle they pushed out
    finish_bin(p, prm, q0, q1, acc);
  });
}

template <template <int, Transfer> class Fn, class... Args>
void dispatch(int order, Transfer t, Args&&... args) {
  if (order == 3) {
    switch (t) {
      case Transfer::PicFlip:
        return Fn<3, Transfer::PicFlip>::run(args...);
      case Transfer::Apic:
        return Fn<3, Transfer::Apic>::run(args...);
      case Transfer::Mls:
        return Fn<3, Transfer::Mls>::run(args...);
    }
  } else {
    switch (t) {
      case Transfer::PicFlip:
        return Fn<2, Transfer::PicFlip>::run(args...);
      case Transfer::Apic:
        return Fn<2, Transfer::Apic>::run(args...);
      case Transfer::Mls:
        return Fn<2, Transfer::Mls>::run(args...);
    }
  }
}

// The Lagrangian mode is a template argument so the Eulerian loops compile as before (a
// per-particle branch cost 5-8 % in P2G/G2P, measured).
template <int O, Transfer T>
struct P2G {
  static void run(const exec::Space& s, const MpmParticleView& p, const MpmGridView& g,
                  const MpmStepParams& prm) {
    if constexpr (T != Transfer::PicFlip) {
      if (p.X_ref && g.q_out) return p2g_impl<O, T, true, true>(s, p, g, prm);
      if (prm.split) return p2g_impl<O, T, false, false, true>(s, p, g, prm);
    }
    if (p.X_ref)
      p2g_impl<O, T, true>(s, p, g, prm);
    else
      p2g_impl<O, T, false>(s, p, g, prm);
  }
};
template <int O, Transfer T>
struct G2P {
  static void run(const exec::Space& s, const MpmParticleView& p, const MpmGridView& g,
                  const MpmStepParams& prm) {
    if (p.X_ref)
      g2p_impl<O, T, true>(s, p, g, prm);
    else
      g2p_impl<O, T, false>(s, p, g, prm);
  }
};

template <int O, Transfer T>
struct G2P2G {
  static void run(const exec::Space& s, const MpmParticleView& p, const MpmGridView& g,
                  const MpmStepParams& prm, const MaterialUpdateParams* mu, Real* blocks,
                  std::uint8_t* far) {
    g2p2g_impl<O, T>(s, p, g, prm, mu, blocks, far);
  }
};

template <int O, Transfer T>
struct P2GDilated {
  static void run(const exec::Space& s, const MpmParticleView& p, const MpmGridView& g,
                  const MpmStepParams& prm, Real* blocks, const std::uint32_t* start,
                  const std::uint32_t* items, const std::int32_t* target, std::uint8_t* far) {
    p2g_dilated_impl<O, T>(s, p, g, prm, blocks, start, items, target, far);
  }
};
template <int O, Transfer T>
struct G2PDilated {
  static void run(const exec::Space& s, const MpmParticleView& p, const MpmGridView& g,
                  const MpmStepParams& prm, std::uint8_t* far) {
    g2p_dilated_impl<O, T>(s, p, g, prm, far);
  }
};

template <int Order>
void p2g_positions_impl(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                        Real dx, const MaterialParams* materials, Real* out) {
  using Blk = Block<Order, 4>;
  const Real inv_dx = Real(1) / dx;
  const Mat3 zero = Mat3::Zero();
  for (int c = 0; c < 8; ++c) {
    const std::uint32_t c0 = g.colour_start[c], c1 = g.colour_start[c + 1];
    exec::parallel_for(
        space, "aul.p2g_positions", exec::Index(c1 - c0),
        [&](exec::Index ci) {
          const std::uint32_t b = g.colour_bins[c0 + std::uint32_t(ci)];
          Blk blk;
          blk.clear();
          const Vec3i origin = g.bin_leaf[b] * kLeafDim;
          // The APIC scatter with v -> x_p and C -> F_s: m w (x_p + F_s (X_i - X_p)), no stress.
          for (std::uint32_t q = g.bin_start[b]; q < g.bin_start[b + 1]; ++q)
            p2g_particle<Order, Transfer::Apic, 4>(blk, origin, p.X_ref[q], p.x[q], p.F_s[q], zero,
                                                   materials[p.material[q]].mass(p.volume0[q]), 0,
                                                   dx, inv_dx, 0);
          blk.flush_add4(g.nbr8[b], out);
        },
        1);
  }
}

}  // namespace

void p2g_positions(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                   const MpmStepParams& prm, Real* out) {
  clear_node4(space, g, out);
  if (prm.order == 3)
    p2g_positions_impl<3>(space, p, g, prm.dx, prm.materials, out);
  else
    p2g_positions_impl<2>(space, p, g, prm.dx, prm.materials, out);
}

void grid_clear(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm) {
  const bool two = prm.transfer == Transfer::PicFlip || prm.split;
  exec::parallel_for(space, "mpm.grid_clear", exec::Index(g.nactive), [&](exec::Index i) {
    const std::size_t leaf = std::size_t(g.active_leaves[i]);
    std::memset(g.a + leaf * kLeafNodes * 4, 0, kLeafNodes * 4 * sizeof(Real));
    if (two) std::memset(g.b + leaf * kLeafNodes * 4, 0, kLeafNodes * 4 * sizeof(Real));
  });
}

void p2g(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
         const MpmStepParams& prm) {
  dispatch<P2G>(prm.order, prm.transfer, space, p, g, prm);
}

template <int O, Transfer T>
struct P2GBlocks {
  static void run(const exec::Space& s, const MpmParticleView& p, const MpmGridView& g,
                  const MpmStepParams& prm, const std::uint32_t* bins, std::size_t n, Real* keep,
                  const std::function<void(std::size_t, const Real*, int)>& take) {
    if constexpr (T != Transfer::PicFlip) {
      if (p.X_ref && g.q_out)
        return p2g_blocks_impl<O, T, true, true>(s, p, g, prm, bins, n, keep, take);
    }
    if (p.X_ref)
      p2g_blocks_impl<O, T, true>(s, p, g, prm, bins, n, keep, take);
    else
      p2g_blocks_impl<O, T>(s, p, g, prm, bins, n, keep, take);
  }
};

void p2g_blocks(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                const MpmStepParams& prm, const std::uint32_t* bins, std::size_t nbins, Real* keep,
                const std::function<void(std::size_t, const Real*, int)>& take) {
  dispatch<P2GBlocks>(prm.order, prm.transfer, space, p, g, prm, bins, nbins, keep, take);
}

void clear_node4(const exec::Space& space, const MpmGridView& g, Real* out) {
  exec::parallel_for(space, "aul.positions_clear", exec::Index(g.nactive), [&](exec::Index i) {
    std::memset(out + std::size_t(g.active_leaves[i]) * kLeafNodes * 4, 0,
                kLeafNodes * 4 * sizeof(Real));
  });
}

void g2p(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
         const MpmStepParams& prm) {
  dispatch<G2P>(prm.order, prm.transfer, space, p, g, prm);
}

void g2p2g(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
           const MpmStepParams& prm, const MaterialUpdateParams* mu, Real* blocks,
           std::uint8_t* far) {
  dispatch<G2P2G>(prm.order, prm.transfer, space, p, g, prm, mu, blocks, far);
}

void g2p2g_flush(const exec::Space& space, const MpmGridView& g, int order, const Real* blocks,
                 const std::uint32_t* start, const std::uint32_t* items) {
  if (order == 3)
    sum_dilated_leaves_impl<3, 8>(space, g, blocks, start, items, "mpm.g2p2g_flush");
  else
    sum_dilated_leaves_impl<2, 8>(space, g, blocks, start, items, "mpm.g2p2g_flush");
}

void p2g_dilated(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                 const MpmStepParams& prm, Real* blocks, const std::uint32_t* start,
                 const std::uint32_t* items, const std::int32_t* target, std::uint8_t* far) {
  dispatch<P2GDilated>(prm.order, prm.transfer, space, p, g, prm, blocks, start, items, target,
                       far);
}

void g2p_dilated(const exec::Space& space, const MpmParticleView& p, const MpmGridView& g,
                 const MpmStepParams& prm, std::uint8_t* far) {
  dispatch<G2PDilated>(prm.order, prm.transfer, space, p, g, prm, far);
}

void sum_dilated_leaves(const exec::Space& space, const MpmGridView& g, int order, int ch,
                        const Real* blocks, const std::uint32_t* start,
                        const std::uint32_t* items) {
  if (order == 3)
    ch == 8 ? sum_dilated_leaves_impl<3, 8>(space, g, blocks, start, items)
            : sum_dilated_leaves_impl<3, 4>(space, g, blocks, start, items);
  else
    ch == 8 ? sum_dilated_leaves_impl<2, 8>(space, g, blocks, start, items)
            : sum_dilated_leaves_impl<2, 4>(space, g, blocks, start, items);
}

// The colliders (bit c) that may constrain a node of the leaf whose first node is node0: not those
// whose phi over the leaf's box of nodes stays above node_tolerance's largest value there
// (Collider::phi_at_least), for which Collider::project returns at once at every node. Lagrangian
// node positions (A-ULMPM) or more than 64 colliders: all of them (callers test c >= 64 first).
static std::uint64_t leaf_colliders(const MpmStepParams& prm, const Vec3i& node0, bool lagrangian,
                                    Real t) {
  if (lagrangian || prm.ncolliders > 64) return ~std::uint64_t(0);
  const Vec3 lo = node0.cast<Real>() * prm.dx;  // as the nodes' x_i = (node0 + ijk) dx
  const Vec3 hi = (node0 + Vec3i::Constant(kLeafDim - 1)).cast<Real>() * prm.dx;
  const double tol = double(node_tolerance(lo.cwiseAbs().cwiseMax(hi.cwiseAbs()), prm.dx));
  std::uint64_t m = 0;
  for (int c = 0; c < prm.ncolliders; ++c)
    if (!(prm.colliders[c].phi_at_least(lo, hi, t) > tol)) m |= std::uint64_t(1) << c;
  return m;
}

// The colliders of `near` (bit c; every c >= 64) applied to the velocity (m, v) of each node of
// a leaf with m > 0 (la: the leaf's nodes), at the node's lattice position, or at its current
// position q_i when the Lagrangian lq is given and its m > 0 (A-ULMPM eq. 12); lb, when given,
// gains each node's change of v.
static void project_leaf(const MpmStepParams& prm, Real* la, Real* lb, const Real* lq,
                         const Vec3i& node0, std::uint64_t near, Real t_end) {
  for (int i = 0; i < kLeafDim; ++i)
    for (int j = 0; j < kLeafDim; ++j)
      for (int k = 0; k < kLeafDim; ++k) {
        const int o = leaf_offset(i, j, k) * 4;
        Real* n = la + o;
        if (n[0] <= 0) continue;
        const Vec3 v0(n[1], n[2], n[3]);
        Vec3 v = v0;
        Vec3 xi = (node0 + Vec3i(i, j, k)).cast<Real>() * prm.dx;
        if (lq && lq[o] > 0) xi = Vec3(lq[o + 1], lq[o + 2], lq[o + 3]) / lq[o];
        const Real tol = node_tolerance(xi, prm.dx);
        for (int c = 0; c < prm.ncolliders; ++c)
          if (c >= 64 || (near >> c & 1)) prm.colliders[c].project(xi, t_end, v, tol);
        for (int c = 0; c < 3; ++c) {
          n[1 + c] = v[c];
          if (lb) lb[o + 1 + c] += v[c] - v0[c];
        }
      }
}

// grid_update's nodes in a leaf no collider can reach (and no node positions): each node (m, p)
// -> (m, v) with v = p / m + dt g (+ (dt / m) f with the force in b; PIC/FLIP's b -> (-, v - p / m)),
// and v = 0 (PIC/FLIP's dv = 0) where m <= 0. The same element-wise operations as the scalar loop
// in grid_update, in the same order, on whole vectors of nodes (4 floats a node: one node per SSE
// register, 2 per AVX, 4 per AVX-512: lanes::V; m broadcast within each node's 4 elements): the
// same bits on every path.
#if !defined(AMALGAM_REAL_DOUBLE)
constexpr bool kVectorFreeLeaf = true;
namespace free_leaf {
using V = lanes::V<float>;  // the path's vector: 1, 2 or 4 nodes of 4 floats
using I = lanes::Mask<float>;
constexpr int kFloats = lanes::kN<float>;
// Element 0 of each node broadcast over the node's 4 elements.
template <int... L>
inline V mass(V a, std::integer_sequence<int, L...>) {
  return __builtin_shufflevector(a, a, (L & ~3)...);
}
}  // namespace free_leaf

template <bool Force, bool Flip>
void update_free_leaf(Real* la, Real* lb, Real dt, const Vec3& dv_gravity) {
  using namespace free_leaf;
  V gv, one = lanes::splat(1.0f), dtv = lanes::splat(float(dt));
  I first;  // all bits set in element 0 of each node: m, kept as it is
  for (int k = 0; k < kFloats; ++k) {
    gv[k] = k % 4 == 0 ? 0.0f : float(dv_gravity[k % 4 - 1]);
    first[k] = k % 4 == 0 ? -1 : 0;
  }
  // element 0 from keep, elements 1-3 from v where m > 0, else +0
  auto finish = [&](V keep, V m, V v) {
    const I le = m <= V{};
    return V((I(keep) & first) | (I(v) & ~first & ~le));
  };
  for (int o = 0; o < kLeafNodes * 4; o += kFloats) {  // (GCC's element-wise vector operators)
    V a;
    std::memcpy(&a, la + o, sizeof a);
    const V m = mass(a, std::make_integer_sequence<int, kFloats>{});
    const V inv = one / m;
    const V v_old = a * inv;
    V v = v_old + gv;
    if (Force) {
      V b;
      std::memcpy(&b, lb + o, sizeof b);
      v = v + (dtv * inv) * b;
      if (Flip) {
        const V dv = finish(b, m, v - v_old);
        std::memcpy(lb + o, &dv, sizeof dv);
      }
    }
    const V out = finish(a, m, v);
    std::memcpy(la + o, &out, sizeof out);
  }
}
#else
constexpr bool kVectorFreeLeaf = false;
template <bool Force, bool Flip>
void update_free_leaf(Real*, Real*, Real, const Vec3&) {}
#endif

void grid_update(const exec::Space& space, const MpmGridView& g, const MpmStepParams& prm) {
  const bool flip = prm.transfer == Transfer::PicFlip;
  const bool force = flip || prm.split;  // b holds the force (PIC/FLIP, or the split scatter)
  const Real dt = prm.dt, dx = prm.dx;
  const Vec3 dv_gravity = dt * prm.gravity;
  const Real t_end = prm.time + prm.dt;
  exec::parallel_for(space, "mpm.grid_update", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t leaf = std::size_t(g.active_leaves[li]);
    const Vec3i node0 = g.leaf_coord[leaf] * kLeafDim;
    Real* la = g.a + leaf * kLeafNodes * 4;
    Real* lb = force ? g.b + leaf * kLeafNodes * 4 : nullptr;
    const std::uint64_t near =
        prm.ncolliders > 0 ? leaf_colliders(prm, node0, g.q != nullptr, t_end) : 0;
    // Vectors of nodes, then (MLS/APIC on lattice nodes) the colliders at the nodes they may
    // reach, as the scalar loop below applies them: to the updated v of each node with m > 0.
    // PIC/FLIP keeps dv = v - v_old of the projected v, so its leaves near a collider stay scalar.
    if (kVectorFreeLeaf && (!near || (!flip && !g.q))) {
      if (flip)
        update_free_leaf<true, true>(la, lb, dt, dv_gravity);
      else if (force)
        update_free_leaf<true, false>(la, lb, dt, dv_gravity);
      else
        update_free_leaf<false, false>(la, lb, dt, dv_gravity);
      if (near) project_leaf(prm, la, nullptr, nullptr, node0, near, t_end);
      return;
    }
    for (int i = 0; i < kLeafDim; ++i)
      for (int j = 0; j < kLeafDim; ++j)
        for (int k = 0; k < kLeafDim; ++k) {
          const int o = leaf_offset(i, j, k) * 4;
          Real* n = la + o;
          const Real m = n[0];
          if (m <= 0) {
            n[1] = n[2] = n[3] = 0;
            if (flip) lb[o + 1] = lb[o + 2] = lb[o + 3] = 0;
            continue;
          }
          const Real inv_m = Real(1) / m;
          const Vec3 v_old(n[1] * inv_m, n[2] * inv_m, n[3] * inv_m);
          Vec3 v = v_old + dv_gravity;
          if (force) v += (dt * inv_m) * Vec3(lb[o + 1], lb[o + 2], lb[o + 3]);
          if (near) {
            Vec3 xi = (node0 + Vec3i(i, j, k)).cast<Real>() * dx;
            if (g.q) {  // Lagrangian: the node's current position q_i (A-ULMPM eq. 12)
              const Real* qn = g.q + leaf * kLeafNodes * 4 + o;
              if (qn[0] > 0) xi = Vec3(qn[1], qn[2], qn[3]) / qn[0];
            }
            const Real tol = node_tolerance(xi, dx);
            for (int c = 0; c < prm.ncolliders; ++c)
              if (c >= 64 || (near >> c & 1)) prm.colliders[c].project(xi, t_end, v, tol);
          }
          n[1] = v[0];
          n[2] = v[1];
          n[3] = v[2];
          if (flip) {
            lb[o + 1] = v[0] - v_old[0];
            lb[o + 2] = v[1] - v_old[1];
            lb[o + 3] = v[2] - v_old[2];
          }
        }
  });
}

void grid_apply_colliders(const exec::Space& space, const MpmGridView& g,
                          const MpmStepParams& prm) {
  if (prm.ncolliders == 0) return;
  const Real t_end = prm.time + prm.dt;
  exec::parallel_for(space, "mpm.grid_colliders", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t leaf = std::size_t(g.active_leaves[li]);
    const Vec3i node0 = g.leaf_coord[leaf] * kLeafDim;
    project_leaf(prm, g.a + leaf * kLeafNodes * 4, g.b ? g.b + leaf * kLeafNodes * 4 : nullptr,
                 g.q ? g.q + leaf * kLeafNodes * 4 : nullptr, node0,
                 leaf_colliders(prm, node0, g.q != nullptr, t_end), t_end);
  });
}

extern const MpmKernelTable mpm_kernels;
const MpmKernelTable mpm_kernels = {
    &grid_clear, &p2g,   &clear_node4, &p2g_positions, &grid_update, &grid_apply_colliders, &g2p,
    &p2g_blocks, &g2p2g, &g2p2g_flush, &p2g_dilated,   &g2p_dilated, &sum_dilated_leaves};

}  // namespace AMALGAM_ISA

// Layout helpers of distributed P2G: plain copies, the same on every instruction set (one copy,
// outside the per-ISA namespace).
int block_part_nodes(int order, int t) {
  return ((t >> 2) & 1 ? order : kLeafDim) * ((t >> 1) & 1 ? order : kLeafDim) *
         (t & 1 ? order : kLeafDim);
}

int p2g_channels(Transfer t, bool fused_positions) {
  return t == Transfer::PicFlip || fused_positions ? 8 : 4;
}

std::size_t g2p2g_block_reals(int order) {
  const std::size_t B = std::size_t(kLeafDim + order + 2 * kG2P2GMargin);
  return B * B * B * 8;
}

std::size_t dilated_block_reals(int order, int ch) {
  const std::size_t B = std::size_t(kLeafDim + order + 2 * kG2P2GMargin);
  return B * B * B * std::size_t(ch);
}

std::size_t p2g_block_reals(int order, int ch) {
  const std::size_t B = std::size_t(kLeafDim + order);
  return B * B * B * std::size_t(ch);
}

void dilated_part_range(int order, int t, int* n0, int* n1) {
  const int B = kLeafDim + order + 2 * kG2P2GMargin;
  const int d[3] = {t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1};
  for (int a = 0; a < 3; ++a) {  // as sum_dilated_leaf
    n0[a] = std::max(0, -d[a] * kLeafDim - kG2P2GMargin);
    n1[a] = std::min(kLeafDim, B - d[a] * kLeafDim - kG2P2GMargin);
  }
}

int dilated_part_nodes(int order, int t) {
  int n0[3], n1[3];
  dilated_part_range(order, t, n0, n1);
  return (n1[0] - n0[0]) * (n1[1] - n0[1]) * (n1[2] - n0[2]);
}

void copy_dilated_part(Real* block, int order, int ch, int t, Real* part, bool to_block) {
  const int B = kLeafDim + order + 2 * kG2P2GMargin, M = kG2P2GMargin;
  const int d[3] = {t / 9 - 1, t / 3 % 3 - 1, t % 3 - 1};
  int n0[3], n1[3];
  dilated_part_range(order, t, n0, n1);
  const std::size_t bytes = std::size_t(ch) * sizeof(Real);
  for (int i = n0[0]; i < n1[0]; ++i)
    for (int j = n0[1]; j < n1[1]; ++j)
      for (int k = n0[2]; k < n1[2]; ++k, part += ch) {
        Real* b = block + (((d[0] * kLeafDim + i + M) * B + d[1] * kLeafDim + j + M) * B +
                           d[2] * kLeafDim + k + M) *
                              ch;
        if (to_block)
          std::memcpy(b, part, bytes);
        else
          std::memcpy(part, b, bytes);
      }
}

void copy_block_part(const Real* block, int order, int ch, int t, Real* out) {
  const int B = kLeafDim + order, tx = (t >> 2) & 1, ty = (t >> 1) & 1, tz = t & 1;
  const int ni = tx ? order : kLeafDim, nj = ty ? order : kLeafDim, nk = tz ? order : kLeafDim;
  for (int i = 0; i < ni; ++i)
    for (int j = 0; j < nj; ++j)
      for (int k = 0; k < nk; ++k, out += ch) {
        const int at = (((tx * kLeafDim + i) * B + ty * kLeafDim + j) * B + tz * kLeafDim + k) * ch;
        std::memcpy(out, block + at, std::size_t(ch) * sizeof(Real));
      }
}

}  // namespace amalgam
