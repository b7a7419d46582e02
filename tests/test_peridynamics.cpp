// Peridynamics: exactness (rigid motions, homogeneous deformations, pair symmetry), effective
// moduli on the lattice with and without the surface correction, the two deviatoric forms under
// hydrostatic load, plasticity and fracture thresholds, and bitwise equality across backends.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <random>

#include "core/errors.hpp"
#include "core/exec/simd.hpp"
#include "io/checkpoint.hpp"
#include "solvers/pd_simulation.hpp"
#include "kernels/peridynamics.hpp"
#include "solvers/pd_solver.hpp"
#include "test_util.hpp"

namespace amalgam {
namespace {

constexpr double kLc = 0.01;
constexpr double kDelta = 3.015 * kLc;  // 122 neighbours on the simple-cubic lattice

// A cube of n^3 particles on a simple-cubic lattice of spacing lc, origin 0.
std::vector<Vec3> lattice(int n, double lc = kLc) {
  std::vector<Vec3> x;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k) x.push_back((lc * Vec3d(i + 0.5, j + 0.5, k + 0.5)).cast<Real>());
  return x;
}

PdMaterial glass() {
  PdMaterial m;
  m.bulk = Real(48e9);
  m.shear = Real(28.8e9);
  m.density = 2200;
  return m;
}

PdSettings settings(PdDeviatoric dev, bool correction, bool partial_volume = true) {
  PdSettings s;
  s.spacing = Real(kLc);
  s.horizon = Real(kDelta);
  s.deviatoric = dev;
  s.surface_correction = correction;
  s.partial_volume = partial_volume;
  s.gravity = Vec3::Zero();
  s.contact = false;
  return s;
}

// A solver over an n^3 cube, initialised (bonds, constants) at rest.
PdSolver make_block(int n, const PdSettings& s, const PdMaterial& m, const exec::Space& space) {
  PdSolver solver(s, {m});
  solver.add_particles(lattice(n), Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0,
                       Real(kLc * kLc * kLc));
  solver.initialize(space);
  return solver;
}

// Moves every particle to x = phi(x0) and recomputes theta and the forces (no fracture).
template <class Map>
void deform(PdSolver& solver, const exec::Space& space, Map&& phi) {
  ParticleSet& ps = solver.particles();
  const Vec3* x0 = ps.vec3(solver.attributes().x0);
  Vec3* x = ps.vec3(solver.attributes().x);
  for (std::size_t i = 0; i < ps.size(); ++i) x[i] = phi(x0[i]);
  solver.compute_dilatation(space);
}

std::vector<Vec3> forces_now(PdSolver& solver, const exec::Space& space) {
  std::vector<Vec3> f(solver.particles().size());
  pd_forces(space, solver.view(), solver.bonds(), solver.params(), false, f.data(), nullptr);
  return f;
}

// Index of the particle nearest the cube's centre, and whether i is at least `depth` from every face.
std::size_t centre_particle(int n) {
  return std::size_t((n / 2) * n * n + (n / 2) * n + n / 2);
}
bool interior(const Vec3& x0, int n, double depth) {
  for (int a = 0; a < 3; ++a)
    if (double(x0[a]) < depth || double(x0[a]) > n * kLc - depth) return false;
  return true;
}

// Force scale: |f| of a surface particle under a 1e-3 uniaxial strain.
double force_scale(const PdMaterial& m) {
  return double(m.bulk) * 1e-3 / kLc;
}

struct Form {
  PdDeviatoric dev;
  bool correction;
};
class PdForms : public ::testing::TestWithParam<Form> {};

TEST_P(PdForms, RigidMotionGivesZeroForce) {
  const exec::Space space;
  const PdMaterial m = glass();
  PdSolver solver = make_block(10, settings(GetParam().dev, GetParam().correction), m, space);
  const Mat3 R = Eigen::AngleAxis<Real>(Real(0.9), Vec3(1, 2, 3).normalized()).toRotationMatrix();
  const Vec3 t(Real(0.3), Real(-1.2), Real(0.05));
  deform(solver, space, [&](const Vec3& x0) { return Vec3(R * x0 + t); });
  const std::vector<Vec3> f = forces_now(solver, space);
  double fmax = 0, tmax = 0;
  for (std::size_t i = 0; i < f.size(); ++i) {
    fmax = std::max(fmax, double(f[i].norm()));
    tmax = std::max(tmax, std::abs(double(solver.view().theta[i])));
  }
  // Round-off only: float positions of magnitude ~1 m carry ~6e-8 m errors on 1 cm bonds.
  const double tol = sizeof(Real) == 4 ? 2e-2 : 1e-8;
  EXPECT_LT(fmax / force_scale(m), tol);
  EXPECT_LT(tmax, sizeof(Real) == 4 ? 1e-4 : 1e-12);
}

TEST_P(PdForms, HomogeneousDeformationGivesZeroForceInTheBulk) {
  const exec::Space space;
  const PdMaterial m = glass();
  const int n = 18;
  PdSolver solver = make_block(n, settings(GetParam().dev, GetParam().correction), m, space);
  Mat3 H;
  H << Real(1.0e-3), Real(0.4e-3), Real(-0.2e-3), Real(0.1e-3), Real(-0.5e-3), Real(0.3e-3),
      Real(0.2e-3), Real(0.6e-3), Real(0.8e-3);
  deform(solver, space, [&](const Vec3& x0) { return Vec3(x0 + H * x0); });
  const std::vector<Vec3> f = forces_now(solver, space);
  const Vec3* x0 = solver.particles().vec3(solver.attributes().x0);
  double bulk_max = 0, surface_max = 0;
  int bulk = 0;
  for (std::size_t i = 0; i < f.size(); ++i) {
    const double fi = double(f[i].norm()) / force_scale(m);
    // A particle whose family and whose neighbours' families are complete: 2 delta from faces.
    if (interior(x0[i], n, 2 * kDelta)) {
      bulk_max = std::max(bulk_max, fi);
      ++bulk;
    } else {
      surface_max = std::max(surface_max, fi);
    }
  }
  ASSERT_GT(bulk, 0);
  EXPECT_LT(bulk_max, sizeof(Real) == 4 ? 1e-3 : 1e-9) << "surface max " << surface_max;
  EXPECT_GT(surface_max, 0.1);  // the test can see a force when there is one
}

TEST_P(PdForms, PairForcesConserveMomentum) {
  const exec::Space space;
  const PdMaterial m = glass();
  PdSolver solver = make_block(8, settings(GetParam().dev, GetParam().correction), m, space);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  deform(solver, space, [&](const Vec3& x0) {
    return Vec3(x0 + Vec3d(u(rng), u(rng), u(rng)).cast<Real>() * Real(2e-4));
  });
  const std::vector<Vec3> f = forces_now(solver, space);
  const Vec3* x = solver.particles().vec3(solver.attributes().x);
  const Real* V = solver.particles().real(solver.attributes().volume);
  Vec3d P = Vec3d::Zero(), Lm = Vec3d::Zero();
  double fsum = 0, lsum = 0;
  for (std::size_t i = 0; i < f.size(); ++i) {
    const Vec3d Fi = f[i].cast<double>() * double(V[i]);
    P += Fi;
    Lm += x[i].cast<double>().cross(Fi);
    fsum += Fi.norm();
    lsum += (x[i].cast<double>().cross(Fi)).norm();
  }
  const double eps = sizeof(Real) == 4 ? 1e-6 : 1e-13;
  EXPECT_LT(P.norm() / fsum, eps);
  EXPECT_LT(Lm.norm() / lsum, 20 * eps);  // forces along the bonds: no torque
}

// With no yielding material the passes skip the (all-zero) plastic extensions: theta, q, the
// forces and the fracture decisions are bitwise those of the path that reads them.
TEST_P(PdForms, ElasticPathIsBitwiseThePlasticPath) {
  const exec::Space space(exec::Backend::OpenMP, 2);
  PdMaterial m = glass();
  m.critical_stretch = Real(3e-4);  // some bonds of the deformed block break
  PdSolver solver = make_block(8, settings(GetParam().dev, GetParam().correction), m, space);
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1, 1);
  deform(solver, space, [&](const Vec3& x0) {
    return Vec3(x0 + Vec3d(u(rng), u(rng), u(rng)).cast<Real>() * Real(2e-4));
  });
  ASSERT_FALSE(solver.params().plastic);
  const PdBonds bonds0 = solver.bonds();
  const PdView v = solver.view();
  struct Out {
    std::vector<Real> theta, q;
    std::vector<Vec3> f;
    std::vector<std::uint8_t> intact;
  };
  auto run = [&](bool plastic) {
    PdParams prm = solver.params();
    prm.consistent = true;
    prm.plastic = plastic;
    PdBonds b = bonds0;
    pd_dilatation(space, v, b, prm);
    Out o{std::vector<Real>(v.theta, v.theta + v.n),
          std::vector<Real>(v.q, v.q + v.n),
          std::vector<Vec3>(v.n),
          {}};
    pd_forces(space, v, b, prm, true, o.f.data(), nullptr);
    o.intact = b.intact;
    return o;
  };
  const Out a = run(false), b = run(true);
  EXPECT_TRUE(test::bitwise_equal(a.theta.data(), b.theta.data(), a.theta.size()));
  EXPECT_TRUE(test::bitwise_equal(a.q.data(), b.q.data(), a.q.size()));
  EXPECT_TRUE(test::bitwise_equal(a.f.data(), b.f.data(), a.f.size()));
  EXPECT_EQ(a.intact, b.intact);
  EXPECT_NE(std::count(a.intact.begin(), a.intact.end(), 0), 0)
      << "no bond broke: the fracture test is vacuous";
  EXPECT_NE(std::count(a.intact.begin(), a.intact.end(), 1), 0);
}

