// Linear, quadratic and cubic B-spline interpolation stencils of MPM (course report,
// "inter_weight"; linear: enriched MPM eqs. 2-3, the domain corners' weights).
// Node i sits at x_i = i dx. A particle's stencil covers nodes base .. base + Order per axis:
//   linear    (Order 1): base = floor(x/dx),       2 nodes (no APIC/MLS scale: unused)
//   quadratic (Order 2): base = floor(x/dx - 1/2), 3 nodes, D_p^{-1} = 4/dx^2 (APIC/MLS)
//   cubic     (Order 3): base = floor(x/dx) - 1,   4 nodes, D_p^{-1} = 3/dx^2
// Both keep the stencil inside the particle's leaf and its +1 neighbours (base & 7 <= 7, base+3
// <= 10 < 16), which is what the 8-leaf block scatter relies on.
#pragma once

#include <cmath>

#include "core/math/simd4.hpp"
#include "core/math/types.hpp"

namespace amalgam {

// floor(x) as an int, branch-free (truncate, then step down where truncation rounded up): the
// same value as int(std::floor(x)) for |x| < 2^31, without the libm call or branchy expansion
// that the portable (SSE2) build gets for std::floor.
inline int ifloor(Real x) {
  const int t = int(x);
  return t - int(Real(t) > x);
}

template <int Order>
struct BSpline;

template <>
struct BSpline<1> {
  static constexpr int kNodes = 2;
  static constexpr Real kDinvScale = 0;  // not an APIC/MLS stencil
  static constexpr int kDrop = 0;        // base = floor(floor_arg(xs)) - kDrop
  template <class T>
  static T floor_arg(T xs) {
    return xs;
  }
  static int base(Real xs) { return ifloor(floor_arg(xs)) - kDrop; }
  // fx = x/dx - base in [0, 1): hat function omega(x) = 1 - |x| (eq. 3). T: Real, or simd::V4
  // (one axis per lane, the same operations).
  template <class T>
  static void eval(T fx, T* w, T* dw) {
    w[0] = Real(1) - fx;
    w[1] = fx;
    dw[0] = T{} - Real(1);  // -1
    dw[1] = T{} + Real(1);
  }
};

template <>
struct BSpline<2> {
  static constexpr int kNodes = 3;
  static constexpr Real kDinvScale = 4;  // D_p^{-1} = 4 / dx^2
  static constexpr int kDrop = 0;
  template <class T>
  static T floor_arg(T xs) {
    return xs - Real(0.5);
  }
  static int base(Real xs) { return ifloor(floor_arg(xs)) - kDrop; }
  // fx = x/dx - base in [0.5, 1.5); weights and d w / d(x/dx).
  template <class T>
  static void eval(T fx, T* w, T* dw) {
    const T a = Real(1.5) - fx, b = fx - Real(1), c = fx - Real(0.5);
    w[0] = Real(0.5) * a * a;
    w[1] = Real(0.75) - b * b;
    w[2] = Real(0.5) * c * c;
    dw[0] = -a;
    dw[1] = Real(-2) * b;
    dw[2] = c;
  }
};

template <>
struct BSpline<3> {
  static constexpr int kNodes = 4;
  static constexpr Real kDinvScale = 3;  // D_p^{-1} = 3 / dx^2
  static constexpr int kDrop = 1;
  template <class T>
  static T floor_arg(T xs) {
    return xs;
  }
  static int base(Real xs) { return ifloor(floor_arg(xs)) - kDrop; }
  // fx = x/dx - base in [1, 2).
  template <class T>
  static void eval(T fx, T* w, T* dw) {
    const T d0 = Real(2) - fx;  // distance-complement for node 0: |d| in [1,2)
    const T d1 = fx - Real(1);  // node 1: |d| in [0,1)
    const T d2 = Real(2) - fx;  // node 2: |d| in (0,1]
    const T d3 = fx - Real(1);  // node 3: 2 - |d| in [0,1)
    w[0] = d0 * d0 * d0 / Real(6);
    w[1] = Real(0.5) * d1 * d1 * d1 - d1 * d1 + Real(2) / Real(3);
    w[2] = Real(0.5) * d2 * d2 * d2 - d2 * d2 + Real(2) / Real(3);
    w[3] = d3 * d3 * d3 / Real(6);
    dw[0] = Real(-0.5) * d0 * d0;
    dw[1] = Real(1.5) * d1 * d1 - Real(2) * d1;
    dw[2] = -(Real(1.5) * d2 * d2 - Real(2) * d2);
    dw[3] = Real(0.5) * d3 * d3;
  }
};

// Tensor-product stencil of one particle: per-axis weights w[axis][k] and derivatives
// dw[axis][k] (already divided by dx, i.e. d/dx of the 1D weight).
template <int Order>
struct Stencil {
  static constexpr int kN = BSpline<Order>::kNodes;
  Vec3i base;
  Vec3 fx;  // x/dx - base
  Real w[3][kN];
  Real dw[3][kN];

