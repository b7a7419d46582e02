// Weakly compressible Newtonian fluid for MPM (the "water" of A-ULMPM Sec. 6 and of
// Tampubolon et al. 2017): pressure from the Tait equation of state on J = det F,
//   p(J) = K / gamma (J^{-gamma} - 1),
// energy Psi(J) = -int_1^J p(j) dj, P = dPsi/dF = -p(J) cof(F), Kirchhoff stress
//   tau = -J p I + J eta (L + L^T - 2/3 tr(L) I)   (L = grad v; Newtonian, Stokes' hypothesis)
// and the F reset F <- J^{1/3} I after every substep, so the fluid keeps no shear memory.
#pragma once

#include <algorithm>
#include <cmath>

#include "core/materials/isotropic.hpp"
#include "core/math/svd3.hpp"

namespace amalgam {

template <class T>
struct WeaklyCompressibleT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  T bulk, gamma, viscosity;
  static constexpr T kMinJ = T(1e-2);  // the EOS is evaluated at J >= kMinJ

  T pressure(T J) const {
    J = std::max(J, kMinJ);
    return bulk / gamma * (std::pow(J, -gamma) - T(1));
  }
  T dpressure_dJ(T J) const { return J > kMinJ ? -bulk * std::pow(J, -gamma - T(1)) : T(0); }
  T energy(const M3& F) const {
    const T J = std::max(F.determinant(), kMinJ);
    // -int_1^J K/gamma (j^-gamma - 1) dj; gamma = 1 is the logarithmic limit.
    const T a = std::abs(gamma - T(1)) < T(1e-9)
                    ? std::log(J)
                    : (std::pow(J, T(1) - gamma) - T(1)) / (T(1) - gamma);
    return -bulk / gamma * (a - (J - T(1)));
  }
  M3 first_piola(const M3& F) const { return -pressure(F.determinant()) * detail::cofactor3(F); }
  M3 dP(const M3& F, const M3& dF) const {
    const M3 cof = detail::cofactor3(F);
    const T J = F.determinant();
    return -dpressure_dJ(J) * cof.cwiseProduct(dF).sum() * cof -
           pressure(J) * cofactor_derivative(F, dF);
  }
  // SVD frame of Psi(J), J = s0 s1 s2, c_i = J / s_i: p_i = -p(J) c_i,
  // H_ii = -p'(J) c_i^2, H_ij = -p'(J) c_i c_j - p(J) s_k (k the third index).
  using V3 = Eigen::Matrix<T, 3, 1>;
  V3 sigma_stress(const V3& s) const {
    const V3 c(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
    return -pressure(s.prod()) * c;
  }
  M3 sigma_hessian(const V3& s) const {
    const T J = s.prod(), pr = pressure(J), dp = dpressure_dJ(J);
    const V3 c(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
    M3 H;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j)
        H(i, j) = i == j ? -dp * c[i] * c[i] : -dp * c[i] * c[j] - pr * s[3 - i - j];
    return H;
  }
  M3 kirchhoff(const M3& F, const M3& L) const {
    const T J = F.determinant();
    M3 tau = (-J * pressure(J)) * M3::Identity();
    if (viscosity > 0) {
      const M3 D2 = L + L.transpose();
      tau += (J * viscosity) * (D2 - (D2.trace() / T(3)) * M3::Identity());
    }
    return tau;
  }
  // F <- J^{1/3} I. Returns true (F always changes unless already isotropic).
  static bool reset(M3& F) {
    const T J = std::max(F.determinant(), kMinJ);
    F = std::cbrt(J) * M3::Identity();
    return true;
  }
};

}  // namespace amalgam
