// Particles entering and leaving an MPM run (solvers/mpm_sources.hpp, issue 30): kill regions
// remove exactly the particles a brute-force check of the positions names, emitters emit
// (V + A |v| t) / h^3 particles, both bitwise on every backend and thread count and across a
// checkpoint resume.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <set>

#include "core/errors.hpp"
#include "io/checkpoint.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "solvers/mpm_simulation.hpp"

using namespace amalgam;

namespace {

// A block falling through a kill volume (sphere) and out of the kill box's floor.
const std::string kKillScene = R"({
  "simulation": {"dx": 0.05, "frames": 2, "gravity": [0, -9.81, 0],
                 "kill": {"outside": {"min": [0, 0.3, 0], "max": [1, 2, 1]},
                          "volumes": [{"type": "sphere", "center": [0.5, 0.62, 0.5], "radius": 0.08},
                                      {"type": "box", "center": [0.3, 0.7, 0.5], "half_extent": [0.05, 0.05, 0.3]}]}},
  "materials": {"jelly": {"density": 1000, "youngs_modulus": 1e4}},
  "objects": [{"shape": "box", "min": [0.2, 0.45, 0.3], "max": [0.8, 0.75, 0.7], "material": "jelly",
               "velocity": [0, -3, 0]}]
})";

// A box emitter pouring down at 4 m/s from t = 0.01 to 1 s, no gravity (the stream keeps its
// speed), and a sphere emitter.
const std::string kEmitScene = R"({
  "simulation": {"dx": 0.05, "frames": 2, "gravity": [0, 0, 0], "max_dt": 2e-3},
  "materials": {"water": {"model": "fluid", "density": 1000, "bulk_modulus": 1e4}},
  "objects": [{"shape": "box", "min": [0.1, 0.1, 0.1], "max": [0.3, 0.2, 0.3], "material": "water"}],
  "emitters": [{"shape": "box", "min": [0.45, 0.8, 0.45], "max": [0.55, 0.9, 0.55], "material": "water",
                "velocity": [0, -4, 0], "start": 0.01, "end": 1.0, "seed": 3},
               {"shape": "sphere", "center": [0.2, 0.8, 0.8], "radius": 0.08, "material": "water",
                "velocity": [0.5, 0, 0], "end": 0.2, "particles_per_cell": 1}]
})";

std::string tmp_path(const std::string& name) {
  return (std::filesystem::temp_directory_path() / ("amalgam_test_" + name)).string();
}

void expect_same(const ParticleSet& a, const ParticleSet& b) {
  ASSERT_EQ(a.size(), b.size());
  for (int at = 0; at < a.attribute_count(); ++at)
    EXPECT_EQ(
        std::memcmp(a.words(at), b.words(at), a.size() * 4 * size_t(a.words_per_particle(at))), 0)
        << a.name(at);
}

// Steps to `t_end` on `space`; returns the substeps taken.
int run_to(MpmSolver& s, const exec::Space& space, double t_end) {
  int n = 0;
  while (s.time() < t_end) {
    s.step(space, std::min(s.stable_dt(space), Real(t_end - s.time() + 1e-9)));
    ++n;
  }
  return n;
}

bool killed_by(const KillSettings& k, const Vec3& x) {
  for (int a = 0; a < 3; ++a)
    if (!(x[a] >= k.min[a] && x[a] <= k.max[a])) return true;
  for (const Collider& c : k.volumes)
    if (c.phi(x, 0) < 0) return true;
  return false;
}

}  // namespace

