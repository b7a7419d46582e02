// Scene validation: every bad input gets an InputError naming the file and the JSON path.
#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <fstream>

#include "core/errors.hpp"
#include "io/mesh.hpp"
#include "io/tetmesh.hpp"
#include "io/scene.hpp"
#include "kernels/mpm_transfers.hpp"
#include "solvers/estimate.hpp"
#include "solvers/factory.hpp"

using namespace amalgam;

namespace {
const std::string kGood = R"({
  "simulation": {"dx": 0.05, "frames": 2},
  "materials": {"jelly": {"density": 1000, "youngs_modulus": 1e4}},
  "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "jelly"}]
})";

std::string error_of(const std::string& text) {
  try {
    parse_scene(text, "s.json");
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}
std::string replace(std::string s, const std::string& a, const std::string& b) {
  const auto p = s.find(a);
  EXPECT_NE(p, std::string::npos) << a;
  return s.replace(p, a.size(), b);
}
}  // namespace

TEST(Scene, GoodSceneParsesWithDefaults) {
  const Scene s = parse_scene(kGood, "s.json");
  EXPECT_EQ(s.frames, 2);
  EXPECT_EQ(s.mpm.transfer, Transfer::Mls);
  EXPECT_EQ(s.mpm.order, 2);
  ASSERT_EQ(s.objects.size(), 1u);
  Real vol = 0;
  const auto x = sample_object(s.objects[0], s.mpm.dx, vol);
  // 0.2^3 box, dx 0.05, 8 per cell: 4^3 cells * 8 = 512 particles of volume (dx/2)^3.
  EXPECT_EQ(x.size(), 512u);
  EXPECT_NEAR(double(vol), 0.025 * 0.025 * 0.025, 1e-9);
  // Reproducible: same seed, same particles.
  const auto y = sample_object(s.objects[0], s.mpm.dx, vol);
  EXPECT_EQ(std::memcmp(x.data(), y.data(), x.size() * sizeof(Vec3)), 0);
}

// Objects refer to materials by name; each gets its own material's index and parameters, in MPM
// and peridynamics scenes alike (a regression once gave every object material 0).
TEST(Scene, ObjectsGetTheirNamedMaterials) {
  for (const char* method : {"mpm", "peridynamics"}) {
    const std::string model = std::string(method) == "mpm" ? "fixed_corotated" : "peridynamic";
    const std::string text = std::string(R"({
      "simulation": {"method": ")") +
                             method + R"(", "dx": 0.05},
      "materials": {"soft": {"model": ")" +
                             model + R"(", "density": 1000, "youngs_modulus": 1e4},
                    "hard": {"model": ")" +
                             model + R"(", "density": 3000, "youngs_modulus": 1e7}},
      "objects": [{"shape": "box", "min": [0,0,0], "max": [0.2,0.2,0.2], "material": "hard"},
                  {"shape": "box", "min": [0.5,0,0], "max": [0.7,0.2,0.2], "material": "soft"},
                  {"shape": "box", "min": [1,0,0], "max": [1.2,0.2,0.2], "material": "hard"}]
    })";
    const Scene s = parse_scene(text, "s.json");
    ASSERT_EQ(s.objects.size(), 3u) << method;
    for (int k = 0; k < 3; ++k) {
      const int m = s.objects[std::size_t(k)].material;
      EXPECT_EQ(s.material_names[std::size_t(m)], k == 1 ? "soft" : "hard")
          << method << " object " << k;
      EXPECT_EQ(double(s.materials[std::size_t(m)].density), k == 1 ? 1000.0 : 3000.0) << method;
    }
    if (std::string(method) == "peridynamics") {
      ASSERT_EQ(s.pd_materials.size(), 2u);
      EXPECT_EQ(double(s.pd_materials[std::size_t(s.objects[0].material)].density), 3000.0);
      PdSolver solver = build_pd_solver(s);
      const std::int32_t* mat = solver.particles().int32(solver.attributes().material);
      EXPECT_EQ(mat[0], s.objects[0].material);
      EXPECT_EQ(mat[solver.particles().size() - 1], s.objects[2].material);
      EXPECT_NE(s.objects[0].material, s.objects[1].material);
    }
  }
}

