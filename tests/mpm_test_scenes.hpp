// MPM scenes and helpers shared by the determinism tests (test_backends, test_g2p2g).
#pragma once

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>
#include <vector>

#include <unistd.h>

#include "core/exec/simd.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "test_util.hpp"

namespace amalgam::test {

// `simulation`: more keys of /simulation, e.g. R"(, "transfer_pass": "fused")".
inline Scene small_scene(const std::string& transfer, int order,
                         const std::string& integrator = "explicit",
                         const std::string& simulation = "") {
  const std::string text = R"({
    "simulation": {"dx": 0.04, "order": )" +
                           std::to_string(order) + R"(, "transfer": ")" + transfer +
                           R"(", "frames": 1, "integrator": ")" + integrator +
                           R"(", "max_dt": 4e-3)" + simulation + R"(},
    "materials": {"a": {"model": "fixed_corotated", "density": 1000, "youngs_modulus": 2e4, "poisson_ratio": 0.3},
                  "b": {"model": "neo_hookean", "density": 500, "youngs_modulus": 1e4, "poisson_ratio": 0.2}},
    "objects": [
      {"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.6, 0.6, 0.5], "material": "a", "velocity": [0, -2, 0],
       "angular_velocity": [1, 2, 3]},
      {"shape": "sphere", "center": [0.5, 0.8, 0.45], "radius": 0.12, "material": "b", "velocity": [0.5, -3, 0]}],
    "colliders": [
      {"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "separate", "friction": 0.3},
      {"type": "sphere", "center": [0.45, 0.2, 0.4], "radius": 0.1, "boundary": "sticky", "velocity": [0, 0.5, 0]},
      {"type": "box", "center": [0.7, 0.3, 0.4], "half_extent": [0.05, 0.2, 0.3], "boundary": "slip"}]
  })";
  return parse_scene(text, "inline.json");
}

// Water (and, `second`, a second fluid) falling in a tank against a wall and a ball: a run that
// keeps J alone (MpmSolver::keeps_J_only) with every collider type its G2P meets.
inline Scene water_scene(const std::string& transfer, const std::string& simulation = "",
                         const std::string& second = "") {
  const std::string text = R"({
    "simulation": {"dx": 0.04, "transfer": ")" +
                           transfer + R"(", "frames": 1, "max_dt": 4e-3)" + simulation + R"(},
    "materials": {"water": {"model": "fluid", "density": 1000, "bulk_modulus": 2e5, "gamma": 7, "viscosity": 0.01},
                  "oil": {"model": "fluid", "density": 800, "bulk_modulus": 1e5)" +
                           second + R"(}},
    "objects": [
      {"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.6, 0.6, 0.5], "material": "water", "velocity": [0, -2, 0],
       "angular_velocity": [1, 2, 3]},
      {"shape": "sphere", "center": [0.5, 0.8, 0.45], "radius": 0.12, "material": "oil", "velocity": [0.5, -3, 0]}],
    "colliders": [
      {"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "separate", "friction": 0.3},
      {"type": "sphere", "center": [0.45, 0.2, 0.4], "radius": 0.1, "boundary": "slip", "velocity": [0, 0.5, 0]},
      {"type": "box", "center": [0.7, 0.3, 0.4], "half_extent": [0.05, 0.2, 0.3], "boundary": "slip"}]
  })";
  return parse_scene(text, "inline.json");
}

inline std::vector<Real> state_bytes(const MpmSolver& s) {
  std::vector<Real> out;
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  for (auto id : {a.x, a.x_lo, a.v, a.C, a.F, a.F_lo, a.J, a.b, a.plastic, a.temperature})
    if (id >= 0) out.insert(out.end(), ps.real(id), ps.real(id) + ps.size() * size_t(ps.width(id)));
  return out;
}

