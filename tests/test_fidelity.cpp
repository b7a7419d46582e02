// Physical fidelity of the float build (issue 27): an elastic column at rest on a floor settles to
// the analytic static compression wherever it sits, including on a grid-node plane and far from
// the origin, and a wall exactly on a node plane holds; a notched peridynamic bar breaks and keeps
// breaking after its halves are free exactly as LAMMPS peri/lps does on the same lattice.
//
// Column: nu = 0 (lambda = 0, mu = E/2, so the 1-D modulus 2 mu = E), height H, density rho,
// under gravity g on a slip floor. At rest the axial strain is eps(y) = -rho g (H - y)/E with y
// measured from the floor, so the displacement is u(y) = -rho g/E (H y - y^2/2) and the top band
// comes down towards the bottom band by u(y_bot) - u(y_top). Kelvin-Voigt viscosity damps the
// column's axial ringing; the compression is averaged over the last second (100 samples).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "solvers/mpm_solver.hpp"
#include "solvers/pd_solver.hpp"

using namespace amalgam;

namespace {

Collider half_space(const Vec3d& point, const Vec3& normal) {
  Collider c;
  c.shape = ColliderShape::HalfSpace;
  c.origin = point.cast<Real>();
  c.normal = normal;
  c.boundary = BoundaryType::Slip;
  return c;
}

void run_until(MpmSolver& solver, const exec::Space& space, double t_end) {
  while (solver.time() < t_end) {
    const double dt = std::min(double(solver.stable_dt(space)), t_end - solver.time() + 1e-12);
    solver.step(space, Real(dt));
  }
}

struct ColumnResult {
  double measured = 0, analytic = 0, spread = 0;  // top-to-bottom compression (m)
  double error() const { return measured / analytic - 1; }
};

// A column 0.1 x 0.4 x 0.1 m with its bottom face on a floor at `floor` (the column's lower corner
// is `floor`), dx = 0.02 m, 2 x 2 x 2 particles per cell. `F0`: every particle's initial
// deformation gradient, a rotation (the material's rest shape turned by F0^T, so the column starts
// unstressed and settles to the same compression; F = (I + strain) F0 stays far from I).
// `keep_F`: the particles keep F + F_lo (as for an output of F: MpmSettings::keep_F) instead of
// b - I (MpmSolver::keeps_b, the default).
ColumnResult settle_column(const Vec3d& floor, const Mat3& F0 = Mat3::Identity(),
                           bool keep_F = false) {
  const double dx = 0.02, W = 0.1, H = 0.4, rho = 1000, E = 3.9e6, g = 9.81;
  MpmSettings s;
  s.dx = Real(dx);
  s.keep_F = keep_F;
  s.transfer = Transfer::Apic;
  s.cfl = Real(0.5);
  MaterialParams m{MaterialModel::FixedCorotated, Real(E / 2), 0, Real(rho)};
  m.viscosity = 200;  // Kelvin-Voigt: damps the axial modes within ~1 s
  MpmSolver solver(s, {m}, {half_space(floor, Vec3::UnitY())});
  std::vector<Vec3> x;
  std::vector<double> y0;
  const double h = dx / 2;
  for (int i = 0; i < int(std::lround(W / h)); ++i)
    for (int j = 0; j < int(std::lround(H / h)); ++j)
      for (int k = 0; k < int(std::lround(W / h)); ++k) {
        const Vec3d p = floor + h * Vec3d(i + 0.5, j + 0.5, k + 0.5);
        x.push_back(p.cast<Real>());
        y0.push_back((j + 0.5) * h);  // height above the floor, exactly
      }
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(std::pow(h, 3)));
  const MpmAttributes& a = solver.attributes();
  EXPECT_EQ(a.F >= 0, keep_F);
  EXPECT_EQ(a.b >= 0, !keep_F);
  for (std::size_t p = 0; p < x.size(); ++p)
    if (keep_F)
      solver.particles().mat3(a.F)[p] = F0;
    else
      solver.particles().sym_dev(a.b)[p] = b_from_F<Real>(F0.cast<double>());
  // Bands: the lowest and highest particle layers, by their (exact) initial heights.
  const double y_bot = 0.5 * h, y_top = H - 0.5 * h;
  auto u = [&](double y) { return -rho * g / E * (H * y - 0.5 * y * y); };
  ColumnResult r;
  r.analytic = u(y_bot) - u(y_top);
  // The bands' mean heights as stored (far from the origin the float lattice is not exact).
  auto band_distance = [&](const std::vector<Vec3d>& pos) {
    double top = 0, bot = 0;
    int nt = 0, nb = 0;
    for (std::size_t p = 0; p < pos.size(); ++p) {
      if (y0[p] == y_top) top += pos[p][1], ++nt;
      if (y0[p] == y_bot) bot += pos[p][1], ++nb;
    }
    return top / nt - bot / nb;
  };
  const double d0 = band_distance(solver.positions_by_id());
  const exec::Space space(exec::Backend::TBB, 2);
  run_until(solver, space, 2.0);
  double sum = 0, sq = 0;
  int samples = 0;
  for (double t = 2.0; t < 3.0 - 1e-9; t += 0.01) {
    run_until(solver, space, t + 0.01);
    // Compression: the initial band distance minus the current one.
    const double c = d0 - band_distance(solver.positions_by_id());
    sum += c, sq += c * c, ++samples;
  }
  r.measured = sum / samples;
  r.spread = std::sqrt(std::max(0.0, sq / samples - r.measured * r.measured));
  std::printf(
      "column at (%.9g, %.9g, %.9g)%s%s: compression %.6e m (sd %.2e), analytic %.6e m, %+.4f "
      "%%\n",
      floor[0], floor[1], floor[2], F0.isIdentity() ? "" : ", rest shape rotated",
      keep_F ? ", F + F_lo" : ", b - I", r.measured, r.spread, r.analytic, 100 * r.error());
  return r;
}

}  // namespace