TEST(Scene, ErrorsNameFileAndPath) {
  EXPECT_NE(error_of(replace(kGood, "\"jelly\"}", "\"steel\"}"))
                .find("s.json: /objects/0/material: unknown material \"steel\""),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "\"frames\": 2", "\"frames\": 2, \"max_dt\": -1"))
                .find("s.json: /simulation/max_dt"),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "\"dx\": 0.05", "\"dx\": 0.05, \"gravty\": [0,0,0]"))
                .find("/simulation/gravty: unknown key"),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "\"dx\": 0.05", "\"dx\": \"small\""))
                .find("/simulation/dx: expected a number"),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "1e4", "-5")).find("/materials/jelly/youngs_modulus"),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "\"box\"", "\"cone\""))
                .find("/objects/0/shape: unknown value \"cone\""),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "[0.6,0.6,0.6]", "[0.6,0.3,0.6]")).find("/objects/0/max"),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "}]\n}",
                             "}], \"colliders\": [{\"type\": \"half_space\", \"point\": [0,0,0], "
                             "\"normal\": [0,0,0]}]\n}"))
                .find("/colliders/0/normal: must be a non-zero vector"),
            std::string::npos);
  EXPECT_NE(error_of(replace(kGood, "[0.4,0.4,0.4]", "[0.4,1e999,0.4]")).find("s.json"),
            std::string::npos);
  EXPECT_NE(error_of("{ not json").find("s.json: not valid JSON"), std::string::npos);
  EXPECT_NE(error_of(R"({"materials": {}})").find("s.json: /simulation: missing"),
            std::string::npos);
}

TEST(Scene, MissingFileIsInputError) {
  try {
    load_scene("/nonexistent/scene.json");
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/scene.json: cannot open"),
              std::string::npos);
  }
}

TEST(Scene, ShippedScenesValidate) {
  for (const char* f : {"jelly_drop.json"}) {
    const Scene s = load_scene(std::string(AMALGAM_SOURCE_DIR) + "/scenes/" + f);
    EXPECT_FALSE(s.objects.empty()) << f;
  }
}

TEST(Solver, NegativeOrNanTimeStepIsRejected) {
  MpmSolver s = build_solver(parse_scene(kGood, "s.json"));
  const exec::Space space;
  EXPECT_THROW(s.step(space, Real(-1e-3)), SimulationError);
  EXPECT_THROW(s.step(space, std::numeric_limits<Real>::quiet_NaN()), SimulationError);
}

TEST(Solver, StabilityGuardNamesParticleAndQuantity) {
  MpmSolver s = build_solver(parse_scene(kGood, "s.json"));
  s.particles().vec3(s.attributes().v)[123] = Vec3(0, std::numeric_limits<Real>::infinity(), 0);
  try {
    s.stable_dt(exec::Space());
    FAIL();
  } catch (const SimulationError& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("particle 123"), std::string::npos) << m;
    EXPECT_NE(m.find("non-finite velocity"), std::string::npos) << m;
  }
}

