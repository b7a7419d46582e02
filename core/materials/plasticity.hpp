// Elastoplastic return mappings as small pure structs. Each acts on the elastic part F_E of the
// multiplicative split F = F_E F_P: after the grid update gives the trial F_E, `project` maps it
// back onto the elastic domain and updates the particle's one plastic scalar. Projections are
// idempotent (projecting twice changes nothing) and land on the yield surface; they return
// whether F_E changed.
#pragma once

#include <algorithm>
#include <cmath>

#include "core/materials/elastic.hpp"
#include "core/math/svd3.hpp"

namespace amalgam {

namespace detail {
// Principal logarithmic strains log(max(sigma_i, min)) and F rebuilt from them, for the return
// mappings on Hencky strain.
template <class T>
Eigen::Matrix<T, 3, 1> log_sigma(const Svd3<T>& d, T min_sigma) {
  Eigen::Matrix<T, 3, 1> e;
  for (int i = 0; i < 3; ++i) e[i] = std::log(std::max(d.sigma[i], min_sigma));
  return e;
}
template <class T>
Eigen::Matrix<T, 3, 3> from_log_sigma(const Svd3<T>& d, const Eigen::Matrix<T, 3, 1>& e) {
  return d.U * Eigen::Matrix<T, 3, 1>(std::exp(e[0]), std::exp(e[1]), std::exp(e[2])).asDiagonal() *
         d.V.transpose();
}
}  // namespace detail

// Snow (Stomakhin et al. 2013, Sec. 5): singular values of F_E clamped to [1 - theta_c,
// 1 + theta_s] (critical compression and stretch), the rest goes to F_P; hardening scales the
// fixed-corotated Lame parameters by exp(xi (1 - J_P)) (their eq. 3). State: J_P = det F_P.
// The factor is capped at max_hardening (a production safeguard the paper does not have: snow
// packed against a wall reaches J_P ~ 0.5, factor e^5 ~ 150, and the explicit time step falls
// with its square root; measured on scenes/snowball_wall.json: dt 1.5e-4 -> 2.1e-5 s uncapped).
template <class T>
struct SnowT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu0, lambda0, theta_c, theta_s, xi;
  T max_hardening = T(1e4);

  T hardening_factor(T JP) const {
    return std::min(std::exp(std::min(xi * (T(1) - JP), T(30))), max_hardening);
  }
  FixedCorotatedT<T> elastic(T JP) const {
    const T h = hardening_factor(JP);
    return {mu0 * h, lambda0 * h};
  }
  bool project(M3& FE, T& JP) const { return project(FE, JP, svd3(FE)); }
  // The same given d = svd3(FE) (MaterialParams::project_lanes computes several at once).
  bool project(M3& FE, T& JP, const Svd3<T>& d) const {
    V3 s = d.sigma;
    const T lo = T(1) - theta_c, hi = T(1) + theta_s;
    bool clamped = false;
    for (int i = 0; i < 3; ++i) {
      const T c = std::min(std::max(s[i], lo), hi);
      clamped |= (c != s[i]);
      s[i] = c;
    }
    if (!clamped) return false;
    // F = F_E F_P is unchanged: J_P absorbs the volume change J_E,trial / J_E,new (|.|: an
    // inverted trial F_E is un-inverted by the clamp).
    JP *= std::abs(d.sigma.prod()) / s.prod();
    FE = d.U * s.asDiagonal() * d.V.transpose();
    return true;
  }
};

