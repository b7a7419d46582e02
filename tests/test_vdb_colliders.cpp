// Sparse, lazily built collider fields (issue 30 items 1-3): mesh colliders as level sets built
// where the material reaches, .vdb level sets from files (static, keyframed, sequences), and
// deforming mesh sequences; contact, velocity, memory, determinism and resume.
#include <gtest/gtest.h>
#include <openvdb/openvdb.h>
#include <openvdb/tools/LevelSetSphere.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <utility>

#include "core/errors.hpp"
#include "core/geometry/level_set_collider.hpp"
#include "io/checkpoint.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "solvers/mpm_simulation.hpp"
#include "solvers/pd_simulation.hpp"

using namespace amalgam;
namespace fs = std::filesystem;

namespace {

// A folder per test and process (ctest -j2 runs tests side by side).
std::string temp_dir(const std::string& name) {
  const fs::path d =
      fs::temp_directory_path() / ("amalgam_vdbcol_" + name + "_" + std::to_string(::getpid()));
  fs::create_directories(d);
  return d.string();
}

void write_sphere_vdb(const std::string& path, double r, const Vec3d& c, double voxel,
                      bool with_velocity = false, double growth = 0, float half_width = 4) {
  openvdb::initialize();
  auto g = openvdb::tools::createLevelSetSphere<openvdb::FloatGrid>(
      float(r), openvdb::Vec3f(float(c[0]), float(c[1]), float(c[2])), float(voxel), half_width);
  g->setName("surface");
  openvdb::GridPtrVec grids{g};
  if (with_velocity) {  // radial growth velocity on the level set's active voxels
    auto v = openvdb::Vec3SGrid::create(openvdb::Vec3s(0.0f));
    v->setName("v");
    v->setTransform(g->transform().copy());
    auto acc = v->getAccessor();
    for (auto it = g->cbeginValueOn(); it; ++it) {
      const openvdb::Vec3d w = g->indexToWorld(it.getCoord());
      openvdb::Vec3d d = w - openvdb::Vec3d(c[0], c[1], c[2]);
      if (d.length() > 0) d.normalize();
      acc.setValue(it.getCoord(), openvdb::Vec3s(float(growth * d[0]), float(growth * d[1]),
                                                 float(growth * d[2])));
    }
    grids.push_back(v);
  }
  openvdb::io::File(path).write(grids);
}

void write_obj(const std::string& path, const TriangleMesh& m, double scale, const Vec3d& c) {
  std::ofstream f(path);
  f.precision(17);
  for (const auto& v : m.vertices)
    f << "v " << c[0] + scale * v[0] << " " << c[1] + scale * v[1] << " " << c[2] + scale * v[2]
      << "\n";
  for (const auto& t : m.triangles)
    f << "f " << t[0] + 1 << " " << t[1] + 1 << " " << t[2] + 1 << "\n";
}

std::string frame_name(const std::string& dir, const char* stem, int k, const char* ext) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%s_%04d.%s", stem, k, ext);
  return dir + "/" + buf;
}

std::vector<Vec3> positions(const MpmSolver& s) {
  const Vec3* x = s.particles().vec3(s.attributes().x);
  return std::vector<Vec3>(x, x + s.particles().size());
}

// A jelly ball dropped on a collider given as JSON, `steps` fixed substeps.
std::vector<Vec3> drop_ball(const std::string& collider, const std::string& dir, int steps,
                            const exec::Space& space) {
  const Scene s = parse_scene(R"({"simulation": {"dx": 0.02, "frames": 1, "max_dt": 0.001},
    "materials": {"a": {"density": 1000, "youngs_modulus": 3e4}},
    "objects": [{"shape": "sphere", "center": [0.5, 0.62, 0.5], "radius": 0.08, "material": "a"}],
    "colliders": [)" + collider + R"(]})",
                              dir + "/scene.json");
  MpmSolver solver = build_solver(s, space);
  for (int i = 0; i < steps; ++i) solver.step(space, Real(0.001));
  return positions(solver);
}

}  // namespace

