// Colliders applied to grid velocities (Stomakhin et al. 2013 grid-based collisions): analytic
// half-spaces, solid boxes and spheres, static or moving with a constant velocity, and triangle
// meshes and .vdb level sets (static, translating or keyframed: rigid translation + rotation about
// a pivot; or per-frame deforming sequences) as a sparse lazily built ColliderField. Sticky, slip
// or separating boundaries with Coulomb friction. Pure functions of (x, t, v) once prepared.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <type_traits>
#include <vector>

#include "core/math/expression.hpp"
#include "core/math/types.hpp"

namespace amalgam {

namespace exec {
class Space;
}

// Trilinear value of the 8 corner samples c[a][b][d] (a along x) at fractions f, and its
// gradient (of the interpolant, per unit of index) if asked.
template <class T>
T trilinear(const T (&c)[2][2][2], const Vec3d& f, Vec3d* grad_index = nullptr) {
  auto lerp = [](const T& u, const T& v, double t) -> T { return u + (v - u) * t; };
  const T x00 = lerp(c[0][0][0], c[1][0][0], f[0]), x10 = lerp(c[0][1][0], c[1][1][0], f[0]);
  const T x01 = lerp(c[0][0][1], c[1][0][1], f[0]), x11 = lerp(c[0][1][1], c[1][1][1], f[0]);
  const T y0 = lerp(x00, x10, f[1]), y1 = lerp(x01, x11, f[1]);
  if constexpr (std::is_arithmetic_v<T>) {
    if (grad_index) {
      const double dx0 = lerp(lerp(c[1][0][0] - c[0][0][0], c[1][1][0] - c[0][1][0], f[1]),
                              lerp(c[1][0][1] - c[0][0][1], c[1][1][1] - c[0][1][1], f[1]), f[2]);
      *grad_index = Vec3d(dx0, lerp(x10 - x00, x11 - x01, f[2]), y1 - y0);
    }
  }
  return lerp(y0, y1, f[2]);
}

// An axis-aligned box [lo, hi].
struct Box3 {
  Vec3d lo, hi;
};

// A collider's shape as a field in its rest frame (core/geometry/level_set_collider.hpp): a mesh
// or a .vdb level set, static or a per-frame sequence interpolated in time. Sparse and built
// lazily: prepare() (serial, between kernels) makes it valid over boxes the material can reach;
// sample() is const and thread-safe (VDB trees read through per-call accessors), so kernels never
// mutate a tree. Every sample is a pure function of (point, time) whatever was built before, so
// runs are bitwise identical on every backend, thread count and after a checkpoint resume.
class ColliderField {
 public:
  virtual ~ColliderField() = default;
  // phi (negative inside) at rest-frame point p, time t; its gradient and the surface's own
  // velocity (a deforming sequence; zero for a rigid shape), both in the rest frame, if asked.
  virtual Real sample(const Vec3& p, Real t, Vec3* grad, Vec3* vel) const = 0;
  // Builds (or loads) the field over these rest-frame boxes for time t. Deterministic.
  virtual void prepare(const std::vector<Box3>& boxes, Real t, const exec::Space& space) = 0;
  virtual bool deforming() const { return false; }
  virtual std::size_t voxels() const = 0;  // voxels built / loaded now
  virtual std::size_t bytes() const = 0;   // memory of the trees now
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
  // Mesh / level set: its field (rest pose), pivot and keyframes (none: moves with `velocity`).
  std::shared_ptr<ColliderField> field;
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
  // Makes a field collider valid where points of these world boxes may query it at time t: the
  // boxes mapped to the rest frame by the pose at t (between kernels, serially).
  void prepare(const std::vector<Box3>& world, Real t, const exec::Space& space) {
    if (!field || t > until) return;
    Mat3 R;
    Vec3 T, v, w;
    pose(t, R, T, v, w);
    std::vector<Box3> rest;
    rest.reserve(world.size());
    const Mat3d Rt = R.transpose().cast<double>();
    const Vec3d shift = (pivot + T).cast<double>(), pv = pivot.cast<double>();
    for (const Box3& b : world) {  // the rest-frame box of the 8 corners
      Box3 r{Vec3d::Constant(1e300), Vec3d::Constant(-1e300)};
      for (int k = 0; k < 8; ++k) {
        const Vec3d c((k & 1) ? b.hi[0] : b.lo[0], (k & 2) ? b.hi[1] : b.lo[1],
                      (k & 4) ? b.hi[2] : b.lo[2]);
        const Vec3d q = Rt * (c - shift) + pv;
        r.lo = r.lo.cwiseMin(q), r.hi = r.hi.cwiseMax(q);
      }
      rest.push_back(r);
    }
    field->prepare(rest, t, space);
  }
  // Velocity of the collider's material point at x, time t.
  Vec3 velocity_at(const Vec3& x, Real t) const {
    if (drive) return drive->at(x.cast<double>(), double(t)).cast<Real>();
    if (shape != ColliderShape::Mesh) return velocity;
    Mat3 R;
    Vec3 T, v, w;
    pose(t, R, T, v, w);
    Vec3 rigid = v + w.cross(x - (pivot + T));
    if (field && field->deforming()) {  // the surface's own motion, turned into the world frame
      Vec3 vf;
      field->sample(R.transpose() * (x - pivot - T) + pivot, t, nullptr, &vf);
      rigid += R * vf;
    }
    return rigid;
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
        return field->sample(R.transpose() * (x - pivot - T) + pivot, t, nullptr, nullptr);
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
  // A number that phi(x, t), as computed above, is at least for every x in the box [lo, hi]
  // (rounding included: the exact bound less 8 float epsilons of the terms' magnitudes), so a
  // kernel skips the collider for a block of particles or nodes whose box bounds it above the
  // test's threshold, with the same bits as testing each. Analytic shapes; -infinity (no bound)
  // for meshes and level sets.
  double phi_at_least(const Vec3& lo, const Vec3& hi, Real t) const {
    if (t > until) return double(kReleased);
    if (shape == ColliderShape::Mesh) return -std::numeric_limits<double>::infinity();
    const Vec3 c = origin + t * velocity;  // (as phi computes it)
    const double eps = 8 * double(std::numeric_limits<Real>::epsilon());
    double scale = 0, sq = 0, worst = -std::numeric_limits<double>::infinity(), plane = 0;
    for (int a = 0; a < 3; ++a) {
      const double l = double(lo[a]) - double(c[a]), h = double(hi[a]) - double(c[a]);
      const double far = std::max(std::abs(double(lo[a])), std::abs(double(hi[a])));
      const double gap = l > 0 ? l : h < 0 ? -h : 0;  // distance from c to [lo, hi] on this axis
      switch (shape) {
        case ColliderShape::HalfSpace:  // the corner least along the normal
          plane += double(normal[a]) * (normal[a] >= 0 ? l : h);
          scale += (far + std::abs(double(c[a]))) * std::abs(double(normal[a]));
          break;
        case ColliderShape::Sphere:
          sq += gap * gap;
          scale += far + std::abs(double(c[a]));
          break;
        default:  // Box: phi >= max over axes of |x - c| - half_extent
          worst = std::max(worst, gap - double(half_extent[a]));
          scale += far + std::abs(double(c[a])) + std::abs(double(half_extent[a]));
          break;
      }
    }
    const double exact = shape == ColliderShape::HalfSpace ? plane
                         : shape == ColliderShape::Sphere  ? std::sqrt(sq) - double(radius)
                                                           : worst;
    if (shape == ColliderShape::Sphere) scale += std::abs(double(radius));
    return exact - eps * scale;
  }

  // Outward unit normal of the collider surface nearest to x.
  Vec3 outward_normal(const Vec3& x, Real t) const {
    const Vec3 c = origin + t * velocity;
    switch (shape) {
      case ColliderShape::Mesh: {
        Mat3 R;
        Vec3 T, v, w, g;
        pose(t, R, T, v, w);
        field->sample(R.transpose() * (x - pivot - T) + pivot, t, &g, nullptr);
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
