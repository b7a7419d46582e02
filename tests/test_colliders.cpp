// Colliders: signed distances of each shape, and the velocity projection of each boundary type
// with Coulomb friction (Stomakhin et al. 2013).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <cstring>
#include <limits>
#include <random>
#include <utility>
#include <vector>

#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "core/geometry/colliders.hpp"
#include "core/exec/exec.hpp"
#include "kernels/mpm_transfers.hpp"
#include "kernels/particle_update.hpp"

using namespace amalgam;

namespace {
Collider floor_at(Real y, BoundaryType b, Real mu) {
  Collider c;
  c.shape = ColliderShape::HalfSpace;
  c.origin = Vec3(0, y, 0);
  c.normal = Vec3::UnitY();
  c.boundary = b;
  c.friction = mu;
  return c;
}
void expect_vec(const Vec3& a, const Vec3& b) {
  EXPECT_LT(double((a - b).norm()), 1e-5) << a.transpose() << " vs " << b.transpose();
}
}  // namespace

TEST(Colliders, SignedDistances) {
  Collider s;
  s.shape = ColliderShape::Sphere;
  s.origin = Vec3(1, 0, 0);
  s.radius = Real(0.5);
  EXPECT_NEAR(double(s.phi(Vec3(2, 0, 0), 0)), 0.5, 1e-6);
  EXPECT_NEAR(double(s.phi(Vec3(1, 0, 0), 0)), -0.5, 1e-6);
  s.velocity = Vec3(1, 0, 0);  // moving: centre at (3,0,0) when t = 2
  EXPECT_NEAR(double(s.phi(Vec3(3, 0, 0), 2)), -0.5, 1e-6);
  Collider b;
  b.shape = ColliderShape::Box;
  b.origin = Vec3::Zero();
  b.half_extent = Vec3(1, 2, 3);
  EXPECT_NEAR(double(b.phi(Vec3(2, 0, 0), 0)), 1.0, 1e-6);
  EXPECT_NEAR(double(b.phi(Vec3(2, 3, 0), 0)), std::sqrt(2.0), 1e-6);  // corner region
  EXPECT_NEAR(double(b.phi(Vec3(0, 0, 2.5), 0)), -0.5, 1e-6);          // inside: nearest face
  expect_vec(b.outward_normal(Vec3(0, 0, 2.5), 0), Vec3::UnitZ());
  expect_vec(b.outward_normal(Vec3(-3, 0, 0), 0), -Vec3::UnitX());
  const Collider h = floor_at(1, BoundaryType::Slip, 0);
  EXPECT_NEAR(double(h.phi(Vec3(5, 0.25, 7), 0)), -0.75, 1e-6);
}

// `until`: a released grip acts up to its release time and not after it.
TEST(Colliders, ReleasedAfterUntil) {
  Collider grip = floor_at(0, BoundaryType::Sticky, 0);
  grip.until = Real(0.5);
  const Vec3 inside(0, Real(-0.1), 0);
  EXPECT_LT(grip.phi(inside, Real(0.5)), 0);
  EXPECT_GT(grip.phi(inside, Real(0.5001)), Real(1e20));
  Vec3 v(1, -2, 3);
  grip.project(inside, Real(0.4), v);
  expect_vec(v, Vec3::Zero());
  v = Vec3(1, -2, 3);
  grip.project(inside, Real(0.6), v);
  expect_vec(v, Vec3(1, -2, 3));
}