// Every scene in tests/data/malformed is rejected with exactly the message in its .expected file
// (or starting with its .expected_prefix), the file named relative to that folder.
TEST(Scene, MalformedScenesGiveExactMessages) {
  namespace fs = std::filesystem;
  const fs::path dir = fs::path(AMALGAM_SOURCE_DIR) / "tests" / "data" / "malformed";
  int count = 0;
  for (const auto& entry : fs::directory_iterator(dir)) {
    if (entry.path().extension() != ".json") continue;
    ++count;
    std::string message;
    try {
      load_scene(entry.path().string());
    } catch (const InputError& e) {
      message = e.what();
    }
    const std::string prefix = dir.string() + "/";
    ASSERT_EQ(message.rfind(prefix, 0), 0u) << entry.path() << " gave: " << message;
    message = message.substr(prefix.size());
    fs::path exact = entry.path(), start = entry.path();
    exact.replace_extension(".expected");
    start.replace_extension(".expected_prefix");
    auto read = [](const fs::path& p) {
      std::ifstream in(p);
      return std::string(std::istreambuf_iterator<char>(in), {});
    };
    if (fs::exists(exact))
      EXPECT_EQ(message, read(exact)) << entry.path();
    else
      EXPECT_EQ(message.rfind(read(start), 0), 0u) << entry.path() << " gave: " << message;
  }
  EXPECT_GE(count, 20);
}

TEST(Scene, PrimitiveVolumesMatchClosedForms) {
  const std::string text = R"({
    "simulation": {"dx": 0.02, "frames": 1},
    "materials": {"m": {"density": 1000, "youngs_modulus": 1e4}},
    "objects": [
      {"shape": "cylinder", "center": [0.5,0.5,0.5], "radius": 0.2, "height": 0.3, "axis": "z", "material": "m"},
      {"shape": "torus", "center": [0.5,0.5,0.5], "major_radius": 0.25, "minor_radius": 0.08, "material": "m"},
      {"shape": "sphere", "center": [0.5,0.5,0.5], "radius": 0.2, "material": "m"}]
  })";
  const Scene s = parse_scene(text, "p.json");
  const double expected[3] = {M_PI * 0.04 * 0.3, 2 * M_PI * M_PI * 0.25 * 0.08 * 0.08,
                              4.0 / 3.0 * M_PI * 0.008};
  for (int i = 0; i < 3; ++i) {
    Real vol = 0;
    const auto x = sample_object(s.objects[size_t(i)], s.mpm.dx, vol);
    EXPECT_NEAR(double(x.size()) * double(vol) / expected[i], 1.0, 0.02) << "object " << i;
  }
  // Torus particles all lie inside the tube.
  Real vol = 0;
  for (const Vec3& p : sample_object(s.objects[1], s.mpm.dx, vol)) {
    const Vec3d d = p.cast<double>() - Vec3d(0.5, 0.5, 0.5);
    const double ring = std::hypot(d[0], d[2]) - 0.25;
    EXPECT_LE(ring * ring + d[1] * d[1], 0.08 * 0.08 * 1.2);
  }
}

TEST(Scene, MeshScaleRotateTranslate) {
  const std::string off =
      (std::filesystem::temp_directory_path() / "amalgam_test_unit_cube.off").string();
  std::ofstream(off) << "OFF\n8 6 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n1 0 1\n1 1 1\n0 1 1\n"
                        "4 0 3 2 1\n4 4 5 6 7\n4 0 1 5 4\n4 2 3 7 6\n4 1 2 6 5\n4 0 4 7 3\n";
  const Scene s = parse_scene(R"({
    "simulation": {"dx": 0.02, "frames": 1},
    "materials": {"m": {"density": 1000, "youngs_modulus": 1e4}},
    "objects": [{"shape": "mesh", "file": ")" +
                                  off + R"(", "scale": 0.2, "rotate_degrees": [0, 0, 45],
                 "translate": [0.5, 0.5, 0.5], "material": "m"}]
  })",
                              "m.json");
  const ObjectSpec& o = s.objects[0];
  EXPECT_NEAR(enclosed_volume(*o.mesh), 0.008, 1e-12);
  EXPECT_NEAR(double(o.max[0] - o.min[0]), 0.2 * std::sqrt(2.0), 1e-6);  // 45 degrees about z
  EXPECT_NEAR(double(o.max[2] - o.min[2]), 0.2, 1e-6);
  Real vol = 0;
  const auto x = sample_object(o, s.mpm.dx, vol);
  EXPECT_NEAR(double(x.size()) * double(vol) / 0.008, 1.0, 0.03);
}

