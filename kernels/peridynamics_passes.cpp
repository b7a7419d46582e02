// The peridynamic bond passes (pd_dilatation, pd_forces with the fused fracture and damage,
// pd_damage), compiled once per instruction set (core/exec/simd.hpp; kernels/CMakeLists.txt,
// amalgam_simd_variants): the block loops over a row's bonds run 4 (baseline), 8 (AVX2) or 16
// (AVX-512) float lanes wide. Every operation is element-wise IEEE arithmetic (no contraction, no
// reassociation) and the row sums run in the kSumLanes logical lanes of PdBonds::lane on every
// path, so the results are bitwise the same on every path (tests/test_peridynamics.cpp,
// PdSimdPaths). The public functions are in kernels/peridynamics_dispatch.cpp.
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstring>
#include <limits>
#include <new>
#include <type_traits>

#include "core/exec/simd.hpp"
#include "kernels/peridynamics.hpp"

#if defined(__SSE2__)
#include <immintrin.h>
#endif

namespace amalgam {
namespace AMALGAM_ISA {
namespace {

// Bond blocks (the force pass below and the dilatation pass): a row is processed in blocks; a
// scalar loop gathers what the neighbour j indexes (positions, its constants) into local arrays,
// a branch-free loop over the block, reading the per-bond arrays in place, is vectorised by the
// compiler (sqrt and division included: IEEE-exact in SIMD), then sums run over the row in lanes
// (PdBonds::lane), each lane in bond order. Broken bonds add exact zeros (x + 0 = x, and +0 + -0 =
// +0 from the +0 start), so every lane sum equals the one that skips them: results do not depend
// on the backend, the thread count or whether broken bonds were compacted away.
constexpr int kBlock = 64;      // force pass
constexpr int kDilBlock = 256;  // dilatation pass: a whole row of up to 256 bonds (delta < 3.9 lc)
                                // stays in one block for the plastic return
static_assert(kBlock % kSumLanes == 0 && kDilBlock % kSumLanes == 0, "blocks start on lane 0");

// Gathers per neighbour: the first Q 16-byte quads of per-particle records, every quad of a
// record loaded from one address (one index load and one address per neighbour for all Q quads).
// out[q][c][m] = rec(idx[m]).quad[q][c] - sub[q][c] for m < n (records `stride` bytes apart,
// 16-byte aligned; nothing subtracted from the last quad when `LastRaw`). Vector code loads the
// quads of W = 4 (SSE), 8 (AVX) or 16 (AVX-512) neighbours into four registers, register r
// holding neighbours r, r + 4, r + 8, r + 12 in its 128-bit lanes, subtracts, and transposes
// within the 128-bit lanes (8 shuffles), which leaves component c of the W neighbours in order in
// one register: for 4 x W values, W loads (3 of 4 of them inserts on AVX-512), 4 subtractions, 8
// shuffles and 4 stores, against 4 W scalar loads and stores. Only data movement and the same
// element-wise subtraction: bitwise the scalar loop's values on every path.
#if defined(__SSE2__) && !defined(AMALGAM_REAL_DOUBLE)
namespace detail {
// One register width: kW neighbours per group; load(r, k, q) is quad q of neighbours k, k + 4, ...
// in the 128-bit lanes.
struct Sse {
  using V = __m128;
  static constexpr int kW = 4;
  static V broadcast(const float* s) { return _mm_loadu_ps(s); }
  static V load(const float* const* r, int k, int q) { return _mm_load_ps(r[k] + 4 * q); }
  static V sub(V a, V b) { return _mm_sub_ps(a, b); }
  static V lo(V a, V b) { return _mm_unpacklo_ps(a, b); }
  static V hi(V a, V b) { return _mm_unpackhi_ps(a, b); }
  template <int Imm>
  static V shuffle(V a, V b) {
    return _mm_shuffle_ps(a, b, Imm);
  }
  static void store(float* p, V v) { _mm_storeu_ps(p, v); }
};
#if defined(__AVX__)
struct Avx {
  using V = __m256;
  static constexpr int kW = 8;
  static V broadcast(const float* s) {
    return _mm256_broadcast_ps(reinterpret_cast<const __m128*>(s));
  }
  static V load(const float* const* r, int k, int q) {
    return _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_load_ps(r[k] + 4 * q)),
                                _mm_load_ps(r[k + 4] + 4 * q), 1);
  }
  static V sub(V a, V b) { return _mm256_sub_ps(a, b); }
  static V lo(V a, V b) { return _mm256_unpacklo_ps(a, b); }
  static V hi(V a, V b) { return _mm256_unpackhi_ps(a, b); }
  template <int Imm>
  static V shuffle(V a, V b) {
    return _mm256_shuffle_ps(a, b, Imm);
  }
  static void store(float* p, V v) { _mm256_storeu_ps(p, v); }
};
#endif
#if defined(__AVX512F__)
struct Avx512 {
  using V = __m512;
  static constexpr int kW = 16;
  static V broadcast(const float* s) { return _mm512_broadcast_f32x4(_mm_loadu_ps(s)); }
  static V load(const float* const* r, int k, int q) {
    V v = _mm512_castps128_ps512(_mm_load_ps(r[k] + 4 * q));
    v = _mm512_insertf32x4(v, _mm_load_ps(r[k + 4] + 4 * q), 1);
    v = _mm512_insertf32x4(v, _mm_load_ps(r[k + 8] + 4 * q), 2);
    return _mm512_insertf32x4(v, _mm_load_ps(r[k + 12] + 4 * q), 3);
  }
  static V sub(V a, V b) { return _mm512_sub_ps(a, b); }
  static V lo(V a, V b) { return _mm512_unpacklo_ps(a, b); }
  static V hi(V a, V b) { return _mm512_unpackhi_ps(a, b); }
  template <int Imm>
  static V shuffle(V a, V b) {
    return _mm512_shuffle_ps(a, b, Imm);
  }
  static void store(float* p, V v) { _mm512_storeu_ps(p, v); }
};
#endif
// Groups of R::kW neighbours from position m while they fit in n; returns the new m (outputs at
// m0 + m). The in-lane 4 x 4 transpose is _MM_TRANSPOSE4_PS's.
template <class R, int Q, bool LastRaw>
inline int gather_groups(const char* base, std::size_t stride, const std::uint32_t* idx, int n,
                         const Real (*sub)[4], Real* const (*out)[4], int m0, int m) {
  using V = typename R::V;
  V sv[Q];
  for (int q = 0; q < Q; ++q) sv[q] = R::broadcast(sub[q]);
  for (; m + R::kW <= n; m += R::kW) {
    const float* r[R::kW];
    for (int k = 0; k < R::kW; ++k)
      r[k] = reinterpret_cast<const float*>(base + std::size_t(idx[m + k]) * stride);
    for (int q = 0; q < Q; ++q) {
      V a = R::load(r, 0, q), b = R::load(r, 1, q), c = R::load(r, 2, q), d = R::load(r, 3, q);
      if (!(LastRaw && q == Q - 1))
        a = R::sub(a, sv[q]), b = R::sub(b, sv[q]), c = R::sub(c, sv[q]), d = R::sub(d, sv[q]);
      const V t0 = R::lo(a, b), t1 = R::lo(c, d), t2 = R::hi(a, b), t3 = R::hi(c, d);
      R::store(out[q][0] + m0 + m, R::template shuffle<0x44>(t0, t1));
      R::store(out[q][1] + m0 + m, R::template shuffle<0xee>(t0, t1));
      R::store(out[q][2] + m0 + m, R::template shuffle<0x44>(t2, t3));
      R::store(out[q][3] + m0 + m, R::template shuffle<0xee>(t2, t3));
    }
  }
  return m;
}
}  // namespace detail
#endif

// The block loops run over n_pad = padded(n) bonds, a multiple of the path's float vector (4, 8,
// 16 lanes), so that GCC vectorises them one vector per iteration with no remainder loop. The pad
// bonds' neighbour is the particle itself: the gathered eta and xi are exactly 0, so they are dead
// bonds (l2 = 0) whose terms are never summed (the sums and write-backs stop at n): the padding
// changes no result, whatever its length.
#if defined(__AVX512F__)
constexpr int kPad = 16;
#elif defined(__AVX__)
constexpr int kPad = 8;
#else
constexpr int kPad = 4;
#endif
inline int padded(int n) {
  return (n + kPad - 1) / kPad * kPad;
}
static_assert(kBlock % kPad == 0 && kDilBlock % kPad == 0, "padded blocks fit");

// out[.][.][m] for m < n_pad (see padded): idx[m] for m < n, `self` after.
template <int Q, bool LastRaw>
void gather_records(const void* records, std::size_t stride, const std::uint32_t* idx, int n,
                    int n_pad, std::uint32_t self, const Real (*sub)[4], Real* const (*out)[4]) {
  const char* base = static_cast<const char*>(records);
  int m = 0;
#if defined(__SSE2__) && !defined(AMALGAM_REAL_DOUBLE)
  auto groups = [&](const std::uint32_t* ix, int count, int m0) {
    int g = 0;
#if defined(__AVX512F__)
    g = detail::gather_groups<detail::Avx512, Q, LastRaw>(base, stride, ix, count, sub, out, m0, g);
#endif
#if defined(__AVX__)
    g = detail::gather_groups<detail::Avx, Q, LastRaw>(base, stride, ix, count, sub, out, m0, g);
#endif
    return detail::gather_groups<detail::Sse, Q, LastRaw>(base, stride, ix, count, sub, out, m0, g);
  };
  m = groups(idx, n, 0);
  if (m < n_pad) {  // the rest (a multiple of 4: m is, n_pad is) from a padded copy of idx
    std::uint32_t tail[kPad + 4];
    const int count = n_pad - m;
    for (int k = 0; k < count; ++k) tail[k] = m + k < n ? idx[m + k] : self;
    m += groups(tail, count, m);
  }
#endif
  for (; m < n_pad; ++m) {
    const Real* r =
        reinterpret_cast<const Real*>(base + std::size_t(m < n ? idx[m] : self) * stride);
    for (int q = 0; q < Q; ++q)
      for (int c = 0; c < 4; ++c)
        out[q][c][m] = (LastRaw && q == Q - 1) ? r[4 * q + c] : r[4 * q + c] - sub[q][c];
  }
}

// live[m] = intact[m] (0 or 1) as a Real, for m < n_pad: the block loops then hold no bytes, so
// GCC vectorises them at one float vector per iteration (bytes made it take 64 lanes at once on
// AVX-512, leaving up to 63 bonds of a row to a narrower loop and a scalar one). Zero-extended
// and converted with intrinsics (GCC's __builtin_convertvector of 8 bytes took 33 instructions).
inline void live_lanes(const std::uint8_t* intact, int n_pad, Real* live) {
  int m = 0;
#if !defined(AMALGAM_REAL_DOUBLE)
#if defined(__AVX512F__)
  for (; m + 16 <= n_pad; m += 16)
    _mm512_storeu_ps(live + m, _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(
                                   _mm_loadu_si128(reinterpret_cast<const __m128i*>(intact + m)))));
#elif defined(__AVX2__)
  for (; m + 8 <= n_pad; m += 8)
    _mm256_storeu_ps(live + m, _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(
                                   _mm_loadl_epi64(reinterpret_cast<const __m128i*>(intact + m)))));
