// Isotropic constitutive models in the singular-value frame.
//
// An isotropic energy Psi(F) = psi(sigma) has P(F) = U diag(p) V^T with p_i = d psi / d sigma_i
// for F = U diag(sigma) V^T (Irving, Teran & Fedkiw 2004; the rotated-frame formulation of
// Stomakhin et al. 2012). The derivative of P in a direction dF is, with M = U^T dF V,
//   dP = U R V^T,  R_ii = sum_j H_ij M_jj             (H_ij = d p_i / d sigma_j)
//   [R_ij]   1 [a+b  a-b] [M_ij]      a = (p_i - p_j) / (sigma_i - sigma_j)
//   [R_ji] = - [a-b  a+b] [M_ji],     b = (p_i + p_j) / (sigma_i + sigma_j)
//            2
// (from differentiating F = U S V^T and P = U diag(p) V^T with U^T dU, V^T dV skew). When
// sigma_i -> sigma_j, a -> H_ii - H_ij, its limit for an isotropic psi; b's denominator is
// kept away from zero for inverted, flattened F. Used by every hyperelastic model for the
// action of dP/dF that implicit solvers need.
#pragma once

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <limits>
#include <cmath>

#include "core/math/svd3.hpp"

namespace amalgam {

// The Hessian d^2 Psi / dF dF of an isotropic energy in the SVD frame of F: the 3x3 block H on
// the diagonal entries and, per pair (i, j), the 2x2 block [c1 c2; c2 c1] on (M_ij, M_ji), whose
// eigenvalues are a = c1 + c2 (eigenvector (1, -1)) and b = c1 - c2 (eigenvector (1, 1)).
// Cached per particle by implicit solvers: one SVD per Newton step, then every Hessian action
// is apply() in the frame. make_psd() is the definiteness fix of Teran et al. 2005 (enriched MPM
// eq. 16): each block's negative eigenvalues are clamped to zero, so the stiffness is positive
// semi-definite even for inverted or flattened F.
template <class T>
struct SvdFrameHessian {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  M3 H;       // d p_i / d sigma_j (symmetric)
  V3 c1, c2;  // pairs (0,1), (0,2), (1,2)

  // From p_i = d psi / d sigma_i and H_ij = d p_i / d sigma_j at singular values sigma.
  static SvdFrameHessian from(const V3& sigma, const V3& p, const M3& H) {
    SvdFrameHessian h;
    h.H = H;
    const T tiny = T(64) * std::numeric_limits<T>::epsilon();
    int k = 0;
    for (int i = 0; i < 3; ++i)
      for (int j = i + 1; j < 3; ++j, ++k) {
        const T si = sigma[i], sj = sigma[j];
        const T diff = si - sj, sum = si + sj;
        const T scale = T(1) + std::abs(si) + std::abs(sj);
        const T a = std::abs(diff) > tiny * scale ? (p[i] - p[j]) / diff : H(i, i) - H(i, j);
        const T den = std::abs(sum) > tiny * scale ? sum : std::copysign(tiny * scale, sum);
        const T b = (p[i] + p[j]) / den;
        h.c1[k] = T(0.5) * (a + b);
        h.c2[k] = T(0.5) * (a - b);
      }
    return h;
  }
  // R = (d^2 Psi / dF dF : (U M V^T)) expressed in the frame, for M = U^T dF V.
  M3 apply(const M3& M) const {
    M3 R;
    for (int i = 0; i < 3; ++i) R(i, i) = H(i, 0) * M(0, 0) + H(i, 1) * M(1, 1) + H(i, 2) * M(2, 2);
    R(0, 1) = c1[0] * M(0, 1) + c2[0] * M(1, 0);
    R(1, 0) = c1[0] * M(1, 0) + c2[0] * M(0, 1);
    R(0, 2) = c1[1] * M(0, 2) + c2[1] * M(2, 0);
    R(2, 0) = c1[1] * M(2, 0) + c2[1] * M(0, 2);
    R(1, 2) = c1[2] * M(1, 2) + c2[2] * M(2, 1);
    R(2, 1) = c1[2] * M(2, 1) + c2[2] * M(1, 2);
    return R;
  }
  // M : apply(M) for M = a b^T, without forming M (the Jacobi diagonal, enriched MPM eq. 18):
  // q^T H q + sum_pairs c1 (a_i^2 b_j^2 + a_j^2 b_i^2) + 2 c2 a_i b_i a_j b_j, q = a o b.
  T rank_one_quadratic(const V3& a, const V3& b) const {
    const V3 q = a.cwiseProduct(b);
    T s = q.dot(H * q);
    int k = 0;
    for (int i = 0; i < 3; ++i)
      for (int j = i + 1; j < 3; ++j, ++k)
        s += c1[k] * (a[i] * a[i] * b[j] * b[j] + a[j] * a[j] * b[i] * b[i]) +
             T(2) * c2[k] * q[i] * q[j];
    return s;
  }
  // Teran et al. 2005: clamp each block's eigenvalues at zero.
  void make_psd() {
    Eigen::SelfAdjointEigenSolver<M3> es;
    es.computeDirect(H);
    const V3 ev = es.eigenvalues().cwiseMax(T(0));
    H = es.eigenvectors() * ev.asDiagonal() * es.eigenvectors().transpose();
    for (int k = 0; k < 3; ++k) {
      const T a = std::max(c1[k] + c2[k], T(0)), b = std::max(c1[k] - c2[k], T(0));
      c1[k] = T(0.5) * (a + b);
      c2[k] = T(0.5) * (a - b);
    }
  }
};

template <class T>
inline Eigen::Matrix<T, 3, 3> isotropic_dP(const Svd3<T>& d, const Eigen::Matrix<T, 3, 1>& p,
                                           const Eigen::Matrix<T, 3, 3>& H,
                                           const Eigen::Matrix<T, 3, 3>& dF) {
  const SvdFrameHessian<T> h = SvdFrameHessian<T>::from(d.sigma, p, H);
  return d.U * h.apply(d.U.transpose() * dF * d.V) * d.V.transpose();
}

// d cof(F)[dF]: cof(F) has columns f1 x f2, f2 x f0, f0 x f1 (f_k the columns of F), so its
// derivative is bilinear in F and dF. Finite for singular F, unlike d(J F^{-T}) written with F^{-1}.
template <class T>
inline Eigen::Matrix<T, 3, 3> cofactor_derivative(const Eigen::Matrix<T, 3, 3>& F,
                                                  const Eigen::Matrix<T, 3, 3>& dF) {
  using V3 = Eigen::Matrix<T, 3, 1>;
  Eigen::Matrix<T, 3, 3> out;
  for (int k = 0; k < 3; ++k) {
    const int a = (k + 1) % 3, b = (k + 2) % 3;
    const V3 fa = F.col(a), fb = F.col(b), da = dF.col(a), db = dF.col(b);
    out.col(k) = da.cross(fb) + fa.cross(db);
  }
  return out;
}

}  // namespace amalgam
