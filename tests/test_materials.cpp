// Constitutive models: zero stress at rest, rotation invariance of the energy, P = dPsi/dF and
// dP = d(P)[dF] by finite differences (in double), objectivity, tau = P F^T, finite stress for
// inverted F; return mappings land on their yield surface, are idempotent and objective.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "core/exec/simd.hpp"
#include "core/materials/material.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "kernels/material_update.hpp"

using namespace amalgam;

namespace {
Mat3 random_rotation(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Mat3 A;
  for (int i = 0; i < 9; ++i) A(i) = Real(u(rng));
  return polar_rotation(A);
}
Mat3 random_F(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  Mat3 F = Mat3::Identity();
  for (int i = 0; i < 9; ++i) F(i) += Real(u(rng));
  return F;
}
// Every model, each plain and melting (at 300 K), with a bulk modulus.
std::vector<MaterialParams> every_model_plain_and_melting(const Lame& l) {
  std::vector<MaterialParams> out;
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k)
    for (int melting = 0; melting < 2; ++melting) {
      MaterialParams m{MaterialModel(k), l.mu, l.lambda, 1000};
      m.bulk = Real(1e5);
      if (melting)
        m.melting = true, m.melting_point = 300, m.liquid_bulk = Real(1e4), m.liquid_viscosity = 5;
      out.push_back(m);
    }
  return out;
}
template <class M>
void check_model(const M& m) {
  std::mt19937 rng(5);
  EXPECT_LT(double(m.first_piola(Mat3::Identity()).norm()), 1e-5);
  EXPECT_LT(double(m.kirchhoff(Mat3::Identity()).norm()), 1e-5);
  EXPECT_NEAR(double(m.energy(Mat3::Identity())), 0.0, 1e-6);
  for (int t = 0; t < 200; ++t) {
    const Mat3 F = random_F(rng), R = random_rotation(rng);
    const double e = double(m.energy(F));
    EXPECT_NEAR(double(m.energy(R * F)), e, 1e-4 * (1 + std::abs(e)))
        << "energy not rotation invariant";
    EXPECT_LT(double((m.first_piola(R * F) - R * m.first_piola(F)).norm()),
              1e-4 * (1 + double(m.first_piola(F).norm())));  // objectivity
    EXPECT_LT(double((m.kirchhoff(F) - m.first_piola(F) * F.transpose()).norm()),
              1e-4 * (1 + double(m.kirchhoff(F).norm())));
  }
}

// P = dPsi/dF by five-point central differences, in double whatever the build's Real.
template <class M>
void check_gradient(const M& m, double min_det = -1e9) {
  std::mt19937 rng(6);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  for (int t = 0; t < 200; ++t) {
    Mat3d F = Mat3d::Identity();
    for (int i = 0; i < 9; ++i) F(i) += u(rng);
    if (t % 4 == 0) F.col(2) *= -0.2;  // inverted (fixed corotated) / clamped region check below
    if (F.determinant() <= 0.05 && std::is_same<M, NeoHookeanT<double>>::value) continue;
    if (F.determinant() <= min_det) continue;
    const Mat3d P = m.first_piola(F);
    const double h = 1e-4;
    for (int i = 0; i < 9; ++i) {
      auto psi = [&](double s) {
        Mat3d G = F;
        G(i) += s * h;
        return m.energy(G);
      };
      const double fd = (psi(-2) - 8 * psi(-1) + 8 * psi(1) - psi(2)) / (12.0 * h);
      EXPECT_NEAR(fd, P(i), 1e-6 * (1 + std::abs(P(i)))) << "t=" << t << " i=" << i;
    }
  }
}

// d/ds P(F + s dF) at s = 0 by five-point central differences.
template <class M>
Mat3d fd_dP(const M& m, const Mat3d& F, const Mat3d& dF) {
  const double h = 1e-5;
  auto P = [&](double s) { return Mat3d(m.first_piola(F + s * h * dF)); };
  return (P(-2) - 8 * P(-1) + 8 * P(1) - P(2)) / (12.0 * h);
}

// dP(F)[dF] against fd_dP for random F and dF, in double. `min_det` skips F outside a model's
// smooth domain (neo-Hookean's clamp at small J).
template <class M>
void check_dP(const M& m, double min_det = -1e9) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  int checked = 0;
  for (int t = 0; t < 200; ++t) {
    Mat3d F = Mat3d::Identity(), dF;
    for (int i = 0; i < 9; ++i) F(i) += u(rng), dF(i) = u(rng);
    if (t % 4 == 0) F.col(2) *= -0.2;
    if (F.determinant() <= min_det) continue;
    const Mat3d fd = fd_dP(m, F, dF);
    const Mat3d an = m.dP(F, dF);
    EXPECT_LT((fd - an).norm(), 1e-6 * (1 + an.norm())) << "t=" << t << "\nfd=\n"
                                                        << fd << "\nan=\n"
                                                        << an;
    ++checked;
  }
  EXPECT_GT(checked, 100);
}

// The action dP at F = diag with repeated singular values (the a = (p_i - p_j)/(s_i - s_j) limit).
template <class M>
void check_dP_repeated(const M& m) {
  std::mt19937 rng(8);
  std::uniform_real_distribution<double> u(-1, 1);
  for (const Mat3d& F : {Mat3d(Mat3d::Identity()), Mat3d(Vec3d(1.2, 1.2, 0.9).asDiagonal())}) {
    Mat3d dF;
    for (int i = 0; i < 9; ++i) dF(i) = u(rng);
    const Mat3d fd = fd_dP(m, F, dF);
    EXPECT_LT((fd - m.dP(F, dF)).norm(), 1e-5 * (1 + fd.norm()));
  }
}