#elif defined(__SSE2__)
  const __m128i zero = _mm_setzero_si128();
  for (; m + 4 <= n_pad; m += 4) {
    std::int32_t w;
    std::memcpy(&w, intact + m, 4);
    const __m128i b = _mm_cvtsi32_si128(w);
    _mm_storeu_ps(live + m, _mm_cvtepi32_ps(_mm_unpacklo_epi16(_mm_unpacklo_epi8(b, zero), zero)));
  }
#endif
#endif
  for (; m < n_pad; ++m) live[m] = Real(intact[m]);
}

// The block loops read the per-bond arrays in place up to the padded end of a block, which runs
// into the next row; only the list's last block can run past the arrays' end, and it reads
// padded copies instead (lengths and weights 1, intact 0: finite, dead).
struct TailCopy {
  static constexpr int kArrays = 8;
  alignas(64) Real v[kArrays][kDilBlock];
  alignas(64) std::uint8_t live[kDilBlock];
  int used = 0;
  const Real* copy(const Real* src, int n) {
    Real* d = v[used++];
    std::copy(src, src + n, d);
    std::fill(d + n, d + padded(n), Real(1));
    return d;
  }
  const std::uint8_t* copy(const std::uint8_t* src, int n) {
    std::copy(src, src + n, live);
    std::fill(live + n, live + padded(n), std::uint8_t(0));
    return live;
  }
};
inline bool past_end(const PdBonds& bonds, std::uint64_t kb, int n) {
  return kb + std::uint64_t(padded(n)) > bonds.size();
}

