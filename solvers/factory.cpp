#include "solvers/factory.hpp"

#include <cmath>

#include "core/dist/comm.hpp"
#include "core/errors.hpp"
#include "core/geometry/level_set_collider.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_simulation.hpp"
#include "solvers/pd_simulation.hpp"

namespace amalgam {

namespace {
// The value of `field` at x, or an InputError naming the field, the component and the position.
Vec3d field_at(const VectorField& field, const Vec3d& x) {
  const Vec3d v = field.at(x);
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(v[a]) || std::abs(v[a]) > 1e30)
      throw InputError(field.where + "/" + std::to_string(a) + ": \"" + field.c[a].text() +
                       "\" gives " + std::to_string(v[a]) + " at (" + std::to_string(x[0]) + ", " +
                       std::to_string(x[1]) + ", " + std::to_string(x[2]) + ")");
  return v;
}
}  // namespace

std::vector<Collider> build_colliders(const SceneSpec& scene, const exec::Space& space) {
  std::vector<Collider> out;
  for (const ColliderSpec& spec : scene.colliders) {
    Collider c = spec;
    // The rest pose's sparse level set of voxel dx, built as the material reaches it (exact
    // within 4 dx of the surface); .vdb files read now (frames 0 and 1 of a sequence).
    try {
      const double dx = double(scene.mpm.dx);
      if (spec.mesh) c.field = make_mesh_field(spec.mesh, dx);
      if (!spec.mesh_frames.empty())
        c.field = make_mesh_sequence_field(spec.mesh_frames, spec.frame_rate, dx);
      if (!spec.vdb_files.empty()) {
        c.field = make_vdb_field(spec.vdb_files, spec.vdb_grid, spec.frame_rate);
        c.field->prepare({}, 0, space);
      }
    } catch (const InputError& e) {
      throw InputError(spec.where + ": " + e.what());
    }
    if (spec.drive)  // a prescribed-velocity region: its field is finite at its corners at t = 0
      for (int k = 0; k < 8; ++k) {
        const Vec3 corner(k & 1 ? 1 : -1, k & 2 ? 1 : -1, k & 4 ? 1 : -1);
        field_at(*spec.drive, (spec.origin + spec.half_extent.cwiseProduct(corner)).cast<double>());
      }
    out.push_back(std::move(c));
  }
  return out;
}