// Objectivity and zero stress at rest in double (for models without a Real-typed check_model).
template <class M>
void check_objective_double(const M& m) {
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  EXPECT_LT(m.first_piola(Mat3d::Identity()).norm(), 1e-12);
  EXPECT_NEAR(m.energy(Mat3d::Identity()), 0.0, 1e-12);
  for (int t = 0; t < 100; ++t) {
    Mat3d F = Mat3d::Identity(), A;
    for (int i = 0; i < 9; ++i) F(i) += u(rng), A(i) = u(rng);
    const Mat3d R = polar_rotation(A);
    EXPECT_LT((m.first_piola(R * F) - R * m.first_piola(F)).norm(),
              1e-9 * (1 + m.first_piola(F).norm()));
    EXPECT_NEAR(m.energy(R * F), m.energy(F), 1e-9 * (1 + std::abs(m.energy(F))));
  }
}
}  // namespace

TEST(Materials, FixedCorotated) {
  const Lame l = Lame::from_young_poisson(1e3, 0.3);
  check_model(FixedCorotated{l.mu, l.lambda});
  const FixedCorotatedT<double> md{double(l.mu), double(l.lambda)};
  check_gradient(md);
  check_dP(md);
  check_dP_repeated(md);
}

TEST(Materials, NeoHookean) {
  const Lame l = Lame::from_young_poisson(1e3, 0.3);
  check_model(NeoHookean{l.mu, l.lambda});
  const NeoHookeanT<double> md{double(l.mu), double(l.lambda)};
  check_gradient(md);
  check_dP(md, 0.05);
  check_dP_repeated(md);
}

TEST(Materials, StvkHencky) {
  const Lame l = Lame::from_young_poisson(1e3, 0.3);
  check_model(StvkHencky{l.mu, l.lambda});
  const StvkHenckyT<double> md{double(l.mu), double(l.lambda)};
  check_gradient(md);
  check_dP(md);
  check_dP_repeated(md);
  check_objective_double(md);
}

TEST(Materials, WeaklyCompressibleFluid) {
  const WeaklyCompressibleT<double> w{1e4, 7, 0};
  check_gradient(w, 0.05);
  check_dP(w, 0.05);
  check_objective_double(w);
  // tau = -J p(J) I, p = K/gamma (J^-gamma - 1): compressed water pushes out.
  const Mat3d F = Vec3d(0.9, 1.0, 1.0).asDiagonal();
  const double p = 1e4 / 7 * (std::pow(0.9, -7.0) - 1);
  EXPECT_NEAR(w.pressure(0.9), p, 1e-9 * p);
  EXPECT_LT((w.kirchhoff(F, Mat3d::Zero()) + 0.9 * p * Mat3d::Identity()).norm(), 1e-9 * p);
  // Newtonian viscosity: simple shear L = [[0, g, 0], 0, 0] at J = 1 gives tau_xy = eta g,
  // traceless; the F reset keeps J and drops the shear.
  const WeaklyCompressibleT<double> visc{1e4, 7, 2.0};
  Mat3d L = Mat3d::Zero();
  L(0, 1) = 3.0;
  const Mat3d tau = visc.kirchhoff(Mat3d::Identity(), L);
  EXPECT_NEAR(tau(0, 1), 6.0, 1e-12);
  EXPECT_NEAR(tau(1, 0), 6.0, 1e-12);
  EXPECT_NEAR(tau.trace(), 0.0, 1e-12);
  Mat3d G = Mat3d::Identity();
  G(0, 1) = 0.4;
  G(2, 2) = 0.8;
  WeaklyCompressibleT<double>::reset(G);
  EXPECT_LT((G - std::cbrt(0.8) * Mat3d::Identity()).norm(), 1e-12);
}

// The fluid's F reset takes J^{1/3} without libm (detail::cube_root): in float the correctly
// rounded cube root (the double std::cbrt rounded once) of every 37th float in [0.01, 1e4] (4.5
// million), exact cubes exactly, within 4 ulps in double; NaN and infinities as std::cbrt.
TEST(Materials, FluidResetCubeRootIsCorrectlyRounded) {
  long checked = 0, wrong = 0;
  float first_wrong = 0;
  for (float J = 0.01f; J < 1e4f;) {
    const float got = detail::cube_root(J), want = float(std::cbrt(double(J)));
    ++checked;
    if (std::memcmp(&got, &want, sizeof got) != 0 && wrong++ == 0) first_wrong = J;
    std::uint32_t bits;
    std::memcpy(&bits, &J, sizeof bits);
    bits += 37;
    std::memcpy(&J, &bits, sizeof bits);
  }
  EXPECT_GT(checked, 4000000);
  EXPECT_EQ(wrong, 0) << "first at J = " << first_wrong;
  for (float c : {0.25f, 0.5f, 1.0f, 2.0f, 3.0f, 10.0f}) EXPECT_EQ(detail::cube_root(c * c * c), c);
  EXPECT_TRUE(std::isnan(detail::cube_root(std::nanf(""))));
  EXPECT_EQ(detail::cube_root(std::numeric_limits<float>::infinity()),
            std::numeric_limits<float>::infinity());
  double worst = 0;
  for (int i = 0; i <= 100000; ++i) {
    const double J = 0.01 * std::pow(1e6, i / 1e5), want = std::cbrt(J);
    worst = std::max(
        worst, std::abs(detail::cube_root(J) - want) / (std::nextafter(want, 2 * want) - want));
  }
  EXPECT_LE(worst, 4.0);
  Eigen::Matrix3f F;
  F << 1.1f, 0.3f, 0, 0, 0.95f, 0.2f, 0.1f, 0, 0.9f;
  const float J = F.determinant();
  WeaklyCompressibleT<float>::reset(F);
  EXPECT_EQ(F, (float(std::cbrt(double(J))) * Eigen::Matrix3f::Identity()).eval());
}

