// Maths invariants: B-spline partition of unity and linear reproduction; 3x3 SVD / polar of
// random, near-singular and inverted matrices reconstruct F with proper rotations; ExactSum is
// exact and correctly rounded whatever the order and grouping of its terms.
#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "core/hash.hpp"
#include "core/math/bspline.hpp"
#include "core/math/exact_sum.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "core/math/svd3.hpp"

using namespace amalgam;

template <int Order>
void check_weights() {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-3.0, 3.0);
  const Real dx = Real(0.1), inv_dx = Real(10);
  const Real tol = std::is_same<Real, float>::value ? Real(2e-5) : Real(1e-12);
  for (int t = 0; t < 2000; ++t) {
    const Vec3 xp(Real(u(rng)), Real(u(rng)), Real(u(rng)));
    const auto st = Stencil<Order>::at(xp, inv_dx);
    Real sum_w = 0;
    Vec3 sum_wx = Vec3::Zero(), sum_grad = Vec3::Zero();
    Mat3 sum_x_grad = Mat3::Zero(), sum_wrr = Mat3::Zero();
    for (int i = 0; i < Stencil<Order>::kN; ++i)
      for (int j = 0; j < Stencil<Order>::kN; ++j)
        for (int k = 0; k < Stencil<Order>::kN; ++k) {
          const Real w = st.weight(i, j, k);
          ASSERT_GE(w, Real(0));
          const Vec3 xi = (st.base + Vec3i(i, j, k)).template cast<Real>() * dx;
          sum_w += w;
          sum_wx += w * xi;
          sum_grad += st.gradient(i, j, k);
          sum_x_grad += xi * st.gradient(i, j, k).transpose();
          const Vec3 r = st.offset(i, j, k, dx);
          sum_wrr += w * r * r.transpose();
          ASSERT_LT((r - (xi - xp)).norm(), 1e-4);
        }
    EXPECT_NEAR(sum_w, 1, tol);                                    // partition of unity
    EXPECT_LT((sum_wx - xp).norm(), tol * 40);                     // linear reproduction
    EXPECT_LT(sum_grad.norm(), tol * 100);                         // gradient of unity
    EXPECT_LT((sum_x_grad - Mat3::Identity()).norm(), tol * 100);  // gradient of x is I
    // D_p = sum w r r^T = (dx^2 / Dinv_scale) I: the APIC/MLS inertia tensor.
    const Mat3 D = Mat3::Identity() * (dx * dx / BSpline<Order>::kDinvScale);
    EXPECT_LT((sum_wrr - D).norm(), tol * 1e-2) << "order " << Order;
  }
}

TEST(BSpline, QuadraticPartitionOfUnityAndLinearReproduction) {
  check_weights<2>();
}
TEST(BSpline, CubicPartitionOfUnityAndLinearReproduction) {
  check_weights<3>();
}

