// Checkpoints: round trip restores every attribute bit for bit and the clock; truncated,
// corrupted, foreign and other-scene files are InputErrors naming the file and the problem.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <cmath>
#include <algorithm>
#include <cstring>
#include <fstream>
#include <limits>
#include <map>

#include "core/errors.hpp"
#include "core/hash.hpp"
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
  a.unprime();  // a checkpoint is a frame's start, where the frame loop unprimes (a re-sort)
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

// The frame loop stages a frame's checkpoint and commits it once the frame's files are on disk
// (apps/frame_loop.cpp): staged, the state is in a temporary file and nothing is at the path;
// the state may change before the commit; dropped uncommitted, the temporary file is removed.
TEST(Checkpoint, StagedIsInPlaceOnlyOnceCommitted) {
  const Scene scene = parse_scene(kScene, "s.json");
  MpmSimulation sim(build_solver(scene));
  const exec::Space space(exec::Backend::Serial, 1);
  for (int i = 0; i < 3; ++i) sim.solver().step(space, sim.solver().stable_dt(space));
  const std::string ref = tmp_path("staged_ref.amck"), path = tmp_path("staged.amck");
  std::remove(path.c_str());
  write_checkpoint(ref, sim, 2, scene.fingerprint);
  const std::string name = std::filesystem::path(path).filename().string();
  const auto temporaries = [&] {
    int n = 0;
    for (const auto& e :
         std::filesystem::directory_iterator(std::filesystem::path(path).parent_path())) {
      const std::string f = e.path().filename().string();
      n += f.rfind(name + ".", 0) == 0 && f.size() > 4 && f.compare(f.size() - 4, 4, ".tmp") == 0;
    }
    return n;
  };
  {
    std::unique_ptr<TempFile> staged = stage_checkpoint(path, sim, 2, scene.fingerprint);
    EXPECT_FALSE(std::filesystem::exists(path));
    EXPECT_EQ(temporaries(), 1);
    sim.solver().step(space, sim.solver().stable_dt(space));  // the state moves on
    staged->commit();
  }
  const std::string d = slurp(path);
  EXPECT_EQ(d, slurp(ref));  // the state at staging, bit for bit
  // The checksum streamed with the bytes is FNV-1a of every byte before it.
  ASSERT_GT(d.size(), 8u);
  std::uint64_t stored = 0;
  std::memcpy(&stored, d.data() + d.size() - 8, 8);
  EXPECT_EQ(stored, fnv1a64(d.data(), d.size() - 8));
  EXPECT_EQ(temporaries(), 0);
  {
    std::unique_ptr<TempFile> dropped = stage_checkpoint(path, sim, 3, scene.fingerprint);
    EXPECT_EQ(temporaries(), 1);
  }
  EXPECT_EQ(temporaries(), 0);
  EXPECT_EQ(slurp(path), d);  // the committed checkpoint untouched
  std::remove(path.c_str());
  std::remove(ref.c_str());
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

namespace {
// A checkpoint with its checksum recomputed after an edit: what a hostile or buggy writer makes,
// which the checksum cannot catch.
std::string resealed(std::string d) {
  const std::uint64_t sum = fnv1a64(d.data(), d.size() - 8);
  std::memcpy(d.data() + d.size() - 8, &sum, 8);
  return d;
}
// Header offsets: magic (13), version (4), precision (4), fingerprint (8), then these.
constexpr std::size_t kTimeAt = 29, kStepsAt = 37, kFrameAt = 45, kRetriesAt = 49, kCountAt = 53;
template <class T>
std::string with_field(std::string d, std::size_t at, T v) {
  std::memcpy(d.data() + at, &v, sizeof v);
  return resealed(d);
}
// Offset of the first particle's value of attribute `name`.
std::size_t attribute_data_at(const std::string& d, const std::string& name) {
  std::size_t at = kCountAt + 8;
  std::uint64_t n;
  std::memcpy(&n, d.data() + kCountAt, 8);
  std::uint32_t nattr;
  std::memcpy(&nattr, d.data() + at, 4);
  at += 4;
  for (std::uint32_t a = 0; a < nattr; ++a) {
    std::uint32_t len, words;
    std::memcpy(&len, d.data() + at, 4);
    const std::string nm(d.data() + at + 4, len);
    at += 4 + len + 8;
    std::memcpy(&words, d.data() + at, 4);
    at += 4;
    if (nm == name) return at;
    at += std::size_t(n) * 4 * words;
  }
  return std::string::npos;
}
}  // namespace

// Header fields and particle values are checked against the scene even when the checksum matches
// (each of these aborted, crashed, or was accepted before): the error names the field.
TEST(Checkpoint, FieldsAreCheckedAgainstTheSceneDespiteAValidChecksum) {
  const Scene scene = parse_scene(kScene, "s.json");
  MpmSimulation a(build_solver(scene));
  const exec::Space space;
  for (int i = 0; i < 3; ++i) a.advance(space, a.stable_dt(space));
  const std::string path = tmp_path("fields.amck"), bad = tmp_path("fields_bad.amck");
  write_checkpoint(path, a, 2, scene.fingerprint);
  const std::string good = slurp(path);
  auto error_of = [&](const std::string& d) {
    spit(bad, d);
    return error_reading(bad, scene.fingerprint);
  };
  ASSERT_EQ(error_of(good), "");
  EXPECT_NE(error_of(with_field(good, kCountAt, std::uint64_t(1) << 40))
                .find("checkpoint field 'particle count' is 1099511627776, this scene has"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, kCountAt, std::uint64_t(a.particle_count() - 1)))
                .find("'particle count'"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, kFrameAt, std::int32_t(-5))).find("field 'frame' is -5"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, kRetriesAt, std::int32_t(11))).find("field 'retries' is 11"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, kTimeAt, std::nan(""))).find("field 'time' is"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, kStepsAt, std::uint64_t(0))).find("disagree"),
            std::string::npos);
  const std::size_t mat = attribute_data_at(good, "material");
  ASSERT_NE(mat, std::string::npos);
  EXPECT_NE(error_of(with_field(good, mat + 4 * 5, std::int32_t(1000000)))
                .find("attribute 'material' of particle 5 is 1000000, outside [0, 0]"),
            std::string::npos);
  const std::size_t id = attribute_data_at(good, "id");
  std::int32_t id0;
  std::memcpy(&id0, good.data() + id, 4);
  EXPECT_NE(error_of(with_field(good, id + 4, id0)).find("attribute 'id' of particle 1 repeats"),
            std::string::npos);
  const std::size_t x = attribute_data_at(good, "x");
  EXPECT_NE(error_of(with_field(good, x + sizeof(Real), std::numeric_limits<Real>::infinity()))
                .find("attribute 'x' of particle 0 is not finite"),
            std::string::npos);
  // A low part larger than its position's last bit (issue 27's compensated x) would move the
  // particle at its next substep.
  const std::size_t lo = attribute_data_at(good, "x_lo");
  ASSERT_NE(lo, std::string::npos);
  EXPECT_NE(error_of(with_field(good, lo + 4 * sizeof(Real), Real(1e-3)))
                .find("attribute 'x_lo' of particle 1 is"),
            std::string::npos);
  std::remove(path.c_str());
  std::remove(bad.c_str());
}