// Lane sums (PdBonds::lane): acc[lane] += t[m] over a block of n terms, in bond order within each
// lane. Dense rows: lane = position mod kSumLanes (blocks start at multiples of kSumLanes), 8
// independent chains the compiler vectorises. Compacted rows: the stored lanes (scalar).
// always_inline: GCC left them out of line, a call per block and force component (inlined: the
// step 1.07x faster, docs/benchmarks.md "The peridynamic force pass").
__attribute__((always_inline)) inline void lane_sum(const Real* t, int n, Real* acc) {
  int m = 0;
  for (; m + kSumLanes <= n; m += kSumLanes)
    for (int l = 0; l < kSumLanes; ++l) acc[l] += t[m + l];
  for (int l = 0; m + l < n; ++l) acc[l] += t[m + l];
}
inline void lane_sum(const Real* t, const std::uint8_t* lane, int n, Real* acc) {
  for (int m = 0; m < n; ++m) acc[lane[m]] += t[m];
}
__attribute__((always_inline)) inline void lane_sum(const Real* t, const std::uint8_t* lane,
                                                    bool dense, int n, Real* acc) {
  if (dense)
    lane_sum(t, n, acc);
  else
    lane_sum(t, lane, n, acc);
}
// The lanes combined in a fixed order.
inline Real lane_total(const Real* a) {
  static_assert(kSumLanes == 8, "lane_total combines 8 lanes");
  return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]));
}