// A fluid run keeping J alone advances it as det((I + A) F) = det(I + A) J (A = dt grad v) from
// the small terms of det(I + A) - 1 (WeaklyCompressibleT::advance_J). In float against the
// double product, over |A| from 1e-7 (a substep at rest) to 0.1 (a CFL-limited splash): within
// one ulp of the result; dropping the 2x2 minors or det A is off by ~|A|^2 or |A|^3 (above a
// float ulp of J for |A| >= 1e-2). The clamp: never below kMinJ, a NaN kept for the guard.
TEST(Materials, FluidVolumeRatioAdvancesAsDetOfTheUpdate) {
  using W = WeaklyCompressibleT<float>;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (const double scale : {1e-7, 1e-5, 1e-3, 1e-2, 0.1}) {
    double worst = 0, worst_no_m2 = 0, worst_no_det = 0;
    for (int t = 0; t < 20000; ++t) {
      const float J = float(0.7 + 0.6 * (u(rng) + 1) / 2);
      float a[3][3], z[3][3] = {};
      Mat3d A;
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) A(r, c) = a[r][c] = float(scale * u(rng));
      const double want = double(J) * (Mat3d::Identity() + A).determinant();
      const double ulp = std::nextafter(float(want), 2.0f) - float(want);
      worst = std::max(worst, std::abs(double(W::advance_J(J, a)) - want) / ulp);
      // What the terms left out would have cost: 2x2 minors sum m2, det A.
      const double tr = A.trace(), det = A.determinant();
      const double m2 = (A(0, 0) * A(1, 1) - A(0, 1) * A(1, 0)) +
                        (A(0, 0) * A(2, 2) - A(0, 2) * A(2, 0)) +
                        (A(1, 1) * A(2, 2) - A(1, 2) * A(2, 1));
      EXPECT_NEAR(double(J) * (1 + tr + m2 + det), want, 1e-12);  // Cayley-Hamilton
      worst_no_m2 = std::max(worst_no_m2, std::abs(double(J) * m2) / ulp);
      worst_no_det = std::max(worst_no_det, std::abs(double(J) * det) / ulp);
      EXPECT_EQ(W::advance_J(J, z), J);
    }
    std::printf("|A| <= %.0e: worst %.3f ulp; m2 alone %.3g ulp, det A alone %.3g ulp\n", scale,
                worst, worst_no_m2, worst_no_det);
    EXPECT_LE(worst, 1.0) << "scale " << scale;
    if (scale >= 1e-2) {
      EXPECT_GT(worst_no_m2, 10.0) << "scale " << scale;
    }
    if (scale >= 0.1) {
      EXPECT_GT(worst_no_det, 10.0) << "scale " << scale;
    }
  }
  float squash[3][3] = {{-0.9f, 0, 0}, {0, 0, 0}, {0, 0, 0}};
  EXPECT_EQ(W::advance_J(0.05f, squash), W::kMinJ);  // 0.005 clamped
  EXPECT_EQ(W::advance_J(W::kMinJ, squash), W::kMinJ);
  const float grow[3][3] = {{0.5f, 0, 0}, {0, 0, 0}, {0, 0, 0}};
  EXPECT_EQ(W::advance_J(W::kMinJ, grow), 1.5f * W::kMinJ);  // leaves the clamp when expanding
  EXPECT_TRUE(std::isnan(W::advance_J(std::nanf(""), grow)));
  squash[1][2] = std::nanf("");
  EXPECT_TRUE(std::isnan(W::advance_J(1.0f, squash)));
}

// The Tait pressure of an integer gamma by products (detail::inverse_power_minus_one), against
// the double pow: a few float ulps relative to p everywhere, in particular as J -> 1, where
// powf(J, -gamma) - 1 cancels (worst 0.14 relative for gamma = 7 on the same J); a non-integer
// gamma keeps pow.
TEST(Materials, TaitPressureKeepsItsDigitsNearRest) {
  for (int gamma : {1, 2, 3, 7, 20}) {
    const WeaklyCompressibleT<float> w{2e5f, float(gamma), 0};
    double worst = 0, worst_pow = 0;
    for (int i = 0; i < 400000; ++i) {
      // Half the samples over [0.01, 5], half within 2e-3 of J = 1 (rest, where water lives).
      const float J = i % 2 ? 0.01f + 4.99f * float(i) / 4e5f : 1.0f + (float(i) - 2e5f) * 1e-8f;
      const double ref = 2e5 / gamma * (std::pow(double(J), -double(gamma)) - 1);
      if (ref == 0 || std::abs(ref) > 1e37) continue;
      worst = std::max(worst, std::abs(double(w.pressure(J)) - ref) / std::abs(ref));
      const float by_pow = 2e5f / float(gamma) * (std::pow(J, -float(gamma)) - 1.0f);
      worst_pow = std::max(worst_pow, std::abs(double(by_pow) - ref) / std::abs(ref));
    }
    EXPECT_LT(worst, 2e-6) << "gamma " << gamma;
    if (gamma >= 2) EXPECT_GT(worst_pow, 1e-4) << "gamma " << gamma << ": the cancellation";
  }
  const WeaklyCompressibleT<double> frac{1e4, 7.5, 0};
  EXPECT_NEAR(frac.pressure(0.9), 1e4 / 7.5 * (std::pow(0.9, -7.5) - 1), 1e-9);
  const WeaklyCompressibleT<float> f7{1e4f, 7, 0};
  EXPECT_EQ(f7.pressure(1.0f), 0.0f);
  EXPECT_EQ(f7.pressure(0.0f), f7.pressure(WeaklyCompressibleT<float>::kMinJ));
  EXPECT_TRUE(std::isnan(f7.pressure(std::nanf(""))));
  EXPECT_EQ(f7.pressure(1e30f), -1e4f / 7);
}

