#include "solvers/mpm_solver.hpp"

#include <algorithm>
#include <climits>
#include <cmath>
#include <limits>
#include <sstream>

#include "core/dist/comm.hpp"
#include "core/errors.hpp"
#include "core/geometry/level_set_collider.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

namespace amalgam {

bool fuses(const MpmSettings& s, bool distributed) {
  return s.fused && !s.implicit && !s.configuration_maps && !s.domains.enabled &&
         !s.sleep.enabled && !distributed;
}

bool sorts_when_needed(const MpmSettings& s) {
  MpmSettings f = s;
  f.fused = true;
  return s.sort_when_needed && !s.fused && fuses(f, false);
}

GridChannels GridChannels::for_run(const MpmSettings& s, bool has_colliders, bool distributed) {
  GridChannels c;
  // The fused substep's split grid keeps the force in set 1 for every transfer; a run that asks
  // for it but falls back to the two passes does not need it.
  const bool split = fuses(s, distributed);
  if (s.transfer == Transfer::PicFlip || s.domains.enabled || split) c.second = c.count++;
  if (s.configuration_maps && (has_colliders || s.contact.mode != ObjectContactMode::None))
    c.positions = c.count++;
  return c;
}

bool MpmSolver::keeps_affine(const MpmSettings& s, const std::vector<MaterialParams>& materials) {
  if (s.transfer != Transfer::PicFlip && !s.domains.enabled) return true;
  for (const MaterialParams& m : materials)
    if (m.reads_velocity_gradient()) return true;
  return false;
}

bool MpmSolver::keeps_F_low_part(const std::vector<MaterialParams>& materials) {
  for (const MaterialParams& m : materials)
    if (m.model != MaterialModel::Fluid) return true;
  return materials.empty();
}

bool MpmSolver::keeps_J_only(const MpmSettings& s, const std::vector<MaterialParams>& materials) {
  if (materials.empty() || s.implicit || s.configuration_maps || s.domains.enabled) return false;
  for (const MaterialParams& m : materials)
    if (m.model != MaterialModel::Fluid || m.melting) return false;
  return true;
}

bool MpmSolver::keeps_b(const MpmSettings& s, const std::vector<MaterialParams>& materials) {
  return !s.implicit && !s.configuration_maps && !s.domains.enabled && !s.keep_F &&
         !keeps_J_only(s, materials);
}

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
  const bool J_only = keeps_J_only(settings_, materials_);
  if (J_only) material_update_ = false;  // the update was the fluid's F reset: nothing to do on J
  attr_ =
      MpmAttributes::add_to(particles_, plastic, melting, keeps_affine(settings_, materials_),
                            keeps_F_low_part(materials_), J_only, keeps_b(settings_, materials_));
  if (settings_.domains.enabled) {
    if (settings_.configuration_maps)
      throw InputError("particle domains and configuration maps (A-ULMPM) cannot be combined");
    for (const auto& m : materials_)
      if (m.model == MaterialModel::Fluid || m.has_plastic_state() || m.viscosity > 0)
        throw InputError(
            "particle domains need elastic solid materials (fixed_corotated, neo_hookean, "
            "stvk_hencky) without viscosity (they may melt)");
  }
  if (settings_.kill.enabled() && (settings_.configuration_maps || settings_.domains.enabled))
    throw InputError("kill regions need plain MPM (not A-ULMPM objects nor particle domains)");
  if (settings_.sleep.enabled) {
    if (settings_.configuration_maps || settings_.domains.enabled || settings_.implicit ||
        settings_.transfer == Transfer::PicFlip)
      throw InputError(
          "sleeping needs explicit MLS or APIC MPM (not implicit, PIC/FLIP, A-ULMPM "
          "objects nor particle domains)");
    sleep_ = std::make_unique<MpmSleep>(particles_, settings_.sleep);
  }
  if (settings_.configuration_maps) aul_ = std::make_unique<MpmAul>(particles_, settings_.contact);
  if (settings_.domains.enabled) enriched_ = std::make_unique<MpmEnriched>(particles_);
  if (settings_.implicit) implicit_ = std::make_unique<MpmImplicit>(settings_.solver);
  channels_ = GridChannels::for_run(settings_, !colliders_.empty());
  grid_.set_node4_channels(channels_.count);
}

