#include "solvers/scene_spec.hpp"

#include <algorithm>
#include <cmath>

#include "core/errors.hpp"
#include "core/geometry/lattice.hpp"

namespace amalgam {

std::vector<Vec3> sample_object(const ObjectSpec& obj, Real dx, Real& volume_per_particle,
                                const exec::Space& space, const LatticeSlice& slice) {
  const double h = double(dx) / std::cbrt(double(obj.particles_per_cell));
  volume_per_particle = Real(h * h * h);
  const Vec3 lo = obj.min, hi = obj.max;  // every shape's bounding box
  long long n[3];
  // A box is filled exactly by whole lattice cells (round); curved shapes need the whole bounding
  // box covered (ceil) and are cut by their inside test.
  for (int a = 0; a < 3; ++a) {
    const double cells = (double(hi[a]) - double(lo[a])) / h;
    n[a] = std::max(
        1LL, (long long)(obj.shape == ObjectShape::Box ? std::llround(cells) : std::ceil(cells)));
  }
  if (double(n[0]) * double(n[1]) * double(n[2]) > 2e9)
    throw InputError(
        "object would be sampled with more than 2e9 particles; increase dx or lower particles_per_cell");
  if (obj.shape == ObjectShape::Mesh)
    return sample_mesh(*obj.mesh, h, double(obj.jitter), obj.seed, space, slice);
  if (obj.shape == ObjectShape::TetMesh) {  // barycentres; their volumes differ: the mean here
    std::vector<Vec3> x;
    std::vector<Real> vol;
    tet_barycentres(*obj.tets, x, vol);
    double sum = 0;
    for (Real v : vol) sum += double(v);
    volume_per_particle = Real(sum / double(std::max<std::size_t>(1, vol.size())));
    if (slice.whole()) return x;
    const long long t = (long long)x.size();
    return std::vector<Vec3>(x.begin() + slice.begin(t), x.begin() + slice.end(t));
  }
  const Vec3d c = obj.center.cast<double>();
  const double r2 = double(obj.radius) * double(obj.radius);
  const int ax = obj.axis;
  const double half_h = 0.5 * double(obj.height), R = double(obj.radius),
               r = double(obj.minor_radius);
  return sample_lattice(
      lo.cast<double>(), n, h, double(obj.jitter), obj.seed,
      [&](const Vec3d& p) {
        const Vec3d d = p - c;
        const double along = d[ax], across2 = d.squaredNorm() - along * along;
        switch (obj.shape) {
          case ObjectShape::Box:
            return true;
          case ObjectShape::Sphere:
            return d.squaredNorm() <= r2;
          case ObjectShape::Cylinder:
            return std::abs(along) <= half_h && across2 <= r2;
          case ObjectShape::Torus: {
            const double ring = std::sqrt(across2) - R;
            return ring * ring + along * along <= r * r;
          }
          case ObjectShape::Mesh:
          case ObjectShape::TetMesh:
            break;
        }
        return false;
      },
      slice);
}

}  // namespace amalgam