// The far flags between sorts test positions right after the pass that moved them: inside exactly
// when every stencil node lies in the block (the same answer as comparing the base itself, every
// order, positions across the block's edges); a non-finite or absurd position (a particle that
// blew up, not yet reported) is outside and never converted to int (the sanitizer suite's UBSan
// reports that), and d is written only for a particle inside.
template <int Order>
void check_stencil_in_block() {
  const Real dx = Real(0.1), inv_dx = 1 / dx;
  const Vec3i origin(8, -16, 0);
  constexpr int B = 14;
  int inside = 0;
  for (int i = -40 * 64; i < 300 * 64; ++i) {  // one axis swept across the block in 1/64 cells
    const Real s = Real(i) / 64;
    const Vec3 x(s * dx, Real(-10.3) * dx, Real(5.7) * dx);
    const int base = BSpline<Order>::base(x[0] * inv_dx);
    const int base1 = BSpline<Order>::base(x[1] * inv_dx);
    const bool in = base >= origin[0] && base + Order < origin[0] + B;
    int d[3] = {-99, -99, -99};
    ASSERT_EQ(stencil_in_block<Order>(x, inv_dx, origin, B, d), in) << s;
    ASSERT_EQ(d[0], in ? base - origin[0] : -99) << s;
    if (in) EXPECT_EQ(d[1], base1 - origin[1]);
    inside += in;
  }
  EXPECT_EQ(inside, (B - Order) * 64);  // B - Order bases, 64 positions each
  const Real inf = std::numeric_limits<Real>::infinity();
  const Real nan = std::numeric_limits<Real>::quiet_NaN();
  for (const Real bad : {nan, inf, -inf, Real(1e30), Real(-1e30)})
    for (int a = 0; a < 3; ++a) {
      Vec3 x(Real(1.4), Real(-1.0), Real(0.5));
      ASSERT_TRUE(stencil_in_block<Order>(x, inv_dx, origin, B, nullptr));
      x[a] = bad;
      int d[3] = {-99, -99, -99};
      EXPECT_FALSE(stencil_in_block<Order>(x, inv_dx, origin, B, d)) << bad;
      EXPECT_EQ(d[a], -99);
    }
}
TEST(BSpline, StencilInBlockAndPositionsThatBlewUp) {
  check_stencil_in_block<1>();
  check_stencil_in_block<2>();
  check_stencil_in_block<3>();
}

// Stencil::at computes the three axes in the lanes of one vector: the same operations as the
// axis-by-axis form, so the same bits (base, fx, weights, derivatives) for every order, at
// positions swept across cells (either side of the floor's integers, where truncation rounds up
// for negative coordinates), far from the origin and at cell boundaries to the last ulp.
template <int Order>
void check_stencil_lanes() {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-1, 1);
  const Real dx = Real(0.013), inv_dx = 1 / dx;
  std::vector<Vec3> xs;
  for (int i = -3 * 64; i <= 3 * 64; ++i) {
    const Real s = Real(i) / 64 * dx;
    xs.emplace_back(s, -s, s + Real(0.5) * dx);
  }
  for (int i = 0; i < 2000; ++i)
    xs.emplace_back(Real(u(rng)) * 50, Real(u(rng)) * 1e-3f, Real(u(rng)) * 3e3f);
  for (int c = -4; c <= 4; ++c)  // the floor's edges: (c + 1/2) dx for quadratic, c dx otherwise
    for (const Real e : {Real(c), Real(c) + Real(0.5)}) {
      const Real y = e * dx;
      for (const Real z : {std::nextafter(y, Real(-1e9)), y, std::nextafter(y, Real(1e9))})
        xs.emplace_back(z, -z, z * 3);
    }
  for (const Vec3& x : xs) {
    const Stencil<Order> a = Stencil<Order>::at(x, inv_dx),
                         b = Stencil<Order>::at_scalar(x, inv_dx);
    ASSERT_EQ(a.base, b.base) << x.transpose();
    ASSERT_EQ(std::memcmp(a.fx.data(), b.fx.data(), sizeof(Real) * 3), 0) << x.transpose();
    ASSERT_EQ(std::memcmp(a.w, b.w, sizeof(a.w)), 0) << x.transpose();
    ASSERT_EQ(std::memcmp(a.dw, b.dw, sizeof(a.dw)), 0) << x.transpose();
  }
}
TEST(BSpline, StencilLanesAreTheAxisByAxisFormBitwise) {
  check_stencil_lanes<1>();
  check_stencil_lanes<2>();
  check_stencil_lanes<3>();
}