MpmSolver::~MpmSolver() = default;
MpmSolver::MpmSolver(MpmSolver&&) noexcept = default;
MpmSolver& MpmSolver::operator=(MpmSolver&&) noexcept = default;

void MpmSolver::save(Snapshot& s) const {
  particles_.save(s.particles);
  s.next_id = next_id_;
  s.sources = sources_;
  s.corners.clear();
  if (enriched_) {
    const Vec3* c = enriched_->domains().corner_positions();
    s.corners.assign(c, c + enriched_->domains().corner_count());
  }
  if (ranks_) save_distributed(s);
}
void MpmSolver::restore(const Snapshot& s) {
  particles_.restore(s.particles);
  next_id_ = s.next_id;
  sources_ = s.sources;
  if (enriched_)
    std::copy(s.corners.begin(), s.corners.end(), enriched_->domains().corner_positions());
  if (aul_) aul_->invalidate_bins();
  if (ranks_) restore_distributed(s);
  ++state_version_;
  primed_ = false;
}
void MpmSolver::restore_clock(double time, std::uint64_t steps) {
  time_ = time;
  steps_ = steps;
  ++state_version_;
  primed_ = false;
  if (aul_)
    aul_->invalidate_bins();  // particles may have been replaced: re-bin before the next transfer
}

void MpmSolver::keep_rest_positions() {
  if (attr_.rest >= 0) return;
  attr_.rest = particles_.add("rest", AttrType::Real, 3);
  const Vec3* x = particles_.vec3(attr_.x);
  std::copy(x, x + particles_.size(), particles_.vec3(attr_.rest));
}

void MpmSolver::add_particles(const std::vector<Vec3>& x, const Vec3& v0, const Vec3& omega,
                              const Vec3& centre, int material, Real volume_per_particle,
                              Real temperature, const ConfigurationPolicy& policy,
                              const IdSlice& ids) {
  if (material < 0 || size_t(material) >= materials_.size())
    throw InputError("material index out of range");
  const std::int64_t total = ids.total < 0 ? std::int64_t(x.size()) : ids.total;
  if (next_id_ + total > std::int64_t(INT32_MAX)) throw InputError("more than 2^31 particle ids");
  const size_t n0 = particles_.size();
  particles_.resize(n0 + x.size());
  Vec3* px = particles_.vec3(attr_.x);
  Vec3* pv = particles_.vec3(attr_.v);
  Mat3* pC = attr_.C >= 0 ? particles_.mat3(attr_.C) : nullptr;
  Mat3* pF = attr_.F >= 0 ? particles_.mat3(attr_.F) : nullptr;
  Real* pJ = attr_.J >= 0 ? particles_.real(attr_.J) : nullptr;
  Real* pV = particles_.real(attr_.volume0);
  std::int32_t* pmat = particles_.int32(attr_.material);
  std::int32_t* pid = particles_.int32(attr_.id);
  Mat3 W;  // velocity gradient of the rigid rotation: v = omega x r  =>  grad v = [omega]_x
  W << 0, -omega[2], omega[1], omega[2], 0, -omega[0], -omega[1], omega[0], 0;
  const MaterialParams& mat = materials_[size_t(material)];
  Real* pplastic = attr_.plastic >= 0 ? particles_.real(attr_.plastic) : nullptr;
  Real* ptemp = attr_.temperature >= 0 ? particles_.real(attr_.temperature) : nullptr;
  Vec3* prest = attr_.rest >= 0 ? particles_.vec3(attr_.rest) : nullptr;
  for (size_t i = 0; i < x.size(); ++i) {
    const size_t p = n0 + i;
    px[p] = x[i];
    pv[p] = v0 + omega.cross(x[i] - centre);
    if (pC) pC[p] = W;
    if (pF) pF[p] = Mat3::Identity();
    if (pJ) pJ[p] = 1;
    pV[p] = volume_per_particle;
    pmat[p] = material;
    pid[p] = std::int32_t(next_id_ + ids.offset + std::int64_t(i));
    if (pplastic) pplastic[p] = mat.initial_plastic();
    if (ptemp) ptemp[p] = temperature;
    if (prest) prest[p] = x[i];
  }
  next_id_ += total;
  primed_ = false;  // the fused grid holds the particles it was scattered from
  if (aul_)
    aul_->add_object(particles_, px, n0, x.size(), std::size_t(total), policy, settings_.dx);
}

