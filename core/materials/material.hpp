// One material of a scene as the kernels see it: plain values and a switch, no virtual calls.
// It dispatches to the model structs (elastic.hpp, plasticity.hpp, fluid.hpp) and adds phase
// change: a material with a melting point behaves as its solid model below it and as a viscous
// weakly compressible liquid at or above it (per-particle temperature; the melting bunny of the
// enriched-MPM paper, Fig. 11, after Stomakhin et al. 2014 without incompressibility).
//
// Per particle, besides F, a material may use one plastic scalar (`plastic`, meaning per model:
// snow J_P, sand v_c, von Mises equivalent plastic strain) and a temperature.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "core/materials/elastic.hpp"
#include "core/materials/fluid.hpp"
#include "core/materials/plasticity.hpp"
#include "core/math/lanes.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "core/math/types.hpp"

namespace amalgam {

enum class MaterialModel : std::int32_t {
  FixedCorotated = 0,
  NeoHookean = 1,
  StvkHencky = 2,
  Snow = 3,
  DruckerPrager = 4,
  VonMises = 5,
  Fluid = 6,
};
const char* material_model_name(MaterialModel m);

struct MaterialParams {
  MaterialModel model = MaterialModel::FixedCorotated;
  Real mu = 0, lambda = 0, density = 1000;
  // Snow (Stomakhin et al. 2013)
  Real theta_c = Real(2.5e-2), theta_s = Real(7.5e-3), hardening = 10, max_hardening = 10;
  // Drucker-Prager (Klar et al. 2016): alpha from the friction angle, apex from the cohesion
  Real friction_alpha = 0, apex_trace = 0;
  bool volume_correction = true;
  // Von Mises
  Real yield_stress = 0, hardening_modulus = 0;
  // Fluid (Tait EOS) and Newtonian viscosity; for solids, Kelvin-Voigt damping viscosity
  Real bulk = 0, gamma = 7, viscosity = 0;
  // Phase change: melting point (K) and the liquid it becomes; melting = false disables it
  bool melting = false;
  Real melting_point = 0, liquid_bulk = 0, liquid_viscosity = 0;

  // A particle's mass from its initial volume: MPM particles store no mass (one float product,
  // the same everywhere, so every use sees the same bits).
  Real mass(Real volume0) const { return density * volume0; }
  bool melted(Real temperature) const { return melting && temperature >= melting_point; }
  // Whether particles of this material carry a plastic scalar, and its value at rest.
  bool has_plastic_state() const {
    return model == MaterialModel::Snow || model == MaterialModel::DruckerPrager ||
           model == MaterialModel::VonMises;
  }
  Real initial_plastic() const { return model == MaterialModel::Snow ? Real(1) : Real(0); }
  // Whether the per-particle state update (return mapping, F reset) has anything to do.
  bool needs_state_update() const {
    return has_plastic_state() || model == MaterialModel::Fluid || melting;
  }

  WeaklyCompressibleT<Real> liquid() const { return {liquid_bulk, gamma, liquid_viscosity}; }
  WeaklyCompressibleT<Real> fluid() const { return {bulk, gamma, viscosity}; }