// A .vdb sphere level set gives the contact of the analytic sphere collider: a jelly ball
// dropped on each ends within a cell of the other, particle by particle.
TEST(VdbCollider, SphereFromFileMatchesAnalyticSphere) {
  const std::string dir = temp_dir("sphere");
  write_sphere_vdb(dir + "/sphere.vdb", 0.2, Vec3d(0.5, 0.3, 0.5), 0.01);
  const exec::Space space(exec::Backend::OpenMP, 2);
  const auto a =
      drop_ball(R"({"type": "mesh", "file": "sphere.vdb", "boundary": "slip"})", dir, 200, space);
  const auto b = drop_ball(
      R"({"type": "sphere", "center": [0.5, 0.3, 0.5], "radius": 0.2, "boundary": "slip"})", dir,
      200, space);
  ASSERT_EQ(a.size(), b.size());
  double worst = 0, lowest = 1e9;
  for (size_t p = 0; p < a.size(); ++p) {
    worst = std::max(worst, double((a[p] - b[p]).norm()));
    lowest = std::min(lowest, double(a[p][1]));
  }
  EXPECT_LT(worst, 0.02);   // within dx
  EXPECT_GT(lowest, 0.45);  // landed on the sphere's top (0.5), not through it
  fs::remove_all(dir);
}

// The lazily built mesh level set: exact distance near a closed mesh, the right sign deep
// inside (far beyond the band), and built only where asked.
TEST(VdbCollider, MeshLevelSetSignFarInsideAndLazy) {
  const TriangleMesh sphere = unit_sphere_mesh(3);
  auto mesh = std::make_shared<TriangleMesh>(sphere);
  for (auto& v : mesh->vertices) v = v * 1.0 + Vec3d(0.5, 0.5, 0.5);  // radius 1 at (.5,.5,.5)
  Collider c;
  c.shape = ColliderShape::Mesh;
  c.field = make_mesh_field(mesh, 0.02);
  const exec::Space space(exec::Backend::Serial, 1);
  EXPECT_EQ(c.field->voxels(), 0u);
  c.prepare({Box3{Vec3d(0.4, 0.4, 0.4), Vec3d(0.6, 0.6, 0.6)}}, 0, space);  // the centre
  EXPECT_LT(double(c.phi(Vec3(0.5, 0.5, 0.5), 0)), -0.079);  // clamped at -band, negative
  EXPECT_LE(c.field->voxels(), size_t(4 * 4 * 4 * 512));
  c.prepare({Box3{Vec3d(1.4, 0.45, 0.45), Vec3d(1.6, 0.55, 0.55)}}, 0, space);  // the surface
  // Exact near the surface (the polyhedron's faces lie within 1.5 % of the radius inside it).
  EXPECT_NEAR(double(c.phi(Vec3(1.55, 0.5, 0.5), 0)), 0.05, 0.01);
  EXPECT_NEAR(double(c.phi(Vec3(1.45, 0.5, 0.5), 0)), -0.05, 0.01);
  EXPECT_GT(c.outward_normal(Vec3(1.5, 0.5, 0.5), 0).dot(Vec3::UnitX()), Real(0.95));
  c.prepare({Box3{Vec3d(3, 3, 3), Vec3d(3.1, 3.1, 3.1)}}, 0, space);  // far outside
  EXPECT_GT(double(c.phi(Vec3(3.05, 3.05, 3.05), 0)), 0.079);
}