// Format 8 dropped the MPM particles' "mass" (density x volume0, recomputed where used): a
// version-7 file, which stored it, is read with it skipped and resumes bitwise; a version-8 file
// with a mass attribute is refused, naming the attribute count.
TEST(Checkpoint, VersionSevenMassIsSkipped) {
  const Scene scene = parse_scene(kScene, "s.json");
  MpmSimulation sim_a(build_solver(scene)), sim_b(build_solver(scene));
  MpmSolver& a = sim_a.solver();
  const exec::Space space;
  for (int i = 0; i < 3; ++i) a.step(space, a.stable_dt(space));
  const std::string path = tmp_path("v7.amck"), old = tmp_path("v7_old.amck");
  write_checkpoint(path, sim_a, 2, scene.fingerprint);
  const std::string v8 = slurp(path);
  // The same state as version 7 wrote it: "mass" inserted as the first attribute.
  std::uint64_t n;
  std::memcpy(&n, v8.data() + kCountAt, 8);
  std::string rec;
  auto put32 = [&](std::uint32_t v) { rec.append(reinterpret_cast<const char*>(&v), 4); };
  put32(4);
  rec += "mass";
  put32(0);  // AttrType::Real
  put32(1);
  put32(std::uint32_t(sizeof(Real) / 4));
  for (std::size_t p = 0; p < n; ++p) {
    const Real m = a.particle_mass(p);
    rec.append(reinterpret_cast<const char*>(&m), sizeof m);
  }
  std::string d = v8;
  std::uint32_t nattr;
  std::memcpy(&nattr, d.data() + kCountAt + 8, 4);
  ++nattr;
  std::memcpy(d.data() + kCountAt + 8, &nattr, 4);
  d.insert(kCountAt + 12, rec);
  spit(old, with_field(d, 13, std::uint32_t(7)));
  read_checkpoint(old, sim_b, scene.fingerprint);
  const ParticleSet &pa = a.particles(), &pb = sim_b.solver().particles();
  ASSERT_EQ(pb.size(), pa.size());
  for (int at = 0; at < pa.attribute_count(); ++at)
    EXPECT_EQ(
        std::memcmp(pa.words(at), pb.words(at), pa.size() * 4 * size_t(pa.words_per_particle(at))),
        0)
        << pa.name(at);
  spit(old, resealed(d));  // version 8 with a mass attribute (one more, as `rest` could be)
  EXPECT_NE(error_reading(old, scene.fingerprint)
                .find("checkpoint attribute 'mass' does not match this solver's layout"),
            std::string::npos);
  // Two more than the layout (three where the run keeps b - I, which a file's F and F_lo may
  // stand for): the count alone refuses it.
  const std::uint32_t layout = nattr - 1;
  nattr = layout + (a.attributes().b >= 0 ? 3 : 2);
  std::memcpy(d.data() + kCountAt + 8, &nattr, 4);
  spit(old, resealed(d));
  EXPECT_NE(error_reading(old, scene.fingerprint)
                .find("checkpoint has " + std::to_string(nattr) +
                      " particle attributes, expected " + std::to_string(layout)),
            std::string::npos);
  std::remove(path.c_str());
  std::remove(old.c_str());
}

