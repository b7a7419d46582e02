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

// The SVD below on the entries of the matrices in storage order (X(r, c) = x[r + 3 c]), written
// once for a scalar V = T (Mask = bool) and for a vector of lanes (V = lanes::V<T>, one matrix
// per lane, Mask from a comparison). Every operation is element-wise IEEE arithmetic and every
// data-dependent branch of the scalar algorithm is a per-lane select, so lane l computes bitwise
// what the scalar instantiation computes for its matrix, whatever the other lanes hold (a lane
// that has converged, or whose rotation is the identity, keeps its values; the discarded
// arithmetic of such a lane may divide by zero, which selects then drop).

// x in every lane (V a vector) or x (V a scalar).
template <class V, class T>
inline V splat_as(T x) {
  return V{} + x;
}
template <class V>
inline V abs_of(const V& x) {
  return x < 0 ? V(-x) : x;  // -0 stays -0; only ever added to a positive number below
}

// One Jacobi rotation zeroing S(p,q) of the symmetric S (lanes in `m` whose S(p,q) != 0),
// accumulated into Vm: S <- J^T S J, Vm <- Vm J with J the Givens rotation in the (p,q) plane.
template <class T, class V, class Mask>
inline void jacobi_rotate(V* S, V* Vm, int p, int q, const Mask& m) {
  const V apq = S[p + 3 * q];
  const Mask go = m & (apq != T(0));
  if (!lanes::any(go)) return;
  const V tau = (S[q + 3 * q] - S[p + 3 * p]) / (T(2) * apq);
  const V sgn = tau >= T(0) ? splat_as<V>(T(1)) : splat_as<V>(T(-1));
  const V t = sgn / (abs_of(tau) + lanes::sqrt(V(T(1) + tau * tau)));
  const V c = T(1) / lanes::sqrt(V(T(1) + t * t));
  const V s = t * c;
  V Sn[9], Vn[9];
  for (int e = 0; e < 9; ++e) Sn[e] = S[e], Vn[e] = Vm[e];
  for (int k = 0; k < 3; ++k) {  // columns p, q
    const V skp = Sn[k + 3 * p], skq = Sn[k + 3 * q];
    Sn[k + 3 * p] = c * skp - s * skq;
    Sn[k + 3 * q] = s * skp + c * skq;
  }
  for (int k = 0; k < 3; ++k) {  // then rows p, q
    const V spk = Sn[p + 3 * k], sqk = Sn[q + 3 * k];
    Sn[p + 3 * k] = c * spk - s * sqk;
    Sn[q + 3 * k] = s * spk + c * sqk;
  }
  for (int k = 0; k < 3; ++k) {
    const V vkp = Vn[k + 3 * p], vkq = Vn[k + 3 * q];
    Vn[k + 3 * p] = c * vkp - s * vkq;
    Vn[k + 3 * q] = s * vkp + c * vkq;
  }
  for (int e = 0; e < 9; ++e) S[e] = go ? Sn[e] : S[e], Vm[e] = go ? Vn[e] : Vm[e];
}

// Givens rotation acting on rows (i, j) of B, zeroing B(j, col); accumulates Q so that the
// original B equals Q * B_now. Lanes with B(i, col) = B(j, col) = 0 are left as they are.
template <class T, class V, class Mask>
inline void givens_zero(V* B, V* Q, int i, int j, int col) {
  const V a = B[i + 3 * col], b = B[j + 3 * col];
  const V r = lanes::sqrt(V(a * a + b * b));
  const Mask go = r != T(0);
  if (!lanes::any(go)) return;
  const V c = a / r, s = b / r;
  for (int k = 0; k < 3; ++k) {
    const V bi = B[i + 3 * k], bj = B[j + 3 * k];
    B[i + 3 * k] = go ? V(c * bi + s * bj) : bi;
    B[j + 3 * k] = go ? V(-s * bi + c * bj) : bj;
  }
  for (int k = 0; k < 3; ++k) {
    const V qi = Q[k + 3 * i], qj = Q[k + 3 * j];
    Q[k + 3 * i] = go ? V(c * qi + s * qj) : qi;
    Q[k + 3 * j] = go ? V(-s * qi + c * qj) : qj;
  }
}

// Where m: columns a and b of Vm and lambda(a), lambda(b) swapped, column b negated (a swap
// flips det; negating one column keeps Vm a rotation).
template <class V, class Mask>
inline void swap_columns_keep_rotation(V* Vm, V* lambda, int a, int b, const Mask& m) {
  const V la = lambda[a], lb = lambda[b];
  lambda[a] = m ? lb : la;
  lambda[b] = m ? la : lb;
  for (int k = 0; k < 3; ++k) {
    const V va = Vm[k + 3 * a], vb = Vm[k + 3 * b];
    Vm[k + 3 * a] = m ? vb : va;
    Vm[k + 3 * b] = m ? V(-va) : vb;
  }
}

