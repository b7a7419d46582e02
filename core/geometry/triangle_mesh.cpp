// Triangle mesh geometry: watertightness, enclosed volume, particle sampling inside a mesh through
// an OpenVDB level set (mesh colliders' fields: level_set_collider.cpp). The OpenVDB tools run in
// the caller's exec::Space's task arena, so `--threads` bounds them (core/exec/exec.hpp).
#include "core/geometry/triangle_mesh.hpp"

#include <openvdb/openvdb.h>
#include <openvdb/tools/Interpolation.h>
#include <openvdb/tools/MeshToVolume.h>

#include <algorithm>
#include <map>
#include <mutex>
#include <sstream>
#include <unordered_map>

#include "core/errors.hpp"
#include "core/geometry/lattice.hpp"

namespace amalgam {

MeshCheck check_mesh(const TriangleMesh& m) {
  std::unordered_map<std::uint64_t, int> uses;
  uses.reserve(m.triangles.size() * 2);
  for (const auto& t : m.triangles)
    for (int e = 0; e < 3; ++e) {
      std::uint64_t a = std::uint32_t(t[size_t(e)]), b = std::uint32_t(t[size_t((e + 1) % 3)]);
      if (a > b) std::swap(a, b);
      ++uses[(a << 32) | b];
    }
  MeshCheck c;
  for (const auto& kv : uses) {
    if (kv.second == 1)
      ++c.boundary_edges;
    else if (kv.second > 2)
      ++c.nonmanifold_edges;
  }
  return c;
}

double enclosed_volume(const TriangleMesh& m) {
  double v = 0;
  for (const auto& t : m.triangles)
    v += m.vertices[size_t(t[0])].dot(m.vertices[size_t(t[1])].cross(m.vertices[size_t(t[2])]));
  return v / 6.0;
}

void mesh_bounds(const TriangleMesh& m, Vec3d& lo, Vec3d& hi) {
  lo = Vec3d::Constant(1e300), hi = Vec3d::Constant(-1e300);
  for (const auto& v : m.vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
}

void check_grid_range(const Vec3d& lo, const Vec3d& hi, double h, const std::string& what) {
  const double far = std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff());
  if (!(far / h < kMaxGridIndex)) {
    std::ostringstream os;
    os << what << " reaches " << far << " m from the origin: more than 2^30 cells of " << h
       << " m (the grid's index range)";
    throw InputError(os.str());
  }
}

namespace {
// The mesh in OpenVDB's types (float points, index triangles), OpenVDB initialised.
struct VdbMesh {
  std::vector<openvdb::Vec3s> pts;
  std::vector<openvdb::Vec3I> tris;
  explicit VdbMesh(const TriangleMesh& m) {
    static std::once_flag init;
    std::call_once(init, [] { openvdb::initialize(); });
    pts.reserve(m.vertices.size());
    for (const auto& v : m.vertices) pts.emplace_back(float(v[0]), float(v[1]), float(v[2]));
    tris.reserve(m.triangles.size());
    for (const auto& t : m.triangles) tris.emplace_back(t[0], t[1], t[2]);
  }
};
}  // namespace

namespace {
// The bodies below run whole inside the space's task arena (sample_mesh): the level set's
// construction and also its destruction, which OpenVDB parallelises too.
std::vector<Vec3> sample_mesh_limited(const TriangleMesh& m, double h, double jitter,
                                      std::uint64_t seed, const LatticeSlice& slice) {
  {
    Vec3d lo, hi;
    mesh_bounds(m, lo, hi);
    check_grid_range(lo, hi, h, "mesh");
  }
  const VdbMesh vm(m);
  const auto& pts = vm.pts;
  const auto& tris = vm.tris;
  const auto xform = openvdb::math::Transform::createLinearTransform(h);
  // Level set in world units; interior beyond the narrow band is flood-filled negative.
  const auto sdf = openvdb::tools::meshToLevelSet<openvdb::FloatGrid>(*xform, pts, tris, 3.0f);
  Vec3d lo(1e300, 1e300, 1e300), hi(-1e300, -1e300, -1e300);
  for (const auto& v : m.vertices) {
    lo = lo.cwiseMin(v);
    hi = hi.cwiseMax(v);
  }
  const auto acc = sdf->getConstAccessor();
  openvdb::tools::GridSampler<openvdb::FloatGrid::ConstAccessor, openvdb::tools::BoxSampler>
      sampler(acc, *xform);
  long long n[3];
  for (int a = 0; a < 3; ++a) n[a] = (long long)std::ceil((hi[a] - lo[a]) / h);
  const std::vector<Vec3> out = sample_lattice(
      lo, n, h, jitter, seed,
      [&](const Vec3d& p) { return sampler.wsSample(openvdb::Vec3d(p[0], p[1], p[2])) < 0; },
      slice);
  return out;
}

}  // namespace

std::vector<Vec3> sample_mesh(const TriangleMesh& m, double h, double jitter, std::uint64_t seed,
                              const exec::Space& space, const LatticeSlice& slice) {
  std::vector<Vec3> out;
  exec::with_thread_limit(space, [&] { out = sample_mesh_limited(m, h, jitter, seed, slice); });
  return out;
}

TriangleMesh unit_sphere_mesh(int levels) {
  TriangleMesh m;
  m.vertices = {Vec3d(1, 0, 0),  Vec3d(-1, 0, 0), Vec3d(0, 1, 0),
                Vec3d(0, -1, 0), Vec3d(0, 0, 1),  Vec3d(0, 0, -1)};
  m.triangles = {{0, 2, 4}, {2, 1, 4}, {1, 3, 4}, {3, 0, 4},
                 {2, 0, 5}, {1, 2, 5}, {3, 1, 5}, {0, 3, 5}};
  for (int l = 0; l < levels; ++l) {
    std::map<std::pair<int, int>, int> mid;
    auto midpoint = [&](int a, int b) {
      const auto key = std::make_pair(std::min(a, b), std::max(a, b));
      const auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      m.vertices.push_back((m.vertices[size_t(a)] + m.vertices[size_t(b)]).normalized());
      return mid[key] = int(m.vertices.size()) - 1;
    };
    std::vector<std::array<std::int32_t, 3>> next;
    for (const auto& t : m.triangles) {
      const int a = midpoint(t[0], t[1]), b = midpoint(t[1], t[2]), c = midpoint(t[2], t[0]);
      next.push_back({t[0], a, c});
      next.push_back({a, t[1], b});
      next.push_back({c, b, t[2]});
      next.push_back({a, b, c});
    }
    m.triangles = next;
  }
  return m;
}

}  // namespace amalgam