// TetGen meshes: a grid of cubes, each split into 6 tetrahedra around its main diagonal, written
// in TetGen's format (1-based, comments, boundary markers) and read back; the peridynamics scene
// puts one particle per tetrahedron with its volume, and takes the mean edge as the spacing.
namespace {
std::string write_cube_tets(const std::string& stem, int n, double h) {
  std::ofstream node(stem + ".node"), ele(stem + ".ele");
  const int m = n + 1;
  node << "# cube grid\n" << m * m * m << " 3 0 1\n";
  auto id = [m](int i, int j, int k) { return 1 + (i * m + j) * m + k; };
  for (int i = 0; i < m; ++i)
    for (int j = 0; j < m; ++j)
      for (int k = 0; k < m; ++k)
        node << id(i, j, k) << " " << i * h << " " << j * h << " " << k * h << " 0\n";
  ele << 6 * n * n * n << "  4  0\n";
  int t = 1;
  const int perm[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      for (int k = 0; k < n; ++k)
        for (const auto& p : perm) {  // path 000 -> e_p0 -> e_p0 + e_p1 -> 111
          int c[3] = {i, j, k};
          const int a = id(c[0], c[1], c[2]);
          c[p[0]]++;
          const int b = id(c[0], c[1], c[2]);
          c[p[1]]++;
          const int d = id(c[0], c[1], c[2]);
          ele << t++ << " " << a << " " << b << " " << d << " " << id(i + 1, j + 1, k + 1)
              << "  # tet\n";
        }
  return stem;
}
}  // namespace

TEST(TetMesh, ReadsTetgenFilesAndSamplesBarycentres) {
  const std::string dir = ::testing::TempDir();
  const std::string stem = write_cube_tets(dir + "/cubes", 4, 0.01);
  const TetMesh m = load_tetgen(stem + ".node");
  EXPECT_EQ(m.nodes.size(), 125u);
  ASSERT_EQ(m.tets.size(), 384u);
  std::vector<Vec3> x;
  std::vector<Real> vol;
  tet_barycentres(m, x, vol);
  double sum = 0;
  for (Real v : vol) sum += double(v);
  EXPECT_NEAR(sum, 0.04 * 0.04 * 0.04, 1e-12);
  EXPECT_NEAR(tet_mean_edge(m), 0.01 * (3 + 2 * std::sqrt(2.0) + std::sqrt(3.0)) / 6, 1e-9);

  const std::string text = R"({
    "simulation": {"method": "peridynamics", "dx": 0.01, "peridynamics": {"horizon_factor": 2.5}},
    "materials": {"m": {"model": "peridynamic", "density": 1000, "youngs_modulus": 1e6}},
    "objects": [{"shape": "tet_mesh", "file": ")" +
                           stem + R"(.ele", "translate": [1, 0, 0], "material": "m"}]
  })";
  const Scene s = parse_scene(text, "s.json");
  EXPECT_NEAR(double(s.pd.spacing), tet_mean_edge(m), 1e-6);
  EXPECT_NEAR(double(s.pd.horizon), 2.5 * tet_mean_edge(m), 1e-6);
  PdSolver solver = build_pd_solver(s);
  ASSERT_EQ(solver.particles().size(), 384u);
  const Real* v = solver.particles().real(solver.attributes().volume);
  const Vec3* px = solver.particles().vec3(solver.attributes().x);
  double vs = 0;
  for (std::size_t i = 0; i < 384; ++i) vs += double(v[i]);
  EXPECT_NEAR(vs, 0.04 * 0.04 * 0.04, 1e-9);
  EXPECT_NEAR(double(px[0][0]), 1.0 + double(x[0][0]), 1e-6);  // translated
  solver.initialize(exec::Space());
  EXPECT_GT(solver.bonds().size(), 384u * 20);
}