// A 100 m x 100 m ground mesh under the default scene: the field holds only the blocks near the
// jelly (a few MB), not the ground's band (25e6 cells per voxel layer) or its box.
TEST(VdbCollider, HundredMetreGroundCostsWhatTheMaterialTouches) {
  const std::string dir = temp_dir("ground");
  {
    std::ofstream f(dir + "/ground.obj");
    f << "v -50 0.05 -50\nv 50 0.05 -50\nv 50 0.05 50\nv -50 0.05 50\nf 1 4 3 2\n";
  }
  std::ifstream in(std::string(AMALGAM_SOURCE_DIR) + "/scenes/jelly_drop.json");
  std::string text((std::istreambuf_iterator<char>(in)), {});
  const std::string floor =
      R"({ "type": "half_space", "point": [0, 0.05, 0], "normal": [0, 1, 0], "boundary": "separate", "friction": 0.4 })";
  const auto at = text.find(floor);
  ASSERT_NE(at, std::string::npos);
  text.replace(
      at, floor.size(),
      R"({ "type": "mesh", "file": "ground.obj", "allow_open": true, "boundary": "separate", "friction": 0.4 })");
  const Scene s = parse_scene(text, dir + "/scene.json");
  const exec::Space space(exec::Backend::OpenMP, 2);
  MpmSolver solver = build_solver(s, space);
  for (int i = 0; i < 20; ++i) solver.step(space, solver.stable_dt(space));
  // The ground is the first collider; the solver's copy shares its field.
  Collider ground = solver.colliders()[0];
  ASSERT_TRUE(ground.field);
  EXPECT_GT(ground.field->voxels(), 0u);
  EXPECT_LT(double(ground.field->bytes()), 5e6) << ground.field->voxels() << " voxels";
  // All the 1 m scene's material could ever reach: still a few MB, where a dense field over the
  // mesh's box (5000 x 5000 x 9 cells) took 7.6 GB.
  ground.prepare({Box3{Vec3d::Zero(), Vec3d::Ones()}}, 0, space);
  EXPECT_LT(double(ground.field->bytes()), 20e6) << ground.field->voxels() << " voxels";
  // Correct where built: below the ground negative, above positive, normal up.
  EXPECT_LT(double(ground.phi(Vec3(0.5, 0.03, 0.5), 0)), 0);
  EXPECT_NEAR(double(ground.phi(Vec3(0.5, 0.1, 0.5), 0)), 0.05, 1e-5);
  EXPECT_GT(ground.outward_normal(Vec3(0.5, 0.06, 0.5), 0)[1], Real(0.999));
  fs::remove_all(dir);
}

namespace {
// A sphere growing at `rate` m/s (radius 0.1 + rate t) about (0.5, 0.5, 0.5), as .vdb frames
// (kind "vdb", "vdb_v" with velocity grids) or OBJ frames ("obj"), 24 frames per second.
std::string growing_sphere(const std::string& dir, const std::string& kind, double rate, int n) {
  const TriangleMesh unit = unit_sphere_mesh(3);
  for (int k = 0; k <= n; ++k) {
    const double r = 0.1 + rate * k / 24.0;
    if (kind == "obj")
      write_obj(frame_name(dir, "grow", k, "obj"), unit, r, Vec3d(0.5, 0.5, 0.5));
    else
      // a band of 8 voxels: wider than a frame's growth (5 voxels), or phi_1 - phi_0 is clipped
      write_sphere_vdb(frame_name(dir, "grow", k, "vdb"), r, Vec3d(0.5, 0.5, 0.5), 0.01,
                       kind == "vdb_v", rate, 8.0f);
  }
  return kind == "obj" ? "grow_%04d.obj" : "grow_%04d.vdb";
}
Scene growing_scene(const std::string& dir, const std::string& pattern, int frames) {
  // A shell of jelly around the sphere, no gravity: the sphere pushes it outward.
  return parse_scene(R"({"simulation": {"dx": 0.02, "frames": )" + std::to_string(frames) +
                         R"(, "fps": 24, "max_dt": 0.001, "gravity": [0, 0, 0]},
    "materials": {"a": {"density": 1000, "youngs_modulus": 1e3}},
    "objects": [{"shape": "box", "min": [0.44, 0.62, 0.44], "max": [0.56, 0.70, 0.56], "material": "a"}],
    "colliders": [{"type": "mesh", "file": ")" +
                         pattern + R"(", "boundary": "sticky"}]})",
                     dir + "/scene.json");
}
}  // namespace

