// VDB point output read back with OpenVDB's own reader and compared field by field.
#include <gtest/gtest.h>

#include <openvdb/openvdb.h>
#include <openvdb/points/AttributeArray.h>
#include <openvdb/points/PointDataGrid.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>

#include "io/scene.hpp"
#include "solvers/mpm_simulation.hpp"
#include "solvers/factory.hpp"
#include "io/vdb_points.hpp"
#include "io/writers.hpp"
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
  write_vdb_points(path,
                   mpm_point_fields(solver.particles(), solver.attributes(), solver.materials(),
                                    {"J", "material", "Jp", "temperature"}, exec::Space()),
                   double(scene.mpm.dx), VdbPrecision::Full, exec::Space());

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
    openvdb::points::AttributeHandle<float> plastic(leaf->constAttributeArray("Jp"));
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
      EXPECT_EQ(J.get(*it), float(at.F >= 0 ? ps.mat3(at.F)[size_t(r)].determinant()
                                            : b_factor(ps.sym_dev(at.b)[size_t(r)]).determinant()));
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
    particles += double(solver.particle_mass(p));
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
  p.attributes.push_back({"J", PointAttribute::Type::Float, std::vector<float>(n, 1.0f), {}});
  const std::string path =
      (std::filesystem::temp_directory_path() / "amalgam_test_points_threads.vdb").string();
  for (const int threads : {1, 2}) {
    test::WorkerRecorder rec;
    write_vdb_points(path, p, 0.02, VdbPrecision::Full, exec::Space(exec::Backend::TBB, threads));
    EXPECT_LE(rec.workers(), std::size_t(threads - 1)) << threads << " thread(s)";
  }
  std::filesystem::remove(path);
}

// ---- Compact VDB points and output.attributes (issue 32 items 1-2, issue 29 item 3).

namespace {

std::string temp_path(const char* name) {
  return (std::filesystem::temp_directory_path() / name).string();
}

std::string file_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

openvdb::points::PointDataGrid::Ptr read_points(const std::string& path,
                                                std::uint32_t* compression = nullptr) {
  openvdb::initialize();
  openvdb::io::File file(path);
  file.open();
  if (compression) *compression = file.compression();
  auto grid = openvdb::gridPtrCast<openvdb::points::PointDataGrid>(file.readGrid("points"));
  file.close();
  return grid;
}

// One particle as read back: world position and velocity, by id.
struct ReadPoint {
  openvdb::Vec3d x;
  openvdb::Vec3f v;
};
std::map<int, ReadPoint> read_by_id(const openvdb::points::PointDataGrid& grid) {
  using namespace openvdb::points;
  std::map<int, ReadPoint> out;
  for (auto leaf = grid.tree().cbeginLeaf(); leaf; ++leaf) {
    AttributeHandle<openvdb::Vec3f> P(leaf->constAttributeArray("P"));
    AttributeHandle<openvdb::Vec3f> v(leaf->constAttributeArray("v"));
    AttributeHandle<openvdb::Int32> id(leaf->constAttributeArray("id"));
    for (auto it = leaf->beginIndexOn(); it; ++it)
      out[id.get(*it)] = {grid.transform().indexToWorld(it.getCoord().asVec3d() + P.get(*it)),
                          v.get(*it)};
  }
  return out;
}

// The (value type, codec) OpenVDB records for attribute `name` in the first leaf.
openvdb::NamePair attribute_type(const openvdb::points::PointDataGrid& grid,
                                 const std::string& name) {
  const auto leaf = grid.tree().cbeginLeaf();
  const auto& desc = leaf->attributeSet().descriptor();
  const std::size_t pos = desc.find(name);
  if (pos == openvdb::points::AttributeSet::INVALID_POS) return {"missing", ""};
  return desc.type(pos);
}

// keep_F: as when the output asks for F (MpmSettings::keep_F).
std::unique_ptr<Simulation> jelly_drop(const exec::Space& space, Scene& scene,
                                       bool keep_F = false) {
  scene = load_scene(std::string(AMALGAM_SOURCE_DIR) + "/scenes/jelly_drop.json");
  scene.mpm.keep_F = keep_F;
  return make_simulation(scene, space);
}

}  // namespace