INSTANTIATE_TEST_SUITE_P(Peridynamics, PdForms,
                         ::testing::Values(Form{PdDeviatoric::Paper, false},
                                           Form{PdDeviatoric::Paper, true},
                                           Form{PdDeviatoric::Lps, false},
                                           Form{PdDeviatoric::Lps, true}),
                         [](const ::testing::TestParamInfo<Form>& i) {
                           return std::string(pd_deviatoric_name(i.param.dev)) +
                                  (i.param.correction ? "_corrected" : "_uncorrected");
                         });

// Stress of the centre particle under a homogeneous strain eps (symmetric, small).
Mat3d centre_stress(PdSolver& solver, const exec::Space& space, int n, const Mat3& eps) {
  deform(solver, space, [&](const Vec3& x0) { return Vec3(x0 + eps * x0); });
  std::vector<Mat3> s;
  solver.compute_stress(space, s);
  return s[centre_particle(n)].cast<double>();
}

struct Moduli {
  double K, C11, C12, C44;
};
Moduli lattice_moduli(PdDeviatoric dev, bool correction, bool partial_volume) {
  const exec::Space space;
  const int n = 13;
  PdSolver solver = make_block(n, settings(dev, correction, partial_volume), glass(), space);
  const double e = 1e-4;
  // Central differences (sigma(+e) - sigma(-e)) / 2: the probe's second-order (finite-strain)
  // terms cancel, which a one-sided probe leaves at ~0.5 e relative in C11 and C12 (seen in the
  // double build, whose tolerance is 1e-6).
  const auto slope = [&](const Mat3& strain) {
    return Mat3d(
        (centre_stress(solver, space, n, strain) - centre_stress(solver, space, n, -strain)) / 2);
  };
  Moduli r;
  const Mat3d iso = slope(Mat3::Identity() * Real(e));
  r.K = iso.trace() / 3 / (3 * e);
  Mat3 uni = Mat3::Zero();
  uni(0, 0) = Real(e);
  const Mat3d su = slope(uni);
  r.C11 = su(0, 0) / e;
  r.C12 = su(1, 1) / e;
  Mat3 sh = Mat3::Zero();
  sh(0, 1) = sh(1, 0) = Real(e);
  r.C44 = slope(sh)(0, 1) / (2 * e);
  return r;
}

// Effective moduli of an interior particle (continuum targets K = 48, C11 = 86.4, C12 = C44 =
// 28.8 GPa). The paper's analytic constants give K about
// +10 % off (no volume rule) or -11 % (partial volumes) on this lattice; the correction makes K
// exact and C44 exact (the three coordinate shears are what it normalises).
TEST(PdModuli, SurfaceCorrectionMakesBulkAndShearModuliExact) {
  const double tol = sizeof(Real) == 4 ? 2e-3 : 1e-6;
  for (PdDeviatoric dev : {PdDeviatoric::Paper, PdDeviatoric::Lps}) {
    const Moduli c = lattice_moduli(dev, true, true);
    EXPECT_NEAR(c.K / 48e9, 1.0, tol) << pd_deviatoric_name(dev);
    EXPECT_NEAR(c.C44 / 28.8e9, 1.0, tol) << pd_deviatoric_name(dev);
    // The lattice shear factor makes the cubic lattice isotropic: C11 and C12 exact too.
    EXPECT_NEAR(c.C11 / 86.4e9, 1.0, tol) << pd_deviatoric_name(dev);
    EXPECT_NEAR(c.C12 / 28.8e9, 1.0, tol) << pd_deviatoric_name(dev);
    const Moduli raw = lattice_moduli(dev, false, false);
    const Moduli pv = lattice_moduli(dev, false, true);
    std::printf(
        "%s: K/K0 uncorrected %.4f, partial volume %.4f, corrected %.4f; C44/G %.4f %.4f %.4f; "
        "(C11-C12)/2G %.4f %.4f %.4f\n",
        pd_deviatoric_name(dev), raw.K / 48e9, pv.K / 48e9, c.K / 48e9, raw.C44 / 28.8e9,
        pv.C44 / 28.8e9, c.C44 / 28.8e9, (raw.C11 - raw.C12) / 2 / 28.8e9,
        (pv.C11 - pv.C12) / 2 / 28.8e9, (c.C11 - c.C12) / 2 / 28.8e9);
    EXPECT_GT(std::abs((pv.C11 - pv.C12) / 2 / 28.8e9 - 1), 0.05) << pd_deviatoric_name(dev);
    // The notes' lattice sums (Madenci/Chen constants): K +6.3 % uncorrected... the test must
    // see the error it corrects.
    EXPECT_GT(std::abs(raw.K / 48e9 - 1), 0.02) << pd_deviatoric_name(dev);
    EXPECT_GT(std::abs(pv.K / 48e9 - 1), 0.02) << pd_deviatoric_name(dev);
  }
}

// Under a pure dilation the LPS deviatoric extension is zero bond by bond, the paper's is not:
// with a low yield threshold, only the paper's form yields (notes, section 1.2).
TEST(PdPlasticity, HydrostaticLoadYieldsOnlyWithThePapersDeviatoricForm) {
  const exec::Space space;
  for (PdDeviatoric dev : {PdDeviatoric::Paper, PdDeviatoric::Lps}) {
    PdMaterial m = glass();
    m.psi0 = pd_psi0_from_yield_stress(Real(20e6), Real(kDelta));  // yield at 20 MPa
    const int n = 13;
    PdSolver solver = make_block(n, settings(dev, true), m, space);
    deform(solver, space,
           [&](const Vec3& x0) { return Vec3(x0 * Real(1.001)); });  // p = 3 K 1e-3 = 144 MPa
    const PdBonds& b = solver.bonds();
    const std::size_t c = centre_particle(n);
    double ep_max = 0;
    for (std::uint64_t k = b.offsets[c]; k < b.offsets[c + 1]; ++k)
      ep_max = std::max(ep_max, std::abs(double(b.plastic[k])));
    if (dev == PdDeviatoric::Lps)
      EXPECT_LT(ep_max, 1e-12 * kLc);
    else
      EXPECT_GT(ep_max, 1e-7 * kLc);
  }
}

// Beyond yield the return puts A_dev on the yield surface; unloading leaves the plastic
// extension; the cap bounds it.
TEST(PdPlasticity, ReturnMappingLandsOnTheYieldSurfaceAndIsCapped) {
  const exec::Space space;
  PdMaterial m = glass();
  const Real sigma_y = Real(20e6);
  m.psi0 = pd_psi0_from_yield_stress(sigma_y, Real(kDelta));
  m.plastic_cap = Real(6e-4);
  const int n = 13;
  PdSolver solver = make_block(n, settings(PdDeviatoric::Lps, true), m, space);
  Mat3 sh = Mat3::Zero();
  sh(0, 1) = sh(1, 0) = Real(1e-3);  // tau = 2 G 1e-3 = 57.6 MPa > sigma_y / sqrt(3)
  deform(solver, space, [&](const Vec3& x0) { return Vec3(x0 + sh * x0); });
  const PdBonds& b = solver.bonds();
  const std::size_t c = centre_particle(n);
  const PdView p = solver.view();
  const double ac = std::sqrt(2.0 * double(m.psi0));
  int yielded = 0, capped = 0;
  for (std::uint64_t k = b.offsets[c]; k < b.offsets[c + 1]; ++k) {
    const Vec3 xi = p.x0[b.neighbor[k]] - p.x0[c], eta = p.x[b.neighbor[k]] - p.x[c];
    const double L = xi.norm(), e = eta.norm() - L;
    const double ed = e - double(p.theta[c]) * L / 3;
    const double adev = 4 * double(b.shear_omega[k]) * double(p.b[c]) * (ed - double(b.plastic[k]));
    const double cap = double(m.plastic_cap) * L;
    EXPECT_LE(std::abs(double(b.plastic[k])), cap * (1 + 1e-6));
    // On the yield surface, unless the cap stopped the plastic flow (then above it).
    if (std::abs(double(b.plastic[k])) < cap * (1 - 1e-6))
      EXPECT_LE(std::abs(adev), ac * (1 + 1e-3));
    else
      ++capped;
    yielded += b.plastic[k] != 0;
  }
  EXPECT_GT(yielded, 10);
  EXPECT_GT(capped, 0);
  EXPECT_LT(capped, yielded);  // both regimes seen
  // Unload to the reference shape: reverse yielding may take back part of e^p (perfect
  // plasticity), but a permanent set of the same sign stays, at |A_dev| <= A_c.
  const std::vector<Real> ep(b.plastic.begin(), b.plastic.end());
  deform(solver, space, [&](const Vec3& x0) { return x0; });
  for (std::uint64_t k = b.offsets[c]; k < b.offsets[c + 1]; ++k) {
    if (ep[k] == 0) continue;
    EXPECT_GT(double(b.plastic[k]) * double(ep[k]), 0.0);
    const double adev =
        4 * double(b.shear_omega[k]) * double(p.b[c]) * (0.0 - double(b.plastic[k]));
    EXPECT_LE(std::abs(adev), ac * (1 + 1e-3));
  }
}