// A growing sphere as a sequence: the collider's surface velocity is the growth rate, in the
// middle of a frame interval, whether it comes from a `v` grid, from phi's time derivative or
// from the meshes' vertex motion; and material touching it (sticky, so it is not thrown ahead
// as an elastic block hit by a wall would be) moves outward at that speed on the surface.
class GrowingSphere : public ::testing::TestWithParam<std::string> {};

TEST_P(GrowingSphere, PushesMaterialOutwardAtTheSurfaceSpeed) {
  const std::string dir = temp_dir("grow_" + GetParam());
  const double rate = 1.2;  // m/s: 0.05 m per frame
  const std::string pattern = growing_sphere(dir, GetParam(), rate, 10);
  const Scene s = growing_scene(dir, pattern, 8);
  const exec::Space space(exec::Backend::OpenMP, 2);
  MpmSolver solver = build_solver(s, space);
  // The field at t = 2.5 frames: the interpolated surface at radius 0.1 + rate t.
  {
    Collider c = solver.colliders()[0];
    const Real t = Real(2.5 / 24);
    c.prepare({Box3{Vec3d(0.3, 0.3, 0.3), Vec3d(0.8, 0.8, 0.8)}}, t, space);
    const double r = 0.1 + rate * double(t);
    const Vec3 dir_x = Vec3(1, 1, 0).normalized();
    EXPECT_NEAR(double(c.phi(Vec3(0.5, 0.5, 0.5) + Real(r) * dir_x, t)), 0.0, 0.004);
    const Vec3 v = c.velocity_at(Vec3(0.5, 0.5, 0.5) + Real(r) * dir_x, t);
    EXPECT_NEAR(double(v.dot(dir_x)), rate, 0.06 * rate);
    EXPECT_LT(double((v - v.dot(dir_x) * dir_x).norm()), 0.06 * rate);
  }
  // The jelly (bottom at y = 0.62) is reached at about t = 0.017 / 1.2 and carried up.
  const double t_end = 6.0 / 24;
  while (solver.time() < t_end - 1e-9) solver.step(space, Real(0.001));
  const auto x = positions(solver);
  const auto& ps = solver.particles();
  const Vec3* v = ps.vec3(solver.attributes().v);
  const double r_end = 0.1 + rate * solver.time();
  double lowest = 1e9, vy = 0;
  std::vector<std::pair<double, double>> axis;  // (distance from the centre, vy) near the axis
  for (size_t p = 0; p < x.size(); ++p) {
    const double d = double((x[p] - Vec3(0.5, 0.5, 0.5)).norm());
    lowest = std::min(lowest, d);
    if (std::abs(double(x[p][0]) - 0.5) < 0.03 && std::abs(double(x[p][2]) - 0.5) < 0.03)
      axis.emplace_back(d, double(v[p][1]));
  }
  EXPECT_GT(lowest, r_end - 0.02);  // nothing left inside the interpolated surface
  ASSERT_GE(axis.size(), 20u);
  std::sort(axis.begin(), axis.end());  // the 20 lowest near the top: those on the surface
  for (int i = 0; i < 20; ++i) vy += axis[size_t(i)].second;
  const int touching = 20;
  EXPECT_LT(axis[0].first, r_end + 0.02) << "the jelly left the surface";
  EXPECT_NEAR(vy / touching, rate, 0.15 * rate);  // carried at the surface speed
  fs::remove_all(dir);
}
INSTANTIATE_TEST_SUITE_P(Sources, GrowingSphere, ::testing::Values("vdb", "vdb_v", "obj"));