// The default scene's frame 0 written compact with its attributes (none asked: P, v, id): at most
// 12 bytes per particle (issue 32). The full-precision size is printed for comparison.
TEST(VdbPoints, CompactJellyDropFrameZeroIsAtMostTwelveBytesPerParticle) {
  const exec::Space space(exec::Backend::TBB, 2);
  Scene scene;
  auto sim = jelly_drop(space, scene);
  EXPECT_EQ(scene.output.vdb_precision, VdbPrecision::Compact);  // the default
  PointFields p = sim->point_fields(scene.output.attributes, space);
  p.material_names = scene.material_names;
  const std::string compact = temp_path("amalgam_jelly_compact.vdb");
  const std::string full = temp_path("amalgam_jelly_full.vdb");
  write_vdb_points(compact, p, sim->point_voxel_size(), VdbPrecision::Compact, space);
  write_vdb_points(full, p, sim->point_voxel_size(), VdbPrecision::Full, space);
  const double n = double(p.n);
  const double compact_bpp = double(std::filesystem::file_size(compact)) / n;
  const double full_bpp = double(std::filesystem::file_size(full)) / n;
  std::printf("jelly_drop frame 0, %zu particles: compact %.2f B/particle, full %.2f\n", p.n,
              compact_bpp, full_bpp);
  EXPECT_LE(compact_bpp, 12.0);
  // Nothing the scene did not ask for (issue 32 item 2): no output.attributes, so P, v, id only.
  EXPECT_TRUE(scene.output.attributes.empty());
  const auto grid = read_points(compact);
  EXPECT_EQ(grid->tree().cbeginLeaf()->attributeSet().descriptor().size(), 3u);
  EXPECT_EQ(attribute_type(*grid, "J").first, "missing");
  std::filesystem::remove(compact);
  std::filesystem::remove(full);
}

// Compact positions read back with OpenVDB's own point reading lie within the stated error of the
// simulation's positions (FixedPointCodec truncates: each axis up to voxel/65535 low, plus 2^-24
// voxel of float rounding), velocities within half precision; stock OpenVDB reads the file.
TEST(VdbPoints, CompactReadsBackWithinTheStatedError) {
  const exec::Space space(exec::Backend::TBB, 2);
  Scene scene;
  auto sim = jelly_drop(space, scene);
  for (int i = 0; i < 40; ++i) sim->advance(space, sim->stable_dt(space));  // moving, deformed
  const PointFields p = sim->point_fields({}, space);
  const double voxel = sim->point_voxel_size();
  const std::string path = temp_path("amalgam_jelly_compact_error.vdb");
  write_vdb_points(path, p, voxel, VdbPrecision::Compact, space);
  std::uint32_t compression = 0;
  const auto grid = read_points(path, &compression);
  ASSERT_TRUE(grid);
  EXPECT_TRUE(compression & openvdb::io::COMPRESS_BLOSC);
  EXPECT_EQ(attribute_type(*grid, "P"), openvdb::NamePair("vec3s", "fxpt16"));
  EXPECT_EQ(attribute_type(*grid, "v"), openvdb::NamePair("vec3s", "trnc"));
  EXPECT_EQ(attribute_type(*grid, "id"), openvdb::NamePair("int32", "null"));
  const std::map<int, ReadPoint> back = read_by_id(*grid);
  ASSERT_EQ(back.size(), p.n);
  const double bound = voxel * (1.0 / 65535 + std::ldexp(1.0, -24));  // truncation + rounding
  double worst = 0, worst_v = 0;
  for (std::size_t i = 0; i < p.n; ++i) {
    const ReadPoint& r = back.at(p.id[i]);
    for (int a = 0; a < 3; ++a) {
      const double err = std::abs(r.x[a] - double(p.x[i][a]));
      worst = std::max(worst, err);
      ASSERT_LE(err, bound) << "particle " << p.id[i] << " axis " << a;
      const double v = double(float(p.v[i][a]));
      const double ev = std::abs(double(r.v[a]) - v);
      if (std::abs(v) >= std::ldexp(1.0, -14)) worst_v = std::max(worst_v, ev / std::abs(v));
      ASSERT_LE(ev, std::ldexp(std::abs(v), -11) + std::ldexp(1.0, -25))
          << "particle " << p.id[i] << " velocity " << a;
    }
  }
  std::printf(
      "compact: largest position error %.7g voxel (1/65535 = %.7g), largest relative "
      "velocity error %.4g over normal halves (2^-11 = %.4g)\n",
      worst / voxel, 1.0 / 65535, worst_v, std::ldexp(1.0, -11));
  std::filesystem::remove(path);
}