TEST(Colliders, StickySlipSeparateAndFriction) {
  const Vec3 inside(0, Real(-0.1), 0), outside(0, Real(0.1), 0);
  // Sticky: takes the collider's velocity.
  Collider sticky = floor_at(0, BoundaryType::Sticky, 0);
  sticky.velocity = Vec3(0.5, 0, 0);
  Vec3 v(1, -2, 3);
  sticky.project(inside, 0, v);
  expect_vec(v, Vec3(0.5, 0, 0));
  // Outside a collider nothing changes.
  v = Vec3(1, -2, 3);
  sticky.project(outside, 0, v);
  expect_vec(v, Vec3(1, -2, 3));
  // Slip without friction: the normal part is removed, approaching or separating.
  const Collider slip = floor_at(0, BoundaryType::Slip, 0);
  v = Vec3(1, -2, 3);
  slip.project(inside, 0, v);
  expect_vec(v, Vec3(1, 0, 3));
  v = Vec3(1, 2, 3);
  slip.project(inside, 0, v);
  expect_vec(v, Vec3(1, 0, 3));
  // Separate: a separating velocity is kept.
  const Collider sep = floor_at(0, BoundaryType::Separate, 0);
  v = Vec3(1, 2, 3);
  sep.project(inside, 0, v);
  expect_vec(v, Vec3(1, 2, 3));
  // Coulomb friction: |v_t| shrinks by mu |v_n|, direction kept ...
  const Collider fric = floor_at(0, BoundaryType::Separate, Real(0.5));
  v = Vec3(3, -2, 4);  // |v_t| = 5, v_n = -2 -> |v_t| = 4
  fric.project(inside, 0, v);
  expect_vec(v, Vec3(Real(2.4), 0, Real(3.2)));
  // ... and static friction stops sliding entirely when mu |v_n| >= |v_t|.
  v = Vec3(0.5, -2, 0);
  fric.project(inside, 0, v);
  expect_vec(v, Vec3::Zero());
  // Moving collider: projection acts on the relative velocity.
  Collider lift = floor_at(0, BoundaryType::Separate, 0);
  lift.velocity = Vec3(0, 1, 0);
  v = Vec3(1, 0.5, 0);  // slower than the lifting floor: pushed up to its speed
  lift.project(inside + Vec3(0, 1, 0), 1, v);
  expect_vec(v, Vec3(1, 1, 0));
}

namespace {
// A closed cube mesh (12 outward triangles) of half size `a` centred at c, written as OBJ.
std::string write_cube(const std::string& name, const Vec3d& c, double a) {
  const std::string path = (std::filesystem::temp_directory_path() / name).string();
  std::ofstream f(path);
  for (int i = 0; i < 8; ++i)
    f << "v " << c[0] + ((i & 1) ? a : -a) << " " << c[1] + ((i & 2) ? a : -a) << " "
      << c[2] + ((i & 4) ? a : -a) << "\n";
  // faces (1-based), counter-clockwise seen from outside
  f << "f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n";
  return path;
}
double box_sdf(const Vec3d& x, const Vec3d& c, double a) {
  const Vec3d q = (x - c).cwiseAbs() - Vec3d::Constant(a);
  return q.cwiseMax(0.0).norm() + std::min(q.maxCoeff(), 0.0);
}
Scene mesh_collider_scene(const std::string& obj, const std::string& collider_extra) {
  return parse_scene(R"({"simulation": {"dx": 0.02, "frames": 1},
    "materials": {"a": {"density": 1000, "youngs_modulus": 2e4}},
    "objects": [{"shape": "box", "min": [0.4, 0.55, 0.4], "max": [0.6, 0.65, 0.6], "material": "a"}],
    "colliders": [{"type": "mesh", "file": ")" +
                         obj + R"(", "boundary": "slip")" + collider_extra + R"(}]})",
                     "inline.json");
}
}  // namespace

// The level set of a cube mesh matches the analytic box distance within one cell (trilinear
// interpolation of the exact field; edges and corners are where it is worst).
TEST(MeshCollider, BakedDistanceMatchesTheBox) {
  const std::string obj = write_cube("amalgam_cube.obj", Vec3d(0.5, 0.3, 0.5), 0.2);
  const Scene s = mesh_collider_scene(obj, "");
  ASSERT_EQ(s.colliders.size(), 1u);
  Collider c = build_colliders(s)[0];
  ASSERT_EQ(c.shape, ColliderShape::Mesh);
  c.prepare({Box3{Vec3d::Zero(), Vec3d::Ones()}}, 0, exec::Space());  // built where sampled
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(0.22, 0.78);
  double worst = 0;
  for (int t = 0; t < 2000; ++t) {
    const Vec3d x(u(rng), u(rng) - 0.2, u(rng));
    // exact within the band of 4 dx, clamped to +-4 dx beyond it (kLevelSetBand)
    const double band = 4 * 0.02;
    const double exact = std::clamp(box_sdf(x, Vec3d(0.5, 0.3, 0.5), 0.2), -band, band);
    worst = std::max(worst, std::abs(double(c.phi(x.cast<Real>(), 0)) - exact));
  }
  EXPECT_LT(worst, 0.02);
  // Normals point out of the faces.
  EXPECT_GT(c.outward_normal(Vec3(0.5, 0.51, 0.5), 0).dot(Vec3::UnitY()), Real(0.99));
  EXPECT_GT(c.outward_normal(Vec3(0.29, 0.3, 0.5), 0).dot(-Vec3::UnitX()), Real(0.99));
  std::remove(obj.c_str());
}

