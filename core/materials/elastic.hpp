// Hyperelastic constitutive models as small pure structs: energy density Psi(F), first
// Piola-Kirchhoff stress P(F) = dPsi/dF, and the Kirchhoff stress tau = P F^T that the MPM force
// f_i = -sum_p V_p^0 P_p F_p^T grad w_ip needs (course report, "Kirchoff corotation").
#pragma once

#include <cmath>
#include <cstdint>

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
// Templated on the scalar so tests and implicit solvers can evaluate it in double.
template <class T>
struct FixedCorotatedT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  using V3 = Eigen::Matrix<T, 3, 1>;
  T mu, lambda;

  T energy(const M3& F) const {
    const Svd3<T> d = svd3(F);
    const T J = d.sigma.prod();
    return mu * (d.sigma - V3::Ones()).squaredNorm() + T(0.5) * lambda * (J - 1) * (J - 1);
  }
  M3 first_piola(const M3& F) const {
    const Svd3<T> d = svd3(F);
    const M3 R = d.U * d.V.transpose();
    const T J = d.sigma.prod();
    // (J - 1) J F^{-T} = (J - 1) cof(F), written through the cofactor so it is finite at J = 0.
    return T(2) * mu * (F - R) + lambda * (J - 1) * cofactor(F);
  }
  // tau = P F^T = 2 mu (F - R) F^T + lambda (J - 1) J I. The hot path of P2G: R by the fast
  // polar iteration (SVD only for inverted or flattened F).
  M3 kirchhoff(const M3& F) const {
    const M3 R = polar_rotation_fast(F);
    const T J = F.determinant();
    return T(2) * mu * (F - R) * F.transpose() + (lambda * (J - 1) * J) * M3::Identity();
  }
  static M3 cofactor(const M3& F) { return detail::cofactor3(F); }
};

// Compressible neo-Hookean (Bonet & Wood): Psi = mu/2 (tr(F^T F) - 3) - mu log J + lambda/2 log^2 J,
// P = mu (F - F^{-T}) + lambda log(J) F^{-T}, tau = mu (F F^T - I) + lambda log(J) I.
// Defined for J > 0 only; J is clamped to kMinJ so an inverted particle is pushed back instead
// of producing NaN.
template <class T>
struct NeoHookeanT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  T mu, lambda;
  static constexpr T kMinJ = T(1e-4);

  T energy(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    const T lj = std::log(J);
    return T(0.5) * mu * ((F.transpose() * F).trace() - 3) - mu * lj + T(0.5) * lambda * lj * lj;
  }
  M3 first_piola(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    const M3 FinvT = FixedCorotatedT<T>::cofactor(F) / J;
    return mu * (F - FinvT) + lambda * std::log(J) * FinvT;
  }
  M3 kirchhoff(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    return mu * (F * F.transpose() - M3::Identity()) + (lambda * std::log(J)) * M3::Identity();
  }
};

using FixedCorotated = FixedCorotatedT<Real>;
using NeoHookean = NeoHookeanT<Real>;

enum class ElasticModel : std::int32_t { FixedCorotated = 0, NeoHookean = 1 };

// One material of a scene as the kernels see it: plain values, no virtual calls.
struct MaterialParams {
  ElasticModel model = ElasticModel::FixedCorotated;
  Real mu = 0, lambda = 0, density = 1000;

  Mat3 kirchhoff(const Mat3& F) const {
    return model == ElasticModel::NeoHookean ? NeoHookean{mu, lambda}.kirchhoff(F)
                                             : FixedCorotated{mu, lambda}.kirchhoff(F);
  }
  Real energy(const Mat3& F) const {
    return model == ElasticModel::NeoHookean ? NeoHookean{mu, lambda}.energy(F)
                                             : FixedCorotated{mu, lambda}.energy(F);
  }
  // P-wave (dilatational) speed sqrt((lambda + 2 mu) / rho): the CFL bound's material speed.
  Real wave_speed() const { return std::sqrt((lambda + 2 * mu) / density); }
};

}  // namespace amalgam