TEST(Kill, RemovesExactlyTheParticlesOutsideKeepingOrderAndIds) {
  const Scene scene = parse_scene(kKillScene, "k.json");
  MpmSolver s = build_solver(scene);
  const exec::Space space(exec::Backend::OpenMP, 2);
  const std::size_t n0 = s.particles().size();
  std::int64_t total_killed = 0;
  int substeps_with_kills = 0;
  for (int step = 0; step < 60; ++step) {
    // The substep without its emission/kill phase, then the brute-force prediction, then the
    // kill phase itself.
    const double t0 = s.time();
    const Real dt = s.stable_dt(space);
    s.sort_particles(space);
    s.update_grid(space);
    s.particle_to_grid(space, dt);
    s.update_grid_velocities(space, dt);
    s.grid_to_particle(space, dt);
    s.collide_particles(space, dt);
    if (s.has_material_update()) s.update_materials(space, dt);
    const ParticleSet& ps = s.particles();
    const Vec3* x = ps.vec3(s.attributes().x);
    const std::int32_t* id = ps.int32(s.attributes().id);
    std::vector<std::int32_t> expect_ids;
    std::vector<Vec3> expect_x;
    for (std::size_t p = 0; p < ps.size(); ++p)
      if (!killed_by(scene.mpm.kill, x[p])) {
        expect_ids.push_back(id[p]);
        expect_x.push_back(x[p]);
      }
    const std::size_t before = ps.size();
    s.emit_and_kill(space, t0, t0 + double(dt));
    s.restore_clock(t0 + double(dt), s.step_count() + 1);
    ASSERT_EQ(s.particles().size(), expect_ids.size()) << "step " << step;
    const std::int32_t* id2 = s.particles().int32(s.attributes().id);
    const Vec3* x2 = s.particles().vec3(s.attributes().x);
    for (std::size_t p = 0; p < expect_ids.size(); ++p) {
      ASSERT_EQ(id2[p], expect_ids[p]);
      ASSERT_EQ(x2[p], expect_x[p]);
    }
    total_killed += std::int64_t(before - expect_ids.size());
    substeps_with_kills += before != expect_ids.size();
  }
  EXPECT_EQ(s.source_counters().killed, total_killed);
  EXPECT_GT(substeps_with_kills, 3);  // the test saw kills happen, over several substeps
  EXPECT_GT(total_killed, std::int64_t(n0 / 4));
  EXPECT_GT(s.particles().size(), 0u);
  EXPECT_EQ(s.next_id(), std::int64_t(n0));  // ids are not reused
}

TEST(Kill, BitwiseAcrossBackendsAndThreads) {
  const Scene scene = parse_scene(kKillScene, "k.json");
  MpmSolver ref = build_solver(scene);
  run_to(ref, exec::Space(exec::Backend::Serial, 1), 0.12);
  EXPECT_GT(ref.source_counters().killed, 0);
  for (const exec::Space& sp :
       {exec::Space(exec::Backend::OpenMP, 1), exec::Space(exec::Backend::OpenMP, 2),
        exec::Space(exec::Backend::TBB, 2)}) {
    MpmSolver s = build_solver(scene);
    run_to(s, sp, 0.12);
    expect_same(ref.particles(), s.particles());
    EXPECT_EQ(s.source_counters().killed, ref.source_counters().killed);
  }
}

TEST(Emitters, CountMatchesDensityTimesVolumeAndFlux) {
  const Scene scene = parse_scene(kEmitScene, "e.json");
  MpmSolver s = build_solver(scene);
  const exec::Space space(exec::Backend::OpenMP, 2);
  const std::size_t n0 = s.particles().size();
  run_to(s, space, 0.72);
  // Emitter 0: box 0.1 x 0.1 x 0.1 at h = dx / 2, flowing at 4 m/s for 0.71 s through 0.1 x 0.1
  // (114 lattice layers: the count is within one layer, 0.9 %, of the formula).
  const double h0 = 0.025, h1 = 0.05;
  const double n_box = (0.1 * 0.1 * 0.1 + 0.1 * 0.1 * 4.0 * 0.71) / (h0 * h0 * h0);
  // Emitter 1: sphere r = 0.08 at h = dx, 0.5 m/s for 0.19 s through a disc of the same radius.
  const double r = 0.08;
  const double n_sphere =
      (4.0 / 3.0 * M_PI * r * r * r + M_PI * r * r * 0.5 * 0.19) / (h1 * h1 * h1);
  std::size_t by_emitter[2] = {0, 0};
  const Real* V = s.particles().real(s.attributes().volume0);
  const std::int32_t* id = s.particles().int32(s.attributes().id);
  for (std::size_t p = 0; p < s.particles().size(); ++p)
    if (std::size_t(id[p]) >= n0) ++by_emitter[std::abs(V[p] - Real(h1 * h1 * h1)) < Real(1e-9)];
  EXPECT_NEAR(double(by_emitter[0]), n_box, 0.01 * n_box);
  // The sphere's lattice is coarse (h = r / 1.6): a sphere sampled this coarsely is good to
  // ~15 % (the next test takes a fine lattice to 1 %).
  EXPECT_NEAR(double(by_emitter[1]), n_sphere, 0.15 * n_sphere);
  EXPECT_EQ(s.source_counters().emitted, std::int64_t(by_emitter[0] + by_emitter[1]));
  // Unique ids, continuing after the objects' particles.
  std::set<std::int32_t> ids(id, id + s.particles().size());
  EXPECT_EQ(ids.size(), s.particles().size());
  EXPECT_EQ(*ids.rbegin(), std::int32_t(s.next_id() - 1));
  // Emitted particles start unstrained: water keeps J alone (MpmSolver::keeps_J_only).
  ASSERT_LT(s.attributes().F, 0);
  const Real* J = s.particles().real(s.attributes().J);
  for (std::size_t p = 0; p < s.particles().size(); ++p)
    EXPECT_TRUE(std::isfinite(J[p]) && J[p] > Real(0.5) && J[p] < Real(2)) << p << ": " << J[p];
}