  __attribute__((always_inline)) static Stencil at(const Vec3& x, Real inv_dx) {
#if !defined(AMALGAM_REAL_DOUBLE)
    // The three axes in the lanes of one V4 (lane 3 repeats z, unused): per lane exactly
    // at_scalar's operations (ifloor as truncation, then one down where it rounded up).
    Stencil s;
    using simd::V4;
    typedef std::int32_t I4 __attribute__((vector_size(16)));
    const V4 xs = V4{x[0], x[1], x[2], x[2]} * inv_dx;
    const V4 y = BSpline<Order>::floor_arg(xs);
    const I4 t = __builtin_convertvector(y, I4);
    const I4 base = t + I4(__builtin_convertvector(t, V4) > y) - BSpline<Order>::kDrop;
    const V4 fx = xs - __builtin_convertvector(base, V4);
    V4 w[kN], dw[kN];
    BSpline<Order>::eval(fx, w, dw);
    for (int a = 0; a < 3; ++a) {
      s.base[a] = base[a];
      s.fx[a] = fx[a];
      for (int k = 0; k < kN; ++k) {
        s.w[a][k] = w[k][a];
        s.dw[a][k] = dw[k][a] * inv_dx;
      }
    }
    return s;
#else
    return at_scalar(x, inv_dx);
#endif
  }
  // The same stencil axis by axis (the double build's form, and the lanes' reference in
  // tests/test_math.cpp).
  static Stencil at_scalar(const Vec3& x, Real inv_dx) {
    Stencil s;
    for (int a = 0; a < 3; ++a) {
      const Real xs = x[a] * inv_dx;
      s.base[a] = BSpline<Order>::base(xs);
      s.fx[a] = xs - Real(s.base[a]);
      BSpline<Order>::eval(s.fx[a], s.w[a], s.dw[a]);
      for (int k = 0; k < kN; ++k) s.dw[a][k] *= inv_dx;
    }
    return s;
  }
  Real weight(int i, int j, int k) const {
    return w[0][i] * w[1][j] * w[2][k];
  }
  Vec3 gradient(int i, int j, int k) const {
    return Vec3(dw[0][i] * w[1][j] * w[2][k], w[0][i] * dw[1][j] * w[2][k],
                w[0][i] * w[1][j] * dw[2][k]);
  }
  // x_i - x_p for stencil node (i, j, k), in world units.
  Vec3 offset(int i, int j, int k, Real dx) const {
    return Vec3((Real(i) - fx[0]) * dx, (Real(j) - fx[1]) * dx, (Real(k) - fx[2]) * dx);
  }
};

// Does particle x's stencil (nodes base .. base + Order per axis) lie inside the block of B nodes
// per axis whose first node is origin? If so, d = base - origin per axis (d may be null). Decided
// in floating point before any conversion (floor(y) >= o exactly when y >= o, o an integer), so a
// position that blew up in the pass that moved it (NaN, infinite or far: the far flags run before
// the stability check reports it) is outside, never an out-of-range float-to-int conversion
// (undefined behaviour); for every other position the same answer as comparing base itself.
template <int Order>
inline bool stencil_in_block(const Vec3& x, Real inv_dx, const Vec3i& origin, int B, int* d) {
  using S = BSpline<Order>;
#if !defined(AMALGAM_REAL_DOUBLE)
  {  // the three axes in one V4's lanes (lane 3 repeats z): the same operations per lane
    using simd::V4;
    typedef std::int32_t I4 __attribute__((vector_size(16)));
    const V4 y = S::floor_arg(V4{x[0], x[1], x[2], x[2]} * inv_dx);
    const V4 lo{Real(origin[0] + S::kDrop), Real(origin[1] + S::kDrop), Real(origin[2] + S::kDrop),
                Real(origin[2] + S::kDrop)};
    const I4 in = (y >= lo) & (y < lo + Real(B - Order));
    if (!(in[0] & in[1] & in[2])) return false;
    if (d) {
      const I4 t = __builtin_convertvector(y, I4);
      const I4 f = t + I4(__builtin_convertvector(t, V4) > y);  // ifloor
      for (int a = 0; a < 3; ++a) d[a] = f[a] - S::kDrop - origin[a];
    }
    return true;
  }
#endif
  Real y[3];
  bool in = true;
  for (int a = 0; a < 3; ++a) {
    y[a] = S::floor_arg(x[a] * inv_dx);
    const Real lo = Real(origin[a] + S::kDrop);  // base >= origin and base + Order < origin + B
    in &= y[a] >= lo && y[a] < lo + Real(B - Order);
  }
  if (in && d)
    for (int a = 0; a < 3; ++a) d[a] = ifloor(y[a]) - S::kDrop - origin[a];
  return in;
}

}  // namespace amalgam
