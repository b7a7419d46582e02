// Deforming-collider cost per substep (issue 30): a sphere mesh sequence (an octahedron subdivided
// --levels times, radius 0.3 m growing 0.01 m per frame, 24 frames/s) as a collider field with
// voxel dx = 0.01, and N particles in a shell about its surface (the region a substep prepares).
// Prints, at 1 and 2 threads (median of --reps):
//  - lookups: one Collider::project per particle (interpolation of two frames, phi, gradient and
//    velocity), ns per particle;
//  - prepare of a substep that builds nothing (every block already built), ns per particle;
//  - building a new frame where the particles are (a frame crossing), ns per collider voxel.
// Usage: amalgam_collider_bench [--particles 200000] [--levels 4] [--reps 5]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <vector>

#include "core/exec/exec.hpp"
#include "core/geometry/level_set_collider.hpp"

using namespace amalgam;

namespace {
TriangleMesh sphere(int levels, double r) {
  TriangleMesh m = unit_sphere_mesh(levels);
  for (auto& v : m.vertices) v *= r;
  return m;
}
double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}
}  // namespace

int main(int argc, char** argv) {
  int n = 200000, levels = 4, reps = 5;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--particles")) n = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--levels")) levels = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--reps")) reps = std::atoi(argv[i + 1]);
  }
  const double dx = 0.01, rate = 24;
  std::vector<std::shared_ptr<const TriangleMesh>> frames;
  for (int k = 0; k < 4; ++k)
    frames.push_back(std::make_shared<TriangleMesh>(sphere(levels, 0.3 + 0.01 * k)));
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-1, 1), shell(0.27, 0.36);
  std::vector<Vec3> x;  // particles in a shell about the surface, sorted by block as in a run
  while (int(x.size()) < n) {
    const Vec3d d(u(rng), u(rng), u(rng));
    if (d.norm() > 1 || d.norm() < 1e-3) continue;
    x.push_back((d.normalized() * shell(rng)).cast<Real>());
  }
  std::sort(x.begin(), x.end(), [&](const Vec3& a, const Vec3& b) {
    for (int c = 0; c < 3; ++c) {
      const auto ka = std::floor(a[c] / (8 * dx)), kb = std::floor(b[c] / (8 * dx));
      if (ka != kb) return ka < kb;
    }
    return false;
  });
  std::printf("%d particles, %zu triangles per frame, voxel %.3g m\n", n,
              frames[0]->triangles.size(), dx);
  std::printf(
      "threads  lookup ns/particle  prepare(no build) ns/particle  build ns/voxel  voxels\n");
  for (int threads = 1; threads <= 2; ++threads) {
    const exec::Space space(exec::Backend::TBB, threads);
    std::vector<double> look, prep, build;
    std::size_t voxels = 0;
    for (int r = 0; r < reps; ++r) {
      std::vector<Collider> cols(1);
      cols[0].shape = ColliderShape::Mesh;
      cols[0].boundary = BoundaryType::Slip;
      cols[0].field = make_mesh_sequence_field(frames, rate, dx);
      const Real t = Real(1.5 / rate);  // between frames 1 and 2
      auto t0 = std::chrono::steady_clock::now();
      prepare_colliders(cols, x.data(), x.size(), Real(dx), t, space);  // builds frames 1, 2
      const double tb = seconds_since(t0);
      voxels = cols[0].field->voxels();
      build.push_back(tb * 1e9 / double(voxels));
      t0 = std::chrono::steady_clock::now();
      prepare_colliders(cols, x.data(), x.size(), Real(dx), t, space);  // nothing new
      prep.push_back(seconds_since(t0) * 1e9 / n);
      std::vector<Vec3> v(x.size(), Vec3(0, -1, 0));
      const Collider* c = cols.data();
      t0 = std::chrono::steady_clock::now();
      exec::parallel_for(space, "bench.project", exec::Index(n),
                         [&](exec::Index i) { c->project(x[size_t(i)], t, v[size_t(i)]); });
      look.push_back(seconds_since(t0) * 1e9 / n);
    }
    std::printf("%7d  %18.1f  %29.1f  %14.1f  %zu\n", threads, median(look), median(prep),
                median(build), voxels);
  }
  return 0;
}