// Compact files do not depend on the thread count: byte-identical for 1 and 2 TBB threads.
TEST(VdbPoints, CompactFilesAreIdenticalForOneAndTwoThreads) {
  const exec::Space space(exec::Backend::TBB, 2);
  Scene scene;
  auto sim = jelly_drop(space, scene, true);
  for (int i = 0; i < 10; ++i) sim->advance(space, sim->stable_dt(space));
  PointFields p = sim->point_fields({"F", "J", "vonmises", "material"}, space);
  p.material_names = scene.material_names;
  std::string bytes[2];
  for (const int threads : {1, 2}) {
    const std::string path = temp_path("amalgam_jelly_threads.vdb");
    write_vdb_points(path, p, sim->point_voxel_size(), VdbPrecision::Compact,
                     exec::Space(exec::Backend::TBB, threads));
    bytes[threads - 1] = file_bytes(path);
    std::filesystem::remove(path);
  }
  ASSERT_FALSE(bytes[0].empty());
  EXPECT_TRUE(bytes[0] == bytes[1]);
}

// Every MPM attribute with its documented name and OpenVDB type (docs/output.md), in compact and
// full files, the material names as metadata, and the PLY properties in the documented order.
TEST(VdbPoints, AttributesHaveTheDocumentedNamesAndTypes) {
  const Scene scene = parse_scene(R"({
    "simulation": {"dx": 0.04, "frames": 1},
    "materials": {"snow": {"model": "snow", "density": 400, "youngs_modulus": 1e4},
                  "jelly": {"density": 1000, "youngs_modulus": 1e4}},
    "objects": [{"shape": "box", "min": [0.2,0.2,0.2], "max": [0.5,0.4,0.5], "material": "snow", "velocity": [1,2,3]},
                {"shape": "sphere", "center": [0.7,0.7,0.7], "radius": 0.1, "material": "jelly"}],
    "output": {"attributes": ["F", "J", "Jp", "vonmises", "rest", "material"]}
  })",
                                  "s.json");
  const exec::Space space(exec::Backend::TBB, 2);
  auto sim = make_simulation(scene, space);
  sim->keep_rest_positions();
  for (int i = 0; i < 5; ++i) sim->advance(space, sim->stable_dt(space));
  PointFields p = sim->point_fields(scene.output.attributes, space);
  p.material_names = scene.material_names;
  const std::string path = temp_path("amalgam_attributes.vdb");
  for (const VdbPrecision prec : {VdbPrecision::Full, VdbPrecision::Compact}) {
    const bool compact = prec == VdbPrecision::Compact;
    write_vdb_points(path, p, sim->point_voxel_size(), prec, space);
    const auto grid = read_points(path);
    ASSERT_TRUE(grid);
    const char* half = compact ? "trnc" : "null";
    EXPECT_EQ(attribute_type(*grid, "v"), openvdb::NamePair("vec3s", half));
    EXPECT_EQ(attribute_type(*grid, "id"), openvdb::NamePair("int32", "null"));
    EXPECT_EQ(attribute_type(*grid, "F"), openvdb::NamePair("mat3s", "null"));
    EXPECT_EQ(attribute_type(*grid, "J"), openvdb::NamePair("float", half));
    EXPECT_EQ(attribute_type(*grid, "Jp"), openvdb::NamePair("float", half));
    EXPECT_EQ(attribute_type(*grid, "vonmises"), openvdb::NamePair("float", "null"));
    EXPECT_EQ(attribute_type(*grid, "rest"), openvdb::NamePair("vec3s", "null"));
    EXPECT_EQ(attribute_type(*grid, "material"), openvdb::NamePair("int32", "null"));
    EXPECT_EQ(grid->metaValue<std::string>("material_names"), "[\"jelly\",\"snow\"]");
    // Values: F row-major as Mat3s, rest the set-up position, material the index.
    const std::map<int, std::size_t> row = [&] {
      std::map<int, std::size_t> m;
      for (std::size_t i = 0; i < p.n; ++i) m[p.id[i]] = i;
      return m;
    }();
    const auto& F = *std::find_if(p.attributes.begin(), p.attributes.end(),
                                  [](const PointAttribute& a) { return a.name == "F"; });
    const auto& rest = *std::find_if(p.attributes.begin(), p.attributes.end(),
                                     [](const PointAttribute& a) { return a.name == "rest"; });
    std::size_t seen = 0;
    for (auto leaf = grid->tree().cbeginLeaf(); leaf; ++leaf) {
      using namespace openvdb::points;
      AttributeHandle<openvdb::math::Mat3s> f(leaf->constAttributeArray("F"));
      AttributeHandle<openvdb::Vec3f> r(leaf->constAttributeArray("rest"));
      AttributeHandle<openvdb::Int32> id(leaf->constAttributeArray("id"));
      AttributeHandle<openvdb::Int32> mat(leaf->constAttributeArray("material"));
      for (auto it = leaf->beginIndexOn(); it; ++it, ++seen) {
        const std::size_t i = row.at(id.get(*it));
        for (int a = 0; a < 3; ++a) {
          for (int b = 0; b < 3; ++b) EXPECT_EQ(f.get(*it)(a, b), F.f[9 * i + 3 * a + b]);
          EXPECT_EQ(r.get(*it)[a], rest.f[3 * i + a]);
        }
        EXPECT_EQ(mat.get(*it), p.material[i]);
      }
    }
    EXPECT_EQ(seen, p.n);
  }
  std::filesystem::remove(path);
  // Rest positions are the set-up's: a fresh simulation's positions by id.
  auto fresh = make_simulation(scene, space);
  const PointFields p0 = fresh->point_fields({}, space);
  const auto& rest = p.attributes[4];
  ASSERT_EQ(rest.name, "rest");
  std::map<int, std::size_t> row;
  for (std::size_t i = 0; i < p.n; ++i) row[p.id[i]] = i;
  for (std::size_t j = 0; j < p0.n; ++j)
    for (int a = 0; a < 3; ++a) ASSERT_EQ(rest.f[3 * row.at(p0.id[j]) + a], float(p0.x[j][a]));
  // PLY: x y z vx vy vz id, then the attributes in order (F00..F22, rest_x..z).
  const std::string ply = temp_path("amalgam_attributes.ply");
  write_ply_points(ply, p);
  const std::string head = file_bytes(ply).substr(0, 1000);
  std::string props;
  for (std::size_t at = head.find("property "); at != std::string::npos;
       at = head.find("property ", at + 1))
    props += head.substr(at + 9, head.find('\n', at) - at - 9) + ",";
  EXPECT_EQ(props,
            "float x,float y,float z,float vx,float vy,float vz,int id,float F00,float F01,float "
            "F02,float F10,float F11,float F12,float F20,float F21,float F22,float J,float "
            "Jp,float vonmises,float rest_x,float rest_y,float rest_z,int material,");
  EXPECT_NE(head.find("comment material_names [\"jelly\",\"snow\"]\n"), std::string::npos);
  EXPECT_EQ(std::filesystem::file_size(ply),
            head.find("end_header\n") + 11 + p.n * 4 * (7 + 9 + 3 + 3 + 1));
  std::filesystem::remove(ply);
}

