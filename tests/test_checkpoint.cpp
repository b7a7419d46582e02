// Checkpoints: round trip restores every attribute bit for bit and the clock; truncated,
// corrupted, foreign and other-scene files are InputErrors naming the file and the problem.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "core/errors.hpp"
#include "io/checkpoint.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"
#include "solvers/mpm_simulation.hpp"

using namespace amalgam;

namespace {
const std::string kScene = R"({
  "simulation": {"dx": 0.05, "frames": 2},
  "materials": {"jelly": {"density": 1000, "youngs_modulus": 1e4}},
  "objects": [{"shape": "sphere", "center": [0.5,0.5,0.5], "radius": 0.15, "material": "jelly", "velocity": [0,-1,0]}]
})";

std::string tmp_path(const std::string& name) {
  return (std::filesystem::temp_directory_path() / ("amalgam_test_" + name)).string();
}
std::string slurp(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}
void spit(const std::string& p, const std::string& d) {
  std::ofstream(p, std::ios::binary).write(d.data(), std::streamsize(d.size()));
}
std::string error_reading(const std::string& path, std::uint64_t fp) {
  MpmSimulation s(build_solver(parse_scene(kScene, "s.json")));
  try {
    read_checkpoint(path, s, fp);
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST(Checkpoint, RoundTripIsBitwise) {
  const Scene scene = parse_scene(kScene, "s.json");
  MpmSimulation sim_a(build_solver(scene)), sim_b(build_solver(scene));
  MpmSolver &a = sim_a.solver(), &b = sim_b.solver();
  const exec::Space space(exec::Backend::OpenMP, 2);
  for (int i = 0; i < 7; ++i) a.step(space, a.stable_dt(space));
  const std::string path = tmp_path("roundtrip.amck");
  write_checkpoint(path, sim_a, 3, scene.fingerprint);
  const CheckpointState st = read_checkpoint(path, sim_b, scene.fingerprint);
  EXPECT_EQ(st.next_frame, 3);
  EXPECT_EQ(st.steps, 7u);
  EXPECT_EQ(b.time(), a.time());
  ASSERT_EQ(b.particles().size(), a.particles().size());
  for (int at = 0; at < a.particles().attribute_count(); ++at)
    EXPECT_EQ(std::memcmp(a.particles().words(at), b.particles().words(at),
                          a.particles().size() * 4 * size_t(a.particles().words_per_particle(at))),
              0)
        << a.particles().name(at);
  // Both continue identically.
  for (int i = 0; i < 5; ++i) {
    a.step(space, a.stable_dt(space));
    b.step(space, b.stable_dt(space));
  }
  const auto x = a.attributes().x;
  EXPECT_EQ(std::memcmp(a.particles().words(x), b.particles().words(x),
                        a.particles().size() * sizeof(Vec3)),
            0);
  std::remove(path.c_str());
}

TEST(Checkpoint, DamagedFilesAreClearErrors) {
  const Scene scene = parse_scene(kScene, "s.json");
  MpmSimulation a(build_solver(scene));
  const std::string path = tmp_path("good.amck"), bad = tmp_path("bad.amck");
  write_checkpoint(path, a, 1, scene.fingerprint);
  const std::string good = slurp(path);

  spit(bad, good.substr(0, good.size() / 2));  // truncated
  EXPECT_NE(
      error_reading(bad, scene.fingerprint).find(bad + ": checkpoint is corrupt or truncated"),
      std::string::npos);
  std::string flipped = good;
  flipped[good.size() / 3] ^= 0x10;  // one bit flipped in the particle data
  spit(bad, flipped);
  EXPECT_NE(error_reading(bad, scene.fingerprint).find("checksum mismatch"), std::string::npos);
  spit(bad, "not a checkpoint at all");
  EXPECT_NE(error_reading(bad, scene.fingerprint).find("not an Amalgam checkpoint"),
            std::string::npos);
  spit(bad, good.substr(0, 5));
  EXPECT_NE(error_reading(bad, scene.fingerprint).find("not an Amalgam checkpoint"),
            std::string::npos);
  EXPECT_NE(error_reading(path, scene.fingerprint + 1).find("different scene"), std::string::npos);
  EXPECT_NE(
      error_reading(tmp_path("missing.amck"), scene.fingerprint).find("cannot open checkpoint"),
      std::string::npos);
  std::remove(path.c_str());
  std::remove(bad.c_str());
}

TEST(Checkpoint, FingerprintIgnoresOutputAndFramesButNotPhysics) {
  const Scene a = parse_scene(kScene, "s.json");
  std::string more_frames = kScene;
  more_frames.replace(more_frames.find("\"frames\": 2"), 11, "\"frames\": 9");
  EXPECT_EQ(parse_scene(more_frames, "s.json").fingerprint, a.fingerprint);
  std::string stiffer = kScene;
  stiffer.replace(stiffer.find("1e4"), 3, "2e4");
  EXPECT_NE(parse_scene(stiffer, "s.json").fingerprint, a.fingerprint);
}