// Kelvin-Voigt damping of solids: tau_v = J eta (L + L^T); zero for a rigid spin (L skew), so
// it damps deformation, never rigid rotation; without viscosity the stress ignores L.
TEST(Materials, SolidViscosityDampsDeformationNotRotation) {
  MaterialParams m;
  m.model = MaterialModel::NeoHookean;
  m.mu = 1000, m.lambda = 2000, m.viscosity = 5;
  Mat3 F;
  F << 1.1, 0.05, 0, 0, 0.95, 0.02, 0.01, 0, 1.02;
  const Mat3 elastic = m.solid_kirchhoff(F, 0);
  Mat3 spin;
  spin << 0, -3, 1, 3, 0, -2, -1, 2, 0;
  EXPECT_LT((m.kirchhoff(F, spin, 0, 0) - elastic).norm(), 1e-3);
  Mat3 L = Mat3::Zero();
  L(0, 0) = 2, L(0, 1) = 1;
  Mat3 expect = L + L.transpose();
  expect *= F.determinant() * m.viscosity;
  EXPECT_LT((m.kirchhoff(F, L, 0, 0) - elastic - expect).norm(), 1e-3);
  m.viscosity = 0;
  EXPECT_LT((m.kirchhoff(F, L, 0, 0) - elastic).norm(), 1e-6);
  EXPECT_NEAR(double(MaterialParams{}.kinematic_viscosity()), 0.0, 0.0);
}

TEST(Materials, SnowHardenedElasticity) {
  const SnowT<double> s{400, 600, 0.025, 0.0075, 10};
  EXPECT_DOUBLE_EQ(s.hardening_factor(1.0), 1.0);
  EXPECT_NEAR(s.hardening_factor(0.9), std::exp(1.0), 1e-12);  // exp(xi (1 - J_P))
  SnowT<double> capped = s;
  capped.max_hardening = 2;
  EXPECT_DOUBLE_EQ(capped.hardening_factor(0.9), 2.0);
  EXPECT_NEAR(capped.hardening_factor(1.05), std::exp(-0.5), 1e-12);  // softening is not capped
  const FixedCorotatedT<double> e = s.elastic(0.95);
  EXPECT_NEAR(e.mu, 400 * std::exp(0.5), 1e-9);
  EXPECT_NEAR(e.lambda, 600 * std::exp(0.5), 1e-9);
  check_gradient(e);
  check_dP(e);
}

TEST(Materials, FixedCorotatedFiniteAndRestoringWhenInverted) {
  const Lame l = Lame::from_young_poisson(1e3, 0.3);
  const FixedCorotated m{l.mu, l.lambda};
  const Mat3 F = Vec3(1, 1, Real(-0.5)).asDiagonal();  // inverted along z
  const Mat3 P = m.first_piola(F);
  EXPECT_TRUE(P.allFinite());
  // The energy decreases when the inverted direction is pushed back towards +1.
  Mat3 F2 = F;
  F2(2, 2) += Real(0.1);
  EXPECT_LT(m.energy(F2), m.energy(F));
}

TEST(Materials, LameFromYoungPoisson) {
  const Lame l = Lame::from_young_poisson(2.0, 0.25);
  EXPECT_NEAR(double(l.mu), 0.8, 1e-6);
  EXPECT_NEAR(double(l.lambda), 0.8, 1e-6);
}

namespace {
Mat3d random_trial_F(std::mt19937& rng, double amp) {
  std::uniform_real_distribution<double> u(-amp, amp);
  Mat3d F = Mat3d::Identity();
  for (int i = 0; i < 9; ++i) F(i) += u(rng);
  return F;
}
Mat3d random_rotation_d(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Mat3d A;
  for (int i = 0; i < 9; ++i) A(i) = u(rng);
  return polar_rotation(A);
}
// A projection is idempotent: projecting its result again changes neither F nor the state.
template <class Model>
void check_idempotent_and_objective(const Model& m, double init_state, double amp,
                                    int* projected_count) {
  std::mt19937 rng(11);
  for (int t = 0; t < 300; ++t) {
    Mat3d F = random_trial_F(rng, amp);
    double st = init_state;
    const Mat3d R = random_rotation_d(rng);
    Mat3d RF = R * F;
    double st_r = init_state;
    const bool changed = m.project(F, st);
    m.project(RF, st_r);
    if (changed) ++*projected_count;
    // objective: project(R F) = R project(F), same state
    EXPECT_LT((RF - R * F).norm(), 1e-9) << "t=" << t;
    EXPECT_NEAR(st_r, st, 1e-9);
    const Mat3d F1 = F;
    const double s1 = st;
    m.project(F, st);
    EXPECT_LT((F - F1).norm(), 1e-9) << "not idempotent, t=" << t;
    EXPECT_NEAR(st, s1, 1e-9);
  }
}
Vec3d log_sigma(const Mat3d& F) {
  const Vec3d s = svd3(F).sigma;
  return Vec3d(std::log(s[0]), std::log(s[1]), std::log(s[2]));
}
}  // namespace

TEST(Plasticity, SnowClampsSingularValuesAndConservesTotalVolume) {
  const SnowT<double> s{400, 600, 0.025, 0.0075, 10};
  int projected = 0;
  check_idempotent_and_objective(s, 1.0, 0.1, &projected);
  EXPECT_GT(projected, 200);
  std::mt19937 rng(12);
  for (int t = 0; t < 200; ++t) {
    Mat3d F = random_trial_F(rng, 0.1);
    const double J0 = F.determinant();
    double JP = 1.0;
    if (!s.project(F, JP)) continue;
    const Vec3d sig = svd3(F).sigma;
    bool on_bound = false;
    for (int i = 0; i < 3; ++i) {
      EXPECT_GE(sig[i], 1 - 0.025 - 1e-12);
      EXPECT_LE(sig[i], 1 + 0.0075 + 1e-12);
      on_bound |= std::abs(sig[i] - (1 - 0.025)) < 1e-12 || std::abs(sig[i] - (1 + 0.0075)) < 1e-12;
    }
    EXPECT_TRUE(on_bound);                         // lands on the yield surface (a clamp bound)
    EXPECT_NEAR(F.determinant() * JP, J0, 1e-12);  // J_E J_P = J
  }
}

