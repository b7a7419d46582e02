#include "io/scene.hpp"

#include <algorithm>
#include <cctype>
#include <cstdio>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <sstream>

#include "core/errors.hpp"
#include "core/geometry/level_set_collider.hpp"
#include "core/hash.hpp"
#include "io/files.hpp"
#include "io/mesh.hpp"
#include "io/scene_parts.hpp"
#include "io/tetmesh.hpp"

namespace amalgam {

namespace scene_detail {

std::filesystem::path scene_relative(const std::string& file, const std::string& scene_file) {
  return std::filesystem::path(file).is_absolute()
             ? std::filesystem::path(file)
             : std::filesystem::path(scene_file).parent_path() / file;
}

void read_box(JsonObject& o, Vec3& min, Vec3& max) {
  min = o.required_vec3("min");
  max = o.required_vec3("max");
  for (int a = 0; a < 3; ++a)
    if (!(max[a] > min[a]))
      o.fail("max", "every component must exceed the matching one of \"min\"");
}

namespace {

// Places mesh points by the object's scale, rotate_degrees and translate:
// x' = Rz Ry Rx (scale x) + translate.
void place_points(JsonObject& o, std::vector<Vec3d>& points) {
  const double scale = o.number("scale", 1.0, 0, 1e30, true);
  const Vec3d deg = o.vec3("rotate_degrees", Vec3::Zero()).cast<double>();
  const Vec3 t = o.vec3("translate", Vec3::Zero());
  const double k = M_PI / 180.0;
  const Mat3d R = (Eigen::AngleAxisd(deg[2] * k, Vec3d::UnitZ()) *
                   Eigen::AngleAxisd(deg[1] * k, Vec3d::UnitY()) *
                   Eigen::AngleAxisd(deg[0] * k, Vec3d::UnitX()))
                      .toRotationMatrix();
  for (auto& v : points) v = R * (v * scale) + t.cast<double>();
}

std::shared_ptr<const TriangleMesh> read_mesh_object(JsonObject& o, const std::string& scene_file) {
  const std::string file = o.string("file", "");
  if (!o.has("file") || file.empty())
    o.fail("file", "missing required mesh file (.obj, .off or .ply)");
  const std::filesystem::path p = scene_relative(file, scene_file);
  auto mesh = std::make_shared<TriangleMesh>();
  try {
    *mesh = load_mesh(p.string());
  } catch (const InputError& e) {
    // Name the mesh as the scene writes it: "mesh file "x.off": cannot open ..." / "...":12: ...
    std::string msg = e.what();
    if (msg.rfind(p.string(), 0) == 0) msg = msg.substr(p.string().size());
    o.fail("file", "mesh file \"" + file + "\"" + msg);
  }
  place_points(o, mesh->vertices);
  const bool allow_open = o.boolean("allow_open", false);
  const MeshCheck c = check_mesh(*mesh);
  if (!c.watertight()) {
    const std::string what = "mesh file \"" + file + "\" is not watertight (" +
                             std::to_string(c.boundary_edges) + " boundary edges, " +
                             std::to_string(c.nonmanifold_edges) +
                             " non-manifold edges): inside and outside may be wrong";
    if (!allow_open) o.fail("file", what + "; repair the mesh or set \"allow_open\": true");
    std::cerr << "amalgam: warning: " << o.where("file") << ": " << what << "\n";
  }
  return mesh;
}

// TetGen mesh object (peridynamics): file (.node/.ele or their stem), scale, rotate_degrees,
// translate, as for triangle meshes.
std::shared_ptr<const TetMesh> read_tet_object(JsonObject& o, const std::string& scene_file) {
  const std::string file = o.string("file", "");
  if (!o.has("file") || file.empty())
    o.fail("file", "missing required TetGen file (.node with its .ele)");
  const std::filesystem::path p = scene_relative(file, scene_file);
  auto mesh = std::make_shared<TetMesh>();
  try {
    *mesh = load_tetgen(p.string());
  } catch (const InputError& e) {
    o.fail("file", std::string("TetGen mesh \"") + file + "\": " + e.what());
  }
  place_points(o, mesh->nodes);
  return mesh;
}

// The index of the material named by key "material".
int read_material_name(JsonObject& o, const std::map<std::string, int>& materials) {
  const std::string mat = o.string("material", "");
  if (!o.has("material")) o.fail("material", "missing required material name");
  const auto it = materials.find(mat);
  if (it == materials.end()) {
    std::string known;
    for (const auto& kv : materials) known += (known.empty() ? "" : ", ") + kv.first;
    o.fail("material", "unknown material \"" + mat + "\" (defined in /materials: " + known + ")");
  }
  return it->second;
}

ObjectSpec read_object(JsonObject o, const std::map<std::string, int>& materials,
                       const std::string& scene_file, bool peridynamics, bool domains) {
  ObjectSpec s;
  const std::string shape =
      o.choice("shape", "", {"box", "sphere", "cylinder", "torus", "mesh", "tet_mesh"});
  if (shape == "tet_mesh") {
    if (!peridynamics)
      o.fail("shape",
             "\"tet_mesh\" needs \"method\": \"peridynamics\" (MPM samples \"mesh\" surfaces)");
    s.shape = ObjectShape::TetMesh;
    s.tets = read_tet_object(o, scene_file);
    Vec3d lo = s.tets->nodes[0], hi = lo;
    for (const auto& v : s.tets->nodes) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
    s.min = lo.cast<Real>();
    s.max = hi.cast<Real>();
    s.center = o.vec3("center", Real(0.5) * (s.min + s.max));
  } else if (shape == "mesh") {
    s.shape = ObjectShape::Mesh;
    s.mesh = read_mesh_object(o, scene_file);
    Vec3d lo = s.mesh->vertices[0], hi = lo;
    for (const auto& v : s.mesh->vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
    s.min = lo.cast<Real>();
    s.max = hi.cast<Real>();
    s.center = o.vec3("center", Real(0.5) * (s.min + s.max));
  } else if (shape == "box") {
    s.shape = ObjectShape::Box;
    read_box(o, s.min, s.max);
    s.center = o.vec3("center", Real(0.5) * (s.min + s.max));
  } else if (shape == "sphere") {
    s.shape = ObjectShape::Sphere;
    s.center = o.required_vec3("center");
    s.radius = Real(o.required_number("radius", 0, kHuge, true));
    s.min = s.center - Vec3::Constant(s.radius);
    s.max = s.center + Vec3::Constant(s.radius);
  } else {  // cylinder or torus about an axis through the centre
    s.shape = shape == "cylinder" ? ObjectShape::Cylinder : ObjectShape::Torus;
    s.center = o.required_vec3("center");
    const std::string axis = o.choice("axis", "y", {"x", "y", "z"});
    s.axis = axis == "x" ? 0 : axis == "y" ? 1 : 2;
    Vec3 half;
    if (s.shape == ObjectShape::Cylinder) {
      s.radius = Real(o.required_number("radius", 0, kHuge, true));
      s.height = Real(o.required_number("height", 0, kHuge, true));
      half = Vec3::Constant(s.radius);
      half[s.axis] = s.height / 2;
    } else {
      s.radius = Real(o.required_number("major_radius", 0, kHuge, true));
      s.minor_radius = Real(o.required_number("minor_radius", 0, kHuge, true));
      if (!(s.minor_radius < s.radius)) o.fail("minor_radius", "must be smaller than major_radius");
      half = Vec3::Constant(s.radius + s.minor_radius);
      half[s.axis] = s.minor_radius;
    }
    s.min = s.center - half;
    s.max = s.center + half;
  }
  s.material = read_material_name(o, materials);
  if (o.has_expressions("velocity"))
    s.velocity_field = o.vector_field("velocity");
  else
    s.velocity = o.vec3("velocity", Vec3::Zero());
  s.displacement_field = o.vector_field("displacement");
  if (s.displacement_field && domains)
    o.fail("displacement", "not with particle domains (their corners start on the lattice)");
  s.angular_velocity = o.vec3("angular_velocity", Vec3::Zero());
  // Peridynamics wants a regular lattice (its bond families and constants assume one).
  s.particles_per_cell = int(o.integer("particles_per_cell", peridynamics ? 1 : 8, 1, 64));
  s.jitter = Real(o.number("jitter", peridynamics || domains ? 0.0 : 0.5, 0, 1));
  // Particle domains are the lattice cells around the particles: corners are shared only on a lattice.
  if (domains && s.jitter != 0)
    o.fail("jitter", "must be 0 with particle domains (/simulation/domains)");
  s.seed = std::uint64_t(o.integer("seed", 1, 0, (1LL << 62)));
  s.temperature = Real(o.number("temperature", 293.15, 0, kHuge));
  if (o.has("configuration")) {
    if (peridynamics) o.fail("configuration", "configuration maps (A-ULMPM) are for MPM objects");
    JsonObject c = o.object("configuration");
    s.has_configuration = true;
    const std::string u =
        c.choice("update", "adaptive", {"adaptive", "total_lagrangian", "eulerian"});
    s.configuration.update = u == "adaptive"           ? ConfigurationUpdate::Adaptive
                             : u == "total_lagrangian" ? ConfigurationUpdate::TotalLagrangian
                                                       : ConfigurationUpdate::Eulerian;
    s.configuration.epsilon = Real(c.number("epsilon", 0.5, 0, kHuge, true));
    s.configuration.eta = Real(c.number("eta", 0.1, 0, 1));
    if (u != "adaptive" && (c.has("epsilon") || c.has("eta")))
      c.fail(c.has("epsilon") ? "epsilon" : "eta", "only used with \"update\": \"adaptive\"");
    c.finish();
    if (s.displacement_field)
      o.fail("displacement", "not with configuration maps (their reference starts undeformed)");
  }
  o.finish();
  return s;
}

// An emitter (solvers/mpm_sources.hpp): a box, sphere or closed mesh the material flows through
// with `velocity` from `start` to `end`, sampled at the object density.
EmitterSpec read_emitter(JsonObject o, const std::map<std::string, int>& materials,
                         const Scene& scene) {
  EmitterSpec e;
  e.where = o.where("");
  if (!e.where.empty() && e.where.back() == '/') e.where.pop_back();
  const std::string shape = o.choice("shape", "", {"box", "sphere", "mesh"});
  std::string shape_key = "min";
  if (shape == "box") {
    e.shape = EmitterShape::Box;
    read_box(o, e.min, e.max);
  } else if (shape == "sphere") {
    e.shape = EmitterShape::Sphere;
    shape_key = "center";
    e.center = o.required_vec3("center");
    e.radius = Real(o.required_number("radius", 0, kHuge, true));
    e.min = e.center - Vec3::Constant(e.radius);
    e.max = e.center + Vec3::Constant(e.radius);
  } else {
    e.shape = EmitterShape::Mesh;
    shape_key = "file";
    e.mesh = read_mesh_object(o, scene.file);
    Vec3d lo, hi;
    mesh_bounds(*e.mesh, lo, hi);
    e.min = lo.cast<Real>();
    e.max = hi.cast<Real>();
  }
  e.material = read_material_name(o, materials);
  e.velocity = o.vec3("velocity", Vec3::Zero());
  e.start = o.number("start", 0, 0, kHuge);
  e.end = o.required_number("end", 0, kHuge, true);
  if (!(e.end > e.start)) o.fail("end", "must be after \"start\"");
  e.particles_per_cell = int(o.integer("particles_per_cell", 8, 1, 64));
  e.jitter = Real(o.number("jitter", 0.5, 0, 1));
  e.seed = std::uint64_t(o.integer("seed", 1, 0, (1LL << 62)));
  e.temperature = Real(o.number("temperature", 293.15, 0, kHuge));
  o.finish();
  // A lattice point must not cross the volume within one substep: the chord through the
  // centre along v is at least two substeps' travel at max_dt.
  const double speed = double(e.velocity.norm());
  if (speed > 0) {
    const Vec3d dir = e.velocity.cast<double>() / speed;
    double chord = 2 * double(e.radius);
    if (e.shape != EmitterShape::Sphere) {
      chord = 1e300;
      for (int a = 0; a < 3; ++a)
        if (std::abs(dir[a]) > 1e-12)
          chord = std::min(chord, double(e.max[a] - e.min[a]) / std::abs(dir[a]));
    }
    if (chord < 2 * speed * double(scene.mpm.max_dt))
      o.fail("velocity", "the material would cross the emitter (" + std::to_string(chord) +
                             " m along the velocity) in under two substeps of max_dt = " +
                             std::to_string(double(scene.mpm.max_dt)) +
                             " s: enlarge the emitter along its velocity or lower max_dt");
  }
  const KillSettings& k = scene.mpm.kill;
  if (k.outside)
    for (int a = 0; a < 3; ++a)
      if (e.min[a] < k.min[a] || e.max[a] > k.max[a])
        o.fail(shape_key,
               "the emitter reaches outside the simulation domain (/simulation/kill/outside)");
  const double most = e.max_particles(scene.mpm.dx);
  if (most > 2e9)
    o.fail("end", "the emitter could emit " + std::to_string(most) +
                      " particles, more than 2e9: shorten it, lower its speed or raise dx");
  return e;
}

}  // namespace

// Geometry and motion shared by colliders and heat sources.
Collider read_region(JsonObject& o, bool allow_mesh) {
  Collider c;
  const std::string type = allow_mesh
                               ? o.choice("type", "", {"half_space", "box", "sphere", "mesh"})
                               : o.choice("type", "", {"half_space", "box", "sphere"});
  if (type == "mesh") {
    c.shape = ColliderShape::Mesh;
    return c;  // the caller reads the mesh
  }
  if (type == "half_space") {
    c.shape = ColliderShape::HalfSpace;
    c.origin = o.required_vec3("point");
    const Vec3 n = o.required_vec3("normal");
    if (!(n.norm() > 0)) o.fail("normal", "must be a non-zero vector");
    c.normal = n.normalized();
  } else if (type == "box") {
    c.shape = ColliderShape::Box;
    c.origin = o.required_vec3("center");
    c.half_extent = o.required_vec3("half_extent");
    if (!(c.half_extent.minCoeff() > 0)) o.fail("half_extent", "every component must be positive");
  } else {
    c.shape = ColliderShape::Sphere;
    c.origin = o.required_vec3("center");
    c.radius = Real(o.required_number("radius", 0, kHuge, true));
  }
  c.velocity = o.vec3("velocity", Vec3::Zero());
  return c;
}

namespace {

// The run's length, which fixes the frames a collider sequence needs.
struct FrameRange {
  int frames = 48;
  double fps = 24;
};

// A frame pattern: exactly one %d, %Nd or %0Nd conversion and no other '%'.
bool is_frame_pattern(const std::string& f) {
  const auto p = f.find('%');
  if (p == std::string::npos || f.find('%', p + 1) != std::string::npos) return false;
  std::size_t q = p + 1;
  while (q < f.size() && q < p + 4 && std::isdigit(static_cast<unsigned char>(f[q]))) ++q;
  return q < f.size() && f[q] == 'd';
}
std::string frame_file(const std::string& pattern, int k) {
  char buf[4096];
  std::snprintf(buf, sizeof buf, pattern.c_str(), k);
  return buf;
}
bool ends_with_vdb(const std::string& f) {
  return f.size() >= 4 && std::equal(f.end() - 4, f.end(), ".vdb");
}

// The collider's geometry: a mesh file, a .vdb level set, or a sequence of either ("%04d" in
// the file name: frame first_frame + k at time k / frame_rate). A sequence needs the frames
// bracketing every time of the run, k = 0 .. ceil(frames / fps * frame_rate); each is checked
// now (exists; a .vdb has a float level set; a mesh has frame 0's topology).
void read_collider_source(JsonObject& o, ColliderSpec& c, const std::string& scene_file,
                          const FrameRange& run) {
  const std::string file = o.string("file", "");
  const bool sequence = file.find('%') != std::string::npos;
  const bool vdb = ends_with_vdb(file);
  if (sequence && !is_frame_pattern(file))
    o.fail("file", "\"" + file + "\": a frame sequence takes one %d, %4d or %04d and no other '%'");
  c.frame_rate = o.number("frame_rate", run.fps, 0, 1e6, true);
  const int first = int(o.integer("first_frame", 0, 0, 100000000));
  if (!sequence && o.has("frame_rate")) o.fail("frame_rate", "only for a frame sequence (%04d)");
  if (!sequence && o.has("first_frame")) o.fail("first_frame", "only for a frame sequence (%04d)");
  if (vdb) c.vdb_grid = o.string("grid", "");
  if (!vdb && o.has("grid")) o.fail("grid", "only for a .vdb level set");
  if (!sequence && !vdb) {
    c.mesh = read_mesh_object(o, scene_file);
    return;
  }
  const std::vector<std::string> placing = {"scale", "rotate_degrees", "translate"};
  if (vdb)
    for (const auto& k : placing)
      if (o.has(k)) o.fail(k, "not for a .vdb level set (place it with keyframes or in the file)");
  const double count = std::ceil(run.frames / run.fps * c.frame_rate - 1e-9) + 1;
  if (!sequence) {
    const std::string path = scene_relative(file, scene_file).string();
    const std::string why = check_level_set_file(path, c.vdb_grid);
    if (!why.empty()) o.fail("file", "\"" + file + "\": " + why);
    c.vdb_files.push_back(path);
    return;
  }
  if (!(count <= 100000))
    o.fail("frame_rate", "the run needs " + std::to_string(count) + " frames of the sequence");
  std::ostringstream wf;
  wf << "frames " << first << " to " << first + int(count) - 1 << " (the run's " << run.frames
     << " frames at fps " << run.fps << ", frame_rate " << c.frame_rate << ")";
  const std::string where_frames = wf.str();
  for (int k = 0; k < int(count); ++k) {
    const std::string name = frame_file(file, first + k);
    const std::string path = scene_relative(name, scene_file).string();
    if (!std::filesystem::exists(path))
      o.fail("file", "frame " + std::to_string(first + k) + " of the sequence, \"" + name +
                         "\", does not exist; the run needs " + where_frames);
    if (vdb) {
      const std::string why = check_level_set_file(path, c.vdb_grid);
      if (!why.empty()) o.fail("file", "\"" + name + "\": " + why);
      c.vdb_files.push_back(path);
      continue;
    }
    auto mesh = std::make_shared<TriangleMesh>();
    try {
      *mesh = load_mesh(path);
    } catch (const InputError& e) {
      std::string msg = e.what();
      if (msg.rfind(path, 0) == 0) msg = msg.substr(path.size());
      o.fail("file", "mesh file \"" + name + "\"" + msg);
    }
    place_points(o, mesh->vertices);
    if (!c.mesh_frames.empty()) {
      const TriangleMesh& m0 = *c.mesh_frames[0];
      if (mesh->vertices.size() != m0.vertices.size() || mesh->triangles != m0.triangles)
        o.fail("file", "mesh file \"" + name + "\" has " + std::to_string(mesh->vertices.size()) +
                           " vertices and " + std::to_string(mesh->triangles.size()) +
                           " triangles, \"" + frame_file(file, first) + "\" " +
                           std::to_string(m0.vertices.size()) + " and " +
                           std::to_string(m0.triangles.size()) +
                           (mesh->vertices.size() == m0.vertices.size() &&
                                    mesh->triangles.size() == m0.triangles.size()
                                ? " connected differently"
                                : "") +
                           ": a deforming sequence keeps one topology");
    }
    c.mesh_frames.push_back(std::move(mesh));
  }
  o.boolean("allow_open", false);
}

// Mesh collider: the mesh (file, scale, rotate_degrees, translate, allow_open) is its rest pose,
// turned by the factory (solvers/factory.hpp) into a sparse level set of spacing dx built lazily
// where the material is (core/geometry/level_set_collider.hpp); it moves
// with `velocity` or by `keyframes` (time, translate, rotate_degrees: a rigid motion about
// `pivot`, default the mesh's box centre).
void read_mesh_collider(JsonObject& o, ColliderSpec& c, const std::string& scene_file,
                        const FrameRange& run) {
  c.where = o.where("file");
  read_collider_source(o, c, scene_file, run);
  Vec3d lo = Vec3d::Constant(1e300), hi = Vec3d::Constant(-1e300);
  if (c.mesh) mesh_bounds(*c.mesh, lo, hi);
  if (!c.mesh_frames.empty()) mesh_bounds(*c.mesh_frames[0], lo, hi);
  if (!c.vdb_files.empty()) lo = hi = Vec3d::Zero();  // a level set: pivot at its origin
  c.pivot = o.vec3("pivot", (0.5 * (lo + hi)).cast<Real>());
  const bool has_velocity = o.has("velocity");
  c.velocity = o.vec3("velocity", Vec3::Zero());
  const double k = M_PI / 180.0;
  for (auto& kf : o.objects("keyframes")) {
    RigidKeyframe key;
    key.time = Real(kf.required_number("time", 0, kHuge));
    if (!c.keys.empty() && !(key.time > c.keys.back().time))
      kf.fail("time", "keyframe times must increase");
    key.translation = kf.vec3("translate", Vec3::Zero());
    const Vec3d deg = kf.vec3("rotate_degrees", Vec3::Zero()).cast<double>();
    key.rotation = Eigen::Quaternion<Real>((Eigen::AngleAxisd(deg[2] * k, Vec3d::UnitZ()) *
                                            Eigen::AngleAxisd(deg[1] * k, Vec3d::UnitY()) *
                                            Eigen::AngleAxisd(deg[0] * k, Vec3d::UnitX()))
                                               .toRotationMatrix()
                                               .cast<Real>());
    kf.finish();
    c.keys.push_back(key);
  }
  if (has_velocity && !c.keys.empty())
    o.fail("velocity", "give either velocity or keyframes, not both");
}

}  // namespace

// `until` (s): the region acts up to this time only (a grip that lets go, a heater switched off).
void read_until(JsonObject& o, Collider& c) {
  if (o.has("until")) c.until = Real(o.required_number("until", 0, kHuge, true));
}

namespace {

ColliderSpec read_collider(JsonObject o, const std::string& scene_file, const FrameRange& run) {
  ColliderSpec c;
  static_cast<Collider&>(c) = read_region(o, true);
  if (c.shape == ColliderShape::Mesh) read_mesh_collider(o, c, scene_file, run);
  read_until(o, c);
  const std::string b = o.choice("boundary", "separate", {"sticky", "slip", "separate"});
  c.boundary = b == "sticky" ? BoundaryType::Sticky
               : b == "slip" ? BoundaryType::Slip
                             : BoundaryType::Separate;
  c.friction = Real(o.number("friction", 0, 0, 100));
  o.finish();
  return c;
}

}  // namespace
}  // namespace scene_detail

using namespace scene_detail;

namespace {

// output.surfacing (io/surfacing.hpp, docs/scenes.md).
void read_surfacing(JsonObject& j, Scene& s, const std::map<std::string, int>& mat_index) {
  SurfacingSpec& r = s.output.surfacing;
  r.enabled = j.boolean("enabled", true);
  parse_surfacing_method(j.choice("method", "smooth", {"smooth", "spheres"}), r.method);
  r.voxel_size = j.number("voxel_size", 0.5 * double(s.mpm.dx), 0, kHuge, true);
  r.radius_scale = j.number("radius_scale", 0, 0, 100, true);  // 0: the method's default
  r.filters = default_surface_filters(r.method);
  const std::vector<std::string> filters = j.strings("filters", {});
  if (j.has("filters")) r.filters.clear();
  for (std::size_t i = 0; i < filters.size(); ++i) {
    SurfaceFilter f;
    if (!parse_surface_filter(filters[i], f))
      j.fail("filters/" + std::to_string(i),
             "unknown filter \"" + filters[i] + "\" (expected one of: dilate, smooth, erode)");
    r.filters.push_back(f);
  }
  const std::vector<std::string> grids = j.strings("grids", {"surface", "density", "v"});
  r.grid_surface = r.grid_density = r.grid_velocity = false;
  for (std::size_t i = 0; i < grids.size(); ++i) {
    bool* g = grids[i] == "surface"   ? &r.grid_surface
              : grids[i] == "density" ? &r.grid_density
              : grids[i] == "v"       ? &r.grid_velocity
                                      : nullptr;
    if (!g)
      j.fail("grids/" + std::to_string(i),
             "unknown grid \"" + grids[i] + "\" (expected one of: surface, density, v)");
    *g = true;
  }
  parse_surface_mesh(j.choice("mesh", "none", {"none", "obj", "ply"}), r.mesh);
  r.adaptivity = j.number("adaptivity", 0, 0, 1);
  const std::vector<std::string> groups = j.strings("groups", {});
  for (std::size_t i = 0; i < groups.size(); ++i) {
    const auto it = mat_index.find(groups[i]);
    if (it == mat_index.end())
      j.fail("groups/" + std::to_string(i),
             "unknown material \"" + groups[i] + "\" (groups name materials of /materials)");
    r.materials.push_back(std::int32_t(it->second));
  }
}

// output.vdb_points: true / false (true: the default precision), or "full" / "compact".
void read_vdb_points(JsonObject& out, OutputSpec& o) {
  if (!out.has_string("vdb_points")) {
    o.vdb_points = out.boolean("vdb_points", true);
    return;
  }
  o.vdb_points = true;
  o.vdb_precision = out.choice("vdb_points", "compact", {"full", "compact"}) == "full"
                        ? VdbPrecision::Full
                        : VdbPrecision::Compact;
}

bool any_material(const SceneSpec& s, bool (*has)(const MaterialParams&)) {
  return std::any_of(s.materials.begin(), s.materials.end(), has);
}

// Why the scene's method cannot give attribute `name` ("" if it can).
std::string attribute_missing(const SceneSpec& s, const std::string& name) {
  const bool pd = s.method == Method::Peridynamics;
  if (name == "vonmises" || name == "rest" || name == "material") return "";
  if (pd) return name == "damage" || name == "theta" ? "" : "MPM only";
  if (name == "F" || name == "J") return "";
  if (name == "damage" || name == "theta") return "peridynamics only";
  if (name == "Jp" &&
      !any_material(s, [](const MaterialParams& m) { return m.has_plastic_state(); }))
    return "no material of the scene has a plastic state (snow, drucker_prager, von_mises)";
  if (name == "temperature" && !any_material(s, [](const MaterialParams& m) { return m.melting; }))
    return "no material of the scene melts";
  if (name == "enrichment" && !s.mpm.domains.enabled) return "the scene has no particle domains";
  return "";
}

// output.attributes: names of point_attribute_names() the method has, each once.
void read_attributes(JsonObject& out, Scene& s) {
  if (!out.has("attributes")) return;  // P, v and id only: nothing the scene did not ask for
  const std::vector<std::string>& known = point_attribute_names();
  s.output.attributes = out.strings("attributes", {});
  for (std::size_t i = 0; i < s.output.attributes.size(); ++i) {
    const std::string& a = s.output.attributes[i];
    const std::string key = "attributes/" + std::to_string(i);
    if (std::find(known.begin(), known.end(), a) == known.end()) {
      std::string list;
      for (const auto& k : known) list += (list.empty() ? "" : ", ") + k;
      out.fail(key, "unknown attribute \"" + a + "\" (expected one of: " + list +
                        "; P, v and id are always written)");
    }
    const std::string why = attribute_missing(s, a);
    if (!why.empty()) out.fail(key, "attribute \"" + a + "\" is not available: " + why);
    if (std::find(s.output.attributes.begin(), s.output.attributes.begin() + long(i), a) !=
        s.output.attributes.begin() + long(i))
      out.fail(key, "attribute \"" + a + "\" is listed twice");
  }
  // MPM particles keep F itself only for this output; else b = F F^T (MpmSolver::keeps_b).
  const auto& as = s.output.attributes;
  s.mpm.keep_F = std::find(as.begin(), as.end(), "F") != as.end();
}

}  // namespace

bool attribute_available(const SceneSpec& scene, const std::string& name) {
  const std::vector<std::string>& known = point_attribute_names();
  return std::find(known.begin(), known.end(), name) != known.end() &&
         attribute_missing(scene, name).empty();
}

Scene parse_scene(const std::string& text, const std::string& file) {
  const nlohmann::json root = detail::parse_json_strict(text, file);
  Scene s;
  s.file = file;
  JsonObject top(root, file, "");
  s.name = top.string("name", file);
  top.string("description", "");

  JsonObject sim = top.object("simulation");
  if (!top.has("simulation")) top.fail("simulation", "missing required object");
  s.method = sim.choice("method", "mpm", {"mpm", "peridynamics"}) == "mpm" ? Method::Mpm
                                                                           : Method::Peridynamics;
  const bool pd = s.method == Method::Peridynamics;
  // Settings every method shares, then the method's own.
  s.mpm.dx = Real(sim.required_number("dx", 0, kHuge, true));
  s.mpm.cfl = Real(sim.number("cfl", pd ? 0.7 : 0.4, 0, 1, true));
  s.fps = sim.number("fps", 24, 0, 1e6, true);
  s.mpm.max_dt = Real(sim.number("max_dt", 1e-3, 0, kHuge, true));
  s.mpm.gravity = sim.vec3("gravity", Vec3(0, Real(-9.81), 0));
  s.mpm.max_speed = Real(sim.number("max_speed", 1e4, 0, kHuge, true));
  s.frames = int(sim.integer("frames", 48, 1, kMaxFrames));
  if (pd) {
    for (const char* k : {"kill", "sleep"})
      if (sim.has(k)) sim.fail(k, "only for MPM scenes (\"method\": \"mpm\")");
    read_pd_simulation(sim, s);
  } else {
    read_mpm_simulation(sim, s);
  }
  sim.finish();

  std::map<std::string, int> mat_index;
  JsonObject mats = top.object("materials");
  if (!top.has("materials") || mats.keys().empty())
    top.fail("materials", "define at least one material");
  // Peridynamics: the lattice spacing comes from dx and the objects' particles_per_cell, and the
  // horizon (which yield_stress needs) from the spacing: read the objects first.
  for (const auto& name : mats.keys()) {
    mat_index[name] = int(s.material_names.size());
    s.material_names.push_back(name);
  }
  if (!top.has("objects")) top.fail("objects", "missing required array of objects");
  for (auto& o : top.objects("objects"))
    s.objects.push_back(read_object(o, mat_index, file, pd, s.mpm.domains.enabled));
  if (s.objects.empty()) top.fail("objects", "define at least one object");
  if (pd)
    pd_spacing(top, s);
  else
    check_mpm_objects(sim, s);
  if (pd)
    read_pd_materials(mats, s);
  else
    read_mpm_materials(mats, s);
  mats.finish();
  if (pd)
    read_pd_conditions(top, s);
  else
    read_mpm_sources(top, s);
  for (auto& c : top.objects("colliders"))
    s.colliders.push_back(read_collider(c, file, FrameRange{s.frames, s.fps}));
  if (top.has("emitters")) {
    if (pd)
      top.fail("emitters", "only for MPM scenes (peridynamic particles are bonded at set-up)");
    if (s.mpm.domains.enabled || s.mpm.configuration_maps)
      top.fail("emitters",
               "not with particle domains (/simulation/domains) nor A-ULMPM objects "
               "(\"configuration\" blocks): plain MPM only");
    for (auto& e : top.objects("emitters")) s.emitters.push_back(read_emitter(e, mat_index, s));
  }

  JsonObject out = top.object("output");
  s.output.directory = out.string("directory", "out");
  s.output.ply = out.boolean("ply", true);
  read_vdb_points(out, s.output);
  s.output.diagnostics_csv = out.boolean("diagnostics_csv", true);
  s.output.grid_volumes = out.boolean("grid_volumes", false);
  // Grid volumes write the frame's last grid (m, v): the fused substep's grid at a frame's end is
  // the next substep's split scatter (m, p, f), so such a run keeps the two passes.
  if (s.output.grid_volumes) s.mpm.fused = false;
  s.output.checkpoint_every = int(out.integer("checkpoint_every", 10, 0, 1000000));
  s.output.every_substeps = out.integer("every_substeps", 0, 0, 1000000000);
  const std::string surf = out.choice("surface", "obj", {"obj", "ply", "both", "none"});
  s.output.surface_obj = surf == "obj" || surf == "both";
  s.output.surface_ply = surf == "ply" || surf == "both";
  if (out.has("surfacing")) {
    JsonObject sj = out.object("surfacing");
    read_surfacing(sj, s, mat_index);
    sj.finish();
  }
  read_attributes(out, s);
  out.finish();

  if (top.has("preview")) {
    JsonObject pv = top.object("preview");
    s.preview.width = int(pv.integer("width", 640, 16, 8192));
    s.preview.height = int(pv.integer("height", 480, 16, 8192));
    const std::string c = pv.choice("color_by", "material",
                                    {"material", "speed", "temperature", "plastic", "damage"});
    s.preview.color_by = c == "speed"         ? ColorBy::Speed
                         : c == "damage"      ? ColorBy::Damage
                         : c == "temperature" ? ColorBy::Temperature
                         : c == "plastic"     ? ColorBy::Plastic
                                              : ColorBy::Material;
    if (pv.has("camera")) {
      JsonObject cam = pv.object("camera");
      s.preview.camera_given = true;
      s.preview.camera.eye = cam.required_vec3("position").cast<double>();
      s.preview.camera.target = cam.required_vec3("look_at").cast<double>();
      if (!((s.preview.camera.eye - s.preview.camera.target).norm() > 0))
        cam.fail("look_at", "must differ from position");
      s.preview.camera.fov_degrees = cam.number("fov_degrees", 35, 1, 170);
      cam.finish();
    }
    pv.finish();
  }
  top.finish();

  nlohmann::json physics = root;
  for (const char* k : {"output", "name", "description", "preview"}) physics.erase(k);
  physics["simulation"].erase("frames");
  const std::string canon = physics.dump();
  s.fingerprint = fnv1a64(canon.data(), canon.size());
  return s;
}

Scene load_scene(const std::string& path) {
  const std::string text = read_input_file(path, "scene file", kMaxSceneBytes);
  const std::size_t nul = text.find('\0');
  if (nul != std::string::npos)
    throw InputError(path + ": byte " + std::to_string(nul) +
                     " is a NUL byte: a scene file is JSON text (is this the right file?)");
  return parse_scene(text, path);
}

Camera preview_camera(const Scene& scene) {
  if (scene.preview.camera_given) return scene.preview.camera;
  Vec3d lo = Vec3d::Constant(1e30), hi = Vec3d::Constant(-1e30);
  for (const auto& o : scene.objects) {
    Vec3d a = o.min.cast<double>(), b = o.max.cast<double>();
    if (o.shape == ObjectShape::Mesh && o.mesh)
      for (const auto& v : o.mesh->vertices) a = a.cwiseMin(v), b = b.cwiseMax(v);
    lo = lo.cwiseMin(a), hi = hi.cwiseMax(b);
  }
  // Material spreads sideways and falls: widen by half the size, down to the floor.
  const Vec3d size = hi - lo;
  lo[0] -= 0.5 * size[0], hi[0] += 0.5 * size[0], lo[2] -= 0.5 * size[2], hi[2] += 0.5 * size[2];
  for (const auto& c : scene.colliders)
    if (c.shape == ColliderShape::HalfSpace && c.normal[1] > 0.9 && double(c.origin[1]) < lo[1])
      lo[1] = double(c.origin[1]);
  return fit_camera(lo, hi, 35, double(scene.preview.width) / double(scene.preview.height));
}

double preview_floor(const Scene& scene) {
  double y = std::numeric_limits<double>::quiet_NaN();
  for (const auto& c : scene.colliders)
    if (c.shape == ColliderShape::HalfSpace && c.normal[1] > 0.9 && !(double(c.origin[1]) <= y))
      y = double(c.origin[1]);
  return y;
}

double particle_spacing(const Scene& scene) {
  if (scene.method == Method::Peridynamics) return double(scene.pd.spacing);
  int ppc = 0;
  for (const auto& o : scene.objects)
    ppc = ppc == 0 ? o.particles_per_cell : std::min(ppc, o.particles_per_cell);
  return double(scene.mpm.dx) / std::cbrt(double(std::max(ppc, 1)));
}

double preview_radius(const Scene& scene) {
  int ppc = 1;
  for (const auto& o : scene.objects) ppc = std::max(ppc, o.particles_per_cell);
  return 0.6 * double(scene.mpm.dx) / std::cbrt(double(ppc));
}

}  // namespace amalgam