// Every material model with state (return mappings, F reset, melting under a heat source), the
// particle collision pass and a keyframed mesh collider (a cube sweeping through the snow).
inline Scene material_scene(const std::string& simulation = "") {
  // One file per process, written once and removed at exit: ctest runs each test as its own
  // process, two at a time, and several tests build this scene. A shared name let one test
  // truncate the file while another read it (BackendDeterminism.MaterialsWithStateBitwiseIdentical
  // failed after 0.1 s, once).
  struct CubeFile {
    std::string path = (std::filesystem::temp_directory_path() /
                        ("amalgam_backend_cube_" + std::to_string(::getpid()) + ".obj"))
                           .string();
    CubeFile() {
      std::ofstream f(path);
      for (int i = 0; i < 8; ++i)
        f << "v " << ((i & 1) ? 0.06 : -0.06) << " " << ((i & 2) ? 0.06 : -0.06) << " "
          << ((i & 4) ? 0.06 : -0.06) << "\n";
      f << "f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n";
    }
    ~CubeFile() {
      std::error_code ec;
      std::filesystem::remove(path, ec);
    }
  };
  static const CubeFile file;
  const std::string& cube = file.path;
  const std::string text = R"({
    "simulation": {"dx": 0.04, "frames": 1)" +
                           simulation + R"(},
    "materials": {
      "snow": {"model": "snow", "density": 400, "youngs_modulus": 1.4e5, "poisson_ratio": 0.2},
      "sand": {"model": "drucker_prager", "density": 2200, "youngs_modulus": 3.5e5, "friction_angle": 30, "cohesion": 10},
      "metal": {"model": "von_mises", "density": 2700, "youngs_modulus": 1e6, "yield_stress": 2e3, "hardening_modulus": 1e4},
      "water": {"model": "fluid", "density": 1000, "bulk_modulus": 1e5, "viscosity": 0.1},
      "wax": {"model": "neo_hookean", "density": 900, "youngs_modulus": 5e4,
              "melting": {"temperature": 320, "bulk_modulus": 5e4, "viscosity": 1}}},
    "objects": [
      {"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.5, 0.5, 0.5], "material": "snow", "velocity": [0, -3, 0]},
      {"shape": "box", "min": [0.55, 0.3, 0.3], "max": [0.7, 0.45, 0.5], "material": "sand", "velocity": [0, -2, 0]},
      {"shape": "sphere", "center": [0.4, 0.7, 0.4], "radius": 0.08, "material": "metal", "velocity": [0, -4, 0]},
      {"shape": "box", "min": [0.6, 0.55, 0.3], "max": [0.75, 0.7, 0.45], "material": "water", "velocity": [0, -1, 0]},
      {"shape": "box", "min": [0.2, 0.26, 0.6], "max": [0.4, 0.4, 0.75], "material": "wax", "temperature": 300}],
    "colliders": [{"type": "half_space", "point": [0, 0.25, 0], "normal": [0, 1, 0], "boundary": "sticky"},
                  {"type": "mesh", "file": ")" +
                           cube + R"(", "translate": [0.25, 0.4, 0.4], "boundary": "separate",
                   "friction": 0.5, "keyframes": [{"time": 0}, {"time": 0.05, "translate": [0.3, 0, 0], "rotate_degrees": [0, 0, 60]}]}],
    "heat_sources": [{"type": "half_space", "point": [0, 0.3, 0], "normal": [0, 1, 0], "temperature": 400, "rate": 200}]
  })";
  return parse_scene(text, "inline.json");
}

// Runs `steps` CFL substeps of the scene on every backend configuration, expects the state to be
// bitwise identical to the first (serial) run, and returns that reference solver's state.
template <class OnReference>
std::vector<Real> run_everywhere(const Scene& scene, int steps, OnReference on_reference) {
  std::vector<Real> ref;
  for (const auto& c : all_configs()) {
    MpmSolver s = build_solver(scene);
    const exec::Space space(c.backend, c.threads);
    for (int i = 0; i < steps; ++i) s.step(space, s.stable_dt(space));
    const std::vector<Real> st = state_bytes(s);
    if (ref.empty()) {
      ref = st;
      on_reference(s);
      continue;
    }
    EXPECT_EQ(st.size(), ref.size());
    if (st.size() == ref.size()) {
      EXPECT_TRUE(bitwise_equal(st.data(), ref.data(), st.size())) << c.name();
    }
  }
  return ref;
}

