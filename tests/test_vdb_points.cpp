// VDB point output read back with OpenVDB's own reader and compared field by field.
#include <gtest/gtest.h>

#include <openvdb/openvdb.h>
#include <openvdb/points/AttributeArray.h>
#include <openvdb/points/PointDataGrid.h>

#include <filesystem>

#include "io/scene.hpp"
#include "solvers/mpm_simulation.hpp"
#include "solvers/factory.hpp"
#include "io/vdb_points.hpp"
#include "thread_recorder.hpp"

using namespace amalgam;

TEST(VdbPoints, ReadBackFieldByField) {
  const Scene scene = parse_scene(R"({
    "simulation": {"dx": 0.04, "frames": 1},
    "materials": {"a": {"model": "snow", "density": 400, "youngs_modulus": 1e4},
                  "b": {"density": 500, "youngs_modulus": 1e4, "melting": {"temperature": 300, "bulk_modulus": 1e4}}},
    "objects": [{"shape": "box", "min": [0.2,0.2,0.2], "max": [0.5,0.4,0.5], "material": "a", "velocity": [1,2,3]},
                {"shape": "sphere", "center": [0.7,0.7,0.7], "radius": 0.1, "material": "b", "angular_velocity": [0,5,0]}],
    "heat_sources": [{"type": "sphere", "center": [0.7,0.7,0.7], "radius": 0.05, "temperature": 350, "rate": 100}]
  })",
                                  "s.json");
  MpmSolver solver = build_solver(scene);
  const exec::Space space(exec::Backend::TBB, 2);
  for (int i = 0; i < 5; ++i) solver.step(space, solver.stable_dt(space));  // sorted: index != id
  const std::string path =
      (std::filesystem::temp_directory_path() / "amalgam_test_points.vdb").string();
  write_vdb_points(path, mpm_point_fields(solver.particles(), solver.attributes()),
                   double(scene.mpm.dx), exec::Space());

  openvdb::initialize();
  openvdb::io::File file(path);
  file.open();
  const auto grid = openvdb::gridPtrCast<openvdb::points::PointDataGrid>(file.readGrid("points"));
  file.close();
  ASSERT_TRUE(grid);

  const ParticleSet& ps = solver.particles();
  const auto& at = solver.attributes();
  std::vector<int> row_of_id(ps.size(), -1);
  for (size_t i = 0; i < ps.size(); ++i) row_of_id[size_t(ps.int32(at.id)[i])] = int(i);
  size_t seen = 0, heated = 0;
  for (auto leaf = grid->tree().cbeginLeaf(); leaf; ++leaf) {
    openvdb::points::AttributeHandle<openvdb::Vec3f> P(leaf->constAttributeArray("P"));
    openvdb::points::AttributeHandle<openvdb::Vec3f> v(leaf->constAttributeArray("v"));
    openvdb::points::AttributeHandle<float> J(leaf->constAttributeArray("J"));
    openvdb::points::AttributeHandle<openvdb::Int32> mat(leaf->constAttributeArray("material"));
    openvdb::points::AttributeHandle<openvdb::Int32> id(leaf->constAttributeArray("id"));
    openvdb::points::AttributeHandle<float> plastic(leaf->constAttributeArray("plastic"));
    openvdb::points::AttributeHandle<float> temperature(leaf->constAttributeArray("temperature"));
    for (auto it = leaf->beginIndexOn(); it; ++it) {
      const int pid = id.get(*it);
      ASSERT_GE(pid, 0);
      ASSERT_LT(size_t(pid), ps.size());
      const int r = row_of_id[size_t(pid)];
      ASSERT_GE(r, 0) << "id " << pid << " appears twice";
      row_of_id[size_t(pid)] = -1;
      const openvdb::Vec3d world =
          grid->transform().indexToWorld(it.getCoord().asVec3d() + P.get(*it));
      const Vec3 x = ps.vec3(at.x)[size_t(r)];
      for (int a = 0; a < 3; ++a) {
        EXPECT_NEAR(world[a], double(x[a]), 1e-6);
        EXPECT_EQ(v.get(*it)[a], float(ps.vec3(at.v)[size_t(r)][a]));
      }
      EXPECT_EQ(J.get(*it), float(ps.mat3(at.F)[size_t(r)].determinant()));
      EXPECT_EQ(mat.get(*it), ps.int32(at.material)[size_t(r)]);
      EXPECT_EQ(plastic.get(*it), float(ps.real(at.plastic)[size_t(r)]));
      EXPECT_EQ(temperature.get(*it), float(ps.real(at.temperature)[size_t(r)]));
      heated += temperature.get(*it) > 300;
      ++seen;
    }
  }
  EXPECT_EQ(seen, ps.size());
  EXPECT_GT(heated, 0u);  // the temperature field is not trivially uniform
  std::filesystem::remove(path);
}