void MpmSolver::set_emitters(std::vector<EmitterSpec> emitters) {
  for (const EmitterSpec& e : emitters) {
    if (aul_ || enriched_)
      throw InputError(e.where +
                       ": emitters need plain MPM (not A-ULMPM objects nor particle "
                       "domains)");
    if (e.material < 0 || size_t(e.material) >= materials_.size())
      throw InputError(e.where + ": material index out of range");
  }
  emitters_ = std::move(emitters);
}

void MpmSolver::restore_sources(std::int64_t next_id, const SourceCounters& c) {
  next_id_ = next_id;
  sources_ = c;
}

void MpmSolver::emit_and_kill(const exec::Space& space, double t0, double t1) {
  const std::size_t before = particles_.size();
  for (const EmitterSpec& e : emitters_) {
    emitted_x_.clear();
    e.emit(settings_.dx, t0, t1, emitted_x_);
    if (emitted_x_.empty()) continue;
    const Real h = Real(e.spacing(settings_.dx));
    add_particles(emitted_x_, e.velocity, Vec3::Zero(), Vec3::Zero(), e.material, h * h * h,
                  e.temperature);
    sources_.emitted += std::int64_t(emitted_x_.size());
    folded_at_ = kNotFolded;  // new particles: stable_dt checks them all
  }
  // Distributed: every rank emits alike (same ids) and keeps what falls in its own leaves.
  if (ranks_ && particles_.size() > before) keep_owned_emitted(space, before);
  if (!settings_.kill.enabled()) return;
  const std::size_t n = particles_.size();
  keep_.resize(n);
  mark_survivors(space, settings_.kill, particles_.vec3(attr_.x), n, keep_.data());
  kept_.clear();
  for (std::size_t p = 0; p < n; ++p)
    if (keep_[p]) kept_.push_back(std::uint32_t(p));
  // Distributed: the count removed on all ranks (every rank's counters stay the same).
  const std::uint64_t killed = ranks_ ? dist::Comm::world().sum(std::uint64_t(n - kept_.size()))
                                      : std::uint64_t(n - kept_.size());
  if (kept_.size() == n && killed == 0) return;
  sources_.killed += std::int64_t(killed);
  if (kept_.size() == n) return;
  primed_ = false;
  folded_at_ = kNotFolded;  // the particles' indices change
  particles_.compact(space, kept_.data(), kept_.size());
  if (ranks_) compact_bins(kept_);
}

MpmParticleView MpmSolver::particle_view() {
  MpmParticleView v{particles_.vec3(attr_.x),
                    particles_.vec3(attr_.v),
                    attr_.C >= 0 ? particles_.mat3(attr_.C) : nullptr,
                    attr_.F >= 0 ? particles_.mat3(attr_.F) : nullptr,
                    particles_.real(attr_.volume0),
                    particles_.int32(attr_.material),
                    particles_.size()};
  v.x_lo = particles_.vec3(attr_.x_lo);
  if (attr_.F_lo >= 0) v.F_lo = particles_.mat3(attr_.F_lo);
  if (attr_.J >= 0) v.J = particles_.real(attr_.J);
  if (attr_.b >= 0) v.b = particles_.sym_dev(attr_.b);
  if (attr_.plastic >= 0) v.plastic = particles_.real(attr_.plastic);
  if (attr_.temperature >= 0) v.temperature = particles_.real(attr_.temperature);
  if (aul_) aul_->fill_view(v, particles_);
  return v;
}

MpmGridView MpmSolver::grid_view() {
  Real* second = channels_.second >= 0 ? grid_.node4(channels_.second) : nullptr;
  MpmGridView g = make_grid_view(grid_, enriched_ ? enriched_->domains().bins() : bins_,
                                 grid_.node4(0), second);
  if (sleep_) g.bin_end = sleep_->bin_end();
  // The fused substep's 27 leaves per bin, while they are the current bins' (update_grid_fused).
  if (!enriched_ && fused_nbr27_.size() == bins_.count() && !fused_nbr27_.empty())
    g.bin_nbr27 = fused_nbr27_.data();
  return g;
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
  if (ranks_) return sort_distributed(space);
  // Particles in (leaf, id) order, independent of their previous order, so that the ranks of a
  // distributed run, each sorting the particles of its own leaves, put every bin's particles in
  // the single process's order (the P2G sums of a node then add the same values in the same
  // order; docs/architecture.md, "Distributed runs"). A-ULMPM bins at the reference positions.
  binning_.sort_and_bin(space, particles_, bin_position(), settings_.dx, settings_.order, bins_,
                        attr_.id);
}

