// Hyperelastic constitutive models as small pure structs, templated on the scalar so tests and
// implicit solvers can evaluate them in double. Each has
//   energy(F)          strain energy density Psi (J/m^3, per reference volume)
//   first_piola(F)     P = dPsi/dF
//   dP(F, dF)          the action of dP/dF on dF (isotropic_dP, core/materials/isotropic.hpp)
//   kirchhoff(F)       tau = P F^T, what the MPM force f_i = -sum_p V_p^0 tau_p grad w_ip needs
//                      (course report, "Kirchoff corotation")
//   sigma_stress / sigma_hessian: p_i = dpsi/dsigma_i and H_ij = dp_i/dsigma_j for the SVD frame.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "core/materials/isotropic.hpp"
#include "core/math/lanes.hpp"
#include "core/math/svd3.hpp"
#include "core/math/types.hpp"

namespace amalgam {

struct Lame {
  Real mu, lambda;
  // From Young's modulus E and Poisson ratio nu (requires -1 < nu < 0.5).
  static Lame from_young_poisson(double E, double nu) {
    return {Real(E / (2.0 * (1.0 + nu))), Real(E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)))};
  }
};

// Fixed corotated (Stomakhin et al. 2012): Psi = mu |F - R|^2 + lambda/2 (J - 1)^2,
// P = 2 mu (F - R) + lambda (J - 1) J F^{-T} (course report), R from the polar decomposition with
// rotations U, V, so it stays a rotation (and P well defined) for inverted F.
template <class T>
struct FixedCorotatedT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu, lambda;

  T energy(const M3& F) const { return energy_sigma(svd3(F).sigma); }
  // The same from F's singular values (MaterialParams::energy_lanes has several SVDs at once).
  T energy_sigma(const V3& s) const {
    const T J = s.prod();
    return mu * (s - V3::Ones()).squaredNorm() + T(0.5) * lambda * (J - 1) * (J - 1);
  }
  M3 first_piola(const M3& F) const {
    const Svd3<T> d = svd3(F);
    const M3 R = d.U * d.V.transpose();
    const T J = d.sigma.prod();
    // (J - 1) J F^{-T} = (J - 1) cof(F), written through the cofactor so it is finite at J = 0.
    return T(2) * mu * (F - R) + lambda * (J - 1) * cofactor(F);
  }
  // p_i = 2 mu (s_i - 1) + lambda (J - 1) c_i with c_i = prod_{k != i} s_k (no division).
  V3 sigma_stress(const V3& s) const {
    const T J = s.prod();
    const V3 c(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
    return T(2) * mu * (s - V3::Ones()) + lambda * (J - 1) * c;
  }
  M3 sigma_hessian(const V3& s) const {
    const T J = s.prod();
    const V3 c(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
    M3 H;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        H(i, j) = i == j ? T(2) * mu + lambda * c[i] * c[i]
                         : lambda * (c[i] * c[j] + (J - 1) * s[3 - i - j]);
    return H;
  }
  M3 dP(const M3& F, const M3& dF) const {
    const Svd3<T> d = svd3(F);
    return isotropic_dP(d, sigma_stress(d.sigma), sigma_hessian(d.sigma), dF);
  }
  // tau = P F^T = 2 mu (F - R) F^T + lambda (J - 1) J I. The hot path of P2G: R by the fast
  // polar iteration (SVD only for inverted or flattened F).
  M3 kirchhoff(const M3& F) const { return kirchhoff(F, polar_rotation_fast(F)); }
  // The same with R = polar rotation of F given.
  M3 kirchhoff(const M3& F, const M3& R) const {
    M3 tau;
    tau_entries<T>(F.data(), R.data(), mu, lambda, tau.data());
    return tau;
  }
  // kirchhoff(F[l]) with Lame parameters mu[l], lambda[l] for n <= lanes::kN<T> particles at
  // once, one per vector lane (P2G's hot spot), bitwise the one-particle values.
  static void kirchhoff_lanes(const M3* F, const T* mu, const T* lambda, M3* tau, int n) {
    lanes::V<T> f[9];
    lanes::load_mat3(F, n, f);
    kirchhoff_lanes(f, mu, lambda, tau, n);
  }
  // The same given F's entries in lanes (lanes::load_mat3's layout), e.g. b's Cholesky factors
  // straight from b_factor_lanes, never stored.
  static void kirchhoff_lanes(const lanes::V<T>* f, const T* mu, const T* lambda, M3* tau, int n) {
    using V = lanes::V<T>;
    V r[9], t[9], vmu = lanes::splat(T(0)), vlambda = vmu;
    for (int l = 0; l < n; ++l) vmu[l] = mu[l], vlambda[l] = lambda[l];
    polar_rotation_fast_lanes<T>(f, n, r);
    tau_entries<V>(f, r, vmu, vlambda, t);
    lanes::store_mat3(t, n, tau);
  }
  // tau from the entries of F and R in storage order, X(i, j) = x[i + 3 j]; V = T for one particle
  // or a vector of lanes (the same operations lane by lane).
  template <class V>
  static void tau_entries(const V* f, const V* r, const V& mu, const V& lambda, V* tau) {
    V a[9];
    for (int e = 0; e < 9; ++e) a[e] = (mu + mu) * (f[e] - r[e]);  // 2 mu (F - R)
    for (int j = 0; j < 3; ++j)
      for (int i = 0; i < 3; ++i)
        tau[i + 3 * j] = a[i] * f[j] + a[i + 3] * f[j + 3] + a[i + 6] * f[j + 6];
    const V J = f[0] * (f[4] * f[8] - f[7] * f[5]) + f[3] * (f[7] * f[2] - f[1] * f[8]) +
                f[6] * (f[1] * f[5] - f[4] * f[2]);
    const V p = lambda * (J - T(1)) * J;
    tau[0] += p, tau[4] += p, tau[8] += p;
  }
  static M3 cofactor(const M3& F) { return detail::cofactor3(F); }
};

// Compressible neo-Hookean (Bonet & Wood): Psi = mu/2 (tr(F^T F) - 3) - mu log J + lambda/2 log^2 J,
// P = mu (F - F^{-T}) + lambda log(J) F^{-T}, tau = mu (F F^T - I) + lambda log(J) I.
// Defined for J > 0 only; J is clamped to kMinJ so an inverted particle is pushed back instead
// of producing NaN (dP is exact for J > kMinJ).
template <class T>
struct NeoHookeanT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu, lambda;
  static constexpr T kMinJ = T(1e-4);

  T energy(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    const T lj = std::log(J);
    return T(0.5) * mu * ((F.transpose() * F).trace() - 3) - mu * lj + T(0.5) * lambda * lj * lj;
  }
  M3 first_piola(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    const M3 FinvT = detail::cofactor3(F) / J;
    return mu * (F - FinvT) + lambda * std::log(J) * FinvT;
  }
  // dP = mu dF + (mu - lambda log J) F^{-T} dF^T F^{-T} + lambda tr(F^{-1} dF) F^{-T}.
  M3 dP(const M3& F, const M3& dF) const {
    const T J = std::max(F.determinant(), kMinJ);
    const M3 FinvT = detail::cofactor3(F) / J;
    const T lj = std::log(J);
    return mu * dF + (mu - lambda * lj) * FinvT * dF.transpose() * FinvT +
           lambda * (FinvT.cwiseProduct(dF)).sum() * FinvT;
  }
  M3 kirchhoff(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    return mu * (F * F.transpose() - M3::Identity()) + (lambda * std::log(J)) * M3::Identity();
  }
  // SVD frame: p_i = mu s_i + (lambda log J - mu) / s_i, H_ii = mu + (mu + lambda - lambda log J) / s_i^2,
  // H_ij = lambda / (s_i s_j); with J clamped at kMinJ the log J terms stop depending on sigma.
  // |s_i| is kept >= kMinSigma so a flattened particle has a large but finite stiffness.
  static constexpr T kMinSigma = T(1e-4);
  static T safe(T s) { return std::abs(s) >= kMinSigma ? s : std::copysign(kMinSigma, s); }
  V3 sigma_stress(const V3& s) const {
    const T lj = std::log(std::max(s.prod(), kMinJ));
    V3 p;
    for (int i = 0; i < 3; ++i) p[i] = mu * s[i] + (lambda * lj - mu) / safe(s[i]);
    return p;
  }
  M3 sigma_hessian(const V3& s) const {
    const T J = s.prod();
    const T lj = std::log(std::max(J, kMinJ));
    const T l = J > kMinJ ? lambda : T(0);
    M3 H;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        H(i, j) = i == j ? mu + (mu + l - lambda * lj) / (safe(s[i]) * safe(s[i]))
                         : l / (safe(s[i]) * safe(s[j]));
    return H;
  }
};

