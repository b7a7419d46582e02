// The stability check folded into the substep's last particle pass (MpmSolver::stable_dt,
// kernels/stability_check.hpp): G2P with the particle collisions (two passes, sorted every substep
// or when needed), G2P2G (fused), or the material update. The folded values are the separate
// pass's: the same dt bits, and a blow-up names the same particle with the same message, on every
// backend and thread count.
#include <gtest/gtest.h>

#include <cstring>
#include <limits>
#include <string>
#include <utility>

#include "mpm_test_scenes.hpp"
#include "solvers/simulation.hpp"

using namespace amalgam;
using namespace amalgam::test;

namespace {
const std::string kLazy = R"(, "sort": "when_needed")";
const std::string kEvery = R"(, "sort": "every_substep")";
const std::string kFused = R"(, "transfer_pass": "fused")";

struct Case {
  std::string name;
  Scene scene;
};

// Every path that folds the check: the two passes sorted when needed, every substep, fused, and
// implicit, for each transfer, and the materials with state (the check in the material update;
// snow's hardening wave speed), with the passes' particle collisions.
std::vector<Case> folding_cases() {
  std::vector<Case> out;
  for (const char* t : {"mls", "apic", "flip"})
    for (const auto& [name, sim] :
         {std::pair<const char*, std::string>{"lazy", kLazy}, {"every", kEvery}, {"fused", kFused}})
      out.push_back({std::string(t) + "_" + name, small_scene(t, 2, "explicit", sim)});
  out.push_back({"mls_order3_lazy", small_scene("mls", 3, "explicit", kLazy)});
  out.push_back({"apic_implicit", small_scene("apic", 2, "implicit")});
  for (const auto& [name, sim] :
       {std::pair<const char*, std::string>{"lazy", kLazy}, {"every", kEvery}, {"fused", kFused}})
    out.push_back({std::string("materials_") + name, material_scene(sim)});
  return out;
}

// stable_dt's result or its error message.
std::string dt_or_error(const MpmSolver& s, const exec::Space& space, Real* dt) {
  try {
    *dt = s.stable_dt(space);
    return "";
  } catch (const SimulationError& e) {
    return e.what();
  }
}
}  // namespace

// After every substep the folded check is there, and its dt has the bits of the separate pass
// (forced by a write access to the particles).
TEST(FoldedStabilityCheck, SameDtAsTheSeparatePassOnEveryPath) {
  for (const Case& c : folding_cases()) {
    SCOPED_TRACE(c.name);
    for (const Config& cfg : {Config{exec::Backend::Serial, 1}, Config{parallel_backend(), 2}}) {
      MpmSolver s = build_solver(c.scene);
      ASSERT_TRUE(s.folds_check());
      const exec::Space space(cfg.backend, cfg.threads);
      EXPECT_FALSE(s.has_folded_check());  // the first substep: the separate pass
      for (int i = 0; i < 12; ++i) {
        Real folded = 0, separate = 0;
        if (i > 0) ASSERT_TRUE(s.has_folded_check()) << "substep " << i;
        const std::string e1 = dt_or_error(s, space, &folded);
        (void)s.particles();  // a write access: stable_dt checks every particle again
        ASSERT_FALSE(s.has_folded_check());
        const std::string e2 = dt_or_error(s, space, &separate);
        ASSERT_EQ(e1, "");
        ASSERT_EQ(e2, "");
        ASSERT_EQ(std::memcmp(&folded, &separate, sizeof(Real)), 0)
            << "substep " << i << ": " << folded << " vs " << separate;
        s.step(space, folded);
      }
    }
  }
}

// A particle whose F turned non-finite spreads NaN through the grid to its neighbours: the folded
// check names the smallest index among them, with the separate pass's message, the same on every
// backend and thread count; likewise a runaway speed above max_speed.
TEST(FoldedStabilityCheck, BlowUpNamesTheSameParticleOnEveryBackend) {
  const std::string slow = R"(, "max_speed": 3.2)";
  std::vector<Case> cases;
  for (const auto& [name, sim] :
       {std::pair<const char*, std::string>{"lazy", kLazy}, {"every", kEvery}, {"fused", kFused}}) {
    cases.push_back({std::string("nan_") + name, small_scene("mls", 2, "explicit", sim)});
    cases.push_back({std::string("speed_") + name, small_scene("apic", 2, "explicit", sim + slow)});
    cases.push_back({std::string("materials_nan_") + name, material_scene(sim)});
  }
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    const bool inject = c.name.find("nan") != std::string::npos;
    std::string reference;
    for (const Config& cfg : all_configs()) {
      MpmSolver s = build_solver(c.scene);
      const exec::Space space(cfg.backend, cfg.threads);
      std::string msg;
      for (int i = 0; i < 60 && msg.empty(); ++i) {
        Real dt = 0;
        msg = dt_or_error(s, space, &dt);
        if (!msg.empty()) break;
        if (inject && i == 3) {  // F (or b - I) of a particle in the middle of the storage: NaN
          const MpmAttributes& a = s.attributes();
          const std::size_t mid = s.particles().size() / 2;
          if (a.F >= 0)
            s.particles().mat3(a.F)[mid](1, 1) = std::numeric_limits<Real>::quiet_NaN();
          else
            s.particles().sym_dev(a.b)[mid].e[1] = std::numeric_limits<Real>::quiet_NaN();
        }
        s.step(space, dt);
        if (i >= 3) ASSERT_TRUE(s.has_folded_check());
      }
      ASSERT_NE(msg, "") << cfg.name() << ": no blow-up";
      EXPECT_NE(msg.find("the simulation blew up"), std::string::npos) << msg;
      (void)s.particles();  // the separate pass on the same state
      Real dt = 0;
      EXPECT_EQ(dt_or_error(s, space, &dt), msg) << cfg.name();
      if (reference.empty()) {
        reference = msg;
        std::printf("%s: %s\n", c.name.c_str(), msg.c_str());
      } else {
        EXPECT_EQ(msg, reference) << cfg.name();
      }
    }
  }
}

// Emission and kill regions change the particles after the last pass: the next stable_dt checks
// them all (the new particles, the compacted indices).
TEST(FoldedStabilityCheck, EmissionFallsBackToTheSeparatePass) {
  const Scene scene = parse_scene(R"({
    "simulation": {"dx": 0.04, "frames": 1, "max_dt": 4e-3},
    "materials": {"w": {"model": "fluid", "density": 1000, "bulk_modulus": 1e4}},
    "objects": [{"shape": "box", "min": [0.3, 0.3, 0.3], "max": [0.5, 0.5, 0.5], "material": "w"}],
    "emitters": [{"shape": "sphere", "center": [0.5, 0.8, 0.5], "radius": 0.05, "material": "w",
                  "velocity": [0, -1, 0], "end": 1}]
  })",
                                  "inline.json");
  MpmSolver s = build_solver(scene);
  const exec::Space space;
  bool emitted = false;
  for (int i = 0; i < 20; ++i) {
    const std::size_t before = std::as_const(s).particles().size();
    s.step(space, s.stable_dt(space));
    const bool grew = std::as_const(s).particles().size() > before;
    emitted |= grew;
    if (grew) EXPECT_FALSE(s.has_folded_check());
  }
  EXPECT_TRUE(emitted);
}
