// Analytic colliders applied to grid velocities (Stomakhin et al. 2013 grid-based collisions):
// half-spaces, solid boxes and spheres, static or moving with a constant velocity, with sticky,
// slip or separating boundaries and Coulomb friction. Pure functions of (x, t, v).
#pragma once

#include <algorithm>
#include <cmath>

#include "core/math/types.hpp"

namespace amalgam {

enum class ColliderShape { HalfSpace, Box, Sphere };
enum class BoundaryType { Sticky, Slip, Separate };

struct Collider {
  ColliderShape shape = ColliderShape::HalfSpace;
  BoundaryType boundary = BoundaryType::Separate;
  Real friction = 0;           // Coulomb coefficient mu
  Vec3 origin = Vec3::Zero();  // half-space: a point on the plane; box/sphere: centre (at t = 0)
  Vec3 normal = Vec3::UnitY(); // half-space: unit normal pointing into the free region
  Vec3 half_extent = Vec3::Ones();
  Real radius = 1;
  Vec3 velocity = Vec3::Zero();  // rigid translation velocity of the collider

  // Signed distance to the collider surface (negative inside the solid) at time t.
  Real phi(const Vec3& x, Real t) const {
    const Vec3 c = origin + t * velocity;
    switch (shape) {
      case ColliderShape::HalfSpace: return (x - c).dot(normal);
      case ColliderShape::Sphere: return (x - c).norm() - radius;
      case ColliderShape::Box: {
        const Vec3 q = (x - c).cwiseAbs() - half_extent;
        return q.cwiseMax(Real(0)).norm() + std::min(q.maxCoeff(), Real(0));
      }
    }
    return 1;
  }
  // Outward unit normal of the collider surface nearest to x.
  Vec3 outward_normal(const Vec3& x, Real t) const {
    const Vec3 c = origin + t * velocity;
    switch (shape) {
      case ColliderShape::HalfSpace: return normal;
      case ColliderShape::Sphere: {
        const Vec3 d = x - c;
        const Real n = d.norm();
        return n > 0 ? Vec3(d / n) : Vec3::UnitY();
      }
      case ColliderShape::Box: {
        const Vec3 d = x - c;
        const Vec3 q = d.cwiseAbs() - half_extent;
        if (q.maxCoeff() > 0) {  // outside: gradient of the distance to the box
          Vec3 g = q.cwiseMax(Real(0));
          for (int a = 0; a < 3; ++a) g[a] = d[a] < 0 ? -g[a] : g[a];
          return g.normalized();
        }
        int a = 0;  // inside: the face of least penetration
        q.maxCoeff(&a);
        Vec3 g = Vec3::Zero();
        g[a] = d[a] < 0 ? Real(-1) : Real(1);
        return g;
      }
    }
    return Vec3::UnitY();
  }

  // Projects the velocity v of a point at x (time t) if it is inside the collider.
  void project(const Vec3& x, Real t, Vec3& v) const {
    if (phi(x, t) > 0) return;
    if (boundary == BoundaryType::Sticky) {
      v = velocity;
      return;
    }
    const Vec3 n = outward_normal(x, t);
    Vec3 v_rel = v - velocity;
    const Real vn = v_rel.dot(n);
    if (boundary == BoundaryType::Separate && vn >= 0) return;  // already separating
    Vec3 vt = v_rel - vn * n;
    const Real vt_norm = vt.norm();
    const Real vn_in = std::min(vn, Real(0));  // approaching part drives friction
    if (friction > 0 && vt_norm > 0) {
      const Real scale = std::max(Real(0), vt_norm + friction * vn_in) / vt_norm;
      vt *= scale;
    }
    v = vt + velocity;
  }
};

}  // namespace amalgam