namespace {
void expect_rotation(const Mat3& R, double tol) {
  EXPECT_LT(double((R.transpose() * R - Mat3::Identity()).norm()), tol);
  EXPECT_NEAR(double(R.determinant()), 1.0, tol);
}
void check_svd(const Mat3& F, double tol) {
  const Svd3<Real> d = svd3(F);
  expect_rotation(d.U, tol);
  expect_rotation(d.V, tol);
  const Mat3 rec = d.U * d.sigma.asDiagonal() * d.V.transpose();
  EXPECT_LT(double((rec - F).norm()), tol * std::max(1.0, double(F.norm()))) << F;
  EXPECT_GE(d.sigma[0], d.sigma[1]);
  EXPECT_GE(d.sigma[1], std::abs(d.sigma[2]) - Real(tol));
  if (F.determinant() < -tol) {
    EXPECT_LT(d.sigma[2], 0) << "inverted F keeps the negative singular value";
  }
}
}  // namespace

TEST(Svd3, RandomMatricesReconstruct) {
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-2.0, 2.0);
  const double tol = sizeof(Real) == 4 ? 2e-5 : 1e-12;
  for (int t = 0; t < 5000; ++t) {
    Mat3 F;
    for (int i = 0; i < 9; ++i) F(i) = Real(u(rng));
    check_svd(F, tol * 10);
  }
}

TEST(Svd3, NearSingularInvertedAndDegenerate) {
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const double tol = sizeof(Real) == 4 ? 5e-5 : 1e-11;
  std::vector<Mat3> cases;
  cases.push_back(Mat3::Identity());
  cases.push_back(Mat3::Zero());
  cases.push_back(Vec3(1, 1, -1).asDiagonal());    // reflection: inverted
  cases.push_back(Vec3(2, 2, 2).asDiagonal());     // repeated singular values
  cases.push_back(Vec3(1, 1e-7, 0).asDiagonal());  // rank 1
  for (int t = 0; t < 2000; ++t) {
    // F = R1 diag(s) R2 with one tiny or negative stretch: flattened and inverted elements.
    Mat3 A, B;
    for (int i = 0; i < 9; ++i) A(i) = Real(u(rng)), B(i) = Real(u(rng));
    const Mat3 R1 = polar_rotation(A), R2 = polar_rotation(B);
    const Real small = Real(std::pow(10.0, -6.0 * std::abs(u(rng))));
    Vec3 s(Real(1 + u(rng) * 0.5), Real(0.5 + std::abs(u(rng))), small * (t % 2 ? 1 : -1));
    cases.push_back(R1 * s.asDiagonal() * R2);
  }
  for (const Mat3& F : cases) check_svd(F, tol);
}

TEST(Svd3, PolarRotationOfInvertedMatrixIsProperRotation) {
  Mat3 F = Vec3(Real(1.2), Real(0.9), Real(-0.3)).asDiagonal();
  const Mat3 R = polar_rotation(F);
  expect_rotation(R, 1e-5);
  // S = R^T F must be symmetric.
  const Mat3 S = R.transpose() * F;
  EXPECT_LT(double((S - S.transpose()).norm()), 1e-5);
}

TEST(Polar, FastRotationMatchesSvdIncludingFallbacks) {
  std::mt19937 rng(8);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const double tol = sizeof(Real) == 4 ? 1e-4 : 1e-10;
  int fast = 0;
  for (int t = 0; t < 5000; ++t) {
    Mat3 F = Mat3::Identity();
    const double scale = (t % 3 == 0) ? 0.1 : (t % 3 == 1 ? 0.6 : 3.0);
    for (int i = 0; i < 9; ++i) F(i) += Real(scale * u(rng));
    if (t % 10 == 0) F.col(1) *= Real(1e-5);  // nearly flat: the SVD fallback
    const Mat3 Rf = polar_rotation_fast(F);
    const Mat3 Rs = polar_rotation(F);
    expect_rotation(Rf, tol);
    const double kappa =
        double(svd3(F).sigma[0] / std::max(std::abs(svd3(F).sigma[2]), Real(1e-30)));
    if (kappa < 1e3) {
      EXPECT_LT(double((Rf - Rs).norm()), tol * kappa) << F;
    }
    fast += F.determinant() > 0;
  }
  EXPECT_GT(fast, 1000);
}