TEST(Emitters, SphereRateWithinOnePercentOnAFineLattice) {
  // The count over 0.2 s of a sphere emitter at 27 particles per cell: (V + pi r^2 |v| t) / h^3.
  std::string scene_text = kEmitScene;
  scene_text.replace(scene_text.find("\"particles_per_cell\": 1"), 23,
                     "\"particles_per_cell\": 27");
  const Scene scene = parse_scene(scene_text, "e.json");
  MpmSolver s = build_solver(scene);
  const std::size_t n0 = s.particles().size();
  run_to(s, exec::Space(exec::Backend::OpenMP, 2), 0.2);
  const double h = 0.05 / 3, r = 0.08;
  const double expect = (4.0 / 3.0 * M_PI * r * r * r + M_PI * r * r * 0.5 * 0.2) / (h * h * h);
  std::size_t n = 0;
  const Real* V = s.particles().real(s.attributes().volume0);
  const std::int32_t* id = s.particles().int32(s.attributes().id);
  for (std::size_t p = 0; p < s.particles().size(); ++p)
    n += std::size_t(id[p]) >= n0 && std::abs(V[p] - Real(h * h * h)) < Real(1e-9);
  EXPECT_NEAR(double(n), expect, 0.01 * expect);
}

TEST(Emitters, BitwiseAcrossBackendsAndThreads) {
  const Scene scene = parse_scene(kEmitScene, "e.json");
  MpmSolver ref = build_solver(scene);
  run_to(ref, exec::Space(exec::Backend::Serial, 1), 0.06);
  for (const exec::Space& sp :
       {exec::Space(exec::Backend::OpenMP, 1), exec::Space(exec::Backend::OpenMP, 2),
        exec::Space(exec::Backend::TBB, 2)}) {
    MpmSolver s = build_solver(scene);
    run_to(s, sp, 0.06);
    expect_same(ref.particles(), s.particles());
  }
}

TEST(Emitters, CheckpointResumeMidEmissionIsBitwise) {
  // Emitters and kill regions together: the count goes up and down across the checkpoint.
  std::string text = kEmitScene;
  text.replace(
      text.find("\"max_dt\": 2e-3"), 14,
      "\"max_dt\": 2e-3, \"kill\": {\"outside\": {\"min\": [0, 0.5, 0], \"max\": [1, 1, 1]}}");
  const Scene scene = parse_scene(text, "e.json");
  const exec::Space space(exec::Backend::OpenMP, 2);
  MpmSimulation a(build_solver(scene));
  run_to(a.solver(), space, 0.07);
  const std::string path = tmp_path("emit.amck");
  write_checkpoint(path, a, 3, scene.fingerprint);
  MpmSimulation b(build_solver(scene));
  read_checkpoint(path, b, scene.fingerprint);
  EXPECT_EQ(b.solver().next_id(), a.solver().next_id());
  expect_same(a.particles(), b.particles());
  run_to(a.solver(), space, 0.2);
  run_to(b.solver(), space, 0.2);
  EXPECT_GT(a.solver().source_counters().killed, 0);
  EXPECT_EQ(b.solver().source_counters().emitted, a.solver().source_counters().emitted);
  EXPECT_EQ(b.solver().source_counters().killed, a.solver().source_counters().killed);
  expect_same(a.particles(), b.particles());

  std::remove(path.c_str());
}