TEST(Plasticity, DruckerPragerLandsOnConeAndIsIdempotent) {
  const Lame l = Lame::from_young_poisson(3.5e5, 0.3);
  for (const double cohesion : {0.0, 200.0}) {
    const double phi = 30 * M_PI / 180;
    DruckerPragerT<double> dp{double(l.mu), double(l.lambda),
                              DruckerPragerT<double>::friction_alpha(phi),
                              DruckerPragerT<double>::apex_trace(l.mu, l.lambda, phi, cohesion)};
    int projected = 0;
    check_idempotent_and_objective(dp, 0.0, 0.05, &projected);
    EXPECT_GT(projected, 100);
    std::mt19937 rng(13);
    int sheared = 0, apex = 0;
    for (int t = 0; t < 500; ++t) {
      Mat3d F = random_trial_F(rng, 0.05);
      const Vec3d e0 = log_sigma(F);
      double vc = 0;
      const bool changed = dp.project(F, vc);
      const Vec3d e = log_sigma(F);
      EXPECT_LE(dp.yield(e), 1e-9);  // inside or on the cone
      if (!changed) continue;
      if (e0.sum() >= dp.trace_c) {  // case II: cone apex, volume gain recorded
        ++apex;
        EXPECT_NEAR(e.sum(), dp.trace_c, 1e-9);
        EXPECT_NEAR(vc, e0.sum() - dp.trace_c, 1e-9);
        EXPECT_LT((e - Vec3d::Constant(dp.trace_c / 3)).norm(), 1e-9);
      } else {  // case III: on the cone, volume unchanged
        ++sheared;
        EXPECT_NEAR(dp.yield(e), 0.0, 1e-9);
        EXPECT_NEAR(e.sum(), e0.sum(), 1e-9);
        EXPECT_NEAR(vc, 0.0, 1e-12);
      }
    }
    EXPECT_GT(sheared, 20);
    EXPECT_GT(apex, 20);
  }
}

TEST(Plasticity, DruckerPragerVolumeCorrectionGivesBackGainedVolume) {
  const Lame l = Lame::from_young_poisson(3.5e5, 0.3);
  const DruckerPragerT<double> dp{double(l.mu), double(l.lambda),
                                  DruckerPragerT<double>::friction_alpha(0.5), 0};
  // Expanded by 3 % in volume: projected to the apex (stress free), v_c records log 1.03.
  Mat3d F = std::cbrt(1.03) * Mat3d::Identity();
  double vc = 0;
  EXPECT_TRUE(dp.project(F, vc));
  EXPECT_LT((F - Mat3d::Identity()).norm(), 1e-12);
  EXPECT_NEAR(vc, std::log(1.03), 1e-12);
  // Compressing by 1 % consumes 1 % of the gain and stays stress free (apex again).
  F = std::cbrt(0.99) * Mat3d::Identity();
  EXPECT_TRUE(dp.project(F, vc));
  EXPECT_LT((F - Mat3d::Identity()).norm(), 1e-12);
  EXPECT_NEAR(vc, std::log(1.03) + std::log(0.99), 1e-12);
  // Without volume correction the same compression is resisted elastically.
  DruckerPragerT<double> plain = dp;
  plain.volume_correction = false;
  Mat3d G = std::cbrt(0.99) * Mat3d::Identity();
  double v2 = 0;
  EXPECT_FALSE(plain.project(G, v2));
  EXPECT_NEAR(G.determinant(), 0.99, 1e-12);
}

TEST(Plasticity, VonMisesRadialReturnWithHardening) {
  const Lame l = Lame::from_young_poisson(2e6, 0.3);
  const VonMisesT<double> vm{double(l.mu), double(l.lambda), 1e4, 5e4};
  int projected = 0;
  check_idempotent_and_objective(vm, 0.0, 0.05, &projected);
  EXPECT_GT(projected, 100);
  std::mt19937 rng(14);
  for (int t = 0; t < 300; ++t) {
    Mat3d F = random_trial_F(rng, 0.05);
    const double J0 = F.determinant();
    const double a0 = 0.01 * (t % 3);
    double a = a0;
    if (!vm.project(F, a)) continue;
    EXPECT_NEAR(vm.yield(log_sigma(F), a), 0.0, 1e-6);  // on the (hardened) yield surface
    EXPECT_GT(a, a0);                                   // plastic strain accumulates
    EXPECT_NEAR(F.determinant(), J0, 1e-9 * J0);        // plastic flow is isochoric
  }
}

TEST(Materials, EveryModelIsStressFreeAtRest) {
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k) {
    MaterialParams m{MaterialModel(k), l.mu, l.lambda, 1000};
    m.bulk = Real(1e5);
    m.viscosity = Real(0.1);
    m.friction_alpha = Real(0.4);
    m.yield_stress = Real(1e3);
    Real plastic = m.initial_plastic();
    EXPECT_LT(double(m.kirchhoff(Mat3::Identity(), Mat3::Zero(), plastic, 0).norm()), 1e-6)
        << material_model_name(m.model);
    EXPECT_NEAR(double(m.energy(Mat3::Identity(), plastic, 0)), 0.0, 1e-6)
        << material_model_name(m.model);
    Mat3 F = Mat3::Identity();
    m.project(F, plastic, 0);
    EXPECT_LT(double((F - Mat3::Identity()).norm()), 1e-6) << material_model_name(m.model);
    EXPECT_EQ(plastic, m.initial_plastic());
  }
}