// The lane version runs several matrices at once, one per vector lane. Each lane must give
// bitwise what the one-matrix call gives, whatever the other lanes hold: lanes that converge at
// different iterations, take the scaled first step or not, or fall back to the SVD share a batch.
template <class T>
void check_lanes_match_one_at_a_time() {
  using M = Eigen::Matrix<T, 3, 3>;
  constexpr int W = lanes::kN<T>;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<M> F;
  for (int t = 0; t < 4000; ++t) {
    M f = M::Identity();
    const double scale = (t % 4 == 0) ? 1e-3 : (t % 4 == 1 ? 0.05 : (t % 4 == 2 ? 0.6 : 3.0));
    for (int i = 0; i < 9; ++i) f(i) += T(scale * u(rng));
    if (t % 7 == 0) f.col(1) *= T(1e-5);  // nearly flat: the SVD fallback
    if (t % 11 == 0) f.col(2) *= T(-1);   // inverted: the SVD fallback
    F.push_back(f);
  }
  std::shuffle(F.begin(), F.end(), rng);
  int batches = 0, mixed = 0;
  for (std::size_t s = 0; s < F.size(); s += W) {
    const int n =
        int(std::min<std::size_t>(W, F.size() - s)) - int(batches % 2);  // also partial batches
    if (n < 1) continue;
    M R[W];
    polar_rotation_fast_lanes<T>(&F[s], R, n);
    int fallback = 0;
    for (int l = 0; l < n; ++l) {
      const M one = polar_rotation_fast<T>(F[s + l]);
      ASSERT_EQ(0, std::memcmp(one.data(), R[l].data(), sizeof(M))) << "lane " << l << " of\n"
                                                                    << F[s + l];
      fallback += F[s + l].determinant() <= 0;
    }
    mixed += fallback > 0 && fallback < n;
    ++batches;
  }
  EXPECT_GT(mixed, 50);  // batches that mix the Newton path with the SVD fallback
}

TEST(Polar, LanesGiveBitwiseTheOneMatrixResult) {
  check_lanes_match_one_at_a_time<float>();
  check_lanes_match_one_at_a_time<double>();
}

// svd3_lanes runs the SVD of several matrices at once, one per vector lane. Each lane must give
// bitwise svd3 of its matrix whatever the other lanes hold: lanes whose Jacobi sweeps stop at
// different counts, whose rotations are skipped (zero off-diagonal, zero columns), that swap
// columns or not, and NaN, zero, huge and tiny matrices share batches, also partial ones.
template <class T>
void check_svd_lanes_match_one_at_a_time() {
  using M = Eigen::Matrix<T, 3, 3>;
  constexpr int W = lanes::kN<T>;
  std::mt19937 rng(12);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<M> F;
  for (int t = 0; t < 6000; ++t) {
    M f = M::Identity();
    const double scale = (t % 4 == 0) ? 1e-4 : (t % 4 == 1 ? 0.05 : (t % 4 == 2 ? 0.6 : 3.0));
    for (int i = 0; i < 9; ++i) f(i) += T(scale * u(rng));
    if (t % 7 == 0) f.col(1) *= T(1e-6);        // nearly flat
    if (t % 11 == 0) f.col(2) *= T(-1);         // inverted
    if (t % 13 == 0) f.col(0) = f.col(2);       // rank 2
    if (t % 17 == 0) f = M::Identity() * T(2);  // repeated singular values, no rotation
    if (t % 19 == 0) f = M::Zero();             // every rotation skipped
    if (t % 23 == 0) f *= T(1e15);              // huge
    if (t % 29 == 0) f *= T(1e-15);             // tiny
    if (t % 31 == 0) f(1, 2) = std::numeric_limits<T>::quiet_NaN();
    if (t % 37 == 0) f = M(Eigen::Matrix<T, 3, 1>(T(0.5), T(3), T(1)).asDiagonal());  // sorting
    F.push_back(f);
  }
  std::shuffle(F.begin(), F.end(), rng);
  int batches = 0;
  for (std::size_t s = 0; s < F.size(); s += W) {
    const int n = int(std::min<std::size_t>(W, F.size() - s)) - int(batches % 2);
    if (n < 1) continue;
    Svd3<T> d[W];
    svd3_lanes<T>(&F[s], n, d);
    // Bitwise equal, or NaN in both (a NaN's payload and sign depend on the operand order the
    // compiler picks for a commutative operation: not part of the contract).
    const auto same = [](const T* a, const T* b, int k) {
      for (int e = 0; e < k; ++e)
        if (std::memcmp(&a[e], &b[e], sizeof(T)) != 0 && !(std::isnan(a[e]) && std::isnan(b[e])))
          return false;
      return true;
    };
    for (int l = 0; l < n; ++l) {
      const Svd3<T> one = svd3<T>(F[s + l]);
      ASSERT_TRUE(same(one.U.data(), d[l].U.data(), 9)) << "lane " << l << " of\n" << F[s + l];
      ASSERT_TRUE(same(one.V.data(), d[l].V.data(), 9)) << F[s + l];
      ASSERT_TRUE(same(one.sigma.data(), d[l].sigma.data(), 3)) << F[s + l];
    }
    ++batches;
  }
  EXPECT_GT(batches, 6000 / W - 1);
}

