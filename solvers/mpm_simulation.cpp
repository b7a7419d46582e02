#include "solvers/mpm_simulation.hpp"

#include <climits>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

#include "core/dist/comm.hpp"
#include "core/errors.hpp"
#include "solvers/mpm_aul.hpp"
#include "solvers/mpm_enriched.hpp"
#include "solvers/mpm_implicit.hpp"

namespace amalgam {

namespace {
// Von Mises equivalent of a Cauchy stress: sqrt(3/2 s:s), s its deviator.
double von_mises(const Mat3d& sigma) {
  const Mat3d s = sigma - (sigma.trace() / 3.0) * Mat3d::Identity();
  return std::sqrt(1.5 * s.cwiseProduct(s).sum());
}

// Per particle: the von Mises stress of the elastic (and pressure) Cauchy stress tau / J of its
// material at its F, plastic state and temperature (MaterialParams::kirchhoff with a zero velocity
// gradient: the viscous stress is left out).
std::vector<float> mpm_von_mises(const ParticleSet& ps, const MpmAttributes& a,
                                 const std::vector<MaterialParams>& materials,
                                 const exec::Space& space) {
  const std::size_t n = ps.size();
  std::vector<float> out(n);
  const std::int32_t* mat = ps.int32(a.material);
  const Real* plastic = a.plastic >= 0 ? ps.real(a.plastic) : nullptr;
  const Real* temp = a.temperature >= 0 ? ps.real(a.temperature) : nullptr;
  const MaterialParams* m = materials.data();
  float* o = out.data();
  if (a.F < 0 && a.b < 0) {  // fluids keeping J alone: tau = -J p(J) I, no deviatoric part
    std::fill(out.begin(), out.end(), 0.0f);
    return out;
  }
  const Mat3* F = a.F >= 0 ? ps.mat3(a.F) : nullptr;
  const SymDev* b = a.b >= 0 ? ps.sym_dev(a.b) : nullptr;  // its Cholesky factor stands in for F
  exec::parallel_for(space, "output.vonmises", exec::Index(n), [=](exec::Index i) {
    const Mat3 Fi = F ? F[i] : b_factor(b[i]);
    const Mat3 tau = m[mat[i]].kirchhoff(Fi, Mat3::Zero(), plastic ? plastic[i] : Real(0),
                                         temp ? temp[i] : Real(0));
    o[i] = float(von_mises(tau.cast<double>() / double(Fi.determinant())));
  });
  return out;
}

std::vector<float> real_values(const ParticleSet& ps, ParticleSet::Id attr, const char* name) {
  if (attr < 0) throw std::logic_error(std::string("MPM particles have no ") + name);
  const Real* r = ps.real(attr);
  return std::vector<float>(r, r + ps.size());
}

// The attribute `name` of MPM particles (mpm_point_fields).
PointAttribute mpm_attribute(const std::string& name, const ParticleSet& ps, const MpmAttributes& a,
                             const std::vector<MaterialParams>& materials,
                             const exec::Space& space) {
  using T = PointAttribute::Type;
  const std::size_t n = ps.size();
  PointAttribute out{name, T::Float, {}, {}};
  const Mat3* F = a.F >= 0 ? ps.mat3(a.F) : nullptr;
  const Real* J = a.J >= 0 ? ps.real(a.J) : nullptr;       // fluids keeping J alone: F = J^{1/3} I
  const SymDev* b = a.b >= 0 ? ps.sym_dev(a.b) : nullptr;  // b - I: no F (MpmSettings::keep_F)
  if (name == "F") {
    if (b) throw std::logic_error("MPM particles keeping b = F F^T have no F");
    out.type = T::Mat3;
    out.f.resize(9 * n);
    for (std::size_t i = 0; i < n; ++i) {
      const Mat3 Fi = F ? F[i] : Mat3(detail::cube_root(J[i]) * Mat3::Identity());
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) out.f[9 * i + std::size_t(3 * r + c)] = float(Fi(r, c));
    }
  } else if (name == "J") {
    out.f.resize(n);
    for (std::size_t i = 0; i < n; ++i)
      out.f[i] = float(F ? F[i].determinant() : b ? b_factor(b[i]).determinant() : J[i]);
  } else if (name == "Jp") {
    out.f = real_values(ps, a.plastic, "plastic state");
  } else if (name == "temperature") {
    out.f = real_values(ps, a.temperature, "temperature");
  } else if (name == "vonmises") {
    out.f = mpm_von_mises(ps, a, materials, space);
  } else if (name == "rest") {
    if (a.rest < 0) throw std::logic_error("MPM rest positions were not kept");
    out.type = T::Vec3;
    out.f.resize(3 * n);
    const Vec3* r = ps.vec3(a.rest);
    for (std::size_t i = 0; i < n; ++i)
      for (int c = 0; c < 3; ++c) out.f[3 * i + std::size_t(c)] = float(r[i][c]);
  } else if (name == "material") {
    out.type = T::Int;
    out.i.assign(ps.int32(a.material), ps.int32(a.material) + n);
  } else if (name == "enrichment") {
    // Enriched MPM: the particle's enrichment state (-1 domain disabled, 0 unenriched,
    // 1 transitional, 2 enriched; enriched MPM Fig. 3), for colour-mapping as in Figs. 6 and 10.
    const ParticleSet::Id ds = ps.find("domain_state");
    if (ds < 0) throw std::logic_error("MPM particles have no particle domains");
    const std::int32_t* st = ps.int32(ds);
    out.f.resize(n);
    for (std::size_t i = 0; i < n; ++i) out.f[i] = float(st[i]);
  } else {
    throw std::logic_error("MPM particles have no attribute " + name);
  }
  return out;
}
}  // namespace

