// What a frame writer (PLY, VDB points, previews) needs of any method's particles: positions,
// velocities, a stable id and the material index, plus the typed attributes the scene's
// output.attributes asks for (docs/output.md), written after P and v in the order asked.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

// The names output.attributes accepts (beyond P, v, id, always written), in documentation order:
// deformation gradient, det F, plastic scalar, von Mises stress, peridynamic damage, rest
// position, material index, temperature (melting MPM), enrichment state (particle domains),
// dilatation (peridynamics). Which ones a scene's method has is checked when the scene is read.
inline const std::vector<std::string>& point_attribute_names() {
  static const std::vector<std::string> names = {"F",          "J",    "Jp",       "vonmises",
                                                 "damage",     "rest", "material", "temperature",
                                                 "enrichment", "theta"};
  return names;
}

// One per-particle output attribute: Float (1 float), Vec3 (3), Mat3 (9, row-major: F00 F01 F02
// F10 ...) or Int (int32).
struct PointAttribute {
  enum class Type { Float, Vec3, Mat3, Int };
  std::string name;
  Type type = Type::Float;
  std::vector<float> f;         // n * width() values (Float, Vec3, Mat3)
  std::vector<std::int32_t> i;  // n values (Int)
  int width() const { return type == Type::Vec3 ? 3 : type == Type::Mat3 ? 9 : 1; }
};

struct PointFields {
  std::size_t n = 0;
  const Vec3* x = nullptr;
  const Vec3* v = nullptr;
  const std::int32_t* material = nullptr;  // always set (previews, surfacing); written on request
  const std::int32_t* id = nullptr;
  std::vector<PointAttribute> attributes;   // written after P and v, in this order
  std::vector<std::string> material_names;  // by index: VDB metadata when `material` is written
  // The Float attribute of that name, or null.
  const std::vector<float>* find(const std::string& name) const {
    for (const auto& a : attributes)
      if (a.name == name && a.type == PointAttribute::Type::Float) return &a.f;
    return nullptr;
  }
};

// A PointFields that owns its particle arrays: a copy of positions, velocities, materials and ids
// taken after a frame's last substep, which asynchronous output writes while the simulation moves
// on (apps/frame_loop.cpp). Not copyable: `fields` points into the vectors (a move keeps their
// buffers).
struct PointSnapshot {
  std::vector<Vec3> x, v;
  std::vector<std::int32_t> material, id;
  PointFields fields;

  explicit PointSnapshot(PointFields p)
      : x(p.x, p.x + p.n),
        v(p.v, p.v + p.n),
        material(p.material, p.material + p.n),
        id(p.id, p.id + p.n),
        fields(std::move(p)) {
    fields.x = x.data();
    fields.v = v.data();
    fields.material = material.data();
    fields.id = id.data();
  }
  PointSnapshot(const PointSnapshot&) = delete;
  PointSnapshot& operator=(const PointSnapshot&) = delete;
};

// A triangle surface written per frame (particle surfaces, enriched MPM's embedded meshes,
// peridynamic crack meshes; io/writers.hpp write_mesh_obj / write_mesh_ply). Optional arrays are
// empty when absent: normals and velocity have one entry per vertex, crack one per triangle
// (crack[f] = 1 marks crack faces).
struct SurfaceMesh {
  std::vector<Vec3> vertices;
  std::vector<std::array<std::uint32_t, 3>> triangles;
  std::vector<Vec3> normals;        // unit vertex normals
  std::vector<Vec3> velocity;       // m/s
  std::vector<std::uint8_t> crack;  // per triangle
};

}  // namespace amalgam