  // Kirchhoff stress tau = P F^T (+ viscous stress) given F, the velocity gradient L and the
  // particle's plastic scalar and temperature.
  Mat3 kirchhoff(const Mat3& F, const Mat3& L, Real plastic, Real temperature) const {
    if (melting && temperature >= melting_point) return liquid().kirchhoff(F, L);
    if (model == MaterialModel::Fluid) return fluid().kirchhoff(F, L);
    const Mat3 tau = solid_kirchhoff(F, plastic);
    if (viscosity <= 0) return tau;
    // Solids: Kelvin-Voigt damping sigma_v = eta (L + L^T), tau_v = J sigma_v. It vanishes for
    // rigid motion (L skew), so a spinning or translating body keeps its momentum.
    return tau + (F.determinant() * viscosity) * (L + L.transpose());
  }
  // kirchhoff() of n <= lanes::kN<Real> particles of this material, tau[l] bitwise what
  // kirchhoff(F[l], L[l], plastic[l], temperature[l]) gives. The fixed corotated models (also
  // snow's elasticity) take the rotations of all n at once, one particle per vector lane (P2G's
  // hot spot), the StVK-Hencky ones (also sand and von Mises) their SVDs, the fluid its
  // pressures; the neo-Hookean model, and any batch with a melted particle, go one particle at
  // a time.
  void kirchhoff_lanes(const Mat3* F, const Mat3* L, const Real* plastic, const Real* temperature,
                       Mat3* tau, int n) const {
    if (model == MaterialModel::Fluid && !melting) {
      Real J[lanes::kN<Real>];
      for (int l = 0; l < n; ++l) J[l] = F[l].determinant();
      fluid_kirchhoff_lanes(J, L, tau, n);
      return;
    }
    const bool hencky = model == MaterialModel::StvkHencky ||
                        model == MaterialModel::DruckerPrager || model == MaterialModel::VonMises;
    bool batch = hencky || model == MaterialModel::FixedCorotated || model == MaterialModel::Snow;
    for (int l = 0; l < n && batch && melting; ++l) batch = !melted(temperature[l]);
    if (!batch) {
      for (int l = 0; l < n; ++l) tau[l] = kirchhoff(F[l], L[l], plastic[l], temperature[l]);
      return;
    }
    if (hencky) {
      Svd3<Real> d[lanes::kN<Real>];
      svd3_lanes(F, n, d);
      for (int l = 0; l < n; ++l) tau[l] = StvkHencky{mu, lambda}.kirchhoff(d[l]);
    } else {
      Real lmu[lanes::kN<Real>], llambda[lanes::kN<Real>];
      corotated_lames(plastic, n, lmu, llambda);
      FixedCorotated::kirchhoff_lanes(F, lmu, llambda, tau, n);
    }
    if (viscosity > 0)
      for (int l = 0; l < n; ++l)
        tau[l] += (F[l].determinant() * viscosity) * (L[l] + L[l].transpose());
  }
  // kirchhoff_lanes of n <= lanes::kN<Real> particles keeping b - I (core/math/left_cauchy_green.hpp)
  // instead of F: the stresses of b's Cholesky factors, bitwise kirchhoff_lanes of the factors
  // b_factor_lanes stores. The fixed corotated models (also snow's elasticity) without viscosity
  // or melting, P2G's common case, take the factors from b's entries to the polar iteration and
  // the stress in vector registers: storing the 16 factors and gathering them back made P2G ~8 %
  // slower (docs/benchmarks.md, "P2G's part of the cost recovered").
  void kirchhoff_lanes_b(const SymDev* d, const Mat3* L, const Real* plastic,
                         const Real* temperature, Mat3* tau, int n) const {
    if ((model != MaterialModel::FixedCorotated && model != MaterialModel::Snow) || melting ||
        viscosity > 0) {
      Mat3 F[lanes::kN<Real>];
      b_factor_lanes(d, n, F);
      kirchhoff_lanes(F, L, plastic, temperature, tau, n);
      return;
    }
    Real lmu[lanes::kN<Real>], llambda[lanes::kN<Real>];
    corotated_lames(plastic, n, lmu, llambda);
    lanes::V<Real> f[9];
    b_factor_lanes(d, n, f);
    FixedCorotated::kirchhoff_lanes(f, lmu, llambda, tau, n);
  }
  // The Lame parameters of n particles of a fixed corotated model (snow's from its hardening).
  void corotated_lames(const Real* plastic, int n, Real* lmu, Real* llambda) const {
    for (int l = 0; l < n; ++l) {
      const FixedCorotated m =
          model == MaterialModel::Snow ? snow().elastic(plastic[l]) : FixedCorotated{mu, lambda};
      lmu[l] = m.mu, llambda[l] = m.lambda;
    }
  }
  // kirchhoff_lanes of n <= lanes::kN<Real> particles of this fluid (model Fluid) from their
  // J = det F alone (the fluid's stress reads nothing else of F).
  void fluid_kirchhoff_lanes(const Real* J, const Mat3* L, Mat3* tau, int n) const {
    Real pr[lanes::kN<Real>];
    const WeaklyCompressibleT<Real> f = fluid();
    f.pressure_lanes(J, pr, n);
    for (int l = 0; l < n; ++l) tau[l] = f.kirchhoff(J[l], pr[l], L[l]);
  }
  // The elastic Kirchhoff stress of a solid model (fluids: zero).
  Mat3 solid_kirchhoff(const Mat3& F, Real plastic) const {
    switch (model) {
      case MaterialModel::FixedCorotated:
        return FixedCorotated{mu, lambda}.kirchhoff(F);
      case MaterialModel::NeoHookean:
        return NeoHookean{mu, lambda}.kirchhoff(F);
      case MaterialModel::StvkHencky:
      case MaterialModel::DruckerPrager:
      case MaterialModel::VonMises:
        return StvkHencky{mu, lambda}.kirchhoff(F);
      case MaterialModel::Snow:
        return snow().elastic(plastic).kirchhoff(F);
      case MaterialModel::Fluid:
        break;
    }
    return Mat3::Zero();
  }
  // energy() of n <= lanes::kN<Real> particles of this material, out[l] bitwise what
  // energy(F[l], plastic[l], temperature[l]) gives: the SVD-based models (fixed corotated, snow,
  // the StVK-Hencky family) take their SVDs at once, one particle per vector lane (svd3_lanes is
  // bitwise svd3 lane by lane); the others, and a batch with a melted particle, one at a time.
  void energy_lanes(const Mat3* F, const Real* plastic, const Real* temperature, Real* out,
                    int n) const {
    const bool hencky = model == MaterialModel::StvkHencky ||
                        model == MaterialModel::DruckerPrager || model == MaterialModel::VonMises;
    bool batch = hencky || model == MaterialModel::FixedCorotated || model == MaterialModel::Snow;
    for (int l = 0; l < n && batch && melting; ++l) batch = !melted(temperature[l]);
    if (!batch) {
      for (int l = 0; l < n; ++l) out[l] = energy(F[l], plastic[l], temperature[l]);
      return;
    }
    Svd3<Real> d[lanes::kN<Real>];
    svd3_lanes(F, n, d);
    for (int l = 0; l < n; ++l)
      out[l] = hencky                         ? StvkHencky{mu, lambda}.energy_sigma(d[l].sigma)
               : model == MaterialModel::Snow ? snow().elastic(plastic[l]).energy_sigma(d[l].sigma)
                                              : FixedCorotated{mu, lambda}.energy_sigma(d[l].sigma);
  }
  // Elastic strain energy density per reference volume.
  Real energy(const Mat3& F, Real plastic, Real temperature) const {
    if (melting && temperature >= melting_point) return liquid().energy(F);
    switch (model) {
      case MaterialModel::FixedCorotated:
        return FixedCorotated{mu, lambda}.energy(F);
      case MaterialModel::NeoHookean:
        return NeoHookean{mu, lambda}.energy(F);
      case MaterialModel::StvkHencky:
      case MaterialModel::DruckerPrager:
      case MaterialModel::VonMises:
        return StvkHencky{mu, lambda}.energy(F);
      case MaterialModel::Snow:
        return snow().elastic(plastic).energy(F);
      case MaterialModel::Fluid:
        return fluid().energy(F);
    }
    return 0;
  }
  // The elastic energy's derivatives in the SVD frame of F (singular values s): p_i = d psi /
  // d s_i and H_ij = d p_i / d s_j, for the first Piola stress P = U diag(p) V^T and the Hessian
  // d^2 Psi / dF dF that implicit solvers need (enriched MPM eq. 15). Plastic models use their
  // elastic part (snow: hardened fixed corotated; sand, von Mises: StVK-Hencky) at the current
  // plastic state; the viscous stress of fluids is not part of the energy.
  void sigma_derivatives(const Vec3& s, Real plastic, Real temperature, Vec3& p, Mat3& H) const {
    if (melting && temperature >= melting_point) {
      p = liquid().sigma_stress(s), H = liquid().sigma_hessian(s);
      return;
    }
    switch (model) {
      case MaterialModel::FixedCorotated: {
        const FixedCorotated m{mu, lambda};
        p = m.sigma_stress(s), H = m.sigma_hessian(s);
        return;
      }
      case MaterialModel::NeoHookean: {
        const NeoHookean m{mu, lambda};
        p = m.sigma_stress(s), H = m.sigma_hessian(s);
        return;
      }
      case MaterialModel::StvkHencky:
      case MaterialModel::DruckerPrager:
      case MaterialModel::VonMises: {
        const StvkHencky m{mu, lambda};
        p = m.sigma_stress(s), H = m.sigma_hessian(s);
        return;
      }
      case MaterialModel::Snow: {
        const FixedCorotated m = snow().elastic(plastic);
        p = m.sigma_stress(s), H = m.sigma_hessian(s);
        return;
      }
      case MaterialModel::Fluid:
        p = fluid().sigma_stress(s), H = fluid().sigma_hessian(s);
        return;
    }
    p.setZero(), H.setZero();
  }
  // Return mapping / F reset after the F update; returns whether F changed.
  bool project(Mat3& F, Real& plastic, Real temperature) const {
    if (melting && temperature >= melting_point) return WeaklyCompressibleT<Real>::reset(F);
    switch (model) {
      case MaterialModel::Snow:
        return snow().project(F, plastic);
      case MaterialModel::DruckerPrager:
        return drucker_prager().project(F, plastic);
      case MaterialModel::VonMises:
        return VonMisesT<Real>{mu, lambda, yield_stress, hardening_modulus}.project(F, plastic);
      case MaterialModel::Fluid:
        return WeaklyCompressibleT<Real>::reset(F);
      default:
        return false;
    }
  }
  // Whether project() is the fluid's F reset (a fluid, or a melted particle), so a caller can
  // take the cube roots of several particles at once (detail::cube_root_lanes) and set
  // F = J^{1/3} I itself: bitwise the same.
  bool project_is_reset(Real temperature) const {
    return model == MaterialModel::Fluid || melted(temperature);
  }
  // Whether project() begins with the SVD of F (the return mappings of the plastic solids), so a
  // caller can compute the SVDs of several particles at once (svd3_lanes) and pass them in.
  bool project_takes_svd(Real temperature) const {
    return !melted(temperature) &&
           (model == MaterialModel::Snow || model == MaterialModel::DruckerPrager ||
            model == MaterialModel::VonMises);
  }
  // project() of a material with project_takes_svd, given d = svd3(F): bitwise the same.
  bool project(Mat3& F, Real& plastic, const Svd3<Real>& d) const {
    switch (model) {
      case MaterialModel::Snow:
        return snow().project(F, plastic, d);
      case MaterialModel::DruckerPrager:
        return drucker_prager().project(F, plastic, d);
      case MaterialModel::VonMises:
        return VonMisesT<Real>{mu, lambda, yield_stress, hardening_modulus}.project(F, plastic, d);
      default:
        return false;
    }
  }
  SnowT<Real> snow() const {
    SnowT<Real> s{mu, lambda, theta_c, theta_s, hardening};
    s.max_hardening = max_hardening;
    return s;
  }
  DruckerPragerT<Real> drucker_prager() const {
    DruckerPragerT<Real> d{mu, lambda, friction_alpha, apex_trace};
    d.volume_correction = volume_correction;
    return d;
  }