// `--resume` of a device, a FIFO or a directory is refused before anything is read (reading
// /dev/zero whole ended in std::bad_alloc).
TEST(Checkpoint, OnlyRegularFilesAreRead) {
  EXPECT_NE(error_reading("/dev/zero", 0).find("/dev/zero: checkpoint is not a regular file"),
            std::string::npos);
  EXPECT_NE(error_reading(std::filesystem::temp_directory_path().string(), 0)
                .find("checkpoint is a directory"),
            std::string::npos);
}

// Emitters and kill regions (checkpoint format 6): the particle count varies, and the state
// section sources.state (next id, emitted, killed) must agree with the particles and ids it
// comes with, whatever the checksum says.
TEST(Checkpoint, EmissionStateIsCheckedAgainstTheParticles) {
  const std::string text = R"({
    "simulation": {"dx": 0.05, "frames": 2, "max_dt": 2e-3,
                   "kill": {"outside": {"min": [0, 0.3, 0], "max": [1, 1, 1]}}},
    "materials": {"water": {"model": "fluid", "density": 1000, "bulk_modulus": 1e4}},
    "objects": [{"shape": "box", "min": [0.1, 0.35, 0.1], "max": [0.3, 0.45, 0.3], "material": "water",
                 "velocity": [0, -2, 0]}],
    "emitters": [{"shape": "box", "min": [0.45, 0.8, 0.45], "max": [0.55, 0.9, 0.55],
                  "material": "water", "velocity": [0, -4, 0], "end": 1.0}]
  })";
  const Scene scene = parse_scene(text, "e.json");
  MpmSimulation a(build_solver(scene));
  const exec::Space space;
  while (a.solver().source_counters().killed == 0 || a.solver().source_counters().emitted == 0)
    a.advance(space, a.stable_dt(space));
  const std::string path = tmp_path("sources.amck"), bad = tmp_path("sources_bad.amck");
  write_checkpoint(path, a, 1, scene.fingerprint);
  const std::string good = slurp(path);
  auto error_of = [&](const std::string& d) {
    spit(bad, d);
    MpmSimulation s(build_solver(scene));
    try {
      read_checkpoint(bad, s, scene.fingerprint);
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  ASSERT_EQ(error_of(good), "");
  const std::size_t name = good.find("sources.state");
  ASSERT_NE(name, std::string::npos);
  const std::size_t state = name + std::strlen("sources.state") + 8;  // after the u64 size
  std::int64_t next, emitted, killed;
  std::memcpy(&next, good.data() + state, 8);
  std::memcpy(&emitted, good.data() + state + 8, 8);
  std::memcpy(&killed, good.data() + state + 16, 8);
  ASSERT_EQ(next, std::int64_t(a.solver().next_id()));
  ASSERT_GT(emitted, 0);
  ASSERT_GT(killed, 0);
  // A next id below an id in use would hand that id out again.
  EXPECT_NE(error_of(with_field(good, state, next - 1)).find("disagree"), std::string::npos);
  EXPECT_NE(error_of(with_field(good, state, std::int64_t(1) << 40))
                .find("section sources.state: next particle id 1099511627776 is outside"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, state + 8, std::int64_t(-1))).find("emitted -1"),
            std::string::npos);
  EXPECT_NE(error_of(with_field(good, state + 16, killed + 1)).find("disagree"), std::string::npos);
  // An id repeated among the particles.
  const std::size_t id = attribute_data_at(good, "id");
  std::int32_t id0;
  std::memcpy(&id0, good.data() + id, 4);
  EXPECT_NE(error_of(with_field(good, id + 4, id0)).find("'id'"), std::string::npos);
  std::remove(path.c_str());
  std::remove(bad.c_str());
}