// Eq. 18: a uniaxial stretch eps gives (e - e^p) / delta = eps for the axis-aligned bond of
// length delta... the longest bonds along x have e / delta = eps L / delta <= eps.
TEST(PdFracture, NoBondBreaksBelowTheCriticalStretch) {
  const exec::Space space;
  PdMaterial m = glass();
  m.critical_stretch = Real(1e-3);
  const int n = 10;
  for (double factor : {0.99, 1.01}) {
    PdSolver solver = make_block(n, settings(PdDeviatoric::Paper, true), m, space);
    Mat3 uni = Mat3::Zero();
    uni(0, 0) = Real(factor * 1e-3);
    deform(solver, space, [&](const Vec3& x0) { return Vec3(x0 + uni * x0); });
    std::vector<Vec3> f(solver.particles().size());
    pd_forces(space, solver.view(), solver.bonds(), solver.params(), true, f.data(), nullptr);
    const std::uint64_t intact = pd_damage(space, solver.view(), solver.bonds());
    if (factor < 1) {
      EXPECT_EQ(intact, solver.bonds().size());
    } else {
      EXPECT_LT(intact, solver.bonds().size());
      // Broken in both directions (symmetric decision).
      const PdBonds& b = solver.bonds();
      for (std::size_t k = 0; k < b.size(); ++k) ASSERT_EQ(b.intact[k], b.intact[b.reverse[k]]);
    }
  }
}

// A single bond of length L = 2 lc (horizon delta = 3.015 lc) stretched to s = (l - L) / L just
// below and just above a threshold: the classical criterion breaks it at s = s_c, the paper's
// (eq. 18, extension over delta) at s = s_c delta / L, both in both directions.
// PdModel::Lps is the linear peridynamic solid as LAMMPS's pair peri/lps computes it: the force
// density of every particle of a randomly deformed block (surfaces, edges and corners included,
// bonds cut by the horizon scaled as LAMMPS's vfrac_scale) against that formula written out
// directly in double (influence 1 / r0, m_i = sum omega r0^2 V, theta_i = 3 / m_i sum omega r0 dr
// V, rk = (3K - 5G) V (omega theta_i / m_i + omega theta_j / m_j) r0 + 15 G V (omega / m_i +
// omega / m_j) dr, f_i += rk (x_j - x_i) / r). The paper's model gives other forces: checked.
TEST(PdLps, ForcesAreTheLinearPeridynamicSolidsAsLammpsComputesThem) {
  const exec::Space space;
  const int n = 6;
  PdSettings s = settings(PdDeviatoric::Lps, false);
  s.model = PdModel::Lps;
  PdSolver solver = make_block(n, s, glass(), space);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Vec3d> x0d, xd;
  for (const Vec3& p : lattice(n)) {
    x0d.push_back(p.cast<double>());
    xd.push_back(p.cast<double>() + 2e-2 * kLc * Vec3d(u(rng), u(rng), u(rng)));
  }
  std::size_t k = 0;
  deform(solver, space, [&](const Vec3&) { return xd[k++].cast<Real>(); });
  const std::vector<Vec3> f = forces_now(solver, space);
  // The reference, from the float positions the solver holds.
  const Vec3* xs = solver.particles().vec3(solver.attributes().x);
  const Vec3* x0s = solver.particles().vec3(solver.attributes().x0);
  const std::size_t np = x0d.size();
  for (std::size_t i = 0; i < np; ++i) xd[i] = xs[i].cast<double>(), x0d[i] = x0s[i].cast<double>();
  const double V = kLc * kLc * kLc, K = 48e9, G = 28.8e9, half = kLc / 2;
  auto scale = [&](double r0) { return r0 > kDelta - half ? (kDelta + half - r0) / kLc : 1.0; };
  std::vector<double> m(np, 0), theta(np, 0);
  for (std::size_t i = 0; i < np; ++i)
    for (std::size_t j = 0; j < np; ++j) {
      const double r0 = (x0d[j] - x0d[i]).norm();
      if (j == i || r0 > double(Real(kDelta))) continue;
      m[i] += (1 / r0) * r0 * r0 * V * scale(r0);
      theta[i] += (1 / r0) * r0 * ((xd[j] - xd[i]).norm() - r0) * V * scale(r0);
    }
  for (std::size_t i = 0; i < np; ++i) theta[i] *= 3 / m[i];
  double fmax = 0, err = 0;
  for (std::size_t i = 0; i < np; ++i) {
    Vec3d fi = Vec3d::Zero();
    for (std::size_t j = 0; j < np; ++j) {
      const double r0 = (x0d[j] - x0d[i]).norm();
      if (j == i || r0 > double(Real(kDelta))) continue;
      const double r = (xd[j] - xd[i]).norm(), dr = r - r0, om = 1 / r0, vs = V * scale(r0);
      const double rk = (3 * K - 5 * G) * vs * (om * theta[i] / m[i] + om * theta[j] / m[j]) * r0 +
                        15 * G * vs * (om / m[i] + om / m[j]) * dr;
      fi += rk * (xd[j] - xd[i]) / r;
    }
    fmax = std::max(fmax, fi.norm());
    err = std::max(err, (f[i].cast<double>() - fi).norm());
  }
  EXPECT_GT(fmax, 0);
  EXPECT_LT(err, (sizeof(Real) == 4 ? 5e-5 : 1e-9) * fmax) << "fmax " << fmax << " err " << err;
  // The paper's model (uncorrected, LPS deviatoric extension) is a different model.
  PdSolver paper = make_block(n, settings(PdDeviatoric::Lps, false), glass(), space);
  k = 0;
  deform(paper, space, [&](const Vec3&) { return xd[k++].cast<Real>(); });
  const std::vector<Vec3> fp = forces_now(paper, space);
  double diff = 0;
  for (std::size_t i = 0; i < np; ++i) diff = std::max(diff, (fp[i] - f[i]).cast<double>().norm());
  EXPECT_GT(diff, 0.05 * fmax);
}

// LPS's normaliser m_i comes from each particle's own family, so a homogeneous dilation gives
// theta = 3 eps at every particle, faces, edges and corners included, and no force in the
// interior (the deviatoric extension e - theta L / 3 vanishes bond by bond).
TEST(PdLps, DilatationIsExactAtEveryParticle) {
  const exec::Space space;
  PdSettings s = settings(PdDeviatoric::Lps, false);
  s.model = PdModel::Lps;
  PdSolver solver = make_block(7, s, glass(), space);
  const double eps = 1e-3;
  deform(solver, space, [&](const Vec3& p) { return Vec3(Real(1 + eps) * p); });
  const Real* theta = solver.particles().real(solver.attributes().theta);
  for (std::size_t i = 0; i < solver.particles().size(); ++i)
    ASSERT_NEAR(double(theta[i]), 3 * eps, 3 * eps * (sizeof(Real) == 4 ? 2e-3 : 1e-9)) << i;
}

TEST(PdFracture, SingleBondBreaksAtEachCriterionsStretch) {
  const exec::Space space;
  const Real sc = Real(1e-3);
  const double L = 2 * kLc;
  const Vec3d dir = Vec3d(1, 2, 2) / 3;
  for (PdCriterion crit : {PdCriterion::Classical, PdCriterion::Paper}) {
    const double threshold = crit == PdCriterion::Classical ? sc : sc * kDelta / L;
    for (double factor : {0.99, 1.01}) {
      PdSettings st = settings(PdDeviatoric::Paper, false);
      st.criterion = crit;
      PdMaterial m = glass();
      m.critical_stretch = sc;
      PdSolver solver(st, {m});
      const Vec3d a(0.1, 0.2, 0.3);
      solver.add_particles({a.cast<Real>(), (a + L * dir).cast<Real>()}, Vec3::Zero(), Vec3::Zero(),
                           Vec3::Zero(), 0, Real(kLc * kLc * kLc));
      solver.initialize(space);
      ASSERT_EQ(solver.bonds().size(), 2u);
      // Stretch the bond symmetrically about its middle to s = factor * threshold, measured on
      // the float positions the kernel sees.
      ParticleSet& ps = solver.particles();
      Vec3* x = ps.vec3(solver.attributes().x);
      const Vec3* x0 = ps.vec3(solver.attributes().x0);
      const double l0 = (x0[1] - x0[0]).cast<double>().norm();
      const double s = factor * threshold;
      const Vec3d mid = 0.5 * (x0[0] + x0[1]).cast<double>();
      x[0] = (mid - 0.5 * l0 * (1 + s) * dir).cast<Real>();
      x[1] = (mid + 0.5 * l0 * (1 + s) * dir).cast<Real>();
      const double stretch = ((x[1] - x[0]).cast<double>().norm() - l0) / l0;
      ASSERT_NEAR(stretch / threshold, factor, 2e-3);
      solver.compute_dilatation(space);
      std::vector<Vec3> f(2);
      pd_forces(space, solver.view(), solver.bonds(), solver.params(), true, f.data(), nullptr);
      const PdBonds& b = solver.bonds();
      EXPECT_EQ(b.intact[0], b.intact[1]);
      EXPECT_EQ(b.intact[0] == 0, factor > 1)
          << pd_criterion_name(crit) << " at " << factor << " x its threshold";
    }
  }
}