// A deforming mesh sequence and a keyframed .vdb: identical bits on serial, OpenMP and TBB at 1
// and 2 threads, and a checkpoint resume mid-run equals the uninterrupted run.
TEST(VdbCollider, SequenceBitwiseAcrossBackendsAndResume) {
  const std::string dir = temp_dir("bitwise");
  const std::string pattern = growing_sphere(dir, "obj", 1.2, 4);
  write_sphere_vdb(dir + "/ball.vdb", 0.05, Vec3d(0, 0, 0), 0.01);
  const Scene s =
      parse_scene(R"({"simulation": {"dx": 0.02, "frames": 3, "fps": 24, "max_dt": 0.001},
    "materials": {"a": {"density": 1000, "youngs_modulus": 1e3}},
    "objects": [{"shape": "box", "min": [0.42, 0.62, 0.42], "max": [0.58, 0.70, 0.58], "material": "a"}],
    "colliders": [{"type": "mesh", "file": ")" +
                      pattern + R"(", "boundary": "sticky"},
      {"type": "mesh", "file": "ball.vdb", "boundary": "separate", "friction": 0.3,
       "keyframes": [{"time": 0, "translate": [0.3, 0.75, 0.5]}, {"time": 0.1, "translate": [0.6, 0.7, 0.5]}]}]})",
                  dir + "/scene.json");
  auto run = [&](exec::Backend b, int threads, int steps) {
    const exec::Space space(b, threads);
    MpmSolver solver = build_solver(s, space);
    for (int i = 0; i < steps; ++i) {
      // Step 30 starts a frame (MpmSimulation::begin_frame unprimes: a re-sort there), where the
      // checkpoint below is taken: the run re-sorting only when needed sorts there either way.
      if (i == 30) solver.unprime();
      solver.step(space, Real(0.001));
    }
    return positions(solver);
  };
  const auto ref = run(exec::Backend::Serial, 1, 60);
  for (const auto& [b, th] : std::vector<std::pair<exec::Backend, int>>{
           {exec::Backend::OpenMP, 1}, {exec::Backend::OpenMP, 2}, {exec::Backend::TBB, 2}}) {
    const auto x = run(b, th, 60);
    ASSERT_EQ(x.size(), ref.size());
    EXPECT_EQ(std::memcmp(x.data(), ref.data(), x.size() * sizeof(Vec3)), 0)
        << "backend " << int(b) << " threads " << th;
  }
  // Resume at step 30 (frames 0-1 built) into a fresh solver whose fields are empty, across
  // the frame change at step 42: the same bits at step 60.
  const exec::Space space(exec::Backend::OpenMP, 2);
  MpmSimulation a(build_solver(s, space)), b(build_solver(s, space));
  for (int i = 0; i < 30; ++i) a.solver().step(space, Real(0.001));
  const std::string ck = dir + "/mid.amck";
  write_checkpoint(ck, a, 1, s.fingerprint);
  read_checkpoint(ck, b, s.fingerprint);
  for (int i = 0; i < 30; ++i) b.solver().step(space, Real(0.001));
  const auto x = positions(b.solver());
  ASSERT_EQ(x.size(), ref.size());
  EXPECT_EQ(std::memcmp(x.data(), ref.data(), x.size() * sizeof(Vec3)), 0);
  fs::remove_all(dir);
}