ParticleSet::Id MpmSolver::bin_position() const {
  return aul_ ? aul_->attributes().X_s : attr_.x;
}

void MpmSolver::update_grid(const exec::Space& space) {
  if (ranks_) return update_grid_distributed(space);
  grid_.update_topology(space, bins_);
  if (sleep_)
    sleep_->decide(space, particles_, attr_, bins_, settings_.dx, time_, colliders_at(Real(time_)),
                   int(colliders_.size()), emitters_);
}

// Lagrangian mode with colliders: MLS/APIC rasterise the node positions q_i inside the momentum
// P2G (one stencil; measured below); PIC/FLIP's 8-lane block already carries its force, so it
// keeps the separate p2g_positions pass.
bool MpmSolver::fused_positions() const {
  return positions_needed() && settings_.transfer != Transfer::PicFlip;
}
// The node positions q_i are needed for colliders and for contact between objects.
bool MpmSolver::positions_needed() const {
  return channels_.positions >= 0 && (!colliders_.empty() || (aul_ && aul_->contact_active()));
}

void MpmSolver::particle_to_grid(const exec::Space& space, Real dt) {
  if (ranks_) return particle_to_grid_distributed(space, dt);
  MpmGridView g = grid_view();
  const MpmStepParams prm = step_params(dt);
  grid_clear(space, g, prm);
  if (fused_positions()) {
    g.q_out = grid_.node4(channels_.positions);
    clear_node4(space, g, g.q_out);
  }
  g.blocks = p2g_blocks_for(g.nbins, g.q_out != nullptr);
  p2g(space, particle_view(), g, prm);
}

// Room for every bin's P2G block (the colour phases' sums without their barriers), or null (the
// colour phases) when it would exceed the budget: a sparse scene of many near-empty bins would
// otherwise hold a (8 + order)^3-node block per handful of particles.
Real* MpmSolver::p2g_blocks_for(std::size_t nbins, bool fused) {
  const std::size_t reals =
      nbins * p2g_block_reals(settings_.order, p2g_channels(settings_.transfer, fused));
  const std::size_t budget = p2g_blocks_budget(particles_.size());
  if (reals * sizeof(Real) > budget) {
    std::vector<Real>().swap(p2g_blocks_);
    return nullptr;
  }
  if (p2g_blocks_.size() < reals) p2g_blocks_.resize(reals);
  return p2g_blocks_.data();
}
void MpmSolver::update_grid_velocities(const exec::Space& space, Real dt) {
  if (ranks_) return update_grid_velocities_distributed(space, dt);
  MpmStepParams prm = step_params(dt);
  if (implicit_) prm.ncolliders = 0;  // the implicit solve takes the colliders as constraints
  MpmGridView g = grid_view();
  if (positions_needed()) {  // Lagrangian: colliders act at the nodes' current positions
    if (!fused_positions())
      p2g_positions(space, particle_view(), g, prm, grid_.node4(channels_.positions));
    g.q = grid_.node4(channels_.positions);
  }
  grid_update(space, g, prm);
  if (sleep_) sleep_->pin_nodes(space, grid_, bins_, grid_.node4(0));
}

MpmGridView MpmSolver::grid_view_with_positions() {
  MpmGridView g = grid_view();
  if (positions_needed()) g.q = grid_.node4(channels_.positions);
  return g;
}

void MpmSolver::grid_to_particle(const exec::Space& space, Real dt) {
  if (ranks_) return grid_to_particle_distributed(space, dt);
  g2p(space, particle_view(), grid_view(), step_params(dt));
  if (sleep_) sleep_->rest(space, particles_, attr_, dt);
}

void MpmSolver::collide_particles(const exec::Space& space, Real dt) {
  if (colliders_.empty()) return;
  const Real t_end =
      Real(time_) + dt;  // the grid update's end-of-substep time (same posed colliders)
  amalgam::collide_particles(space, particle_view(), colliders_at(t_end), int(colliders_.size()),
                             t_end);
}