// A pre-crack on the plane x = 0.05 over half the block (y < 0.05) breaks exactly the bonds
// that cross it there, in both directions.
TEST(PdFracture, PrecrackBreaksExactlyTheCrossingBonds) {
  const exec::Space space(test::parallel_backend(), 2);
  PdSolver solver(settings(PdDeviatoric::Paper, true), {glass()});
  solver.add_particles(lattice(10), Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0,
                       Real(kLc * kLc * kLc));
  solver.add_precrack(Vec3(Real(0.05), 0, 0), Vec3(1, 0, 0), Vec3(-1, -1, -1),
                      Vec3(1, Real(0.05), 1));
  solver.initialize(space);
  const PdBonds& b = solver.bonds();
  const Vec3* x0 = solver.particles().vec3(solver.attributes().x0);
  std::size_t broken = 0;
  for (std::size_t i = 0; i + 1 < b.offsets.size(); ++i)
    for (std::uint64_t k = b.offsets[i]; k < b.offsets[i + 1]; ++k) {
      const Vec3 a = x0[i], c = x0[b.neighbor[k]];
      const bool crosses = (a[0] - Real(0.05)) * (c[0] - Real(0.05)) < 0;
      const Real y = a[1] + (Real(0.05) - a[0]) / (c[0] - a[0]) * (c[1] - a[1]);
      const bool expect_broken = crosses && y <= Real(0.05);
      ASSERT_EQ(b.intact[k] == 0, expect_broken) << i << " -> " << b.neighbor[k];
      ASSERT_EQ(b.intact[k], b.intact[b.reverse[k]]);
      broken += !b.intact[k];
    }
  EXPECT_GT(broken, 1000u);
  EXPECT_GT(solver.diagnostics(space).max_damage, 0.3);
}

TEST(PdBonds, CsrIsSymmetricSortedAndCompactionKeepsIntactBonds) {
  const exec::Space space(test::parallel_backend(), 2);
  PdMaterial m = glass();
  PdSolver solver = make_block(7, settings(PdDeviatoric::Paper, true), m, space);
  PdBonds& b = solver.bonds();
  EXPECT_EQ(b.offsets[centre_particle(7) + 1] - b.offsets[centre_particle(7)], 122u);
  for (std::size_t i = 0; i + 1 < b.offsets.size(); ++i)
    for (std::uint64_t k = b.offsets[i]; k < b.offsets[i + 1]; ++k) {
      if (k + 1 < b.offsets[i + 1]) {
        ASSERT_LT(b.neighbor[k], b.neighbor[k + 1]);
      }
      ASSERT_EQ(b.neighbor[b.reverse[k]], i);
      ASSERT_EQ(b.reverse[b.reverse[k]], k);
    }
  // Break every bond of particle 0 (both directions), compact, check the rest survives.
  for (std::uint64_t k = b.offsets[0]; k < b.offsets[1]; ++k)
    b.intact[k] = b.intact[b.reverse[k]] = 0;
  const std::size_t before = b.size(), row0 = b.offsets[1] - b.offsets[0];
  pd_compact_bonds(space, b);
  EXPECT_EQ(b.size(), before - 2 * row0);
  EXPECT_EQ(b.offsets[1], 0u);
  for (std::size_t i = 0; i + 1 < b.offsets.size(); ++i)
    for (std::uint64_t k = b.offsets[i]; k < b.offsets[i + 1]; ++k) {
      ASSERT_NE(b.neighbor[k], 0u);
      ASSERT_EQ(b.neighbor[b.reverse[k]], i);
    }
  // With contact at distance lc, broken bonds with 0.9 L < lc stay (the contact rule reads their
  // length): of the centre particle's broken bonds, its 6 nearest neighbours' remain.
  const std::size_t p = centre_particle(7);
  const std::size_t before2 = b.size(), row = b.offsets[p + 1] - b.offsets[p];
  for (std::uint64_t k = b.offsets[p]; k < b.offsets[p + 1]; ++k)
    b.intact[k] = b.intact[b.reverse[k]] = 0;
  EXPECT_EQ(pd_compact_bonds(space, b, Real(kLc)), 2 * (row - 6));
  EXPECT_EQ(b.size(), before2 - 2 * (row - 6));
  ASSERT_EQ(b.offsets[p + 1] - b.offsets[p], 6u);
  for (std::uint64_t k = b.offsets[p]; k < b.offsets[p + 1]; ++k) {
    EXPECT_EQ(b.intact[k], 0);
    EXPECT_NEAR(double(b.length[k]), kLc, 1e-6);
    EXPECT_EQ(b.neighbor[b.reverse[k]], p);
    EXPECT_EQ(b.intact[b.reverse[k]], 0);
  }
  // Restricting a full list to a compacted layout reproduces the compacted arrays.
  PdSolver full = make_block(7, settings(PdDeviatoric::Paper, true), m, space);
  PdBonds f = full.bonds();
  ASSERT_TRUE(pd_restrict_bonds(space, f, b.offsets, b.neighbor));
  EXPECT_EQ(f.neighbor, b.neighbor);
  EXPECT_EQ(f.reverse, b.reverse);
  EXPECT_EQ(f.omega, b.omega);
  EXPECT_EQ(f.shear_omega, b.shear_omega);
  EXPECT_EQ(f.length, b.length);
  // ... and refuses rows that are not a subset (here: particle 0 regains a bond).
  std::vector<std::uint64_t> off = b.offsets;
  std::vector<std::uint32_t> nb = b.neighbor;
  nb.insert(nb.begin(), 1u);
  for (std::size_t i = 1; i < off.size(); ++i) ++off[i];
  PdBonds g = f;
  EXPECT_TRUE(pd_restrict_bonds(space, g, off, nb) == false);
  EXPECT_EQ(g.neighbor, f.neighbor);
}

void expect_same_state(const PdSolver& a, const PdSolver& b, const std::string& what) {
  const ParticleSet &pa = a.particles(), &pb = b.particles();
  for (int k = 0; k < pa.attribute_count(); ++k)
    EXPECT_TRUE(test::bitwise_equal(pa.words(k), pb.words(k),
                                    pa.size() * std::size_t(pa.words_per_particle(k))))
        << what << ": attribute " << pa.name(k);
  EXPECT_TRUE(test::bitwise_equal(a.forces().data(), b.forces().data(), a.forces().size()))
      << what << ": forces";
}

PdMaterial breakable() {
  PdMaterial m;
  m.bulk = Real(2e6);
  m.shear = Real(1.2e6);
  m.density = 1000;
  m.critical_stretch = Real(0.02);
  m.alpha = Real(0.5);
  m.psi0 = pd_psi0_from_yield_stress(Real(2e5), Real(kDelta));
  m.plastic_cap = Real(0.05);
  return m;
}

// A 24 x 6 x 6 bar with plasticity, fracture and contact, its ends pulled apart at 3 m/s.
PdSolver pulled_bar(const exec::Space& space, Real compact_fraction,
                    PdModel model = PdModel::Paper) {
  PdSettings s = model == PdModel::Lps ? settings(PdDeviatoric::Lps, false)
                                       : settings(PdDeviatoric::Paper, true);
  s.model = model;
  s.contact = true;
  s.compact_fraction = compact_fraction;
  PdSolver solver(s, {breakable()});
  std::vector<Vec3> x;
  for (int i = 0; i < 24; ++i)
    for (int j = 0; j < 6; ++j)
      for (int k = 0; k < 6; ++k)
        x.push_back((kLc * Vec3d(i + 0.5, j + 0.5, k + 0.5)).cast<Real>());
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(kLc * kLc * kLc));
  solver.prescribe_velocity(Vec3(-1, -1, -1), Vec3(Real(0.03), 1, 1), Vec3(-3, 0, 0));
  solver.prescribe_velocity(Vec3(Real(0.21), -1, -1), Vec3(1, 1, 1), Vec3(3, 0, 0));
  solver.initialize(space);
  return solver;
}

// A bar pulled apart at both ends breaks; every backend and thread count gives the same bits.
TEST(PdBackends, FractureRunIsBitwiseIdentical) {
  auto run = [](const exec::Space& space) {
    PdSolver solver = pulled_bar(space, PdSettings().compact_fraction);
    const Real dt = solver.stable_dt(space);
    for (int k = 0; k < 60; ++k) solver.step(space, dt);
    return solver;
  };
  const PdSolver ref = run(exec::Space());
  const PdDiagnostics d = ref.diagnostics(exec::Space());
  EXPECT_LT(d.intact, d.bonds);  // it did fracture
  for (const test::Config& c : test::all_configs()) {
    const PdSolver other = run(exec::Space(c.backend, c.threads));
    expect_same_state(ref, other, c.name());
    EXPECT_EQ(ref.bonds().intact, other.bonds().intact) << c.name();
    EXPECT_EQ(ref.bonds().plastic, other.bonds().plastic) << c.name();
  }
}

// The same with the LPS model (its own normaliser per particle, the dilatation along |xi|).
TEST(PdBackends, LpsFractureRunIsBitwiseIdentical) {
  auto run = [](const exec::Space& space) {
    PdSolver solver = pulled_bar(space, PdSettings().compact_fraction, PdModel::Lps);
    const Real dt = solver.stable_dt(space);
    for (int k = 0; k < 60; ++k) solver.step(space, dt);
    return solver;
  };
  const PdSolver ref = run(exec::Space());
  const PdDiagnostics d = ref.diagnostics(exec::Space());
  EXPECT_LT(d.intact, d.bonds);
  for (const test::Config& c : test::all_configs()) {
    const PdSolver other = run(exec::Space(c.backend, c.threads));
    expect_same_state(ref, other, c.name());
    EXPECT_EQ(ref.bonds().intact, other.bonds().intact) << c.name();
  }
}