// St. Venant-Kirchhoff with Hencky strain (Klar et al. 2016, Sec. 5): with eps = log(sigma),
// Psi = mu tr(eps^2) + lambda/2 tr(eps)^2, p_i = (2 mu eps_i + lambda tr eps) / sigma_i and
// tau = U diag(2 mu eps + lambda tr eps) U^T. The elasticity under the Drucker-Prager and von
// Mises return mappings, which act on eps. log|sigma| with |sigma| >= kMinSigma keeps it
// finite for inverted or flattened F.
template <class T>
struct StvkHenckyT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu, lambda;
  static constexpr T kMinSigma = T(1e-4);

  static V3 log_strain(const V3& s) {
    return V3(std::log(std::max(std::abs(s[0]), kMinSigma)),
              std::log(std::max(std::abs(s[1]), kMinSigma)),
              std::log(std::max(std::abs(s[2]), kMinSigma)));
  }
  static T safe(T s) { return std::abs(s) >= kMinSigma ? s : std::copysign(kMinSigma, s); }
  T energy(const M3& F) const { return energy_sigma(svd3(F).sigma); }
  T energy_sigma(const V3& s) const {  // the same from F's singular values
    const V3 e = log_strain(s);
    const T tr = e.sum();
    return mu * e.squaredNorm() + T(0.5) * lambda * tr * tr;
  }
  V3 sigma_stress(const V3& s) const {
    const V3 e = log_strain(s);
    const T tr = e.sum();
    V3 p;
    for (int i = 0; i < 3; ++i) p[i] = (T(2) * mu * e[i] + lambda * tr) / safe(s[i]);
    return p;
  }
  M3 sigma_hessian(const V3& s) const {
    const V3 e = log_strain(s);
    const T tr = e.sum();
    M3 H;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        H(i, j) = i == j ? (T(2) * mu + lambda - T(2) * mu * e[i] - lambda * tr) /
                               (safe(s[i]) * safe(s[i]))
                         : lambda / (safe(s[i]) * safe(s[j]));
    return H;
  }
  M3 first_piola(const M3& F) const {
    const Svd3<T> d = svd3(F);
    return d.U * sigma_stress(d.sigma).asDiagonal() * d.V.transpose();
  }
  M3 dP(const M3& F, const M3& dF) const {
    const Svd3<T> d = svd3(F);
    return isotropic_dP(d, sigma_stress(d.sigma), sigma_hessian(d.sigma), dF);
  }
  // Kirchhoff stress from the singular values alone: tau = U diag(tau_hat) U^T.
  V3 kirchhoff_sigma(const V3& s) const {
    const V3 e = log_strain(s);
    return T(2) * mu * e + V3::Constant(lambda * e.sum());
  }
  M3 kirchhoff(const M3& F) const { return kirchhoff(svd3(F)); }
  // The same given the SVD of F (MaterialParams::kirchhoff_lanes computes several at once).
  M3 kirchhoff(const Svd3<T>& d) const {
    V3 t = kirchhoff_sigma(d.sigma);
    // sign of sigma_i (inverted F): tau = P F^T = U diag(p_i sigma_i) U^T, p_i sigma_i = tau_hat_i
    // exactly when |sigma_i| >= kMinSigma.
    for (int i = 0; i < 3; ++i)
      if (std::abs(d.sigma[i]) < kMinSigma) t[i] *= std::abs(d.sigma[i]) / kMinSigma;
    return d.U * t.asDiagonal() * d.U.transpose();
  }
};

using FixedCorotated = FixedCorotatedT<Real>;
using NeoHookean = NeoHookeanT<Real>;
using StvkHencky = StvkHenckyT<Real>;

}  // namespace amalgam