// The displacement u = (x - x0) + x_lo the bond passes read: eta = xi + (u_j - u_i) keeps the
// increments that x alone rounds away far from the origin (x - x0 is exact while x is within a
// factor 2 of x0, and xi = x0_j - x0_i is exact between neighbours).
inline Vec3 displacement(const PdView& p, std::size_t i) {
  const Vec3 u = p.x[i] - p.x0[i];
  return p.x_lo ? Vec3(u + p.x_lo[i]) : u;
}

// What the dilatation pass gathers per neighbour.
struct alignas(16) PosRec {
  Real y[4];   // displacement u, 0
  Real x0[4];  // reference position, 0
};

// Gathered per block: the neighbour's current and reference position; the per-bond arrays are
// read in place (DilSlice).
struct DilBlock {
  alignas(64) Real ex[kDilBlock], ey[kDilBlock], ez[kDilBlock];     // u_j - u_i (eta - xi)
  alignas(64) Real xx[kDilBlock], xy[kDilBlock], xz[kDilBlock];     // xi = x0_j - x0_i
  alignas(64) Real pad[kDilBlock];                                  // the gathers' unused lane
  alignas(64) Real live[kDilBlock];                                 // intact (live_lanes)
  alignas(64) Real e[kDilBlock], lambda[kDilBlock], ok[kDilBlock];  // geometry (0 for dead bonds)
  alignas(64) Real t[kDilBlock], w1[kDilBlock], w2[kDilBlock], w3[kDilBlock];  // terms of the sums
  alignas(64) Real ep_new[kDilBlock];                                          // plastic return
};
struct DilSlice {
  const Real *L, *omega, *shear, *vol, *ep;
  const std::uint8_t* live;
};

void gather_dilatation(const PosRec* recs, const PdBonds& bonds, std::uint64_t kb, int n,
                       std::uint32_t self, const Real sub_y[4], const Real sub_x0[4], DilBlock& B) {
  const Real sub[2][4] = {{sub_y[0], sub_y[1], sub_y[2], sub_y[3]},
                          {sub_x0[0], sub_x0[1], sub_x0[2], sub_x0[3]}};
  Real* const out[2][4] = {{B.ex, B.ey, B.ez, B.pad}, {B.xx, B.xy, B.xz, B.pad}};
  gather_records<2, false>(recs, sizeof(PosRec), bonds.neighbor.data() + kb, n, padded(n), self,
                           sub, out);
}

// e, Lambda (eqs. 3, 6) and the terms of theta (eq. 5) and of the consistent sums (see header):
// w = shear_omega V d with d = kappa Lambda (paper) or L / 3 (LPS).
template <bool Paper, bool Plastic, bool Lps>
void dilatation_block(DilBlock& B, const DilSlice& S, int n, Real kappa) {
  const int n_pad = padded(n);
  live_lanes(S.live, n_pad, B.live);
  for (int m = 0; m < n_pad; ++m) {  // vectorised
    const Real ex = B.xx[m] + B.ex[m], ey = B.xy[m] + B.ey[m], ez = B.xz[m] + B.ez[m];  // eta
    const Real l2 = ex * ex + ey * ey + ez * ez;
    const bool ok = (l2 > 0) & (B.live[m] != 0);  // coincident particles: no direction
    const Real l = std::sqrt(ok ? l2 : Real(1));
    const Real L = S.L[m];
    const Real live = ok ? Real(1) : Real(0);  // times 0, not a select (see force_block)
    const Real e = live * (l - L);
    const Real lambda = live * ((ex * B.xx[m] + ey * B.xy[m] + ez * B.xz[m]) / (l * L));
    B.e[m] = e, B.lambda[m] = lambda, B.ok[m] = live;
    // omega s Lambda |xi| V (eq. 5), s = e / |xi|; PdModel::Lps: omega |xi| e V (Silling et al.
    // 2007 eq. 4.3)
    B.t[m] = S.omega[m] * e * (Lps ? L : lambda) * S.vol[m];
    const Real d = Paper ? kappa * lambda : L / Real(3);
    const Real w = live * (S.shear[m] * S.vol[m] * d);
    B.w1[m] = w * e, B.w2[m] = w * d;
    if (Plastic) B.w3[m] = w * S.ep[m];  // else every ep = 0: the sum s3 is +0
  }
}

