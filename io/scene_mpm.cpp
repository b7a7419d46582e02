// Scene files, the MPM part: MPM materials, the MPM keys of /simulation (transfer, order,
// integrator, contact between A-ULMPM objects, particle domains), A-ULMPM's rule that every
// object or none keeps a configuration map, and heat sources. Other methods' keys are rejected.
#include <cmath>
#include <string>

#include "core/errors.hpp"
#include "io/scene_parts.hpp"

namespace amalgam::scene_detail {

namespace {

// Elastic constants: Young's modulus and Poisson ratio, or the Lame parameters (not both).
void read_elasticity(JsonObject& o, MaterialParams& m) {
  if (o.has("lame_mu") || o.has("lame_lambda")) {
    if (o.has("youngs_modulus"))
      o.fail("youngs_modulus", "give either youngs_modulus/poisson_ratio or lame_mu/lame_lambda");
    if (o.has("poisson_ratio"))
      o.fail("poisson_ratio", "give either youngs_modulus/poisson_ratio or lame_mu/lame_lambda");
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
                                     {"fixed_corotated", "neo_hookean", "stvk_hencky", "snow",
                                      "drucker_prager", "von_mises", "fluid"});
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

HeatSource read_heat_source(JsonObject o) {
  HeatSource h;
  h.region = read_region(o);
  read_until(o, h.region);
  h.temperature = Real(o.required_number("temperature", 0, kHuge));
  h.rate = Real(o.required_number("rate", 0, kHuge, true));
  o.finish();
  return h;
}

// Kill regions (solvers/mpm_sources.hpp): "outside" {min, max}, "volumes" [regions].
void read_kill(JsonObject& sim, Scene& s) {
  JsonObject k = sim.object("kill");
  KillSettings& kill = s.mpm.kill;
  if (k.has("outside")) {
    JsonObject b = k.object("outside");
    kill.outside = true;
    read_box(b, kill.min, kill.max);
    b.finish();
  }
  for (auto& v : k.objects("volumes")) {
    if (v.has("velocity")) v.fail("velocity", "kill volumes do not move");
    kill.volumes.push_back(read_region(v));
    v.finish();
  }
  k.finish();
  if (!kill.enabled()) sim.fail("kill", "give \"outside\" or \"volumes\"");
  if (s.mpm.domains.enabled)
    sim.fail("kill", "not with particle domains (/simulation/domains): plain MPM only");
}

}  // namespace

void read_mpm_simulation(JsonObject& sim, Scene& s) {
  if (sim.has("peridynamics"))
    sim.fail("peridynamics", "set \"method\": \"peridynamics\" to use these settings");
  s.mpm.order = int(sim.integer("order", 2, 2, 3));
  const std::string tr = sim.choice("transfer", "mls", {"mls", "apic", "pic", "flip"});
  s.mpm.transfer = tr == "mls" ? Transfer::Mls : tr == "apic" ? Transfer::Apic : Transfer::PicFlip;
  s.mpm.flip_alpha = Real(sim.number("flip_alpha", tr == "pic" ? 0.0 : 0.95, 0, 1));
  if (tr == "pic" && s.mpm.flip_alpha != 0)
    sim.fail("flip_alpha", "must be 0 (or absent) with transfer \"pic\"");
  s.mpm.implicit = sim.choice("integrator", "explicit", {"explicit", "implicit"}) == "implicit";
  // One pass over the particles per substep (G2P2G) where the variant fuses; docs/architecture.md.
  s.mpm.fused = sim.choice("transfer_pass", "two_pass", {"fused", "two_pass"}) == "fused";
  // The two passes re-sort the particles only when one leaves its bin's dilated block, where the
  // variant allows it (sorts_when_needed); docs/architecture.md.
  s.mpm.sort_when_needed =
      sim.choice("sort", "when_needed", {"every_substep", "when_needed"}) == "when_needed";
  {
    JsonObject imp = sim.object("implicit");
    if (imp.has("tolerance") || imp.has("max_iterations") || imp.has("solver") ||
        imp.has("definiteness_fix"))
      if (!s.mpm.implicit)
        sim.fail("implicit", "set \"integrator\": \"implicit\" to use these settings");
    s.mpm.solver.tolerance = imp.number("tolerance", 1e-4, 0, 1, true);
    s.mpm.solver.max_iterations = int(imp.integer("max_iterations", 200, 1, 100000));
    s.mpm.solver.method = imp.choice("solver", "cg", {"cg", "minres"}) == "cg"
                              ? KrylovMethod::Cg
                              : KrylovMethod::Minres;
    s.mpm.solver.definiteness_fix = imp.boolean("definiteness_fix", true);
    imp.finish();
  }
  {
    JsonObject contact = sim.object("contact");
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
    JsonObject d = sim.object("domains");
    s.mpm.domains.enabled = true;
    s.mpm.domains.enrichment = d.boolean("enrichment", true);
    s.mpm.domains.epsilon = Real(d.number("epsilon", 0.6, 0, 1));
    if (d.has("epsilon") && !s.mpm.domains.enrichment)
      d.fail("epsilon", "only with \"enrichment\": true");
    s.mpm.domains.clamp = Real(d.number("inversion_clamp", 0.15, 0, 1, true));
    s.mpm.domains.elasticity_from = Real(d.number("elasticity_from", 0, 0, kHuge));
    s.mpm.domains.gauss_quadrature =
        d.choice("quadrature", "gauss", {"gauss", "one_point"}) == "gauss";
    d.finish();
    if (sim.has("transfer") && tr != "flip" && tr != "pic")
      sim.fail(
          "transfer",
          "particle domains transfer by PIC/FLIP on linear weights: \"flip\" (flip_alpha, default "
          "0.95) or \"pic\"");
    if (sim.has("order"))
      sim.fail("order", "particle domains use linear grid weights (enriched MPM eq. 3)");
  }
  if (sim.has("kill")) read_kill(sim, s);
  if (sim.has("sleep")) {
    JsonObject z = sim.object("sleep");
    SleepSettings& sl = s.mpm.sleep;
    sl.enabled = z.boolean("enabled", true);
    sl.speed = Real(z.number("speed", 0.02, 0, kHuge, true));
    sl.strain_rate = Real(z.number("strain_rate", 0.5, 0, kHuge, true));
    sl.time = Real(z.number("time", 0.1, 0, kHuge));
    sl.halo = Real(z.number("halo", 2 * double(s.mpm.dx), 0, kHuge));
    z.finish();
    if (sl.enabled &&
        (s.mpm.implicit || s.mpm.transfer == Transfer::PicFlip || s.mpm.domains.enabled))
      sim.fail("sleep",
               "needs the explicit integrator with transfer \"mls\" or \"apic\" (not implicit, "
               "PIC/FLIP nor particle domains)");
  }
}

void check_mpm_objects(JsonObject& sim, Scene& s) {
  // A-ULMPM: objects in their own configuration maps do not share reference nodes and touch
  // through the global-grid contact (simulation/contact), shared-grid objects through their one
  // grid: mixing the two would leave them passing through each other. (An object that should
  // behave like plain MPM takes "configuration": {"update": "eulerian"}.)
  for (std::size_t k = 0; k < s.objects.size(); ++k)
    if (s.objects[k].has_configuration != s.objects[0].has_configuration) {
      const std::size_t bad = s.objects[0].has_configuration ? k : 0;
      throw InputError(
          s.file + ": /objects/" + std::to_string(bad) +
          "/configuration: missing; when one object keeps a configuration map (A-ULMPM), every "
          "object must have a \"configuration\" block");
    }
  s.mpm.configuration_maps = s.objects[0].has_configuration;
  if (s.mpm.domains.enabled && s.mpm.configuration_maps)
    sim.fail(
        "domains",
        "particle domains cannot be combined with configuration maps (objects' \"configuration\")");
  if (s.mpm.sleep.enabled && s.mpm.configuration_maps)
    sim.fail("sleep", "not with A-ULMPM objects (\"configuration\" blocks): plain MPM only");
  if (sim.has("kill") && s.mpm.configuration_maps)
    sim.fail("kill", "not with A-ULMPM objects (\"configuration\" blocks): plain MPM only");
  if (sim.has("contact") && !s.mpm.configuration_maps)
    sim.fail(
        "contact",
        "only for objects with a \"configuration\" block (A-ULMPM); objects on the shared grid "
        "already interact through it");
}

void read_mpm_materials(JsonObject& mats, Scene& s) {
  for (const auto& name : s.material_names) {
    JsonObject mo = mats.object(name);
    if (mo.has("model") && mo.string("model", "") == "peridynamic")
      mo.fail("model", "\"peridynamic\" needs \"method\": \"peridynamics\" in /simulation");
    s.materials.push_back(read_material(mats.object(name)));
    const MaterialParams& m = s.materials.back();
    if (s.mpm.domains.enabled &&
        (m.model == MaterialModel::Fluid || m.has_plastic_state() || m.viscosity > 0))
      throw InputError(
          s.file + ": /materials/" + name +
          ": particle domains (/simulation/domains) need an elastic solid (fixed_corotated, "
          "neo_hookean or stvk_hencky, no viscosity; it may melt)");
  }
}

void read_mpm_sources(JsonObject& top, Scene& s) {
  // Prescribed-velocity regions: grid nodes in [min, max] take v(x, t), a sticky box collider
  // that does not move and whose velocity is the field (Collider::drive).
  for (auto& b : top.objects("boundary_conditions")) {
    ColliderSpec c;
    const Vec3 lo = b.required_vec3("min"), hi = b.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(hi[a] > lo[a]))
        b.fail("max", "every component must be above the matching one of \"min\"");
    if (b.has("force_density"))
      b.fail("force_density", "only for \"method\": \"peridynamics\" (MPM: use gravity)");
    c.shape = ColliderShape::Box;
    c.boundary = BoundaryType::Sticky;
    c.origin = Real(0.5) * (lo + hi);
    c.half_extent = Real(0.5) * (hi - lo);
    c.drive = b.has("velocity") ? b.vector_field("velocity", true)
                                : std::make_shared<const VectorField>();
    c.where = b.where("velocity");
    read_until(b, c);
    b.finish();
    if (s.mpm.domains.enabled)
      b.fail("velocity", "not with particle domains (/simulation/domains): use a sticky collider");
    s.colliders.push_back(c);
  }
  if (top.has("precracks")) top.fail("precracks", "only for \"method\": \"peridynamics\"");
  for (auto& h : top.objects("heat_sources")) s.heat_sources.push_back(read_heat_source(h));
  if (!s.heat_sources.empty()) {
    bool melts = false;
    for (const auto& m : s.materials) melts |= m.melting;
    if (!melts)
      top.fail("heat_sources",
               "no material has a \"melting\" block, so heat sources would do nothing");
  }
}

}  // namespace amalgam::scene_detail