PointFields mpm_point_fields(const ParticleSet& ps, const MpmAttributes& a,
                             const std::vector<MaterialParams>& materials,
                             const std::vector<std::string>& names, const exec::Space& space) {
  PointFields p;
  p.n = ps.size();
  p.x = ps.vec3(a.x);
  p.v = ps.vec3(a.v);
  p.material = ps.int32(a.material);
  p.id = ps.int32(a.id);
  for (const std::string& name : names)
    p.attributes.push_back(mpm_attribute(name, ps, a, materials, space));
  return p;
}

// A checkpoint written before the output asked for `rest` has none: the set-up's positions are
// the rest positions of the particles it made (joined by id, over the ranks when the set-up was
// sliced); a particle emitted later has no rest position to recover.
void MpmSimulation::before_checkpoint_read() {
  setup_rest_.clear();
  const MpmAttributes& a = s_.attributes();
  if (a.rest < 0) return;
  const ParticleSet& ps = s_.particles();
  const Vec3* r = ps.vec3(a.rest);
  const std::int32_t* id = ps.int32(a.id);
  setup_rest_.resize(ps.size());
  for (std::size_t i = 0; i < ps.size(); ++i) setup_rest_[i] = {id[i], r[i]};
  setup_sliced_ = s_.sliced();
}

void MpmSimulation::fill_absent_attribute(const std::string& name) {
  const MpmAttributes& a = s_.attributes();
  if (name != "rest" || a.rest < 0) return Simulation::fill_absent_attribute(name);
  std::vector<RestById> table = std::move(setup_rest_);
  setup_rest_ = {};
  if (setup_sliced_)  // collective: every rank of a sliced set-up gets here
    table =
        dist::from_bytes<RestById>(dist::Comm::world().allgather(dist::as_bytes(table), nullptr));
  std::sort(table.begin(), table.end(),
            [](const RestById& x, const RestById& y) { return x.id < y.id; });
  ParticleSet& ps = s_.particles();
  Vec3* r = ps.vec3(a.rest);
  const std::int32_t* id = ps.int32(a.id);
  for (std::size_t i = 0; i < ps.size(); ++i) {
    const auto it = std::lower_bound(table.begin(), table.end(), id[i],
                                     [](const RestById& x, std::int32_t v) { return x.id < v; });
    if (it == table.end() || it->id != id[i])
      throw InputError(
          "particle attribute 'rest': the checkpoint was written without it and "
          "particle id " +
          std::to_string(id[i]) +
          " was emitted after set-up, so its rest position is unknown (resume "
          "without output attribute 'rest', or run from the start)");
    r[i] = it->x;
  }
}