TEST(Svd3, LanesGiveBitwiseTheOneMatrixResult) {
  check_svd_lanes_match_one_at_a_time<float>();
  check_svd_lanes_match_one_at_a_time<double>();
}

namespace {
double exact_sum(const std::vector<double>& v) {
  ExactSum s;
  for (double x : v) s.add(x);
  return s.value();
}
std::uint64_t bits(double x) {
  std::uint64_t b;
  std::memcpy(&b, &x, sizeof b);
  return b;
}
}  // namespace

// The VDB files' content UUID (io/vdb_points.cpp) hashes each file from two starting values in
// one pass: each must be the plain FNV-1a of the bytes, in pieces as in one (the file is read in
// chunks), for any length (no word-at-a-time tail to get wrong).
TEST(Hash, FnvPairIsTwoPlainHashes) {
  std::mt19937_64 rng(5);
  std::vector<unsigned char> d(1000);
  for (auto& c : d) c = static_cast<unsigned char>(rng());
  // Known values: FNV-1a 64 of "" and "a" (the published test vectors).
  EXPECT_EQ(fnv1a64("", 0), 0xcbf29ce484222325ULL);
  EXPECT_EQ(fnv1a64("a", 1), 0xaf63dc4c8601ec8cULL);
  for (std::size_t n : {0, 1, 7, 8, 9, 333, 1000}) {
    std::uint64_t h1 = 0xcbf29ce484222325ULL, h2 = 0x84222325cbf29ce4ULL;
    const std::size_t cut = n / 3;
    fnv1a64_pair(d.data(), cut, h1, h2);
    fnv1a64_pair(d.data() + cut, n - cut, h1, h2);
    EXPECT_EQ(h1, fnv1a64(d.data(), n)) << n;
    EXPECT_EQ(h2, fnv1a64(d.data(), n, 0x84222325cbf29ce4ULL)) << n;
  }
}

// Terms a·2^b (|a| < 2^53, b in [-40, 0]) have an exact sum that is an integer times 2^-40 and
// fits in 128 bits: its correctly rounded value is the one rounding of that integer.
TEST(ExactSum, IsTheCorrectlyRoundedExactSum) {
  std::mt19937_64 rng(11);
  for (int trial = 0; trial < 200; ++trial) {
    const int n = 1 + int(rng() % 2000);
    std::vector<double> v;
    __int128 exact = 0;
    for (int i = 0; i < n; ++i) {
      const std::int64_t a =
          std::int64_t(rng() % (std::uint64_t(1) << 53)) - std::int64_t(std::uint64_t(1) << 52);
      const int b = -int(rng() % 41);
      v.push_back(std::ldexp(double(a), b));
      exact += static_cast<__int128>(a) * (static_cast<__int128>(1) << (b + 40));
    }
    const double want = std::ldexp(static_cast<double>(exact), -40);
    EXPECT_EQ(bits(exact_sum(v)), bits(want)) << "trial " << trial;
  }
}