MaterialUpdateParams MpmSolver::material_params(Real dt) const {
  MaterialUpdateParams prm;
  prm.materials = materials_.data();
  prm.sources = heat_sources_.data();
  prm.nsources = int(heat_sources_.size());
  prm.dt = dt;
  prm.time = Real(time_ + double(dt));
  return prm;
}

void MpmSolver::update_materials(const exec::Space& space, Real dt) {
  update_material_state(space, particle_view(), material_params(dt));
}

bool MpmSolver::folds_check() const {
  return !ranks_ && !aul_ && !enriched_ && !sleep_;
}

StabilityLimits MpmSolver::check_limits() const {
  StabilityLimits lim;
  lim.max_speed = settings_.max_speed;
  if (hardening_) {
    lim.materials = materials_.data();
    lim.material = particles_.int32(attr_.material);
    lim.plastic = particles_.real(attr_.plastic);
  }
  return lim;
}

MpmStepParams MpmSolver::g2p_params(MpmStepParams prm) {
  if (!folds_check()) return prm;
  prm.collide = true;
  if (!material_update_) {
    prm.check = &folded_;
    prm.check_limits = check_limits();
    fold_pending_ = true;
  }
  return prm;
}

void MpmSolver::after_g2p(const exec::Space& space, Real dt) {
  if (!folds_check()) {
    collide_particles(space, dt);
    if (material_update_) update_materials(space, dt);
    return;
  }
  if (!material_update_) return;  // G2P ran the collisions and the check
  MaterialUpdateParams mu = material_params(dt);
  mu.check = &folded_;
  mu.check_limits = check_limits();
  update_material_state(space, particle_view(), mu);
  fold_pending_ = true;
}

void MpmSolver::step(const exec::Space& space, Real dt) {
  if (!(dt > 0) || !std::isfinite(dt)) {
    std::ostringstream os;
    os << "step " << steps_ << ": time step must be positive and finite, got " << dt;
    throw SimulationError(os.str());
  }
  // Field colliders (meshes, level sets) built around the material for this substep's end time,
  // where every kernel queries them (core/geometry/level_set_collider.hpp).
  if (ranks_)
    prepare_colliders_distributed(space, Real(time_) + dt);
  else
    prepare_colliders(colliders_, particles_.vec3(attr_.x), particles_.size(), settings_.dx,
                      Real(time_) + dt, space);
  fold_pending_ = false;
  if (enriched_) {
    enriched_->step(space, *this, dt);  // particle domains: their own substep (Algorithm 1)
  } else if (fused_eligible()) {
    step_fused(space, dt);  // one pass over the particles (solvers/mpm_fused.cpp)
  } else if (sort_when_needed_eligible()) {
    step_sorted_when_needed(space, dt);  // the two passes, re-sorted only when needed (same file)
  } else {
    if (aul_)
      aul_->update_configurations(space, *this);  // eq. 33; re-bins only when a reference changed
    else {
      sort_particles(space);
      update_grid(space);
    }
    particle_to_grid(space, dt);
    update_grid_velocities(space, dt);
    if (implicit_) implicit_->solve_grid_velocities(space, *this, dt);
    if (aul_) aul_->couple_objects(space, *this, dt);
    if (folds_check()) {  // the collisions and the stability check in the last particle pass
      g2p(space, particle_view(), grid_view(), g2p_params(step_params(dt)));
      after_g2p(space, dt);
    } else {
      grid_to_particle(space, dt);
      collide_particles(space, dt);
      if (material_update_) {
        update_materials(space, dt);
        if (aul_) aul_->keep_split(space, particles_, attr_.F);
      }
    }
  }
  const double t0 = time_;
  time_ += double(dt);
  ++steps_;
  ++state_version_;
  folded_at_ = fold_pending_ ? state_version_ : kNotFolded;
  if (!emitters_.empty() || settings_.kill.enabled()) emit_and_kill(space, t0, time_);
}