namespace {
// grad f at x (column j = d f / d x_j) by central differences of step h.
Mat3 field_gradient(const VectorField& field, const Vec3d& x, double h) {
  Mat3 g;
  for (int j = 0; j < 3; ++j) {
    const Vec3d e = h * Vec3d::Unit(j);
    g.col(j) = ((field_at(field, x + e) - field_at(field, x - e)) / (2 * h)).cast<Real>();
  }
  return g;
}

// The object's velocity and displacement fields on its particles [first, end): v += f(X) (and C
// += grad f, the affine velocity APIC and MLS carry), x = X + u(X) held as x + x_lo, F = I + grad u.
void apply_fields(const ObjectSpec& obj, MpmSolver& solver, std::size_t first, double dx) {
  ParticleSet& ps = solver.particles();
  const MpmAttributes& a = solver.attributes();
  Vec3* x = ps.vec3(a.x);
  Vec3* lo = ps.vec3(a.x_lo);
  Vec3* v = ps.vec3(a.v);
  Mat3* C = a.C >= 0 ? ps.mat3(a.C) : nullptr;  // PIC/FLIP without viscosity: no C
  Mat3* F = a.F >= 0 ? ps.mat3(a.F) : nullptr;
  Real* J = a.J >= 0 ? ps.real(a.J) : nullptr;       // fluids keeping J alone: J = det F
  SymDev* b = a.b >= 0 ? ps.sym_dev(a.b) : nullptr;  // b - I instead of F (MpmSolver::keeps_b)
  const double h = 1e-3 * dx;
  for (std::size_t p = first; p < ps.size(); ++p) {
    const Vec3d X = x[p].cast<double>() + lo[p].cast<double>();
    if (obj.velocity_field) {
      v[p] += field_at(*obj.velocity_field, X).cast<Real>();
      if (C) C[p] += field_gradient(*obj.velocity_field, X, h);
    }
    if (obj.displacement_field) {
      const Vec3d y = X + field_at(*obj.displacement_field, X);
      x[p] = y.cast<Real>();
      lo[p] = (y - x[p].cast<double>()).cast<Real>();
      const Mat3 Fp = Mat3::Identity() + field_gradient(*obj.displacement_field, X, h);
      if (F) F[p] = Fp;
      if (J) J[p] = Fp.determinant();
      if (b) b[p] = b_from_F<Real>(Fp.cast<double>());
    }
  }
}

// Peridynamics: v += f(X); x = X + u(X) with the reference (x0, the bonds') left at X.
void apply_fields(const ObjectSpec& obj, PdSolver& solver, std::size_t first) {
  ParticleSet& ps = solver.particles();
  Vec3* x = ps.vec3(solver.attributes().x);
  Vec3* xlo = ps.vec3(solver.attributes().x_lo);
  const Vec3* x0 = ps.vec3(solver.attributes().x0);
  Vec3* v = ps.vec3(solver.attributes().v);
  for (std::size_t p = first; p < ps.size(); ++p) {
    const Vec3d X = x0[p].cast<double>();
    if (obj.velocity_field) v[p] += field_at(*obj.velocity_field, X).cast<Real>();
    if (obj.displacement_field) {
      const Vec3d xd = X + field_at(*obj.displacement_field, X);
      x[p] = xd.cast<Real>();
      xlo[p] = (xd - x[p].cast<double>()).cast<Real>();  // the rounding, kept (as for MPM)
    }
  }
}

// An object that samples no particle would silently be missing from the run.
void check_sampled(std::int64_t count, std::size_t k, Real dx) {
  if (count == 0)
    throw InputError("/objects/" + std::to_string(k) +
                     ": samples no particles at dx = " + std::to_string(double(dx)) +
                     " (smaller than its lattice spacing?): enlarge it, lower dx or raise "
                     "particles_per_cell");
}

// This rank's share of an object sampled in slices (one per rank): where its particles start in
// the object's order (the ranks before it) and how many the object has. Collective.
IdSlice slice_ids(std::size_t mine) {
  const dist::Comm& comm = dist::Comm::world();
  const std::vector<std::uint64_t> counts = dist::from_bytes<std::uint64_t>(
      comm.allgather(dist::as_bytes(std::vector<std::uint64_t>{mine}), nullptr));
  IdSlice ids;
  ids.total = 0;
  for (std::size_t r = 0; r < counts.size(); ++r) {
    if (int(r) < comm.rank()) ids.offset += std::int64_t(counts[r]);
    ids.total += std::int64_t(counts[r]);
  }
  return ids;
}
}  // namespace

