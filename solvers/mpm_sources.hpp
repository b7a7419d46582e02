// Particles entering and leaving an MPM run (issue 30): emitters and kill regions. MpmSolver::step
// calls them after the substep's transfers, at the substep's end time:
//   emit   every emitter adds the lattice points that entered its volume during the substep
//   kill   particles outside `kill.outside` or inside a kill volume are removed, the survivors
//          keep their order (a stable compaction of every attribute), ids unchanged
//
// Emission (documented in docs/scenes.md, "emitters"): an emitter is a source volume (box, sphere
// or closed mesh) that material flows through with the emitter's velocity v. Its particles come
// from a seeded, jittered lattice of spacing h = dx / cbrt(particles_per_cell) anchored at the
// emitter's box corner and moving with v from `start`: lattice point L is at
//   P_L(t) = lo + h (L + 1/2 + jitter_L) + v (t - start)
// (jitter_L hashed from (seed, L) as for objects, core/geometry/lattice.hpp). In the first substep
// that reaches `start` the points inside the volume are emitted (the source fills); afterwards a
// point is emitted in the substep (t0, t1] in which it enters the volume (inside at t1, outside
// at t0; times clamped to [start, end]). So the emitter holds particles at the object density
// 1/h^3 and emits density * A * |v| particles per second, A the volume's cross-section normal to
// v: N(t) = (V + A |v| (t - start)) / h^3 for a convex volume. Emission is a function of the
// substep's times only (no state but the next particle id), serial and in lattice order: the same
// on every backend and thread count, and a checkpoint resumes it bitwise.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/colliders.hpp"
#include "core/geometry/triangle_mesh.hpp"
#include "core/math/types.hpp"

namespace amalgam {

enum class EmitterShape { Box, Sphere, Mesh };

struct EmitterSpec {
  EmitterShape shape = EmitterShape::Box;
  Vec3 min = Vec3::Zero(), max = Vec3::Ones();  // bounding box (a box emitter's box)
  Vec3 center = Vec3::Zero();                   // sphere
  Real radius = 1;                              // sphere
  std::shared_ptr<const TriangleMesh> mesh;     // mesh: placed in the scene
  std::shared_ptr<const ColliderField> field;   // mesh: its level set over min..max (the factory)
  int material = 0;
  Vec3 velocity = Vec3::Zero();
  double start = 0, end = 0;  // s
  int particles_per_cell = 8;
  Real jitter = Real(0.5);
  std::uint64_t seed = 1;
  Real temperature = Real(293.15);
  std::string where;  // scene file and JSON path (/emitters/k), for errors

  double spacing(Real dx) const;  // h = dx / cbrt(particles_per_cell)
  bool inside(const Vec3d& p) const;
  // The largest number of particles it can emit over [start, end]: the lattice points that can
  // enter its bounding box (grown by one lattice spacing for the jitter) swept by v (end - start).
  double max_particles(Real dx) const;
  // Positions of the particles it emits in the substep (t0, t1] (appended to x).
  void emit(Real dx, double t0, double t1, std::vector<Vec3>& x) const;
};

// Kill regions (simulation.kill): particles outside the box [min, max] (when `outside`) or inside
// one of the volumes are removed.
struct KillSettings {
  bool outside = false;
  Vec3 min = Vec3::Zero(), max = Vec3::Zero();
  std::vector<Collider> volumes;  // static half-spaces, boxes and spheres (phi < 0: inside)
  bool enabled() const { return outside || !volumes.empty(); }
};

// Emitted and removed particle counts (the particle-id counter lives in MpmSolver).
struct SourceCounters {
  std::int64_t emitted = 0, killed = 0;
};

// Marks keep[p] = 0 for the particles of x[0 .. n) a kill region removes, 1 otherwise.
void mark_survivors(const exec::Space& space, const KillSettings& kill, const Vec3* x,
                    std::size_t n, std::uint8_t* keep);

}  // namespace amalgam