// Keyframes: translation is linear and rotation slerped between keys; the collider's point
// velocity is the segment's v + omega x r.
TEST(MeshCollider, KeyframedPoseAndVelocity) {
  const std::string obj = write_cube("amalgam_cube2.obj", Vec3d(0.5, 0.3, 0.5), 0.1);
  const Scene s =
      mesh_collider_scene(obj, R"(, "keyframes": [{"time": 0}, {"time": 1, "translate": [0.2, 0, 0],
                                              "rotate_degrees": [0, 90, 0]}])");
  Collider c = build_colliders(s)[0];
  c.prepare({Box3{Vec3d::Constant(-0.5), Vec3d::Constant(1.5)}}, 0, exec::Space());
  // At t = 1 the cube is at (0.7, 0.3, 0.5); at t = 0.5 at (0.6, 0.3, 0.5), turned 45 deg.
  // the centre, 0.1 deep, is beyond the level set's exact band of 4 dx: clamped to -0.08
  EXPECT_NEAR(double(c.phi(Vec3(0.7, 0.3, 0.5), 1)), -0.08, 0.01);
  EXPECT_NEAR(double(c.phi(Vec3(0.7, 0.45, 0.5), 1)), 0.05, 0.01);
  const double diag = 0.1 * std::sqrt(2.0);  // half diagonal of the turned square along x
  EXPECT_NEAR(double(c.phi(Vec3(Real(0.6 + diag + 0.03), 0.3, 0.5), 0.5)), 0.03 / 1.0, 0.012);
  const Vec3 v = c.velocity_at(Vec3(0.6, 0.3, 0.6), 0.5);   // 0.1 m from the pivot along z
  EXPECT_NEAR(double(v[0]), 0.2 + (M_PI / 2) * 0.1, 1e-4);  // v + omega x r: omega = pi/2 about y
  EXPECT_NEAR(double(v[2]), 0.0, 1e-4);
  // The pose evaluated once per substep (what the kernels get) agrees with the keyframes.
  const Collider posed = c.posed_at(Real(0.5));
  EXPECT_TRUE(posed.keys.empty());
  for (const Vec3& x : {Vec3(0.6, 0.3, 0.6), Vec3(0.72, 0.35, 0.45), Vec3(0.5, 0.2, 0.5)}) {
    EXPECT_NEAR(double(posed.phi(x, Real(0.5))), double(c.phi(x, Real(0.5))), 1e-5);
    EXPECT_NEAR(double((posed.velocity_at(x, Real(0.5)) - c.velocity_at(x, Real(0.5))).norm()), 0.0,
                1e-5);
  }
  // Before the first and after the last key the collider rests.
  EXPECT_NEAR(double(c.velocity_at(Vec3(0.7, 0.3, 0.5), 2).norm()), 0.0, 1e-9);
  std::remove(obj.c_str());
}

// An elastic block dropped on a mesh box lands on its top face and bounces there: during the whole
// run no particle goes more than a millimetre into the box or below its top face by more than
// a cell, and the block ends above the face.
TEST(MeshCollider, BlockLandsOnMeshBox) {
  const std::string obj = write_cube("amalgam_cube3.obj", Vec3d(0.5, 0.3, 0.5), 0.2);
  const Scene s = mesh_collider_scene(obj, "");
  MpmSolver solver = build_solver(s);
  const exec::Space space(exec::Backend::OpenMP, 2);
  Collider box = build_colliders(s)[0];
  box.prepare({Box3{Vec3d::Zero(), Vec3d::Ones()}}, 0, space);
  const auto& ps = solver.particles();
  double ymin_run = 1e9, centre = 0;
  int steps = 0;
  while (solver.time() < 0.6) {
    solver.step(space, solver.stable_dt(space));
    if (++steps % 10) continue;
    centre = 0;
    for (size_t p = 0; p < ps.size(); ++p) {
      const Vec3 x = ps.vec3(solver.attributes().x)[p];
      ymin_run = std::min(ymin_run, double(x[1]));
      centre += double(x[1]) / double(ps.size());
      ASSERT_GE(double(box.phi(x, Real(solver.time()))), -1e-3) << "particle inside the mesh";
    }
  }
  EXPECT_GT(ymin_run, 0.5 - 0.02);
  EXPECT_GT(centre, 0.5);
  EXPECT_LT(centre, 0.7);
  std::remove(obj.c_str());
}

