// Surfacing throughput (issue 29): a lattice ball of about 10^6 particles (R = 62 h, voxel = h =
// dx / 2 at 8 particles per cell) surfaced by io/surfacing.hpp with the default grids (surface,
// density, v; no mesh, then with an OBJ mesh), smooth and spheres, at 1 and 2 threads; prints
// seconds and ns per particle (best of --reps, default 3). Files go to a temporary directory.
// Usage: amalgam_surfacing_bench [--radius-cells 62] [--reps 3]
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <vector>

#include "io/surfacing.hpp"

using namespace amalgam;

int main(int argc, char** argv) {
  int cells = 62, reps = 3;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--radius-cells")) cells = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--reps")) reps = std::atoi(argv[i + 1]);
  }
  const double h = 0.01, R = cells * h;
  std::vector<Vec3> x, v;
  std::vector<std::int32_t> material, id;
  for (int i = -cells - 1; i <= cells; ++i)
    for (int j = -cells - 1; j <= cells; ++j)
      for (int k = -cells - 1; k <= cells; ++k) {
        const Vec3d q = h * Vec3d(i + 0.5, j + 0.5, k + 0.5);
        if (q.norm() > R) continue;
        x.push_back((q + Vec3d(1, 1, 1)).cast<Real>());
        v.push_back(Vec3(0, -1, 0));
        material.push_back(0);
        id.push_back(std::int32_t(id.size()));
      }
  PointFields p;
  p.n = x.size();
  p.x = x.data();
  p.v = v.data();
  p.material = material.data();
  p.id = id.data();
  const std::string dir =
      (std::filesystem::temp_directory_path() / "amalgam_surfacing_bench").string();
  std::filesystem::create_directories(dir);
  std::printf("%zu particles, voxel = h = %.3g m\n", p.n, h);
  std::printf("method   mesh  threads  seconds  ns/particle  voxels  triangles\n");
  for (const SurfaceMeshFormat mesh : {SurfaceMeshFormat::None, SurfaceMeshFormat::Obj})
    for (const SurfacingMethod m : {SurfacingMethod::Smooth, SurfacingMethod::Spheres})
      for (int t = 1; t <= 2; ++t) {
        SurfacingSpec s;
        s.method = m;
        s.voxel_size = h;
        s.filters = default_surface_filters(m);
        s.mesh = mesh;
        double best = 1e30;
        SurfacingStats st;
        for (int r = 0; r < reps; ++r) {
          const auto t0 = std::chrono::steady_clock::now();
          st = write_surfacing(dir + "/s", p, h, s, exec::Space(exec::Backend::TBB, t));
          best = std::min(
              best, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
        }
        std::printf("%-8s %-5s %7d  %7.3f  %11.0f  %6zu  %9zu\n",
                    m == SurfacingMethod::Smooth ? "smooth" : "spheres",
                    mesh == SurfaceMeshFormat::Obj ? "obj" : "none", t, best,
                    best / double(p.n) * 1e9, st.active_voxels, st.triangles);
      }
  std::filesystem::remove_all(dir);
  return 0;
}