// Before the change the float build was -19 % (floor at 0.05), -37 % (node plane) and +45 % (50 m
// out) off; the double build within 1 %.
//
// Near the origin, and the same column with a rotated rest shape: F = (I + strain) R, every
// entry O(1), so the increments of a column coming to rest are below a float ulp of F and only the
// compensated F (F + F_lo) keeps them. The physics does not depend on the rest shape's
// orientation, so the two columns must settle alike: the compressions within 0.02 % of the
// analytic one of each other and the rotated column as still (its sd over the window at most
// twice the other's). Measured (float, TBB 2 threads): +0.8627 % and +0.8669 %, sd 1.88e-7 and
// 1.84e-7 m. With F stored as I + D, D one float and no F_lo (36 B less per particle,
// docs/benchmarks.md "Memory"), the rotated column settles at +0.78 % with sd 1.1e-6 m; with
// plain float F at -1.37 %, sd 1.0e-6 m (and the unrotated one at +3.84 %): both within the 2 %
// of the other columns, neither rotation-invariant.
//
// The particles keep b - I of b = F F^T by default (MpmSolver::keeps_b): the rotated rest shape has
// b = I to double rounding (~1e-16), the unrotated one's state; measured +0.8625 % and +0.8658 %,
// sd 1.88e-7 m both. The pair F + F_lo (kept when the output asks for F) as before: +0.8627 % and
// +0.8670 %, sd 1.88e-7 and 1.83e-7 m.
TEST(Fidelity, ColumnAtRestNearTheOriginAndWithARotatedRestShape) {
  const Vec3d floor(0.13, 0.05, 0.17);
  const Mat3 R = Eigen::AngleAxis<Real>(Real(0.7), Vec3(1, 2, 3).normalized()).toRotationMatrix();
  for (const bool keep_F : {false, true}) {
    const ColumnResult plain = settle_column(floor, Mat3::Identity(), keep_F),
                       turned = settle_column(floor, R, keep_F);
    EXPECT_LT(std::abs(plain.error()), 0.02);
    EXPECT_LT(std::abs(turned.error()), 0.02);
    EXPECT_NEAR(turned.error(), plain.error(), 2e-4);
    EXPECT_LE(turned.spread, 2 * plain.spread);
  }
}

TEST(Fidelity, ColumnAtRestFiftyMetresOut) {
  EXPECT_LT(std::abs(settle_column(Vec3d(50.03, 50.05, -49.97)).error()), 0.02);
}

// A floor on a node plane (y = 0.08 = 4 dx), and placed one float ulp above and below it: grid
// nodes on the plane are constrained in all three placements (colliders.hpp: node_tolerance), so
// the column rests the same way on each (before, a node one ulp outside the wall was free and the
// column settled differently). The first placement is the former Fidelity.ColumnAtRestOnANodePlane
// (the same floor, 0.08 as a double), which is therefore not settled twice (docs/testing.md, CI time).
TEST(Fidelity, FloorOneUlpOffANodePlaneHoldsTheSame) {
  const float plane = 0.08f;
  std::vector<double> errors;
  for (double y :
       {0.08, double(std::nextafter(plane, 1.0f)), double(std::nextafter(plane, 0.0f))}) {
    const ColumnResult r = settle_column(Vec3d(0.1, y, 0.1));
    EXPECT_LT(std::abs(r.error()), 0.02) << "floor at " << y;
    errors.push_back(r.error());
  }
  EXPECT_NEAR(errors[1], errors[0], 2e-3);
  EXPECT_NEAR(errors[2], errors[0], 2e-3);
}