// The output attribute `rest` is a particle attribute: each particle keeps the position it was
// made at (set-up or emission) through sorting, steps and checkpoints; a checkpoint that has it
// is read by a run that does not ask for it, and one written without it gives a run that asks the
// set-up's positions by id, unless particles were emitted since (no rest position to recover).
TEST(Checkpoint, RestPositionsTravelWithTheirParticles) {
  const std::string text = R"({
    "simulation": {"dx": 0.05, "frames": 2, "max_dt": 2e-3},
    "materials": {"water": {"model": "fluid", "density": 1000, "bulk_modulus": 1e4}},
    "objects": [{"shape": "box", "min": [0.1, 0.35, 0.1], "max": [0.3, 0.45, 0.3], "material": "water",
                 "velocity": [0, -2, 0]}],
    "emitters": [{"shape": "box", "min": [0.45, 0.8, 0.45], "max": [0.55, 0.9, 0.55],
                  "material": "water", "velocity": [0, -4, 0], "end": 1.0}],
    "output": {"attributes": ["rest"]}
  })";
  const Scene scene = parse_scene(text, "e.json");
  const exec::Space space(exec::Backend::TBB, 2);
  auto positions = [](const MpmSolver& s, ParticleSet::Id attr) {
    std::map<std::int32_t, Vec3> m;
    const Vec3* x = s.particles().vec3(attr);
    const std::int32_t* id = s.particles().int32(s.attributes().id);
    for (std::size_t i = 0; i < s.particles().size(); ++i) m[id[i]] = x[i];
    return m;
  };
  MpmSimulation a(build_solver(scene));
  a.keep_rest_positions();
  const MpmSolver& sa = a.solver();
  ASSERT_GE(sa.attributes().rest, 0);
  std::map<std::int32_t, Vec3> made = positions(sa, sa.attributes().x);  // where each was made
  const std::size_t set_up = made.size();
  for (int k = 0; k < 40; ++k) {
    const std::int64_t before = sa.next_id();
    a.advance(space, a.stable_dt(space));
    for (const auto& [id, x] : positions(sa, sa.attributes().x))
      if (id >= before) made.emplace(id, x);  // emitted in this substep, not moved yet
  }
  ASSERT_GT(made.size(), set_up);
  std::size_t moved = 0;
  const std::map<std::int32_t, Vec3> now = positions(sa, sa.attributes().x);
  for (const auto& [id, r] : positions(sa, sa.attributes().rest)) {
    ASSERT_TRUE(made.count(id)) << id;
    EXPECT_EQ(r, made.at(id)) << "particle " << id;
    moved += now.at(id) != r;
  }
  EXPECT_GT(moved, set_up / 2);  // the rest positions are not the current ones

  const std::string with = tmp_path("rest.amck"), without = tmp_path("no_rest.amck");
  write_checkpoint(with, a, 2, scene.fingerprint);
  {  // read back with rest: every attribute bitwise
    MpmSimulation b(build_solver(scene));
    b.keep_rest_positions();
    read_checkpoint(with, b, scene.fingerprint);
    const ParticleSet &pa = sa.particles(), &pb = b.solver().particles();
    ASSERT_EQ(pa.attribute_count(), pb.attribute_count());
    for (int at = 0; at < pa.attribute_count(); ++at)
      EXPECT_EQ(std::memcmp(pa.words(at), pb.words(at),
                            pa.size() * 4 * size_t(pa.words_per_particle(at))),
                0)
          << pa.name(at);
  }
  {  // a run without rest skips it
    MpmSimulation c(build_solver(scene));
    read_checkpoint(with, c, scene.fingerprint);
    EXPECT_LT(c.solver().attributes().rest, 0);
    EXPECT_EQ(positions(c.solver(), c.solver().attributes().x), now);
    // ... and its own checkpoint, without rest, cannot give emitted particles theirs.
    write_checkpoint(without, c, 2, scene.fingerprint);
    MpmSimulation d(build_solver(scene));
    d.keep_rest_positions();
    try {
      read_checkpoint(without, d, scene.fingerprint);
      ADD_FAILURE() << "emitted particles got a rest position";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find(without + ": particle attribute 'rest'"),
                std::string::npos)
          << e.what();
      EXPECT_NE(std::string(e.what()).find("emitted after set-up"), std::string::npos);
    }
  }
  // Without emission, a checkpoint lacking rest gives the set-up's positions by id.
  const Scene plain = parse_scene(kScene, "s.json");
  MpmSimulation e(build_solver(plain));
  const std::map<std::int32_t, Vec3> start = positions(e.solver(), e.solver().attributes().x);
  for (int k = 0; k < 10; ++k) e.advance(space, e.stable_dt(space));
  write_checkpoint(without, e, 2, plain.fingerprint);
  MpmSimulation f(build_solver(plain));
  f.keep_rest_positions();
  read_checkpoint(without, f, plain.fingerprint);
  EXPECT_EQ(positions(f.solver(), f.solver().attributes().rest), start);
  EXPECT_EQ(positions(f.solver(), f.solver().attributes().x),
            positions(e.solver(), e.solver().attributes().x));
  std::remove(with.c_str());
  std::remove(without.c_str());
}

