// The per-particle part of MPM's CFL condition and stability guard (MpmSolver::stable_dt): the
// largest particle speed, the largest wave speed that depends on the plastic state, and the first
// particle (smallest index) with a non-finite v or F or a speed above max_speed. Either a pass of
// its own (stable_dt) or folded into the last particle pass of a substep (G2P, G2P2G, the
// material update: MpmStepParams::check), which already holds v and F: the same values, since
// maxima and the smallest index do not depend on the order the particles are visited in.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "core/materials/material.hpp"
#include "core/math/left_cauchy_green.hpp"
#include "core/math/types.hpp"

namespace amalgam {

struct StabilityCheck {
  Real max_speed = 0;
  Real max_wave = 0;      // largest particle wave speed when it depends on the plastic state
  std::int64_t bad = -1;  // smallest index of a particle with a non-finite v or F, or runaway
  int what = 0;           // 1 velocity, 2 deformation gradient, 3 runaway speed
};

// What check_particle needs besides the particle: the guard's speed limit, and (wave) the
// materials whose wave speed scales with the plastic scalar (null: no material hardens).
struct StabilityLimits {
  Real max_speed = Real(1e4);
  const MaterialParams* materials = nullptr;
  const std::int32_t* material = nullptr;  // per particle (with materials)
  const Real* plastic = nullptr;           // per particle (with materials)
};

// The particle's deformation: F, or J alone (MpmParticleView::J), checked the same way.
inline bool all_finite(const Mat3& F) {
  return F.allFinite();
}
inline bool all_finite(Real J) {
  return std::isfinite(J);
}
inline Real entry_sum(const Mat3& F) {
  return F.sum();
}
inline Real entry_sum(Real J) {
  return J;
}
// b - I (MpmParticleView::b) likewise.
inline bool all_finite(const SymDev& d) {
  bool ok = true;
  for (Real e : d.e) ok &= std::isfinite(e);
  return ok;
}
inline Real entry_sum(const SymDev& d) {
  return ((d.e[0] + d.e[1]) + (d.e[2] + d.e[3])) + (d.e[4] + d.e[5]);
}

template <class D>  // Mat3, SymDev or Real
inline void check_particle(StabilityCheck& acc, std::int64_t i, const Vec3& v, const D& F,
                           const StabilityLimits& lim) {
  const Real s = v.norm();
  int what = 0;
  if (!std::isfinite(s))
    what = 1;
  else if (!all_finite(F))
    what = 2;
  else if (s > lim.max_speed)
    what = 3;
  if (what && (acc.bad < 0 || i < acc.bad)) {
    acc.bad = i;
    acc.what = what;
  }
  if (s > acc.max_speed) acc.max_speed = s;
  if (lim.plastic) {
    const MaterialParams& m = lim.materials[lim.material[i]];
    acc.max_wave = std::max(acc.max_wave, m.wave_speed() * m.wave_speed_factor(lim.plastic[i]));
  }
}

// check_particle for particles [i0, i1) in order, with a fast path for the common particle (finite,
// well below max_speed): its squared speed only, the largest square root taken once at the end.
// The same result: IEEE sqrt is correctly rounded and monotonic, so the square root of the largest
// |v|^2 is the largest |v| (v.norm() is sqrt(v.squaredNorm())), and a particle whose |v|^2 or F
// is not finite, or whose |v|^2 exceeds a quarter of max_speed^2, takes check_particle itself.
template <class Index, class D>  // D: Mat3, SymDev (b - I) or Real (J)
inline void check_range(StabilityCheck& acc, Index i0, Index i1, const Vec3* v, const D* F,
                        const StabilityLimits& lim) {
  const Real slow = Real(0.25) * lim.max_speed * lim.max_speed;
  Real most = 0;  // largest |v|^2 of the fast path
  for (Index i = i0; i < i1; ++i) {
    const Real s2 = v[i].squaredNorm();
    if (!std::isfinite(s2 + entry_sum(F[i])) || !(s2 <= slow)) {
      check_particle(acc, std::int64_t(i), v[i], F[i], lim);
      continue;
    }
    most = s2 > most ? s2 : most;
  }
  acc.max_speed = std::max(acc.max_speed, std::sqrt(most));
  if (lim.plastic)
    for (Index i = i0; i < i1; ++i) {
      const MaterialParams& m = lim.materials[lim.material[i]];
      acc.max_wave = std::max(acc.max_wave, m.wave_speed() * m.wave_speed_factor(lim.plastic[i]));
    }
}

// Two partial checks in one: the same result in any order and grouping.
inline StabilityCheck merge_checks(StabilityCheck a, const StabilityCheck& b) {
  if (b.bad >= 0 && (a.bad < 0 || b.bad < a.bad)) {
    a.bad = b.bad;
    a.what = b.what;
  }
  a.max_speed = std::max(a.max_speed, b.max_speed);
  a.max_wave = std::max(a.max_wave, b.max_wave);
  return a;
}

}  // namespace amalgam
