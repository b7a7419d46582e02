// libFuzzer target for the mesh readers (OBJ, OFF, PLY, STL): any byte string must either read
// into a mesh whose indices all address its vertices, or be rejected with an InputError; a
// crash, a sanitizer report, another exception, or a large allocation (-rss_limit_mb) is a bug.
// The first byte chooses the format, the rest is the file. Build and run: docs/fuzzing.md.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/errors.hpp"
#include "io/mesh.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  static const char* const kNames[4] = {"fuzz.obj", "fuzz.off", "fuzz.ply", "fuzz.stl"};
  const std::string bytes(reinterpret_cast<const char*>(data) + 1, size - 1);
  try {
    const amalgam::TriangleMesh m = amalgam::parse_mesh(bytes, kNames[data[0] % 4]);
    for (const auto& t : m.triangles)
      for (const auto i : t)
        if (i < 0 || std::size_t(i) >= m.vertices.size()) __builtin_trap();
  } catch (const amalgam::InputError&) {
  }
  return 0;
}