// A run whose materials are all fluids keeps J = det F alone, no F nor its low part F_lo
// (MpmSolver::keeps_J_only). A checkpoint an older binary wrote for such a run holds F and F_lo
// where the run has J: it is read with J = det F and F_lo skipped, and resumes bitwise as the
// run that wrote J (whose J is set to det F of the F written, F full and non-symmetric: a reader
// taking a diagonal entry, the diagonal's product or anything but the determinant fails). A file
// with both F and J, in either order, is refused; so is a file without F_lo read by a run keeping
// it (no binary writes one).
TEST(Checkpoint, FluidFileWithFReadAsJAndLowPartRefusedWhereAbsent) {
  std::string water_text = kScene;
  water_text.replace(water_text.find("\"youngs_modulus\": 1e4"), 21,
                     "\"model\": \"fluid\", \"bulk_modulus\": 2e5");
  water_text.replace(water_text.find("\"velocity\": [0,-1,0]"), 20,
                     "\"velocity\": [0,-1,0], \"angular_velocity\": [1,2,3]");
  // Sorted every substep: a run that keeps its bins between sorts re-sorts at a frame's start,
  // which advance() alone does not make (the CLI's restart tests cover that).
  water_text.replace(water_text.find("\"frames\": 2"), 11,
                     "\"frames\": 2, \"sort\": \"every_substep\"");
  const Scene water = parse_scene(water_text, "water.json");
  const exec::Space space(exec::Backend::TBB, 2);
  MpmSimulation a(build_solver(water)), b(build_solver(water));
  ASSERT_LT(a.solver().attributes().F_lo, 0);
  ASSERT_LT(a.solver().attributes().F, 0);
  const int jid = a.solver().attributes().J;
  ASSERT_GE(jid, 0);
  for (int i = 0; i < 5; ++i) a.advance(space, a.stable_dt(space));
  const std::string path = tmp_path("water.amck"), old = tmp_path("water_old.amck");
  write_checkpoint(path, a, 2, water.fingerprint);
  const std::string now = slurp(path);
  EXPECT_EQ(attribute_data_at(now, "F_lo"), std::string::npos);
  EXPECT_EQ(attribute_data_at(now, "F"), std::string::npos);
  std::uint64_t n;
  std::memcpy(&n, now.data() + kCountAt, 8);
  Real* J = a.solver().particles().real(jid);
  ASSERT_TRUE(std::any_of(J, J + n, [](Real j) { return j != 1; }));
  // Each particle's F: its J's shape, sheared and rotated a little (every entry non-zero, F not
  // symmetric); a's J becomes det F, the value the reader must compute.
  std::vector<Mat3> Fs(static_cast<std::size_t>(n));
  for (std::uint64_t i = 0; i < n; ++i) {
    Mat3 F = Mat3::Identity() * std::cbrt(J[i]);
    for (int k = 0; k < 9; ++k)
      F(k) += Real(0.004) * Real(int((i * 7 + std::uint64_t(k) * 5) % 11) - 5);
    Fs[std::size_t(i)] = F;
    J[i] = F.determinant();
    ASSERT_NE(J[i], F(0, 0) * F(1, 1) * F(2, 2)) << i;
  }
  write_checkpoint(path, a, 2, water.fingerprint);
  const std::string now_F = slurp(path);
  // As the older binary wrote it: "F" and "F_lo" (9 Reals a particle each) where "J" is.
  std::string rec;
  auto put32 = [&](std::uint32_t v) { rec.append(reinterpret_cast<const char*>(&v), 4); };
  auto header = [&](const std::string& name) {
    put32(std::uint32_t(name.size()));
    rec += name;
    put32(0);  // AttrType::Real
    put32(9);
    put32(std::uint32_t(9 * sizeof(Real) / 4));
  };
  header("F");
  for (const Mat3& F : Fs) rec.append(reinterpret_cast<const char*>(F.data()), sizeof(Mat3));
  header("F_lo");
  rec.append(std::size_t(n) * sizeof(Mat3), '\0');
  std::string d = now_F;
  const std::size_t j_data = attribute_data_at(d, "J");
  ASSERT_NE(j_data, std::string::npos);
  const std::size_t j_record = j_data - (4 + 1 + 12);  // name length, "J", type, width, words
  d.replace(j_record, j_data - j_record + std::size_t(n) * sizeof(Real), rec);
  std::uint32_t nattr;
  std::memcpy(&nattr, d.data() + kCountAt + 8, 4);
  ++nattr;  // F and F_lo for J
  std::memcpy(d.data() + kCountAt + 8, &nattr, 4);
  spit(old, resealed(d));
  ASSERT_NE(attribute_data_at(slurp(old), "F_lo"), std::string::npos);
  read_checkpoint(old, b, water.fingerprint);
  const ParticleSet &pa = a.solver().particles(), &pb = b.solver().particles();
  ASSERT_EQ(pa.attribute_count(), pb.attribute_count());
  auto same = [](const ParticleSet& p, const ParticleSet& q) {
    for (int at = 0; at < p.attribute_count(); ++at)
      if (std::memcmp(p.words(at), q.words(at), p.size() * 4 * size_t(p.words_per_particle(at))) !=
          0)
        return p.name(at);
    return std::string();
  };
  EXPECT_EQ(same(pa, pb), "");
  for (int i = 0; i < 5; ++i) {
    a.advance(space, a.stable_dt(space));
    b.advance(space, b.stable_dt(space));
  }
  EXPECT_EQ(same(pa, pb), "");  // resumed bitwise

  // A file holding both F and J, J before F or after F_lo: refused by name.
  const std::string J_record = now.substr(attribute_data_at(now, "J") - (4 + 1 + 12),
                                          4 + 1 + 12 + std::size_t(n) * sizeof(Real));
  for (const bool J_first : {true, false}) {
    std::string both = d;
    both.insert(J_first ? attribute_data_at(both, "v") + std::size_t(n) * sizeof(Vec3)
                        : attribute_data_at(both, "F_lo") + std::size_t(n) * sizeof(Mat3),
                J_record);
    std::memcpy(&nattr, both.data() + kCountAt + 8, 4);
    ++nattr;
    std::memcpy(both.data() + kCountAt + 8, &nattr, 4);
    spit(old, resealed(both));
    MpmSimulation c(build_solver(water));
    try {
      read_checkpoint(old, c, water.fingerprint);
      ADD_FAILURE() << "a fluid run read a checkpoint holding both F and J";
    } catch (const InputError& err) {
      EXPECT_NE(std::string(err.what())
                    .find(old + ": checkpoint attributes 'F' and 'J' both hold the volume ratio"),
                std::string::npos)
          << err.what();
    }
  }

  // A jelly run's checkpoint without F_lo: refused (the attribute count, or F_lo by name when
  // the count allows an optional attribute's absence). The run keeps F, as for an output of F
  // (else it keeps b - I: LeftCauchyGreen below).
  Scene jelly = parse_scene(kScene, "s.json");
  jelly.mpm.keep_F = true;
  MpmSimulation j(build_solver(jelly));
  const int lo = j.solver().attributes().F_lo;
  ASSERT_GE(lo, 0);
  for (int i = 0; i < 5; ++i) j.advance(space, j.stable_dt(space));
  for (const bool rest : {false, true}) {
    MpmSimulation r(build_solver(jelly));
    if (rest) j.keep_rest_positions(), r.keep_rest_positions();
    write_checkpoint(path, j, 2, jelly.fingerprint);
    std::string e = slurp(path);
    const std::size_t lo_data = attribute_data_at(e, "F_lo");
    ASSERT_NE(lo_data, std::string::npos);
    const std::size_t lo_record =
        lo_data - (4 + 4 + 12);  // name length, "F_lo", type, width, words
    e.erase(lo_record, lo_data - lo_record + j.solver().particles().size() * sizeof(Mat3));
    std::memcpy(&nattr, e.data() + kCountAt + 8, 4);
    --nattr;
    std::memcpy(e.data() + kCountAt + 8, &nattr, 4);
    spit(old, resealed(e));
    try {
      read_checkpoint(old, r, jelly.fingerprint);
      ADD_FAILURE() << "a jelly run read a checkpoint without F_lo";
    } catch (const InputError& err) {
      const std::string what = err.what();
      EXPECT_NE(what.find(old + (rest ? ": checkpoint has no particle attribute 'F_lo'"
                                      : ": checkpoint has ")),
                std::string::npos)
          << what;
    }
  }
  std::remove(path.c_str());
  std::remove(old.c_str());
}