TEST(Materials, MeltingSwitchesToViscousLiquid) {
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  MaterialParams m{MaterialModel::NeoHookean, l.mu, l.lambda, 1000};
  m.melting = true;
  m.melting_point = 300;
  m.liquid_bulk = Real(1e4);
  m.liquid_viscosity = 5;
  Mat3 F = Mat3::Identity();
  F(0, 1) = Real(0.2);  // sheared solid
  Real plastic = 0;
  EXPECT_GT(double(m.kirchhoff(F, Mat3::Zero(), plastic, 290).norm()),
            1e3);                            // elastic shear stress
  EXPECT_FALSE(m.project(F, plastic, 290));  // solid keeps its shear
  EXPECT_TRUE(m.project(F, plastic, 310));   // melted: F reset
  EXPECT_LT(double((F - Mat3::Identity()).norm()), 1e-6);
  Mat3 L = Mat3::Zero();
  L(0, 1) = 1;
  EXPECT_NEAR(double(m.kirchhoff(F, L, plastic, 310)(0, 1)), 5.0, 1e-4);  // eta * shear rate
  EXPECT_GT(m.wave_speed(), Real(0));
  EXPECT_NEAR(double(m.kinematic_viscosity()), 5e-3, 1e-9);
}

namespace {
// Model k with its parameters set (fluid bulk, sand friction, von Mises yield): variant 0 plain,
// 1 viscous, 2 melting at 300 K into a viscous liquid.
MaterialParams model_variant(MaterialModel k, int variant, const Lame& l) {
  MaterialParams m{k, l.mu, l.lambda, 1000};
  m.bulk = Real(1e5);
  m.friction_alpha = Real(0.4);
  m.yield_stress = Real(1e3);
  m.viscosity = variant == 1 ? Real(0.1) : Real(0);
  if (variant == 2)
    m.melting = true, m.melting_point = 300, m.liquid_bulk = Real(1e4), m.liquid_viscosity = 5;
  return m;
}
}  // namespace

// P2G takes the stresses of several particles at once (kirchhoff_lanes: the fixed corotated
// rotations one per vector lane). Every model, with viscosity, snow's per-particle hardening and a
// melting point crossed inside a batch, must give bitwise the one-particle kirchhoff().
TEST(Materials, KirchhoffOfABatchIsBitwiseThatOfOneParticle) {
  constexpr int W = lanes::kN<Real>;
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int compared = 0;
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k)
    for (int variant = 0; variant < 3; ++variant) {
      const MaterialParams m = model_variant(MaterialModel(k), variant, l);
      for (int t = 0; t < 200; ++t) {
        const int n = 1 + t % W;
        Mat3 F[W], L[W], tau[W];
        Real plastic[W], temperature[W];
        for (int i = 0; i < n; ++i) {
          F[i] = random_F(rng);
          if (t % 5 == 0 && i == 0) F[i].col(2) *= Real(-1);  // inverted: the SVD fallback
          L[i] = random_F(rng) - Mat3::Identity();
          plastic[i] =
              m.model == MaterialModel::Snow ? Real(1 + 0.05 * u(rng)) : m.initial_plastic();
          temperature[i] = Real(300 + 5 * u(rng));  // some lanes melted, some not
        }
        m.kirchhoff_lanes(F, L, plastic, temperature, tau, n);
        for (int i = 0; i < n; ++i) {
          const Mat3 one = m.kirchhoff(F[i], L[i], plastic[i], temperature[i]);
          ASSERT_EQ(0, std::memcmp(one.data(), tau[i].data(), sizeof(Mat3)))
              << material_model_name(m.model) << " variant " << variant << " lane " << i << "\n"
              << one << "\n"
              << tau[i];
          ++compared;
        }
      }
    }
  EXPECT_GT(compared, 1000);
}

// P2G's stresses of particles keeping b - I (kirchhoff_lanes_b: for the fixed corotated models the
// Cholesky factors go from b to the stress in registers, never stored) are bitwise the
// one-particle kirchhoff() of each particle's factor b_factor(d), for every model and variant, in
// full and partial groups, with nearly flat b among them (the polar iteration's SVD fallback,
// taken from the lanes) and b that is not positive definite (NaN, carried as the stored path
// carries it).
TEST(Materials, KirchhoffOfBIsBitwiseThatOfItsFactor) {
  constexpr int W = lanes::kN<Real>;
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  std::mt19937 rng(37);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int compared = 0, flat = 0;
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k)
    for (int variant = 0; variant < 3; ++variant) {
      const MaterialParams m = model_variant(MaterialModel(k), variant, l);
      const bool registers =
          (m.model == MaterialModel::FixedCorotated || m.model == MaterialModel::Snow) &&
          variant == 0;
      for (int t = 0; t < 200; ++t) {
        const int n = 1 + t % W;
        SymDev d[W];
        Mat3 L[W], tau[W];
        Real plastic[W], temperature[W];
        for (int i = 0; i < n; ++i) {
          Mat3 F = random_F(rng) * random_rotation(rng);
          if (t % 3 == 0 && i == 0) F.col(1) *= Real(5e-4);  // nearly flat: SVD fallback
          d[i] = b_from_F<Real>(F.cast<double>());
          if (t % 11 == 0 && i == n - 1) d[i].e[1] = Real(-2);  // not positive definite
          // Lanes of the register path (fixed corotated, snow) that take the polar iteration's
          // SVD fallback (its test, core/math/svd3.hpp).
          const Mat3 Lb = b_factor(d[i]);
          const double n2 = double(Lb.squaredNorm());
          flat +=
              registers && Lb.allFinite() && double(Lb.determinant()) <= 2e-4 * n2 * std::sqrt(n2);
          L[i] = random_F(rng) - Mat3::Identity();
          plastic[i] =
              m.model == MaterialModel::Snow ? Real(1 + 0.05 * u(rng)) : m.initial_plastic();
          temperature[i] = Real(300 + 5 * u(rng));  // some lanes melted, some not
        }
        m.kirchhoff_lanes_b(d, L, plastic, temperature, tau, n);
        for (int i = 0; i < n; ++i) {
          const Mat3 one = m.kirchhoff(b_factor(d[i]), L[i], plastic[i], temperature[i]);
          bool same = true;  // entry by entry: bitwise, or NaN in both
          for (int e = 0; e < 9; ++e)
            same = same && (std::memcmp(&one.data()[e], &tau[i].data()[e], sizeof(Real)) == 0 ||
                            (std::isnan(one.data()[e]) && std::isnan(tau[i].data()[e])));
          ASSERT_TRUE(same) << material_model_name(m.model) << " variant " << variant << " lane "
                            << i << "\n"
                            << one << "\n"
                            << tau[i];
          ++compared;
        }
      }
    }
  std::printf("%d lanes compared, %d nearly flat on the register path\n", compared, flat);
  EXPECT_GT(compared, 1000);
  EXPECT_GT(flat, 60);
}

