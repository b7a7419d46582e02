// Scene files, the peridynamics part: peridynamic materials, /simulation/peridynamics, the
// lattice spacing and horizon from the objects, boundary conditions and pre-cracks. Other
// methods' keys are rejected.
#include <cmath>
#include <string>

#include "core/errors.hpp"
#include "io/scene_parts.hpp"

namespace amalgam::scene_detail {

namespace {

// Peridynamic material (model "peridynamic"): elastic constants as bulk/shear modulus or
// Young's modulus/Poisson ratio; plasticity by yield_stress (or the paper's psi0) and
// plastic_cap; fracture by critical_stretch and damage_alpha (eq. 18); anisotropy (eq. 16) as
// G = I + (ratio - 1) n n^T for a unit axis n.
PdMaterial read_pd_material(JsonObject o, Real horizon) {
  PdMaterial m;
  o.choice("model", "", {"peridynamic"});
  m.density = Real(o.required_number("density", 0, kHuge, true));
  if (o.has("bulk_modulus") || o.has("shear_modulus")) {
    if (o.has("youngs_modulus"))
      o.fail("youngs_modulus",
             "give either youngs_modulus/poisson_ratio or bulk_modulus/shear_modulus");
    if (o.has("poisson_ratio"))
      o.fail("poisson_ratio",
             "give either youngs_modulus/poisson_ratio or bulk_modulus/shear_modulus");
    m.bulk = Real(o.required_number("bulk_modulus", 0, kHuge, true));
    m.shear = Real(o.required_number("shear_modulus", 0, kHuge, true));
  } else {
    const double E = o.required_number("youngs_modulus", 0, kHuge, true);
    const double nu = o.number("poisson_ratio", 0.25, -0.999, 0.499);
    m.bulk = Real(E / (3 * (1 - 2 * nu)));
    m.shear = Real(E / (2 * (1 + nu)));
  }
  if (o.has("yield_stress") && o.has("psi0"))
    o.fail("psi0", "give either yield_stress or psi0, not both");
  if (o.has("yield_stress"))
    m.psi0 =
        pd_psi0_from_yield_stress(Real(o.required_number("yield_stress", 0, kHuge, true)), horizon);
  if (o.has("psi0")) m.psi0 = Real(o.required_number("psi0", 0, 1e38, true));
  const bool plastic = o.has("yield_stress") || o.has("psi0");
  if (o.has("plastic_cap") && !plastic)
    o.fail("plastic_cap", "needs yield_stress or psi0 (the material is elastic)");
  if (o.has("plastic_cap")) m.plastic_cap = Real(o.required_number("plastic_cap", 0, kHuge, true));
  if (o.has("critical_stretch"))
    m.critical_stretch = Real(o.required_number("critical_stretch", 0, kHuge, true));
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

}  // namespace

void read_pd_simulation(JsonObject& sim, Scene& s) {
  for (const char* k : {"transfer", "order", "flip_alpha", "integrator", "implicit"})
    if (sim.has(k)) sim.fail(k, "only for \"method\": \"mpm\"");
  if (sim.has("contact"))
    sim.fail("contact",
             "only for \"method\": \"mpm\" (peridynamics sets its contact in \"peridynamics\")");
  if (sim.has("domains")) sim.fail("domains", "only for \"method\": \"mpm\"");
  {
    JsonObject p = sim.object("peridynamics");
    const double factor = p.number("horizon_factor", 3.015, 1, 8, true);
    // "model": "paper" (Chen et al. 2018, corrected) or "lps" (Silling et al. 2007, as LAMMPS
    // peri/lps: its own normaliser per particle, LPS deviatoric extension, no fitted correction).
    s.pd.model =
        p.choice("model", "paper", {"paper", "lps"}) == "paper" ? PdModel::Paper : PdModel::Lps;
    const bool lps = s.pd.model == PdModel::Lps;
    if (lps && p.has("deviatoric") && p.string("deviatoric", "lps") != "lps")
      p.fail("deviatoric", "the \"lps\" model uses the LPS deviatoric extension (omit the key)");
    s.pd.deviatoric = p.choice("deviatoric", lps ? "lps" : "paper", {"paper", "lps"}) == "paper"
                          ? PdDeviatoric::Paper
                          : PdDeviatoric::Lps;
    if (lps && p.has("surface_correction") && p.boolean("surface_correction", false))
      p.fail("surface_correction",
             "the \"lps\" model normalises each particle by its own family (m_i); the fitted "
             "correction belongs to \"model\": \"paper\"");
    s.pd.surface_correction = p.boolean("surface_correction", !lps);
    s.pd.partial_volume = p.boolean("partial_volume", true);
    // "fracture": true / false, or {"enabled": true, "criterion": "paper" | "classical"}
    if (p.has_object("fracture")) {
      JsonObject f = p.object("fracture");
      s.pd.fracture = f.boolean("enabled", true);
      s.pd.criterion = f.choice("criterion", "paper", {"paper", "classical"}) == "paper"
                           ? PdCriterion::Paper
                           : PdCriterion::Classical;
      f.finish();
    } else {
      s.pd.fracture = p.boolean("fracture", true);
    }
    s.pd.contact = p.boolean("contact", true);
    const double contact = p.number("contact_distance", 0.9, 0, 3, true);
    s.pd.damping = Real(p.number("damping", 0, 0, 1e12));
    s.pd.compact_fraction = Real(p.number("compact_fraction", 0.1, 0, 1));
    p.finish();
    s.pd.horizon = Real(factor);  // times the spacing, set once the objects are known
    s.pd.contact_distance = Real(contact);
  }
}

void pd_spacing(JsonObject& top, Scene& s) {
  std::size_t tet_objects = 0;
  double edge_sum = 0, edge_count = 0;
  for (const auto& o : s.objects)
    if (o.shape == ObjectShape::TetMesh) {
      ++tet_objects;
      edge_sum += tet_mean_edge(*o.tets) * double(o.tets->tets.size());
      edge_count += double(o.tets->tets.size());
    }
  if (tet_objects > 0 && tet_objects < s.objects.size())
    top.fail(
        "objects",
        "tet_mesh objects cannot be mixed with lattice-sampled objects (their spacings differ)");
  if (tet_objects > 0) {
    // One particle per tetrahedron: the spacing is the mean edge length (the paper's lambda).
    s.pd.spacing = Real(edge_sum / edge_count);
  } else {
    const int ppc = s.objects[0].particles_per_cell;
    for (std::size_t k = 1; k < s.objects.size(); ++k)
      if (s.objects[k].particles_per_cell != ppc)
        throw InputError(
            s.file + ": /objects/" + std::to_string(k) +
            "/particles_per_cell: peridynamic objects share one lattice spacing; use the same value as "
            "/objects/0 (" +
            std::to_string(ppc) + ")");
    s.pd.spacing = Real(double(s.mpm.dx) / std::cbrt(double(ppc)));
  }
  s.pd.horizon *= s.pd.spacing;
  s.pd.contact_distance *= s.pd.spacing;
  s.pd.gravity = s.mpm.gravity;
  s.pd.cfl = s.mpm.cfl;
  s.pd.max_dt = s.mpm.max_dt;
  s.pd.max_speed = s.mpm.max_speed;
}

void read_pd_materials(JsonObject& mats, Scene& s) {
  for (const auto& name : s.material_names) {
    JsonObject mo = mats.object(name);
    if (!(mo.has("model") && mo.string("model", "") == "peridynamic"))
      mo.fail("model", "a peridynamics scene needs \"model\": \"peridynamic\"");
    s.pd_materials.push_back(read_pd_material(mats.object(name), s.pd.horizon));
    MaterialParams mp;  // density only: what the shared diagnostics and previews read
    mp.density = s.pd_materials.back().density;
    s.materials.push_back(mp);
  }
}

void read_pd_conditions(JsonObject& top, Scene& s) {
  if (!top.objects("heat_sources").empty())
    top.fail("heat_sources", "only for \"method\": \"mpm\"");
  for (auto& b : top.objects("boundary_conditions")) {
    PdBoundarySpec bc;
    bc.min = b.required_vec3("min");
    bc.max = b.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(bc.max[a] >= bc.min[a]))
        b.fail("max", "every component must be at least the matching one of \"min\"");
    if (b.has("velocity") && b.has("force_density"))
      b.fail("force_density",
             "give either velocity (prescribed motion) or force_density (a load), not both");
    if (b.has_expressions("velocity"))
      bc.velocity_field = b.vector_field("velocity", true);
    else
      bc.velocity = b.vec3("velocity", Vec3::Zero());
    bc.load = b.has("force_density");
    bc.force_density = b.vec3("force_density", Vec3::Zero());
    b.finish();
    s.pd_boundaries.push_back(bc);
  }
  for (auto& c : top.objects("precracks")) {
    PdPrecrackSpec pc;
    pc.point = c.required_vec3("point");
    pc.normal = c.required_vec3("normal");
    if (!(pc.normal.norm() > 0)) c.fail("normal", "must be a non-zero vector");
    pc.min = c.required_vec3("min");
    pc.max = c.required_vec3("max");
    for (int a = 0; a < 3; ++a)
      if (!(pc.max[a] >= pc.min[a]))
        c.fail("max", "every component must be at least the matching one of \"min\"");
    c.finish();
    s.pd_precracks.push_back(pc);
  }
}

}  // namespace amalgam::scene_detail
