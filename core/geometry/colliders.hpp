// Colliders applied to grid velocities (Stomakhin et al. 2013 grid-based collisions): analytic
// half-spaces, solid boxes and spheres, static or moving with a constant velocity, and triangle
// meshes as a baked signed distance field, static, translating or keyframed (rigid translation +
// rotation about a pivot). Sticky, slip or separating boundaries with Coulomb friction. Pure
// functions of (x, t, v): a mesh's SDF is a dense array (built by io/ from an OpenVDB level
// set), so kernels never touch an OpenVDB tree.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <vector>

#include "core/math/expression.hpp"
#include "core/math/types.hpp"

namespace amalgam {

// Dense signed distance samples phi(origin + h (i, j, k)) of a mesh in its rest pose, i fastest;
// negative inside. Outside the sampled box phi is the distance to the box plus `outside`.
struct SdfGrid {
  Vec3d origin = Vec3d::Zero();
  double h = 1;
  int n[3] = {0, 0, 0};
  std::vector<float> phi;
  float outside = 1;

  float at(int i, int j, int k) const {
    return phi[(size_t(k) * size_t(n[1]) + size_t(j)) * size_t(n[0]) + size_t(i)];
  }
  // Trilinear phi and its gradient (of the interpolant) at rest-pose point p.
  Real sample(const Vec3& p, Vec3* grad) const {
    Vec3d g = (p.cast<double>() - origin) / h;
    const Vec3d clamped =
        g.cwiseMax(Vec3d::Zero()).cwiseMin(Vec3d(n[0] - 1.001, n[1] - 1.001, n[2] - 1.001));
    const double box = (g - clamped).norm() * h;
    const int i = int(clamped[0]), j = int(clamped[1]), k = int(clamped[2]);
    const double fx = clamped[0] - i, fy = clamped[1] - j, fz = clamped[2] - k;
    double c[2][2][2];
    for (int a = 0; a < 2; ++a)
      for (int b = 0; b < 2; ++b)
        for (int d = 0; d < 2; ++d) c[a][b][d] = at(i + a, j + b, k + d);
    auto lerp = [](double u, double v, double t) { return u + (v - u) * t; };
    const double x00 = lerp(c[0][0][0], c[1][0][0], fx), x10 = lerp(c[0][1][0], c[1][1][0], fx);
    const double x01 = lerp(c[0][0][1], c[1][0][1], fx), x11 = lerp(c[0][1][1], c[1][1][1], fx);
    const double y0 = lerp(x00, x10, fy), y1 = lerp(x01, x11, fy);
    if (grad) {
      const double dx0 = lerp(lerp(c[1][0][0] - c[0][0][0], c[1][1][0] - c[0][1][0], fy),
                              lerp(c[1][0][1] - c[0][0][1], c[1][1][1] - c[0][1][1], fy), fz);
      const double dy = lerp(x10 - x00, x11 - x01, fz);
      const double dz = y1 - y0;
      *grad = (Vec3d(dx0, dy, dz) / h).cast<Real>();
    }
    return Real(lerp(y0, y1, fz) + (box > 0 ? box + outside : 0.0));
  }
};

// Rigid pose at a time: x = R (x0 - pivot) + pivot + translation for rest-pose x0.
struct RigidKeyframe {
  Real time = 0;
  Vec3 translation = Vec3::Zero();
  Eigen::Quaternion<Real> rotation = Eigen::Quaternion<Real>::Identity();
};

enum class ColliderShape { HalfSpace, Box, Sphere, Mesh };
enum class BoundaryType { Sticky, Slip, Separate };

struct Collider {
  static constexpr Real kReleased = Real(1e30);  // phi of every point once the collider is released
  ColliderShape shape = ColliderShape::HalfSpace;
  BoundaryType boundary = BoundaryType::Separate;
  Real friction = 0;            // Coulomb coefficient mu
  Vec3 origin = Vec3::Zero();   // half-space: a point on the plane; box/sphere: centre (at t = 0)
  Vec3 normal = Vec3::UnitY();  // half-space: unit normal pointing into the free region
  Vec3 half_extent = Vec3::Ones();
  Real radius = 1;
  Vec3 velocity = Vec3::Zero();  // rigid translation velocity of the collider
  // Mesh: the baked SDF (rest pose), its pivot and keyframes (none: moves with `velocity`).
  std::shared_ptr<const SdfGrid> sdf;
  Vec3 pivot = Vec3::Zero();
  std::vector<RigidKeyframe> keys;
  // Mesh without keys: constant pose rate, R = rotation, T = translation + t velocity, spin omega
  // (what posed_at leaves, so kernels do not slerp per node).
  Mat3 rotation = Mat3::Identity();
  Vec3 translation = Vec3::Zero();
  Vec3 omega = Vec3::Zero();
  // The collider acts up to this time and not after it (a grip that lets go); infinity: always.
  Real until = std::numeric_limits<Real>::infinity();
  // A prescribed-velocity region (an MPM scene's `boundary_conditions`): a fixed sticky box whose
  // velocity at x, t is this field, so grid nodes (and particles) inside move with v(x, t).
  std::shared_ptr<const VectorField> drive;