// material_scene's run was not trivial: some snow, sand and metal projected, some wax melted.
inline void expect_plastic_flow_and_melting(const MpmSolver& s) {
  const auto& ps = s.particles();
  const auto& a = s.attributes();
  int plastic = 0, melted = 0;
  for (size_t p = 0; p < ps.size(); ++p) {
    const MaterialParams& m = s.materials()[size_t(ps.int32(a.material)[p])];
    plastic += m.has_plastic_state() && ps.real(a.plastic)[p] != m.initial_plastic();
    melted += ps.real(a.temperature)[p] >= 320;
  }
  std::printf("particles with plastic flow: %d, melted: %d of %zu\n", plastic, melted, ps.size());
  EXPECT_GT(plastic, 10);
  EXPECT_GT(melted, 10);
}

// Run-time vector width (core/exec/simd.hpp): the kernels compiled for AVX2 and AVX-512 give
// the baseline's state bit for bit, on Serial and on 2 TBB threads. Paths this CPU (or build)
// lacks are skipped, saying so.
struct SimdGuard {  // restores the path a test found
  exec::SimdPath saved = exec::simd_path();
  ~SimdGuard() { exec::set_simd_path(saved); }
};

// The state after `steps` substeps of `scene` on every supported path and two configurations,
// compared with the baseline path on Serial.
inline void expect_same_on_every_path(const Scene& scene, int steps) {
  SimdGuard guard;
  std::vector<Real> ref;
  for (const exec::SimdPath path :
       {exec::SimdPath::Baseline, exec::SimdPath::Avx2, exec::SimdPath::Avx512}) {
    if (!exec::simd_path_supported(path)) {
      std::printf("SIMD path %s: skipped (%s)\n", exec::simd_path_name(path),
                  exec::simd_path_compiled(path) ? "this CPU lacks it" : "not in this build");
      continue;
    }
    exec::set_simd_path(path);
    for (const exec::Space& space : {exec::Space(), exec::Space(exec::Backend::TBB, 2)}) {
      MpmSolver s = build_solver(scene);
      for (int i = 0; i < steps; ++i) s.step(space, s.stable_dt(space));
      const std::vector<Real> st = state_bytes(s);
      if (ref.empty()) {
        ref = st;
        continue;
      }
      ASSERT_EQ(st.size(), ref.size());
      EXPECT_TRUE(bitwise_equal(st.data(), ref.data(), st.size()))
          << exec::simd_path_name(path) << " on " << space.describe();
    }
    if (path != exec::SimdPath::Baseline)
      std::printf("SIMD path %s: bitwise the baseline's\n", exec::simd_path_name(path));
  }
}

// The same for the small MLS, APIC and FLIP scenes and the materials scene, `simulation` added to
// each scene's simulation block (the transfer pass, the sort), `steps` CFL substeps each.
inline void expect_bitwise_on_every_simd_path(const std::string& simulation, int steps) {
  for (const Scene& scene :
       {small_scene("mls", 2, "explicit", simulation),
        small_scene("apic", 3, "explicit", simulation),
        small_scene("flip", 2, "explicit", simulation), material_scene(simulation)})
    expect_same_on_every_path(scene, steps);
}

// A frame's start unprimes the bins and the grid (a checkpoint holds particles only): a run
// unprimed at a substep is bitwise a fresh solver started from that substep's particles and
// clock, `steps` CFL substeps later.
inline void expect_unprimed_start_is_a_fresh_start(const Scene& scene, int steps) {
  const exec::Space space(exec::Backend::TBB, 2);
  MpmSolver a = build_solver(scene);
  for (int i = 0; i < 4; ++i) a.step(space, a.stable_dt(space));
  MpmSolver::Snapshot snap;
  a.save(snap);
  MpmSolver b = build_solver(scene);
  b.restore(snap);
  b.restore_clock(a.time(), a.step_count());
  a.unprime();
  for (int i = 0; i < steps; ++i) {
    const Real dt = a.stable_dt(space);
    a.step(space, dt);
    b.step(space, dt);
  }
  const std::vector<Real> sa = state_bytes(a), sb = state_bytes(b);
  ASSERT_EQ(sa.size(), sb.size());
  EXPECT_TRUE(bitwise_equal(sa.data(), sb.data(), sa.size()));
}

}  // namespace amalgam::test