Real MpmSolver::stable_dt(const exec::Space& space) const {
  const Vec3* v = particles_.vec3(attr_.v);
  const Mat3* F = attr_.F >= 0 ? particles_.mat3(attr_.F) : nullptr;
  const Real* J = attr_.J >= 0 ? particles_.real(attr_.J) : nullptr;
  const SymDev* b = attr_.b >= 0 ? particles_.sym_dev(attr_.b) : nullptr;
  const Real limit = settings_.max_speed;
  StabilityCheck chk = folded_;
  if (folded_at_ != state_version_) {  // not folded into the last particle pass: a pass of its own
    const StabilityLimits lim = check_limits();
    chk = exec::parallel_reduce(
        space, "mpm.cfl_check", exec::Index(particles_.size()), StabilityCheck{},
        [=](exec::Index i, StabilityCheck& acc) {
          if (J)
            check_particle(acc, i, v[i], J[i], lim);
          else if (b)
            check_particle(acc, i, v[i], b[i], lim);
          else
            check_particle(acc, i, v[i], F[i], lim);
        },
        merge_checks);
  }
  // Distributed: the guard's verdict and the speeds are reduced exactly (a flag, maxima), and
  // every rank throws the message of the first rank that found a bad particle.
  const dist::Comm& comm = dist::Comm::world();
  const bool many = ranks_ && comm.size() > 1;
  // One reduction for the flag and both speeds (one synchronisation point a substep, not three).
  const std::vector<double> most =
      many ? comm.max(std::vector<double>{double(chk.bad >= 0), double(chk.max_wave),
                                          double(chk.max_speed)})
           : std::vector<double>{};
  // A run keeping J alone (keeps_J_only) has no F to name.
  const char* deformation_what = attr_.J >= 0 ? "has a non-finite volume ratio J = det F"
                                              : "has a non-finite deformation gradient F";
  if (many && most[0] > 0) {
    std::string msg;
    if (chk.bad >= 0)
      msg = "step " + std::to_string(steps_) + ": particle id " +
            std::to_string(particles_.int32(attr_.id)[chk.bad]) + " (rank " +
            std::to_string(comm.rank()) + ") " +
            (chk.what == 1   ? "has a non-finite velocity"
             : chk.what == 2 ? deformation_what
                             : "moves above the stability limit max_speed") +
            "; the simulation blew up (reduce cfl or max_dt, or check material stiffness)";
    std::vector<std::size_t> sizes;
    const std::vector<char> all = comm.allgather(std::vector<char>(msg.begin(), msg.end()), &sizes);
    std::size_t at = 0;
    for (std::size_t q = 0; q < sizes.size() && msg.empty(); at += sizes[q++])
      if (sizes[q] > 0)
        msg.assign(all.begin() + std::ptrdiff_t(at), all.begin() + std::ptrdiff_t(at + sizes[q]));
    throw SimulationError(msg);
  }
  if (chk.bad >= 0) {
    std::ostringstream os;
    os << "step " << steps_ << " (t = " << time_ << " s): particle " << chk.bad << " ";
    const Vec3 vb = v[chk.bad];
    if (chk.what == 1)
      os << "has a non-finite velocity (" << vb.transpose() << ")";
    else if (chk.what == 2)
      os << deformation_what;
    else
      os << "moves at " << vb.norm() << " m/s, above the stability limit max_speed = " << limit
         << " m/s";
    os << "; the simulation blew up (reduce cfl or max_dt, or check material stiffness)";
    throw SimulationError(os.str());
  }
  // Implicit: the elastic waves are integrated stably, only the material speed limits dt (but
  // particles whose domain is disabled have explicit stresses).
  const bool explicit_stress = !implicit_ || (enriched_ && enriched_->explicit_stresses());
  const Real max_wave = many ? Real(most[1]) : chk.max_wave;
  const Real wave = explicit_stress ? std::max(max_wave_speed_, max_wave) : Real(0);
  // Emitters about to emit start at their velocity.
  Real speed = many ? Real(most[2]) : chk.max_speed;
  for (const EmitterSpec& e : emitters_)
    if (time_ < e.end) speed = std::max(speed, e.velocity.norm());
  const Real denom = speed + wave;
  Real dt = denom > 0 ? settings_.cfl * settings_.dx / denom : settings_.max_dt;
  // Explicit viscosity: the diffusion number nu dt / dx^2 must stay below 1/(2 d) = 1/6.
  if (max_kinematic_viscosity_ > 0)
    dt = std::min(dt, settings_.cfl * settings_.dx * settings_.dx / (3 * max_kinematic_viscosity_));
  // Explicit particle domains: enriched corners are FE nodes finer than the grid and stiffer when
  // compressed.
  if (enriched_ && !implicit_) dt = std::min(dt, enriched_->dt_limit(space, *this));
  return std::min(dt, settings_.max_dt);
}

