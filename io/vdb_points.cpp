// Sees OpenVDB's points headers (slow to compile): keep it the only io file that does.
#include "io/vdb_points.hpp"

#include <openvdb/openvdb.h>
#include <openvdb/points/PointConversion.h>
#include <openvdb/points/PointDataGrid.h>
#include <openvdb/tools/PointIndexGrid.h>

#include <cstdio>
#include <mutex>

#include "core/errors.hpp"
#include "io/writers.hpp"

namespace amalgam {

namespace {
template <class T>
void add_attribute(openvdb::points::PointDataGrid& grid,
                   const openvdb::tools::PointIndexGrid& index, const std::string& name,
                   const std::vector<T>& values) {
  using namespace openvdb::points;
  appendAttribute<T>(grid.tree(), name);
  populateAttribute<PointDataTree, openvdb::tools::PointIndexTree, PointAttributeVector<T>>(
      grid.tree(), index.tree(), name, PointAttributeVector<T>(values));
}
}  // namespace

void write_vdb_points(const std::string& path, const PointFields& p, double voxel_size,
                      const exec::Space& space) {
  static std::once_flag init;
  std::call_once(init, [] { openvdb::initialize(); });
  const size_t n = p.n;
  std::vector<openvdb::Vec3R> P(n);
  std::vector<openvdb::Vec3s> v(n);
  std::vector<openvdb::Int32> material(p.material, p.material + n), id(p.id, p.id + n);
  for (size_t i = 0; i < n; ++i) {
    P[i] = openvdb::Vec3R(double(p.x[i][0]), double(p.x[i][1]), double(p.x[i][2]));
    v[i] = openvdb::Vec3s(float(p.v[i][0]), float(p.v[i][1]), float(p.v[i][2]));
  }
  const openvdb::math::Transform::Ptr xform =
      openvdb::math::Transform::createLinearTransform(voxel_size);
  const openvdb::points::PointAttributeVector<openvdb::Vec3R> positions(P);
  const std::string tmp = path + ".tmp";
  bool written = false;
  std::string error;
  exec::with_thread_limit(space, [&] {  // the grids' construction and destruction
    const auto index =
        openvdb::tools::createPointIndexGrid<openvdb::tools::PointIndexGrid>(positions, *xform);
    const auto grid = openvdb::points::createPointDataGrid<openvdb::points::NullCodec,
                                                           openvdb::points::PointDataGrid>(
        *index, positions, *xform);
    add_attribute(*grid, *index, "v", v);
    for (const auto& s : p.primary) add_attribute(*grid, *index, s.first, s.second);
    add_attribute(*grid, *index, "material", material);
    add_attribute(*grid, *index, "id", id);
    for (const auto& s : p.extra) add_attribute(*grid, *index, s.first, s.second);
    grid->setName("points");
    try {
      openvdb::io::File file(tmp);
      file.write(openvdb::GridCPtrVec{grid});
      file.close();
      written = true;
    } catch (const std::exception& e) {
      error = e.what();
    }
  });
  if (!written) {
    std::remove(tmp.c_str());
    throw InputError(path + ": cannot write VDB points: " + error);
  }
  commit_temporary(tmp, path);
}

void write_vdb_grid_fields(const std::string& path, const SparseGrid& grid, double dx,
                           const exec::Space& space) {
  static std::once_flag init;
  std::call_once(init, [] { openvdb::initialize(); });
  const std::string tmp = path + ".tmp";
  std::string error;
  exec::with_thread_limit(space, [&] {  // the grids' construction, writing and destruction
    const openvdb::math::Transform::Ptr xform = openvdb::math::Transform::createLinearTransform(dx);
    auto mass = openvdb::FloatGrid::create(0.0f);
    auto vel = openvdb::Vec3SGrid::create(openvdb::Vec3s(0.0f));
    mass->setTransform(xform);
    vel->setTransform(xform->copy());
    mass->setName("mass");
    vel->setName("velocity");
    vel->setVectorType(openvdb::VEC_CONTRAVARIANT_RELATIVE);
    auto ma = mass->getAccessor();
    auto va = vel->getAccessor();
    const Real* a = grid.node4(0);
    for (const std::int32_t leaf : grid.active_leaves()) {
      const Vec3i base = grid.leaf_coords()[size_t(leaf)] * kLeafDim;
      const Real* n = a + size_t(leaf) * kLeafNodes * 4;
      for (int i = 0; i < kLeafDim; ++i)
        for (int j = 0; j < kLeafDim; ++j)
          for (int k = 0; k < kLeafDim; ++k) {
            const Real* node = n + leaf_offset(i, j, k) * 4;
            if (!(node[0] > 0)) continue;
            const openvdb::Coord c(base[0] + i, base[1] + j, base[2] + k);
            ma.setValue(c, float(node[0]));
            va.setValue(c, openvdb::Vec3s(float(node[1]), float(node[2]), float(node[3])));
          }
    }
    try {
      openvdb::io::File file(tmp);
      file.write(openvdb::GridCPtrVec{mass, vel});
      file.close();
    } catch (const std::exception& e) {
      error = std::string(e.what()).empty() ? "unknown error" : e.what();
    }
  });
  if (!error.empty()) {
    std::remove(tmp.c_str());
    throw InputError(path + ": cannot write VDB grid fields: " + error);
  }
  commit_temporary(tmp, path);
}

}  // namespace amalgam