// Collider::phi_at_least: below phi as computed at every point of the box (corners, faces,
// inside), rounding included, for every analytic shape, moving or not, near the origin and far
// from it; and above 0 for a box well clear of the collider (so kernels skip it there).
TEST(Colliders, PhiAtLeastBoundsEveryPointOfTheBox) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1, 1);
  int useful = 0, cases = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    const double at = (trial % 3 == 0) ? 0 : (trial % 3 == 1 ? 7 : 3000);  // where the box sits
    const double size = std::pow(10.0, 2 * u(rng) - 1);                    // 0.01 .. 10
    Vec3 lo, hi;
    for (int a = 0; a < 3; ++a) {
      lo[a] = Real(at + 2 * size * u(rng));
      hi[a] = lo[a] + Real(size * (1 + u(rng)) / 2);
    }
    Collider c;
    c.shape = trial % 4 == 0   ? ColliderShape::Sphere
              : trial % 4 == 1 ? ColliderShape::Box
                               : ColliderShape::HalfSpace;
    c.normal = Vec3(Real(u(rng)), Real(u(rng)), Real(u(rng))).normalized();
    if (trial % 5 == 0) c.normal = Vec3::UnitY();
    c.radius = Real(size * (1 + u(rng)));
    c.half_extent = Vec3(Real(size), Real(size / 2), Real(size * 2));
    c.velocity = trial % 2 ? Vec3(Real(u(rng)), Real(u(rng)), Real(u(rng))) : Vec3::Zero();
    const Real t = Real(0.5 + 0.5 * u(rng));
    // The collider's surface through a corner of the box (phi = 0 there up to rounding), or near
    // it, or well away from it.
    const Vec3 corner((trial & 1) ? lo[0] : hi[0], (trial & 2) ? lo[1] : hi[1],
                      (trial & 4) ? lo[2] : hi[2]);
    const double shift = (trial / 8) % 3 == 0 ? 0 : (trial / 8) % 3 == 1 ? 1e-6 : 5 * size;
    c.origin = corner - t * c.velocity - Real(shift) * c.normal;
    if (c.shape == ColliderShape::Sphere) c.origin -= c.radius * c.normal;
    if (c.shape == ColliderShape::Box) c.origin -= c.half_extent.cwiseProduct(c.normal);
    const double bound = c.phi_at_least(lo, hi, t);
    ++cases;
    if (bound > 0) ++useful;
    for (int k = 0; k < 64; ++k) {
      Vec3 x;
      for (int a = 0; a < 3; ++a)
        x[a] = k < 8    ? ((k >> a & 1) ? hi[a] : lo[a])  // the corners
               : k < 16 ? (a == k % 3 ? lo[a] : Real(lo[a] + (hi[a] - lo[a]) * (0.5 + u(rng) / 2)))
                        : Real(lo[a] + (hi[a] - lo[a]) * (0.5 + u(rng) / 2));
      for (int a = 0; a < 3; ++a) x[a] = std::min(std::max(x[a], lo[a]), hi[a]);
      ASSERT_GE(double(c.phi(x, t)), bound) << "trial " << trial << " point " << k;
    }
  }
  EXPECT_GT(useful, cases / 4) << "the bound should clear boxes well away from the collider";
  Collider mesh;
  mesh.shape = ColliderShape::Mesh;
  EXPECT_EQ(mesh.phi_at_least(Vec3::Zero(), Vec3::Ones(), 0),
            -std::numeric_limits<double>::infinity());
  Collider gone = floor_at(10, BoundaryType::Slip, 0);  // the box is below it, but it let go
  gone.until = 1;
  EXPECT_GT(gone.phi_at_least(Vec3::Zero(), Vec3::Ones(), 2), 0);
  EXPECT_LT(gone.phi_at_least(Vec3::Zero(), Vec3::Ones(), 0.5), 0);
}

