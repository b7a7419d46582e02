#include "solvers/pd_simulation.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

#include "core/dist/comm.hpp"
#include "core/errors.hpp"

namespace amalgam {

PdSimulation::PdSimulation(PdSolver solver, const exec::Space& space) : s_(std::move(solver)) {
  const PdDiagnostics d = s_.diagnostics(space);
  const std::size_t np = s_.global_particle_count();
  std::ostringstream os;
  os << "peridynamics, " << np << " particles, " << d.bonds << " directed bonds ("
     << double(d.bonds) / double(std::max<std::size_t>(1, np)) << " per particle), spacing "
     << s_.settings().spacing << " m, horizon " << s_.settings().horizon << " m, model "
     << pd_model_name(s_.settings().model) << ", deviatoric "
     << pd_deviatoric_name(s_.settings().deviatoric) << ", fracture "
     << (s_.settings().fracture ? pd_criterion_name(s_.settings().criterion) : "off")
     << ", stable dt " << s_.stable_dt(space) << " s";
  description_ = os.str();
}

namespace {
std::vector<Column> state_columns(const PdDiagnostics& d) {
  return {{"kinetic_J", d.kinetic},         {"momentum_x", d.momentum[0]},
          {"momentum_y", d.momentum[1]},    {"momentum_z", d.momentum[2]},
          {"max_speed_m_s", d.max_speed},   {"max_damage", d.max_damage},
          {"bonds", double(d.bonds), true}, {"intact_bonds", double(d.intact), true}};
}
}  // namespace

const ParticleSet& PdSimulation::all_particles() const {
  if (!s_.distributed()) return s_.particles();
  if (gathered_version_ != s_.state_version()) {
    s_.gather_particles(gathered_);
    gathered_version_ = s_.state_version();
  }
  return gathered_;
}

std::vector<Column> PdSimulation::sample(const exec::Space& space) const {
  return state_columns(s_.diagnostics(space));
}

FrameReport PdSimulation::end_frame(const exec::Space& space, long long) {
  const PdDiagnostics d = s_.diagnostics(space);
  if (s_.distributed()) {
    const PdSolver::CrossRank c = s_.cross_rank();
    cross_broken_ = std::max(cross_broken_, s_.global_sum(c.broken));
    cross_contacts_ = std::max(cross_contacts_, s_.global_sum(c.contacts));
  }
  FrameReport r;
  r.kinetic = d.kinetic;
  r.max_speed = d.max_speed;
  r.columns = state_columns(d);
  r.columns.insert(r.columns.end(), {{"stored_bonds", double(d.stored), true},
                                     {"particles", double(s_.global_particle_count()), true}});
  char line[64];
  std::snprintf(line, sizeof line, "broken %.2f%%",
                100.0 * double(d.bonds - d.intact) / double(std::max<std::uint64_t>(1, d.bonds)));
  r.progress = line;
  return r;
}

// The dilatation (with plasticity), force (with fracture) and contact passes.
std::vector<std::string> PdSimulation::profile_columns() const {
  return {"dilatation_s", "force_s", "contact_s"};
}
int PdSimulation::profile_column(const std::string& l) const {
  if (l == "pd.dilatation") return 0;
  if (l.rfind("pd.forces", 0) == 0) return 1;  // with pd.forces_rows
  if (l.rfind("pd.contact", 0) == 0 || l == "pd.cell_keys") return 2;
  return -1;
}

std::string PdSimulation::run_summary(double) const {
  std::ostringstream os;
  os << "amalgam: bonds: " << s_.global_sum(s_.bonds().size())
     << " directed bonds stored at the end, " << s_.compactions() << " compactions\n";
  if (s_.distributed()) {  // this rank's (rank 0's) figures
    const PdSolver::DistStats& st = s_.dist_stats();
    os << "amalgam: distributed: rank 0 holds " << st.owned << " own particles and " << st.ghosts
       << " ghosts; " << st.reghosts << " re-ghosts, " << st.repartitions
       << " repartitions, imbalance " << st.imbalance << "; last step's halo " << st.step_bytes
       << " bytes in " << st.step_messages << " messages; " << st.comm_seconds
       << " s in exchanges; at most " << cross_broken_
       << " directed bonds broken between ranks and " << cross_contacts_
       << " contacts with another rank's particles at a frame's end\n";
    // The set-up's bond rows over every rank: each particle's row once (its owner's), plus the
    // rows of the families' first members owned by another rank (initialize_distributed), and
    // the surface correction's families, each fitted on one rank.
    const dist::Comm& comm = dist::Comm::world();
    os << "amalgam: distributed set-up: " << s_.global_sum(st.rows_built)
       << " bond rows built over the ranks for " << s_.global_particle_count() << " particles ("
       << s_.global_sum(st.family_rows) << " of them families' first members owned elsewhere, "
       << "at most " << comm.max(std::int64_t(st.rows_built)) << " on a rank); "
       << s_.global_sum(st.families_fitted) << " families fitted over the ranks, at most "
       << comm.max(std::int64_t(st.families_fitted)) << " on a rank; " << comm.max(st.setup_seconds)
       << " s at most per rank\n";
  }
  return os.str();
}

namespace {
// Von Mises equivalent of a stress: sqrt(3/2 s:s), s its deviator.
float von_mises(const Mat3& sigma) {
  const Mat3d d = sigma.cast<double>();
  const Mat3d s = d - (d.trace() / 3.0) * Mat3d::Identity();
  return float(std::sqrt(1.5 * s.cwiseProduct(s).sum()));
}
}  // namespace

PointFields PdSimulation::point_fields(const std::vector<std::string>& names,
                                       const exec::Space& space) {
  return fields_of(all_particles(), names, space, s_.distributed());  // collective when distributed
}

// Per-rank output: this rank's local particles (own and ghosts; my_part names the own rows).
PointFields PdSimulation::my_point_fields(const std::vector<std::string>& names,
                                          const exec::Space& space) {
  if (!s_.distributed()) return point_fields(names, space);
  return fields_of(s_.particles(), names, space, false);
}

// The point fields of `ps`: the solver's local particles, or (gathered) every rank's own ones on
// rank 0, whose per-particle stresses are then gathered too.
PointFields PdSimulation::fields_of(const ParticleSet& ps, const std::vector<std::string>& names,
                                    const exec::Space& space, bool gathered) {
  using T = PointAttribute::Type;
  const PdAttributes& a = s_.attributes();
  PointFields p;
  p.n = ps.size();
  p.x = ps.vec3(a.x);
  p.v = ps.vec3(a.v);
  p.material = ps.int32(a.material);
  p.id = ps.int32(a.id);
  for (const std::string& name : names) {
    PointAttribute out{name, T::Float, {}, {}};
    if (name == "damage" || name == "theta") {
      const Real* r = ps.real(name == "damage" ? a.damage : a.theta);
      out.f.assign(r, r + p.n);
    } else if (name == "rest") {
      out.type = T::Vec3;
      const Real* r = ps.real(a.x0);
      out.f.assign(r, r + 3 * p.n);
    } else if (name == "material") {
      out.type = T::Int;
      out.i.assign(p.material, p.material + p.n);
    } else if (name == "vonmises") {
      s_.compute_stress(space, stress_);  // sigma_i = 1/2 sum_j f_ij (x) xi_ij V_j
      if (gathered) stress_ = dist::from_bytes<Mat3>(s_.gather_owned(stress_.data(), sizeof(Mat3)));
      out.f.resize(p.n);
      for (std::size_t i = 0; i < p.n; ++i) out.f[i] = von_mises(stress_[i]);
    } else {
      throw std::logic_error("peridynamic particles have no attribute " + name);
    }
    p.attributes.push_back(std::move(out));
  }
  return p;
}

bool PdSimulation::surface(SurfaceMesh& out) const {
  if (s_.crack_meshes().empty()) return false;
  out = SurfaceMesh();
  std::vector<Vec3> verts;
  std::vector<std::array<std::uint32_t, 3>> tris;
  std::vector<std::uint8_t> crack;
  std::vector<double> weight;
  std::vector<Vec3d> vertex_v;
  std::vector<Vec3> vel;
  const ParticleSet& ps = s_.particles();
  const PdAttributes& a = s_.attributes();
  for (const PdCrackMesh& m : s_.crack_meshes()) {  // one surface file for all meshes
    // Per-vertex velocity: the motion move_vertices gives the vertex (eqs. 19, 20).
    m.vertex_velocities(ps.vec3(a.v), ps.real(a.volume), ps.int32(a.material),
                        s_.materials().data(), weight, vertex_v);
    m.surface(verts, tris, crack, &vertex_v, &vel);
    const auto base = std::uint32_t(out.vertices.size());
    out.vertices.insert(out.vertices.end(), verts.begin(), verts.end());
    out.velocity.insert(out.velocity.end(), vel.begin(), vel.end());
    for (auto t : tris) out.triangles.push_back({t[0] + base, t[1] + base, t[2] + base});
    out.crack.insert(out.crack.end(), crack.begin(), crack.end());
  }
  return true;
}

namespace {
// The embedded meshes' state arrays (vertex positions, split tetrahedra, crack faces).
void add_mesh_sections(PdSolver& s, std::vector<StateSection>& out) {
  for (std::size_t k = 0; k < s.crack_meshes().size(); ++k)
    for (const auto& a : s.crack_meshes()[k].state())
      out.push_back({"crack_mesh" + std::to_string(k) + "." + a.name, a.data, a.bytes});
}
// Where a variable-size section of T goes: `v` resized to the file's bytes (a whole number of T).
template <class T>
std::function<char*(std::uint64_t)> resize_into(std::vector<T>& v, const char* name) {
  return [&v, name](std::uint64_t bytes) {
    if (bytes % sizeof(T) != 0)
      throw InputError(std::string("checkpoint section '") + name + "' has " +
                       std::to_string(bytes) +
                       " bytes, not a whole number of entries (corrupt file)");
    v.resize(std::size_t(bytes / sizeof(T)));
    return reinterpret_cast<char*>(v.data());
  };
}
}  // namespace

// The bond layout (rows may have been compacted) and the per-bond state, then the embedded
// meshes; the per-bond constants are rebuilt from the reference positions on restore.
void PdSimulation::prepare_checkpoint() {
  if (!s_.distributed()) return;
  (void)all_particles();
  s_.gather_bonds(offsets_, neighbor_, plastic_, intact_);
}

std::vector<StateSection> PdSimulation::checkpoint_sections() {
  PdBonds& m = s_.bonds();
  const bool gathered = s_.distributed();  // rank 0 writes the rows prepare_checkpoint gathered
  std::vector<std::uint64_t>& off = gathered ? offsets_ : m.offsets;
  std::vector<std::uint32_t>& nb = gathered ? neighbor_ : m.neighbor;
  std::vector<Real>& pl = gathered ? plastic_ : m.plastic;
  std::vector<std::uint8_t>& in = gathered ? intact_ : m.intact;
  std::vector<StateSection> out = {
      {"bonds.offsets", reinterpret_cast<char*>(off.data()), off.size() * sizeof(std::uint64_t)},
      {"bonds.neighbor", reinterpret_cast<char*>(nb.data()), nb.size() * sizeof(std::uint32_t)},
      {"bonds.plastic", reinterpret_cast<char*>(pl.data()), pl.size() * sizeof(Real)},
      {"bonds.intact", reinterpret_cast<char*>(in.data()), in.size()}};
  add_mesh_sections(s_, out);
  return out;
}

void PdSimulation::before_restore() {
  if (!s_.distributed()) return;
  // Distributed since the set-up: the checkpoint is read whole here (every particle, every row),
  // then restored() keeps this rank's local particles and own rows.
  const ParticleSet& ps = s_.particles();
  gathered_ = ParticleSet();
  for (int a = 0; a < ps.attribute_count(); ++a) gathered_.add(ps.name(a), ps.type(a), ps.width(a));
  gathered_.resize(s_.global_particle_count());
  gathered_version_ = ~std::uint64_t(0);
}

std::vector<StateSection> PdSimulation::restore_sections() {
  offsets_.assign(s_.distributed() ? s_.global_particle_count() + 1 : s_.bonds().offsets.size(), 0);
  const std::size_t nb = s_.bonds().size();
  std::vector<StateSection> out = {
      {"bonds.offsets", reinterpret_cast<char*>(offsets_.data()),
       offsets_.size() * sizeof(std::uint64_t)},
      {"bonds.neighbor", nullptr, nb * sizeof(std::uint32_t),
       resize_into(neighbor_, "bonds.neighbor")},
      {"bonds.plastic", nullptr, nb * sizeof(Real), resize_into(plastic_, "bonds.plastic")},
      {"bonds.intact", nullptr, nb, resize_into(intact_, "bonds.intact")}};
  add_mesh_sections(s_, out);
  return out;
}

// Distributed: the own particles among the local ones, keyed by global id (the single process's
// order: one process holds the particles by global id).
Simulation::RankPart PdSimulation::my_part() const {
  if (!s_.distributed()) return Simulation::my_part();
  RankPart r;
  r.all = false;
  r.rows = s_.owned_local();
  const std::vector<std::uint64_t> gid = s_.global_ids();
  for (std::uint32_t i : r.rows) r.order.insert(r.order.end(), {gid[i], 0});
  return r;
}

void PdSimulation::restored(double time, std::uint64_t steps) {
  const ParticleSet& ps = s_.distributed() ? gathered_ : s_.particles();
  check_finite_attributes(ps);
  check_index_attribute(ps, "material", 0, std::int64_t(s_.materials().size()) - 1);
  check_permutation_attribute(ps, "id");
  check_low_part(ps, "x", "x_lo");
  check_index_attribute(ps, "fixed", 0, 1);
  if (plastic_.size() != neighbor_.size() || intact_.size() != neighbor_.size())
    throw InputError("checkpoint's bond sections disagree in length (" +
                     std::to_string(neighbor_.size()) + " neighbours, " +
                     std::to_string(plastic_.size()) + " plastic extensions, " +
                     std::to_string(intact_.size()) + " flags)");
  if (s_.distributed() ? !s_.restore_distributed(exec::Space(), gathered_, offsets_, neighbor_,
                                                 plastic_, intact_)
                       : !s_.restore_bonds(offsets_, neighbor_, plastic_, intact_))
    throw InputError(
        "checkpoint's bond list is not a subset of this scene's bonds (written for other "
        "particles or another horizon?)");
  for (PdCrackMesh& m : s_.crack_meshes()) m.restored();
  s_.restore_clock(time, steps);
  if (s_.distributed()) gathered_version_ = ~std::uint64_t(0);  // regathered when asked
  offsets_ = {};
  neighbor_ = {};
  plastic_ = {};
  intact_ = {};
}

}  // namespace amalgam