// Run-time vector width (core/exec/simd.hpp): the bond passes compiled for AVX2 and AVX-512
// (kernels/peridynamics_passes.cpp, 8 and 16 float lanes per block loop) give the baseline's
// state bit for bit, on Serial and on 2 threads: the pulled bar with plasticity, fracture,
// damage and contact, in the paper's form with and without bond compaction (the compacted rows
// sum through their stored lanes) and in the LPS form (the baseline on every backend:
// PdBackends). Paths the CPU or build lacks are skipped, saying
// so; the test fails if a path diverges (checked by making the AVX-512 force pass add 1 ulp).
TEST(PdSimdPaths, FracturePlasticityContactBitwiseOnEveryPath) {
  const exec::SimdPath saved = exec::simd_path();
  struct Restore {
    exec::SimdPath p;
    ~Restore() { exec::set_simd_path(p); }
  } restore{saved};
  if (exec::supported_simd_paths().size() < 2)
    GTEST_SKIP() << "only the baseline path runs here: " << exec::simd_description();
  for (const std::pair<PdModel, Real>& c : std::vector<std::pair<PdModel, Real>>{
           {PdModel::Paper, Real(0)}, {PdModel::Paper, Real(0.005)}, {PdModel::Lps, Real(0)}}) {
    const PdModel model = c.first;
    const Real fraction = c.second;
    const std::string form =
        std::string(pd_model_name(model)) + " form, compact_fraction " + std::to_string(fraction);
    auto run = [&](const exec::Space& space) {
      PdSolver solver = pulled_bar(space, fraction, model);
      const Real dt = solver.stable_dt(space);
      for (int k = 0; k < 60; ++k) solver.step(space, dt);
      return solver;
    };
    exec::set_simd_path(exec::SimdPath::Baseline);
    const PdSolver ref = run(exec::Space());
    const PdDiagnostics d = ref.diagnostics(exec::Space());
    EXPECT_LT(d.intact, d.bonds * 97 / 100) << form;  // it fractured
    if (fraction > 0) EXPECT_GT(d.compactions, 0u) << form;
    std::size_t yielded = 0;
    for (const Real ep : ref.bonds().plastic) yielded += ep != 0;
    if (model == PdModel::Paper) EXPECT_GT(yielded, 100u) << form;  // it flowed
    for (const exec::SimdPath path : {exec::SimdPath::Avx2, exec::SimdPath::Avx512}) {
      if (!exec::simd_path_supported(path)) {
        std::printf("SIMD path %s: skipped (%s)\n", exec::simd_path_name(path),
                    exec::simd_path_compiled(path) ? "this CPU lacks it" : "not in this build");
        continue;
      }
      exec::set_simd_path(path);
      for (const exec::Space& space : {exec::Space(), exec::Space(test::parallel_backend(), 2)}) {
        const std::string what =
            form + ", " + exec::simd_path_name(path) + " on " + space.describe();
        const PdSolver other = run(space);
        expect_same_state(ref, other, what);
        EXPECT_EQ(ref.bonds().intact, other.bonds().intact) << what;
        EXPECT_TRUE(test::bitwise_equal(ref.bonds().plastic.data(), other.bonds().plastic.data(),
                                        ref.bonds().plastic.size()))
            << what;
      }
    }
    std::printf("%s: %zu plastic bonds, %llu of %llu intact, bitwise on every path run\n",
                form.c_str(), yielded, (unsigned long long)d.intact, (unsigned long long)d.bonds);
  }
}

// A copied solver is independent of its source (the benchmarks build one block and copy it per
// configuration): the source destroyed, the copy steps bitwise like an uncopied twin. Before
// params() bound the materials on each call, the copy kept a pointer into the source's materials.
TEST(PdSolverCopy, CopyStepsLikeTheOriginalAfterTheSourceIsGone) {
  PdMaterial m;
  m.bulk = Real(2e6);
  m.shear = Real(1.2e6);
  m.density = 1000;
  m.critical_stretch = Real(0.02);
  const exec::Space space;
  auto make = [&](Real bulk) {
    PdMaterial mm = m;
    mm.bulk = bulk;
    auto s =
        std::make_unique<PdSolver>(make_block(6, settings(PdDeviatoric::Paper, true), mm, space));
    s->prescribe_velocity(Vec3(-1, -1, -1), Vec3(Real(0.015), 1, 1), Vec3(-2, 0, 0));
    return s;
  };
  auto twin = make(m.bulk);
  auto source = make(m.bulk);
  PdSolver copy(*source);
  {  // what a stale pointer would read before the memory goes (materials_ is not const: defined)
    PdMaterial& sm = const_cast<PdMaterial&>(source->materials().front());
    sm.bulk = sm.shear = Real(9e9);
    sm.critical_stretch = Real(1e-9);
  }
  source.reset();
  const Real dt = twin->stable_dt(space);
  for (int k = 0; k < 20; ++k) {
    twin->step(space, dt);
    copy.step(space, dt);
  }
  const auto& a = twin->particles();
  const auto& b = copy.particles();
  for (int i = 0; i < a.attribute_count(); ++i)
    EXPECT_TRUE(test::bitwise_equal(a.words(i), b.words(i),
                                    a.size() * std::size_t(a.words_per_particle(i))))
        << a.name(i);
  EXPECT_GT(copy.diagnostics(space).kinetic, 0.0);
}

// Free flight without gravity: momentum is conserved and the elastic vibration of a spinning,
// prestrained block stays bounded at the estimated stable time step.
TEST(PdDynamics, VerletAtTheStableStepConservesMomentumAndStaysBounded) {
  const exec::Space space(test::parallel_backend(), 2);
  PdMaterial m;
  m.bulk = Real(2e6);
  m.shear = Real(1.2e6);
  m.density = 1000;
  PdSettings s = settings(PdDeviatoric::Paper, true);
  PdSolver solver(s, {m});
  std::vector<Vec3> x = lattice(8);
  for (Vec3& p : x) p[0] *= Real(1.02);  // prestretched along x: it will vibrate
  solver.add_particles(x, Vec3(1, 0, 0), Vec3(0, 0, 3), Vec3::Constant(Real(0.04)), 0,
                       Real(kLc * kLc * kLc));
  // Reference configuration = the unstretched lattice: rebuild x0 so the body starts strained.
  {
    ParticleSet& ps = solver.particles();
    Vec3* x0 = ps.vec3(solver.attributes().x0);
    for (std::size_t i = 0; i < ps.size(); ++i) x0[i][0] /= Real(1.02);
  }
  solver.initialize(space);
  const PdDiagnostics d0 = solver.diagnostics(space);
  const Real dt = solver.stable_dt(space);
  double vmax = 0;
  for (int k = 0; k < 400; ++k) {
    solver.step(space, dt);
    vmax = std::max(vmax, solver.diagnostics(space).max_speed);
  }
  const PdDiagnostics d1 = solver.diagnostics(space);
  const double pscale = d0.momentum.norm();
  EXPECT_LT((d1.momentum - d0.momentum).norm() / pscale, sizeof(Real) == 4 ? 1e-4 : 1e-10);
  // Elastic energy of the 2 % prestrain is E eps^2 / 2 ~ 1.3 kJ/m^3: speeds of order 1 m/s.
  EXPECT_LT(vmax, 5.0);
  EXPECT_EQ(d1.intact, d1.bonds);
}

// A bar of nx x ny x nz particles along x (lattice spacing lc, origin 0).
std::vector<Vec3> bar(int nx, int ny, int nz) {
  std::vector<Vec3> x;
  for (int i = 0; i < nx; ++i)
    for (int j = 0; j < ny; ++j)
      for (int k = 0; k < nz; ++k)
        x.push_back((kLc * Vec3d(i + 0.5, j + 0.5, k + 0.5)).cast<Real>());
  return x;
}

// Validation: the fundamental longitudinal mode of a free-free bar, u = A cos(pi x / L) sin(w t),
// w = pi c / L, c = sqrt(E / rho) (a thin bar: uniaxial stress; the wavelength 2 L is 16 bar
// widths, so lateral inertia changes c by < 0.1 %). Started with v = V cos(pi x / L), the mode's
// displacement amplitude crosses zero at t = L / c: the time for a wave to cross the bar.
TEST(PdValidation, LongitudinalWaveTravelsAtTheBarSpeed) {
  const exec::Space space(test::parallel_backend(), 2);
  for (PdDeviatoric dev : {PdDeviatoric::Paper, PdDeviatoric::Lps}) {
    const int nx = 48, ny = 6, nz = 6;
    const double Lb = nx * kLc;
    PdSolver solver(settings(dev, true), {glass()});
    const std::vector<Vec3> x = bar(nx, ny, nz);
    solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(kLc * kLc * kLc));
    ParticleSet& ps = solver.particles();
    Vec3* v = ps.vec3(solver.attributes().v);
    for (std::size_t i = 0; i < x.size(); ++i)
      v[i] = Vec3(Real(5 * std::cos(M_PI * double(x[i][0]) / Lb)), 0, 0);
    solver.initialize(space);
    const double E = 9 * 48e9 * 28.8e9 / (3 * 48e9 + 28.8e9), c = std::sqrt(E / 2200);
    auto amplitude = [&] {
      const Vec3* px = ps.vec3(solver.attributes().x);
      double a = 0;
      for (std::size_t i = 0; i < x.size(); ++i)
        a += double(px[i][0] - x[i][0]) * std::cos(M_PI * double(x[i][0]) / Lb);
      return a;
    };
    const Real dt = solver.stable_dt(space);
    double t = 0, a_prev = 0, crossing = 0;
    bool positive = false;
    for (int k = 0; k < 100000 && crossing == 0; ++k) {
      solver.step(space, dt);
      t += double(dt);
      const double a = amplitude();
      if (a > 0) positive = true;
      if (positive && a < 0) crossing = t - double(dt) * a / (a - a_prev);  // linear interpolation
      a_prev = a;
    }
    const double c_measured = Lb / crossing;
    std::printf("%s: bar wave speed %.1f m/s, sqrt(E/rho) = %.1f m/s: ratio %.4f\n",
                pd_deviatoric_name(dev), c_measured, c, c_measured / c);
    EXPECT_NEAR(c_measured / c, 1.0, 0.02) << pd_deviatoric_name(dev);
  }
}

