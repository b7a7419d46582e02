// Contact between objects that keep their own configuration maps (A-ULMPM Secs. 5.1, 5.5, 7.1).
//
// In A-ULMPM every object lives on its own reference nodes (object k's lane of the reference
// grid), so two objects never share a node and would pass through each other. The paper
// "projects q_i^{n+1} for all objects to the global grid and processes grid-based collisions"
// (Sec. 5.5, eq. 27). These kernels do that:
//   1. collect   every reference node with mass becomes a contact point at its current
//                position q_i^{n+1} = q_i^n + dt v_i (eq. 27), with m_i, v_i and its object k;
//   2. scatter   the points onto a global grid with quadratic B-spline weights w (PIC):
//                M_I = sum w m, P_I = sum w m v, and two colour lanes K_I = sum w m k,
//                S_I = sum w m k^2;
//   3. gather    at each point of object k: the centre-of-mass velocity V = sum w P / sum w M,
//                c = sum w (K - k M) = sum over the other objects j of w m_j (k_j - k) and
//                D = sum w (S - 2 k K + k^2 M) = sum w m_j (k_j - k)^2, so that f = c^2 / (D M)
//                is the others' share of the mass at q_i (exact with one other object near, a
//                lower bound with several), and the direction towards the others
//                n = sgn(c) grad c / |grad c|; where f >= shared_fraction,
//                  stick     v_i <- V                       (single-grid MPM's no-slip coupling)
//                  separate  if (v_i - V).n > 0 (approaching): remove the normal part of v_i - V
//                            and shrink its tangential part by mu times the normal part removed
//                            (Bardenhagen et al. 2000's multi-velocity contact, Coulomb friction);
//                            separating nodes keep their velocity.
// Every point is its own reference node, so the gather writes the reference grid without races;
// the scatter is colour-partitioned like P2G: the result is deterministic on every backend.
#pragma once

#include <cstdint>

#include "core/exec/exec.hpp"
#include "core/math/types.hpp"
#include "kernels/mpm_transfers.hpp"

namespace amalgam {

enum class ObjectContactMode { None, Stick, Separate };
const char* object_contact_mode_name(ObjectContactMode m);

struct ObjectContactParams {
  ObjectContactMode mode = ObjectContactMode::Stick;
  Real friction = 0;  // Coulomb coefficient (separate only)
  Real dx = Real(0.01);
  Real dt = Real(1e-4);
  // A reference node is in contact where the other objects' share of the global mass at q_i
  // reaches this (measured on two cubes: docs/aulmpm.md).
  Real shared_fraction = Real(0.2);
};

// Contact points (SoA, one per reference node with mass).
struct ContactPointView {
  Vec3* x;               // q_i^{n+1}
  Vec3* v;               // v_i
  Real* m;               // m_i
  std::int32_t* object;  // k
  std::int32_t* leaf;    // reference leaf of the node (-1: another rank's, distributed)
  std::int32_t* offset;  // offset of the node in its leaf
  std::size_t n;
};

// Bounding boxes of the objects' contact points (q^{n+1} of their reference nodes with mass).
struct ContactBoxes {
  static constexpr int kMax = 32;
  int n = 0;
  Vec3 lo[kMax], hi[kMax];
  // Whether x (a point of object k) lies in the box of another object grown by `margin`.
  bool near_other(const Vec3& x, int k, Real margin) const {
    for (int j = 0; j < n; ++j)
      if (j != k && (x.array() >= lo[j].array() - margin).all() &&
          (x.array() <= hi[j].array() + margin).all())
        return true;
    return false;
  }
};
// Per-object boxes of the points. `q` = (m, m q^n) of the reference nodes, leaf_object[leaf] =
// the object owning a reference leaf (ref.active_leaves lists the leaves to visit).
ContactBoxes contact_boxes(const exec::Space& space, const MpmGridView& ref, const Real* q,
                           const std::int32_t* leaf_object, int objects, Real dt);
// Broad phase and collection. Only points within `margin` of another object's box can matter:
// a corrected point has the others' mass within 3 dx (two quadratic stencils) and its
// centre-of-mass velocity comes from points within 3 dx of it, so margin = 6 dx leaves the
// result bit for bit unchanged while objects that are apart cost two passes over their nodes.
// Pass 1: per active reference leaf li, the number of such points; pass 2 writes them at start[li].
void contact_count_points(const exec::Space& space, const MpmGridView& ref, const Real* q,
                          const std::int32_t* leaf_object, const ContactBoxes& boxes, Real margin,
                          Real dt, std::uint32_t* count);
void contact_collect_points(const exec::Space& space, const MpmGridView& ref, const Real* q,
                            const std::int32_t* leaf_object, const ContactBoxes& boxes, Real margin,
                            Real dt, const std::uint32_t* start, const ContactPointView& out);
// Scatter of the binned points (bins/colours of `global`) into global.a = (M, P) and
// global.b = (K, S, 0, 0).
void contact_scatter(const exec::Space& space, const ContactPointView& pts,
                     const MpmGridView& global, const ObjectContactParams& prm);
// Gather and velocity correction written back into ref.a (and ref.b's v_new - v_old for
// PIC/FLIP when ref.b is set). Returns the number of reference nodes whose velocity changed.
// Points with leaf < 0 (other ranks' nodes in a distributed run) are scattered, not corrected.
std::size_t contact_gather(const exec::Space& space, const ContactPointView& pts,
                           const MpmGridView& global, const MpmGridView& ref,
                           const ObjectContactParams& prm);

}  // namespace amalgam