TEST(TetMesh, BadFilesNameFileAndLine) {
  const std::string dir = ::testing::TempDir();
  const std::string stem = write_cube_tets(dir + "/bad", 1, 0.01);
  {
    std::ofstream ele(stem + ".ele");
    ele << "1 4 0\n1 1 2 3 99\n";
  }
  try {
    load_tetgen(stem);
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find(
                  "bad.ele:2: node 99 does not exist (the .node file numbers 1..8)"),
              std::string::npos)
        << e.what();
  }
  {
    std::ofstream ele(stem + ".ele");
    ele << "1 4 0\n1 1 2 3 4\n";  // the 4 nodes of a cube face: flat
  }
  try {
    load_tetgen(stem);
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("bad.ele:2: tetrahedron 1 has zero volume"),
              std::string::npos)
        << e.what();
  }
  EXPECT_THROW(load_tetgen(dir + "/missing"), InputError);
  const std::string mpm = R"({
    "simulation": {"dx": 0.01},
    "materials": {"m": {"density": 1000, "youngs_modulus": 1e6}},
    "objects": [{"shape": "tet_mesh", "file": ")" +
                          stem + R"(", "material": "m"}]
  })";
  EXPECT_NE(error_of(mpm).find("/objects/0/shape: \"tet_mesh\" needs \"method\": \"peridynamics\""),
            std::string::npos)
      << error_of(mpm);
}

// Initial velocity and displacement as expressions of the position (issue 27): each particle
// gets v = f(X), C = grad f, x = X + u(X) (with its low part) and F = I + grad u; peridynamics
// keeps X as the reference. Bad expressions name the file, the path and the component.
TEST(Scene, VelocityAndDisplacementExpressions) {
  const std::string text =
      replace(kGood, "\"material\": \"jelly\"}",
              "\"material\": \"jelly\", \"velocity\": [\"0\", 2, \"1e-3*cos(pi*x/0.1)\"], "
              "\"displacement\": [\"1e-4*y\", 0, 0]}");
  MpmSolver s = build_solver(parse_scene(text, "s.json"));
  const ParticleSet& ps = s.particles();
  const MpmAttributes& a = s.attributes();
  ASSERT_GT(ps.size(), 0u);
  for (std::size_t p = 0; p < ps.size(); ++p) {
    const Vec3d x = ps.vec3(a.x)[p].cast<double>() + ps.vec3(a.x_lo)[p].cast<double>();
    const double X = x[0] - 1e-4 * x[1];  // u depends on y only, which is not displaced
    EXPECT_NEAR(ps.vec3(a.v)[p][2], 1e-3 * std::cos(M_PI * X / 0.1), 1e-9);
    EXPECT_EQ(ps.vec3(a.v)[p][1], Real(2));
    EXPECT_NEAR(ps.mat3(a.C)[p](2, 0), -1e-3 * M_PI / 0.1 * std::sin(M_PI * X / 0.1), 1e-6);
    // F = I + grad u, kept as b - I = F F^T - I (MpmSolver::keeps_b): (0, 1) 1e-4, (0, 0) 1e-8.
    ASSERT_GE(a.b, 0);
    EXPECT_NEAR(ps.sym_dev(a.b)[p].e[3], 1e-4, 1e-9);
    EXPECT_NEAR(ps.sym_dev(a.b)[p].e[0], 1e-8, 1e-11);
  }
  const std::string pd = R"({
  "simulation": {"method": "peridynamics", "dx": 0.05, "frames": 2},
  "materials": {"glass": {"model": "peridynamic", "density": 2200, "youngs_modulus": 1e9}},
  "objects": [{"shape": "box", "min": [0,0,0], "max": [0.3,0.2,0.2], "material": "glass",
               "velocity": ["x", 0, 0], "displacement": ["1e-3*x", 0, 0]}]
})";
  PdSolver q = build_pd_solver(parse_scene(pd, "pd.json"), exec::Space());
  const Vec3* x = q.particles().vec3(q.attributes().x);
  const Vec3* x0 = q.particles().vec3(q.attributes().x0);
  const Vec3* v = q.particles().vec3(q.attributes().v);
  for (std::size_t p = 0; p < q.particles().size(); ++p) {
    EXPECT_FLOAT_EQ(x[p][0], x0[p][0] * Real(1.001));
    EXPECT_FLOAT_EQ(v[p][0], x0[p][0]);
  }
  const auto bad = [&](const std::string& value) {
    return error_of(replace(kGood, "\"material\": \"jelly\"}",
                            "\"material\": \"jelly\", \"velocity\": " + value + "}"));
  };
  const std::string unknown = bad("[\"0\", \"sinx(1)\", 0]"), timed = bad("[\"0\", \"0\", \"t\"]"),
                    nested = bad("[\"0\", [1], 0]"), short2 = bad("[\"0\", \"0\"]");
  EXPECT_NE(unknown.find("s.json: /objects/0/velocity/1: expression"), std::string::npos)
      << unknown;
  EXPECT_NE(timed.find("/objects/0/velocity/2: an initial value cannot"), std::string::npos);
  EXPECT_NE(nested.find("/objects/0/velocity/1: expected a number or"), std::string::npos);
  EXPECT_NE(short2.find("/objects/0/velocity: expected an array of 3"), std::string::npos);
  // A value that is not finite on some particle is refused at set-up, naming where.
  try {
    build_solver(
        parse_scene(replace(kGood, "\"material\": \"jelly\"}",
                            "\"material\": \"jelly\", \"velocity\": [\"log(x-0.5)\", 0, 0]}"),
                    "s.json"));
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("s.json: /objects/0/velocity/0: \"log(x-0.5)\" gives"),
              std::string::npos)
        << e.what();
  }
}

