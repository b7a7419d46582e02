// Internal to io/scene*.cpp: the helpers every method's part of scene parsing shares, and the
// parts themselves (io/scene_mpm.cpp, io/scene_pd.cpp), called by parse_scene (io/scene.cpp) in
// this order: simulation keys, objects check, materials, conditions.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "io/json_reader.hpp"
#include "io/scene.hpp"

namespace amalgam::scene_detail {

using detail::JsonObject;

constexpr double kHuge = 1e30;

// A file named in a scene: absolute, or relative to the scene file's folder.
std::filesystem::path scene_relative(const std::string& file, const std::string& scene_file);
// Keys "min" and "max" of a box, max above min in every component.
void read_box(JsonObject& o, Vec3& min, Vec3& max);
// Geometry and motion shared by colliders and heat sources (mesh: the caller reads the mesh).
Collider read_region(JsonObject& o, bool allow_mesh = false);
// `until` (s): the region acts up to this time only (a grip that lets go, a heater switched off).
void read_until(JsonObject& o, Collider& c);

// MPM (io/scene_mpm.cpp).
void read_mpm_simulation(JsonObject& sim, Scene& s);
void check_mpm_objects(JsonObject& sim, Scene& s);
void read_mpm_materials(JsonObject& mats, Scene& s);
void read_mpm_sources(JsonObject& top, Scene& s);

// Peridynamics (io/scene_pd.cpp).
void read_pd_simulation(JsonObject& sim, Scene& s);
void pd_spacing(JsonObject& top, Scene& s);
void read_pd_materials(JsonObject& mats, Scene& s);
void read_pd_conditions(JsonObject& top, Scene& s);

}  // namespace amalgam::scene_detail