MpmSimulation::MpmSimulation(MpmSolver solver) : s_(std::move(solver)) {
  initial_particles_ = s_.next_id();
  double most = 0;
  for (const EmitterSpec& e : s_.emitters()) most += e.max_particles(s_.settings().dx);
  emitted_bound_ = std::int64_t(std::min(most, double(INT32_MAX)));
  max_particles_ =
      std::size_t(std::min(initial_particles_ + emitted_bound_, std::int64_t(INT32_MAX)));
}

std::string MpmSimulation::describe() const {
  std::ostringstream os;
  // A distributed set-up's slice holds part of them: the set-up's count is its ids'.
  os << (s_.sliced() ? std::size_t(s_.next_id()) : s_.particles().size())
     << " particles, dx = " << s_.settings().dx << ", transfer "
     << transfer_name(s_.settings().transfer);
  return os.str();
}

void MpmSimulation::save_frame_start() {
  s_.save(snapshot_);
  frame_time_ = s_.time();
  frame_steps_ = s_.step_count();
}

void MpmSimulation::restore_frame_start() {
  s_.restore(snapshot_);
  s_.restore_clock(frame_time_, frame_steps_);
  begin_frame();
}

void MpmSimulation::begin_frame() {
  // A checkpoint holds particles only: every frame starts from them (a fused substep's grid never
  // crosses a frame's start), so a resumed run computes what the uninterrupted run did.
  s_.unprime();
  frame_sources_ = s_.source_counters();
  if (s_.implicit()) s_.implicit()->reset_counters();
  if (s_.enriched()) s_.enriched()->domains().reset_counters();
}

namespace {
// The physical state's columns (diagnostics.csv and samples.csv share them).
std::vector<Column> state_columns(const MpmDiagnostics& d) {
  return {{"kinetic_J", d.kinetic},      {"elastic_J", d.elastic},
          {"momentum_x", d.momentum[0]}, {"momentum_y", d.momentum[1]},
          {"momentum_z", d.momentum[2]}, {"max_speed_m_s", d.max_speed}};
}
}  // namespace

const SparseGrid* MpmSimulation::grid() const {
  if (!s_.distributed()) return &s_.grid();
  if (!gathered_grid_ || gathered_grid_version_ != s_.state_version()) {
    gathered_grid_ = std::make_unique<SparseGrid>();
    s_.gather_grid(*gathered_grid_);
    gathered_grid_version_ = s_.state_version();
  }
  return gathered_grid_.get();
}

const ParticleSet& MpmSimulation::all_particles() const {
  if (!s_.distributed()) return s_.particles();
  if (gathered_version_ != s_.state_version()) {
    s_.gather_particles(gathered_);
    gathered_version_ = s_.state_version();
  }
  return gathered_;
}

Simulation::RankPart MpmSimulation::my_part() const {
  RankPart r;
  r.order = s_.order_keys();
  return r;
}

std::vector<Column> MpmSimulation::sample(const exec::Space& space) const {
  return state_columns(s_.diagnostics(space));
}

