// Four Reals in one vector register, for the 4-lane node rows of the transfer kernels (a grid node
// is (m, p) after P2G and (m, v) after the grid update: one vector). GCC/Clang vector extensions: SSE in the portable float build,
// AVX with -march=native; element-wise IEEE operations, so a kernel written with V4 computes
// exactly what the same scalar loop over 4 lanes computes (no reassociation, no FMA contraction in
// the portable build). Only for inline kernel code: vectors are not passed across translation
// units.
#pragma once

#include <cstring>

#include "core/math/types.hpp"

namespace amalgam::simd {

#if defined(AMALGAM_REAL_DOUBLE) && !defined(__AVX__)
// 4 doubles need AVX: without it GCC lowers a 32-byte vector type piecewise through the stack,
// which made the double build's G2P 2-3x slower than scalar code (measured). There V4 is two SSE2
// halves with element-wise operators.
typedef double V2 __attribute__((vector_size(16)));
struct V4 {
  V2 lo, hi;
  V4() : lo{0, 0}, hi{0, 0} {}
  V4(Real a, Real b, Real c, Real d) : lo{a, b}, hi{c, d} {}
  V4(V2 l, V2 h) : lo(l), hi(h) {}
  Real operator[](int i) const { return i < 2 ? lo[i] : hi[i - 2]; }
  V4& operator+=(const V4& b) {
    lo += b.lo, hi += b.hi;
    return *this;
  }
  V4& operator-=(const V4& b) {
    lo -= b.lo, hi -= b.hi;
    return *this;
  }
};
inline V4 operator+(const V4& a, const V4& b) {
  return V4(a.lo + b.lo, a.hi + b.hi);
}
inline V4 operator-(const V4& a, const V4& b) {
  return V4(a.lo - b.lo, a.hi - b.hi);
}
inline V4 operator*(const V4& a, const V4& b) {
  return V4(a.lo * b.lo, a.hi * b.hi);
}
inline V4 operator*(const V4& a, Real s) {
  return V4(a.lo * s, a.hi * s);
}
inline V4 operator*(Real s, const V4& a) {
  return V4(s * a.lo, s * a.hi);
}
#else
typedef Real V4 __attribute__((vector_size(4 * sizeof(Real))));
#endif

inline V4 load4(const Real* p) {
  V4 v;
  std::memcpy(static_cast<void*>(&v), p, sizeof v);
  return v;
}
inline void store4(Real* p, const V4& v) {
  std::memcpy(p, static_cast<const void*>(&v), sizeof v);
}
// (lead, c0, c1, c2): a node row with a scalar first lane and a 3-vector after it.
inline V4 row4(Real lead, const Vec3& c) {
  return V4{lead, c[0], c[1], c[2]};
}
// Column a of a 3x3 matrix behind a zero lane: (0, M(0,a), M(1,a), M(2,a)).
inline V4 col4(const Mat3& M, int a) {
  return V4{0, M(0, a), M(1, a), M(2, a)};
}

}  // namespace amalgam::simd