// Grid fields read back with OpenVDB: the node masses sum to the particles' mass (P2G conserves
// mass), and every active voxel's velocity equals the grid's node velocity.
TEST(VdbGridFields, ReadBackMassAndVelocity) {
  const Scene scene = parse_scene(R"({
    "simulation": {"dx": 0.04, "frames": 1},
    "materials": {"a": {"density": 1000, "youngs_modulus": 1e4}},
    "objects": [{"shape": "sphere", "center": [0.5,0.5,0.5], "radius": 0.15, "material": "a", "velocity": [1,-2,0.5]}]
  })",
                                  "s.json");
  MpmSolver solver = build_solver(scene);
  const exec::Space space(exec::Backend::Serial, 1);
  for (int i = 0; i < 3; ++i) solver.step(space, solver.stable_dt(space));
  const std::string path =
      (std::filesystem::temp_directory_path() / "amalgam_test_grid.vdb").string();
  write_vdb_grid_fields(path, solver.grid(), double(scene.mpm.dx), exec::Space());
  openvdb::initialize();
  openvdb::io::File file(path);
  file.open();
  const auto mass = openvdb::gridPtrCast<openvdb::FloatGrid>(file.readGrid("mass"));
  const auto vel = openvdb::gridPtrCast<openvdb::Vec3SGrid>(file.readGrid("velocity"));
  file.close();
  ASSERT_TRUE(mass && vel);
  EXPECT_NEAR(mass->voxelSize()[0], 0.04, 1e-7);
  double total = 0;
  size_t voxels = 0;
  for (auto it = mass->cbeginValueOn(); it; ++it) total += double(*it), ++voxels;
  double particles = 0;
  for (size_t p = 0; p < solver.particles().size(); ++p)
    particles += double(solver.particles().real(solver.attributes().mass)[p]);
  EXPECT_NEAR(total, particles, 1e-4 * particles);
  EXPECT_EQ(vel->activeVoxelCount(), voxels);
  // Spot-check velocities against the grid's own storage.
  const SparseGrid& g = solver.grid();
  auto va = vel->getConstAccessor();
  size_t checked = 0;
  for (const std::int32_t leaf : g.active_leaves()) {
    const Vec3i base = g.leaf_coords()[size_t(leaf)] * kLeafDim;
    const Real* n = g.node4(0) + size_t(leaf) * kLeafNodes * 4 + leaf_offset(3, 4, 5) * 4;
    if (!(n[0] > 0)) continue;
    const openvdb::Vec3s v = va.getValue(openvdb::Coord(base[0] + 3, base[1] + 4, base[2] + 5));
    EXPECT_EQ(v[0], float(n[1]));
    EXPECT_EQ(v[1], float(n[2]));
    EXPECT_EQ(v[2], float(n[3]));
    ++checked;
  }
  EXPECT_GT(checked, 0u);
  std::filesystem::remove(path);
}

// Writing VDB points obeys the space's thread count: under one thread no TBB worker joins the
// point-index and point-data construction (nor the grids' destruction); both writes hold the same
// points.
TEST(VdbPoints, WritingUsesTheSpacesThreadCount) {
  const std::size_t n = 400000;
  std::vector<Vec3> x(n), v(n, Vec3(1, 2, 3));
  std::vector<std::int32_t> material(n, 0), id(n);
  for (std::size_t i = 0; i < n; ++i) {
    x[i] = Vec3(Real(i % 97) * Real(0.01), Real((i / 97) % 89) * Real(0.01),
                Real(i / (97 * 89)) * Real(0.01));
    id[i] = std::int32_t(i);
  }
  PointFields p;
  p.n = n;
  p.x = x.data();
  p.v = v.data();
  p.material = material.data();
  p.id = id.data();
  p.primary.emplace_back("J", std::vector<float>(n, 1.0f));
  const std::string path =
      (std::filesystem::temp_directory_path() / "amalgam_test_points_threads.vdb").string();
  for (const int threads : {1, 2}) {
    test::WorkerRecorder rec;
    write_vdb_points(path, p, 0.02, exec::Space(exec::Backend::TBB, threads));
    EXPECT_LE(rec.workers(), std::size_t(threads - 1)) << threads << " thread(s)";
  }
  std::filesystem::remove(path);
}