// A distributed set-up samples each object in slices, one per rank (solvers/factory.cpp): the
// slices of 1..5 parts in turn are the whole sample, point for point, for every shape (lattice
// shapes, a mesh through its level set, a tet mesh's barycentres).
TEST(Scene, ObjectSlicesInTurnAreTheWholeSample) {
  std::vector<std::pair<Scene, std::size_t>> objects;
  const Scene shapes = parse_scene(R"({
    "simulation": {"dx": 0.05},
    "materials": {"m": {"density": 1000, "youngs_modulus": 1e4, "poisson_ratio": 0.3}},
    "objects": [
      {"shape": "box", "min": [0, 0, 0], "max": [0.3, 0.2, 0.25], "material": "m"},
      {"shape": "sphere", "center": [0.5, 0.5, 0.5], "radius": 0.17, "material": "m"},
      {"shape": "cylinder", "center": [0.5, 0.5, 0.5], "radius": 0.1, "height": 0.3, "axis": "x",
       "material": "m"},
      {"shape": "torus", "center": [0.5, 0.5, 0.5], "major_radius": 0.2, "minor_radius": 0.06,
       "material": "m"}
    ]})",
                                   "shapes.json");
  for (std::size_t k = 0; k < shapes.objects.size(); ++k) objects.push_back({shapes, k});
  for (const char* f : {"/tests/data/domain_restart.json", "/tests/data/pd_tet_restart.json"})
    objects.push_back({load_scene(std::string(AMALGAM_SOURCE_DIR) + f), 0});
  for (const auto& [s, k] : objects) {
    Real vol = 0;
    const std::vector<Vec3> whole = sample_object(s.objects[k], s.mpm.dx, vol);
    ASSERT_GT(whole.size(), 20u) << s.file << " object " << k;
    for (int parts = 1; parts <= 5; ++parts) {
      std::vector<Vec3> joined;
      std::size_t nonempty = 0;
      for (int part = 0; part < parts; ++part) {
        Real v = 0;
        const std::vector<Vec3> x =
            sample_object(s.objects[k], s.mpm.dx, v, exec::Space(), LatticeSlice{part, parts});
        EXPECT_EQ(v, vol);
        nonempty += !x.empty();
        joined.insert(joined.end(), x.begin(), x.end());
      }
      ASSERT_EQ(joined.size(), whole.size()) << s.file << " object " << k << ", " << parts;
      EXPECT_EQ(std::memcmp(joined.data(), whole.data(), whole.size() * sizeof(Vec3)), 0)
          << s.file << " object " << k << ", " << parts << " parts";
      EXPECT_GE(nonempty, std::size_t(std::min(parts, 2))) << "one part holds everything";
    }
  }
}