// Bad input, named by file and key before anything runs: a hostile .vdb, a missing frame.
TEST(VdbCollider, CorruptVdbAndMissingFrameAreInputErrors) {
  const std::string dir = temp_dir("bad");
  {
    std::ofstream f(dir + "/junk.vdb", std::ios::binary);
    f << "\x20\x42\x44\x56" << std::string(64, '\xff') << "not a vdb";
  }
  auto error = [&](const std::string& file) {
    try {
      parse_scene(R"({"simulation": {"dx": 0.02, "frames": 2},
        "materials": {"a": {"density": 1000, "youngs_modulus": 1e3}},
        "objects": [{"shape": "box", "min": [0.4, 0.6, 0.4], "max": [0.6, 0.7, 0.6], "material": "a"}],
        "colliders": [{"type": "mesh", "file": ")" +
                      file + R"("}]})",
                  dir + "/scene.json");
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  EXPECT_NE(error("junk.vdb").find("/colliders/0/file: \"junk.vdb\": cannot read it as a .vdb"),
            std::string::npos)
      << error("junk.vdb");
  growing_sphere(dir, "vdb", 1.0, 2);  // frames 0-2; 2 frames at 24 fps need 0-2
  EXPECT_EQ(error("grow_%04d.vdb"), "");
  fs::remove(frame_name(dir, "grow", 1, "vdb"));
  EXPECT_NE(error("grow_%04d.vdb")
                .find("/colliders/0/file: frame 1 of the sequence, "
                      "\"grow_0001.vdb\", does not exist"),
            std::string::npos)
      << error("grow_%04d.vdb");
  fs::remove_all(dir);
}

// Peridynamics takes field colliders too: a plate pressed by a keyframed .vdb ball ends within a
// cell of the same plate pressed by the analytic sphere moving at the same speed.
TEST(VdbCollider, PeridynamicsPressWithVdbBallMatchesAnalytic) {
  const std::string dir = temp_dir("pd");
  write_sphere_vdb(dir + "/ball.vdb", 0.05, Vec3d(0, 0, 0), 0.005);
  auto run = [&](const std::string& collider) {
    const Scene s = parse_scene(
        R"({"simulation": {"method": "peridynamics", "dx": 0.01, "fps": 400, "frames": 1,
      "gravity": [0, 0, 0]},
      "materials": {"p": {"model": "peridynamic", "density": 1000, "bulk_modulus": 1e6, "shear_modulus": 6e5}},
      "objects": [{"shape": "box", "min": [0, 0, 0], "max": [0.2, 0.03, 0.2], "material": "p"}],
      "boundary_conditions": [{"min": [-1, -1, -1], "max": [0.012, 1, 1]}, {"min": [0.188, -1, -1], "max": [1, 1, 1]}],
      "colliders": [)" +
            collider + R"(]})",
        dir + "/scene.json");
    const exec::Space space(exec::Backend::OpenMP, 2);
    auto sim = make_simulation(s, space);
    for (int i = 0; i < 200; ++i) sim->advance(space, Real(1e-4));
    const auto& pd = dynamic_cast<PdSimulation&>(*sim).solver();
    const Vec3* x = pd.particles().vec3(pd.attributes().x);
    const Vec3* x0 = pd.particles().vec3(pd.attributes().x0);
    double pressed = 0;  // the deepest a particle was pushed down
    for (size_t p = 0; p < pd.particles().size(); ++p)
      pressed = std::max(pressed, double(x0[p][1] - x[p][1]));
    return std::make_pair(std::vector<Vec3>(x, x + pd.particles().size()), pressed);
  };
  // The ball's bottom starts at 0.028, in the plate's top layer, and moves down at 0.4 m/s.
  const auto [a, pressed_a] = run(R"({"type": "mesh", "file": "ball.vdb", "boundary": "slip",
    "keyframes": [{"time": 0, "translate": [0.1, 0.078, 0.1]}, {"time": 1, "translate": [0.1, -0.322, 0.1]}]})");
  const auto [b, pressed_b] = run(
      R"({"type": "sphere", "center": [0.1, 0.078, 0.1], "radius": 0.05, "velocity": [0, -0.4, 0], "boundary": "slip"})");
  ASSERT_EQ(a.size(), b.size());
  double worst = 0;
  for (size_t p = 0; p < a.size(); ++p) worst = std::max(worst, double((a[p] - b[p]).norm()));
  EXPECT_GT(pressed_b, 5e-4);  // the ball did press the plate
  EXPECT_NEAR(pressed_a, pressed_b, 0.25 * pressed_b);
  EXPECT_LT(worst, 0.01);
  fs::remove_all(dir);
}
