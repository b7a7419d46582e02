// Weakly compressible Newtonian fluid for MPM (the "water" of A-ULMPM Sec. 6 and of
// Tampubolon et al. 2017): pressure from the Tait equation of state on J = det F,
//   p(J) = K / gamma (J^{-gamma} - 1),
// energy Psi(J) = -int_1^J p(j) dj, P = dPsi/dF = -p(J) cof(F), Kirchhoff stress
//   tau = -J p I + J eta (L + L^T - 2/3 tr(L) I)   (L = grad v; Newtonian, Stokes' hypothesis)
// and the F reset F <- J^{1/3} I after every substep, so the fluid keeps no shear memory.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "core/materials/isotropic.hpp"
#include "core/math/lanes.hpp"
#include "core/math/svd3.hpp"

namespace amalgam {

namespace detail {

// J^{1/3} for the fluid's F reset, the same bits on every instruction set (IEEE adds,
// multiplies and divides only; the build has no FMA contraction). Start from the float's bits
// with the exponent divided by three (musl's cbrtf constant: within ~3 %), then Halley steps in
// double, c <- c (c^3 + 2J) / (2c^3 + J), each cubing the relative error (3e-2 -> ~1e-5 ->
// ~1e-15), rounded once to T. Float: the correctly rounded cube root of every float in
// [0.01, 1e4] (checked exhaustively; glibc's cbrtf is not for 11 % of them); double: within 4
// ulps (std::cbrt: 1). glibc's cbrtf, with its scalbnf and frexpf, was 6 % of `dam_break`'s
// profile (docs/benchmarks.md). NaN, infinities and values outside [1e-30, 1e30] (never a
// reset's J >= kMinJ but at a blow-up) go to std::cbrt.
// cube_root's parts: the starting guess from a float's bits, and its Halley steps on a double
// or on a vector of doubles (the same operations lane by lane).
inline double cube_root_guess(float J) {
  std::uint32_t bits;
  std::memcpy(&bits, &J, sizeof bits);
  bits = bits / 3 + 709958130u;
  std::memcpy(&J, &bits, sizeof bits);
  return J;
}
template <int Steps, class D>
inline D cube_root_halley(D c, D a) {
  for (int k = 0; k < Steps; ++k) {
    const D c3 = c * c * c;
    c = c * (c3 + (a + a)) / ((c3 + c3) + a);
  }
  return c;
}
template <class T>
inline constexpr int kCubeRootSteps = sizeof(T) == 4 ? 2 : 3;
template <class T>
inline bool cube_root_in_range(T J) {
  return J >= T(1e-30) && J <= T(1e30);
}

template <class T>
inline T cube_root(T J) {
  if (!cube_root_in_range(J)) return std::cbrt(J);
  return T(cube_root_halley<kCubeRootSteps<T>>(cube_root_guess(float(J)), double(J)));
}

// c[l] = cube_root(J[l]) for n <= lanes::kN<T> values, bitwise, the Halley steps a vector of
// doubles at a time (one particle's dependent divisions otherwise bound the F reset's pass).
template <class T>
inline void cube_root_lanes(const T* J, T* c, int n) {
  constexpr int kN = lanes::kN<T>, kD = lanes::kN<double>;
  using VD = lanes::V<double>;
  alignas(64) double a[kN], g[kN];
  for (int l = 0; l < kN; ++l) {
    a[l] = l < n && cube_root_in_range(J[l]) ? double(J[l]) : 1.0;
    g[l] = cube_root_guess(float(a[l]));
  }
  for (int l = 0; l < kN; l += kD) {
    VD va, vg;
    std::memcpy(&va, a + l, sizeof va);
    std::memcpy(&vg, g + l, sizeof vg);
    vg = cube_root_halley<kCubeRootSteps<T>>(vg, va);
    std::memcpy(g + l, &vg, sizeof vg);
  }
  for (int l = 0; l < n; ++l) c[l] = cube_root_in_range(J[l]) ? T(g[l]) : std::cbrt(J[l]);
}

// inverse_power_minus_one's two forms, on a scalar or a vector of lanes (S).
template <class S>
inline S inverse_power_minus_one_near(S d, int n) {
  S e = d, sq = d;  // e = (1 + d)^(bits of n so far) - 1, sq = (1 + d)^(2^k) - 1
  bool first = true;
  for (int m = n;;) {
    if (m & 1) {
      e = first ? sq : e + sq + e * sq;
      first = false;
    }
    m >>= 1;
    if (m == 0) break;
    sq = sq + sq + sq * sq;
  }
  return -e / (1 + e);
}
template <class S>
inline S inverse_power_minus_one_far(S J, int n) {
  S r = J, b = J;  // r = J^(bits of n so far), b = J^(2^k)
  bool first = true;
  for (int m = n;;) {
    if (m & 1) {
      r = first ? b : r * b;
      first = false;
    }
    m >>= 1;
    if (m == 0) break;
    b = b * b;
  }
  return 1 / r - 1;
}
// Which form: |d| max(n, 2) < 1 (a bool for a scalar, a mask for a vector of lanes).
template <class T, class S>
inline auto inverse_power_near(S d, int n) {
  return (d < 0 ? -d : d) * T(std::max(n, 2)) < T(1);
}
// J^{-n} - 1 for an integer n >= 1 without pow and without the cancellation of forming
// J^{-n} first: near J = 1 (|J - 1| max(n, 2) < 1) from d = J - 1 (exact there, Sterbenz), with
// e_k = (1 + d)^k - 1 combined by squaring as e_{a+b} = e_a + e_b + e_a e_b (no cancellation:
// the terms share their sign but for the small product) and J^{-n} - 1 = -e_n / (1 + e_n);
// elsewhere from J^n by squaring, 1 / J^n - 1, then at least 1 - e^{-1} from zero. Float,
// against double over J in [0.01, 5] and J within 1e-3 of 1: worst relative error 4.3e-7 for
// n = 7 (1.0e-6 for n = 20); powf(J, -n) - 1 loses the difference as J -> 1 (worst 0.14 for
// n = 7: rounded near 1, J^{-n} keeps few of its bits).
template <class T>
inline T inverse_power_minus_one(T J, int n) {
  const T d = J - T(1);
  return inverse_power_near<T>(d, n) ? inverse_power_minus_one_near(d, n)
                                     : inverse_power_minus_one_far(J, n);
}

}  // namespace detail

template <class T>
struct WeaklyCompressibleT {
  using M3 = Eigen::Matrix<T, 3, 3>;
  T bulk, gamma, viscosity;
  static constexpr T kMinJ = T(1e-2);  // the EOS is evaluated at J >= kMinJ