// The memory estimate counts P2G's blocks kept between substeps, one per bin, and the leaves the
// dilated blocks reach: a box from 0.3 to 0.55 at dx = 0.05 (leaves of 0.4) lies in 2 x 2 x 2
// leaves, so 8 bins; the grid has the 3^3 leaves their stencils reach, 4^3 with the dilated
// blocks (one more on the - side).
namespace {
Scene block_scene(const char* sort, const char* pass) {
  return parse_scene(std::string(R"({
  "simulation": {"dx": 0.05, "frames": 2, "sort": ")") +
                         sort + R"(", "transfer_pass": ")" + pass + R"("},
  "materials": {"jelly": {"density": 1000, "youngs_modulus": 1e4}},
  "objects": [{"shape": "box", "min": [0.3,0.3,0.3], "max": [0.55,0.55,0.55], "material": "jelly"}]
})",
                     "blocks.json");
}
}  // namespace

TEST(EstimateBlocks, WhenNeededAddsTheDilatedBlocks) {
  const RunEstimate every = estimate_run(block_scene("every_substep", "two_pass"));
  const RunEstimate lazy = estimate_run(block_scene("when_needed", "two_pass"));
  EXPECT_EQ(every.bins, 8);
  EXPECT_EQ(lazy.bins, 8);
  const double real = double(sizeof(Real));
  // MLS: 4 lanes; the plain (8 + 2)^3-node blocks, the dilated (10 + 2)^3-node ones.
  EXPECT_EQ(every.block_bytes, 8 * 1000 * 4 * real);
  EXPECT_EQ(lazy.block_bytes, 8 * 1728 * 4 * real);
  EXPECT_EQ(every.grid_leaves, 27);
  EXPECT_EQ(lazy.grid_leaves, 64);
  const double leaf =
      double(build_solver(block_scene("every_substep", "two_pass")).grid().bytes_per_leaf());
  EXPECT_EQ(lazy.bytes - every.bytes, lazy.block_bytes - every.block_bytes + (64 - 27) * leaf);
  EXPECT_EQ(lazy.block_bytes, 8 * double(dilated_block_reals(2, 4)) * real);
  // The fused pass's dilated blocks have 8 lanes.
  const RunEstimate fused = estimate_run(block_scene("every_substep", "fused"));
  EXPECT_EQ(fused.block_bytes, 8 * 1728 * 8 * real);
  // Several ranks do not fuse: the plain blocks.
  EXPECT_EQ(estimate_run(block_scene("every_substep", "fused"), false, 2).block_bytes,
            every.block_bytes);
}

// What the solver allocates after a few substeps, in each path: the estimate's bins, blocks and
// leaves.
TEST(EstimateBlocks, MatchWhatTheSolverAllocates) {
  for (const auto& [sort, pass] :
       {std::pair{"every_substep", "two_pass"}, std::pair{"when_needed", "two_pass"},
        std::pair{"every_substep", "fused"}}) {
    const Scene scene = block_scene(sort, pass);
    const RunEstimate e = estimate_run(scene);
    MpmSolver solver = build_solver(scene);
    const exec::Space space;
    for (int k = 0; k < 3; ++k) solver.step(space, solver.stable_dt(space));
    EXPECT_EQ(double(solver.bins().count()), e.bins) << sort << " " << pass;
    EXPECT_EQ(double(solver.p2g_block_bytes()), e.block_bytes) << sort << " " << pass;
    EXPECT_EQ(double(solver.grid().leaf_count()), e.grid_leaves) << sort << " " << pass;
  }
}