MpmSolver build_solver(const SceneSpec& scene, const exec::Space& space) {
  MpmSolver solver(scene.mpm, scene.materials, build_colliders(scene, space), scene.heat_sources);
  // On several ranks each samples one slice of every object (its lattice planes, or its share of
  // a tet mesh's cells), so no rank holds the whole set-up; `distribute` then sends each particle
  // to the owner of its leaf. The ids are the single process's (the slices in rank order).
  // Particle domains are refused on several ranks (begin_run) and set up whole.
  const dist::Comm& comm = dist::Comm::world();
  const bool sliced = comm.size() > 1 && !scene.mpm.domains.enabled;
  LatticeSlice slice;
  if (sliced) slice.part = comm.rank(), slice.parts = comm.size();
  solver.set_sliced(sliced);
  for (std::size_t k = 0; k < scene.objects.size(); ++k) {
    const ObjectSpec& obj = scene.objects[k];
    Real vol = 0;
    std::vector<Vec3> x;
    {
      exec::ScopedRegion region(space.profiler(), "setup.sample");
      x = sample_object(obj, scene.mpm.dx, vol, space, slice);
    }
    IdSlice ids;
    if (sliced) {  // collective: includes waiting for the slowest rank's sampling
      exec::ScopedRegion region(space.profiler(), "setup.slice_ids");
      ids = slice_ids(x.size());
    }
    check_sampled(sliced ? ids.total : std::int64_t(x.size()), k, scene.mpm.dx);
    const std::size_t first = solver.particles().size();
    {
      exec::ScopedRegion region(space.profiler(), "setup.particles");
      solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol,
                           obj.temperature, obj.configuration, ids);
      apply_fields(obj, solver, first, double(scene.mpm.dx));
    }
    if (scene.mpm.domains.enabled) {
      const Real h = Real(double(scene.mpm.dx) / std::cbrt(double(obj.particles_per_cell)));
      if (obj.mesh)  // the mesh is embedded in the domains and written deformed every frame (Sec. 4.1)
        solver.enriched()->add_object(solver, first, h, &obj.mesh->vertices, &obj.mesh->triangles);
      else
        solver.enriched()->add_object(solver, first, h);
    }
  }
  std::vector<EmitterSpec> emitters = scene.emitters;
  for (EmitterSpec& e : emitters)
    if (e.mesh) {  // inside/outside from the mesh's level set at the emitter's spacing, built
      const double h = e.spacing(scene.mpm.dx);  // over the emitter's box once (it does not move)
      try {
        std::shared_ptr<ColliderField> field = make_mesh_field(e.mesh, h);
        const Vec3d pad = Vec3d::Constant(2 * h);
        field->prepare({Box3{e.min.cast<double>() - pad, e.max.cast<double>() + pad}}, 0, space);
        e.field = std::move(field);
      } catch (const InputError& err) {
        throw InputError(e.where + "/file: " + err.what());
      }
    }
  solver.set_emitters(std::move(emitters));
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
      apply_fields(obj, solver, first);
      solver.add_crack_mesh(obj.tets->nodes, obj.tets->tets, first);  // crack surfaces (Sec. 5.2)
      continue;
    }
    Real vol = 0;
    const std::vector<Vec3> x = sample_object(obj, scene.mpm.dx, vol, space);
    check_sampled(std::int64_t(x.size()), k, scene.mpm.dx);
    const std::size_t first = solver.particles().size();
    solver.add_particles(x, obj.velocity, obj.angular_velocity, obj.center, obj.material, vol);
    apply_fields(obj, solver, first);
  }
  for (const auto& b : scene.pd_boundaries) {
    if (b.load) {
      solver.apply_force_density(b.min, b.max, b.force_density);
    } else if (b.velocity_field) {
      try {
        solver.prescribe_velocity(b.min, b.max, b.velocity_field);
      } catch (const SimulationError& e) {  // its value at t = 0: an error of the scene
        throw InputError(e.what());
      }
    } else {
      solver.prescribe_velocity(b.min, b.max, b.velocity);
    }
  }
  for (const auto& c : scene.pd_precracks) solver.add_precrack(c.point, c.normal, c.min, c.max);
  return solver;
}

std::unique_ptr<Simulation> make_simulation(const SceneSpec& scene, const exec::Space& space) {
  if (scene.method == Method::Peridynamics) {
    PdSolver solver = build_pd_solver(scene, space);
    // On several ranks every rank holds every particle but builds only the bond rows it needs
    // (solvers/pd_distributed.cpp); one rank: initialize().
    solver.initialize_distributed(space);
    return std::make_unique<PdSimulation>(std::move(solver), space);
  }
  return std::make_unique<MpmSimulation>(build_solver(scene, space));
}

}  // namespace amalgam
