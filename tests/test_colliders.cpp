// Colliders: signed distances of each shape, and the velocity projection of each boundary type
// with Coulomb friction (Stomakhin et al. 2013).
#include <gtest/gtest.h>

#include "kernels/colliders.hpp"

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
void expect_vec(const Vec3& a, const Vec3& b) { EXPECT_LT(double((a - b).norm()), 1e-5) << a.transpose() << " vs " << b.transpose(); }
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
