// Meshes: the readers agree on a cube in every format; watertightness is detected; the armadillo
// sampled at a given spacing carries its enclosed volume within 2 % (issue 3).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "core/errors.hpp"
#include "io/mesh.hpp"
#include "io/tetmesh.hpp"
#include "thread_recorder.hpp"

using namespace amalgam;

namespace {
namespace fs = std::filesystem;
const double kCube[8][3] = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0},
                            {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
const int kQuads[6][4] = {{0, 3, 2, 1}, {4, 5, 6, 7}, {0, 1, 5, 4},
                          {2, 3, 7, 6}, {1, 2, 6, 5}, {0, 4, 7, 3}};

std::string write(const std::string& name, const std::string& text) {
  const std::string p = (fs::temp_directory_path() / ("amalgam_test_" + name)).string();
  std::ofstream(p, std::ios::binary) << text;
  return p;
}
// The message of the InputError load_mesh throws for p ("" when it reads).
std::string err(const std::string& p) {
  try {
    load_mesh(p);
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}
std::string mesh_dir() {
  const char* d = std::getenv("AMALGAM_MESH_DIR");
  return d ? d : "";
}
}  // namespace

TEST(Mesh, CubeInEveryFormat) {
  std::string obj, off = "OFF\n8 6 0\n", ply_a, ply_b_header, ply_b;
  for (auto& v : kCube)
    obj += "v " + std::to_string(v[0]) + " " + std::to_string(v[1]) + " " + std::to_string(v[2]) +
           "\n";
  for (auto& q : kQuads)
    obj += "f " + std::to_string(q[0] + 1) + "/1 " + std::to_string(q[1] + 1) + "//2 " +
           std::to_string(q[2] + 1) + " " + std::to_string(q[3] + 1) + "\n";
  for (auto& v : kCube)
    off += std::to_string(v[0]) + " " + std::to_string(v[1]) + " " + std::to_string(v[2]) + "\n";
  for (auto& q : kQuads)
    off += "4 " + std::to_string(q[0]) + " " + std::to_string(q[1]) + " " + std::to_string(q[2]) +
           " " + std::to_string(q[3]) + "\n";
  const std::string header =
      "element vertex 8\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\n"
      "element face 6\nproperty list uchar int vertex_indices\nend_header\n";
  ply_a = "ply\nformat ascii 1.0\n" + header;
  for (auto& v : kCube)
    ply_a +=
        std::to_string(v[0]) + " " + std::to_string(v[1]) + " " + std::to_string(v[2]) + " 7\n";
  for (auto& q : kQuads)
    ply_a += "4 " + std::to_string(q[0]) + " " + std::to_string(q[1]) + " " + std::to_string(q[2]) +
             " " + std::to_string(q[3]) + "\n";
  ply_b = "ply\nformat binary_little_endian 1.0\n" + header;
  for (auto& v : kCube) {
    const float f[3] = {float(v[0]), float(v[1]), float(v[2])};
    ply_b.append(reinterpret_cast<const char*>(f), 12);
    ply_b.push_back(char(7));
  }
  for (auto& q : kQuads) {
    ply_b.push_back(char(4));
    ply_b.append(reinterpret_cast<const char*>(q), 16);
  }
  for (const auto& [name, text] : std::vector<std::pair<std::string, std::string>>{
           {"cube.obj", obj}, {"cube.off", off}, {"cube_a.ply", ply_a}, {"cube_b.ply", ply_b}}) {
    const TriangleMesh m = load_mesh(write(name, text));
    EXPECT_EQ(m.vertices.size(), 8u) << name;
    EXPECT_EQ(m.triangles.size(), 12u) << name;
    EXPECT_TRUE(check_mesh(m).watertight()) << name;
    EXPECT_NEAR(enclosed_volume(m), 1.0, 1e-12) << name;
    Real h = Real(0.05);
    const auto pts = sample_mesh(m, double(h), 0.0, 1, exec::Space());
    EXPECT_NEAR(double(pts.size()) * 0.05 * 0.05 * 0.05, 1.0, 0.02) << name;
  }
  // An open box (one face missing) is reported.
  TriangleMesh open = load_mesh(write("cube.off", off));
  open.triangles.pop_back();
  open.triangles.pop_back();
  const MeshCheck c = check_mesh(open);
  EXPECT_FALSE(c.watertight());
  EXPECT_EQ(c.boundary_edges, 4u);
}

TEST(Mesh, BadFilesAreClearErrors) {
  EXPECT_NE(err("/nonexistent/a.obj").find("cannot open mesh file"), std::string::npos);
  EXPECT_NE(err(write("x.xyz", "solid")).find("unknown mesh format '.xyz'"), std::string::npos);
  EXPECT_NE(err(write("x.stl", "solid")).find("mesh has no faces"), std::string::npos);
  EXPECT_NE(err(write("bad.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 9\n"))
                .find("vertex index 9 out of range"),
            std::string::npos);
  EXPECT_NE(err(write("short.off", "OFF\n4 1 0\n0 0 0\n")).find("can hold"), std::string::npos);
  EXPECT_NE(err(write("short2.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n                  \n"))
                .find("truncated"),
            std::string::npos);
  EXPECT_NE(err(write("bad.obj", "v 0 0\n")).find("bad.obj:1: expected 'v x y z'"),
            std::string::npos);
}

TEST(Mesh, ArmadilloSampledVolumeWithinTwoPercent) {
  if (mesh_dir().empty())
    GTEST_SKIP() << "AMALGAM_MESH_DIR not set (ctest sets it via scripts/get_meshes.sh)";
  const TriangleMesh m = load_mesh(mesh_dir() + "/armadillo.off");
  EXPECT_TRUE(check_mesh(m).watertight());
  const double V = std::abs(enclosed_volume(m));
  Vec3d lo = m.vertices[0], hi = m.vertices[0];
  for (const auto& v : m.vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
  const double h = (hi - lo).maxCoeff() / 100.0;  // 100 lattice spacings across the largest extent
  const auto pts = sample_mesh(m, h, 0.5, 7, exec::Space());
  const double sampled = double(pts.size()) * h * h * h;
  std::printf("armadillo: enclosed volume %.6g, sampled %zu particles x h^3 = %.6g (%.3f %%)\n", V,
              pts.size(), sampled, 100 * (sampled / V - 1));
  EXPECT_NEAR(sampled / V, 1.0, 0.02);
}

TEST(Mesh, ChineseDragonIsReportedNotWatertight) {
  if (mesh_dir().empty()) GTEST_SKIP() << "AMALGAM_MESH_DIR not set";
  const MeshCheck c = check_mesh(load_mesh(mesh_dir() + "/ChineseDragon-10kv.off"));
  EXPECT_FALSE(c.watertight());
  EXPECT_GT(c.boundary_edges + c.nonmanifold_edges, 0u);
}

// `--threads 1` means one thread during mesh voxelisation: sample_mesh runs OpenVDB's
// meshToLevelSet in the exec layer's arena, so no TBB worker joins it under a one-thread space
// (a sphere of 80 000 triangles voxelised at 1/150 of its size keeps a 2-core machine's worker
// busy otherwise), and both spaces sample the same points.
TEST(Mesh, VoxelisationUsesTheSpacesThreadCount) {
  TriangleMesh m;
  const int nu = 200, nv = 200;  // UV sphere of radius 0.5
  for (int j = 0; j <= nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const double th = M_PI * j / nv, ph = 2 * M_PI * i / nu;
      m.vertices.emplace_back(0.5 * std::sin(th) * std::cos(ph), 0.5 * std::cos(th),
                              0.5 * std::sin(th) * std::sin(ph));
    }
  auto at = [&](int i, int j) { return std::int32_t(j * nu + (i % nu)); };
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      m.triangles.push_back({at(i, j), at(i + 1, j), at(i + 1, j + 1)});
      m.triangles.push_back({at(i, j), at(i + 1, j + 1), at(i, j + 1)});
    }
  std::vector<Vec3> pts[2];
  for (const int threads : {1, 2}) {
    test::WorkerRecorder rec;
    pts[threads - 1] = sample_mesh(m, 1.0 / 150, 0.0, 1, exec::Space(exec::Backend::TBB, threads));
    EXPECT_LE(rec.workers(), std::size_t(threads - 1)) << threads << " thread(s)";
  }
  EXPECT_GT(pts[0].size(), 1000000u);
  EXPECT_EQ(pts[0], pts[1]);
}

// Hostile mesh files from issue 26: header counts are checked against the file's bytes before
// anything is allocated (an OFF claiming 2e9 vertices in 25 bytes ended in std::bad_alloc; a face
// claiming 2e9 indices took 7.8 GB), and indices against their range (an OBJ index of 2^32 + 1
// wrapped to 1).
TEST(Mesh, HeaderClaimsAreCheckedAgainstTheFileSize) {
  EXPECT_NE(err(write("claim.off", "OFF\n2000000000 1 0\n0 0 0\n")).find("can hold"),
            std::string::npos);
  EXPECT_NE(err(write("face.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n2000000000 0 1 2\n"))
                .find("a face of 2000000000 vertices"),
            std::string::npos);
  EXPECT_NE(err(write("wrap.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 4294967297 2 3\n"))
                .find("face index '4294967297' out of range"),
            std::string::npos);
  EXPECT_NE(err(write("claim.ply",
                      "ply\nformat binary_little_endian 1.0\nelement vertex 2000000000\n"
                      "property float x\nproperty float y\nproperty float z\n"
                      "end_header\n"))
                .find("element counts need at least 24000000000 bytes"),
            std::string::npos);
  EXPECT_NE(err(write("list.ply",
                      "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                      "property float y\nproperty float z\nelement face 1\n"
                      "property list uchar int vertex_indices\nend_header\n"
                      "0 0 0\n1 0 0\n0 1 0\n250 0 1 2\n"))
                .find("a list of 250"),
            std::string::npos);
  // Directories and devices are not mesh files.
  EXPECT_NE(err("/dev/zero.off").find("cannot open mesh file"), std::string::npos);
  const std::string dir = ::testing::TempDir() + "adir.off";
  std::filesystem::create_directories(dir);
  EXPECT_NE(err(dir).find("is a directory"), std::string::npos);
}

// STL, ASCII and binary: the per-triangle vertices are welded, so a closed surface is watertight
// and the same in both encodings.
TEST(Mesh, StlAsciiAndBinaryReadTheSameWatertightMesh) {
  const float p[4][3] = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
  const int f[4][3] = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
  std::string ascii = "solid tet\n", bin(80, ' ');
  const std::uint32_t n = 4;
  bin.append(reinterpret_cast<const char*>(&n), 4);
  for (const auto& t : f) {
    ascii += " facet normal 0 0 0\n  outer loop\n";
    float rec[12] = {};
    for (int c = 0; c < 3; ++c) {
      ascii += "   vertex " + std::to_string(p[t[c]][0]) + " " + std::to_string(p[t[c]][1]) + " " +
               std::to_string(p[t[c]][2]) + "\n";
      for (int a = 0; a < 3; ++a) rec[3 + 3 * c + a] = p[t[c]][a];
    }
    ascii += "  endloop\n endfacet\n";
    bin.append(reinterpret_cast<const char*>(rec), sizeof rec);
    bin.append(2, '\0');
  }
  ascii += "endsolid tet\n";
  const TriangleMesh a = load_mesh(write("tet_ascii.stl", ascii));
  const TriangleMesh b = load_mesh(write("tet_binary.stl", bin));
  EXPECT_EQ(a.vertices.size(), 4u);
  EXPECT_EQ(a.triangles.size(), 4u);
  EXPECT_TRUE(check_mesh(a).watertight());
  EXPECT_EQ(a.vertices, b.vertices);
  EXPECT_EQ(a.triangles, b.triangles);
  EXPECT_NEAR(enclosed_volume(b), 1.0 / 6.0, 1e-12);
}

// A tetrahedron given twice (in any node order) is refused with both lines named: before, it
// passed `validate` and `run` failed later with a message naming no file.
TEST(Mesh, DuplicatedTetrahedronIsRefused) {
  const std::string dir = std::string(AMALGAM_SOURCE_DIR) + "/tests/data/malformed/";
  try {
    load_tetgen(dir + "dup_tets.node");
    FAIL() << "accepted a duplicated tetrahedron";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find(dir + "dup_tets.ele:4: tetrahedron 2 repeats the one on "
                                               "line 3 (same four nodes)"),
              std::string::npos)
        << e.what();
  }
}
