// An MPM particle's deformation where nothing reads F itself: the left Cauchy-Green tensor
// b = F F^T, stored as D = b - I, 6 entries (MpmSolver::keeps_b; docs/benchmarks.md, "Memory").
// Every material of the engine is isotropic: its Kirchhoff stress, energy and return mapping
// depend on F only through b (tau(F Q) = tau(F) for a rotation Q), so any L with L L^T = b stands
// in for F there; b_factor gives its Cholesky factor. b - I keeps the digits of a small strain
// whatever the body's rotation (a rest shape turned by R has b = I, to rounding), which the compensated
// pair F + F_lo (core/math/types.hpp: add_compensated; 72 B in float) kept for F: 24 B instead.
#pragma once

#include <Eigen/Core>

#include "core/math/lanes.hpp"
#include "core/math/types.hpp"

namespace amalgam {

// D = b - I: D(0,0), D(1,1), D(2,2), D(0,1), D(0,2), D(1,2).
template <class T>
struct SymDevT {
  T e[6];
};
using SymDev = SymDevT<Real>;
static_assert(sizeof(SymDev) == 6 * sizeof(Real), "six entries, densely");

namespace detail {
// Entry (r, c) of D in SymDevT's order.
constexpr int sym_index(int r, int c) {
  return r == c ? r : (r + c == 1 ? 3 : (r + c == 2 ? 4 : 5));
}
}  // namespace detail

// b <- (I + G) b (I + G)^T for the substep's increment G = dt grad v (g[row][col]), i.e. F <-
// (I + G) F. With Q = G + G D = G (I + D):
//   D <- D + ((Q + Q^T) + Q G^T),
// every term of the bracket small, summed first and added to D last: D keeps the digits of its
// change (forming I + G or I + D first would round to float's spacing around 1: issue 27's bias).
// G2P computes the same operations in the same order on 4-lane columns (kernels/mpm_transfers.cpp,
// advance_b_columns): the same bits.
template <class T>
inline void advance_b(T* d, const T (&g)[3][3]) {
  using detail::sym_index;
  T D[3][3], Q[3][3];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) D[r][c] = d[sym_index(r, c)];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      Q[r][c] = g[r][c] + ((g[r][0] * D[0][c] + g[r][1] * D[1][c]) + g[r][2] * D[2][c]);
  constexpr int rs[6] = {0, 1, 2, 0, 0, 1}, cs[6] = {0, 1, 2, 1, 2, 2};
  for (int e = 0; e < 6; ++e) {
    const int r = rs[e], c = cs[e];
    const T qg = (Q[r][0] * g[c][0] + Q[r][1] * g[c][1]) + Q[r][2] * g[c][2];
    d[e] += (Q[r][c] + Q[c][r]) + qg;
  }
}

// L, lower triangular, with L L^T = I + D (Cholesky): an F with the particle's b. V is T or a
// vector of lanes::V<T> (one particle per lane, each computing what the scalar code computes),
// l[9] the entries in Eigen's storage order (L(r, c) = l[r + 3 c]). A b that is not positive
// definite gives NaN entries, which the stress carries to v and the stability check names.
template <class T, class V>
inline void b_factor_entries(const V* d, V* l) {
  const V l00 = lanes::sqrt(V(T(1) + d[0]));
  const V l10 = d[3] / l00, l20 = d[4] / l00;
  const V l11 = lanes::sqrt(V((T(1) + d[1]) - l10 * l10));
  const V l21 = (d[5] - l20 * l10) / l11;
  const V l22 = lanes::sqrt(V((T(1) + d[2]) - (l20 * l20 + l21 * l21)));
  l[0] = l00, l[1] = l10, l[2] = l20;
  l[3] = V{}, l[4] = l11, l[5] = l21;
  l[6] = V{}, l[7] = V{}, l[8] = l22;
}
template <class T>
inline Eigen::Matrix<T, 3, 3> b_factor(const SymDevT<T>& d) {
  Eigen::Matrix<T, 3, 3> L;
  b_factor_entries<T, T>(d.e, L.data());
  return L;
}
// b_factor of n <= lanes::kN<T> particles at once, one per lane: l[e] holds entry e of each
// factor (lanes::load_mat3's layout; spare lanes the identity), lane k bitwise b_factor(d[k]).
template <class T>
inline void b_factor_lanes(const SymDevT<T>* d, int n, lanes::V<T>* l) {
  using V = lanes::V<T>;
  V dv[6];
  if (n == lanes::kN<T>) {
    for (int e = 0; e < 6; ++e) dv[e] = lanes::gather(d[0].e + e, 6);
  } else {
    for (int e = 0; e < 6; ++e) dv[e] = V{};
    for (int k = 0; k < n; ++k)
      for (int e = 0; e < 6; ++e) dv[e][k] = d[k].e[e];
  }
  b_factor_entries<T, V>(dv, l);
}
// The same stored as matrices: L[k] is bitwise b_factor(d[k]).
template <class T>
inline void b_factor_lanes(const SymDevT<T>* d, int n, Eigen::Matrix<T, 3, 3>* L) {
  lanes::V<T> l[9];
  b_factor_lanes(d, n, l);
  lanes::store_mat3(l, n, L);
}

// D = F F^T - I of F (in double: (F - I) + (F - I)^T + (F - I)(F - I)^T, each term small near
// I), rounded once to T.
template <class T>
inline SymDevT<T> b_from_F(const Eigen::Matrix3d& F) {
  const Eigen::Matrix3d A = F - Eigen::Matrix3d::Identity();
  const Eigen::Matrix3d D = (A + A.transpose()) + A * A.transpose();
  SymDevT<T> d;
  for (int r = 0; r < 3; ++r)
    for (int c = r; c < 3; ++c) d.e[detail::sym_index(r, c)] = T(D(r, c));
  return d;
}

// I + D as a full matrix (double), e.g. to compare with F F^T.
template <class T>
inline Eigen::Matrix3d b_matrix(const SymDevT<T>& d) {
  Eigen::Matrix3d b;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) b(r, c) = double(d.e[detail::sym_index(r, c)]) + (r == c);
  return b;
}

}  // namespace amalgam