  // Mesh pose at time t: rotation R, translation T and its rates (piecewise linear in T,
  // slerp in R between keyframes; constant before the first and after the last).
  void pose(Real t, Mat3& R, Vec3& T, Vec3& v, Vec3& omega) const {
    if (keys.empty()) {
      R = rotation;
      T = translation + t * velocity;
      v = velocity;
      omega = this->omega;
      return;
    }
    if (t <= keys.front().time || keys.size() == 1) {
      R = keys.front().rotation.toRotationMatrix();
      T = keys.front().translation;
      v.setZero(), omega.setZero();
      return;
    }
    if (t >= keys.back().time) {
      R = keys.back().rotation.toRotationMatrix();
      T = keys.back().translation;
      v.setZero(), omega.setZero();
      return;
    }
    size_t s = 1;
    while (keys[s].time < t) ++s;
    const RigidKeyframe &a = keys[s - 1], &b = keys[s];
    const Real span = b.time - a.time, u = (t - a.time) / span;
    R = a.rotation.slerp(u, b.rotation).toRotationMatrix();
    T = a.translation + u * (b.translation - a.translation);
    v = (b.translation - a.translation) / span;
    const Eigen::AngleAxis<Real> rel(b.rotation * a.rotation.conjugate());
    omega = rel.axis() * (rel.angle() / span);
  }
  // The same collider with its keyframed pose evaluated once at time t (keys dropped): what a
  // substep hands the kernels, so a node or particle test costs a transform, not a slerp.
  Collider posed_at(Real t) const {
    Collider c = *this;
    if (shape != ColliderShape::Mesh || keys.empty()) return c;
    Vec3 T;
    pose(t, c.rotation, T, c.velocity, c.omega);
    c.translation = T - t * c.velocity;
    c.keys.clear();
    return c;
  }
  // Velocity of the collider's material point at x, time t.
  Vec3 velocity_at(const Vec3& x, Real t) const {
    if (drive) return drive->at(x.cast<double>(), double(t)).cast<Real>();
    if (shape != ColliderShape::Mesh) return velocity;
    Mat3 R;
    Vec3 T, v, w;
    pose(t, R, T, v, w);
    return v + w.cross(x - (pivot + T));
  }

  // Signed distance to the collider surface (negative inside the solid) at time t.
  Real phi(const Vec3& x, Real t) const {
    if (t > until) return kReleased;  // released: every point is outside
    const Vec3 c = origin + t * velocity;
    switch (shape) {
      case ColliderShape::Mesh: {
        Mat3 R;
        Vec3 T, v, w;
        pose(t, R, T, v, w);
        return sdf->sample(R.transpose() * (x - pivot - T) + pivot, nullptr);
      }
      case ColliderShape::HalfSpace:
        return (x - c).dot(normal);
      case ColliderShape::Sphere:
        return (x - c).norm() - radius;
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
      case ColliderShape::Mesh: {
        Mat3 R;
        Vec3 T, v, w, g;
        pose(t, R, T, v, w);
        sdf->sample(R.transpose() * (x - pivot - T) + pivot, &g);
        const Vec3 n = R * g;
        return n.norm() > 0 ? Vec3(n.normalized()) : Vec3::UnitY();
      }
      case ColliderShape::HalfSpace:
        return normal;
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

  // Projects the velocity v of a point at x (time t) if it is inside the collider, or within
  // `tolerance` of its surface (grid nodes: node_tolerance).
  void project(const Vec3& x, Real t, Vec3& v, Real tolerance = 0) const {
    if (phi(x, t) > tolerance) return;
    const Vec3 vc = velocity_at(x, t);
    if (boundary == BoundaryType::Sticky) {
      v = vc;
      return;
    }
    const Vec3 n = outward_normal(x, t);
    Vec3 v_rel = v - vc;
    const Real vn = v_rel.dot(n);
    if (boundary == BoundaryType::Separate && vn >= 0) return;  // already separating
    Vec3 vt = v_rel - vn * n;
    const Real vt_norm = vt.norm();
    const Real vn_in = std::min(vn, Real(0));  // approaching part drives friction
    if (friction > 0 && vt_norm > 0) {
      const Real scale = std::max(Real(0), vt_norm + friction * vn_in) / vt_norm;
      vt *= scale;
    }
    v = vt + vc;
  }
};

// How far outside a collider a grid node still counts as touching it (phi <= tolerance). A node
// exactly on a collider's surface (a wall on a node plane, the usual way a scene is laid out) has
// phi = 0 in exact arithmetic, but the node position i dx and the wall's origin are each rounded,
// so phi comes out as a few ulps of either sign and the node would be in or out by accident: the
// wall held or the body fell a cell through it depending on the placement (issue 27). The
// tolerance is 1e-3 dx, plus 8 ulps of the node's coordinates where those are larger (far from
// the origin): every node within it is constrained, the same on every placement, and a node
// 1e-3 dx outside a wall moves its boundary by at most that (docs/validation.md).
inline Real node_tolerance(const Vec3& x, Real dx) {
  return Real(1e-3) * dx + 8 * std::numeric_limits<Real>::epsilon() * x.cwiseAbs().maxCoeff();
}

}  // namespace amalgam