TEST(ExactSum, RoundsOnceToNearestEven) {
  const double u = std::ldexp(1.0, -52);                    // ulp of 1
  EXPECT_EQ(exact_sum(std::vector<double>(10, 0.1)), 1.0);  // the naive sum is 1 - u
  EXPECT_EQ(exact_sum({1e300, 1.0, -1e300}), 1.0);
  EXPECT_EQ(exact_sum({1.0, u / 2}), 1.0);                             // a tie: to even
  EXPECT_EQ(exact_sum({1.0 + u, u / 2}), 1.0 + 2 * u);                 // a tie: to even
  EXPECT_EQ(exact_sum({1.0, u / 2, std::ldexp(1.0, -200)}), 1.0 + u);  // above the tie
  EXPECT_EQ(exact_sum({1.0, u / 2, -std::ldexp(1.0, -200)}), 1.0);     // below it
  EXPECT_EQ(exact_sum({-1.0, -u / 2, -std::ldexp(1.0, -200)}), -1.0 - u);
  const double big = std::numeric_limits<double>::max();
  EXPECT_EQ(exact_sum({big, big, -big}), big);  // beyond the range on the way, not at the end
  EXPECT_EQ(exact_sum({big, big}), std::numeric_limits<double>::infinity());
  EXPECT_EQ(exact_sum({-big, -big}), -std::numeric_limits<double>::infinity());
  const double tiny = std::numeric_limits<double>::denorm_min();
  EXPECT_EQ(exact_sum({tiny, tiny, tiny}), 3 * tiny);
  EXPECT_EQ(exact_sum({-tiny, std::numeric_limits<double>::min()}),
            std::numeric_limits<double>::min() - tiny);
  EXPECT_EQ(bits(exact_sum({2.5, -2.5})), bits(0.0));
  EXPECT_EQ(bits(exact_sum({})), bits(0.0));
  EXPECT_EQ(exact_sum({-0.0, 7.0}), 7.0);
}

TEST(ExactSum, NonFiniteTerms) {
  const double inf = std::numeric_limits<double>::infinity();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(std::isnan(exact_sum({1.0, nan, 2.0})));
  EXPECT_TRUE(std::isnan(exact_sum({inf, 1.0, -inf})));
  EXPECT_EQ(exact_sum({inf, 1.0, 1e308}), inf);
  EXPECT_EQ(exact_sum({-inf, -1e308, -1e308}), -inf);
}

// The same terms in any order, split into any chunks merged in any order or summed word by word
// (as ranks do): the same bits. Terms spread over 600 binary orders of magnitude, both signs.
TEST(ExactSum, OrderAndGroupingChangeNoBit) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> mant(-1.0, 1.0);
  std::vector<double> v(20000);
  for (double& x : v) x = std::ldexp(mant(rng), int(rng() % 600) - 300);
  const double want = exact_sum(v);
  double naive_fwd = 0, naive_rev = 0;
  for (double x : v) naive_fwd += x;
  for (auto it = v.rbegin(); it != v.rend(); ++it) naive_rev += *it;
  EXPECT_NE(bits(naive_fwd), bits(naive_rev));  // the order matters to a plain sum here
  for (int trial = 0; trial < 20; ++trial) {
    std::vector<double> w = v;
    std::shuffle(w.begin(), w.end(), rng);
    EXPECT_EQ(bits(exact_sum(w)), bits(want));
    // Chunks of random sizes, merged in reverse, and their words summed.
    std::vector<ExactSum> parts;
    for (std::size_t i = 0; i < w.size();) {
      const std::size_t len = 1 + rng() % 3000;
      ExactSum s;
      for (std::size_t j = i; j < std::min(w.size(), i + len); ++j) s.add(w[j]);
      parts.push_back(s);
      i += len;
    }
    ExactSum merged;
    std::vector<std::int64_t> words(ExactSum::kWords, 0);
    for (auto it = parts.rbegin(); it != parts.rend(); ++it) {
      merged.merge(*it);
      const std::vector<std::int64_t> pw = it->words();
      for (int k = 0; k < ExactSum::kWords; ++k) words[std::size_t(k)] += pw[std::size_t(k)];
    }
    EXPECT_EQ(bits(merged.value()), bits(want));
    EXPECT_EQ(bits(ExactSum::from_words(words).value()), bits(want));
  }
}

