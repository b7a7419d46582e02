#include "solvers/mpm_sources.hpp"

#include <algorithm>
#include <cmath>

#include "core/geometry/lattice.hpp"

namespace amalgam {

double EmitterSpec::spacing(Real dx) const {
  return double(dx) / std::cbrt(double(particles_per_cell));
}

bool EmitterSpec::inside(const Vec3d& p) const {
  switch (shape) {
    case EmitterShape::Box:
      for (int a = 0; a < 3; ++a)
        if (!(p[a] >= double(min[a]) && p[a] < double(max[a]))) return false;
      return true;
    case EmitterShape::Sphere:
      return (p - center.cast<double>()).squaredNorm() <= double(radius) * double(radius);
    case EmitterShape::Mesh:
      for (int a = 0; a < 3; ++a)
        if (!(p[a] >= double(min[a]) && p[a] <= double(max[a]))) return false;
      return field->sample(p.cast<Real>(), 0, nullptr, nullptr) < 0;
  }
  return false;
}

double EmitterSpec::max_particles(Real dx) const {
  const double h = spacing(dx);
  const Vec3d size = (max - min).cast<double>() + Vec3d::Constant(2 * h);
  const Vec3d d = velocity.cast<double>() * (end - start);
  // Minkowski sum of the grown box and the segment d: its volume plus |d_a| times each face.
  double vol = size[0] * size[1] * size[2];
  for (int a = 0; a < 3; ++a) vol += std::abs(d[a]) * size[(a + 1) % 3] * size[(a + 2) % 3];
  return std::ceil(vol / (h * h * h));
}

void EmitterSpec::emit(Real dx, double t0, double t1, std::vector<Vec3>& x) const {
  if (!(t1 > start) || !(t0 < end)) return;
  using detail::centred_unit;
  using detail::splitmix64;
  const double h = spacing(dx);
  const double tau0 = std::max(t0, start), tau1 = std::min(t1, end);
  const bool fill = t0 <= start;  // the first substep reaching `start` fills the volume
  const Vec3d lo = min.cast<double>(), v = velocity.cast<double>();
  const Vec3d shift1 = v * (tau1 - start), shift0 = v * (tau0 - start), at_t1 = v * (t1 - start);
  // Lattice indices whose point can lie in the box at tau1 (one more each side for the jitter).
  long long first[3], last[3];
  for (int a = 0; a < 3; ++a) {
    first[a] = (long long)std::floor((double(min[a]) - lo[a] - shift1[a]) / h) - 1;
    last[a] = (long long)std::ceil((double(max[a]) - lo[a] - shift1[a]) / h) + 1;
  }
  for (long long i = first[0]; i <= last[0]; ++i)
    for (long long j = first[1]; j <= last[1]; ++j)
      for (long long k = first[2]; k <= last[2]; ++k) {
        // The lattice hash of core/geometry/lattice.hpp, so a still emitter fills its volume
        // exactly as an object of the same shape and seed is sampled.
        const std::uint64_t id =
            splitmix64(seed ^ splitmix64(std::uint64_t(i) * 0x1000003ULL ^
                                         std::uint64_t(j) * 0x10007ULL ^ std::uint64_t(k)));
        const double jit = double(jitter) * h;
        const Vec3d base =
            lo + h * Vec3d(double(i) + 0.5, double(j) + 0.5, double(k) + 0.5) +
            jit * Vec3d(centred_unit(splitmix64(id + 1)), centred_unit(splitmix64(id + 2)),
                        centred_unit(splitmix64(id + 3)));
        if (!inside(base + shift1)) continue;
        if (!fill && inside(base + shift0)) continue;  // entered before t0: emitted already
        x.push_back((base + at_t1).cast<Real>());
      }
}

void mark_survivors(const exec::Space& space, const KillSettings& kill, const Vec3* x,
                    std::size_t n, std::uint8_t* keep) {
  const Collider* vol = kill.volumes.data();
  const int nvol = int(kill.volumes.size());
  const bool outside = kill.outside;
  const Vec3 lo = kill.min, hi = kill.max;
  exec::parallel_for(space, "mpm.kill", exec::Index(n), [=](exec::Index p) {
    const Vec3& y = x[p];
    bool k = true;
    if (outside)
      for (int a = 0; a < 3; ++a) k = k && y[a] >= lo[a] && y[a] <= hi[a];
    for (int c = 0; c < nvol && k; ++c) k = !(vol[c].phi(y, Real(0)) < 0);
    keep[p] = k ? 1 : 0;
  });
}

}  // namespace amalgam
