#include "io/scene.hpp"

#include <cmath>
#include <limits>
#include <filesystem>
#include <iostream>
#include <fstream>
#include <map>
#include <sstream>

#include "core/errors.hpp"
#include "core/hash.hpp"
#include "io/json_reader.hpp"
#include "io/lattice.hpp"

namespace amalgam {

using detail::JsonObject;

namespace {

constexpr double kHuge = 1e30;

// Elastic constants: Young's modulus and Poisson ratio, or the Lame parameters (not both).
void read_elasticity(JsonObject& o, MaterialParams& m) {
  if (o.has("lame_mu") || o.has("lame_lambda")) {
    if (o.has("youngs_modulus")) o.fail("youngs_modulus", "give either youngs_modulus/poisson_ratio or lame_mu/lame_lambda");
    if (o.has("poisson_ratio")) o.fail("poisson_ratio", "give either youngs_modulus/poisson_ratio or lame_mu/lame_lambda");
    m.mu = Real(o.required_number("lame_mu", 0, kHuge, true));
    m.lambda = Real(o.required_number("lame_lambda", 0, kHuge));
    return;
  }
  const double E = o.required_number("youngs_modulus", 0, kHuge, true);
  const double nu = o.number("poisson_ratio", 0.3, -0.999, 0.499);
  const Lame l = Lame::from_young_poisson(E, nu);
  m.mu = l.mu;
  m.lambda = l.lambda;
}

MaterialParams read_material(JsonObject o) {
  MaterialParams m;
  const std::string model = o.choice("model", "fixed_corotated",
                                     {"fixed_corotated", "neo_hookean", "stvk_hencky", "snow", "drucker_prager",
                                      "von_mises", "fluid"});
  for (int k = 0; k <= int(MaterialModel::Fluid); ++k)
    if (model == material_model_name(MaterialModel(k))) m.model = MaterialModel(k);
  m.density = Real(o.required_number("density", 0, kHuge, true));
  if (m.model == MaterialModel::Fluid) {
    m.bulk = Real(o.required_number("bulk_modulus", 0, kHuge, true));
    m.gamma = Real(o.number("gamma", 7, 1, 20));
    m.viscosity = Real(o.number("viscosity", 0, 0, kHuge));
  } else {
    read_elasticity(o, m);
    m.viscosity = Real(o.number("viscosity", 0, 0, kHuge));  // Kelvin-Voigt damping
  }
  if (m.model == MaterialModel::Snow) {
    m.theta_c = Real(o.number("critical_compression", 2.5e-2, 0, 1, true));
    if (!(m.theta_c < 1)) o.fail("critical_compression", "must be below 1");
    m.theta_s = Real(o.number("critical_stretch", 7.5e-3, 0, 10, true));
    m.hardening = Real(o.number("hardening", 10, 0, 100));
    m.max_hardening = Real(o.number("max_hardening", 10, 1, 1e4));
  } else if (m.model == MaterialModel::DruckerPrager) {
    const double phi = o.number("friction_angle", 30, 0, 80, true) * M_PI / 180.0;
    const double c = o.number("cohesion", 0, 0, kHuge);
    m.friction_alpha = Real(DruckerPragerT<double>::friction_alpha(phi));
    m.apex_trace = Real(DruckerPragerT<double>::apex_trace(m.mu, m.lambda, phi, c));
    m.volume_correction = o.boolean("volume_correction", true);
  } else if (m.model == MaterialModel::VonMises) {
    m.yield_stress = Real(o.required_number("yield_stress", 0, kHuge, true));
    m.hardening_modulus = Real(o.number("hardening_modulus", 0, 0, kHuge));
  }
  if (o.has("melting")) {
    JsonObject melt = o.object("melting");
    m.melting = true;
    m.melting_point = Real(melt.required_number("temperature", 0, kHuge, true));
    m.liquid_bulk = Real(melt.required_number("bulk_modulus", 0, kHuge, true));
    m.liquid_viscosity = Real(melt.number("viscosity", 0, 0, kHuge));
    melt.finish();
  }
  o.finish();
  return m;
}

// Peridynamic material (model "peridynamic"): elastic constants as bulk/shear modulus or
// Young's modulus/Poisson ratio; plasticity by yield_stress (or the paper's psi0) and
// plastic_cap; fracture by critical_stretch and damage_alpha (eq. 18); anisotropy (eq. 16) as
// G = I + (ratio - 1) n n^T for a unit axis n.
PdMaterial read_pd_material(JsonObject o, Real horizon) {
  PdMaterial m;
  o.choice("model", "", {"peridynamic"});
  m.density = Real(o.required_number("density", 0, kHuge, true));
  if (o.has("bulk_modulus") || o.has("shear_modulus")) {
    if (o.has("youngs_modulus")) o.fail("youngs_modulus", "give either youngs_modulus/poisson_ratio or bulk_modulus/shear_modulus");
    if (o.has("poisson_ratio")) o.fail("poisson_ratio", "give either youngs_modulus/poisson_ratio or bulk_modulus/shear_modulus");
    m.bulk = Real(o.required_number("bulk_modulus", 0, kHuge, true));
    m.shear = Real(o.required_number("shear_modulus", 0, kHuge, true));
  } else {
    const double E = o.required_number("youngs_modulus", 0, kHuge, true);
    const double nu = o.number("poisson_ratio", 0.25, -0.999, 0.499);
    m.bulk = Real(E / (3 * (1 - 2 * nu)));
    m.shear = Real(E / (2 * (1 + nu)));
  }
  if (o.has("yield_stress") && o.has("psi0")) o.fail("psi0", "give either yield_stress or psi0, not both");
  if (o.has("yield_stress")) m.psi0 = pd_psi0_from_yield_stress(Real(o.required_number("yield_stress", 0, kHuge, true)), horizon);
  if (o.has("psi0")) m.psi0 = Real(o.required_number("psi0", 0, 1e38, true));
  const bool plastic = o.has("yield_stress") || o.has("psi0");
  if (o.has("plastic_cap") && !plastic) o.fail("plastic_cap", "needs yield_stress or psi0 (the material is elastic)");
  if (o.has("plastic_cap")) m.plastic_cap = Real(o.required_number("plastic_cap", 0, kHuge, true));
  if (o.has("critical_stretch")) m.critical_stretch = Real(o.required_number("critical_stretch", 0, kHuge, true));
  if (o.has("damage_alpha") && !o.has("critical_stretch"))
    o.fail("damage_alpha", "needs critical_stretch (the material does not fracture)");
  m.alpha = Real(o.number("damage_alpha", 0, 0, 1e6));
  if (o.has("anisotropy")) {
    JsonObject an = o.object("anisotropy");
    const Vec3 axis = an.required_vec3("axis");
    if (!(axis.norm() > 0)) an.fail("axis", "must be a non-zero vector");
    const Real ratio = Real(an.required_number("ratio", 0, 1e6, true));
    const Vec3 n = axis.normalized();
    m.G = Mat3::Identity() + (ratio - 1) * n * n.transpose();
    an.finish();
  }
  o.finish();
  return m;
}

// A file named in a scene: absolute, or relative to the scene file's folder.
std::filesystem::path scene_relative(const std::string& file, const std::string& scene_file) {
  return std::filesystem::path(file).is_absolute() ? std::filesystem::path(file)
                                                   : std::filesystem::path(scene_file).parent_path() / file;
}

// Places mesh points by the object's scale, rotate_degrees and translate:
// x' = Rz Ry Rx (scale x) + translate.
void place_points(JsonObject& o, std::vector<Vec3d>& points) {
  const double scale = o.number("scale", 1.0, 0, 1e30, true);
  const Vec3d deg = o.vec3("rotate_degrees", Vec3::Zero()).cast<double>();
  const Vec3 t = o.vec3("translate", Vec3::Zero());
  const double k = M_PI / 180.0;
  const Mat3d R = (Eigen::AngleAxisd(deg[2] * k, Vec3d::UnitZ()) * Eigen::AngleAxisd(deg[1] * k, Vec3d::UnitY()) *
                   Eigen::AngleAxisd(deg[0] * k, Vec3d::UnitX()))
                      .toRotationMatrix();
  for (auto& v : points) v = R * (v * scale) + t.cast<double>();
}

std::shared_ptr<const TriangleMesh> read_mesh_object(JsonObject& o, const std::string& scene_file) {
  const std::string file = o.string("file", "");
  if (!o.has("file") || file.empty()) o.fail("file", "missing required mesh file (.obj, .off or .ply)");
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
    const std::string what = "mesh file \"" + file + "\" is not watertight (" + std::to_string(c.boundary_edges) +
                             " boundary edges, " + std::to_string(c.nonmanifold_edges) +
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
  if (!o.has("file") || file.empty()) o.fail("file", "missing required TetGen file (.node with its .ele)");
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

ObjectSpec read_object(JsonObject o, const std::map<std::string, int>& materials, const std::string& scene_file,
                       bool peridynamics, bool domains) {
  ObjectSpec s;
  const std::string shape = o.choice("shape", "", {"box", "sphere", "cylinder", "torus", "mesh", "tet_mesh"});
  if (shape == "tet_mesh") {
    if (!peridynamics) o.fail("shape", "\"tet_mesh\" needs \"method\": \"peridynamics\" (MPM samples \"mesh\" surfaces)");
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
    s.min = o.required_vec3("min");
    s.max = o.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(s.max[a] > s.min[a])) o.fail("max", "every component must exceed the matching one of \"min\"");
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
  // Peridynamics wants a regular lattice (its bond families and constants assume one).
  s.particles_per_cell = int(o.integer("particles_per_cell", peridynamics ? 1 : 8, 1, 64));
  s.jitter = Real(o.number("jitter", peridynamics || domains ? 0.0 : 0.5, 0, 1));
  // Particle domains are the lattice cells around the particles: corners are shared only on a lattice.
  if (domains && s.jitter != 0) o.fail("jitter", "must be 0 with particle domains (/simulation/domains)");
  s.seed = std::uint64_t(o.integer("seed", 1, 0, (1LL << 62)));
  s.temperature = Real(o.number("temperature", 293.15, 0, kHuge));
  if (o.has("configuration")) {
    if (peridynamics) o.fail("configuration", "configuration maps (A-ULMPM) are for MPM objects");
    JsonObject c = o.object("configuration");
    s.has_configuration = true;
    const std::string u = c.choice("update", "adaptive", {"adaptive", "total_lagrangian", "eulerian"});
    s.configuration.update = u == "adaptive"           ? ConfigurationUpdate::Adaptive
                             : u == "total_lagrangian" ? ConfigurationUpdate::TotalLagrangian
                                                       : ConfigurationUpdate::Eulerian;
    s.configuration.epsilon = Real(c.number("epsilon", 0.5, 0, kHuge, true));
    s.configuration.eta = Real(c.number("eta", 0.1, 0, 1));
    if (u != "adaptive" && (c.has("epsilon") || c.has("eta")))
      c.fail(c.has("epsilon") ? "epsilon" : "eta", "only used with \"update\": \"adaptive\"");
    c.finish();
  }
  o.finish();
  return s;
}

// Geometry and motion shared by colliders and heat sources.
Collider read_region(JsonObject& o, bool allow_mesh = false) {
  Collider c;
  const std::string type = allow_mesh ? o.choice("type", "", {"half_space", "box", "sphere", "mesh"})
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

// Mesh collider: the mesh (file, scale, rotate_degrees, translate, allow_open) is its rest pose,
// baked to a signed distance field of spacing dx; it moves with `velocity` or by `keyframes`
// (time, translate, rotate_degrees: a rigid motion about `pivot`, default the mesh's box centre).
void read_mesh_collider(JsonObject& o, Collider& c, const std::string& scene_file, Real dx) {
  const std::shared_ptr<const TriangleMesh> mesh = read_mesh_object(o, scene_file);
  Vec3d lo = Vec3d::Constant(1e300), hi = Vec3d::Constant(-1e300);
  for (const auto& v : mesh->vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
  try {
    c.sdf = bake_sdf(*mesh, double(dx), 4.0 * double(dx));
  } catch (const InputError& e) {
    o.fail("file", e.what());
  }
  c.pivot = o.vec3("pivot", (0.5 * (lo + hi)).cast<Real>());
  const bool has_velocity = o.has("velocity");
  c.velocity = o.vec3("velocity", Vec3::Zero());
  const double k = M_PI / 180.0;
  for (auto& kf : o.objects("keyframes")) {
    RigidKeyframe key;
    key.time = Real(kf.required_number("time", 0, kHuge));
    if (!c.keys.empty() && !(key.time > c.keys.back().time)) kf.fail("time", "keyframe times must increase");
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
  if (has_velocity && !c.keys.empty()) o.fail("velocity", "give either velocity or keyframes, not both");
}

// `until` (s): the region acts up to this time only (a grip that lets go, a heater switched off).
void read_until(JsonObject& o, Collider& c) {
  if (o.has("until")) c.until = Real(o.required_number("until", 0, kHuge, true));
}

Collider read_collider(JsonObject o, const std::string& scene_file, Real dx) {
  Collider c = read_region(o, true);
  if (c.shape == ColliderShape::Mesh) read_mesh_collider(o, c, scene_file, dx);
  read_until(o, c);
  const std::string b = o.choice("boundary", "separate", {"sticky", "slip", "separate"});
  c.boundary = b == "sticky" ? BoundaryType::Sticky : b == "slip" ? BoundaryType::Slip : BoundaryType::Separate;
  c.friction = Real(o.number("friction", 0, 0, 100));
  o.finish();
  return c;
}

HeatSource read_heat_source(JsonObject o) {
  HeatSource h;
  h.region = read_region(o);
  read_until(o, h.region);
  h.temperature = Real(o.required_number("temperature", 0, kHuge));
  h.rate = Real(o.required_number("rate", 0, kHuge, true));
  o.finish();
  return h;
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
  s.method = sim.choice("method", "mpm", {"mpm", "peridynamics"}) == "mpm" ? Method::Mpm : Method::Peridynamics;
  const bool pd = s.method == Method::Peridynamics;
  if (pd)
    for (const char* k : {"transfer", "order", "flip_alpha", "integrator", "implicit"})
      if (sim.has(k)) sim.fail(k, "only for \"method\": \"mpm\"");
  if (!pd && sim.has("peridynamics")) sim.fail("peridynamics", "set \"method\": \"peridynamics\" to use these settings");
  s.mpm.dx = Real(sim.required_number("dx", 0, kHuge, true));
  s.mpm.order = int(sim.integer("order", 2, 2, 3));
  const std::string tr = sim.choice("transfer", "mls", {"mls", "apic", "pic", "flip"});
  s.mpm.transfer = tr == "mls" ? Transfer::Mls : tr == "apic" ? Transfer::Apic : Transfer::PicFlip;
  s.mpm.flip_alpha = Real(sim.number("flip_alpha", tr == "pic" ? 0.0 : 0.95, 0, 1));
  if (tr == "pic" && s.mpm.flip_alpha != 0) sim.fail("flip_alpha", "must be 0 (or absent) with transfer \"pic\"");
  s.mpm.cfl = Real(sim.number("cfl", pd ? 0.7 : 0.4, 0, 1, true));
  s.fps = sim.number("fps", 24, 0, 1e6, true);
  s.mpm.max_dt = Real(sim.number("max_dt", 1e-3, 0, kHuge, true));
  s.mpm.gravity = sim.vec3("gravity", Vec3(0, Real(-9.81), 0));
  s.mpm.max_speed = Real(sim.number("max_speed", 1e4, 0, kHuge, true));
  s.frames = int(sim.integer("frames", 48, 1, 1000000));
  s.mpm.implicit = sim.choice("integrator", "explicit", {"explicit", "implicit"}) == "implicit";
  {
    JsonObject imp = sim.object("implicit");
    if (imp.has("tolerance") || imp.has("max_iterations") || imp.has("solver") || imp.has("definiteness_fix"))
      if (!s.mpm.implicit) sim.fail("implicit", "set \"integrator\": \"implicit\" to use these settings");
    s.mpm.solver.tolerance = imp.number("tolerance", 1e-4, 0, 1, true);
    s.mpm.solver.max_iterations = int(imp.integer("max_iterations", 200, 1, 100000));
    s.mpm.solver.method = imp.choice("solver", "cg", {"cg", "minres"}) == "cg" ? KrylovMethod::Cg : KrylovMethod::Minres;
    s.mpm.solver.definiteness_fix = imp.boolean("definiteness_fix", true);
    imp.finish();
  }
  JsonObject contact = sim.object("contact");
  const bool has_contact = sim.has("contact");
  if (pd && has_contact) sim.fail("contact", "only for \"method\": \"mpm\" (peridynamics sets its contact in \"peridynamics\")");
  {
    const std::string mode = contact.choice("mode", "stick", {"stick", "separate", "none"});
    s.mpm.contact.mode = mode == "stick"      ? ObjectContactMode::Stick
                         : mode == "separate" ? ObjectContactMode::Separate
                                              : ObjectContactMode::None;
    s.mpm.contact.friction = Real(contact.number("friction", 0, 0, kHuge));
    if (contact.has("friction") && mode != "separate")
      contact.fail("friction", "only with \"mode\": \"separate\" (stick contact has no slip)");
    contact.finish();
  }
  if (sim.has("domains")) {
    if (pd) sim.fail("domains", "only for \"method\": \"mpm\"");
    JsonObject d = sim.object("domains");
    s.mpm.domains.enabled = true;
    s.mpm.domains.enrichment = d.boolean("enrichment", true);
    s.mpm.domains.epsilon = Real(d.number("epsilon", 0.6, 0, 1));
    if (d.has("epsilon") && !s.mpm.domains.enrichment) d.fail("epsilon", "only with \"enrichment\": true");
    s.mpm.domains.clamp = Real(d.number("inversion_clamp", 0.15, 0, 1, true));
    s.mpm.domains.elasticity_from = Real(d.number("elasticity_from", 0, 0, kHuge));
    s.mpm.domains.gauss_quadrature = d.choice("quadrature", "gauss", {"gauss", "one_point"}) == "gauss";
    d.finish();
    if (sim.has("transfer") && tr != "flip" && tr != "pic")
      sim.fail("transfer", "particle domains transfer by PIC/FLIP on linear weights: \"flip\" (flip_alpha, default "
                           "0.95) or \"pic\"");
    if (sim.has("order")) sim.fail("order", "particle domains use linear grid weights (enriched MPM eq. 3)");
  }
  {
    JsonObject p = sim.object("peridynamics");
    const double factor = p.number("horizon_factor", 3.015, 1, 8, true);
    s.pd.deviatoric = p.choice("deviatoric", "paper", {"paper", "lps"}) == "paper" ? PdDeviatoric::Paper : PdDeviatoric::Lps;
    s.pd.surface_correction = p.boolean("surface_correction", true);
    s.pd.partial_volume = p.boolean("partial_volume", true);
    s.pd.fracture = p.boolean("fracture", true);
    s.pd.contact = p.boolean("contact", true);
    const double contact = p.number("contact_distance", 0.9, 0, 3, true);
    s.pd.damping = Real(p.number("damping", 0, 0, 1e12));
    s.pd.compact_fraction = Real(p.number("compact_fraction", 0.1, 0, 1));
    p.finish();
    s.pd.horizon = Real(factor);  // times the spacing, set once the objects are known
    s.pd.contact_distance = Real(contact);
  }
  sim.finish();

  std::map<std::string, int> mat_index;
  JsonObject mats = top.object("materials");
  if (!top.has("materials") || mats.keys().empty()) top.fail("materials", "define at least one material");
  // Peridynamics: the lattice spacing comes from dx and the objects' particles_per_cell, and the
  // horizon (which yield_stress needs) from the spacing: read the objects first.
  for (const auto& name : mats.keys()) {
    mat_index[name] = int(s.material_names.size());
    s.material_names.push_back(name);
  }
  if (!top.has("objects")) top.fail("objects", "missing required array of objects");
  for (auto& o : top.objects("objects")) s.objects.push_back(read_object(o, mat_index, file, pd, s.mpm.domains.enabled));
  if (s.objects.empty()) top.fail("objects", "define at least one object");
  // A-ULMPM: objects in their own configuration maps do not share reference nodes and touch
  // through the global-grid contact (simulation/contact), shared-grid objects through their one
  // grid: mixing the two would leave them passing through each other. (An object that should
  // behave like plain MPM takes "configuration": {"update": "eulerian"}.)
  for (std::size_t k = 0; k < s.objects.size(); ++k)
    if (s.objects[k].has_configuration != s.objects[0].has_configuration) {
      const std::size_t bad = s.objects[0].has_configuration ? k : 0;
      throw InputError(file + ": /objects/" + std::to_string(bad) +
                       "/configuration: missing; when one object keeps a configuration map (A-ULMPM), every "
                       "object must have a \"configuration\" block");
    }
  s.mpm.configuration_maps = s.objects[0].has_configuration;
  if (s.mpm.domains.enabled && s.mpm.configuration_maps)
    sim.fail("domains", "particle domains cannot be combined with configuration maps (objects' \"configuration\")");
  if (has_contact && !s.mpm.configuration_maps)
    sim.fail("contact", "only for objects with a \"configuration\" block (A-ULMPM); objects on the shared grid "
                        "already interact through it");
  std::size_t tet_objects = 0;
  double edge_sum = 0, edge_count = 0;
  for (const auto& o : s.objects)
    if (o.shape == ObjectShape::TetMesh) {
      ++tet_objects;
      edge_sum += tet_mean_edge(*o.tets) * double(o.tets->tets.size());
      edge_count += double(o.tets->tets.size());
    }
  if (tet_objects > 0 && tet_objects < s.objects.size())
    top.fail("objects", "tet_mesh objects cannot be mixed with lattice-sampled objects (their spacings differ)");
  if (pd && tet_objects > 0) {
    // One particle per tetrahedron: the spacing is the mean edge length (the paper's lambda).
    s.pd.spacing = Real(edge_sum / edge_count);
    s.pd.horizon *= s.pd.spacing;
    s.pd.contact_distance *= s.pd.spacing;
    s.pd.gravity = s.mpm.gravity;
    s.pd.cfl = s.mpm.cfl;
    s.pd.max_dt = s.mpm.max_dt;
  } else if (pd) {
    const int ppc = s.objects[0].particles_per_cell;
    for (std::size_t k = 1; k < s.objects.size(); ++k)
      if (s.objects[k].particles_per_cell != ppc)
        throw InputError(file + ": /objects/" + std::to_string(k) +
                         "/particles_per_cell: peridynamic objects share one lattice spacing; use the same value as "
                         "/objects/0 (" + std::to_string(ppc) + ")");
    s.pd.spacing = Real(double(s.mpm.dx) / std::cbrt(double(ppc)));
    s.pd.horizon *= s.pd.spacing;
    s.pd.contact_distance *= s.pd.spacing;
    s.pd.gravity = s.mpm.gravity;
    s.pd.cfl = s.mpm.cfl;
    s.pd.max_dt = s.mpm.max_dt;
  }
  for (const auto& name : s.material_names) {
    JsonObject mo = mats.object(name);
    const bool is_pd = mo.has("model") && mo.string("model", "") == "peridynamic";
    if (pd && !is_pd) mo.fail("model", "a peridynamics scene needs \"model\": \"peridynamic\"");
    if (!pd && is_pd) mo.fail("model", "\"peridynamic\" needs \"method\": \"peridynamics\" in /simulation");
    if (pd) {
      s.pd_materials.push_back(read_pd_material(mats.object(name), s.pd.horizon));
      MaterialParams mp;  // density only: what the shared diagnostics and previews read
      mp.density = s.pd_materials.back().density;
      s.materials.push_back(mp);
    } else {
      s.materials.push_back(read_material(mats.object(name)));
      const MaterialParams& m = s.materials.back();
      if (s.mpm.domains.enabled && (m.model == MaterialModel::Fluid || m.has_plastic_state() || m.viscosity > 0))
        throw InputError(file + ": /materials/" + name +
                         ": particle domains (/simulation/domains) need an elastic solid (fixed_corotated, "
                         "neo_hookean or stvk_hencky, no viscosity; it may melt)");
    }
  }
  mats.finish();
  if (!pd && top.has("boundary_conditions"))
    top.fail("boundary_conditions", "only for \"method\": \"peridynamics\" (MPM uses colliders)");
  for (auto& b : top.objects("boundary_conditions")) {
    PdBoundarySpec bc;
    bc.min = b.required_vec3("min");
    bc.max = b.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(bc.max[a] >= bc.min[a])) b.fail("max", "every component must be at least the matching one of \"min\"");
    if (b.has("velocity") && b.has("force_density"))
      b.fail("force_density", "give either velocity (prescribed motion) or force_density (a load), not both");
    bc.velocity = b.vec3("velocity", Vec3::Zero());
    bc.load = b.has("force_density");
    bc.force_density = b.vec3("force_density", Vec3::Zero());
    b.finish();
    s.pd_boundaries.push_back(bc);
  }
  for (auto& c : top.objects("colliders")) s.colliders.push_back(read_collider(c, file, s.mpm.dx));
  for (auto& h : top.objects("heat_sources")) s.heat_sources.push_back(read_heat_source(h));
  if (!pd && top.has("precracks")) top.fail("precracks", "only for \"method\": \"peridynamics\"");
  for (auto& c : top.objects("precracks")) {
    PdPrecrackSpec pc;
    pc.point = c.required_vec3("point");
    pc.normal = c.required_vec3("normal");
    if (!(pc.normal.norm() > 0)) c.fail("normal", "must be a non-zero vector");
    pc.min = c.required_vec3("min");
    pc.max = c.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(pc.max[a] >= pc.min[a])) c.fail("max", "every component must be at least the matching one of \"min\"");
    c.finish();
    s.pd_precracks.push_back(pc);
  }
  if (pd && !s.heat_sources.empty()) top.fail("heat_sources", "only for \"method\": \"mpm\"");
  if (!s.heat_sources.empty()) {
    bool melts = false;
    for (const auto& m : s.materials) melts |= m.melting;
    if (!melts) top.fail("heat_sources", "no material has a \"melting\" block, so heat sources would do nothing");
  }

  JsonObject out = top.object("output");
  s.output.directory = out.string("directory", "out");
  s.output.ply = out.boolean("ply", true);
  s.output.vdb_points = out.boolean("vdb_points", true);
  s.output.diagnostics_csv = out.boolean("diagnostics_csv", true);
  s.output.grid_volumes = out.boolean("grid_volumes", false);
  s.output.checkpoint_every = int(out.integer("checkpoint_every", 10, 0, 1000000));
  const std::string surf = out.choice("surface", "obj", {"obj", "ply", "both", "none"});
  s.output.surface_obj = surf == "obj" || surf == "both";
  s.output.surface_ply = surf == "ply" || surf == "both";
  out.finish();

  if (top.has("preview")) {
    JsonObject pv = top.object("preview");
    s.preview.width = int(pv.integer("width", 640, 16, 8192));
    s.preview.height = int(pv.integer("height", 480, 16, 8192));
    const std::string c = pv.choice("color_by", "material", {"material", "speed", "temperature", "plastic", "damage"});
    s.preview.color_by = c == "speed" ? ColorBy::Speed
                         : c == "damage" ? ColorBy::Damage
                         : c == "temperature" ? ColorBy::Temperature
                         : c == "plastic" ? ColorBy::Plastic
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
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path + ": cannot open scene file");
  std::ostringstream ss;
  ss << in.rdbuf();
  return parse_scene(ss.str(), path);
}

std::vector<Vec3> sample_object(const ObjectSpec& obj, Real dx, Real& volume_per_particle) {
  const double h = double(dx) / std::cbrt(double(obj.particles_per_cell));
  volume_per_particle = Real(h * h * h);
  const Vec3 lo = obj.min, hi = obj.max;  // every shape's bounding box
  long long n[3];
  // A box is filled exactly by whole lattice cells (round); curved shapes need the whole bounding
  // box covered (ceil) and are cut by their inside test.
  for (int a = 0; a < 3; ++a) {
    const double cells = (double(hi[a]) - double(lo[a])) / h;
    n[a] = std::max(1LL, (long long)(obj.shape == ObjectShape::Box ? std::llround(cells) : std::ceil(cells)));
  }
  if (double(n[0]) * double(n[1]) * double(n[2]) > 2e9)
    throw InputError("object would be sampled with more than 2e9 particles; increase dx or lower particles_per_cell");
  if (obj.shape == ObjectShape::Mesh) return sample_mesh(*obj.mesh, h, double(obj.jitter), obj.seed);
  if (obj.shape == ObjectShape::TetMesh) {  // barycentres; their volumes differ: the mean here
    std::vector<Vec3> x;
    std::vector<Real> vol;
    tet_barycentres(*obj.tets, x, vol);
    double sum = 0;
    for (Real v : vol) sum += double(v);
    volume_per_particle = Real(sum / double(std::max<std::size_t>(1, vol.size())));
    return x;
  }
  const Vec3d c = obj.center.cast<double>();
  const double r2 = double(obj.radius) * double(obj.radius);
  const int ax = obj.axis;
  const double half_h = 0.5 * double(obj.height), R = double(obj.radius), r = double(obj.minor_radius);
  return sample_lattice(lo.cast<double>(), n, h, double(obj.jitter), obj.seed, [&](const Vec3d& p) {
    const Vec3d d = p - c;
    const double along = d[ax], across2 = d.squaredNorm() - along * along;
    switch (obj.shape) {
      case ObjectShape::Box: return true;
      case ObjectShape::Sphere: return d.squaredNorm() <= r2;
      case ObjectShape::Cylinder: return std::abs(along) <= half_h && across2 <= r2;
      case ObjectShape::Torus: {
        const double ring = std::sqrt(across2) - R;
        return ring * ring + along * along <= r * r;
      }
      case ObjectShape::Mesh:
      case ObjectShape::TetMesh: break;
    }
    return false;
  });
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

double preview_radius(const Scene& scene) {
  int ppc = 1;
  for (const auto& o : scene.objects) ppc = std::max(ppc, o.particles_per_cell);
  return 0.6 * double(scene.mpm.dx) / std::cbrt(double(ppc));
}

MpmSolver build_solver(const Scene& scene) {
  MpmSolver solver(scene.mpm, scene.materials, scene.colliders, scene.heat_sources);
  for (const auto& obj : scene.objects) {
    Real vol = 0;
    const std::vector<Vec3> x = sample_object(obj, scene.mpm.dx, vol);
    const std::size_t first = solver.particles().size();
    solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol, obj.temperature,
                         obj.configuration);
    if (scene.mpm.domains.enabled) {
      const Real h = Real(double(scene.mpm.dx) / std::cbrt(double(obj.particles_per_cell)));
      if (obj.mesh)  // the mesh is embedded in the domains and written deformed every frame (Sec. 4.1)
        solver.add_particle_domains(first, h, &obj.mesh->vertices, &obj.mesh->triangles);
      else
        solver.add_particle_domains(first, h);
    }
  }
  return solver;
}

PdSolver build_pd_solver(const Scene& scene) {
  PdSolver solver(scene.pd, scene.pd_materials, scene.colliders);
  for (const auto& obj : scene.objects) {
    if (obj.shape == ObjectShape::TetMesh) {
      std::vector<Vec3> x;
      std::vector<Real> vol;
      tet_barycentres(*obj.tets, x, vol);
      const auto first = std::uint32_t(solver.particles().size());
      solver.add_particles(x, vol, obj.velocity, obj.angular_velocity, obj.center, obj.material);
      solver.add_crack_mesh(obj.tets->nodes, obj.tets->tets, first);  // crack surfaces (Sec. 5.2)
      continue;
    }
    Real vol = 0;
    const std::vector<Vec3> x = sample_object(obj, scene.mpm.dx, vol);
    solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol);
  }
  for (const auto& b : scene.pd_boundaries) {
    if (b.load) solver.apply_force_density(b.min, b.max, b.force_density);
    else solver.prescribe_velocity(b.min, b.max, b.velocity);
  }
  for (const auto& c : scene.pd_precracks) solver.add_precrack(c.point, c.normal, c.min, c.max);
  return solver;
}

}  // namespace amalgam
