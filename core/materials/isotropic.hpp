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
#include <cmath>

#include "core/math/svd3.hpp"

namespace amalgam {

template <class T>
inline Eigen::Matrix<T, 3, 3> isotropic_dP(const Svd3<T>& d, const Eigen::Matrix<T, 3, 1>& p,
                                           const Eigen::Matrix<T, 3, 3>& H, const Eigen::Matrix<T, 3, 3>& dF) {
  using M3 = Eigen::Matrix<T, 3, 3>;
  const M3 M = d.U.transpose() * dF * d.V;
  M3 R;
  for (int i = 0; i < 3; ++i) R(i, i) = H(i, 0) * M(0, 0) + H(i, 1) * M(1, 1) + H(i, 2) * M(2, 2);
  const T tiny = T(64) * std::numeric_limits<T>::epsilon();
  for (int i = 0; i < 3; ++i)
    for (int j = i + 1; j < 3; ++j) {
      const T si = d.sigma[i], sj = d.sigma[j];
      const T diff = si - sj, sum = si + sj;
      const T scale = T(1) + std::abs(si) + std::abs(sj);
      const T a = std::abs(diff) > tiny * scale ? (p[i] - p[j]) / diff : H(i, i) - H(i, j);
      const T den = std::abs(sum) > tiny * scale ? sum : std::copysign(tiny * scale, sum);
      const T b = (p[i] + p[j]) / den;
      const T c1 = T(0.5) * (a + b), c2 = T(0.5) * (a - b);
      R(i, j) = c1 * M(i, j) + c2 * M(j, i);
      R(j, i) = c1 * M(j, i) + c2 * M(i, j);
    }
  return d.U * R * d.V.transpose();
}

// d cof(F)[dF]: cof(F) has columns f1 x f2, f2 x f0, f0 x f1 (f_k the columns of F), so its
// derivative is bilinear in F and dF. Finite for singular F, unlike d(J F^{-T}) written with F^{-1}.
template <class T>
inline Eigen::Matrix<T, 3, 3> cofactor_derivative(const Eigen::Matrix<T, 3, 3>& F, const Eigen::Matrix<T, 3, 3>& dF) {
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