TEST(Emitters, SceneErrorsNameTheKey) {
  auto error = [](const std::string& text) {
    try {
      parse_scene(text, "e.json");
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  std::string outside = kEmitScene;
  outside.replace(
      outside.find("\"max_dt\": 2e-3"), 14,
      "\"max_dt\": 2e-3, \"kill\": {\"outside\": {\"min\": [0, 0, 0], \"max\": [1, 0.85, 1]}}");
  EXPECT_EQ(error(outside),
            "e.json: /emitters/0/min: the emitter reaches outside the simulation domain "
            "(/simulation/kill/outside)");
  std::string fast = kEmitScene;
  fast.replace(fast.find("[0, -4, 0]"), 10, "[0, -40, 0]");
  EXPECT_NE(error(fast).find("e.json: /emitters/0/velocity: the material would cross the emitter"),
            std::string::npos);
  std::string no_end = kEmitScene;
  no_end.replace(no_end.find("\"end\": 1.0, \"seed\""), 18, "\"seed\"");
  EXPECT_NE(error(no_end).find("/emitters/0/end"), std::string::npos);
}

namespace {
// A damped jelly block settling on the floor (asleep from about t = 0.27 s), with a ball falling
// onto it from 1.2 m above: it comes within the halo (the next leaf, 0.4 m) at about 0.38 s and
// lands at about 0.49 s.
const std::string kSleepScene = R"({
  "simulation": {"dx": 0.05, "frames": 2, "max_dt": 2e-3,
                 "sleep": {"speed": 0.05, "strain_rate": 2, "time": 0.05}},
  "materials": {"jelly": {"density": 1000, "youngs_modulus": 1e5, "viscosity": 100},
                "rock": {"density": 3000, "youngs_modulus": 1e6}},
  "objects": [{"shape": "box", "min": [0.2, 0.1, 0.2], "max": [0.8, 0.3, 0.8], "material": "jelly",
               "particles_per_cell": 1},
              {"shape": "sphere", "center": [0.5, 1.5, 0.5], "radius": 0.08, "material": "rock",
               "particles_per_cell": 1}],
  "colliders": [{"type": "half_space", "point": [0, 0.1, 0], "normal": [0, 1, 0], "boundary": "sticky"}]
})";

std::size_t asleep_count(const MpmSolver& s) {
  return s.sleep()->sleeping(s.particles());
}
}  // namespace

TEST(Sleep, RestingMaterialSleepsStaysPutAndWakesWhenHit) {
  const Scene scene = parse_scene(kSleepScene, "z.json");
  MpmSolver s = build_solver(scene);
  const exec::Space space(exec::Backend::OpenMP, 2);
  const std::size_t n = s.particles().size();
  std::size_t most = 0;
  std::vector<Vec3d> at_sleep;
  double slept_at = -1;
  while (s.time() < 0.33) {
    s.step(space, s.stable_dt(space));
    const std::size_t z = asleep_count(s);
    most = std::max(most, z);
    if (slept_at < 0 && z + 20 >= n) {  // all of the block (the ball, 20 particles, falls)
      slept_at = s.time();
      at_sleep = s.positions_by_id();
    }
  }
  ASSERT_GT(slept_at, 0) << "the block never fell asleep (most asleep: " << most << " of " << n
                         << ")";
  // While asleep, the block does not move at all.
  const std::vector<Vec3d> before = s.positions_by_id();
  const std::int32_t* flag = s.particles().int32(s.particles().id("asleep"));
  const std::int32_t* id = s.particles().int32(s.attributes().id);
  std::size_t still = 0;
  for (std::size_t p = 0; p < n; ++p)
    if (flag[p]) {
      EXPECT_EQ(before[std::size_t(id[p])], at_sleep[std::size_t(id[p])]);
      ++still;
    }
  EXPECT_GT(still, n / 2);
  // The ball lands: the block under it wakes and moves.
  std::size_t fewest = n;
  while (s.time() < 0.7) {
    s.step(space, s.stable_dt(space));
    fewest = std::min(fewest, asleep_count(s));
  }
  const std::vector<Vec3d> after = s.positions_by_id();
  double moved = 0;
  for (std::size_t i = 0; i + 20 < n; ++i) moved = std::max(moved, (after[i] - before[i]).norm());
  EXPECT_GT(moved, 1e-3) << "the block did not move when the ball hit it";
  EXPECT_EQ(fewest, 0u);  // the whole block woke (it lies within one halo of the ball)
}