FrameReport MpmSimulation::end_frame(const exec::Space& space, long long substeps) {
  // Distributed: every sum over the ranks, exact (no particle is gathered); the leaf counts' sums
  // are the single process's (owned active leaves: its active leaves).
  const MpmDiagnostics d = s_.diagnostics(space);
  const dist::Comm& comm = dist::Comm::world();
  const bool many = s_.distributed();
  auto over_ranks = [&](std::size_t local) {
    return many ? double(comm.sum(std::uint64_t(local))) : double(local);
  };
  const double particles = over_ranks(s_.particles().size());
  const double sleeping = s_.sleep() ? over_ranks(s_.sleep()->sleeping(s_.particles())) : 0.0;
  const double leaves = over_ranks(s_.grid().leaf_count());
  const double active =
      many ? over_ranks(s_.owned_active_leaves()) : double(s_.grid().active_leaves().size());
  FrameReport r;
  r.columns = state_columns(d);
  r.kinetic = d.kinetic;
  r.max_speed = d.max_speed;
  const ImplicitCounters ic = s_.implicit() ? s_.implicit()->counters() : ImplicitCounters();
  const DomainCounters dc = s_.enriched() ? s_.enriched()->domains().counters() : DomainCounters();
  const double enriched = dc.steps ? dc.enriched_fraction_sum / double(dc.steps) : 0.0;
  const double transitional = dc.steps ? dc.transitional_fraction_sum / double(dc.steps) : 0.0;
  if (s_.enriched()) {
    enriched_sum_ += enriched;
    enriched_max_ = std::max(enriched_max_, dc.max_enriched_fraction);
  }
  ++frames_;
  r.columns.insert(
      r.columns.end(),
      {{"particles", particles, true},
       {"leaves", leaves, true},
       {"active_leaves", active, true},
       {"cg_iterations", double(ic.iterations), true},
       {"cg_max_iterations", double(ic.max_iterations), true},
       {"cg_max_residual", ic.max_residual},
       {"cg_unconverged", double(ic.unconverged), true},
       {"enriched_fraction", enriched},
       {"transitional_fraction", transitional},
       {"max_enriched_fraction", dc.max_enriched_fraction},
       {"enriched_corners", double(dc.last_enriched_corners), true},
       {"emitted", double(s_.source_counters().emitted - frame_sources_.emitted), true},
       {"killed", double(s_.source_counters().killed - frame_sources_.killed), true},
       {"sleeping", sleeping, true}});
  if (s_.settings().implicit) {
    char cg[64];
    std::snprintf(cg, sizeof cg, "CG %.1f it/step",
                  double(ic.iterations) / double(std::max(1LL, substeps)));
    r.progress = cg;
  }
  if (ic.unconverged > 0) {
    std::ostringstream w;
    w << ic.unconverged
      << " implicit solve(s) stopped at max_iterations = " << s_.settings().solver.max_iterations
      << " (worst relative residual " << ic.max_residual
      << "); raise simulation.implicit.max_iterations or lower max_dt";
    r.warnings.push_back(w.str());
  }
  return r;
}

std::vector<std::string> MpmSimulation::profile_columns() const {
  return {"p2g_s", "g2p_s", "sort_s", "grid_s", "solve_s"};
}

int MpmSimulation::profile_column(const std::string& l) const {
  auto starts = [&l](const char* p) { return l.rfind(p, 0) == 0; };
  // Particle domains: particle -> corner -> grid is the P2G side, grid -> corner -> particle (with
  // the corner collisions and the advection) the G2P side.
  if (l == "mpm.p2g" || l == "mpm.g2p2g_flush" || l == "domain.p2c" ||
      l == "domain.points_to_grid" || l == "domain.stress")
    return 0;
  if (l == "mpm.g2p" || l == "mpm.g2p2g" || l == "domain.grid_to_corners" || l == "domain.c2p" ||
      l == "domain.collide_corners" || starts("domain.advect"))
    return 1;
  if (starts("bin.") || l == "particles.permute") return 2;
  if (starts("grid.") || l == "mpm.grid_clear" || l == "mpm.grid_update") return 3;
  if (starts("implicit.")) return 4;
  return -1;
}

std::string MpmSimulation::substep_log_name() const {
  return s_.settings().implicit ? "implicit_steps.csv" : "";
}
std::string MpmSimulation::substep_log_header() const {
  return "frame,step,time_s,dt_s,iterations,relative_residual,converged,minres\n";
}
std::string MpmSimulation::substep_log_row(int frame, Real dt) const {
  const SolveStats& ls = s_.implicit()->last_solve();
  char row[160];
  std::snprintf(row, sizeof row, "%d,%llu,%.9g,%.9g,%d,%.4g,%d,%d\n", frame,
                (unsigned long long)(s_.step_count() - 1), s_.time(), double(dt), ls.iterations,
                ls.residual, ls.converged ? 1 : 0, ls.used_minres ? 1 : 0);
  return row;
}