// collide_range (a chunk's box skips the colliders it lies clear of) gives the bits of
// collide_particle particle by particle: particles straddling walls, a sphere, a box and a moving
// plane, the compensated low parts, chunks in and out of reach, one NaN position.
TEST(Colliders, RangeWithSkippedCollidersIsBitwiseEachParticle) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<Real> u(0, 1);
  const std::size_t n = 3000;
  std::vector<Vec3> x(n), v(n), xlo(n), x2, v2, xlo2;
  for (std::size_t i = 0; i < n; ++i) {  // sorted along x (as bins are): most chunks far away
    const Real s = Real(i) / Real(n);
    x[i] = Vec3(Real(-0.1) + Real(1.2) * s, Real(-0.05) + Real(0.3) * u(rng), u(rng));
    v[i] = Vec3(u(rng) - Real(0.5), u(rng) - Real(0.5), u(rng) - Real(0.5));
    xlo[i] = Vec3::Constant(Real(1e-9) * u(rng));
  }
  x[1234][1] = std::numeric_limits<Real>::quiet_NaN();
  std::vector<Collider> cols;
  cols.push_back(floor_at(Real(0.05), BoundaryType::Separate, Real(0.4)));
  Collider wall = floor_at(0, BoundaryType::Slip, 0);
  wall.normal = Vec3::UnitX();
  cols.push_back(wall);
  wall.origin = Vec3(1, 0, 0), wall.normal = -Vec3::UnitX(), wall.velocity = Vec3(-1, 0, 0);
  cols.push_back(wall);
  Collider ball;
  ball.shape = ColliderShape::Sphere, ball.origin = Vec3(Real(0.5), 0, Real(0.5));
  ball.radius = Real(0.1), ball.boundary = BoundaryType::Sticky;
  cols.push_back(ball);
  Collider box;
  box.shape = ColliderShape::Box, box.origin = Vec3(Real(0.8), Real(0.1), Real(0.2));
  box.half_extent = Vec3(Real(0.05), Real(0.05), Real(0.1));
  cols.push_back(box);
  x2 = x, v2 = v, xlo2 = xlo;
  const Real time = Real(0.02);
  MpmParticleView a{x.data(), v.data(), nullptr, nullptr, nullptr, nullptr, n};
  a.x_lo = xlo.data();
  MpmParticleView b{x2.data(), v2.data(), nullptr, nullptr, nullptr, nullptr, n};
  b.x_lo = xlo2.data();
  isa_baseline::collide_range(a, cols.data(), int(cols.size()), 0, exec::Index(n), time);
  for (std::size_t i = 0; i < n; ++i)
    isa_baseline::collide_particle(b, cols.data(), int(cols.size()), exec::Index(i), time);
  for (std::size_t i = 0; i < n; ++i) {
    ASSERT_EQ(std::memcmp(&x[i], &x2[i], sizeof(Vec3)), 0) << i;
    ASSERT_EQ(std::memcmp(&v[i], &v2[i], sizeof(Vec3)), 0) << i;
    ASSERT_EQ(std::memcmp(&xlo[i], &xlo2[i], sizeof(Vec3)), 0) << i;
  }
  EXPECT_GE(std::count_if(v.begin(), v.end(), [](const Vec3& w) { return w.isZero(); }), 1)
      << "the sticky ball held some particles";
}

// More colliders than the grid update's 64-bit mask of those near a leaf: the 65th (the floor)
// still holds the block, with the same bits whichever of the others lie clear of every leaf (64
// far walls first, then the floor; against the floor alone plus the 64 far walls after it).
TEST(Colliders, MoreThanSixtyFourCollidersAllAct) {
  auto scene = [](bool floor_first) {
    std::string walls;
    for (int k = 0; k < 64; ++k)
      walls += R"({"type": "half_space", "point": [0, )" + std::to_string(-1 - k) +
               R"(, 0], "normal": [0, 1, 0]},)";
    const std::string floor =
        R"({"type": "half_space", "point": [0, 0.1, 0], "normal": [0, 1, 0], "friction": 0.5},)";
    std::string all = floor_first ? floor + walls : walls + floor;
    all.pop_back();
    return parse_scene(R"({"simulation": {"dx": 0.05, "frames": 1, "max_dt": 2e-3},
      "materials": {"j": {"model": "fixed_corotated", "density": 1000, "youngs_modulus": 1e4,
                          "poisson_ratio": 0.3}},
      "objects": [{"shape": "box", "min": [0.3, 0.15, 0.3], "max": [0.6, 0.45, 0.6],
                   "material": "j", "velocity": [0, -2, 0]}],
      "colliders": [)" + all +
                           "]}",
                       "inline.json");
  };
  const exec::Space space;
  MpmSolver last = build_solver(scene(false)), first = build_solver(scene(true));
  for (int i = 0; i < 150; ++i) {
    last.step(space, Real(2e-3));
    first.step(space, Real(2e-3));
  }
  const auto& pa = std::as_const(last).particles();
  const auto& pb = std::as_const(first).particles();
  const Vec3* xa = pa.vec3(last.attributes().x);
  const Vec3* xb = pb.vec3(first.attributes().x);
  double ymin = 1e9;
  for (std::size_t p = 0; p < pa.size(); ++p) {
    ymin = std::min(ymin, double(xa[p][1]));
    ASSERT_EQ(std::memcmp(&xa[p], &xb[p], sizeof(Vec3)), 0) << p;
  }
  EXPECT_GT(ymin, 0.1 - 0.05) << "the 65th collider, the floor, held the block";
}
