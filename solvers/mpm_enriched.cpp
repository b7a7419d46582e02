#include "solvers/mpm_enriched.hpp"

#include "solvers/mpm_implicit.hpp"
#include "solvers/mpm_solver.hpp"

namespace amalgam {

namespace {
// The elastic Hessian of the particle domains over the stacked DOFs: grid nodes, then the
// enriched corners from `corner_base` (enriched MPM eqs. 12-19).
class DomainElasticTerm final : public ImplicitTerm {
 public:
  DomainElasticTerm(ParticleDomains* d, const DomainParticleView& p, const MpmGridView& g, Real dx,
                    std::size_t corner_base)
      : d_(d), p_(p), g_(g), dx_(dx), base_(corner_base) {}
  void add_hessian_action(const exec::Space& space, const Real* du, Real scale,
                          Real* out) const override {
    d_->hessian_action(space, p_, g_, dx_, du, du + 4 * base_, scale, out, out + 4 * base_);
  }
  void add_hessian_diagonal(const exec::Space& space, Real scale, Real* diag) const override {
    d_->hessian_diagonal(space, p_, g_, dx_, scale, diag, diag + 4 * base_);
  }

 private:
  ParticleDomains* d_;
  DomainParticleView p_;
  MpmGridView g_;
  Real dx_;
  std::size_t base_;
};
}  // namespace

MpmEnriched::MpmEnriched(ParticleSet& particles) : dattr_(DomainAttributes::add_to(particles)) {}
MpmEnriched::~MpmEnriched() = default;

void MpmEnriched::add_object(MpmSolver& mpm, std::size_t first, Real h,
                             const std::vector<Vec3d>* surface_vertices,
                             const std::vector<std::array<std::int32_t, 3>>* surface_triangles) {
  domains_.add_object(mpm.particles(), dattr_, mpm.attributes().x, first, h, surface_vertices,
                      surface_triangles);
}

DomainParticleView MpmEnriched::particle_view(MpmSolver& mpm) {
  ParticleSet& ps = mpm.particles();
  const MpmAttributes& a = mpm.attributes();
  DomainParticleView v{ps.vec3(a.x),       ps.vec3(a.v),           ps.mat3(a.F),
                       ps.real(a.volume0), ps.int32(a.material),   ps.int32(dattr_.corners),
                       ps.vec3(dattr_.h),  ps.int32(dattr_.state), ps.size()};
  v.materials = mpm.materials().data();
  if (a.plastic >= 0) v.plastic = ps.real(a.plastic);
  if (a.temperature >= 0) v.temperature = ps.real(a.temperature);
  if (a.C >= 0) v.C = ps.mat3(a.C);
  v.x_lo = ps.vec3(a.x_lo);
  if (a.F_lo >= 0) v.F_lo = ps.mat3(a.F_lo);
  return v;
}

DomainParams MpmEnriched::params(const MpmSolver& mpm, Real dt) const {
  const MpmStepParams s =
      mpm.step_params(dt);  // the fields both methods share, posed colliders included
  const DomainSettings& ds = mpm.settings().domains;
  DomainParams p;
  p.dx = s.dx, p.dt = s.dt, p.flip_alpha = s.flip_alpha, p.gravity = s.gravity, p.time = s.time;
  p.materials = s.materials, p.colliders = s.colliders, p.ncolliders = s.ncolliders;
  p.epsilon = ds.epsilon;
  p.enrichment = ds.enrichment;
  p.clamp = ds.clamp;
  p.elastic = mpm.time() >= double(ds.elasticity_from);
  return p;
}

Real MpmEnriched::dt_limit(const exec::Space& space, const MpmSolver& mpm) const {
  const ParticleSet& ps = mpm.particles();
  return domains_.enriched_dt_limit(space, ps.int32(dattr_.state), ps.vec3(dattr_.h),
                                    mpm.settings().cfl, mpm.max_wave_speed_);
}

void MpmEnriched::solve_velocities(const exec::Space& space, MpmSolver& mpm, Real dt) {
  MpmImplicit& imp = *mpm.implicit();
  ImplicitSystem& sys = imp.system();
  const MpmGridView g = mpm.grid_view();
  const std::size_t ngrid = mpm.grid().leaf_count() * std::size_t(kLeafNodes);
  sys.begin(ngrid, mpm.grid().active_leaves());
  const std::size_t base = sys.add_dof_set(domains_.number_enriched_dofs(space));
  sys.finalize();
  grid_velocities_to_dofs(space, g, sys.mass(), sys.rhs());
  domains_.enriched_to_dofs(space, sys.mass() + base, sys.rhs() + 4 * base);
  std::copy(sys.rhs(), sys.rhs() + sys.dof_count() * 4, sys.solution());
  imp.add_collider_constraints(space, mpm, g,
                               dt);  // grid nodes; corners meet the colliders after the solve
  term_ = std::make_unique<DomainElasticTerm>(&domains_, particle_view(mpm), g, mpm.settings().dx,
                                              base);
  sys.add_term(term_.get());
  imp.solve_and_count(space, dt);
  Real* v = sys.solution();
  imp.apply_friction(v);
  dofs_to_grid_velocities(space, g, v);
  domains_.dofs_to_enriched(space, v + 4 * base);
  grid_apply_colliders(space, g, mpm.step_params(dt));
}

void MpmEnriched::step(const exec::Space& space, MpmSolver& mpm, Real dt) {
  const bool implicit = mpm.implicit() != nullptr;
  const DomainSettings& ds = mpm.settings().domains;
  const DomainParams prm = params(mpm, dt);
  const DomainParticleView pv = particle_view(mpm);
  domains_.stresses_and_enrichment(space, pv, prm, implicit, mpm.settings().solver.definiteness_fix,
                                   ds.gauss_quadrature);
  domains_.particles_to_corners(space, pv);
  domains_.corners_to_grid(space, pv, prm, mpm.grid_, mpm.settings().dx);
  MpmStepParams sp = mpm.step_params(dt);
  sp.transfer = Transfer::PicFlip;  // the scatter's layout: (m, p) and (-, f)
  if (implicit) sp.ncolliders = 0;  // constraints of the solve
  const MpmGridView g = mpm.grid_view();
  grid_update(space, g, sp);
  domains_.update_enriched_corners(space, prm);
  if (implicit) solve_velocities(space, mpm, dt);
  domains_.grid_to_corners(space, g, pv, prm);
  domains_.corners_to_particles(space, pv, prm);
  if (mpm.has_material_update()) {  // heat sources, melting; melted particles leave their domains (Sec. 8)
    mpm.update_materials(space, dt);
    domains_.disable_melted(space, pv, mpm.materials().data());
  }
}

}  // namespace amalgam