std::string MpmSimulation::run_summary(double wall) const {
  std::ostringstream os;
  os << s_.distributed_summary();  // collective
  // A-ULMPM: configuration resets per object and the time they (and the re-binning they force)
  // took, against the whole run.
  const MpmAul* aul = s_.aul();
  for (int k = 0; aul && k < aul->maps().object_count(); ++k) {
    const ConfigurationMaps& maps = aul->maps();
    const ConfigurationStats& st = maps.stats(k);
    os << "amalgam: object " << k << " (" << configuration_update_name(maps.policy(k).update)
       << "): " << st.updates << " configuration updates in " << st.steps << " substeps, "
       << st.update_seconds << " s updating + " << st.check_seconds << " s checking the criterion ("
       << 100.0 * (st.update_seconds + st.check_seconds) / wall << " % of the run)\n";
  }
  if (s_.enriched())
    os << "amalgam: particle domains: " << s_.enriched()->domains().corner_count()
       << " corners; enriched particles " << 100.0 * enriched_sum_ / double(std::max(1, frames_))
       << " % on average over frames, at most " << 100.0 * enriched_max_ << " % in a substep"
       << (s_.settings().domains.enrichment ? "" : " (enrichment off)") << "\n";
  if (aul && aul->contact_active())
    os << "amalgam: contact between objects ("
       << object_contact_mode_name(s_.settings().contact.mode) << ", friction "
       << s_.settings().contact.friction << "): " << aul->contact_nodes()
       << " reference-node velocity corrections, " << aul->contact_seconds() << " s ("
       << 100.0 * aul->contact_seconds() / wall << " % of the run)\n";
  return os.str();
}

bool MpmSimulation::surface(SurfaceMesh& out) const {
  // Enriched MPM: the meshes embedded in the particle domains, deformed (Sec. 4.1).
  const MpmEnriched* e = s_.enriched();
  if (!e || !e->domains().has_surface()) return false;
  e->domains().surface(s_.particles().int32(e->attributes().corners), out.vertices, out.triangles);
  // Per-vertex velocity: the velocity of the particle whose domain embeds the vertex (particles
  // are checkpointed, so a resumed run writes the same; the corners' velocities are not).
  e->domains().surface_velocity(s_.particles().vec3(s_.attributes().v), out.velocity);
  out.normals.clear();
  out.crack.clear();
  return true;
}

// Enriched MPM: the particle-domain corners' positions (the rest of the corner state is rebuilt
// every substep from the particles).
// Emitters and kill regions: the next particle id and the emitted and killed counts (emission
// itself is a function of the clock).
std::vector<StateSection> MpmSimulation::checkpoint_sections() {
  source_state_[0] = s_.next_id();
  source_state_[1] = s_.source_counters().emitted;
  source_state_[2] = s_.source_counters().killed;
  return restore_sections();
}

std::vector<StateSection> MpmSimulation::restore_sections() {
  std::vector<StateSection> out;
  if (variable_particle_count())
    out.push_back({"sources.state", reinterpret_cast<char*>(source_state_), sizeof source_state_});
  if (MpmEnriched* e = s_.enriched())
    out.push_back({"domains.corner_x", reinterpret_cast<char*>(e->domains().corner_positions()),
                   e->domains().corner_count() * sizeof(Vec3)});
  return out;
}

Simulation::Slice MpmSimulation::checkpoint_slice() const {
  const dist::Comm& comm = dist::Comm::world();
  return s_.sliced() ? Slice{comm.rank(), comm.size()} : Slice{};
}

void MpmSimulation::before_restore() {
  if (!s_.sliced()) return;
  s_.particles().resize(std::size_t(s_.next_id()));
  s_.set_sliced(false);  // the checkpoint fills every particle
}

void MpmSimulation::restoring_slice(std::vector<std::uint64_t> keys, std::uint64_t total) {
  s_.set_slice_keys(std::move(keys));
  slice_total_ = std::int64_t(total);
}