// Von Mises stress of MPM particles: under a uniaxial stretch F = diag(1 + e, 1, 1) a fixed
// corotated material's Cauchy stress has von Mises value 2 mu e (tau = 2 mu (F - R) F^T +
// lambda (J - 1) J I with R = I; sigma = tau / J), and zero under a uniform dilation.
TEST(VdbPoints, VonMisesOfAStretchAndADilation) {
  const Scene scene = parse_scene(R"({
    "simulation": {"dx": 0.05, "frames": 1},
    "materials": {"a": {"density": 1000, "youngs_modulus": 1e6, "poisson_ratio": 0.3}},
    "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "a"}]
  })",
                                  "s.json");
  MpmSolver solver = build_solver(scene);
  const double e = 0.01, mu = double(scene.materials[0].mu);
  for (const bool stretch : {true, false}) {
    const MpmAttributes& a = solver.attributes();
    for (std::size_t i = 0; i < solver.particles().size(); ++i) {
      const Mat3 F = stretch ? Mat3(Vec3(Real(1 + e), 1, 1).asDiagonal())
                             : Mat3(Real(1.01) * Mat3::Identity());
      if (a.F >= 0)
        solver.particles().mat3(a.F)[i] = F;
      else  // b - I (MpmSolver::keeps_b)
        solver.particles().sym_dev(a.b)[i] = b_from_F<Real>(F.cast<double>());
    }
    const PointFields p = mpm_point_fields(solver.particles(), solver.attributes(),
                                           solver.materials(), {"vonmises"}, exec::Space());
    const std::vector<float>& vm = *p.find("vonmises");
    for (std::size_t i = 0; i < p.n; ++i) {
      if (stretch)
        ASSERT_NEAR(vm[i], 2 * mu * e, 1e-4 * 2 * mu * e);
      else
        ASSERT_NEAR(vm[i], 0.0, 1e-6 * mu);
    }
  }
}

