#include "solvers/mpm_solver.hpp"

#include <algorithm>
#include <chrono>
#include <climits>
#include <cmath>
#include <sstream>

#include "core/errors.hpp"
#include "solvers/mpm_elastic_term.hpp"

namespace amalgam {

MpmSolver::MpmSolver(const MpmSettings& settings, std::vector<MaterialParams> materials,
                     std::vector<Collider> colliders, std::vector<HeatSource> heat_sources)
    : settings_(settings),
      materials_(std::move(materials)),
      colliders_(std::move(colliders)),
      heat_sources_(std::move(heat_sources)) {
  if (!(settings_.dx > 0)) throw InputError("MPM grid spacing dx must be positive");
  if (settings_.order != 2 && settings_.order != 3)
    throw InputError("B-spline order must be 2 or 3");
  bool plastic = false, melting = false;
  for (const auto& m : materials_) {
    max_wave_speed_ = std::max(max_wave_speed_, m.wave_speed());
    max_kinematic_viscosity_ = std::max(max_kinematic_viscosity_, m.kinematic_viscosity());
    plastic |= m.has_plastic_state();
    melting |= m.melting;
    hardening_ |= m.model == MaterialModel::Snow;
    material_update_ |= m.needs_state_update();
  }
  material_update_ |= melting && !heat_sources_.empty();
  attr_ = MpmAttributes::add_to(particles_, plastic, melting);
  int sets = settings_.transfer == Transfer::PicFlip ? 2 : 1;
  if (settings_.configuration_maps) {
    cattr_ = ConfigurationAttributes::add_to(particles_);
    if (!colliders_.empty() || settings_.contact.mode != ObjectContactMode::None)
      positions_set_ = sets++;
  }
  if (settings_.domains.enabled) {
    if (settings_.configuration_maps)
      throw InputError("particle domains and configuration maps (A-ULMPM) cannot be combined");
    for (const auto& m : materials_)
      if (m.model == MaterialModel::Fluid || m.has_plastic_state() || m.viscosity > 0)
        throw InputError(
            "particle domains need elastic solid materials (fixed_corotated, neo_hookean, "
            "stvk_hencky) without viscosity (they may melt)");
    dattr_ = DomainAttributes::add_to(particles_);
    sets = 2;  // (m, p) -> (m, v) and (-, f) -> (-, dv): the PIC/FLIP layout of grid_update
  }
  grid_.set_node4_channels(sets);
}

void MpmSolver::add_particle_domains(
    std::size_t first, Real h, const std::vector<Vec3d>* surface_vertices,
    const std::vector<std::array<std::int32_t, 3>>* surface_triangles) {
  if (!settings_.domains.enabled)
    throw std::logic_error("add_particle_domains: domains are not enabled");
  domains_.add_object(particles_, dattr_, attr_.x, first, h, surface_vertices, surface_triangles);
}

void MpmSolver::save(Snapshot& s) const {
  particles_.save(s.particles);
  const Vec3* c = domains_.corner_positions();
  s.corners.assign(c, c + domains_.corner_count());
}
void MpmSolver::restore(const Snapshot& s) {
  particles_.restore(s.particles);
  std::copy(s.corners.begin(), s.corners.end(), domains_.corner_positions());
  bins_valid_ = false;
}

DomainParticleView MpmSolver::domain_particle_view() {
  DomainParticleView v{particles_.vec3(attr_.x),         particles_.vec3(attr_.v),       particles_.mat3(attr_.F),
                       particles_.real(attr_.mass),      particles_.real(attr_.volume0), particles_.int32(attr_.material),
                       particles_.int32(dattr_.corners), particles_.vec3(dattr_.h),     particles_.int32(dattr_.state),
                       particles_.size()};
  if (attr_.plastic >= 0) v.plastic = particles_.real(attr_.plastic);
  if (attr_.temperature >= 0) v.temperature = particles_.real(attr_.temperature);
  v.C = particles_.mat3(attr_.C);
  return v;
}

DomainParams MpmSolver::domain_params(Real dt) const {
  const MpmStepParams s = step_params(dt);  // the fields both methods share, posed colliders included
  DomainParams p;
  p.dx = s.dx, p.dt = s.dt, p.flip_alpha = s.flip_alpha, p.gravity = s.gravity, p.time = s.time;
  p.materials = s.materials, p.colliders = s.colliders, p.ncolliders = s.ncolliders;
  p.epsilon = settings_.domains.epsilon;
  p.enrichment = settings_.domains.enrichment;
  p.clamp = settings_.domains.clamp;
  p.elastic = time_ >= double(settings_.domains.elasticity_from);
  return p;
}

void MpmSolver::add_particles(const std::vector<Vec3>& x, const Vec3& v0, const Vec3& omega,
                              const Vec3& centre, int material, Real volume_per_particle,
                              Real temperature, const ConfigurationPolicy& policy) {
  if (material < 0 || size_t(material) >= materials_.size())
    throw InputError("material index out of range");
  if (particles_.size() + x.size() > size_t(INT32_MAX))
    throw InputError("more than 2^31 particles");
  const size_t n0 = particles_.size();
  particles_.resize(n0 + x.size());
  Vec3* px = particles_.vec3(attr_.x);
  Vec3* pv = particles_.vec3(attr_.v);
  Mat3* pC = particles_.mat3(attr_.C);
  Mat3* pF = particles_.mat3(attr_.F);
  Real* pm = particles_.real(attr_.mass);
  Real* pV = particles_.real(attr_.volume0);
  std::int32_t* pmat = particles_.int32(attr_.material);
  std::int32_t* pid = particles_.int32(attr_.id);
  Mat3 W;  // velocity gradient of the rigid rotation: v = omega x r  =>  grad v = [omega]_x
  W << 0, -omega[2], omega[1], omega[2], 0, -omega[0], -omega[1], omega[0], 0;
  const MaterialParams& mat = materials_[size_t(material)];
  const Real mass = mat.density * volume_per_particle;
  Real* pplastic = attr_.plastic >= 0 ? particles_.real(attr_.plastic) : nullptr;
  Real* ptemp = attr_.temperature >= 0 ? particles_.real(attr_.temperature) : nullptr;
  for (size_t i = 0; i < x.size(); ++i) {
    const size_t p = n0 + i;
    px[p] = x[i];
    pv[p] = v0 + omega.cross(x[i] - centre);
    pC[p] = W;
    pF[p] = Mat3::Identity();
    pm[p] = mass;
    pV[p] = volume_per_particle;
    pmat[p] = material;
    pid[p] = std::int32_t(p);
    if (pplastic) pplastic[p] = mat.initial_plastic();
    if (ptemp) ptemp[p] = temperature;
  }
  if (settings_.configuration_maps) {
    const int k = maps_.add_object(policy, x.size());
    const Vec3 offset = maps_.lane_offset(k, settings_.dx);
    Vec3* Xs = particles_.vec3(cattr_.X_s);
    Mat3* Fs = particles_.mat3(cattr_.F_s);
    Mat3* F0s = particles_.mat3(cattr_.F_0s);
    std::int32_t* obj = particles_.int32(cattr_.object);
    for (size_t p = n0; p < particles_.size(); ++p) {
      Xs[p] = px[p] + offset;
      Fs[p] = F0s[p] = Mat3::Identity();
      obj[p] = k;
    }
    bins_valid_ = false;
  }
}

MpmParticleView MpmSolver::particle_view() {
  MpmParticleView v{particles_.vec3(attr_.x),         particles_.vec3(attr_.v),
                    particles_.mat3(attr_.C),         particles_.mat3(attr_.F),
                    particles_.real(attr_.mass),      particles_.real(attr_.volume0),
                    particles_.int32(attr_.material), particles_.size()};
  if (attr_.plastic >= 0) v.plastic = particles_.real(attr_.plastic);
  if (attr_.temperature >= 0) v.temperature = particles_.real(attr_.temperature);
  if (settings_.configuration_maps) {
    v.X_ref = particles_.vec3(cattr_.X_s);
    v.F_s = particles_.mat3(cattr_.F_s);
    v.F_0s = particles_.mat3(cattr_.F_0s);
  }
  return v;
}

MpmGridView MpmSolver::grid_view() {
  if (settings_.domains.enabled)
    return make_grid_view(grid_, domains_.bins(), grid_.node4(0), grid_.node4(1));
  return make_grid_view(grid_, bins_, grid_.node4(0),
                        settings_.transfer == Transfer::PicFlip ? grid_.node4(1) : nullptr);
}

const Collider* MpmSolver::colliders_at(Real t) const {
  bool keyed = false;
  for (const auto& c : colliders_) keyed |= !c.keys.empty();
  if (!keyed) return colliders_.data();
  if (posed_colliders_.size() != colliders_.size() || posed_time_ != t) {
    posed_colliders_.clear();
    for (const auto& c : colliders_) posed_colliders_.push_back(c.posed_at(t));
    posed_time_ = t;
  }
  return posed_colliders_.data();
}

MpmStepParams MpmSolver::step_params(Real dt) const {
  MpmStepParams p;
  p.transfer = settings_.transfer;
  p.order = settings_.order;
  p.dx = settings_.dx;
  p.dt = dt;
  p.flip_alpha = settings_.flip_alpha;
  p.gravity = settings_.gravity;
  p.time = Real(time_);
  p.materials = materials_.data();
  p.colliders = colliders_at(p.time + dt);
  p.ncolliders = int(colliders_.size());
  return p;
}

void MpmSolver::sort_particles(const exec::Space& space) {
  binning_.sort_and_bin(space, particles_, settings_.configuration_maps ? cattr_.X_s : attr_.x,
                        settings_.dx, settings_.order, bins_);
}

void MpmSolver::update_configurations(const exec::Space& space) {
  const auto t0 = std::chrono::steady_clock::now();
  const bool any = maps_.decide(space, particles_, cattr_, reset_flags_);
  if (any)
    maps_.reset(space, particles_, cattr_, attr_.x, attr_.F, attr_.C, settings_.dx, reset_flags_);
  if (any || !bins_valid_) {
    sort_particles(space);
    update_grid(space);
    // Which object owns each reference leaf (for the contact), and the check that no two
    // objects share reference nodes (an object that left its lane), with or without contact.
    if (maps_.object_count() > 1)
      contact_.map_leaves(space, grid_, bins_, particles_.int32(cattr_.object));
    bins_valid_ = true;
  }
  maps_.account(reset_flags_,
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}
void MpmSolver::update_grid(const exec::Space& space) {
  grid_.update_topology(space, bins_);
}

// Lagrangian mode with colliders: MLS/APIC rasterise the node positions q_i inside the momentum
// P2G (one stencil; measured below); PIC/FLIP's 8-lane block already carries its force, so it
// keeps the separate p2g_positions pass.
bool MpmSolver::fused_positions() const {
  return positions_needed() && settings_.transfer != Transfer::PicFlip;
}
// The node positions q_i are needed for colliders and for contact between objects.
bool MpmSolver::positions_needed() const {
  return positions_set_ >= 0 && (!colliders_.empty() || contact_active());
}
bool MpmSolver::contact_active() const {
  return settings_.configuration_maps && settings_.contact.mode != ObjectContactMode::None &&
         maps_.object_count() > 1;
}

void MpmSolver::particle_to_grid(const exec::Space& space, Real dt) {
  MpmGridView g = grid_view();
  const MpmStepParams prm = step_params(dt);
  grid_clear(space, g, prm);
  if (fused_positions()) {
    g.q_out = grid_.node4(positions_set_);
    clear_node4(space, g, g.q_out);
  }
  p2g(space, particle_view(), g, prm);
}
void MpmSolver::update_grid_velocities(const exec::Space& space, Real dt) {
  MpmStepParams prm = step_params(dt);
  if (settings_.implicit)
    prm.ncolliders = 0;  // the implicit solve takes the colliders as constraints
  MpmGridView g = grid_view();
  if (positions_needed()) {  // Lagrangian: colliders act at the nodes' current positions
    if (!fused_positions())
      p2g_positions(space, particle_view(), g, prm, grid_.node4(positions_set_));
    g.q = grid_.node4(positions_set_);
  }
  grid_update(space, g, prm);
}

namespace {
// Where a node is tested against colliders: its lattice position, or in A-ULMPM its rasterised
// current position q_i (eq. 12) when the grid view carries them.
inline Vec3 node_position(const MpmGridView& g, std::size_t d, const Vec3& lattice) {
  if (!g.q) return lattice;
  const Real* q = g.q + d * 4;
  return q[0] > 0 ? Vec3(q[1] / q[0], q[2] / q[0], q[3] / q[0]) : lattice;
}
}  // namespace

MpmGridView MpmSolver::grid_view_with_positions() {
  MpmGridView g = grid_view();
  if (positions_needed()) g.q = grid_.node4(positions_set_);
  return g;
}

void MpmSolver::add_collider_constraints(const exec::Space& space, const MpmGridView& g, Real dt) {
  // Colliders -> constraints (enriched MPM Sec. 7 / Stomakhin et al. 2013, as projections): a
  // node inside a sticky collider takes its velocity; slip fixes the normal velocity; separating
  // only while v* approaches. Friction is applied after the solve from the normal velocity v*
  // had to lose. Detection in parallel, constraints added serially (few nodes).
  contacts_.clear();
  if (colliders_.empty()) return;
  const Real t_end = Real(time_) + dt, dx = settings_.dx;
  const Collider* cols = colliders_at(t_end);
  const int ncol = int(colliders_.size());
  const std::size_t ngrid = grid_.leaf_count() * std::size_t(kLeafNodes);
  in_collider_.assign(ngrid, 0);
  std::uint8_t* flag = in_collider_.data();
  const Real* mass = implicit_.mass();
  exec::parallel_for(space, "implicit.find_contacts", exec::Index(g.nactive), [&](exec::Index li) {
    const std::size_t leaf = std::size_t(g.active_leaves[li]);
    const Vec3i node0 = g.leaf_coord[leaf] * kLeafDim;
    for (int i = 0; i < kLeafDim; ++i)
      for (int j = 0; j < kLeafDim; ++j)
        for (int k = 0; k < kLeafDim; ++k) {
          const std::size_t d = leaf * kLeafNodes + std::size_t(leaf_offset(i, j, k));
          if (mass[d] <= 0) continue;
          const Vec3 xi = node_position(g, d, (node0 + Vec3i(i, j, k)).cast<Real>() * dx);
          for (int c = 0; c < ncol; ++c)
            if (cols[c].phi(xi, t_end) <= 0) flag[d] = 1;
        }
  });
  const Real* vstar = implicit_.rhs();
  for (const std::int32_t leaf : grid_.active_leaves()) {
    const Vec3i node0 = g.leaf_coord[leaf] * kLeafDim;
    for (int o = 0; o < kLeafNodes; ++o) {
      const std::size_t d = std::size_t(leaf) * kLeafNodes + std::size_t(o);
      if (!flag[d]) continue;
      const Vec3 xi =
          node_position(g, d, (node0 + Vec3i(o >> 6, (o >> 3) & 7, o & 7)).cast<Real>() * dx);
      const Vec3 vs(vstar[d * 4], vstar[d * 4 + 1], vstar[d * 4 + 2]);
      for (int c = 0; c < ncol; ++c) {
        const Collider& col = cols[c];
        if (col.phi(xi, t_end) > 0) continue;
        const Vec3 vc = col.velocity_at(xi, t_end);
        if (col.boundary == BoundaryType::Sticky) {
          implicit_.fix(d, vc);
          continue;
        }
        const Vec3 n = col.outward_normal(xi, t_end);
        const Real vn = (vs - vc).dot(n);
        if (col.boundary == BoundaryType::Separate && vn >= 0) continue;
        implicit_.constrain_normal(d, n, n.dot(vc));
        if (col.friction > 0) contacts_.push_back({d, n, vc, std::min(vn, Real(0)), col.friction});
      }
    }
  }
}

void MpmSolver::assemble_implicit(const exec::Space& space, Real dt) {
  const MpmGridView g = grid_view_with_positions();
  const std::size_t ngrid = grid_.leaf_count() * std::size_t(kLeafNodes);
  implicit_.begin(ngrid, grid_.active_leaves());
  implicit_.finalize();
  grid_velocities_to_dofs(space, g, implicit_.mass(), implicit_.rhs());
  std::copy(implicit_.rhs(), implicit_.rhs() + ngrid * 4, implicit_.solution());  // v*, guess below

  add_collider_constraints(space, g, dt);

  hessians_.resize(particles_.size());
  ImplicitKernelParams kp;
  kp.order = settings_.order;
  kp.transfer = settings_.transfer;
  kp.dx = settings_.dx;
  kp.materials = materials_.data();
  const MpmParticleView pv = particle_view();
  prepare_particle_hessians(space, pv, kp, settings_.solver.definiteness_fix, hessians_.data());
  elastic_term_ = std::make_unique<MpmElasticTerm>(pv, g, kp, hessians_.data());
  implicit_.add_term(elastic_term_.get());

  // Initial guess v* - dt M^-1 f^n (the grid velocity before the elastic force, with gravity):
  // the explicit predictor v* itself overshoots by (dt / dt_CFL)^2 wherever the body deforms,
  // so starting from it costs CG many iterations just to undo the explicit step (measured:
  // a stiff armadillo at 28x CFL, 25 -> 7-10 CG iterations per substep in free fall, 60-120 ->
  // 35-58 on the floor; docs/benchmarks.md).
  guess_force_.assign(ngrid * 4, Real(0));
  mpm_cached_elastic_forces(space, pv, g, kp, hessians_.data(), guess_force_.data());
  initial_guess_from_force(space, g, implicit_.mass(), guess_force_.data(), dt,
                           implicit_.solution());
}

// Coulomb friction at the contacts: the tangential velocity loses mu times the normal velocity
// the constraint removed (Stomakhin et al. 2013's grid collision, after the solve).
void MpmSolver::apply_friction(Real* v) const {
  for (const FrictionContact& c : contacts_) {
    Real* vd = v + c.dof * 4;
    const Vec3 vrel = Vec3(vd[0], vd[1], vd[2]) - c.vc;
    const Real vn = vrel.dot(c.n);
    Vec3 vt = vrel - vn * c.n;
    const Real vt_norm = vt.norm();
    if (vt_norm > 0) vt *= std::max(Real(0), vt_norm + c.mu * c.vn_star) / vt_norm;
    const Vec3 out = c.vc + vn * c.n + vt;
    vd[0] = out[0], vd[1] = out[1], vd[2] = out[2];
  }
}

// Solves the assembled system and adds the solve to the per-frame counters.
void MpmSolver::solve_and_count(const exec::Space& space, Real dt) {
  last_solve_ = implicit_.solve(space, dt, settings_.solver);
  ++counters_.solves;
  counters_.iterations += std::uint64_t(last_solve_.iterations);
  counters_.max_iterations = std::max(counters_.max_iterations, last_solve_.iterations);
  counters_.max_residual = std::max(counters_.max_residual, last_solve_.residual);
  counters_.minres += last_solve_.used_minres ? 1 : 0;
  counters_.unconverged += last_solve_.converged ? 0 : 1;
}

void MpmSolver::solve_grid_velocities(const exec::Space& space, Real dt) {
  assemble_implicit(space, dt);
  solve_and_count(space, dt);
  Real* v = implicit_.solution();
  apply_friction(v);
  const MpmGridView g = grid_view_with_positions();
  dofs_to_grid_velocities(space, g, v);
  // Separating nodes left free by the solve may approach a collider now: one more projection.
  grid_apply_colliders(space, g, step_params(dt));
}
void MpmSolver::couple_objects(const exec::Space& space, Real dt) {
  if (!contact_active()) return;
  const auto t0 = std::chrono::steady_clock::now();
  contact_nodes_ += contact_.apply(space, grid_view(), grid_.node4(positions_set_),
                                   settings_.contact, settings_.dx, dt);
  contact_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void MpmSolver::grid_to_particle(const exec::Space& space, Real dt) {
  g2p(space, particle_view(), grid_view(), step_params(dt));
}

void MpmSolver::update_materials(const exec::Space& space, Real dt) {
  MaterialUpdateParams prm;
  prm.materials = materials_.data();
  prm.sources = heat_sources_.data();
  prm.nsources = int(heat_sources_.size());
  prm.dt = dt;
  prm.time = Real(time_ + double(dt));
  update_material_state(space, particle_view(), prm);
}

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

void MpmSolver::solve_domain_velocities(const exec::Space& space, Real dt) {
  const MpmGridView g = grid_view();
  const std::size_t ngrid = grid_.leaf_count() * std::size_t(kLeafNodes);
  implicit_.begin(ngrid, grid_.active_leaves());
  const std::size_t base = implicit_.add_dof_set(domains_.number_enriched_dofs(space));
  implicit_.finalize();
  grid_velocities_to_dofs(space, g, implicit_.mass(), implicit_.rhs());
  domains_.enriched_to_dofs(space, implicit_.mass() + base, implicit_.rhs() + 4 * base);
  std::copy(implicit_.rhs(), implicit_.rhs() + implicit_.dof_count() * 4, implicit_.solution());
  add_collider_constraints(space, g, dt);  // grid nodes; corners meet the colliders after the solve
  domain_term_ =
      std::make_unique<DomainElasticTerm>(&domains_, domain_particle_view(), g, settings_.dx, base);
  implicit_.add_term(domain_term_.get());
  solve_and_count(space, dt);
  Real* v = implicit_.solution();
  apply_friction(v);
  dofs_to_grid_velocities(space, g, v);
  domains_.dofs_to_enriched(space, v + 4 * base);
  grid_apply_colliders(space, g, step_params(dt));
}

void MpmSolver::step_domains(const exec::Space& space, Real dt) {
  const DomainParams prm = domain_params(dt);
  const DomainParticleView pv = domain_particle_view();
  domains_.stresses_and_enrichment(space, pv, prm, settings_.implicit,
                                   settings_.solver.definiteness_fix,
                                   settings_.domains.gauss_quadrature);
  domains_.particles_to_corners(space, pv);
  domains_.corners_to_grid(space, pv, prm, grid_, settings_.dx);
  MpmStepParams sp = step_params(dt);
  sp.transfer = Transfer::PicFlip;            // the scatter's layout: (m, p) and (-, f)
  if (settings_.implicit) sp.ncolliders = 0;  // constraints of the solve
  const MpmGridView g = grid_view();
  grid_update(space, g, sp);
  domains_.update_enriched_corners(space, prm);
  if (settings_.implicit) solve_domain_velocities(space, dt);
  domains_.grid_to_corners(space, g, pv, prm);
  domains_.corners_to_particles(space, pv, prm);
  if (material_update_) {  // heat sources, melting; melted particles leave their domains (Sec. 8)
    update_materials(space, dt);
    domains_.disable_melted(space, pv, materials_.data());
  }
}

void MpmSolver::step(const exec::Space& space, Real dt) {
  if (!(dt > 0) || !std::isfinite(dt)) {
    std::ostringstream os;
    os << "step " << steps_ << ": time step must be positive and finite, got " << dt;
    throw SimulationError(os.str());
  }
  if (settings_.domains.enabled) {
    step_domains(space, dt);
    time_ += double(dt);
    ++steps_;
    return;
  }
  if (settings_.configuration_maps) {
    update_configurations(space);
  } else {
    sort_particles(space);
    update_grid(space);
  }
  particle_to_grid(space, dt);
  update_grid_velocities(space, dt);
  if (settings_.implicit) solve_grid_velocities(space, dt);
  couple_objects(space, dt);
  grid_to_particle(space, dt);
  if (!colliders_.empty()) {
    const Real t_end =
        Real(time_) + dt;  // the grid update's end-of-substep time (same posed colliders)
    collide_particles(space, particle_view(), colliders_at(t_end), int(colliders_.size()), t_end);
  }
  if (material_update_) {
    update_materials(space, dt);
    if (settings_.configuration_maps) {
      // The return mapping changed F^{0n}: keep F = F_s F_0s (eq. 32) with F_s = F (F^{0s})^{-1}.
      Mat3* F = particles_.mat3(attr_.F);
      Mat3* Fs = particles_.mat3(cattr_.F_s);
      const Mat3* F0s = particles_.mat3(cattr_.F_0s);
      exec::parallel_for(space, "aul.sync_F_s", exec::Index(particles_.size()),
                         [=](exec::Index i) { Fs[i] = F[i] * F0s[i].inverse(); });
    }
  }
  time_ += double(dt);
  ++steps_;
}

namespace {
struct SpeedCheck {
  Real max_speed = 0;
  Real max_wave = 0;     // largest particle wave speed when it depends on the plastic state
  exec::Index bad = -1;  // first particle with a non-finite v or F, or a runaway speed
  int what = 0;          // 1 velocity, 2 deformation gradient, 3 runaway speed
};
}  // namespace

Real MpmSolver::stable_dt(const exec::Space& space) const {
  const Vec3* v = particles_.vec3(attr_.v);
  const Mat3* F = particles_.mat3(attr_.F);
  const Real limit = settings_.max_speed;
  const Real* plastic = hardening_ ? particles_.real(attr_.plastic) : nullptr;
  const std::int32_t* mat = particles_.int32(attr_.material);
  const MaterialParams* mats = materials_.data();
  const SpeedCheck chk = exec::parallel_reduce(
      space, "mpm.cfl_check", exec::Index(particles_.size()), SpeedCheck{},
      [=](exec::Index i, SpeedCheck& acc) {
        const Real s = v[i].norm();
        int what = 0;
        if (!std::isfinite(s))
          what = 1;
        else if (!F[i].allFinite())
          what = 2;
        else if (s > limit)
          what = 3;
        if (what && acc.bad < 0) {
          acc.bad = i;
          acc.what = what;
        }
        if (s > acc.max_speed) acc.max_speed = s;
        if (plastic) {
          const MaterialParams& m = mats[mat[i]];
          acc.max_wave = std::max(acc.max_wave, m.wave_speed() * m.wave_speed_factor(plastic[i]));
        }
      },
      [](SpeedCheck a, const SpeedCheck& b) {
        if (a.bad < 0 && b.bad >= 0) {
          a.bad = b.bad;
          a.what = b.what;
        }
        a.max_speed = std::max(a.max_speed, b.max_speed);
        a.max_wave = std::max(a.max_wave, b.max_wave);
        return a;
      });
  if (chk.bad >= 0) {
    std::ostringstream os;
    os << "step " << steps_ << " (t = " << time_ << " s): particle " << chk.bad << " ";
    const Vec3 vb = v[chk.bad];
    if (chk.what == 1)
      os << "has a non-finite velocity (" << vb.transpose() << ")";
    else if (chk.what == 2)
      os << "has a non-finite deformation gradient F";
    else
      os << "moves at " << vb.norm() << " m/s, above the stability limit max_speed = " << limit
         << " m/s";
    os << "; the simulation blew up (reduce cfl or max_dt, or check material stiffness)";
    throw SimulationError(os.str());
  }
  // Implicit: the elastic waves are integrated stably, only the material speed limits dt (but
  // particles whose domain is disabled have explicit stresses).
  const bool explicit_stress = !settings_.implicit || (settings_.domains.enabled && domains_.disabled_count() > 0);
  const Real wave = explicit_stress ? std::max(max_wave_speed_, chk.max_wave) : Real(0);
  const Real denom = chk.max_speed + wave;
  Real dt = denom > 0 ? settings_.cfl * settings_.dx / denom : settings_.max_dt;
  // Explicit viscosity: the diffusion number nu dt / dx^2 must stay below 1/(2 d) = 1/6.
  if (max_kinematic_viscosity_ > 0)
    dt = std::min(dt, settings_.cfl * settings_.dx * settings_.dx / (3 * max_kinematic_viscosity_));
  // Explicit particle domains: enriched corners are FE nodes finer than the grid and stiffer when
  // compressed.
  if (settings_.domains.enabled && !settings_.implicit) {
    dt = std::min(
        dt, domains_.enriched_dt_limit(space, particles_.int32(dattr_.state),
                                       particles_.vec3(dattr_.h), settings_.cfl, max_wave_speed_));
  }
  return std::min(dt, settings_.max_dt);
}

std::vector<Vec3d> MpmSolver::positions_by_id() const {
  std::vector<Vec3d> out(particles_.size());
  const std::int32_t* id = particles_.int32(attr_.id);
  const Vec3* x = particles_.vec3(attr_.x);
  for (std::size_t p = 0; p < particles_.size(); ++p) out[std::size_t(id[p])] = x[p].cast<double>();
  return out;
}

MpmDiagnostics MpmSolver::diagnostics(const exec::Space& space) const {
  struct Acc {
    double ke = 0, ee = 0, m = 0, vmax = 0;
    Vec3d p = Vec3d::Zero();
  };
  const Vec3* v = particles_.vec3(attr_.v);
  const Mat3* F = particles_.mat3(attr_.F);
  const Real* m = particles_.real(attr_.mass);
  const Real* V0 = particles_.real(attr_.volume0);
  const std::int32_t* mat = particles_.int32(attr_.material);
  const MaterialParams* mats = materials_.data();
  const Real* plastic = attr_.plastic >= 0 ? particles_.real(attr_.plastic) : nullptr;
  const Real* temp = attr_.temperature >= 0 ? particles_.real(attr_.temperature) : nullptr;
  const Acc a = exec::parallel_reduce(
      space, "mpm.diagnostics", exec::Index(particles_.size()), Acc{},
      [=](exec::Index i, Acc& acc) {
        const Vec3d vi = v[i].cast<double>();
        acc.ke += 0.5 * double(m[i]) * vi.squaredNorm();
        acc.ee += double(V0[i]) * double(mats[mat[i]].energy(F[i], plastic ? plastic[i] : Real(0),
                                                             temp ? temp[i] : Real(0)));
        acc.p += double(m[i]) * vi;
        acc.m += double(m[i]);
        acc.vmax = std::max(acc.vmax, vi.norm());
      },
      [](Acc x, const Acc& y) {
        x.ke += y.ke;
        x.ee += y.ee;
        x.p += y.p;
        x.m += y.m;
        x.vmax = std::max(x.vmax, y.vmax);
        return x;
      });
  MpmDiagnostics d;
  d.kinetic = a.ke;
  d.elastic = a.ee;
  d.momentum = a.p;
  d.max_speed = a.vmax;
  d.mass = a.m;
  return d;
}

}  // namespace amalgam