// The plastic return (eqs. 11-15) of every live bond of the block: B.ep_new the new plastic
// extension, B.t the term of Q (see header). (Not in place: a conditional store would stop the
// vectorisation.)
template <bool Paper>
void plastic_block(DilBlock& B, const DilSlice& S, int n, Real theta, Real kappa, Real stiff_i,
                   Real psi0, Real ac, Real cap_ratio) {
  for (int m = 0, n_pad = padded(n); m < n_pad; ++m) {  // vectorised
    const Real e = B.e[m], lambda = B.lambda[m], L = S.L[m];
    const Real ed = Paper ? e - kappa * lambda * theta : e - theta * L / Real(3);  // eq. 8 / LPS
    const Real stiff = stiff_i * S.shear[m];                                       // 4 omega b
    const Real ep = S.ep[m];
    const Real adev = stiff * (ed - ep);                         // eq. 11
    const bool yield = Real(0.5) * adev * adev > psi0;           // eq. 12
    const Real flow = (adev - std::copysign(ac, adev)) / stiff;  // eqs. 13-14 (exact return)
    const Real ep1 = yield ? ep + flow : ep;
    const Real cap = cap_ratio * L;  // eq. 15
    const Real ep2 = std::copysign(std::min(std::abs(ep1), cap), ep1);
    const bool ok = B.ok[m] != 0;
    B.ep_new[m] = ok ? ep2 : ep;
    B.t[m] =
        B.ok[m] * (S.shear[m] * (ed - ep2) * (Paper ? kappa * lambda : L / Real(3)) * S.vol[m]);
  }
}

// fn(std::true_type{}) or fn(std::false_type{}): a run-time flag as a template argument.
template <class Fn>
void with_flag(bool flag, Fn&& fn) {
  if (flag)
    fn(std::true_type{});
  else
    fn(std::false_type{});
}

// fn(paper, lps) with the model's form as template arguments: the paper's deviatoric extension
// (Paper), the dilatation along |xi| instead of Lambda (Lps: PdModel::Lps, whose deviatoric
// extension is always LPS's). Three combinations, so three instantiations, not four.
template <class Fn>
void with_form(const PdParams& prm, Fn&& fn) {
  if (prm.model == PdModel::Lps)
    fn(std::false_type{}, std::true_type{});
  else if (prm.deviatoric == PdDeviatoric::Paper)
    fn(std::true_type{}, std::false_type{});
  else
    fn(std::false_type{}, std::false_type{});
}

// n records of type Rec in the caller's scratch (reused, not zeroed: every record is written
// before it is read), or in `local` when there is none.
template <class Rec>
Rec* scratch_records(PdScratch* scratch, std::vector<Real>& local, std::size_t n) {
  static_assert(sizeof(Rec) % sizeof(Real) == 0 && alignof(Rec) <= __STDCPP_DEFAULT_NEW_ALIGNMENT__,
                "Real storage");
  std::vector<Real>& v = scratch ? scratch->records : local;
  const std::size_t need = n * (sizeof(Rec) / sizeof(Real));
  if (v.size() < need) v.resize(need);
  return reinterpret_cast<Rec*>(v.data());
}

}  // namespace