// b - I of the left Cauchy-Green tensor (core/math/left_cauchy_green.hpp).
namespace {
Eigen::Matrix3d random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::Quaterniond q(n(rng), n(rng), n(rng), n(rng));
  q.normalize();
  return q.toRotationMatrix();
}
double sym_dev_error(const SymDevT<float>& d, const Eigen::Matrix3d& b) {
  return (b_matrix(d) - b).norm();
}
}  // namespace

// advance_b is b <- (I + G) b (I + G)^T: against F <- (I + G) F in double, for deformations from
// rest to large strain under arbitrary rotations. Float keeps relative precision on the strain
// and the increment (the terms it sums are small), not only on b's entries of order 1.
TEST(LeftCauchyGreen, AdvanceIsFFTransposeOfTheAdvancedF) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int t = 0; t < 4000; ++t) {
    const double strain = t % 3 == 0 ? 1e-4 : (t % 3 == 1 ? 1e-2 : 0.4);
    const double rate = t % 2 == 0 ? 1e-4 : 3e-2;
    Eigen::Matrix3d S, G;
    for (int e = 0; e < 9; ++e) S(e) = strain * u(rng), G(e) = rate * u(rng);
    const Eigen::Matrix3d F = (Eigen::Matrix3d::Identity() + S) * random_rotation(rng);
    SymDevT<float> df = b_from_F<float>(F);
    SymDevT<double> dd = b_from_F<double>(F);
    float gf[3][3];
    double gd[3][3];
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) gf[r][c] = float(G(r, c)), gd[r][c] = double(gf[r][c]);
    const Eigen::Matrix3d Gr =
        Eigen::Matrix3d::NullaryExpr([&](Eigen::Index r, Eigen::Index c) { return gd[r][c]; });
    const Eigen::Matrix3d F1 = (Eigen::Matrix3d::Identity() + Gr) * F;
    const Eigen::Matrix3d b_in = b_matrix(df);  // the float state advanced, in exact-ish double
    const Eigen::Matrix3d want =
        (Eigen::Matrix3d::Identity() + Gr) * b_in * (Eigen::Matrix3d::Identity() + Gr).transpose();
    advance_b(df.e, gf);
    advance_b(dd.e, gd);
    const double scale = (b_in - Eigen::Matrix3d::Identity()).norm() + G.norm();
    // Float: a few roundings of the small terms, relative to them (never float's 6e-8 absolute
    // spacing around 1, which F kept in one float would have).
    ASSERT_LT(sym_dev_error(df, want), 4e-7 * scale) << "strain " << strain << " rate " << rate;
    ASSERT_LT((b_matrix(dd) - F1 * F1.transpose()).norm(), 1e-14 * (scale + 1));
  }
}

