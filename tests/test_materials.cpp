// Constitutive models: zero stress at rest, rotation invariance of the energy, P = dPsi/dF by
// finite differences (in double), tau = P F^T, and finite stress for inverted F.
#include <gtest/gtest.h>

#include <random>

#include "core/materials/elastic.hpp"

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
template <class M>
void check_model(const M& m) {
  std::mt19937 rng(5);
  EXPECT_LT(double(m.first_piola(Mat3::Identity()).norm()), 1e-5);
  EXPECT_LT(double(m.kirchhoff(Mat3::Identity()).norm()), 1e-5);
  EXPECT_NEAR(double(m.energy(Mat3::Identity())), 0.0, 1e-6);
  for (int t = 0; t < 200; ++t) {
    const Mat3 F = random_F(rng), R = random_rotation(rng);
    const double e = double(m.energy(F));
    EXPECT_NEAR(double(m.energy(R * F)), e, 1e-4 * (1 + std::abs(e))) << "energy not rotation invariant";
    EXPECT_LT(double((m.first_piola(R * F) - R * m.first_piola(F)).norm()),
              1e-4 * (1 + double(m.first_piola(F).norm())));  // objectivity
    EXPECT_LT(double((m.kirchhoff(F) - m.first_piola(F) * F.transpose()).norm()),
              1e-4 * (1 + double(m.kirchhoff(F).norm())));
  }
}

// P = dPsi/dF by five-point central differences, in double whatever the build's Real.
template <class M>
void check_gradient(const M& m) {
  std::mt19937 rng(6);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  for (int t = 0; t < 200; ++t) {
    Mat3d F = Mat3d::Identity();
    for (int i = 0; i < 9; ++i) F(i) += u(rng);
    if (t % 4 == 0) F.col(2) *= -0.2;  // inverted (fixed corotated) / clamped region check below
    if (F.determinant() <= 0.05 && std::is_same<M, NeoHookeanT<double>>::value) continue;
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
}  // namespace

TEST(Materials, FixedCorotated) {
  const Lame l = Lame::from_young_poisson(1e3, 0.3);
  check_model(FixedCorotated{l.mu, l.lambda});
  check_gradient(FixedCorotatedT<double>{double(l.mu), double(l.lambda)});
}

TEST(Materials, NeoHookean) {
  const Lame l = Lame::from_young_poisson(1e3, 0.3);
  check_model(NeoHookean{l.mu, l.lambda});
  check_gradient(NeoHookeanT<double>{double(l.mu), double(l.lambda)});
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