std::vector<Vec3d> MpmSolver::positions_by_id() const {
  std::vector<Vec3d> out(std::size_t(next_id_),
                         Vec3d::Constant(std::numeric_limits<double>::quiet_NaN()));
  const std::int32_t* id = particles_.int32(attr_.id);
  const Vec3* x = particles_.vec3(attr_.x);
  const Vec3* lo = particles_.vec3(attr_.x_lo);
  for (std::size_t p = 0; p < particles_.size(); ++p)
    out[std::size_t(id[p])] = x[p].cast<double>() + lo[p].cast<double>();
  return out;
}

MpmDiagnostics MpmSolver::diagnostics(const exec::Space& space) const {
  return mpm_diagnostics(space, particles_, attr_, materials_, distributed());
}

// Each sum is exact until one rounding at the end (ExactSum), so the chunks and ranks the particles
// fall in change no bit: a distributed run's diagnostics are the single process's without
// gathering a particle.
MpmDiagnostics mpm_diagnostics(const exec::Space& space, const ParticleSet& particles_,
                               const MpmAttributes& attr_,
                               const std::vector<MaterialParams>& materials_, bool over_ranks) {
  struct Acc {
    ExactSum s[6];  // kinetic, elastic, mass, momentum x, y, z
    double vmax = 0;
  };
  const Vec3* v = particles_.vec3(attr_.v);
  const Real* V0 = particles_.real(attr_.volume0);
  const std::int32_t* mat = particles_.int32(attr_.material);
  const MaterialParams* mats = materials_.data();
  // What the energies read: F, J (fluids alone) or b - I, and the plastic and temperature fields.
  MpmParticleView p{};
  p.F = attr_.F >= 0 ? const_cast<Mat3*>(particles_.mat3(attr_.F)) : nullptr;
  p.J = attr_.J >= 0 ? const_cast<Real*>(particles_.real(attr_.J)) : nullptr;
  p.b = attr_.b >= 0 ? const_cast<SymDev*>(particles_.sym_dev(attr_.b)) : nullptr;
  p.plastic = attr_.plastic >= 0 ? const_cast<Real*>(particles_.real(attr_.plastic)) : nullptr;
  p.temperature =
      attr_.temperature >= 0 ? const_cast<Real*>(particles_.real(attr_.temperature)) : nullptr;
  p.material = mat;
  // Batches of kEnergyBatch particles: their energy densities at the vector path's width
  // (energy_densities, kernels/material_update.hpp: bitwise energy() per particle; the scalar
  // SVDs were ~3/4 of this pass, and then the baseline's 4-wide ones ~2/3).
  constexpr std::size_t W = kEnergyBatch;
  const std::size_t n = particles_.size();
  Acc a = exec::parallel_reduce(
      space, "mpm.diagnostics", exec::Index((n + W - 1) / W), Acc{},
      [=](exec::Index g, Acc& acc) {
        const std::size_t q0 = std::size_t(g) * W, q1 = std::min(n, q0 + W);
        Real e[W];
        energy_densities(p, mats, q0, q1, e);
        for (std::size_t i = q0; i < q1; ++i) {
          const Vec3d vi = v[i].cast<double>();
          const double mi = double(mats[mat[i]].mass(V0[i]));
          acc.s[0].add(0.5 * mi * vi.squaredNorm());
          acc.s[1].add(double(V0[i]) * double(e[i - q0]));
          acc.s[2].add(mi);
          for (int c = 0; c < 3; ++c) acc.s[3 + c].add(mi * vi[c]);
          acc.vmax = std::max(acc.vmax, vi.norm());
        }
      },
      [](Acc x, const Acc& y) {
        for (int k = 0; k < 6; ++k) x.s[k].merge(y.s[k]);
        x.vmax = std::max(x.vmax, y.vmax);
        return x;
      });
  if (over_ranks) {
    const dist::Comm& comm = dist::Comm::world();
    dist::sum_over_ranks(comm, a.s, 6);
    a.vmax = comm.max(a.vmax);
  }
  MpmDiagnostics d;
  d.kinetic = a.s[0].value();
  d.elastic = a.s[1].value();
  d.mass = a.s[2].value();
  d.momentum = Vec3d(a.s[3].value(), a.s[4].value(), a.s[5].value());
  d.max_speed = a.vmax;
  return d;
}

}  // namespace amalgam