  // Dilatational wave speed sqrt((lambda + 2 mu) / rho) (fluid: sqrt(K / rho)) for the CFL
  // bound, the larger of solid and liquid phase; snow's hardening scales it by
  // sqrt(hardening_factor(J_P)) (see wave_speed_factor).
  Real wave_speed() const {
    Real c2 = model == MaterialModel::Fluid ? bulk / density : (lambda + 2 * mu) / density;
    if (melting) c2 = std::max(c2, liquid_bulk / density);
    return std::sqrt(c2);
  }
  Real wave_speed_factor(Real plastic) const {
    return model == MaterialModel::Snow ? std::sqrt(snow().hardening_factor(plastic)) : Real(1);
  }
  // Whether kirchhoff() reads the velocity gradient L: a viscous stress (Newtonian fluid,
  // Kelvin-Voigt solid, or the liquid phase of a melting material). Otherwise L is never read.
  bool reads_velocity_gradient() const {
    return viscosity > 0 || (melting && liquid_viscosity > 0);
  }
  // Kinematic viscosity eta / rho of the more viscous phase (explicit viscosity limits dt).
  Real kinematic_viscosity() const {
    Real eta = viscosity;  // fluid: Newtonian; solids: Kelvin-Voigt (the same explicit bound)
    if (melting) eta = std::max(eta, liquid_viscosity);
    return eta / density;
  }
};

inline const char* material_model_name(MaterialModel m) {
  switch (m) {
    case MaterialModel::FixedCorotated:
      return "fixed_corotated";
    case MaterialModel::NeoHookean:
      return "neo_hookean";
    case MaterialModel::StvkHencky:
      return "stvk_hencky";
    case MaterialModel::Snow:
      return "snow";
    case MaterialModel::DruckerPrager:
      return "drucker_prager";
    case MaterialModel::VonMises:
      return "von_mises";
    case MaterialModel::Fluid:
      return "fluid";
  }
  return "?";
}

}  // namespace amalgam
