#include "solvers/pd_solver.hpp"

#include <algorithm>
#include <cstring>
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "core/dist/comm.hpp"
#include "core/geometry/level_set_collider.hpp"
#include "core/errors.hpp"

namespace amalgam {

PdAttributes PdAttributes::add_to(ParticleSet& ps) {
  PdAttributes a;
  a.x = ps.add("x", AttrType::Real, 3);
  a.x_lo = ps.add("x_lo", AttrType::Real, 3);
  a.x0 = ps.add("x0", AttrType::Real, 3);
  a.v = ps.add("v", AttrType::Real, 3);
  a.acc = ps.add("acc", AttrType::Real, 3);
  a.volume = ps.add("volume", AttrType::Real, 1);
  a.material = ps.add("material", AttrType::Int32, 1);
  a.id = ps.add("id", AttrType::Int32, 1);
  a.theta = ps.add("theta", AttrType::Real, 1);
  a.damage = ps.add("damage", AttrType::Real, 1);
  a.fixed = ps.add("fixed", AttrType::Int32, 1);
  a.fixed_v = ps.add("fixed_v", AttrType::Real, 3);
  a.f_ext = ps.add("f_ext", AttrType::Real, 3);
  return a;
}

PdSolver::PdSolver(const PdSettings& settings, std::vector<PdMaterial> materials,
                   std::vector<Collider> colliders)
    : settings_(settings), materials_(std::move(materials)), colliders_(std::move(colliders)) {
  if (materials_.empty()) throw std::invalid_argument("PdSolver: no materials");
  if (!(settings_.spacing > 0) || !(settings_.horizon > settings_.spacing))
    throw std::invalid_argument("PdSolver: the horizon must exceed the particle spacing");
  attr_ = PdAttributes::add_to(particles_);
  params_.horizon = settings_.horizon;
  params_.spacing = settings_.spacing;
  if (settings_.model == PdModel::Lps &&
      (settings_.surface_correction || settings_.deviatoric != PdDeviatoric::Lps))
    throw std::invalid_argument(
        "PdSolver: the LPS model has its own normalisation (m_i) and deviatoric extension: "
        "surface_correction off and deviatoric lps");
  params_.model = settings_.model;
  params_.deviatoric = settings_.deviatoric;
  params_.criterion = settings_.criterion;
  params_.consistent = settings_.surface_correction && settings_.model == PdModel::Paper;
}

void PdSolver::add_particles(const std::vector<Vec3>& x, const Vec3& v, const Vec3& omega,
                             const Vec3& centre, int material, Real volume) {
  add_particles(x, std::vector<Real>(x.size(), volume), v, omega, centre, material);
}

void PdSolver::add_particles(const std::vector<Vec3>& x, const std::vector<Real>& volume,
                             const Vec3& v, const Vec3& omega, const Vec3& centre, int material) {
  if (initialized_) throw std::logic_error("PdSolver: particles added after initialize()");
  if (material < 0 || std::size_t(material) >= materials_.size())
    throw std::invalid_argument("PdSolver: bad material");
  const std::size_t n0 = particles_.size();
  particles_.resize(n0 + x.size());
  Vec3* px = particles_.vec3(attr_.x);
  Vec3* plo = particles_.vec3(attr_.x_lo);
  Vec3* px0 = particles_.vec3(attr_.x0);
  Vec3* pv = particles_.vec3(attr_.v);
  Real* vol = particles_.real(attr_.volume);
  std::int32_t* mat = particles_.int32(attr_.material);
  std::int32_t* id = particles_.int32(attr_.id);
  for (std::size_t k = 0; k < x.size(); ++k) {
    const std::size_t i = n0 + k;
    px[i] = px0[i] = x[k];
    plo[i] = Vec3::Zero();
    pv[i] = v + omega.cross(x[k] - centre);
    vol[i] = volume[k];
    mat[i] = material;
    id[i] = std::int32_t(i);
  }
}

void PdSolver::prescribe_velocity(const Vec3& lo, const Vec3& hi, const Vec3& velocity) {
  const Vec3* x0 = particles_.vec3(attr_.x0);
  std::int32_t* fixed = particles_.int32(attr_.fixed);
  Vec3* fv = particles_.vec3(attr_.fixed_v);
  Vec3* v = particles_.vec3(attr_.v);
  for (std::size_t i = 0; i < particles_.size(); ++i)
    if ((x0[i].array() >= lo.array()).all() && (x0[i].array() <= hi.array()).all()) {
      fixed[i] = 1;
      fv[i] = velocity;
      v[i] = velocity;
    }
}

void PdSolver::prescribe_velocity(const Vec3& lo, const Vec3& hi,
                                  std::shared_ptr<const VectorField> velocity) {
  const Vec3* x0 = particles_.vec3(attr_.x0);
  std::int32_t* fixed = particles_.int32(attr_.fixed);
  Drive d{std::move(velocity), {}, lo, hi};
  for (std::size_t i = 0; i < particles_.size(); ++i)
    if ((x0[i].array() >= lo.array()).all() && (x0[i].array() <= hi.array()).all()) {
      fixed[i] = 1;
      d.particles.push_back(std::uint32_t(i));
    }
  drives_.push_back(std::move(d));
  drive_velocities(exec::Space(exec::Backend::Serial, 1), time_);
  Vec3* v = particles_.vec3(attr_.v);
  const Vec3* fv = particles_.vec3(attr_.fixed_v);
  for (std::uint32_t i : drives_.back().particles) v[i] = fv[i];
  if (!drives_.back().v->uses_time()) drives_.pop_back();  // set once, for the whole run
}

// fixed_v = v(X, t) on every driven particle; a value that is not finite (or beyond 1e30) stops
// the run naming the condition, the component, the time and the particle's reference position.
void PdSolver::drive_velocities(const exec::Space& space, double t) {
  const Vec3* x0 = particles_.vec3(attr_.x0);
  Vec3* fv = particles_.vec3(attr_.fixed_v);
  for (const Drive& d : drives_) {
    const VectorField* f = d.v.get();
    const std::uint32_t* idx = d.particles.data();
    const long long bad = exec::parallel_reduce(
        space, "pd.drive", exec::Index(d.particles.size()), (long long)-1,
        [=](exec::Index k, long long& first) {
          const std::uint32_t i = idx[k];
          const Vec3d v = f->at(x0[i].cast<double>(), t);
          if (!(v.cwiseAbs().maxCoeff() <= 1e30)) {  // also NaN
            if (first < 0) first = (long long)k;
            return;
          }
          fv[i] = v.cast<Real>();
        },
        [](long long a, long long b) { return a >= 0 ? a : b; });
    if (bad < 0) continue;
    const Vec3d X = x0[idx[bad]].cast<double>(), v = f->at(X, t);
    int a = 0;
    while (a < 2 && v[a] == v[a] && std::abs(v[a]) <= 1e30) ++a;
    std::ostringstream os;
    os << f->where << "/" << a << ": \"" << f->c[a].text() << "\" gives " << v[a] << " at t = " << t
       << " s and (" << X[0] << ", " << X[1] << ", " << X[2] << ")";
    throw SimulationError(os.str());
  }
}

void PdSolver::apply_force_density(const Vec3& lo, const Vec3& hi, const Vec3& force_density) {
  const Vec3* x0 = particles_.vec3(attr_.x0);
  Vec3* fe = particles_.vec3(attr_.f_ext);
  for (std::size_t i = 0; i < particles_.size(); ++i)
    if ((x0[i].array() >= lo.array()).all() && (x0[i].array() <= hi.array()).all())
      fe[i] += force_density;
}

void PdSolver::add_crack_mesh(const std::vector<Vec3d>& nodes,
                              const std::vector<std::array<std::int32_t, 4>>& tets,
                              std::uint32_t first_particle) {
  if (initialized_) throw std::logic_error("PdSolver: mesh added after initialize()");
  if (std::size_t(first_particle) + tets.size() > particles_.size())
    throw std::invalid_argument("PdSolver: the mesh's tetrahedra have no particles");
  meshes_.emplace_back(nodes, tets, first_particle);
}

void PdSolver::move_meshes(Real dt) {
  for (PdCrackMesh& m : meshes_)
    m.move_vertices(particles_.vec3(attr_.v), particles_.real(attr_.volume),
                    particles_.int32(attr_.material), materials_.data(), dt);
}

void PdSolver::split_meshes() {
  if (intact_ == meshes_intact_) return;  // no bond broke since the last look
  for (PdCrackMesh& m : meshes_) m.update_topology(bonds_);
  meshes_intact_ = intact_;
}

void PdSolver::add_precrack(const Vec3& point, const Vec3& n, const Vec3& lo, const Vec3& hi) {
  if (initialized_) throw std::logic_error("PdSolver: pre-crack added after initialize()");
  precracks_.push_back({point, n.normalized(), lo, hi});
}

PdView PdSolver::view() {
  PdView p;
  p.n = particles_.size();
  p.x0 = particles_.vec3(attr_.x0);
  p.x = particles_.vec3(attr_.x);
  p.x_lo = particles_.vec3(attr_.x_lo);
  p.volume = particles_.real(attr_.volume);
  p.material = particles_.int32(attr_.material);
  p.theta = particles_.real(attr_.theta);
  p.q = q_.data();
  p.damage = particles_.real(attr_.damage);
  p.m = constants_.m.data();
  p.a = constants_.a.data();
  p.b = constants_.b.data();
  p.kappa = constants_.kappa.data();
  p.bonds0 = constants_.bonds0.data();
  return p;
}

void PdSolver::initialize(const exec::Space& space) {
  const std::size_t n = particles_.size();
  pd_build_bonds(space, particles_.vec3(attr_.x0), particles_.real(attr_.volume),
                 particles_.int32(attr_.material), n, params(), settings_.partial_volume, bonds_);
  dist_stats_.families_fitted =
      pd_constants(space, particles_.vec3(attr_.x0), particles_.int32(attr_.material), bonds_,
                   params(), settings_.surface_correction, constants_);
  // Pre-cracks break bonds after the constants: the material around a crack is the same material,
  // only disconnected (its damage is > 0 from the start).
  apply_precracks(space, bonds_, nullptr);
  force_.assign(n, Vec3::Zero());
  q_.assign(n, Real(0));
  for (PdCrackMesh& m : meshes_) m.attach(bonds_);
  bonds_initial_ = bonds_.size();
  initialized_ = true;
  crit_dt_ = critical_dt(space);
  // Initial accelerations (velocity Verlet needs a^0).
  compute_dilatation(space);
  compute_forces(space);
  contact_forces(space);
  update_damage(space);
  kick(space, 0);
}

void PdSolver::apply_precracks(const exec::Space& space, PdBonds& b, const std::uint32_t* rows) {
  if (precracks_.empty()) return;
  const Vec3* x0 = particles_.vec3(attr_.x0);
  const Precrack* cracks = precracks_.data();
  const std::size_t nc = precracks_.size();
  exec::parallel_for(space, "pd.precracks", exec::Index(b.particles()), [&](exec::Index q) {
    const std::size_t i = rows ? rows[q] : std::size_t(q);
    for (std::uint64_t k = b.offsets[std::size_t(q)]; k < b.offsets[std::size_t(q) + 1]; ++k) {
      const std::uint32_t j =
          b.neighbor[k];  // evaluate from the lower index: both rows decide alike
      const Vec3 &a = x0[std::min<std::size_t>(i, j)], &c = x0[std::max<std::size_t>(i, j)];
      for (std::size_t p = 0; p < nc; ++p) {
        const Real sa = (a - cracks[p].point).dot(cracks[p].n),
                   sc = (c - cracks[p].point).dot(cracks[p].n);
        if (!(sa * sc < 0)) continue;
        const Vec3 hit = a + (sa / (sa - sc)) * (c - a);
        if ((hit.array() >= cracks[p].lo.array()).all() &&
            (hit.array() <= cracks[p].hi.array()).all())
          b.intact[k] = 0;
      }
    }
  });
}

std::vector<Vec3> PdSolver::probe_start() const {
  const std::size_t n = particles_.size();
  const std::int32_t* fixed = particles_.int32(attr_.fixed);
  std::vector<Vec3> v(n);
  std::mt19937 rng(20261123);  // a fixed start vector: the estimate is reproducible
  std::uniform_real_distribution<double> u(-1, 1);
  for (std::size_t i = 0; i < n; ++i)
    v[i] = fixed[i] ? Vec3::Zero() : Vec3(Real(u(rng)), Real(u(rng)), Real(u(rng)));
  return v;
}

Real PdSolver::critical_dt(const exec::Space& space, const std::vector<Vec3>* start) {
  const std::size_t n = particles_.size();
  if (global_particle_count() == 0) return std::numeric_limits<Real>::infinity();
  Vec3* x = particles_.vec3(attr_.x);
  const std::int32_t* fixed = particles_.int32(attr_.fixed);
  const std::int32_t* mat = particles_.int32(attr_.material);
  const std::vector<Vec3> x_start(x, x + n);
  // Elastic copies of the materials (a yield in the probe would soften the operator) and no
  // fracture: the probe only reads forces.
  std::vector<PdMaterial> elastic = materials_;
  for (PdMaterial& m : elastic) m.psi0 = std::numeric_limits<Real>::infinity();
  PdParams prm = params();
  prm.materials = elastic.data();
  const PdView p = view();
  // Distributed: the own particles' values (rows), their ghosts' from the owners before each pass
  // that reads them; the sums |v|^2 and |A v|^2 of the last iteration in the single process's
  // order (global id) on rank 0.
  const std::vector<std::uint32_t> act = owned_local();
  auto forces = [&](std::vector<Vec3>& f) {
    if (ranks_) share(x);
    pd_dilatation(space, p, bonds_, prm, &scratch_);
    share(particles_.real(attr_.theta));
    share(q_.data());
    pd_forces(space, p, bonds_, prm, false, f.data(), nullptr, &scratch_);
  };
  std::vector<Vec3> f0(n), f(n), v = start ? *start : probe_start();
  forces(f0);
  const Real amp =
      Real(3e-3) * settings_.spacing;  // probe displacement: linear, above float round-off
  double lambda = 0;
  std::vector<double> vv_terms(ranks_ ? act.size() : 0), aa_terms(vv_terms.size());
  bool iterated = false;
  for (int it = 0; it < 40; ++it) {
    double vmax = 0, vv = 0;
    for (std::uint32_t i : act) vmax = std::max(vmax, double(v[i].cwiseAbs().maxCoeff()));
    if (ranks_) vmax = dist::Comm::world().max(vmax);  // exact
    if (!(vmax > 0)) break;
    for (std::size_t k = 0; k < act.size(); ++k) {
      const std::uint32_t i = act[k];
      v[i] /= Real(vmax);
      const double t = double(v[i].squaredNorm());
      if (ranks_) vv_terms[k] = t;
      vv += t;
      x[i] = x_start[i] + amp * v[i];
    }
    forces(f);
    double aa = 0;
    for (std::size_t k = 0; k < act.size(); ++k) {
      const std::uint32_t i = act[k];
      v[i] = fixed[i] ? Vec3::Zero()
                      : Vec3(-(f[i] - f0[i]) / (amp * materials_[std::size_t(mat[i])].density));
      const double t = double(v[i].squaredNorm());
      if (ranks_) aa_terms[k] = t;
      aa += t;
    }
    lambda = std::sqrt(aa / vv);  // |A v| / |v| -> the largest |eigenvalue| of A = rho^-1 K
    iterated = true;
  }
  std::copy(x_start.begin(), x_start.end(), x);
  if (ranks_ && iterated) {  // the sums in global id order (as one process adds them)
    const dist::Comm& comm = dist::Comm::world();
    const std::vector<std::uint64_t> gid = global_ids();
    std::vector<double> mine;
    for (std::size_t k = 0; k < act.size(); ++k)
      mine.insert(mine.end(), {double(gid[act[k]]), vv_terms[k], aa_terms[k]});
    const std::vector<double> all =
        dist::from_bytes<double>(comm.gather(dist::as_bytes(mine), nullptr));
    std::vector<char> out(sizeof(double));
    if (comm.root()) {
      std::vector<double> vv_g(global_particle_count(), 0), aa_g(vv_g.size(), 0);
      for (std::size_t k = 0; k + 2 < all.size(); k += 3)
        vv_g[std::size_t(all[k])] = all[k + 1], aa_g[std::size_t(all[k])] = all[k + 2];
      double vv = 0, aa = 0;
      for (std::size_t i = 0; i < vv_g.size(); ++i) vv += vv_g[i], aa += aa_g[i];
      lambda = std::sqrt(aa / vv);
      std::memcpy(out.data(), &lambda, sizeof lambda);
    }
    comm.broadcast(out);
    std::memcpy(&lambda, out.data(), sizeof lambda);
  }
  // Power iteration approaches the largest eigenvalue from below: 10 % margin on omega^2.
  return Real(2.0 / std::sqrt(1.1 * lambda));
}

Real PdSolver::stable_dt(const exec::Space& space) const {
  struct Check {
    Real vmax = 0;
    exec::Index bad = -1;
    int what = 0;  // 1 non-finite velocity, 2 non-finite position, 3 runaway speed
  };
  const Vec3* v = particles_.vec3(attr_.v);
  const Vec3* x = particles_.vec3(attr_.x);
  const Real limit = settings_.max_speed;
  // Distributed: this rank's own particles (ghosts are some other rank's), the maximum reduced
  // exactly over the ranks.
  const std::vector<std::uint32_t> own = ranks_ ? owned_local() : std::vector<std::uint32_t>();
  const std::uint32_t* ol = own.data();
  const bool all = !ranks_;
  const Check c = exec::parallel_reduce(
      space, "pd.cfl_check", exec::Index(all ? particles_.size() : own.size()), Check{},
      [=](exec::Index k, Check& acc) {
        const exec::Index i = all ? k : exec::Index(ol[k]);
        const Real s = v[i].norm();
        const int what = !std::isfinite(s) ? 1 : !x[i].allFinite() ? 2 : s > limit ? 3 : 0;
        if (what && (acc.bad < 0 || i < acc.bad)) acc.bad = i, acc.what = what;
        acc.vmax = std::max(acc.vmax, s);
      },
      [](Check a, const Check& b) {
        if (a.bad < 0 && b.bad >= 0) a.bad = b.bad, a.what = b.what;
        a.vmax = std::max(a.vmax, b.vmax);
        return a;
      });
  // Distributed: the guard's verdict is reduced (a flag), and every rank throws the message of
  // the first rank that found a bad particle (so every rank retries the frame alike).
  const dist::Comm& comm = dist::Comm::world();
  const bool many = ranks_ && comm.size() > 1;
  const bool any_bad = many ? comm.max(std::int64_t(c.bad >= 0)) > 0 : c.bad >= 0;
  if (any_bad) {
    std::string msg;
    if (c.bad >= 0) {
      std::ostringstream os;
      os << "step " << steps_ << " (t = " << time_ << " s): particle " << c.bad << " (id "
         << particles_.int32(attr_.id)[c.bad]
         << (many ? ", rank " + std::to_string(comm.rank()) : "") << ") ";
      if (c.what == 1)
        os << "has a non-finite velocity (" << v[c.bad].transpose() << ")";
      else if (c.what == 2)
        os << "has a non-finite position";
      else
        os << "moves at " << v[c.bad].norm()
           << " m/s, above the stability limit max_speed = " << limit << " m/s";
      os << "; the simulation blew up (reduce cfl or max_dt, or check the material stiffness)";
      msg = os.str();
    }
    if (many) {
      std::vector<std::size_t> sizes;
      const std::vector<char> all =
          comm.allgather(std::vector<char>(msg.begin(), msg.end()), &sizes);
      std::size_t at = 0;
      msg.clear();
      for (std::size_t q = 0; q < sizes.size() && msg.empty(); at += sizes[q++])
        if (sizes[q] > 0)
          msg.assign(all.begin() + std::ptrdiff_t(at), all.begin() + std::ptrdiff_t(at + sizes[q]));
    }
    throw SimulationError(msg);
  }
  const Real vmax = ranks_ ? Real(dist::Comm::world().max(double(c.vmax))) : c.vmax;  // exact
  Real dt = std::min(settings_.max_dt, settings_.cfl * crit_dt_);
  if (vmax > 0) dt = std::min(dt, settings_.cfl * settings_.spacing / vmax);
  return dt;
}

void PdSolver::kick_drift(const exec::Space& space, Real dt) {
  Vec3* x = particles_.vec3(attr_.x);
  Vec3* xlo = particles_.vec3(attr_.x_lo);
  Vec3* v = particles_.vec3(attr_.v);
  const Vec3* a = particles_.vec3(attr_.acc);
  const std::int32_t* fixed = particles_.int32(attr_.fixed);
  const Vec3* fv = particles_.vec3(attr_.fixed_v);
  const Real h = Real(0.5) * dt;
  const Real damp = Real(std::exp(-double(settings_.damping) * double(h)));
  exec::parallel_for(space, "pd.kick_drift", exec::Index(particles_.size()), [=](exec::Index i) {
    v[i] = fixed[i] ? fv[i] : Vec3(damp * (v[i] + h * a[i]));
    add_compensated(x[i], xlo[i], Vec3(dt * v[i]));
  });
}

void PdSolver::apply_colliders(const exec::Space& space, Real t) {
  if (colliders_.empty()) return;
  prepare_colliders(colliders_, particles_.vec3(attr_.x), particles_.size(), settings_.horizon, t,
                    space);  // field colliders around the particles
  std::vector<Collider> posed;
  for (const Collider& c : colliders_) posed.push_back(c.posed_at(t));
  const Collider* cols = posed.data();
  const int nc = int(posed.size());
  Vec3* x = particles_.vec3(attr_.x);
  Vec3* xlo = particles_.vec3(attr_.x_lo);
  Vec3* v = particles_.vec3(attr_.v);
  const std::int32_t* fixed = particles_.int32(attr_.fixed);
  exec::parallel_for(space, "pd.colliders", exec::Index(particles_.size()), [=](exec::Index i) {
    if (fixed[i]) return;
    for (int c = 0; c < nc; ++c) {
      const Real phi = cols[c].phi(x[i], t);
      if (phi >= 0) continue;
      cols[c].project(x[i], t, v[i]);  // velocity: sticky / slip / separating + friction
      x[i] -= phi * cols[c].outward_normal(x[i], t);  // position back onto the surface
      xlo[i] = Vec3::Zero();                          // the projected position is exact as is
    }
  });
}

void PdSolver::compute_dilatation(const exec::Space& space) {
  pd_dilatation(space, view(), bonds_, params(), &scratch_);
}

void PdSolver::compute_forces(const exec::Space& space) {
  // With the damage (update_damage's work, in the same pass: one pass over the bonds fewer).
  pd_forces(space, view(), bonds_, params(), settings_.fracture, force_.data(), nullptr, &scratch_,
            &intact_);
}

Real PdSolver::contact_distance() const {
  return settings_.contact_distance > 0 ? settings_.contact_distance
                                        : Real(0.9) * settings_.spacing;
}

void PdSolver::contact_forces(const exec::Space& space) {
  if (!settings_.contact) return;
  const Real d = contact_distance();
  const Real skin =
      settings_.contact_skin > 0 ? settings_.contact_skin : Real(0.5) * settings_.spacing;
  const Vec3* x = particles_.vec3(attr_.x);
  // Distributed: exchange_positions decided (by a maximum over every rank) and rebuilt.
  if (!ranks_ && (contact_list_.x_built.size() != particles_.size() ||
                  pd_max_displacement(space, x, contact_list_) > skin / 2)) {
    pd_build_contact_list(space, x, particles_.size(), d + skin, contact_list_);
    ++contact_builds_;
  }
  pd_contact_forces(space, view(), bonds_, params(), d, contact_list_, force_.data());
}

void PdSolver::update_damage(const exec::Space& space) {
  intact_ = pd_damage(space, view(), bonds_);
}

void PdSolver::compact_bonds(const exec::Space& space) {
  if (!(settings_.compact_fraction > 0)) return;
  const std::uint64_t stored = bonds_.size();
  const std::uint64_t removable =
      stored - intact_ - kept_broken_;  // broken since the last compaction
  if (!(double(removable) > double(settings_.compact_fraction) * double(stored))) return;
  if (armed_.p && !armed_.p->layout_saved) {  // a retry of this frame needs the layout back
    armed_.p->layout = bonds_;
    armed_.p->layout_saved = true;
  }
  pd_compact_bonds(space, bonds_, settings_.contact ? contact_distance() : Real(0));
  kept_broken_ = bonds_.size() - intact_;
  ++compactions_;
  for (PdCrackMesh& m : meshes_) m.reattach(bonds_);
}

bool PdSolver::restore_bonds(const std::vector<std::uint64_t>& offsets,
                             const std::vector<std::uint32_t>& neighbor,
                             const std::vector<Real>& plastic,
                             const std::vector<std::uint8_t>& intact) {
  if (!initialized_) throw std::logic_error("PdSolver: restore_bonds() before initialize()");
  if (plastic.size() != neighbor.size() || intact.size() != neighbor.size()) return false;
  const exec::Space serial;
  if (!pd_restrict_bonds(serial, bonds_, offsets, neighbor)) return false;
  bonds_.plastic = plastic;
  bonds_.intact = intact;
  pd_mirror_bonds(serial, bonds_);
  const Real d = settings_.contact ? contact_distance() : Real(0);
  intact_ = kept_broken_ = 0;
  for (std::size_t k = 0; k < bonds_.size(); ++k) {
    intact_ += bonds_.intact[k];
    kept_broken_ += !bonds_.intact[k] &&
                    pd_contact_reads_broken_bond(bonds_.length[k], d);  // what compaction keeps
  }
  meshes_intact_ = intact_;
  for (PdCrackMesh& m : meshes_) m.reattach(bonds_);
  return true;
}

void PdSolver::save(Snapshot& s) {
  particles_.save(s.particles);
  s.plastic = bonds_.plastic;
  s.plastic_r = bonds_.plastic_r;
  s.intact = bonds_.intact;
  s.layout = PdBonds();
  s.layout_saved = false;
  s.meshes = meshes_;
  s.intact_count = intact_, s.meshes_intact = meshes_intact_, s.kept_broken = kept_broken_;
  s.compactions = compactions_, s.bond_updates = bond_updates_;
  s.time = time_, s.steps = steps_;
  s.ranks = ranks_;
  if (ranks_) {  // the local layout changes when re-ghosting: keep it whole
    s.layout = bonds_;
    s.layout_saved = true;
    s.constants = constants_;
  }
  armed_.p = &s;
}

void PdSolver::restore(Snapshot& s) {
  particles_.restore(s.particles);
  if (s.layout_saved) bonds_ = s.layout;  // a compaction ran since save(): its layout back
  bonds_.plastic = s.plastic;
  bonds_.plastic_r = s.plastic_r;
  bonds_.intact = s.intact;
  meshes_ = s.meshes;
  intact_ = s.intact_count, meshes_intact_ = s.meshes_intact, kept_broken_ = s.kept_broken;
  compactions_ = s.compactions, bond_updates_ = s.bond_updates;
  time_ = s.time, steps_ = s.steps;
  contact_list_ = PdContactList();  // positions changed: rebuilt at the next contact pass
  if (s.ranks) {
    ranks_ = s.ranks;
    constants_ = s.constants;
    force_.assign(particles_.size(), Vec3::Zero());
    q_.assign(particles_.size(), Real(0));
    select_drives();
  }
  ++version_;
}

void PdSolver::kick(const exec::Space& space, Real dt) {
  Vec3* v = particles_.vec3(attr_.v);
  Vec3* a = particles_.vec3(attr_.acc);
  const std::int32_t* fixed = particles_.int32(attr_.fixed);
  const Vec3* fv = particles_.vec3(attr_.fixed_v);
  const std::int32_t* mat = particles_.int32(attr_.material);
  const PdMaterial* mats = materials_.data();
  const Vec3* f = force_.data();
  const Vec3* fe = particles_.vec3(attr_.f_ext);
  const Vec3 g = settings_.gravity;
  const Real h = Real(0.5) * dt;
  const Real damp = Real(std::exp(-double(settings_.damping) * double(h)));
  exec::parallel_for(space, "pd.kick", exec::Index(particles_.size()), [=](exec::Index i) {
    a[i] = (f[i] + fe[i]) / mats[mat[i]].density + g;  // rho a = f + b (eq. 1)
    v[i] = fixed[i] ? fv[i] : Vec3(damp * (v[i] + h * a[i]));
  });
}

void PdSolver::step(const exec::Space& space, Real dt) {
  if (!initialized_) throw std::logic_error("PdSolver: step() before initialize()");
  if (!(dt > 0) || !std::isfinite(dt))
    throw SimulationError("peridynamics: invalid time step " + std::to_string(dt));
  drive_velocities(space, time_ + 0.5 * double(dt));  // the drift's midpoint
  kick_drift(space, dt);
  move_meshes(dt);  // with the half-step velocities that moved the particles
  apply_colliders(space, Real(time_ + double(dt)));
  if (ranks_) dist_stats_.step_bytes = dist_stats_.step_messages = 0;
  if (ranks_) exchange_positions(space);  // the owners' positions in the ghosts
  compute_dilatation(space);
  share(particles_.real(attr_.theta));  // what the force pass reads of its ghosts
  share(q_.data());
  share_plastic();        // plastic: the far ends' returns of bonds to ghosts
  compute_forces(space);  // and the damage (update_damage)
  contact_forces(space);
  bond_updates_ += ranks_ ? global_stored_ : bonds_.size();
  share(particles_.real(attr_.damage));  // the next force pass's critical stretch of ghosts
  split_meshes();
  compact_bonds(space);
  drive_velocities(space, time_ + double(dt));
  kick(space, dt);  // ghosts' velocities are never read: not exchanged
  time_ += double(dt);
  ++steps_;
  ++version_;
}

void PdSolver::compute_stress(const exec::Space& space, std::vector<Mat3>& stress) {
  stress.resize(particles_.size());
  std::vector<Vec3> f(particles_.size());
  pd_forces(space, view(), bonds_, params(), false, f.data(), stress.data(), &scratch_);
  // distributed: the own rows' stresses (gather_owned joins them for output)
}

// Exact sums rounded once (ExactSum) over each rank's own particles: the single process's bits on
// every rank count, without gathering a particle.
PdDiagnostics PdSolver::diagnostics(const exec::Space& space) const {
  struct Acc {
    ExactSum ke, p[3];
    double vmax = 0, dmax = 0;
  };
  const std::vector<std::uint32_t> own = owned_local();
  const std::uint32_t* idx = own.data();
  const Vec3* v = particles_.vec3(attr_.v);
  const Real* vol = particles_.real(attr_.volume);
  const Real* dmg = particles_.real(attr_.damage);
  const std::int32_t* mat = particles_.int32(attr_.material);
  const PdMaterial* mats = materials_.data();
  Acc r = exec::parallel_reduce(
      space, "pd.diagnostics", exec::Index(own.size()), Acc{},
      [=](exec::Index k, Acc& a) {
        const std::uint32_t i = idx[k];
        const double m = double(mats[mat[i]].density) * double(vol[i]);
        const Vec3d vi = v[i].cast<double>();
        a.ke.add(0.5 * m * vi.squaredNorm());
        for (int c = 0; c < 3; ++c) a.p[c].add(m * vi[c]);
        a.vmax = std::max(a.vmax, vi.norm());
        a.dmax = std::max(a.dmax, double(dmg[i]));
      },
      [](Acc a, const Acc& b) {
        a.ke.merge(b.ke);
        for (int c = 0; c < 3; ++c) a.p[c].merge(b.p[c]);
        a.vmax = std::max(a.vmax, b.vmax);
        a.dmax = std::max(a.dmax, b.dmax);
        return a;
      });
  if (ranks_) {
    const dist::Comm& comm = dist::Comm::world();
    ExactSum sums[4] = {r.ke, r.p[0], r.p[1], r.p[2]};
    dist::sum_over_ranks(comm, sums, 4);
    r.ke = sums[0];
    for (int c = 0; c < 3; ++c) r.p[c] = sums[1 + c];
    const std::vector<double> mx = comm.max(std::vector<double>{r.vmax, r.dmax});
    r.vmax = mx[0], r.dmax = mx[1];
  }
  PdDiagnostics d;
  d.kinetic = r.ke.value();
  d.momentum = Vec3d(r.p[0].value(), r.p[1].value(), r.p[2].value());
  d.max_speed = r.vmax;
  d.max_damage = r.dmax;
  d.bonds = bonds_initial_;
  d.stored = global_sum(bonds_.size());
  d.compactions = compactions_;
  std::uint64_t intact = 0;
  for (std::uint8_t b : bonds_.intact) intact += b;
  d.intact = global_sum(intact);
  return d;
}

}  // namespace amalgam