// F = U diag(sigma) Vm^T (see svd3): f the entries of F; u, vm receive those of U and V.
template <class T, class V, class Mask>
inline void svd3_entries(const V* f, V* u, V* vm, V* sigma) {
  V S[9];  // F^T F
  for (int j = 0; j < 3; ++j)
    for (int i = 0; i < 3; ++i)
      S[i + 3 * j] =
          f[3 * i] * f[3 * j] + f[1 + 3 * i] * f[1 + 3 * j] + f[2 + 3 * i] * f[2 + 3 * j];
  for (int e = 0; e < 9; ++e) vm[e] = splat_as<V>(e % 4 == 0 ? T(1) : T(0));
  const V scale = S[0] + S[4] + S[8];
  const T eps = std::numeric_limits<T>::epsilon();
  const V tol = (eps * eps) * scale * scale;
  Mask active = scale == scale;  // every lane (a NaN lane stops at the first test below)
  for (int sweep = 0; sweep < 12; ++sweep) {
    const V off = S[3] * S[3] + S[6] * S[6] + S[7] * S[7];
    active = active & (off > tol);  // a lane stops for good once converged (or NaN)
    if (!lanes::any(active)) break;
    jacobi_rotate<T>(S, vm, 0, 1, active);
    jacobi_rotate<T>(S, vm, 0, 2, active);
    jacobi_rotate<T>(S, vm, 1, 2, active);
  }
  // Eigenvalues of F^T F in decreasing order, keeping V a rotation.
  V lambda[3] = {S[0], S[4], S[8]};
  swap_columns_keep_rotation(vm, lambda, 0, 1, lambda[0] < lambda[1]);
  swap_columns_keep_rotation(vm, lambda, 0, 2, lambda[0] < lambda[2]);
  swap_columns_keep_rotation(vm, lambda, 1, 2, lambda[1] < lambda[2]);
  // QR of B = F V by Givens rotations: B = U R, U a rotation, R (nearly) diagonal.
  V B[9];
  for (int j = 0; j < 3; ++j)
    for (int i = 0; i < 3; ++i)
      B[i + 3 * j] = f[i] * vm[3 * j] + f[i + 3] * vm[1 + 3 * j] + f[i + 6] * vm[2 + 3 * j];
  for (int e = 0; e < 9; ++e) u[e] = splat_as<V>(e % 4 == 0 ? T(1) : T(0));
  givens_zero<T, V, Mask>(B, u, 0, 1, 0);
  givens_zero<T, V, Mask>(B, u, 0, 2, 0);
  givens_zero<T, V, Mask>(B, u, 1, 2, 1);
  sigma[0] = B[0], sigma[1] = B[4], sigma[2] = B[8];
}

}  // namespace detail

template <class T>
inline Svd3<T> svd3(const Eigen::Matrix<T, 3, 3>& F) {
  Svd3<T> out;
  detail::svd3_entries<T, T, bool>(F.data(), out.U.data(), out.V.data(), out.sigma.data());
  return out;
}

// svd3 of n <= lanes::kN<T> matrices at once, one per vector lane: out[l] is bitwise svd3(F[l]).
template <class T>
inline void svd3_lanes(const Eigen::Matrix<T, 3, 3>* F, int n, Svd3<T>* out) {
  using V = lanes::V<T>;
  V f[9], u[9], v[9], s[3];
  lanes::load_mat3(F, n, f);
  detail::svd3_entries<T, V, lanes::Mask<T>>(f, u, v, s);
  for (int l = 0; l < n; ++l) {
    for (int e = 0; e < 9; ++e) out[l].U.data()[e] = u[e][l], out[l].V.data()[e] = v[e][l];
    for (int i = 0; i < 3; ++i) out[l].sigma[i] = s[i][l];
  }
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
// entries (lanes::load_mat3's layout), R receives the rotations the same way; lane l is bitwise
// polar_rotation_fast of the matrix in lane l.
template <class T>
inline void polar_rotation_fast_lanes(const lanes::V<T>* f, int n, lanes::V<T>* R) {
  assert(n >= 1 && n <= lanes::kN<T>);
  const lanes::Mask<T> converged = detail::polar_newton<T, lanes::V<T>, lanes::Mask<T>>(f, R);
  for (int l = 0; l < n; ++l) {
    if (converged[l]) continue;
    Eigen::Matrix<T, 3, 3> Fl;
    for (int e = 0; e < 9; ++e) Fl.data()[e] = f[e][l];
    const Svd3<T> s = svd3(Fl);
    const Eigen::Matrix<T, 3, 3> Rl = s.U * s.V.transpose();
    for (int e = 0; e < 9; ++e) R[e][l] = Rl.data()[e];
  }
}
template <class T>
inline void polar_rotation_fast_lanes(const Eigen::Matrix<T, 3, 3>* F, Eigen::Matrix<T, 3, 3>* R,
                                      int n) {
  lanes::V<T> f[9], r[9];
  lanes::load_mat3(F, n, f);
  polar_rotation_fast_lanes<T>(f, n, r);
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