void pd_dilatation(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
                   PdScratch* scratch) {
  const bool consistent = prm.consistent;
  std::vector<Real> local;
  PosRec* const recs = scratch_records<PosRec>(scratch, local, p.n);
  exec::parallel_for(space, "pd.dilatation_rows", exec::Index(p.n), [&](exec::Index i) {
    const Vec3 u = displacement(p, std::size_t(i));
    ::new (static_cast<void*>(recs + i))
        PosRec{{u[0], u[1], u[2], 0}, {p.x0[i][0], p.x0[i][1], p.x0[i][2], 0}};
  });
  auto kernel = [&](auto paper_c, auto plastic_c, auto lps_c) {
    constexpr bool Paper = decltype(paper_c)::value, Plastic = decltype(plastic_c)::value;
    constexpr bool Lps = decltype(lps_c)::value;
    exec::parallel_for(space, "pd.dilatation", exec::Index(p.n), [&](exec::Index ii) {
      const std::size_t i = std::size_t(ii);
      const std::uint64_t k0 = bonds.offsets[i], k1 = bonds.offsets[i + 1];
      const Real sub_y[4] = {recs[i].y[0], recs[i].y[1], recs[i].y[2], 0};
      const Real sub_x0[4] = {p.x0[i][0], p.x0[i][1], p.x0[i][2], 0};
      const Real kap = p.kappa[i];
      const bool one_block = k1 - k0 <= std::uint64_t(kDilBlock);
      DilBlock B;
      TailCopy tail;
      auto slice = [&](std::uint64_t kb, int n) {
        DilSlice S{bonds.length.data() + kb,      bonds.omega.data() + kb,
                   bonds.shear_omega.data() + kb, bonds.volume.data() + kb,
                   bonds.plastic.data() + kb,     bonds.intact.data() + kb};
        if (past_end(bonds, kb, n)) {
          tail.used = 0;
          S = DilSlice{tail.copy(S.L, n),   tail.copy(S.omega, n), tail.copy(S.shear, n),
                       tail.copy(S.vol, n), tail.copy(S.ep, n),    tail.copy(S.live, n)};
        }
        return S;
      };
      auto load = [&](std::uint64_t kb) {
        const int n = int(std::min<std::uint64_t>(kDilBlock, k1 - kb));
        gather_dilatation(recs, bonds, kb, n, std::uint32_t(i), sub_y, sub_x0, B);
        dilatation_block<Paper, Plastic, Lps>(B, slice(kb, n), n, kap);
        return n;
      };
      const PdMaterial& mat = prm.materials[p.material[i]];
      const bool plastic = Plastic && mat.psi0 < std::numeric_limits<Real>::infinity();
      // s1..s3: the consistent term's sums (see header); a plastic particle's q comes from the
      // plastic return below instead.
      const bool sums = consistent && !plastic;
      const bool dense = bonds.dense[i] != 0;
      alignas(32) Real a0[kSumLanes] = {}, a1[kSumLanes] = {}, a2[kSumLanes] = {},
                       a3[kSumLanes] = {};
      for (std::uint64_t kb = k0; kb < k1; kb += kDilBlock) {
        const int n = load(kb);
        const std::uint8_t* lane = bonds.lane.data() + kb;
        lane_sum(B.t, lane, dense, n, a0);
        if (sums) lane_sum(B.w1, lane, dense, n, a1), lane_sum(B.w2, lane, dense, n, a2);
        if (sums && Plastic) lane_sum(B.w3, lane, dense, n, a3);
      }
      const Real sum = lane_total(a0), s1 = lane_total(a1), s2 = lane_total(a2),
                 s3 = lane_total(a3);
      const Real theta = Real(3) * sum / p.m[i];
      p.theta[i] = theta;
      const Real qscale = p.b[i] * Real(3) / p.m[i];
      if (sums) p.q[i] = qscale * (s1 - theta * s2 - s3);
      if (!plastic) return;
      Real Q = 0;
      const Real ac = std::sqrt(Real(2) * mat.psi0);
      for (std::uint64_t kb = k0; kb < k1; kb += kDilBlock) {
        const int n = one_block ? int(k1 - k0) : load(kb);  // one block: still loaded
        plastic_block<Paper>(B, slice(kb, n), n, theta, kap, Real(4) * p.b[i], mat.psi0, ac,
                             mat.plastic_cap);
        for (int m = 0; m < n; ++m) {
          const std::uint64_t k = kb + std::uint64_t(m);
          if (B.ep_new[m] !=
              bonds.plastic[k]) {  // yielded: row j's force pass reads it from plastic_r
            bonds.plastic[k] = B.ep_new[m];
            // (kNoReverse: row j is another rank's, which receives it by its bond halo)
            if (bonds.reverse[k] != kNoReverse) bonds.plastic_r[bonds.reverse[k]] = B.ep_new[m];
          }
          Q += B.t[m];
        }
      }
      if (consistent) p.q[i] = qscale * Q;  // with the returned plastic extensions
    });
  };
  with_form(prm, [&](auto paper_c, auto lps_c) {
    with_flag(prm.plastic, [&](auto plastic_c) { kernel(paper_c, plastic_c, lps_c); });
  });
}