TEST(Sleep, BitwiseAcrossBackendsThreadsAndCheckpoint) {
  const Scene scene = parse_scene(kSleepScene, "z.json");
  MpmSimulation ref(build_solver(scene));
  run_to(ref.solver(), exec::Space(exec::Backend::Serial, 1), 0.3);
  EXPECT_GT(asleep_count(ref.solver()), 0u);
  for (const exec::Space& sp :
       {exec::Space(exec::Backend::OpenMP, 2), exec::Space(exec::Backend::TBB, 2)}) {
    MpmSolver s = build_solver(scene);
    run_to(s, sp, 0.3);
    expect_same(ref.particles(), s.particles());
  }
  const std::string path = tmp_path("sleep.amck");
  write_checkpoint(path, ref, 3, scene.fingerprint);
  MpmSimulation b(build_solver(scene));
  read_checkpoint(path, b, scene.fingerprint);
  const exec::Space space(exec::Backend::OpenMP, 2);
  run_to(ref.solver(), space, 0.6);
  run_to(b.solver(), space, 0.6);
  expect_same(ref.particles(), b.particles());
  std::remove(path.c_str());
}

TEST(Emitters, MeshEmitterFillsLikeTheSameBox) {
  // A closed cube mesh emitter (inside/outside from its sparse level set, built once over the
  // emitter's box) emits the same lattice points as a box emitter of the same box: the lattice
  // is the same (seed, spacing, velocity), only points within round-off of a face may differ.
  const std::filesystem::path dir = tmp_path("mesh_emitter");
  std::filesystem::create_directories(dir);
  {
    std::FILE* f = std::fopen((dir / "cube.obj").c_str(), "w");
    ASSERT_NE(f, nullptr);
    for (int k = 0; k < 8; ++k)
      std::fprintf(f, "v %g %g %g\n", k & 1 ? 0.55 : 0.45, k & 2 ? 0.9 : 0.8, k & 4 ? 0.55 : 0.45);
    const int q[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                         {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};  // outward, counter-clockwise
    for (const auto& r : q)
      std::fprintf(f, "f %d %d %d\nf %d %d %d\n", r[0] + 1, r[1] + 1, r[2] + 1, r[0] + 1, r[2] + 1,
                   r[3] + 1);
    std::fclose(f);
  }
  const std::string box = R"({"shape": "box", "min": [0.45, 0.8, 0.45], "max": [0.55, 0.9, 0.55],)";
  const std::string mesh = R"({"shape": "mesh", "file": "cube.obj",)";
  auto count = [&](const std::string& shape) {
    const std::string text =
        R"({
      "simulation": {"dx": 0.05, "frames": 1, "gravity": [0, 0, 0], "max_dt": 2e-3},
      "materials": {"water": {"model": "fluid", "density": 1000, "bulk_modulus": 1e4}},
      "objects": [{"shape": "box", "min": [0.1, 0.1, 0.1], "max": [0.3, 0.2, 0.3], "material": "water"}],
      "emitters": [)" +
        shape + R"( "material": "water", "velocity": [0, -2, 0], "end": 0.05, "seed": 5}]
    })";
    const Scene scene = parse_scene(text, (dir / "scene.json").string());
    MpmSolver s = build_solver(scene);
    run_to(s, exec::Space(exec::Backend::TBB, 2), 0.06);
    return double(s.source_counters().emitted);
  };
  const double n_box = count(box), n_mesh = count(mesh);
  const double h = 0.025, expect = (1e-3 + 0.01 * 2.0 * 0.05) / (h * h * h);
  EXPECT_NEAR(n_box, expect, 0.01 * expect);
  EXPECT_NEAR(n_mesh, n_box, 0.01 * n_box);
  std::filesystem::remove_all(dir);
}