// A body turned by any rotation keeps its strain's digits: b - I of R (I + E) is that of
// (I + E) turned, whose entries are of the strain's size, while F = R (I + E) in float has the
// strain in entries of order one (float's spacing 6e-8 there: 6e-4 of a 1e-4 strain).
TEST(LeftCauchyGreen, RotatedStrainKeepsItsDigits) {
  std::mt19937 rng(8);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  double worst_b = 0, worst_F = 0;
  for (int t = 0; t < 1000; ++t) {
    Eigen::Matrix3d E;
    for (int e = 0; e < 9; ++e) E(e) = 1e-4 * u(rng);
    E = (E + E.transpose()).eval();
    const Eigen::Matrix3d R = random_rotation(rng);
    const Eigen::Matrix3d F = R * (Eigen::Matrix3d::Identity() + E);  // b = R (I + E)^2 R^T
    const Eigen::Matrix3d want = F * F.transpose() - Eigen::Matrix3d::Identity();
    const SymDevT<float> d = b_from_F<float>(F);
    worst_b =
        std::max(worst_b, (b_matrix(d) - Eigen::Matrix3d::Identity() - want).norm() / want.norm());
    const Eigen::Matrix3d Ff = F.cast<float>().cast<double>();
    worst_F = std::max(
        worst_F, (Ff * Ff.transpose() - Eigen::Matrix3d::Identity() - want).norm() / want.norm());
  }
  EXPECT_LT(worst_b, 2e-7);
  EXPECT_GT(worst_F, 100 * worst_b);  // what storing F in one float would lose
  // A rigid rotation of the rest shape is b = I, to double's rounding.
  for (int t = 0; t < 100; ++t)
    EXPECT_LT(
        (b_matrix(b_from_F<float>(random_rotation(rng))) - Eigen::Matrix3d::Identity()).norm(),
        1e-14);
}

// b_factor is a Cholesky factor of I + D (lower triangular, L L^T = I + D), NaN where I + D is
// not positive definite; b_factor_lanes gives it bitwise lane by lane, in full and partial groups.
TEST(LeftCauchyGreen, FactorReconstructsAndLanesAreBitwise) {
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<SymDevT<float>> d;
  for (int t = 0; t < 3000; ++t) {
    Eigen::Matrix3d A;
    const double s = t % 3 == 0 ? 1e-5 : (t % 3 == 1 ? 0.1 : 1.0);
    for (int e = 0; e < 9; ++e) A(e) = s * u(rng);
    d.push_back(b_from_F<float>(Eigen::Matrix3d::Identity() + A));
    if (t % 41 == 0) d.back().e[0] = -2;  // b(0,0) < 0: not positive definite
    if (t % 43 == 0) d.back().e[5] = std::numeric_limits<float>::quiet_NaN();
  }
  constexpr int W = lanes::kN<float>;
  int checked = 0;
  for (std::size_t s0 = 0; s0 < d.size(); s0 += W) {
    const int n = std::min<int>(W - int((s0 / W) % 2), int(d.size() - s0));
    Eigen::Matrix3f L[W];
    b_factor_lanes<float>(&d[s0], n, L);
    for (int l = 0; l < n; ++l) {
      const Eigen::Matrix3f one = b_factor(d[s0 + std::size_t(l)]);
      for (int e = 0; e < 9; ++e)
        ASSERT_TRUE(std::memcmp(&one(e), &L[l](e), 4) == 0 ||
                    (std::isnan(one(e)) && std::isnan(L[l](e))));
      const Eigen::Matrix3d b = b_matrix(d[s0 + std::size_t(l)]);
      const Eigen::Matrix3d Ld = one.cast<double>();
      if (b.allFinite() && b.llt().info() == Eigen::Success) {
        EXPECT_EQ(one(0, 1), 0.0f);
        EXPECT_EQ(one(0, 2), 0.0f);
        EXPECT_EQ(one(1, 2), 0.0f);
        ASSERT_LT((Ld * Ld.transpose() - b).norm(), 1e-6 * b.norm());
        ++checked;
      } else {
        EXPECT_FALSE(one.allFinite());
      }
    }
  }
  EXPECT_GT(checked, 2300);  // (the rest: NaN, negative, the odd groups' last lane, near-singular)
}