namespace {

// The force pass: blocks of kBlock bonds (see the bond blocks above).

// Gathered per block: only what is indexed by the neighbour j (the per-bond arrays are read in
// place, contiguous from the block's first bond).
struct ForceBlock {
  alignas(64) Real ex[kBlock], ey[kBlock], ez[kBlock];  // u_j - u_i (eta - xi)
  alignas(64) Real xx[kBlock], xy[kBlock], xz[kBlock];  // xi = x0_j - x0_i
  alignas(64) Real dil_j[kBlock], b_j[kBlock], c_j[kBlock], crit_j[kBlock];
  alignas(64) Real pad0[kBlock], pad1[kBlock];  // the gathers' unused lanes
  alignas(64) Real fx[kBlock], fy[kBlock],
      fz[kBlock];                           // out: pair force density (0 for dead bonds)
  alignas(64) Real live[kBlock];            // intact (live_lanes)
  alignas(64) std::int32_t broken[kBlock];  // out: eq. 18 holds (fracture)
};

// Per particle i: the terms of A_ij that depend on i only.
struct ForceRow {
  Real dil, b, c,
      crit;  // a theta - q; b; ed = e - c g (g = Lambda: paper, L: LPS); critical stretch
};

// What the force pass gathers per neighbour, in three 16-byte quads (gather_records).
struct alignas(16) ForceRec {
  Real y[4];   // displacement u (see displacement()), a theta - q
  Real x0[4];  // reference position, b
  Real cc[4];  // c, critical stretch, 0, 0
};

// The block's bonds k = kb .. kb + n - 1 of particle i (arrays offset by kb).
struct BondSlice {
  const Real *L, *omega, *shear, *vol, *epi, *omega_r, *shear_r, *epj;
  const std::uint8_t* live;
};

template <bool Paper, bool Fracture, bool Plastic, bool Lps>
void force_block(ForceBlock& B, const BondSlice& S, int n, const ForceRow& r, Real delta,
                 bool classical) {
  const int n_pad = padded(n);
  live_lanes(S.live, n_pad, B.live);
  for (int m = 0; m < n_pad; ++m) {  // vectorised: no branches, no gathers
    const Real epi = Plastic ? S.epi[m] : Real(0), epj = Plastic ? S.epj[m] : Real(0);
    const Real ex = B.xx[m] + B.ex[m], ey = B.xy[m] + B.ey[m], ez = B.xz[m] + B.ez[m];  // eta
    const Real l2 = ex * ex + ey * ey + ez * ez;
    const bool ok = (l2 > 0) & (B.live[m] != 0);  // coincident particles: no direction, no force
    const Real l = std::sqrt(ok ? l2 : Real(1));
    const Real L = S.L[m];
    const Real inv = Real(1) / (l * L);  // r = 1 / (l L): 1 / l = r L, Lambda = (eta . xi) r
    const Real e = l - L;
    const Real lambda = (ex * B.xx[m] + ey * B.xy[m] + ez * B.xz[m]) * inv;
    const Real g = Paper ? lambda : L;
    const Real gd = Lps ? L : lambda;  // the dilatational term's direction factor
    // eqs. 3, 7, 11 from each end of the bond (PdModel::Lps: 2 t_ij of Silling et al. 2007 eq. 4.5)
    const Real aij = Real(4) * (S.omega[m] * gd * r.dil + S.shear[m] * r.b * (e - r.c * g - epi));
    const Real aji = Real(4) * (S.omega_r[m] * gd * B.dil_j[m] +
                                S.shear_r[m] * B.b_j[m] * (e - B.c_j[m] * g - epj));
    // Dead bonds: times 0 (not a select, which would make the per-bond loads conditional and stop
    // the vectorisation); their operands are finite (l = 1 stands in when l2 = 0).
    const Real live = ok ? Real(1) : Real(0);
    const Real c =
        live * (Real(0.5) * (aij + aji) * S.vol[m] * (inv * L));  // eq. 1 with eq. 2, / l
    B.fx[m] = c * ex, B.fy[m] = c * ey, B.fz[m] = c * ez;
    if (Fracture) {  // eq. 18 (or the classical bond stretch), from both ends: symmetric
      const Real d = classical ? L : delta;
      B.broken[m] = ok & (((e - epi) / d > r.crit) | ((e - epj) / d > B.crit_j[m]));
    }
  }
}

// phi_i = 1 - n_i / N_i (eq. 18's damage) of row i; returns n_i.
inline std::uint64_t row_damage(const PdView& p, const PdBonds& bonds, std::size_t i) {
  std::int32_t c = 0;
  for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k) c += bonds.intact[k];
  p.damage[i] = p.bonds0[i] > 0 ? Real(1) - Real(c) / Real(p.bonds0[i]) : Real(0);
  return std::uint64_t(c);
}

}  // namespace