// PIC/FLIP runs of materials without viscosity keep no affine matrix C (MpmSolver::keeps_affine).
// A checkpoint an older binary wrote for such a run holds C after v: it is read with C skipped
// and resumes bitwise as the run that wrote it (C was never read). An APIC/MLS run refuses a file
// without C, naming the file and the attribute.
TEST(Checkpoint, AffineMatrixOnlyWhereTheTransferNeedsIt) {
  std::string flip_text = kScene;
  flip_text.replace(flip_text.find("\"frames\": 2"), 11, "\"frames\": 2, \"transfer\": \"flip\"");
  const Scene flip = parse_scene(flip_text, "flip.json");
  const exec::Space space(exec::Backend::TBB, 2);
  MpmSimulation a(build_solver(flip)), b(build_solver(flip));
  ASSERT_LT(a.solver().attributes().C, 0);
  for (int i = 0; i < 5; ++i) a.advance(space, a.stable_dt(space));
  const std::string path = tmp_path("flip.amck"), old = tmp_path("flip_old.amck");
  write_checkpoint(path, a, 2, flip.fingerprint);
  const std::string now = slurp(path);
  EXPECT_EQ(attribute_data_at(now, "C"), std::string::npos);
  // As the older binary wrote it: "C" (9 Reals a particle, here arbitrary finite values) after v.
  std::uint64_t n;
  std::memcpy(&n, now.data() + kCountAt, 8);
  std::string rec;
  auto put32 = [&](std::uint32_t v) { rec.append(reinterpret_cast<const char*>(&v), 4); };
  put32(1);
  rec += "C";
  put32(0);  // AttrType::Real
  put32(9);
  put32(std::uint32_t(9 * sizeof(Real) / 4));
  for (std::size_t k = 0; k < 9 * n; ++k) {
    const Real c = Real(0.25) * Real(k % 7) - Real(0.5);
    rec.append(reinterpret_cast<const char*>(&c), sizeof c);
  }
  std::string d = now;
  std::uint32_t nattr;
  std::memcpy(&nattr, d.data() + kCountAt + 8, 4);
  ++nattr;
  std::memcpy(d.data() + kCountAt + 8, &nattr, 4);
  d.insert(attribute_data_at(d, "v") + std::size_t(n) * sizeof(Vec3), rec);
  spit(old, resealed(d));
  ASSERT_NE(attribute_data_at(slurp(old), "C"), std::string::npos);
  read_checkpoint(old, b, flip.fingerprint);
  const ParticleSet &pa = a.solver().particles(), &pb = b.solver().particles();
  ASSERT_EQ(pa.attribute_count(), pb.attribute_count());
  auto same = [&] {
    for (int at = 0; at < pa.attribute_count(); ++at)
      if (std::memcmp(pa.words(at), pb.words(at),
                      pa.size() * 4 * size_t(pa.words_per_particle(at))) != 0)
        return pa.name(at);
    return std::string();
  };
  EXPECT_EQ(same(), "");
  for (int i = 0; i < 5; ++i) {
    a.advance(space, a.stable_dt(space));
    b.advance(space, b.stable_dt(space));
  }
  EXPECT_EQ(same(), "");  // resumed bitwise

  // An MLS run's checkpoint without C: refused by name (also when rest may be absent too).
  const Scene mls = parse_scene(kScene, "s.json");
  MpmSimulation m(build_solver(mls));
  ASSERT_GE(m.solver().attributes().C, 0);
  m.advance(space, m.stable_dt(space));
  write_checkpoint(path, m, 2, mls.fingerprint);
  std::string e = slurp(path);
  const std::size_t c_data = attribute_data_at(e, "C");
  ASSERT_NE(c_data, std::string::npos);
  const std::size_t c_record = c_data - (4 + 1 + 12);  // name length, "C", type, width, words
  e.erase(c_record, c_data - c_record + m.solver().particles().size() * sizeof(Mat3));
  std::memcpy(&nattr, e.data() + kCountAt + 8, 4);
  --nattr;
  std::memcpy(e.data() + kCountAt + 8, &nattr, 4);
  spit(old, resealed(e));
  for (const bool rest : {false, true}) {
    MpmSimulation r(build_solver(mls));
    if (rest) r.keep_rest_positions();
    try {
      read_checkpoint(old, r, mls.fingerprint);
      ADD_FAILURE() << "an MLS run read a checkpoint without C";
    } catch (const InputError& err) {
      EXPECT_NE(std::string(err.what()).find(old + ": checkpoint has no particle attribute 'C'"),
                std::string::npos)
          << err.what();
    }
  }
  std::remove(path.c_str());
  std::remove(old.c_str());
}