// The notched glass bar of docs/validation.md ("Peridynamics after fracture"), 40 x 8 x 8 lattice
// (lc = 0.01 m, delta = 3.015 lc, K = 48 GPa, G = 28.8 GPa, rho = 2200), a notch 2 layers wide
// and 3 deep at mid-length, the end layers started at -+12 m/s; the LPS model, the classical
// criterion s00 = 1e-3 and LAMMPS's contact distance 1.35 lc, against LAMMPS peri/lps on the same
// lattice (tests/data/lammps/notch_40x8x8_lps.txt, bench/pd_notch.lmp). The bar breaks within
// 0.05 ms; its halves then ring undamped and keep losing bonds near the crack (the damage grows
// by 40 % by 2 ms in LAMMPS too: the model, not numerics). The damage sums must follow LAMMPS's
// within 3 % at every sample (measured: 0.1 % to 1.65 ms, 1.5 % at 2 ms, where the float and
// double runs' round-off has grown into different late breaks), and the largest speed stay below
// the end speed once the halves are free, as in LAMMPS (at most 8.8 m/s).
TEST(Fidelity, NotchedPdBarFollowsLammpsPeriLps) {
  std::ifstream in(std::string(AMALGAM_SOURCE_DIR) + "/tests/data/lammps/notch_40x8x8_lps.txt");
  ASSERT_TRUE(in) << "tests/data/lammps/notch_40x8x8_lps.txt";
  struct Sample {
    double t_ms, left, right, vmax;
  };
  std::vector<Sample> peer;
  for (std::string line; std::getline(in, line);) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ls(line);
    Sample s{};
    ls >> s.t_ms >> s.left >> s.right >> s.vmax;
    peer.push_back(s);
  }
  ASSERT_EQ(peer.size(), 40u);
  const int nx = 40, ny = 8, nz = 8, notch = 3;
  const double lc = 0.01, vend = 12;
  PdSettings st;
  st.spacing = Real(lc);
  st.horizon = Real(3.015 * lc);
  st.model = PdModel::Lps;
  st.deviatoric = PdDeviatoric::Lps;
  st.surface_correction = false;
  st.criterion = PdCriterion::Classical;
  st.contact_distance = Real(1.35 * lc);
  st.gravity = Vec3::Zero();
  PdMaterial glass;
  glass.bulk = Real(48e9);
  glass.shear = Real(28.8e9);
  glass.density = 2200;
  glass.critical_stretch = Real(1e-3);
  PdSolver solver(st, {glass});
  std::vector<Vec3> x;
  std::vector<int> column;
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) {
        if ((a == nx / 2 - 1 || a == nx / 2) && b >= ny - notch) continue;
        x.push_back(Vec3(Real(lc * (a - 0.5 * (nx - 1))), Real(lc * (b - 0.5 * (ny - 1))),
                         Real(lc * (c - 0.5 * (nz - 1)))));
        column.push_back(a);
      }
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(lc * lc * lc));
  const exec::Space space(exec::Backend::Serial, 1);
  solver.initialize(space);
  Vec3* v = solver.particles().vec3(solver.attributes().v);
  for (std::size_t i = 0; i < x.size(); ++i) {
    if (column[i] == 0) v[i] = Vec3(Real(-vend), 0, 0);
    if (column[i] == nx - 1) v[i] = Vec3(Real(vend), 0, 0);
  }
  const Real* damage = solver.particles().real(solver.attributes().damage);
  const Real dt = Real(1e-6);
  long step = 0;
  double worst = 0;
  for (const Sample& s : peer) {
    for (; step < std::lround(s.t_ms * 1e3); ++step) solver.step(space, dt);
    double left = 0, right = 0, vmax = 0;
    for (std::size_t i = 0; i < x.size(); ++i) {
      (column[i] < nx / 2 ? left : right) += double(damage[i]);
      vmax = std::max(vmax, double(v[i].norm()));
    }
    const double rel = (left + right) / (s.left + s.right) - 1;
    worst = std::max(worst, std::abs(rel));
    EXPECT_LT(std::abs(rel), 0.03)
        << "t = " << s.t_ms << " ms: damage " << left + right << ", LAMMPS " << s.left + s.right;
    EXPECT_LT(vmax, vend) << "t = " << s.t_ms << " ms (LAMMPS " << s.vmax << " m/s)";
  }
  std::printf("notched bar against LAMMPS: largest damage difference %.3f %%\n", 100 * worst);
}