// Peridynamic attributes: rest = the reference positions, damage and theta as before, von Mises
// from PdSolver::compute_stress (zero at rest, positive once pulled); computing it leaves the run
// bitwise as it was.
TEST(VdbPoints, PeridynamicAttributes) {
  const Scene scene = load_scene(std::string(AMALGAM_SOURCE_DIR) + "/tests/data/pd_small.json");
  const exec::Space space(exec::Backend::TBB, 2);
  auto a = make_simulation(scene, space), b = make_simulation(scene, space);
  const std::vector<std::string> names = {"vonmises", "damage", "rest", "material", "theta"};
  const PointFields p0 = a->point_fields(names, space);
  ASSERT_EQ(p0.attributes.size(), names.size());
  for (std::size_t i = 0; i < p0.n; ++i) {
    EXPECT_LE(p0.attributes[0].f[i], 2.0f);  // Pa, at rest: round-off of E = 2e6 Pa
    for (int c = 0; c < 3; ++c) EXPECT_EQ(p0.attributes[2].f[3 * i + c], float(p0.x[i][c]));
  }
  for (int s = 0; s < 20; ++s) {
    const Real dt = a->stable_dt(space);
    a->advance(space, dt);
    b->advance(space, dt);
    a->point_fields(names, space);  // b never computes stresses
  }
  const PointFields pa = a->point_fields(names, space), pb = b->point_fields({}, space);
  float largest = 0;
  for (std::size_t i = 0; i < pa.n; ++i) {
    for (int c = 0; c < 3; ++c) ASSERT_EQ(pa.x[i][c], pb.x[i][c]);
    largest = std::max(largest, pa.attributes[0].f[i]);
  }
  EXPECT_GT(largest, 1e3f);
}
