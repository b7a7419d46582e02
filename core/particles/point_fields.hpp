// What a frame writer (PLY, VDB points, previews) needs of any method's particles: positions,
// velocities, material and a stable id, plus named float attributes, `primary` written before
// material and id, `extra` after them (the PLY property order; VDB points keep the names).
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

struct PointFields {
  std::size_t n = 0;
  const Vec3* x = nullptr;
  const Vec3* v = nullptr;
  const std::int32_t* material = nullptr;
  const std::int32_t* id = nullptr;
  std::vector<std::pair<std::string, std::vector<float>>> primary, extra;
  // The float attribute of that name (primary or extra), or null.
  const std::vector<float>* find(const std::string& name) const {
    for (const auto* list : {&primary, &extra})
      for (const auto& a : *list)
        if (a.first == name) return &a.second;
    return nullptr;
  }
};

// A triangle surface written per frame (enriched MPM's embedded meshes, peridynamic crack
// meshes): crack[f] = 1 marks crack faces.
struct SurfaceMesh {
  std::vector<Vec3> vertices;
  std::vector<std::array<std::uint32_t, 3>> triangles;
  std::vector<std::uint8_t> crack;
};

}  // namespace amalgam