// The correction's fit chain on a thin bar: interior and face particles get the full fit, edge
// particles (families cut by two faces, whose cross moments cannot vanish with positive weights)
// the axis-diagonal one, and no particle is left with the scalar fallback.
TEST(PdModuli, CorrectionFitsEveryParticleOfABar) {
  const exec::Space space;
  PdSolver solver(settings(PdDeviatoric::Paper, true), {glass()});
  const std::vector<Vec3> x = bar(24, 6, 6);
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(kLc * kLc * kLc));
  solver.initialize(space);
  const std::vector<std::uint8_t>& fitted = solver.constants().fitted;
  int full = 0, diagonal = 0, checked = 0;
  for (std::size_t i = 0; i < x.size(); ++i) {
    ASSERT_GT(fitted[i], 0) << "particle " << i << " fell back to the scalar correction";
    full += fitted[i] == 2;
    diagonal += fitted[i] == 1;
    // Away from the bar's ends: a particle on a face, mid-width, gets the full fit; one on an
    // edge of the bar, the diagonal fit.
    const long xx = std::lround(double(x[i][0]) / kLc - 0.5),
               y = std::lround(double(x[i][1]) / kLc - 0.5),
               z = std::lround(double(x[i][2]) / kLc - 0.5);
    if (xx < 4 || xx > 19 || y != 0) continue;
    if (z == 2) {
      EXPECT_EQ(fitted[i], 2) << i;
      ++checked;
    }
    if (z == 0) {
      EXPECT_EQ(fitted[i], 1) << i;
      ++checked;
    }
  }
  EXPECT_GT(full, 0);
  EXPECT_GT(diagonal, 0);  // the edges
  EXPECT_EQ(checked, 2 * 16);
}

// The correction's constants are mirror-symmetric: the notched bar of bench/pd_notch.cpp, centred
// on x = 0 so that its mirror image is exact, must give a particle and its mirror image the same
// fit and the same per-bond factors. A family and its mirror image hold their bonds in different
// orders, so their fits sum in different orders; a notch-corner family once had its full fit
// accepted on one side and rejected on the other (the backtracking failed on round-off one step
// before convergence), dilatational weights 20x apart, and the bar's response lost its symmetry
// by ~10 % of the displacement at that corner (docs/validation.md).
TEST(PdModuli, CorrectionIsMirrorSymmetricOnANotchedBar) {
  const exec::Space space;
  const int nx = 60, ny = 10, nz = 10, notch = 3;
  std::vector<Vec3> x;
  std::vector<long> index(std::size_t(nx * ny * nz), -1), mirror;
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) {
        if ((a == nx / 2 - 1 || a == nx / 2) && b >= ny - notch) continue;
        index[std::size_t((a * ny + b) * nz + c)] = long(x.size());
        x.push_back(Vec3(Real(kLc * (a - 0.5 * (nx - 1))), Real(kLc * (b - 0.5 * (ny - 1))),
                         Real(kLc * (c - 0.5 * (nz - 1)))));
      }
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c)
        if (index[std::size_t((a * ny + b) * nz + c)] >= 0)
          mirror.push_back(index[std::size_t(((nx - 1 - a) * ny + b) * nz + c)]);
  PdSolver solver(settings(PdDeviatoric::Paper, true), {glass()});
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(kLc * kLc * kLc));
  solver.initialize(space);
  const PdBonds& bonds = solver.bonds();
  const PdConstants& c = solver.constants();
  double worst = 0;
  for (std::size_t i = 0; i < x.size(); ++i) {
    const std::size_t m = std::size_t(mirror[i]);
    ASSERT_EQ(c.fitted[i], c.fitted[m]) << "particle " << i;
    ASSERT_EQ(bonds.offsets[i + 1] - bonds.offsets[i], bonds.offsets[m + 1] - bonds.offsets[m]);
    double top = 0;
    for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k)
      top = std::max({top, double(bonds.omega[k]), double(bonds.shear_omega[k])});
    for (std::uint64_t k = bonds.offsets[i]; k < bonds.offsets[i + 1]; ++k) {
      const std::uint32_t jm = std::uint32_t(mirror[bonds.neighbor[k]]);
      const std::uint32_t* row = bonds.neighbor.data() + bonds.offsets[m];
      const std::uint32_t* end = bonds.neighbor.data() + bonds.offsets[m + 1];
      const std::uint32_t* hit = std::lower_bound(row, end, jm);
      ASSERT_TRUE(hit != end && *hit == jm);
      const std::uint64_t km = bonds.offsets[m] + std::uint64_t(hit - row);
      worst =
          std::max({worst, std::abs(double(bonds.omega[k]) - double(bonds.omega[km])) / top,
                    std::abs(double(bonds.shear_omega[k]) - double(bonds.shear_omega[km])) / top});
    }
  }
  std::printf("notched bar: largest mirror difference of the bond weights %.3e of the row's\n",
              worst);
  // Double: the fits' round-off (3.6e-14 measured; 1.7 before d089baf). Float: the lattice positions'
  // own rounding (~1e-6 of delta) reaches the fits through the bond vectors and the sharing of
  // fits between families equal to 1e-6 delta (1.9e-6 measured).
  EXPECT_LT(worst, sizeof(Real) == sizeof(double) ? 1e-10 : 1e-4);
}

// Validation: static tension. A bar clamped over one horizon at x = 0 carries a traction sigma on
// its last layer (force density sigma / lc); dynamic relaxation (viscous damping at about twice
// the fundamental frequency) brings it to rest. An extensometer between the material planes at
// 0.3 L and 0.7 L (away from the clamp and the loaded end, Saint-Venant) reads
// sigma L_gauge / E; the lateral strain gives Poisson's ratio.
TEST(PdValidation, StaticTensionMatchesTheAnalyticElongation) {
  const exec::Space space(test::parallel_backend(), 2);
  const int nx = 40, ny = 6, nz = 6;
  const double Lb = nx * kLc, E = 72e9, sigma = 1e-3 * E;
  PdSettings s = settings(PdDeviatoric::Paper, true);
  s.damping = Real(2 * M_PI * std::sqrt(E / 2200) / (2 * Lb));
  PdSolver solver(s, {glass()});
  const std::vector<Vec3> x = bar(nx, ny, nz);
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(kLc * kLc * kLc));
  solver.prescribe_velocity(Vec3(-1, -1, -1), Vec3(Real(3 * kLc), 1, 1), Vec3::Zero());
  solver.apply_force_density(Vec3(Real(Lb - kLc), -1, -1), Vec3(1, 1, 1),
                             Vec3(Real(sigma / kLc), 0, 0));
  solver.initialize(space);
  const Real dt = solver.stable_dt(space);
  ParticleSet& ps = solver.particles();
  const Vec3* px = ps.vec3(solver.attributes().x);
  for (int k = 0; k < 1500; ++k) solver.step(space, dt);
  // At rest: below 1 % of the loading's velocity scale sigma / sqrt(E rho) (float round-off in
  // the extensions keeps a small jitter alive).
  EXPECT_LT(solver.diagnostics(space).max_speed, 1e-2 * sigma / std::sqrt(E * 2200));
  // Mean axial displacement of the layers i = 12 and i = 28, and the lateral strain between.
  auto layer_ux = [&](int layer) {
    double u = 0;
    int count = 0;
    for (std::size_t i = 0; i < x.size(); ++i)
      if (int(double(x[i][0]) / kLc) == layer) u += double(px[i][0] - x[i][0]), ++count;
    return u / count;
  };
  const double gauge = 16 * kLc;
  const double elongation = layer_ux(28) - layer_ux(12), expected = sigma * gauge / E;
  // Lateral strain: least-squares slope of u_y against y over the gauge section.
  double syy = 0, suy = 0, ym = 0.5 * ny * kLc;
  for (std::size_t i = 0; i < x.size(); ++i) {
    const int layer = int(double(x[i][0]) / kLc);
    if (layer < 12 || layer > 28) continue;
    const double y = double(x[i][1]) - ym;
    syy += y * y;
    suy += y * double(px[i][1] - x[i][1]);
  }
  const double nu = -(suy / syy) / (elongation / gauge);
  std::printf(
      "gauge elongation %.4e m, analytic %.4e m: ratio %.4f; Poisson ratio %.3f (input 0.25)\n",
      elongation, expected, elongation / expected, nu);
  EXPECT_NEAR(elongation / expected, 1.0, 0.03);
  EXPECT_NEAR(nu, 0.25, 0.03);
}

// The stability guard names the step, the particle and the quantity.
TEST(PdDynamics, StabilityGuardNamesParticleAndQuantity) {
  const exec::Space space;
  PdSolver solver = make_block(4, settings(PdDeviatoric::Paper, true), glass(), space);
  Vec3* v = solver.particles().vec3(solver.attributes().v);
  v[17] = Vec3(std::numeric_limits<Real>::quiet_NaN(), 0, 0);
  try {
    solver.stable_dt(space);
    FAIL() << "no error on a NaN velocity";
  } catch (const SimulationError& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("step 0"), std::string::npos) << m;
    EXPECT_NE(m.find("particle 17 (id 17)"), std::string::npos) << m;
    EXPECT_NE(m.find("non-finite velocity"), std::string::npos) << m;
  }
  v[17] = Vec3(Real(2e4), 0, 0);
  try {
    solver.stable_dt(space);
    FAIL() << "no error on a runaway speed";
  } catch (const SimulationError& e) {
    EXPECT_NE(std::string(e.what()).find("above the stability limit max_speed"), std::string::npos)
        << e.what();
  }
  EXPECT_THROW(solver.step(space, Real(-1)), SimulationError);
}

}  // namespace
}  // namespace amalgam