void pd_forces(const exec::Space& space, const PdView& p, PdBonds& bonds, const PdParams& prm,
               bool fracture, Vec3* force, Mat3* stress, PdScratch* scratch,
               std::uint64_t* intact) {
  const Real delta = prm.horizon;
  const bool paper = prm.model == PdModel::Paper && prm.deviatoric == PdDeviatoric::Paper;
  const bool classical = prm.criterion == PdCriterion::Classical;
  const PdMaterial* mats = prm.materials;
  const bool consistent = prm.consistent;
  // Per particle: the far end's terms and positions, gathered once per bond below (and a row's
  // own terms read back from its record).
  std::vector<Real> local;
  ForceRec* const recs = scratch_records<ForceRec>(scratch, local, p.n);
  exec::parallel_for(space, "pd.forces_rows", exec::Index(p.n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    const PdMaterial& mi = mats[p.material[i]];
    const Real ti = p.theta[i];
    const Real dil =
        p.a[i] * ti - (consistent ? p.q[i] : Real(0));  // a theta (- q: consistent term)
    const Real c = paper ? p.kappa[i] * ti : ti / Real(3);
    const Real crit = mi.critical_stretch * (Real(1) + mi.alpha * p.damage[i]);
    const Vec3 u = displacement(p, i);
    ::new (static_cast<void*>(recs + i)) ForceRec{
        {u[0], u[1], u[2], dil}, {p.x0[i][0], p.x0[i][1], p.x0[i][2], p.b[i]}, {c, crit, 0, 0}};
  });
  auto kernel = [&](auto paper_c, auto fracture_c, auto plastic_c, auto lps_c) {
    constexpr bool Paper = decltype(paper_c)::value, Fracture = decltype(fracture_c)::value;
    constexpr bool Plastic = decltype(plastic_c)::value, Lps = decltype(lps_c)::value;
    const std::uint64_t count = exec::parallel_reduce(
        space, "pd.forces", exec::Index(p.n), std::uint64_t(0),
        [&](exec::Index ii, std::uint64_t& acc) {
          const std::size_t i = std::size_t(ii);
          const std::uint64_t k0 = bonds.offsets[i], k1 = bonds.offsets[i + 1];
          const Real sub_y[4] = {recs[i].y[0], recs[i].y[1], recs[i].y[2], 0};
          const Real sub[3][4] = {{sub_y[0], sub_y[1], sub_y[2], 0},
                                  {p.x0[i][0], p.x0[i][1], p.x0[i][2], 0},
                                  {0, 0, 0, 0}};
          const ForceRec& own = recs[i];
          const ForceRow ri{own.y[3], own.x0[3], own.cc[0], own.cc[1]};
          const bool dense = bonds.dense[i] != 0;
          alignas(32) Real ax[kSumLanes] = {}, ay[kSumLanes] = {}, az[kSumLanes] = {};
          Mat3 s = Mat3::Zero();
          ForceBlock B;
          TailCopy tail;
          Real* const out[3][4] = {{B.ex, B.ey, B.ez, B.dil_j},
                                   {B.xx, B.xy, B.xz, B.b_j},
                                   {B.c_j, B.crit_j, B.pad0, B.pad1}};
          for (std::uint64_t kb = k0; kb < k1; kb += kBlock) {
            const int n = int(std::min<std::uint64_t>(kBlock, k1 - kb));
            const std::uint32_t* nb = bonds.neighbor.data() + kb;  // gather: eta, xi and j's terms
            gather_records<3, true>(recs, sizeof(ForceRec), nb, n, padded(n), std::uint32_t(i), sub,
                                    out);
            BondSlice S{bonds.length.data() + kb,        bonds.omega.data() + kb,
                        bonds.shear_omega.data() + kb,   bonds.volume.data() + kb,
                        bonds.plastic.data() + kb,       bonds.omega_r.data() + kb,
                        bonds.shear_omega_r.data() + kb, bonds.plastic_r.data() + kb,
                        bonds.intact.data() + kb};
            if (past_end(bonds, kb, n)) {
              tail.used = 0;
              S = BondSlice{tail.copy(S.L, n),       tail.copy(S.omega, n), tail.copy(S.shear, n),
                            tail.copy(S.vol, n),     tail.copy(S.epi, n),   tail.copy(S.omega_r, n),
                            tail.copy(S.shear_r, n), tail.copy(S.epj, n),   tail.copy(S.live, n)};
            }
            force_block<Paper, Fracture, Plastic, Lps>(B, S, n, ri, delta, classical);
            const std::uint8_t* lane = bonds.lane.data() + kb;
            lane_sum(B.fx, lane, dense, n, ax), lane_sum(B.fy, lane, dense, n, ay),
                lane_sum(B.fz, lane, dense, n, az);
            if (stress)  // sigma_i = 1/2 sum_j f_ij (x) xi V_j
              for (int m = 0; m < n; ++m)
                s += Real(0.5) * Vec3(B.fx[m], B.fy[m], B.fz[m]) *
                     Vec3(B.xx[m], B.xy[m], B.xz[m]).transpose();
            if (Fracture) {
              unsigned any = 0;  // vectorised OR first: bonds rarely break
              for (int m = 0; m < n; ++m) any |= B.broken[m];
              if (any)
                for (int m = 0; m < n; ++m)
                  if (B.broken[m]) bonds.intact[kb + std::uint64_t(m)] = 0;
            }
          }
          force[i] = Vec3(lane_total(ax), lane_total(ay), lane_total(az));
          if (stress) stress[i] = s;
          if (intact) acc += row_damage(p, bonds, i);  // after the row's fracture (pd_damage)
        },
        [](std::uint64_t a, std::uint64_t b) { return a + b; });
    if (intact) *intact = count;
  };
  with_form(prm, [&](auto paper_c, auto lps_c) {
    with_flag(fracture, [&](auto fracture_c) {
      with_flag(prm.plastic,
                [&](auto plastic_c) { kernel(paper_c, fracture_c, plastic_c, lps_c); });
    });
  });
}

std::uint64_t pd_damage(const exec::Space& space, const PdView& p, const PdBonds& bonds) {
  return exec::parallel_reduce(
      space, "pd.damage", exec::Index(p.n), std::uint64_t(0),
      [&](exec::Index i, std::uint64_t& acc) { acc += row_damage(p, bonds, std::size_t(i)); },
      [](std::uint64_t a, std::uint64_t b) { return a + b; });
}

extern const PdKernelTable pd_kernels;
const PdKernelTable pd_kernels = {&pd_dilatation, &pd_forces, &pd_damage};

}  // namespace AMALGAM_ISA
}  // namespace amalgam