// Drucker-Prager granular plasticity on Hencky strain (Klar et al. 2016, Sec. 7.3 "Projection"),
// with the volume correction of Tampubolon et al. 2017 (Sec. 4.3.1). With eps = log(sigma) +
// v_c / 3, eps_hat its deviatoric part and kappa = (3 lambda + 2 mu) / (2 mu):
//   case II  tr eps >= tr_c          (separation)  eps <- tr_c / 3            (cone apex)
//   case I   dgamma <= 0             (inside)      eps unchanged
//   case III dgamma = |eps_hat| + alpha kappa (tr eps - tr_c) > 0: eps <- eps - dgamma eps_hat / |eps_hat|
// alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) (friction angle phi). Cohesion c moves the cone's
// apex into tension: tr tau_c = 3 c cot(phi), tr_c = tr tau_c / (3 lambda + 2 mu); c = 0 is Klar's
// cohesionless sand. State: v_c, the log volume gained by projections (case II) that later
// compression gives back before the sand resists again.
template <class T>
struct DruckerPragerT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu, lambda, alpha, trace_c;
  bool volume_correction = true;
  static constexpr T kMinSigma = T(1e-3);

  static T friction_alpha(T phi_radians) {
    const T s = std::sin(phi_radians);
    return std::sqrt(T(2) / T(3)) * T(2) * s / (T(3) - s);
  }
  static T apex_trace(T mu, T lambda, T phi_radians, T cohesion) {
    return cohesion > 0 ? T(3) * cohesion / std::tan(phi_radians) / (T(3) * lambda + T(2) * mu)
                        : T(0);
  }
  StvkHenckyT<T> elastic() const { return {mu, lambda}; }
  // Yield function in strain space: <= 0 inside the cone (for tr eps < tr_c).
  T yield(const V3& eps) const {
    const T tr = eps.sum();
    const V3 dev = eps - V3::Constant(tr / T(3));
    return dev.norm() + alpha * (T(3) * lambda + T(2) * mu) / (T(2) * mu) * (tr - trace_c);
  }
  bool project(M3& FE, T& vc) const { return project(FE, vc, svd3(FE)); }
  // The same given d = svd3(FE) (MaterialParams::project_lanes computes several at once).
  bool project(M3& FE, T& vc, const Svd3<T>& d) const {
    const V3 e0 = detail::log_sigma(d, kMinSigma);
    const T shift = volume_correction ? vc / T(3) : T(0);
    V3 e = e0 + V3::Constant(shift);
    const T tr = e.sum();
    if (tr >= trace_c) {
      e = V3::Constant(trace_c / T(3));
    } else {
      const V3 dev = e - V3::Constant(tr / T(3));
      const T n = dev.norm();
      const T dgamma = n + alpha * (T(3) * lambda + T(2) * mu) / (T(2) * mu) * (tr - trace_c);
      if (dgamma <= 0 || n <= T(0)) {
        // Inside the cone: only a pending volume correction (if any) is absorbed.
        if (shift == T(0) && d.sigma.minCoeff() >= kMinSigma) return false;
      } else {
        e -= (dgamma / n) * dev;
      }
    }
    // v_c <- v_c + log det F_trial - log det F_E,new (Tampubolon et al. 2017): zero after
    // cases I and III, the volume gained after case II.
    if (volume_correction) vc += e0.sum() - e.sum();
    FE = detail::from_log_sigma(d, e);
    return true;
  }
};

// Von Mises (J2) plasticity with linear isotropic hardening on Hencky strain (radial return,
// Simo & Hughes 1998, Box 3.1, in principal logarithmic strains): s = 2 mu eps_hat (deviatoric
// Kirchhoff stress), f = |s| - sqrt(2/3) (tau_y + H a); if f > 0, dlambda = f / (2 mu + 2/3 H),
// eps <- eps - dlambda eps_hat / |eps_hat|, a <- a + sqrt(2/3) dlambda. Volume is elastic.
// State: a, the equivalent plastic strain.
template <class T>
struct VonMisesT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu, lambda, yield_stress, hardening;
  static constexpr T kMinSigma = T(1e-3);

  StvkHenckyT<T> elastic() const { return {mu, lambda}; }
  T yield(const V3& eps, T a) const {
    const V3 dev = eps - V3::Constant(eps.sum() / T(3));
    return T(2) * mu * dev.norm() - std::sqrt(T(2) / T(3)) * (yield_stress + hardening * a);
  }
  bool project(M3& FE, T& a) const { return project(FE, a, svd3(FE)); }
  // The same given d = svd3(FE) (MaterialParams::project_lanes computes several at once).
  bool project(M3& FE, T& a, const Svd3<T>& d) const {
    V3 e = detail::log_sigma(d, kMinSigma);
    const V3 dev = e - V3::Constant(e.sum() / T(3));
    const T n = dev.norm();
    const T f = T(2) * mu * n - std::sqrt(T(2) / T(3)) * (yield_stress + hardening * a);
    if (f <= 0 || n <= T(0)) return false;
    const T dl = f / (T(2) * mu + T(2) / T(3) * hardening);
    e -= (dl / n) * dev;
    a += std::sqrt(T(2) / T(3)) * dl;
    FE = detail::from_log_sigma(d, e);
    return true;
  }
};

}  // namespace amalgam