namespace amalgam {
namespace {

// A conforming tetrahedral mesh of an n x n x n grid of cubes of side h (6 Kuhn tetrahedra per
// cube: the paths from corner 000 to 111 along the three axes in every order).
void kuhn_grid(int n, double h, std::vector<Vec3d>& nodes,
               std::vector<std::array<std::int32_t, 4>>& tets) {
  const int m = n + 1;
  auto id = [m](int i, int j, int k) { return std::int32_t((i * m + j) * m + k); };
  nodes.clear();
  tets.clear();
  for (int i = 0; i < m; ++i)
    for (int j = 0; j < m; ++j)
      for (int k = 0; k < m; ++k) nodes.emplace_back(i * h, j * h, k * h);
  const int perms[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k)
        for (const auto& p : perms) {
          int c[3] = {i, j, k};
          std::array<std::int32_t, 4> t;
          t[0] = id(c[0], c[1], c[2]);
          for (int s = 0; s < 3; ++s) {
            ++c[p[s]];
            t[s + 1] = id(c[0], c[1], c[2]);
          }
          tets.push_back(t);
        }
}

// A solver with one particle per tetrahedron (barycentre, volume) and the mesh embedded.
PdSolver tet_solver(int n, double h, const PdSettings& s, const PdMaterial& m) {
  std::vector<Vec3d> nodes;
  std::vector<std::array<std::int32_t, 4>> tets;
  kuhn_grid(n, h, nodes, tets);
  std::vector<Vec3> x;
  std::vector<Real> vol;
  for (const auto& t : tets) {
    const Vec3d a = nodes[t[0]], b = nodes[t[1]], c = nodes[t[2]], d = nodes[t[3]];
    x.push_back(((a + b + c + d) / 4).cast<Real>());
    vol.push_back(Real(std::abs((b - a).cross(c - a).dot(d - a)) / 6));
  }
  PdSolver solver(s, {m});
  solver.add_particles(x, vol, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0);
  solver.add_crack_mesh(nodes, tets, 0);
  return solver;
}

// Every directed edge of the surface, counted: a closed, consistently oriented 2-manifold has
// each directed edge exactly once and its reverse exactly once.
bool closed_oriented_manifold(const std::vector<std::array<std::uint32_t, 3>>& tris) {
  std::map<std::pair<std::uint32_t, std::uint32_t>, int> edges;
  for (const auto& t : tris)
    for (int k = 0; k < 3; ++k) ++edges[{t[k], t[(k + 1) % 3]}];
  for (const auto& e : edges)
    if (e.second != 1 || edges.count({e.first.second, e.first.first}) == 0) return false;
  return true;
}

// Sec. 5.2: a crack through the whole body (a pre-crack across the plane x = 2h of a 4^3 grid)
// splits every vertex on the plane in two, the crack faces appear on both sides, and the surface
// is two closed, outward-oriented pieces.
TEST(PdCrackMesh, ACrackThroughTheBodySplitsThePlaneVerticesAndClosesBothPieces) {
  const exec::Space space;
  const double h = 0.01;
  PdSettings s = settings(PdDeviatoric::Paper, true);
  s.spacing = Real(0.5 * h);
  s.horizon = Real(1.5 * h);
  PdSolver solver = tet_solver(4, h, s, glass());
  std::vector<Vec3> v;
  std::vector<std::array<std::uint32_t, 3>> tris;
  std::vector<std::uint8_t> crack;
  solver.crack_meshes()[0].surface(v, tris, crack);
  EXPECT_EQ(tris.size(), std::size_t(6 * 16 * 2));  // 6 faces x 16 squares x 2 triangles
  EXPECT_TRUE(closed_oriented_manifold(tris));
  solver.add_precrack(Vec3(Real(2 * h), 0, 0), Vec3(1, 0, 0), Vec3::Constant(-1),
                      Vec3::Constant(1));
  solver.initialize(space);
  const PdCrackMesh& mesh = solver.crack_meshes()[0];
  EXPECT_EQ(mesh.vertices(), std::size_t(125 + 25));   // the 5 x 5 vertices of the plane, twice
  EXPECT_EQ(mesh.crack_faces(), std::size_t(16 * 2));  // 16 squares of 2 triangles in the plane
  mesh.surface(v, tris, crack);
  EXPECT_EQ(tris.size(), std::size_t(6 * 16 * 2 + 2 * 32));
  EXPECT_EQ(std::count(crack.begin(), crack.end(), 1), 64);
  EXPECT_TRUE(closed_oriented_manifold(tris));
  // No vertex is shared across the plane any more.
  for (const auto& t : mesh.tets()) {
    const bool left = (mesh.positions()[t[0]] + mesh.positions()[t[1]] + mesh.positions()[t[2]] +
                       mesh.positions()[t[3]])[0] /
                          4 <
                      Real(2 * h);
    for (const auto& u : mesh.tets()) {
      const bool uleft = (mesh.positions()[u[0]] + mesh.positions()[u[1]] + mesh.positions()[u[2]] +
                          mesh.positions()[u[3]])[0] /
                             4 <
                         Real(2 * h);
      if (left == uleft) continue;
      for (auto a : t)
        for (auto b : u) ASSERT_NE(a, b);
    }
  }
}

// Eqs. 19-21: under a rigid translation every vertex moves with the particles; under fracture
// the vertices stay with their tetrahedra's particles.
TEST(PdCrackMesh, VerticesFollowTheParticles) {
  const exec::Space space(test::parallel_backend(), 2);
  const double h = 0.01;
  PdSettings s = settings(PdDeviatoric::Paper, true);
  s.spacing = Real(0.5 * h);
  s.horizon = Real(1.5 * h);
  PdMaterial m = glass();
  m.critical_stretch = Real(2e-3);
  PdSolver solver = tet_solver(4, h, s, m);
  ParticleSet& ps = solver.particles();
  {  // rigid translation, eqs. 19-21 directly: every vertex moves by v dt
    PdCrackMesh mesh = solver.crack_meshes()[0];
    const std::vector<Vec3> before = mesh.positions();
    const std::vector<Vec3> v(ps.size(), Vec3(1, -2, 3));
    mesh.move_vertices(v.data(), ps.real(solver.attributes().volume),
                       ps.int32(solver.attributes().material), solver.materials().data(),
                       Real(1e-3));
    for (std::size_t k = 0; k < mesh.vertices(); ++k)
      EXPECT_LT((mesh.positions()[k] - before[k] - Vec3(1, -2, 3) * Real(1e-3)).norm(), 1e-6) << k;
    // The velocity written with the surface (PLY vx vy vz) is that motion: v for every vertex.
    std::vector<double> weight;
    std::vector<Vec3d> vertex_v;
    mesh.vertex_velocities(v.data(), ps.real(solver.attributes().volume),
                           ps.int32(solver.attributes().material), solver.materials().data(),
                           weight, vertex_v);
    std::vector<Vec3> verts, vel;
    std::vector<std::array<std::uint32_t, 3>> tris;
    std::vector<std::uint8_t> crack;
    mesh.surface(verts, tris, crack, &vertex_v, &vel);
    ASSERT_EQ(vel.size(), verts.size());
    for (const Vec3& u : vel) EXPECT_LT((u - Vec3(1, -2, 3)).norm(), 1e-5);
  }
  solver.prescribe_velocity(Vec3::Constant(-1), Vec3(Real(0.8 * h), 1, 1), Vec3(-20, 0, 0));
  solver.prescribe_velocity(Vec3(Real(3.2 * h), -1, -1), Vec3::Constant(1), Vec3(20, 0, 0));
  solver.initialize(space);
  const Real dt = solver.stable_dt(space);
  for (int k = 0; k < 200; ++k) solver.step(space, dt);
  const PdCrackMesh& mesh = solver.crack_meshes()[0];
  EXPECT_GT(mesh.crack_faces(), 0u);
  EXPECT_GT(mesh.vertices(), 125u);
  // Each tetrahedron's vertex centroid stays near its particle (within half a cell).
  const Vec3* x = ps.vec3(solver.attributes().x);
  double worst = 0;
  for (std::size_t t = 0; t < mesh.tets().size(); ++t) {
    Vec3 c = Vec3::Zero();
    for (auto vtx : mesh.tets()[t]) c += mesh.positions()[vtx] / Real(4);
    worst = std::max(worst, double((c - x[t]).norm()));
  }
  EXPECT_LT(worst, 0.5 * h);
  // The surface's per-vertex velocity after the fracture: the ends' vertices (all their
  // tetrahedra's particles prescribed) move at exactly -20 and +20 m/s along x, and every vertex's
  // (a weighted mean of particle velocities) lies within the particles' range on each axis.
  std::vector<double> weight;
  std::vector<Vec3d> vertex_v;
  mesh.vertex_velocities(ps.vec3(solver.attributes().v), ps.real(solver.attributes().volume),
                         ps.int32(solver.attributes().material), solver.materials().data(), weight,
                         vertex_v);
  std::vector<Vec3> verts, vel;
  std::vector<std::array<std::uint32_t, 3>> tris;
  std::vector<std::uint8_t> crack;
  mesh.surface(verts, tris, crack, &vertex_v, &vel);
  ASSERT_EQ(vel.size(), verts.size());
  const Vec3* pv = ps.vec3(solver.attributes().v);
  Vec3 lo = pv[0], hi = pv[0];
  for (std::size_t i = 0; i < ps.size(); ++i) lo = lo.cwiseMin(pv[i]), hi = hi.cwiseMax(pv[i]);
  int left = 0, right = 0;
  for (const Vec3& u : vel) {
    for (int k = 0; k < 3; ++k) {
      EXPECT_GE(u[k], lo[k] - 1e-4 * (1 + std::abs(lo[k])));
      EXPECT_LE(u[k], hi[k] + 1e-4 * (1 + std::abs(hi[k])));
    }
    left += (u - Vec3(-20, 0, 0)).norm() < 1e-4;
    right += (u - Vec3(20, 0, 0)).norm() < 1e-4;
  }
  EXPECT_GE(left, 25);  // the 5 x 5 vertices of the plane x = 0, at least
  EXPECT_GE(right, 25);
}

// Bond compaction (PdSettings::compact_fraction) must not change the run: every kernel skips
// broken bonds and a compacted row keeps its order, so sums are the same in the same order, and
// broken bonds the contact rule still reads (0.9 L < contact distance) are kept.
TEST(PdCompaction, ABreakingBarRunsBitwiseAsWithout) {
  const exec::Space space(test::parallel_backend(), 2);
  PdSolver ref = pulled_bar(space, 0);
  const Real dt = ref.stable_dt(space);
  for (int k = 0; k < 80; ++k) ref.step(space, dt);
  const PdDiagnostics dr = ref.diagnostics(space);
  EXPECT_EQ(dr.compactions, 0u);
  EXPECT_EQ(dr.stored, dr.bonds);
  EXPECT_LT(dr.intact, dr.bonds * 95 / 100);  // more than 5 % broke
  for (const Real fraction : {Real(0.005), Real(0.1)}) {
    PdSolver c = pulled_bar(space, fraction);
    for (int k = 0; k < 80; ++k) c.step(space, dt);
    const PdDiagnostics d = c.diagnostics(space);
    const std::string what = "compact_fraction " + std::to_string(fraction);
    EXPECT_GT(d.compactions, fraction < Real(0.01) ? 2u : 0u) << what;
    EXPECT_LT(d.stored, dr.bonds) << what;
    EXPECT_EQ(d.intact, dr.intact) << what;
    EXPECT_EQ(d.bonds, dr.bonds) << what;
    expect_same_state(ref, c, what);
  }
}

// Tetrahedron barycentres lie closer than the contact distance, so broken bonds are kept for the
// contact rule; the crack mesh's faces find their bonds again after each compaction.
TEST(PdCompaction, TetMeshCracksAndSurfaceAreUnchanged) {
  const exec::Space space(test::parallel_backend(), 2);
  const double h = 0.01;
  auto run = [&](Real fraction) {
    PdSettings s = settings(PdDeviatoric::Paper, true);
    s.spacing = Real(0.5 * h);
    s.horizon = Real(1.5 * h);
    s.contact = true;
    s.compact_fraction = fraction;
    PdMaterial m = glass();
    m.critical_stretch = Real(2e-3);
    PdSolver solver = tet_solver(4, h, s, m);
    solver.prescribe_velocity(Vec3::Constant(-1), Vec3(Real(0.8 * h), 1, 1), Vec3(-20, 0, 0));
    solver.prescribe_velocity(Vec3(Real(3.2 * h), -1, -1), Vec3::Constant(1), Vec3(20, 0, 0));
    solver.initialize(space);
    const Real dt = solver.stable_dt(space);
    for (int k = 0; k < 200; ++k) solver.step(space, dt);
    return solver;
  };
  const PdSolver ref = run(0), c = run(Real(0.01));
  const PdDiagnostics dr = ref.diagnostics(space), d = c.diagnostics(space);
  EXPECT_GT(d.compactions, 0u);
  EXPECT_LT(d.stored, dr.stored);
  EXPECT_GT(d.stored, d.intact);  // short broken bonds kept for contact
  expect_same_state(ref, c, "tet mesh");
  const PdCrackMesh &mr = ref.crack_meshes()[0], &mc = c.crack_meshes()[0];
  EXPECT_GT(mr.crack_faces(), 0u);
  EXPECT_EQ(mr.crack_faces(), mc.crack_faces());
  EXPECT_EQ(mr.vertices(), mc.vertices());
  EXPECT_EQ(mr.tets(), mc.tets());
  EXPECT_TRUE(test::bitwise_equal(mr.positions().data(), mc.positions().data(), mr.vertices()));
}

// A frame's retry (PdSolver::save / restore, what the frame loop uses): after steps that break
// bonds and compact them, restoring the snapshot brings back the bond layout, the per-bond state,
// the counters and the clock, and the same steps again give bitwise the same state.
TEST(PdCompaction, SnapshotRestoresAcrossCompactions) {
  const exec::Space space(test::parallel_backend(), 2);
  PdSolver a = pulled_bar(space, Real(0.005)), twin = pulled_bar(space, Real(0.005));
  const Real dt = a.stable_dt(space);
  for (int k = 0; k < 10; ++k) a.step(space, dt), twin.step(space, dt);
  PdSolver::Snapshot snap;
  a.save(snap);
  const std::uint64_t compactions = a.diagnostics(space).compactions;
  const std::size_t stored = a.bonds().size();
  for (int k = 0; k < 50; ++k) a.step(space, dt);
  ASSERT_GT(a.diagnostics(space).compactions, compactions);  // the layout changed since save()
  a.restore(snap);
  EXPECT_EQ(a.bonds().size(), stored);
  EXPECT_EQ(a.bonds().neighbor, twin.bonds().neighbor);
  EXPECT_EQ(a.bonds().intact, twin.bonds().intact);
  EXPECT_EQ(a.time(), twin.time());
  EXPECT_EQ(a.step_count(), twin.step_count());
  for (int k = 0; k < 50; ++k) a.step(space, dt), twin.step(space, dt);
  expect_same_state(twin, a, "restored and stepped again");
  EXPECT_EQ(a.bonds().neighbor, twin.bonds().neighbor);
  EXPECT_EQ(a.bonds().plastic, twin.bonds().plastic);
  EXPECT_EQ(a.diagnostics(space).compactions, twin.diagnostics(space).compactions);
  // Restored twice (a second retry of the same frame) is the same.
  a.restore(snap);
  for (int k = 0; k < 50; ++k) a.step(space, dt);
  expect_same_state(twin, a, "restored again");
}

// A copy of a solver does not carry the original's armed snapshot: the copy's compactions leave
// the original's frame-start snapshot alone (before, the copy wrote its own bond layout into it,
// and a retry of the original would have restored the copy's bonds).
TEST(PdCompaction, CopyDoesNotWriteIntoTheOriginalsSnapshot) {
  const exec::Space space(test::parallel_backend(), 2);
  PdSolver a = pulled_bar(space, Real(0.005));
  const Real dt = a.stable_dt(space);
  for (int k = 0; k < 10; ++k) a.step(space, dt);
  PdSolver::Snapshot snap;
  a.save(snap);
  PdSolver copy = a;
  for (int k = 0; k < 50; ++k) copy.step(space, dt);
  ASSERT_GT(copy.diagnostics(space).compactions, a.diagnostics(space).compactions);
  EXPECT_FALSE(snap.layout_saved);
}

// A checkpoint of a compacted run stores its bond rows; a fresh solver (full bond list) restricts
// its bonds to them and continues bitwise like the uninterrupted run (and like one that never
// compacted). A checkpoint whose rows are not a subset of the scene's bonds is an InputError.
TEST(PdCompaction, CheckpointOfACompactedRunResumesBitwise) {
  const exec::Space space(test::parallel_backend(), 2);
  const std::string path = ::testing::TempDir() + "pd_compacted.amck";
  PdSolver a = pulled_bar(space, Real(0.005)), never = pulled_bar(space, 0);
  const Real dt = a.stable_dt(space);
  for (int k = 0; k < 50; ++k) a.step(space, dt), never.step(space, dt);
  ASSERT_GT(a.diagnostics(space).compactions, 0u);
  ASSERT_LT(a.bonds().size(), never.bonds().size());
  PdSimulation sim_a(std::move(a), space), sim_b(pulled_bar(space, Real(0.005)), space);
  write_checkpoint(path, sim_a, 7, 42);
  const CheckpointState st = read_checkpoint(path, sim_b, 42);
  PdSolver &a2 = sim_a.solver(), &b = sim_b.solver();
  EXPECT_EQ(st.next_frame, 7);
  EXPECT_EQ(b.bonds().neighbor, a2.bonds().neighbor);
  EXPECT_EQ(b.bonds().reverse, a2.bonds().reverse);
  EXPECT_EQ(b.bonds().omega, a2.bonds().omega);
  EXPECT_EQ(b.bonds().intact, a2.bonds().intact);
  EXPECT_EQ(b.bonds().plastic, a2.bonds().plastic);
  for (int k = 0; k < 30; ++k) a2.step(space, dt), b.step(space, dt), never.step(space, dt);
  expect_same_state(a2, b, "resumed");
  expect_same_state(never, b, "resumed vs never compacted");
  // The same lattice with a smaller horizon has fewer bonds per row: not a superset.
  PdSettings s = settings(PdDeviatoric::Paper, true);
  s.contact = true;
  s.horizon = Real(2.2 * kLc);
  PdSolver other(s, {breakable()});
  other.add_particles(
      std::vector<Vec3>(a2.particles().vec3(a2.attributes().x0),
                        a2.particles().vec3(a2.attributes().x0) + a2.particles().size()),
      Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(kLc * kLc * kLc));
  other.initialize(space);
  PdSimulation sim_other(std::move(other), space);
  try {
    read_checkpoint(path, sim_other, 42);
    ADD_FAILURE() << "a foreign bond list was accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("not a subset of this scene's bonds"), std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace amalgam