  // p(J) = K / gamma (J^{-gamma} - 1); an integer gamma (water's 7, the scenes' [1, 20]) by
  // products (detail::inverse_power_minus_one: cheaper than pow and accurate near J = 1).
  T pressure(T J) const {
    J = std::max(J, kMinJ);
    const T ratio = integer_gamma() ? detail::inverse_power_minus_one(J, int(gamma))
                                    : std::pow(J, -gamma) - T(1);
    return bulk / gamma * ratio;
  }
  bool integer_gamma() const {
    const int n = int(gamma);
    return T(n) == gamma && n >= 1 && n <= 64;
  }
  // p[l] = pressure(J[l]) for n <= lanes::kN<T> values, bitwise: both forms of an integer gamma
  // on every lane of a vector, each lane taking the one pressure() takes.
  void pressure_lanes(const T* J, T* p, int n) const {
    if (!integer_gamma()) {
      for (int l = 0; l < n; ++l) p[l] = pressure(J[l]);
      return;
    }
    using V = lanes::V<T>;
    V j = lanes::splat(T(1));
    for (int l = 0; l < n; ++l) j[l] = std::max(J[l], kMinJ);
    const int m = int(gamma);
    const V d = j - T(1);
    const auto near = detail::inverse_power_near<T>(d, m);
    const V ratio = near ? detail::inverse_power_minus_one_near(d, m)
                         : detail::inverse_power_minus_one_far(j, m);
    const V out = (bulk / gamma) * ratio;
    for (int l = 0; l < n; ++l) p[l] = out[l];
  }
  T dpressure_dJ(T J) const { return J > kMinJ ? -bulk * std::pow(J, -gamma - T(1)) : T(0); }
  T energy(const M3& F) const { return energy_of_J(F.determinant()); }
  T energy_of_J(T J) const {
    J = std::max(J, kMinJ);
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
    return kirchhoff(J, pressure(J), L);
  }
  // The same from J = det F and p = pressure(J) (kirchhoff_lanes has the pressures of several
  // particles at once: pressure_lanes).
  M3 kirchhoff(T J, T p, const M3& L) const {
    M3 tau = (-J * p) * M3::Identity();
    if (viscosity > 0) {
      const M3 D2 = L + L.transpose();
      tau += (J * viscosity) * (D2 - (D2.trace() / T(3)) * M3::Identity());
    }
    return tau;
  }
  // F <- J^{1/3} I. Returns true (F always changes unless already isotropic).
  static bool reset(M3& F) {
    F = detail::cube_root(reset_J(F)) * M3::Identity();
    return true;
  }
  // The J whose cube root reset() takes (update_material_group takes a group's roots at once).
  static T reset_J(const M3& F) { return std::max(F.determinant(), kMinJ); }
  // J = det F after F <- (I + A) F, A = dt grad v (row-major a[row][col]), for a run that keeps
  // J alone (MpmSolver::keeps_J_only): J <- J + J e with e = det(I + A) - 1 = tr A + (the
  // principal 2x2 minors of A) + det A (Cayley-Hamilton). Every term is small, so J keeps the
  // digits of its change (forming 1 + e first would round e to float's spacing around 1).
  // Clamped at kMinJ as reset_J clamps F's J; std::max keeps a NaN (the stability check then
  // names the particle) where a comparison would turn it into kMinJ.
  static T advance_J(T J, const T (&a)[3][3]) {
    const T m2 = (a[0][0] * a[1][1] - a[0][1] * a[1][0]) + (a[0][0] * a[2][2] - a[0][2] * a[2][0]) +
                 (a[1][1] * a[2][2] - a[1][2] * a[2][1]);
    const T det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) -
                  a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0]) +
                  a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    const T e = (a[0][0] + a[1][1] + a[2][2]) + (m2 + det);
    return std::max(J + J * e, kMinJ);
  }
};

}  // namespace amalgam
