// Robust 3x3 singular value decomposition and polar decomposition.
//
// F = U diag(sigma) V^T with U, V proper rotations (det = +1). sigma is sorted by magnitude,
// sigma0 >= sigma1 >= |sigma2|, and sigma2 < 0 exactly when det F < 0 (inverted element): this is
// the sign convention of the course report's "polar SVD" (flip the last column of U or V when its
// determinant is negative, and the matching singular value with it), which keeps R = U V^T a
// rotation for inverted F.
//
// Method (McAdams et al. 2011 structure, exact rotations): cyclic Jacobi on S = F^T F gives V,
// columns sorted by eigenvalue; B = F V is then orthogonalised by Givens QR, B = U R, so U is a
// rotation even when columns of B vanish (singular F); sigma = diag(R). Computed in the
// precision T (float or double).
#pragma once

#include <Eigen/Core>
#include <cassert>
#include <cmath>
#include <limits>

#include "core/math/lanes.hpp"

namespace amalgam {

template <class T>
struct Svd3 {
  Eigen::Matrix<T, 3, 3> U, V;
  Eigen::Matrix<T, 3, 1> sigma;
};

namespace detail {

// One Jacobi rotation zeroing S(p,q) of symmetric S, accumulated into V.
template <class T>
inline void jacobi_rotate(Eigen::Matrix<T, 3, 3>& S, Eigen::Matrix<T, 3, 3>& V, int p, int q) {
  const T apq = S(p, q);
  if (apq == T(0)) return;
  const T tau = (S(q, q) - S(p, p)) / (T(2) * apq);
  const T t = (tau >= T(0) ? T(1) : T(-1)) / (std::abs(tau) + std::sqrt(T(1) + tau * tau));
  const T c = T(1) / std::sqrt(T(1) + t * t);
  const T s = t * c;
  // S <- J^T S J with J the Givens rotation in the (p,q) plane.
  for (int k = 0; k < 3; ++k) {
    const T skp = S(k, p), skq = S(k, q);
    S(k, p) = c * skp - s * skq;
    S(k, q) = s * skp + c * skq;
  }
  for (int k = 0; k < 3; ++k) {
    const T spk = S(p, k), sqk = S(q, k);
    S(p, k) = c * spk - s * sqk;
    S(q, k) = s * spk + c * sqk;
  }
  for (int k = 0; k < 3; ++k) {
    const T vkp = V(k, p), vkq = V(k, q);
    V(k, p) = c * vkp - s * vkq;
    V(k, q) = s * vkp + c * vkq;
  }
}

// Givens rotation acting on rows (i, j) of B, zeroing B(j, col); accumulates Q so that the
// original B equals Q * B_now.
template <class T>
inline void givens_zero(Eigen::Matrix<T, 3, 3>& B, Eigen::Matrix<T, 3, 3>& Q, int i, int j,
                        int col) {
  const T a = B(i, col), b = B(j, col);
  const T r = std::sqrt(a * a + b * b);
  if (r == T(0)) return;
  const T c = a / r, s = b / r;
  for (int k = 0; k < 3; ++k) {
    const T bi = B(i, k), bj = B(j, k);
    B(i, k) = c * bi + s * bj;
    B(j, k) = -s * bi + c * bj;
  }
  for (int k = 0; k < 3; ++k) {
    const T qi = Q(k, i), qj = Q(k, j);
    Q(k, i) = c * qi + s * qj;
    Q(k, j) = -s * qi + c * qj;
  }
}

template <class T>
inline void swap_columns_keep_rotation(Eigen::Matrix<T, 3, 3>& V, Eigen::Matrix<T, 1, 3>& lambda,
                                       int a, int b) {
  std::swap(lambda(a), lambda(b));
  for (int k = 0; k < 3; ++k) {
    const T t = V(k, a);
    V(k, a) = V(k, b);
    V(k, b) = -t;  // a swap flips det; negating one column restores det = +1
  }
}

}  // namespace detail

template <class T>
inline Svd3<T> svd3(const Eigen::Matrix<T, 3, 3>& F) {
  using M = Eigen::Matrix<T, 3, 3>;
  Svd3<T> out;
  M S = F.transpose() * F;
  M V = M::Identity();
  const T scale = S.diagonal().sum();
  const T tol =
      std::numeric_limits<T>::epsilon() * std::numeric_limits<T>::epsilon() * scale * scale;
  for (int sweep = 0; sweep < 12; ++sweep) {
    const T off = S(0, 1) * S(0, 1) + S(0, 2) * S(0, 2) + S(1, 2) * S(1, 2);
    if (!(off > tol)) break;  // also stops on NaN
    detail::jacobi_rotate(S, V, 0, 1);
    detail::jacobi_rotate(S, V, 0, 2);
    detail::jacobi_rotate(S, V, 1, 2);
  }
  // Sort eigenvalues of F^T F in decreasing order, keeping V a rotation.
  Eigen::Matrix<T, 1, 3> lambda(S(0, 0), S(1, 1), S(2, 2));
  if (lambda(0) < lambda(1)) detail::swap_columns_keep_rotation(V, lambda, 0, 1);
  if (lambda(0) < lambda(2)) detail::swap_columns_keep_rotation(V, lambda, 0, 2);
  if (lambda(1) < lambda(2)) detail::swap_columns_keep_rotation(V, lambda, 1, 2);
  // QR of B = F V by Givens rotations: B = U R, U a rotation, R (nearly) diagonal.
  M B = F * V;
  M U = M::Identity();
  detail::givens_zero(B, U, 0, 1, 0);
  detail::givens_zero(B, U, 0, 2, 0);
  detail::givens_zero(B, U, 1, 2, 1);
  out.U = U;
  out.V = V;
  out.sigma = Eigen::Matrix<T, 3, 1>(B(0, 0), B(1, 1), B(2, 2));
  return out;
}

namespace detail {
template <class T>
inline Eigen::Matrix<T, 3, 3> cofactor3(const Eigen::Matrix<T, 3, 3>& F) {
  Eigen::Matrix<T, 3, 3> c;
  c(0, 0) = F(1, 1) * F(2, 2) - F(1, 2) * F(2, 1);
  c(0, 1) = F(1, 2) * F(2, 0) - F(1, 0) * F(2, 2);
  c(0, 2) = F(1, 0) * F(2, 1) - F(1, 1) * F(2, 0);
  c(1, 0) = F(0, 2) * F(2, 1) - F(0, 1) * F(2, 2);
  c(1, 1) = F(0, 0) * F(2, 2) - F(0, 2) * F(2, 0);
  c(1, 2) = F(0, 1) * F(2, 0) - F(0, 0) * F(2, 1);
  c(2, 0) = F(0, 1) * F(1, 2) - F(0, 2) * F(1, 1);
  c(2, 1) = F(0, 2) * F(1, 0) - F(0, 0) * F(1, 2);
  c(2, 2) = F(0, 0) * F(1, 1) - F(0, 1) * F(1, 0);
  return c;
}
}  // namespace detail

namespace detail {
// The Newton polar iteration of polar_rotation_fast on f (the 9 entries of F in storage order,
// X(r, c) = x[r + 3 c]), written once for a scalar V = T (Mask = bool) and for a vector of lanes
// (V = lanes::V<T>, one matrix per lane, Mask from a comparison). Every operation is per lane and
// a lane stops changing once it has converged, so each lane computes bitwise what the scalar
// instantiation computes for its matrix, whatever the other lanes hold. Returns, per lane,
// whether X holds the converged rotation (false: the caller takes the SVD).
template <class T, class V, class Mask>
inline Mask polar_newton(const V* f, V* X) {
  const auto cof = [](const V* x, V* c) {
    c[0] = x[4] * x[8] - x[7] * x[5];
    c[3] = x[7] * x[2] - x[1] * x[8];
    c[6] = x[1] * x[5] - x[4] * x[2];
    c[1] = x[6] * x[5] - x[3] * x[8];
    c[4] = x[0] * x[8] - x[6] * x[2];
    c[7] = x[3] * x[2] - x[0] * x[5];
    c[2] = x[3] * x[7] - x[6] * x[4];
    c[5] = x[6] * x[1] - x[0] * x[7];
    c[8] = x[0] * x[4] - x[3] * x[1];
  };
  // det X: row 0 of X times row 0 of cof(X).
  const auto det = [](const V* x, const V* c) { return x[0] * c[0] + x[3] * c[3] + x[6] * c[6]; };
  V nF2 = f[0] * f[0];
  for (int e = 1; e < 9; ++e) nF2 += f[e] * f[e];
  V c0[9];
  cof(f, c0);
  const V det0 = det(f, c0);
  // det >= 1e-3 |F|^3 / 3^{3/2} keeps the condition number moderate (<~ 1e3): Newton converges
  // in a handful of steps. Otherwise (inverted, flattened, NaN) the SVD.
  Mask active = det0 > T(2e-4) * nF2 * lanes::sqrt(nF2);
  for (int e = 0; e < 9; ++e) X[e] = f[e];
  // Near a rotation (|F|^2 ~ 3, det ~ 1: the usual MPM substep) plain Newton steps converge
  // quadratically from X = F. Far from it, the first step is scaled (Higham), which brings the
  // singular values near 1; its two square roots are what the near-rotation test saves.
  const V d3 = nF2 - T(3), d1 = det0 - T(1);
  const Mask scaled = active & ((d3 > T(0.75)) | (d3 < T(-0.75)) | (d1 > T(0.5)) | (d1 < T(-0.5)));
  if (lanes::any(scaled)) {
    V nC2 = c0[0] * c0[0];
    for (int e = 1; e < 9; ++e) nC2 += c0[e] * c0[e];
    const V zeta = lanes::sqrt(lanes::sqrt(nC2 / nF2) / det0);  // (|F^{-1}| / |F|)^{1/2}
    const V zd = zeta * det0;
    for (int e = 0; e < 9; ++e) X[e] = scaled ? V(T(0.5) * (zeta * f[e] + c0[e] / zd)) : f[e];
  }
  const T tol = std::numeric_limits<T>::epsilon() * T(8);
  Mask converged{};
  for (int it = 0; it < 10 && lanes::any(active); ++it) {
    V C[9], Xn[9];
    cof(X, C);
    const V h = T(0.5) / det(X, C);  // X^{-T} / 2 = cof(X) h
    V change2{};
    for (int e = 0; e < 9; ++e) {
      Xn[e] = T(0.5) * X[e] + C[e] * h;
      const V s = Xn[e] - X[e];
      change2 = e == 0 ? V(s * s) : V(change2 + s * s);
    }
    for (int e = 0; e < 9; ++e) X[e] = active ? Xn[e] : X[e];
    // |change| <= sqrt(tol): the next error is ~tol, already met.
    const Mask done = active & (change2 <= tol);
    converged = converged | done;
    active = lanes::andnot(active, done);
  }
  return converged;
}
}  // namespace detail

// Rotation of the polar decomposition, fast path. For det F clearly positive it runs Higham's
// scaled Newton iteration X <- (zeta X + X^{-T} / zeta) / 2, zeta = (|X^{-1}|_F / |X|_F)^{1/2}
// (Higham 1986), which converges quadratically to the orthogonal polar factor (a rotation, since
// det stays positive); X^{-T} = cof(X) / det X. Inverted, near-singular or non-converging F fall
// back to the SVD, whose sign convention keeps R a rotation there too. Same result as U V^T of
// svd3 up to round-off.
template <class T>
inline Eigen::Matrix<T, 3, 3> polar_rotation_fast(const Eigen::Matrix<T, 3, 3>& F) {
  Eigen::Matrix<T, 3, 3> R;
  if (detail::polar_newton<T, T, bool>(F.data(), R.data())) return R;
  const Svd3<T> s = svd3(F);
  return s.U * s.V.transpose();
}

// polar_rotation_fast of n <= lanes::kN<T> matrices at once, one per vector lane: f holds their
// entries (lanes::load_mat3 of F), R receives the rotations the same way; lane l is bitwise
// polar_rotation_fast(F[l]).
template <class T>
inline void polar_rotation_fast_lanes(const lanes::V<T>* f, const Eigen::Matrix<T, 3, 3>* F, int n,
                                      lanes::V<T>* R) {
  assert(n >= 1 && n <= lanes::kN<T>);
  const lanes::Mask<T> converged = detail::polar_newton<T, lanes::V<T>, lanes::Mask<T>>(f, R);
  for (int l = 0; l < n; ++l) {
    if (converged[l]) continue;
    const Svd3<T> s = svd3(F[l]);
    const Eigen::Matrix<T, 3, 3> Rl = s.U * s.V.transpose();
    for (int e = 0; e < 9; ++e) R[e][l] = Rl.data()[e];
  }
}
template <class T>
inline void polar_rotation_fast_lanes(const Eigen::Matrix<T, 3, 3>* F, Eigen::Matrix<T, 3, 3>* R,
                                      int n) {
  lanes::V<T> f[9], r[9];
  lanes::load_mat3(F, n, f);
  polar_rotation_fast_lanes(f, F, n, r);
  lanes::store_mat3(r, n, R);
}

// Polar decomposition F = R S with R = U V^T a rotation (also for inverted F) and
// S = V diag(sigma) V^T symmetric.
template <class T>
inline Eigen::Matrix<T, 3, 3> polar_rotation(const Eigen::Matrix<T, 3, 3>& F) {
  const Svd3<T> d = svd3(F);
  return d.U * d.V.transpose();
}

}  // namespace amalgam
