#include "io/scene.hpp"

#include <cmath>
#include <filesystem>
#include <iostream>
#include <fstream>
#include <map>
#include <sstream>

#include "core/errors.hpp"
#include "core/hash.hpp"
#include "io/json_reader.hpp"

namespace amalgam {

using detail::JsonObject;

namespace {

constexpr double kHuge = 1e30;

MaterialParams read_material(JsonObject o) {
  MaterialParams m;
  const std::string model = o.choice("model", "fixed_corotated", {"fixed_corotated", "neo_hookean"});
  m.model = model == "neo_hookean" ? ElasticModel::NeoHookean : ElasticModel::FixedCorotated;
  m.density = Real(o.required_number("density", 0, kHuge, true));
  const double E = o.required_number("youngs_modulus", 0, kHuge, true);
  const double nu = o.number("poisson_ratio", 0.3, -0.999, 0.499);
  const Lame l = Lame::from_young_poisson(E, nu);
  m.mu = l.mu;
  m.lambda = l.lambda;
  o.finish();
  return m;
}

std::shared_ptr<const TriangleMesh> read_mesh_object(JsonObject& o, const std::string& scene_file) {
  const std::string file = o.string("file", "");
  if (!o.has("file") || file.empty()) o.fail("file", "missing required mesh file (.obj, .off or .ply)");
  const std::filesystem::path p = std::filesystem::path(file).is_absolute()
                                      ? std::filesystem::path(file)
                                      : std::filesystem::path(scene_file).parent_path() / file;
  auto mesh = std::make_shared<TriangleMesh>();
  try {
    *mesh = load_mesh(p.string());
  } catch (const InputError& e) {
    // Name the mesh as the scene writes it: "mesh file "x.off": cannot open ..." / "...":12: ...
    std::string msg = e.what();
    if (msg.rfind(p.string(), 0) == 0) msg = msg.substr(p.string().size());
    o.fail("file", "mesh file \"" + file + "\"" + msg);
  }
  const double scale = o.number("scale", 1.0, 0, 1e30, true);
  const Vec3 t = o.vec3("translate", Vec3::Zero());
  for (auto& v : mesh->vertices) v = v * scale + t.cast<double>();
  const bool allow_open = o.boolean("allow_open", false);
  const MeshCheck c = check_mesh(*mesh);
  if (!c.watertight()) {
    const std::string what = "mesh file \"" + file + "\" is not watertight (" + std::to_string(c.boundary_edges) +
                             " boundary edges, " + std::to_string(c.nonmanifold_edges) +
                             " non-manifold edges): inside and outside may be wrong";
    if (!allow_open) o.fail("file", what + "; repair the mesh or set \"allow_open\": true");
    std::cerr << "amalgam: warning: " << o.where("file") << ": " << what << "\n";
  }
  return mesh;
}

ObjectSpec read_object(JsonObject o, const std::map<std::string, int>& materials, const std::string& scene_file) {
  ObjectSpec s;
  const std::string shape = o.choice("shape", "", {"box", "sphere", "mesh"});
  if (shape == "mesh") {
    s.shape = ObjectShape::Mesh;
    s.mesh = read_mesh_object(o, scene_file);
    Vec3d lo = s.mesh->vertices[0], hi = lo;
    for (const auto& v : s.mesh->vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
    s.min = lo.cast<Real>();
    s.max = hi.cast<Real>();
    s.center = o.vec3("center", Real(0.5) * (s.min + s.max));
  } else if (shape == "box") {
    s.shape = ObjectShape::Box;
    s.min = o.required_vec3("min");
    s.max = o.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(s.max[a] > s.min[a])) o.fail("max", "every component must exceed the matching one of \"min\"");
    s.center = o.vec3("center", Real(0.5) * (s.min + s.max));
  } else {
    s.shape = ObjectShape::Sphere;
    s.center = o.required_vec3("center");
    s.radius = Real(o.required_number("radius", 0, kHuge, true));
  }
  const std::string mat = o.string("material", "");
  if (!o.has("material")) o.fail("material", "missing required material name");
  const auto it = materials.find(mat);
  if (it == materials.end()) {
    std::string known;
    for (const auto& kv : materials) known += (known.empty() ? "" : ", ") + kv.first;
    o.fail("material", "unknown material \"" + mat + "\" (defined in /materials: " + known + ")");
  }
  s.material = it->second;
  s.velocity = o.vec3("velocity", Vec3::Zero());
  s.angular_velocity = o.vec3("angular_velocity", Vec3::Zero());
  s.particles_per_cell = int(o.integer("particles_per_cell", 8, 1, 64));
  s.jitter = Real(o.number("jitter", 0.5, 0, 1));
  s.seed = std::uint64_t(o.integer("seed", 1, 0, (1LL << 62)));
  o.finish();
  return s;
}

Collider read_collider(JsonObject o) {
  Collider c;
  const std::string type = o.choice("type", "", {"half_space", "box", "sphere"});
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
  const std::string b = o.choice("boundary", "separate", {"sticky", "slip", "separate"});
  c.boundary = b == "sticky" ? BoundaryType::Sticky : b == "slip" ? BoundaryType::Slip : BoundaryType::Separate;
  c.friction = Real(o.number("friction", 0, 0, 100));
  c.velocity = o.vec3("velocity", Vec3::Zero());
  o.finish();
  return c;
}

}  // namespace

Scene parse_scene(const std::string& text, const std::string& file) {
  nlohmann::json root;
  try {
    root = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {  // parse_error, out_of_range (1e999), ...
    throw InputError(file + ": not valid JSON: " + e.what());
  }
  Scene s;
  s.file = file;
  JsonObject top(root, file, "");
  s.name = top.string("name", file);
  top.string("description", "");

  JsonObject sim = top.object("simulation");
  if (!top.has("simulation")) top.fail("simulation", "missing required object");
  s.mpm.dx = Real(sim.required_number("dx", 0, kHuge, true));
  s.mpm.order = int(sim.integer("order", 2, 2, 3));
  const std::string tr = sim.choice("transfer", "mls", {"mls", "apic", "pic", "flip"});
  s.mpm.transfer = tr == "mls" ? Transfer::Mls : tr == "apic" ? Transfer::Apic : Transfer::PicFlip;
  s.mpm.flip_alpha = Real(sim.number("flip_alpha", tr == "pic" ? 0.0 : 0.95, 0, 1));
  if (tr == "pic" && s.mpm.flip_alpha != 0) sim.fail("flip_alpha", "must be 0 (or absent) with transfer \"pic\"");
  s.mpm.cfl = Real(sim.number("cfl", 0.4, 0, 1, true));
  s.fps = sim.number("fps", 24, 0, 1e6, true);
  s.mpm.max_dt = Real(sim.number("max_dt", 1e-3, 0, kHuge, true));
  s.mpm.gravity = sim.vec3("gravity", Vec3(0, Real(-9.81), 0));
  s.mpm.max_speed = Real(sim.number("max_speed", 1e4, 0, kHuge, true));
  s.frames = int(sim.integer("frames", 48, 1, 1000000));
  sim.finish();

  std::map<std::string, int> mat_index;
  JsonObject mats = top.object("materials");
  if (!top.has("materials") || mats.keys().empty()) top.fail("materials", "define at least one material");
  for (const auto& name : mats.keys()) {
    mat_index[name] = int(s.materials.size());
    s.material_names.push_back(name);
    s.materials.push_back(read_material(mats.object(name)));
  }
  mats.finish();

  if (!top.has("objects")) top.fail("objects", "missing required array of objects");
  for (auto& o : top.objects("objects")) s.objects.push_back(read_object(o, mat_index, file));
  if (s.objects.empty()) top.fail("objects", "define at least one object");
  for (auto& c : top.objects("colliders")) s.colliders.push_back(read_collider(c));

  JsonObject out = top.object("output");
  s.output.directory = out.string("directory", "out");
  s.output.ply = out.boolean("ply", true);
  s.output.vdb_points = out.boolean("vdb_points", true);
  s.output.diagnostics_csv = out.boolean("diagnostics_csv", true);
  s.output.checkpoint_every = int(out.integer("checkpoint_every", 10, 0, 1000000));
  out.finish();
  top.finish();

  nlohmann::json physics = root;
  for (const char* k : {"output", "name", "description"}) physics.erase(k);
  physics["simulation"].erase("frames");
  const std::string canon = physics.dump();
  s.fingerprint = fnv1a64(canon.data(), canon.size());
  return s;
}

Scene load_scene(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path + ": cannot open scene file");
  std::ostringstream ss;
  ss << in.rdbuf();
  return parse_scene(ss.str(), path);
}

namespace {
// splitmix64: a reproducible hash for per-lattice-point jitter (independent of threads/platform).
inline std::uint64_t splitmix(std::uint64_t z) {
  z += 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}
inline Real unit(std::uint64_t h) { return Real(double(h >> 11) * (1.0 / 9007199254740992.0)); }
}  // namespace

std::vector<Vec3> sample_object(const ObjectSpec& obj, Real dx, Real& volume_per_particle) {
  const double h = double(dx) / std::cbrt(double(obj.particles_per_cell));
  volume_per_particle = Real(h * h * h);
  Vec3 lo = obj.min, hi = obj.max;  // box, and the mesh's bounding box
  if (obj.shape == ObjectShape::Sphere) {
    lo = obj.center - Vec3::Constant(obj.radius);
    hi = obj.center + Vec3::Constant(obj.radius);
  }
  long long n[3];
  for (int a = 0; a < 3; ++a) n[a] = std::max(1LL, (long long)std::floor((double(hi[a]) - double(lo[a])) / h));
  if (double(n[0]) * double(n[1]) * double(n[2]) > 2e9)
    throw InputError("object would be sampled with more than 2e9 particles; increase dx or lower particles_per_cell");
  if (obj.shape == ObjectShape::Mesh) return sample_mesh(*obj.mesh, h, double(obj.jitter), obj.seed);
  std::vector<Vec3> pts;
  const double r2 = double(obj.radius) * double(obj.radius);
  for (long long i = 0; i < n[0]; ++i)
    for (long long j = 0; j < n[1]; ++j)
      for (long long k = 0; k < n[2]; ++k) {
        const std::uint64_t id = splitmix(obj.seed ^ splitmix(std::uint64_t(i) * 0x1000003ULL ^ std::uint64_t(j) * 0x10007ULL ^ std::uint64_t(k)));
        Vec3d p(double(lo[0]) + (double(i) + 0.5) * h, double(lo[1]) + (double(j) + 0.5) * h,
                double(lo[2]) + (double(k) + 0.5) * h);
        const double jx = double(obj.jitter) * h;
        p[0] += jx * (double(unit(splitmix(id + 1))) - 0.5);
        p[1] += jx * (double(unit(splitmix(id + 2))) - 0.5);
        p[2] += jx * (double(unit(splitmix(id + 3))) - 0.5);
        if (obj.shape == ObjectShape::Sphere && (p - obj.center.cast<double>()).squaredNorm() > r2) continue;
        pts.push_back(p.cast<Real>());
      }
  return pts;
}

ExplicitMpm build_solver(const Scene& scene) {
  ExplicitMpm solver(scene.mpm, scene.materials, scene.colliders);
  for (const auto& obj : scene.objects) {
    Real vol = 0;
    const std::vector<Vec3> x = sample_object(obj, scene.mpm.dx, vol);
    solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol);
  }
  return solver;
}

}  // namespace amalgam
