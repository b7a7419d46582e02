// A half-space collider for the tests' scenes.
#pragma once

#include "core/geometry/colliders.hpp"

namespace amalgam::test {

// A half-space collider through `point`, `normal` pointing out of the solid.
inline Collider half_space(const Vec3& point, const Vec3& normal, BoundaryType b,
                           Real friction = 0) {
  Collider c;
  c.shape = ColliderShape::HalfSpace;
  c.origin = point;
  c.normal = normal;
  c.boundary = b;
  c.friction = friction;
  return c;
}

}  // namespace amalgam::test
