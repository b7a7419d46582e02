// libFuzzer target for the scene parser: any byte string must either parse into a Scene or be
// rejected with an InputError; anything else (crash, sanitizer report, other exception) is a bug.
// Build and run: see docs/fuzzing.md.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/errors.hpp"
#include "io/scene.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    const amalgam::Scene s = amalgam::parse_scene(text, "fuzz.json");
    if (s.objects.empty() || !(s.mpm.dx > 0)) __builtin_trap();  // parse_scene guarantees both
  } catch (const amalgam::InputError&) {
  }
  return 0;
}
