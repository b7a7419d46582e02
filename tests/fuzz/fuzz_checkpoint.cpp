// libFuzzer target for checkpoint reading: any byte string given to `--resume` must either load
// into the simulation or be rejected with an InputError; a crash, a sanitizer report, another
// exception or a large allocation is a bug. The first byte chooses the simulation (explicit MPM,
// A-ULMPM, enriched MPM, peridynamics, and explicit MPM of a fluid alone, which keeps J instead of
// F: MpmSolver::keeps_J_only); the rest is the file, whose scene fingerprint and
// checksum are rewritten to match before reading, so the fuzzer gets past the checksum into the
// header, attribute and section parsing (a hostile writer can seal its file too). Seeds: real
// checkpoints of the five scenes (scripts/fuzz.sh writes them). Build and run: docs/fuzzing.md.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <memory>
#include <string>

#include "core/errors.hpp"
#include "core/hash.hpp"
#include "io/checkpoint.hpp"
#include "io/scene.hpp"
#include "solvers/factory.hpp"

namespace {
constexpr int kCases = 5;
const char* const kScenes[kCases] = {
    R"({"simulation": {"dx": 0.1}, "materials": {"m": {"density": 1000, "youngs_modulus": 1e4}},
        "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "m"}]})",
    R"({"simulation": {"dx": 0.1}, "materials": {"m": {"density": 1000, "youngs_modulus": 1e4}},
        "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "m",
                     "configuration": {"update": "adaptive"}}]})",
    R"({"simulation": {"dx": 0.1, "domains": {}},
        "materials": {"m": {"density": 1000, "youngs_modulus": 1e4}},
        "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "m",
                     "jitter": 0}]})",
    R"({"simulation": {"method": "peridynamics", "dx": 0.01},
        "materials": {"g": {"model": "peridynamic", "density": 2200, "youngs_modulus": 1e7,
                            "critical_stretch": 0.01}},
        "objects": [{"shape": "box", "min": [0,0,0], "max": [0.04,0.04,0.04], "material": "g"}]})",
    R"({"simulation": {"dx": 0.1},
        "materials": {"w": {"model": "fluid", "density": 1000, "bulk_modulus": 2e5}},
        "objects": [{"shape": "box", "min": [0.4,0.4,0.4], "max": [0.6,0.6,0.6], "material": "w"}]})"};

struct Case {
  amalgam::Scene scene;
  std::unique_ptr<amalgam::Simulation> sim;
};

Case& case_of(int k) {
  static std::unique_ptr<Case> cases[kCases];
  if (!cases[k]) {
    cases[k] = std::make_unique<Case>();
    cases[k]->scene = amalgam::parse_scene(kScenes[k], "fuzz.json");
    cases[k]->sim = amalgam::make_simulation(cases[k]->scene, amalgam::exec::Space());
    // FUZZ_CHECKPOINT_SEEDS=DIR writes each case's own checkpoint there (the seed corpus).
    if (const char* dir = std::getenv("FUZZ_CHECKPOINT_SEEDS")) {
      const std::string path = std::string(dir) + "/seed_" + std::to_string(k) + ".amck";
      amalgam::write_checkpoint(path, *cases[k]->sim, 1, cases[k]->scene.fingerprint);
      std::ifstream in(path, std::ios::binary);
      std::string d((std::istreambuf_iterator<char>(in)), {});
      std::ofstream(path, std::ios::binary) << char(k) << d;
    }
  }
  return *cases[k];
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  const int k = data[0] % kCases;
  Case& c = case_of(k);
  std::string d(reinterpret_cast<const char*>(data) + 1, size - 1);
  if (d.size() >= 37) std::memcpy(d.data() + 21, &c.scene.fingerprint, 8);
  if (d.size() >= 8 + 13) {
    const std::uint64_t sum = amalgam::fnv1a64(d.data(), d.size() - 8);
    std::memcpy(d.data() + d.size() - 8, &sum, 8);
  }
  static const std::string path = "/tmp/amalgam_fuzz_" + std::to_string(getpid()) + ".amck";
  std::ofstream(path, std::ios::binary | std::ios::trunc)
      .write(d.data(), std::streamsize(d.size()));
  try {
    amalgam::read_checkpoint(path, *c.sim, c.scene.fingerprint);
  } catch (const amalgam::InputError&) {
  }
  return 0;
}