// A symmetric peridynamic body under a symmetric load stays mirror-symmetric to round-off, and
// the same body 10 m from the origin responds as it does at the origin. A 20 x 8 x 8 block
// (paper model, surface correction), its end layers pulled apart at -+1 m/s for 1 ms, no
// fracture. Before the peridynamic positions were compensated (x + x_lo, the bond passes reading
// the displacement), the block at 10 m had its increments dt v (~1e-6 m) rounded to the float
// spacing of 10 m (~1e-6 m): mirror difference 1.7e-3 lc and the kinetic energy pumped ~100x.
namespace {
struct PulledBlock {
  double mirror = 0;  // largest |x_i - mirror(x_j)| over the run, in lattice spacings
  double kinetic = 0;
};
PulledBlock pull_block(double shift) {
  const int nx = 20, ny = 8, nz = 8;
  const double lc = 0.01;
  PdSettings st;
  st.spacing = Real(lc);
  st.horizon = Real(3.015 * lc);
  st.gravity = Vec3::Zero();
  st.fracture = false;
  PdMaterial glass;
  glass.bulk = Real(48e9);
  glass.shear = Real(28.8e9);
  glass.density = 2200;
  PdSolver solver(st, {glass});
  std::vector<Vec3> x;
  std::vector<long> mirror;
  for (int a = 0; a < nx; ++a)
    for (int b = 0; b < ny; ++b)
      for (int c = 0; c < nz; ++c) {
        x.push_back(Vec3(Real(lc * (a - 0.5 * (nx - 1)) + shift), Real(lc * (b - 0.5 * (ny - 1))),
                         Real(lc * (c - 0.5 * (nz - 1)))));
        mirror.push_back(long(((nx - 1 - a) * ny + b) * nz + c));
      }
  solver.add_particles(x, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), 0, Real(lc * lc * lc));
  const Real lo = Real(shift - 0.5 * (nx - 1) * lc), hi = Real(shift + 0.5 * (nx - 1) * lc);
  solver.prescribe_velocity(Vec3(lo - Real(lc / 2), -1, -1), Vec3(lo + Real(lc / 2), 1, 1),
                            Vec3(-1, 0, 0));
  solver.prescribe_velocity(Vec3(hi - Real(lc / 2), -1, -1), Vec3(hi + Real(lc / 2), 1, 1),
                            Vec3(1, 0, 0));
  const exec::Space space(exec::Backend::Serial, 1);
  solver.initialize(space);
  const Vec3* px = solver.particles().vec3(solver.attributes().x);
  const Vec3* plo = solver.particles().vec3(solver.attributes().x_lo);
  PulledBlock r;
  const Real dt = Real(1e-6);
  for (int step = 1; step <= 1000; ++step) {
    solver.step(space, dt);
    if (step % 50) continue;
    for (std::size_t i = 0; i < x.size(); ++i) {
      const std::size_t j = std::size_t(mirror[i]);
      const double xi = double(px[i][0]) - shift + double(plo[i][0]);
      const double xj = double(px[j][0]) - shift + double(plo[j][0]);
      const Vec3d d(xi + xj, double(px[i][1] - px[j][1]), double(px[i][2] - px[j][2]));
      r.mirror = std::max(r.mirror, d.norm() / lc);
    }
  }
  r.kinetic = solver.diagnostics(space).kinetic;
  return r;
}
}  // namespace

TEST(Fidelity, PulledPdBlockStaysSymmetricAtTheOriginAndTenMetresOut) {
  const PulledBlock here = pull_block(0), away = pull_block(10);
  std::printf(
      "pulled block: mirror difference %.3e lc at the origin, %.3e lc at 10 m; kinetic "
      "energy %.6e J and %.6e J\n",
      here.mirror, away.mirror, here.kinetic, away.kinetic);
  EXPECT_LT(here.mirror, 1e-4);
  EXPECT_LT(away.mirror, 1e-4);
  EXPECT_NEAR(away.kinetic / here.kinetic, 1, 1e-3);
}