// A run keeping b - I of b = F F^T (MpmSolver::keeps_b) reads a checkpoint holding F and F_lo (an
// older binary's, or a run that output F) with b - I = (F + F_lo)(F + F_lo)^T - I, and goes on
// as that run does, to rounding; a run keeping F refuses a file holding b, naming it; a b that is
// not positive definite (a hostile file) is refused naming the attribute and the particle.
TEST(Checkpoint, LeftCauchyGreenFromAFileHoldingF) {
  const exec::Space space(exec::Backend::TBB, 2);
  Scene with_F = parse_scene(kScene, "s.json");
  with_F.mpm.keep_F = true;
  const Scene with_b = parse_scene(kScene, "s.json");
  MpmSimulation f(build_solver(with_F)), b(build_solver(with_b)), b2(build_solver(with_b));
  ASSERT_GE(f.solver().attributes().F_lo, 0);
  ASSERT_GE(b.solver().attributes().b, 0);
  for (int i = 0; i < 20; ++i) f.advance(space, f.stable_dt(space));
  const std::string path = tmp_path("lcg.amck"), bpath = tmp_path("lcg_b.amck");
  write_checkpoint(path, f, 2, with_F.fingerprint);
  read_checkpoint(path, b, with_b.fingerprint);
  const ParticleSet &pf = f.solver().particles(), &pb = b.solver().particles();
  ASSERT_EQ(pf.size(), pb.size());
  double most = 0;
  for (std::size_t i = 0; i < pf.size(); ++i) {
    const Eigen::Matrix3d F = pf.mat3(f.solver().attributes().F)[i].cast<double>() +
                              pf.mat3(f.solver().attributes().F_lo)[i].cast<double>();
    const SymDev want = b_from_F<Real>(F);
    const SymDev& got = pb.sym_dev(b.solver().attributes().b)[i];
    for (int e = 0; e < 6; ++e) ASSERT_EQ(got.e[e], want.e[e]) << i;
    most = std::max(most, (F * F.transpose() - Eigen::Matrix3d::Identity()).norm());
  }
  EXPECT_GT(most, 1e-7);  // the jelly deformed: the conversion converted something
  for (int i = 0; i < 20; ++i) {
    const Real dt = f.stable_dt(space);
    f.advance(space, dt);
    b.advance(space, dt);
  }
  const std::vector<Vec3d> xf = f.solver().positions_by_id(), xb = b.solver().positions_by_id();
  double dx_most = 0;
  for (std::size_t i = 0; i < xf.size(); ++i) dx_most = std::max(dx_most, (xf[i] - xb[i]).norm());
  EXPECT_LT(dx_most, 1e-4 * double(with_b.mpm.dx));

  write_checkpoint(bpath, b, 3, with_b.fingerprint);
  std::string bytes = slurp(bpath);
  ASSERT_NE(attribute_data_at(bytes, "b"), std::string::npos);
  EXPECT_EQ(attribute_data_at(bytes, "F"), std::string::npos);
  read_checkpoint(bpath, b2, with_b.fingerprint);  // b - I as written
  MpmSimulation f2(build_solver(with_F));
  try {
    read_checkpoint(bpath, f2, with_F.fingerprint);
    ADD_FAILURE() << "a run keeping F read a checkpoint holding b";
  } catch (const InputError& err) {
    EXPECT_NE(std::string(err.what()).find(bpath + ": checkpoint holds 'b'"), std::string::npos)
        << err.what();
  }
  // b(0, 0) = 1 + D(0, 0) = -1 for one particle: not a b = F F^T.
  const std::size_t at = attribute_data_at(bytes, "b") + 5 * sizeof(SymDev);
  const Real minus2 = -2;
  std::memcpy(&bytes[at], &minus2, sizeof(Real));
  spit(bpath, resealed(bytes));
  MpmSimulation b3(build_solver(with_b));
  try {
    read_checkpoint(bpath, b3, with_b.fingerprint);
    ADD_FAILURE() << "a checkpoint with a b that is not positive definite was read";
  } catch (const InputError& err) {
    EXPECT_NE(
        std::string(err.what()).find("attribute 'b' of particle 5 is not b - I of a positive"),
        std::string::npos)
        << err.what();
  }
  std::remove(path.c_str());
  std::remove(bpath.c_str());
}