// A per-rank checkpoint read in slices: the ids of this rank's rows are distinct and in range,
// the slices' counts add up to the checkpoint's, and (every particle kept from the set-up) the
// ids' sum and sum of squares over the ranks are those of 0 .. n - 1, which a duplicate across
// ranks would change. Collective.
void MpmSimulation::check_slice_ids(std::int64_t limit) const {
  const dist::Comm& comm = dist::Comm::world();
  const ParticleSet& ps = s_.particles();
  check_unique_attribute(ps, "id", limit);
  if (comm.sum(std::uint64_t(ps.size())) != std::uint64_t(slice_total_))
    throw InputError("the checkpoint's parts hold " +
                     std::to_string(comm.sum(std::uint64_t(ps.size()))) +
                     " particles, its manifest says " + std::to_string(slice_total_));
  if (variable_particle_count()) return;
  const std::int32_t* id = ps.int32(s_.attributes().id);
  std::uint64_t sum = 0, squares = 0;
  for (std::size_t i = 0; i < ps.size(); ++i)
    sum += std::uint64_t(id[i]), squares += std::uint64_t(id[i]) * std::uint64_t(id[i]);
  const std::uint64_t n = std::uint64_t(slice_total_);
  // 0 + 1 + ... + (n - 1) and 0 + 1 + ... + (n - 1)^2, modulo 2^64 as the sums above.
  const std::uint64_t a = n % 2 == 0 ? (n / 2) * (n - 1) : n * ((n - 1) / 2);
  // n (n - 1) (2n - 1) / 6: one factor divided by 2 and one by 3 first (exact), then modulo 2^64.
  std::uint64_t f[3] = {n, n - 1, 2 * n - 1};
  for (std::uint64_t d : {2u, 3u})
    for (std::uint64_t& x : f)
      if (x % d == 0) {
        x /= d;
        break;
      }
  const std::uint64_t b = f[0] * f[1] * f[2];
  if (comm.sum(sum) != a || comm.sum(squares) != b)
    throw InputError("attribute 'id' repeats across the checkpoint's parts");
}

// What a checkpoint gave the particles is checked before a kernel indexes with it (a material
// index out of range would read past the material table).
void MpmSimulation::restored(double time, std::uint64_t steps) {
  const ParticleSet& ps = s_.particles();
  check_finite_attributes(ps);
  check_index_attribute(ps, "material", 0, std::int64_t(s_.materials().size()) - 1);
  const bool slice = slice_total_ >= 0;
  if (slice && !variable_particle_count()) {
    check_slice_ids(std::int64_t(s_.next_id()));
  } else if (variable_particle_count()) {
    const std::int64_t next = source_state_[0], emitted = source_state_[1],
                       killed = source_state_[2];
    const std::int64_t least = slice ? slice_total_ : std::int64_t(ps.size());
    if (next < least || next > std::int64_t(INT32_MAX))
      throw InputError("section sources.state: next particle id " + std::to_string(next) +
                       " is outside [" + std::to_string(least) + ", 2^31 - 1]");
    const std::int64_t count = slice ? slice_total_ : std::int64_t(ps.size());
    if (emitted < 0 || emitted > emitted_bound_ || killed < 0 || killed > next ||
        next != initial_particles_ + emitted || count != next - killed)
      throw InputError("section sources.state: emitted " + std::to_string(emitted) +
                       " and killed " + std::to_string(killed) + " particles disagree with " +
                       std::to_string(count) + " particles and next id " + std::to_string(next));
    if (slice)
      check_slice_ids(next);
    else
      check_unique_attribute(ps, "id", next);
    s_.restore_sources(next, SourceCounters{emitted, killed});
  } else {
    check_permutation_attribute(ps, "id");
  }
  check_index_attribute(ps, "asleep", 0, 1);
  check_low_part(ps, "x", "x_lo");
  check_low_part(ps, "F", "F_lo");
  check_positive_definite(ps, "b");
  if (const MpmAul* a = s_.aul())
    check_index_attribute(ps, "object", 0, a->maps().object_count() - 1);
  if (const MpmEnriched* e = s_.enriched()) {
    check_index_attribute(ps, "domain_corners", -1, std::int64_t(e->domains().corner_count()) - 1);
    check_index_attribute(ps, "domain_state", kDomainDisabled, kEnriched);
    const Vec3* c = e->domains().corner_positions();
    for (std::size_t k = 0; k < e->domains().corner_count(); ++k)
      if (!c[k].allFinite())
        throw InputError("section domains.corner_x: corner " + std::to_string(k) +
                         " is not finite");
  }
  slice_total_ = -1;
  s_.restore_clock(time, steps);
}

}  // namespace amalgam
