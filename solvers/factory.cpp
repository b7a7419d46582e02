#include "solvers/factory.hpp"

#include <cmath>

#include "core/errors.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_simulation.hpp"
#include "solvers/pd_simulation.hpp"

namespace amalgam {

std::vector<Collider> build_colliders(const SceneSpec& scene, const exec::Space& space) {
  std::vector<Collider> out;
  for (const ColliderSpec& spec : scene.colliders) {
    Collider c = spec;
    if (spec.mesh) {  // the rest pose's distance field, exact to 4 dx beyond the surface
      try {
        c.sdf = bake_sdf(*spec.mesh, double(scene.mpm.dx), 4.0 * double(scene.mpm.dx), space);
      } catch (const InputError& e) {
        throw InputError(spec.where + ": " + e.what());
      }
    }
    out.push_back(std::move(c));
  }
  return out;
}

namespace {
// An object that samples no particle would silently be missing from the run.
void check_sampled(const std::vector<Vec3>& x, std::size_t k, Real dx) {
  if (x.empty())
    throw InputError("/objects/" + std::to_string(k) +
                     ": samples no particles at dx = " + std::to_string(double(dx)) +
                     " (smaller than its lattice spacing?): enlarge it, lower dx or raise "
                     "particles_per_cell");
}
}  // namespace

MpmSolver build_solver(const SceneSpec& scene, const exec::Space& space) {
  MpmSolver solver(scene.mpm, scene.materials, build_colliders(scene, space), scene.heat_sources);
  for (std::size_t k = 0; k < scene.objects.size(); ++k) {
    const ObjectSpec& obj = scene.objects[k];
    Real vol = 0;
    const std::vector<Vec3> x = sample_object(obj, scene.mpm.dx, vol, space);
    check_sampled(x, k, scene.mpm.dx);
    const std::size_t first = solver.particles().size();
    solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol,
                         obj.temperature, obj.configuration);
    if (scene.mpm.domains.enabled) {
      const Real h = Real(double(scene.mpm.dx) / std::cbrt(double(obj.particles_per_cell)));
      if (obj.mesh)  // the mesh is embedded in the domains and written deformed every frame (Sec. 4.1)
        solver.enriched()->add_object(solver, first, h, &obj.mesh->vertices, &obj.mesh->triangles);
      else
        solver.enriched()->add_object(solver, first, h);
    }
  }
  return solver;
}

PdSolver build_pd_solver(const SceneSpec& scene, const exec::Space& space) {
  PdSolver solver(scene.pd, scene.pd_materials, build_colliders(scene, space));
  for (std::size_t k = 0; k < scene.objects.size(); ++k) {
    const ObjectSpec& obj = scene.objects[k];
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
    const std::vector<Vec3> x = sample_object(obj, scene.mpm.dx, vol, space);
    check_sampled(x, k, scene.mpm.dx);
    solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol);
  }
  for (const auto& b : scene.pd_boundaries) {
    if (b.load)
      solver.apply_force_density(b.min, b.max, b.force_density);
    else
      solver.prescribe_velocity(b.min, b.max, b.velocity);
  }
  for (const auto& c : scene.pd_precracks) solver.add_precrack(c.point, c.normal, c.min, c.max);
  return solver;
}

std::unique_ptr<Simulation> make_simulation(const SceneSpec& scene, const exec::Space& space) {
  if (scene.method == Method::Peridynamics) {
    PdSolver solver = build_pd_solver(scene, space);
    solver.initialize(space);
    return std::make_unique<PdSimulation>(std::move(solver), space);
  }
  return std::make_unique<MpmSimulation>(build_solver(scene, space));
}

}  // namespace amalgam