// The diagnostics take the elastic energies of several particles at once (energy_lanes: the SVDs
// one per vector lane). Every model, snow's per-particle hardening and a melting point crossed
// inside a batch, inverted F included, must give bitwise the one-particle energy().
TEST(Materials, EnergyOfABatchIsBitwiseThatOfOneParticle) {
  constexpr int W = lanes::kN<Real>;
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  std::mt19937 rng(23);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int compared = 0;
  for (MaterialParams m : every_model_plain_and_melting(l)) {
    for (int t = 0; t < 200; ++t) {
      const int n = 1 + t % W;
      Mat3 F[W];
      Real plastic[W], temperature[W], e[W];
      for (int i = 0; i < n; ++i) {
        F[i] = random_F(rng);
        if (t % 5 == 0 && i == 0) F[i].col(2) *= Real(-1);  // inverted: the SVD fallback
        plastic[i] = m.model == MaterialModel::Snow ? Real(1 + 0.05 * u(rng)) : m.initial_plastic();
        temperature[i] = Real(300 + 5 * u(rng));  // some lanes melted, some not
      }
      m.energy_lanes(F, plastic, temperature, e, n);
      for (int i = 0; i < n; ++i) {
        const Real one = m.energy(F[i], plastic[i], temperature[i]);
        ASSERT_EQ(0, std::memcmp(&one, &e[i], sizeof(Real)))
            << material_model_name(m.model) << " melting " << m.melting << " lane " << i << ": "
            << one << " vs " << e[i];
        ++compared;
      }
    }
  }
  EXPECT_GT(compared, 1000);
}

// The material update computes the SVDs that the plastic return mappings start from for several
// particles at once (svd3_lanes) and passes them to project(F, plastic, svd): the projected F and
// plastic state must be bitwise those of project(F, plastic, temperature), for every plastic
// model, in batches that mix projected and elastic particles.
TEST(Materials, ReturnMappingWithBatchSvdIsBitwiseThatOfOneParticle) {
  constexpr int W = lanes::kN<Real>;
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  std::mt19937 rng(22);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (MaterialModel model :
       {MaterialModel::Snow, MaterialModel::DruckerPrager, MaterialModel::VonMises}) {
    MaterialParams m{model, l.mu, l.lambda, 1000};
    m.friction_alpha = Real(0.4);
    m.yield_stress = Real(1e3);
    ASSERT_TRUE(m.project_takes_svd(300));
    int projected = 0, kept = 0;
    for (int t = 0; t < 400; ++t) {
      const int n = 1 + t % W;
      Mat3 F[W];
      Real plastic[W];
      for (int i = 0; i < n; ++i) {
        F[i] = (t + i) % 3 == 0
                   ? Mat3(Mat3::Identity() + Real(1e-4) * (random_F(rng) - Mat3::Identity()))
                   : random_F(rng);
        if (t % 5 == 0 && i == 0) F[i].col(2) *= Real(-1);  // inverted
        plastic[i] = model == MaterialModel::Snow ? Real(1 + 0.05 * u(rng)) : m.initial_plastic();
      }
      Svd3<Real> d[W];
      svd3_lanes(F, n, d);
      for (int i = 0; i < n; ++i) {
        Mat3 F1 = F[i], F2 = F[i];
        Real p1 = plastic[i], p2 = plastic[i];
        const bool c1 = m.project(F1, p1, Real(300));
        const bool c2 = m.project(F2, p2, d[i]);
        ASSERT_EQ(c1, c2);
        ASSERT_EQ(0, std::memcmp(F1.data(), F2.data(), sizeof(Mat3))) << material_model_name(model);
        ASSERT_EQ(0, std::memcmp(&p1, &p2, sizeof(Real)));
        (c1 ? projected : kept)++;
      }
    }
    EXPECT_GT(projected, 100) << material_model_name(model);
    EXPECT_GT(kept, 50) << material_model_name(model);
  }
}

// Particles that keep b = F F^T instead of F (MpmSolver::keeps_b) hand the materials the Cholesky
// factor L of b (core/math/left_cauchy_green.hpp), which is F Q for some rotation Q. That is only
// right because every model is isotropic: its stress, energy and return mapping read F only
// through b. Checked for every model (with viscosity, and melted): tau(F Q) = tau(F),
// energy(F Q) = energy(F), and the projection of F Q has the b of the projection of F, with the
// same plastic state.
TEST(Materials, EveryModelReadsFOnlyThroughB) {
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  std::mt19937 rng(31);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k)
    for (int variant = 0; variant < 3; ++variant) {
      const MaterialParams m = model_variant(MaterialModel(k), variant, l);
      for (int t = 0; t < 100; ++t) {
        Mat3 F = random_F(rng) * random_rotation(rng), L;
        for (int e = 0; e < 9; ++e) L(e) = Real(u(rng));
        if (F.determinant() < Real(0.2)) continue;  // inverted: b cannot tell (docs/benchmarks.md)
        const Mat3 Fb = b_factor(b_from_F<Real>(F.cast<double>()));
        const Real temp = t % 2 ? Real(310) : Real(290);
        const Real plastic0 = m.initial_plastic() * (1 + Real(0.1) * Real(u(rng)));
        const Mat3 tau = m.kirchhoff(F, L, plastic0, temp),
                   taub = m.kirchhoff(Fb, L, plastic0, temp);
        const double tol = std::is_same<Real, float>::value ? 2e-4 : 1e-9;
        ASSERT_LT(double((tau - taub).norm()), tol * (1 + double(tau.norm())))
            << material_model_name(m.model) << " variant " << variant << "\n"
            << F;
        const double e = double(m.energy(F, plastic0, temp));
        EXPECT_NEAR(double(m.energy(Fb, plastic0, temp)), e, tol * (1 + std::abs(e)));
        Mat3 Fp = F, Fbp = Fb;
        Real pl = plastic0, plb = plastic0;
        const bool moved = m.project(Fp, pl, temp), movedb = m.project(Fbp, plb, temp);
        EXPECT_EQ(moved, movedb) << material_model_name(m.model);
        EXPECT_NEAR(double(pl), double(plb), tol * (1 + std::abs(double(pl))));
        const Mat3d bp = Fp.cast<double>() * Fp.cast<double>().transpose(),
                    bbp = Fbp.cast<double>() * Fbp.cast<double>().transpose();
        EXPECT_LT((bp - bbp).norm(), tol * (1 + bp.norm())) << material_model_name(m.model);
      }
    }
}

// The diagnostics' elastic energies (kernels/material_update.hpp, energy_densities: the SVDs at
// the SIMD path's width) on every path this CPU runs: bitwise MaterialParams::energy per particle,
// with F, with b - I (its Cholesky factor standing in for F) and with J alone (fluids), for every
// model, melting lanes, snow's hardening, and materials changing in runs that cross the vector
// groups and the batches.
TEST(Materials, EnergyDensitiesAreBitwiseEnergyOnEverySimdPath) {
  const Lame l = Lame::from_young_poisson(1e5, 0.3);
  std::vector<MaterialParams> mats, fluids;
  for (const MaterialParams& m : every_model_plain_and_melting(l))
    (m.model == MaterialModel::Fluid ? fluids : mats).push_back(m);
  std::mt19937 rng(31);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const std::size_t n = 3 * kEnergyBatch + 11;
  std::vector<Mat3> F(n);
  std::vector<SymDev> b(n);
  std::vector<Real> plastic(n), temperature(n), J(n);
  std::vector<std::int32_t> mat(n), fluid_mat(n);
  for (std::size_t i = 0; i < n;) {  // runs of 1 to 20 particles of one material
    const auto m = std::int32_t(rng() % mats.size()), fm = std::int32_t(rng() % fluids.size());
    for (std::size_t end = std::min(n, i + 1 + rng() % 20); i < end; ++i)
      mat[i] = m, fluid_mat[i] = fm;
  }
  for (std::size_t i = 0; i < n; ++i) {
    F[i] = random_F(rng);
    if (i % 17 == 0) F[i].col(2) *= Real(-1);  // inverted: the SVD's sign convention
    const Mat3 B = F[i] * F[i].transpose();
    b[i] = {{B(0, 0) - 1, B(1, 1) - 1, B(2, 2) - 1, B(0, 1), B(0, 2), B(1, 2)}};
    plastic[i] = mats[mat[i]].model == MaterialModel::Snow ? Real(1 + 0.05 * u(rng))
                                                           : mats[mat[i]].initial_plastic();
    temperature[i] = Real(300 + 5 * u(rng));  // some melted, some not
    J[i] = Real(1 + 0.4 * u(rng));
  }
  const exec::SimdPath before = exec::simd_path();
  int paths = 0;
  for (const exec::SimdPath path : exec::supported_simd_paths()) {
    exec::set_simd_path(path);
    ++paths;
    for (int storage = 0; storage < 3; ++storage) {  // F, b - I, J
      MpmParticleView p{};
      if (storage == 0) p.F = F.data();
      if (storage == 1) p.b = b.data();
      if (storage == 2) p.J = J.data();
      p.plastic = plastic.data();
      p.temperature = temperature.data();
      p.material = storage == 2 ? fluid_mat.data() : mat.data();
      const std::vector<MaterialParams>& ms = storage == 2 ? fluids : mats;
      std::vector<Real> e(n);
      for (std::size_t q0 = 0; q0 < n; q0 += kEnergyBatch)
        energy_densities(p, ms.data(), q0, std::min(n, q0 + kEnergyBatch), e.data() + q0);
      for (std::size_t i = 0; i < n; ++i) {
        const MaterialParams& m = ms[p.material[i]];
        const Real one = storage == 2   ? m.fluid().energy_of_J(J[i])
                         : storage == 1 ? m.energy(b_factor(b[i]), plastic[i], temperature[i])
                                        : m.energy(F[i], plastic[i], temperature[i]);
        ASSERT_EQ(0, std::memcmp(&one, &e[i], sizeof(Real)))
            << exec::simd_path_name(path) << " storage " << storage << " particle " << i << " "
            << material_model_name(m.model) << ": " << one << " vs " << e[i];
      }
    }
  }
  exec::set_simd_path(before);
  EXPECT_GE(paths, 1);
}
