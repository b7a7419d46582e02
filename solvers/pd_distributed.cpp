// Peridynamics across MPI ranks (issue 28, item 3): PdSolver::distribute and what it needs.
//
// Ownership. Zoltan's RCB cuts the particles' reference positions (each moved by less than a
// tenth of the spacing by a hash of its id, so no lattice plane sits on a cut), weighted by their
// bond rows, and the cuts are kept (dist::RcbCuts): the owner of a particle is the cut box of its
// point, known to every rank without communication.
//
// Set-up (PdSolver::initialize_distributed, what `amalgam run` uses). Every rank holds every
// particle's per-particle data (the scene is set up alike on every rank, about 100 bytes a
// particle) but builds bond rows only for its own particles, plus, per family of the surface
// correction, the row of the family's first member when another rank owns it; the whole list is
// never built (~46 bytes per directed bond, ~120 bonds a particle). distribute() after a whole
// initialize() gives the same bits (tests and one-process callers).
//
// Local particles. A rank holds its own particles and ghosts: the bond neighbours of its rows
// (reference configuration: the ranks whose cut boxes meet the horizon box of a particle,
// Zoltan_LB_Box_Assign, receive it and keep it when one of their rows names it) and the
// particles within contact reach (current configuration: within distance + skin of the bounding
// box of the rank's own particles). Local particles are ordered by global id, so a row's
// neighbours, renumbered to local indices, stay sorted; rows are copied whole (every per-bond
// array, lanes included), so a row sums the same terms in the same lanes in the same order as on
// one process: bitwise.
//
// Per step (PdSolver::step): the owners' positions into the ghosts before the dilatation, the
// dilatation and consistent term before the force pass, the damage after it (the next force
// pass's critical stretch); point to point between the ranks that share ghosts (HaloPlan). Bond
// breaking is decided in both rows from bitwise-identical inputs (eta and e of the bond, each
// end's critical stretch), so it stays symmetric across ranks and the damage is the same.
//
// Contact and re-ghosting. When some particle has moved more than skin / 2 since the contact list
// was built (an exact maximum over the ranks), the ghosts are chosen anew from the current
// positions and the list is rebuilt. The contact force of a particle sums the pairs closer than
// the contact distance in neighbour order, which any valid Verlet list gives alike, so the
// rebuild's timing changes no bit.
//
// Repartition. At a re-ghost, when the bond and contact work per rank is imbalanced (max / mean
// above 1.25, at most every 16 steps) or AMALGAM_TEST_REPARTITION_EVERY=N says so (every N
// steps), the cuts are made anew and the particles migrate with their bond rows.
//
// Output. gather_particles / gather_owned join the own particles on rank 0 in global id order
// (frames, samples, checkpoints; gather_bonds for the checkpoint's bond rows).
#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <optional>
#include <string>
#include <unordered_map>
#include <utility>

#include "core/dist/comm.hpp"
#include "core/dist/halo.hpp"
#include "core/errors.hpp"
#include "solvers/pd_solver.hpp"

namespace amalgam {

struct PdSolver::Ranks {
  dist::RcbCuts cuts;
  std::vector<std::uint64_t> gid;   // per local particle, increasing
  std::vector<std::uint8_t> owned;  // per local particle: 1 on its owner
  std::vector<int> owner;           // per local particle
  std::vector<std::uint32_t> own;   // the own particles' local indices, increasing
  dist::HaloPlan halo;
  // Plastic materials: the far ends' plastic extensions of the bonds whose far end is a ghost
  // (plastic_r), from the rank that owns that row; bond (i, j) known by the id i N + j.
  dist::HaloPlan bond_halo;
  std::uint64_t n_global = 0;
  std::uint64_t last_cut_step = 0;
};

namespace {

constexpr double kImbalance = 1.25;
constexpr const char* kMeshesNotDistributed =
    "peridynamics on several MPI ranks: embedded tet_mesh crack surfaces are not distributed yet "
    "(issue 28); run one rank";
constexpr std::uint64_t kRepartitionGap = 16;

// The point a particle is owned by: its reference position moved by less than 0.1 spacing along
// each axis by a hash of its id (splitmix64), so that lattice planes do not lie on cuts.
void own_point(const Vec3& x0, std::uint64_t id, Real spacing, double* p) {
  std::uint64_t h = id + 0x9e3779b97f4a7c15ULL;
  h = (h ^ (h >> 30)) * 0xbf58476d1ce4e5b9ULL;
  h = (h ^ (h >> 27)) * 0x94d049bb133111ebULL;
  h ^= h >> 31;
  for (int a = 0; a < 3; ++a) {
    const double f = double((h >> (20 * a)) & 0xfffff) / double(1 << 20) - 0.5;  // [-0.5, 0.5)
    p[a] = double(x0[a]) + 0.2 * double(spacing) * f;
  }
}

}  // namespace

// A bond as it migrates: the neighbour by global id, every per-bond array's value.
struct PdSolver::BondRec {
  std::uint64_t nb;
  Real L, omega, shear, vol, plastic, omega_r, shear_r, plastic_r;
  std::uint8_t intact, lane;
};

// One local particle as the rebuild sees it: its id, owner, record (particle attributes,
// constants, q) and, for an own particle, its row.
struct PdSolver::LocalEntry {
  std::uint64_t gid;
  int owner;
  const char* rec;
  const BondRec* row;  // null: a ghost
  std::uint32_t len;
  std::uint8_t dense;
};

namespace {
template <class T>
void put(std::vector<char>& b, const T& v) {
  const char* p = reinterpret_cast<const char*>(&v);
  b.insert(b.end(), p, p + sizeof(T));
}
template <class T>
T get(const char*& p) {
  T v;
  std::memcpy(&v, p, sizeof(T));
  p += sizeof(T);
  return v;
}

}  // namespace

// --- Particle records: every attribute's words, the constants m, a, b, kappa, bonds0, fitted,
// and q.
namespace {
struct RecordLayout {
  std::vector<std::size_t> attr_offset;  // bytes into the record, per attribute
  std::size_t constants = 0, bytes = 0;
};
RecordLayout record_layout(const ParticleSet& ps) {
  RecordLayout L;
  std::size_t o = 0;
  for (int a = 0; a < ps.attribute_count(); ++a) {
    L.attr_offset.push_back(o);
    o += std::size_t(ps.words_per_particle(a)) * 4;
  }
  L.constants = o;
  L.bytes = o + 5 * sizeof(Real) + sizeof(std::int32_t) + 1;
  return L;
}
}  // namespace

// Particle i's record (every attribute's words, the constants, q) appended to b.
void PdSolver::pack_record(std::vector<char>& b, std::size_t i) const {
  for (int a = 0; a < particles_.attribute_count(); ++a) {
    const std::size_t wa = std::size_t(particles_.words_per_particle(a));
    const char* src = reinterpret_cast<const char*>(particles_.words(a) + i * wa);
    b.insert(b.end(), src, src + wa * 4);
  }
  put(b, constants_.m[i]), put(b, constants_.a[i]), put(b, constants_.b[i]);
  put(b, constants_.kappa[i]), put(b, q_[i]), put(b, constants_.bonds0[i]);
  put(b, constants_.fitted[i]);
}

// Bond k with its neighbour named by global id.
PdSolver::BondRec PdSolver::bond_record(std::uint64_t k, std::uint64_t neighbour_gid) const {
  BondRec br{};
  br.nb = neighbour_gid;
  br.L = bonds_.length[k], br.omega = bonds_.omega[k], br.shear = bonds_.shear_omega[k];
  br.vol = bonds_.volume[k], br.plastic = bonds_.plastic[k];
  br.omega_r = bonds_.omega_r[k], br.shear_r = bonds_.shear_omega_r[k];
  br.plastic_r = bonds_.plastic_r[k];
  br.intact = bonds_.intact[k], br.lane = bonds_.lane[k];
  return br;
}

// How far from a rank's own particles contact ghosts are kept: the contact distance plus the
// Verlet skin (default half a spacing), 1 % over.
double PdSolver::contact_reach() const {
  return 1.01 *
         double(contact_distance() + (settings_.contact_skin > 0 ? settings_.contact_skin
                                                                 : Real(0.5) * settings_.spacing));
}

// With contact on, marks in `keep` the particles within contact_reach() of the box [lo, hi].
void PdSolver::keep_within_contact_reach(const Vec3* x, std::size_t n, const double* lo,
                                         const double* hi, std::vector<std::uint8_t>& keep) const {
  if (!settings_.contact) return;
  const double reach = contact_reach();
  for (std::size_t i = 0; i < n; ++i) {
    bool in = true;
    for (int a = 0; a < 3; ++a)
      in &= double(x[i][a]) >= lo[a] - reach && double(x[i][a]) <= hi[a] + reach;
    keep[i] |= in;
  }
}

void PdSolver::distribute(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  if (comm.size() == 1 || ranks_) return;
  if (!initialized_) throw std::logic_error("PdSolver: distribute() before initialize()");
  if (!meshes_.empty()) throw InputError(kMeshesNotDistributed);
  // Every rank holds the whole state here (each set the scene up alike): it passes Zoltan a slice
  // of the particles, weighted by their bond rows, and then takes its own particles and their
  // ghosts from the whole state.
  const std::size_t n = particles_.size();
  const std::uint64_t r = std::uint64_t(comm.rank()), R = std::uint64_t(comm.size());
  const std::uint64_t b = n * r / R, e = n * (r + 1) / R;
  const Vec3* x0 = particles_.vec3(attr_.x0);
  const Vec3* x = particles_.vec3(attr_.x);
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  std::vector<float> w;
  for (std::uint64_t i = b; i < e; ++i) {
    double p[3];
    own_point(x0[i], i, settings_.spacing, p);
    ids.push_back(i);
    xyz.insert(xyz.end(), p, p + 3);
    w.push_back(float(1 + bonds_.offsets[i + 1] - bonds_.offsets[i]));
  }
  auto ranks = std::make_shared<Ranks>();
  ranks->cuts = dist::RcbCuts::partition(ids, xyz, w);
  ranks->n_global = n;
  std::vector<int> owner(n);
  for (std::size_t i = 0; i < n; ++i) {
    double p[3];
    own_point(x0[i], i, settings_.spacing, p);
    owner[i] = ranks->cuts.owner(p);
  }
  // Ghosts: the bond neighbours of the own rows, and the particles within contact reach of the
  // own particles' bounding box.
  std::vector<std::uint8_t> keep(n, 0);
  double lo[3] = {1e300, 1e300, 1e300}, hi[3] = {-1e300, -1e300, -1e300};
  for (std::size_t i = 0; i < n; ++i) {
    if (owner[i] != comm.rank()) continue;
    keep[i] = 1;
    for (std::uint64_t k = bonds_.offsets[i]; k < bonds_.offsets[i + 1]; ++k)
      keep[bonds_.neighbor[k]] = 1;
    for (int a = 0; a < 3; ++a)
      lo[a] = std::min(lo[a], double(x[i][a])), hi[a] = std::max(hi[a], double(x[i][a]));
  }
  keep_within_contact_reach(x, n, lo, hi, keep);
  // Records of the kept particles from the whole state, then the local state from them.
  if (constants_.fitted.empty()) constants_.fitted.assign(n, 0);
  std::vector<char> recs;
  std::vector<BondRec> rows;
  std::vector<LocalEntry> entries;
  std::vector<std::size_t> rec_at, row_at;
  for (std::size_t i = 0; i < n; ++i) {
    if (!keep[i]) continue;
    rec_at.push_back(recs.size());
    pack_record(recs, i);
    row_at.push_back(rows.size());
    const bool own = owner[i] == comm.rank();
    if (own)
      for (std::uint64_t k = bonds_.offsets[i]; k < bonds_.offsets[i + 1]; ++k)
        rows.push_back(bond_record(k, bonds_.neighbor[k]));
    entries.push_back({i, owner[i], nullptr, nullptr,
                       own ? std::uint32_t(bonds_.offsets[i + 1] - bonds_.offsets[i]) : 0,
                       own ? bonds_.dense[i] : std::uint8_t(1)});
  }
  for (std::size_t k = 0; k < entries.size(); ++k) {
    entries[k].rec = recs.data() + rec_at[k];
    entries[k].row = entries[k].owner == comm.rank() ? rows.data() + row_at[k] : nullptr;
  }
  // Compaction changes no result (broken bonds add exact zeros in their lanes) but rebuilds the
  // reverse indices, which need the other ranks' rows: off when distributed.
  settings_.compact_fraction = 0;
  assemble_local(space, entries, ranks);
  build_contact_list(space);
}

namespace {
// Rows of b appended to a (both built by pd_build_bond_rows: no mirrored arrays yet).
void append_rows(PdBonds& a, const PdBonds& b) {
  const std::uint64_t base = a.offsets.empty() ? 0 : a.offsets.back();
  if (a.offsets.empty()) a.offsets.push_back(0);
  for (std::size_t q = 1; q < b.offsets.size(); ++q) a.offsets.push_back(base + b.offsets[q]);
  auto cat = [](auto& to, const auto& from) { to.insert(to.end(), from.begin(), from.end()); };
  cat(a.neighbor, b.neighbor), cat(a.reverse, b.reverse), cat(a.length, b.length);
  cat(a.omega, b.omega), cat(a.volume, b.volume), cat(a.plastic, b.plastic);
  cat(a.intact, b.intact), cat(a.lane, b.lane), cat(a.dense, b.dense);
}

// Who fits which family of the surface correction (pd_constants) in a distributed set-up. A
// family (hash key) is held by the ranks with an own row in it; its first member (the lowest
// global id) gives the fit. Every family is fitted once over the ranks, preferably by one of its
// holders: in key order, by the least loaded holder while that one is under the mean load, else
// (deferred, in key order) by the least loaded rank, which builds the first member's row for it
// (every rank holds every particle during set-up). Families are far from evenly spread over the
// owners: on the peer block float round-off in the bond vectors makes 36,377 families, 27,216 of
// them held by the rank of the lower x alone. The fitter sends the fit to the other holders.
// Every rank computes the same plan from the same gathered list.
struct FamilyPlan {
  // Rows built besides the own ones, increasing: the first members owned elsewhere of the
  // families held here, and of the families fitted here for others; and their families' keys.
  std::vector<std::uint32_t> extra;
  std::vector<std::uint64_t> extra_keys;
  // First members of the families held here that another rank fits -> that rank.
  std::unordered_map<std::uint32_t, int> given;
  // First members of the families fitted here that other ranks hold, increasing, and those ranks.
  std::vector<std::pair<std::uint32_t, std::vector<int>>> serve;
};

FamilyPlan family_plan(const dist::Comm& comm, const std::vector<std::uint32_t>& own,
                       const std::vector<std::uint64_t>& own_key) {
  std::unordered_map<std::uint64_t, std::uint64_t> first_own;  // key -> first own id
  for (std::size_t q = 0; q < own.size(); ++q) first_own.emplace(own_key[q], own[q]);
  std::vector<std::uint64_t> mine;
  for (const auto& [k, id] : first_own) mine.insert(mine.end(), {k, id});
  std::vector<std::size_t> sizes;
  const std::vector<std::uint64_t> all =
      dist::from_bytes<std::uint64_t>(comm.allgather(dist::as_bytes(mine), &sizes));
  struct Entry {
    std::uint64_t key, id;
    int rank;
  };
  std::vector<Entry> e;
  e.reserve(all.size() / 2);
  std::size_t at = 0;
  for (int r = 0; r < comm.size(); ++r)
    for (std::size_t k = 0; k < sizes[std::size_t(r)] / (2 * sizeof(std::uint64_t)); ++k, at += 2)
      e.push_back({all[at], all[at + 1], r});
  std::sort(e.begin(), e.end(), [](const Entry& a, const Entry& b) {
    return a.key != b.key ? a.key < b.key : a.rank < b.rank;
  });
  std::vector<std::pair<std::size_t, std::size_t>> fam;  // [begin, end) of e per family
  for (std::size_t b = 0, f; b < e.size(); b = f) {
    for (f = b + 1; f < e.size() && e[f].key == e[b].key;) ++f;
    fam.emplace_back(b, f);
  }
  const std::size_t R = std::size_t(comm.size());
  const std::uint64_t mean = (fam.size() + R - 1) / R;
  std::vector<std::uint64_t> load(R, 0);
  std::vector<int> fitter(fam.size(), -1);
  for (std::size_t g = 0; g < fam.size(); ++g) {
    int best = -1;
    for (std::size_t k = fam[g].first; k < fam[g].second; ++k)
      if (best < 0 || load[std::size_t(e[k].rank)] < load[std::size_t(best)]) best = e[k].rank;
    if (load[std::size_t(best)] < mean) fitter[g] = best, ++load[std::size_t(best)];
  }
  for (std::size_t g = 0; g < fam.size(); ++g) {
    if (fitter[g] >= 0) continue;
    const std::size_t r = std::size_t(std::min_element(load.begin(), load.end()) - load.begin());
    fitter[g] = int(r), ++load[r];
  }
  FamilyPlan plan;
  const int me = comm.rank();
  std::vector<std::pair<std::uint32_t, std::uint64_t>> extra;  // (first member, key)
  for (std::size_t g = 0; g < fam.size(); ++g) {
    const auto [b, f] = fam[g];
    std::uint64_t lowest = e[b].id;
    bool held = false;
    for (std::size_t k = b; k < f; ++k)
      lowest = std::min(lowest, e[k].id), held = held || e[k].rank == me;
    const std::uint32_t first = std::uint32_t(lowest);
    if (held && fitter[g] != me) plan.given.emplace(first, fitter[g]);
    if ((held || fitter[g] == me) && !(held && first_own.at(e[b].key) == lowest))
      extra.emplace_back(first, e[b].key);
    if (fitter[g] == me) {
      std::vector<int> to;
      for (std::size_t k = b; k < f; ++k)
        if (e[k].rank != me) to.push_back(e[k].rank);
      if (!to.empty()) plan.serve.emplace_back(first, std::move(to));
    }
  }
  std::sort(extra.begin(), extra.end());
  for (const auto& [id, key] : extra) plan.extra.push_back(id), plan.extra_keys.push_back(key);
  std::sort(plan.serve.begin(), plan.serve.end());
  return plan;
}

// The fits this rank made of families other ranks hold, to those ranks, and theirs into this
// rank's given rows (first members' rows of the families held here that another rank fits): per
// family its first member, row length, m, a, b, kappa, bonds0, fitted, omega and shear_omega.
void exchange_fits(const dist::Comm& comm, const FamilyPlan& plan,
                   const std::unordered_map<std::uint32_t, std::size_t>& row_of, PdConstants& out,
                   PdBonds& b) {
  std::vector<std::vector<char>> send(std::size_t(comm.size()));
  for (const auto& [id, to] : plan.serve) {
    const std::size_t q = row_of.at(id);
    const std::uint64_t k0 = b.offsets[q], k1 = b.offsets[q + 1];
    std::vector<char> rec;
    put(rec, id), put(rec, std::uint32_t(k1 - k0));
    put(rec, out.m[q]), put(rec, out.a[q]), put(rec, out.b[q]), put(rec, out.kappa[q]);
    put(rec, out.bonds0[q]), put(rec, out.fitted[q]);
    for (std::uint64_t k = k0; k < k1; ++k) put(rec, b.omega[k]), put(rec, b.shear_omega[k]);
    for (int r : to)
      send[std::size_t(r)].insert(send[std::size_t(r)].end(), rec.begin(), rec.end());
  }
  const std::vector<std::vector<char>> recv = comm.alltoall(send);
  std::size_t got = 0;
  for (const std::vector<char>& from : recv)
    for (const char *p = from.data(), *end = p + from.size(); p < end; ++got) {
      const auto id = get<std::uint32_t>(p), nb = get<std::uint32_t>(p);
      const auto it = plan.given.count(id) ? row_of.find(id) : row_of.end();
      if (it == row_of.end() || b.offsets[it->second + 1] - b.offsets[it->second] != nb)
        throw std::logic_error("distributed peridynamics: a family's fit for no row here");
      const std::size_t q = it->second;
      out.m[q] = get<Real>(p), out.a[q] = get<Real>(p), out.b[q] = get<Real>(p);
      out.kappa[q] = get<Real>(p);
      out.bonds0[q] = get<std::int32_t>(p), out.fitted[q] = get<std::uint8_t>(p);
      for (std::uint64_t k = b.offsets[q]; k < b.offsets[q + 1]; ++k)
        b.omega[k] = get<Real>(p), b.shear_omega[k] = get<Real>(p);
    }
  if (got != plan.given.size())
    throw std::logic_error("distributed peridynamics: a shared family's fit did not arrive");
}

}  // namespace

// The set-up of a distributed run without the whole bond list. Every rank holds every particle's
// attributes (the scene was set up alike on every rank: ~100 bytes per particle, against ~46 per
// directed bond and ~120 bonds per particle) and their positions serve three look-ups that need
// no communication: the row lengths of a slice (the cuts' weights), the owners, and each row's
// neighbours. Rows are built for the own particles only, plus, with the surface correction, the
// first particle (global id) of each of their families owned by another rank: pd_constants fits a
// family once, at its first member, whose bond vectors (rounded differently at other positions)
// give the shared factors, so that particle's row is fitted here too, first. The ghosts' constants
// and the far ends' per-bond values (omega_r, shear_omega_r) come from their owners. The power
// iteration of the critical step runs on the distributed layout, its two sums in global id order
// on rank 0. Bitwise initialize() then distribute() (tests/test_dist_pd.cpp).
void PdSolver::initialize_distributed(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  if (comm.size() == 1) return initialize(space);
  if (initialized_) throw std::logic_error("PdSolver: initialize_distributed() twice");
  if (!meshes_.empty()) throw InputError(kMeshesNotDistributed);
  const auto t0 = std::chrono::steady_clock::now();
  const std::size_t n = particles_.size();
  if (n >= std::size_t(UINT32_MAX))
    throw std::runtime_error("distributed peridynamics: over 2^32 particles");
  const Vec3* x0 = particles_.vec3(attr_.x0);
  const Vec3* x = particles_.vec3(attr_.x);
  const Real* vol = particles_.real(attr_.volume);
  const std::int32_t* mat = particles_.int32(attr_.material);
  const PdParams prm = params();
  std::optional<exec::ScopedRegion> region;  // the set-up's steps, each a profiler region
  region.emplace(space.profiler(), "pd.setup_cut");
  // 1. The cuts: a slice of the particles, weighted by their row lengths (counted, not stored).
  const std::uint64_t r = std::uint64_t(comm.rank()), R = std::uint64_t(comm.size());
  const std::uint64_t b = n * r / R, e = n * (r + 1) / R;
  std::vector<std::uint32_t> slice(e - b);
  for (std::uint64_t i = b; i < e; ++i) slice[i - b] = std::uint32_t(i);
  const std::vector<std::uint64_t> len =
      pd_count_bonds(space, x0, n, slice.data(), slice.size(), settings_.horizon);
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  std::vector<float> w;
  for (std::uint64_t i = b; i < e; ++i) {
    double p[3];
    own_point(x0[i], i, settings_.spacing, p);
    ids.push_back(i);
    xyz.insert(xyz.end(), p, p + 3);
    w.push_back(float(1 + len[i - b]));
  }
  auto ranks = std::make_shared<Ranks>();
  ranks->cuts = dist::RcbCuts::partition(ids, xyz, w);
  ranks->n_global = n;
  std::vector<int> owner(n);
  std::vector<std::uint32_t> own;
  for (std::size_t i = 0; i < n; ++i) {
    double p[3];
    own_point(x0[i], i, settings_.spacing, p);
    owner[i] = ranks->cuts.owner(p);
    if (owner[i] == comm.rank()) own.push_back(std::uint32_t(i));
  }
  // 2. The own rows (neighbours by global id), and the families' first members elsewhere.
  region.emplace(space.profiler(), "pd.setup_rows");
  PdBonds rows;
  pd_build_bond_rows(space, x0, vol, mat, n, own.data(), own.size(), prm, settings_.partial_volume,
                     rows);
  double vmax = 0;
  for (Real v : rows.volume) vmax = std::max(vmax, double(v));
  vmax = comm.max(vmax);                // the whole list's largest bond volume (exact)
  std::vector<std::uint32_t> at = own;  // row q's particle
  std::size_t extra = 0;
  // Every model: a family's rows copy its first member's omega (and fits), that member's row
  // being the whole list's first of the family. Each family is fitted once over the ranks, by one
  // of the ranks that hold a row of it (family_plan), from that member's row (here a rank's
  // own row, or built here first when another rank owns it); the others receive the fit.
  region.emplace(space.profiler(), "pd.setup_families");
  PdRowSubset own_sub;
  own_sub.particle = own.data(), own_sub.vmax = vmax;
  const std::vector<std::uint64_t> own_key = pd_family_keys(space, x0, mat, rows, prm, &own_sub);
  const FamilyPlan plan = family_plan(comm, own, own_key);
  std::vector<std::uint64_t> key = own_key;
  if (!plan.extra.empty()) {  // their rows first: each family's first row is the whole list's
    PdBonds with;
    pd_build_bond_rows(space, x0, vol, mat, n, plan.extra.data(), plan.extra.size(), prm,
                       settings_.partial_volume, with);
    append_rows(with, rows);
    rows = std::move(with);
    at.insert(at.begin(), plan.extra.begin(), plan.extra.end());
    key.insert(key.begin(), plan.extra_keys.begin(), plan.extra_keys.end());
    extra = plan.extra.size();
  }
  // The first members' rows of the families fitted elsewhere (given: their fits are received)
  // or fitted here for other ranks.
  std::vector<std::uint8_t> given(at.size(), 0);
  std::unordered_map<std::uint32_t, std::size_t> row_of;  // first member -> its row here
  for (const auto& [id, r] : plan.given) row_of.emplace(id, 0);
  for (const auto& sv : plan.serve) row_of.emplace(sv.first, 0);
  std::size_t found = 0;
  for (std::size_t q = 0; q < at.size(); ++q) {
    const auto it = row_of.find(at[q]);
    if (it == row_of.end()) continue;
    it->second = q, ++found;
    given[q] = plan.given.count(at[q]) ? 1 : 0;
  }
  if (found != row_of.size())
    throw std::logic_error("distributed peridynamics: a family's first member has no row here");
  region.emplace(space.profiler(), "pd.setup_constants");
  PdConstants c;
  PdRowSubset sub;
  sub.particle = at.data(), sub.vmax = vmax, sub.key = key.data(), sub.given = given.data();
  sub.exchange = [&](PdConstants& out, PdBonds& b) { exchange_fits(comm, plan, row_of, out, b); };
  dist_stats_.families_fitted =
      pd_constants(space, x0, mat, rows, prm, settings_.surface_correction, c, &sub);
  apply_precracks(space, rows, at.data());
  dist_stats_.rows_built = at.size();
  dist_stats_.family_rows = extra;
  region.emplace(space.profiler(), "pd.setup_records");
  // 3. The local particles as distribute() takes them: the own ones with their rows, the bond
  // neighbours of those rows and the particles within contact reach of their bounding box. Their
  // records carry the own particles' constants (ghosts': zero until their owners send them).
  constants_ = PdConstants();
  constants_.m.assign(n, 0), constants_.a.assign(n, 0), constants_.b.assign(n, 0);
  constants_.kappa.assign(n, 0), constants_.bonds0.assign(n, 0), constants_.fitted.assign(n, 0);
  for (std::size_t q = extra; q < at.size(); ++q) {
    const std::uint32_t i = at[q];
    constants_.m[i] = c.m[q], constants_.a[i] = c.a[q], constants_.b[i] = c.b[q];
    constants_.kappa[i] = c.kappa[q], constants_.bonds0[i] = c.bonds0[q];
    constants_.fitted[i] = c.fitted[q];
  }
  c = PdConstants();
  q_.assign(n, Real(0));
  std::vector<std::uint8_t> keep(n, 0);
  double lo[3] = {1e300, 1e300, 1e300}, hi[3] = {-1e300, -1e300, -1e300};
  for (std::size_t q = extra; q < at.size(); ++q) {
    const std::uint32_t i = at[q];
    keep[i] = 1;
    for (std::uint64_t k = rows.offsets[q]; k < rows.offsets[q + 1]; ++k)
      keep[rows.neighbor[k]] = 1;
    for (int a = 0; a < 3; ++a)
      lo[a] = std::min(lo[a], double(x[i][a])), hi[a] = std::max(hi[a], double(x[i][a]));
  }
  keep_within_contact_reach(x, n, lo, hi, keep);
  std::vector<char> recs;
  std::vector<BondRec> brs;
  std::vector<LocalEntry> entries;
  std::vector<std::size_t> rec_at, row_at;
  brs.reserve(rows.offsets.back() - rows.offsets[extra]);
  const std::size_t kept = std::size_t(std::count(keep.begin(), keep.end(), std::uint8_t(1)));
  recs.reserve(kept * record_layout(particles_).bytes);
  rec_at.reserve(kept), row_at.reserve(kept), entries.reserve(kept);
  std::size_t q = extra;  // the next own row
  for (std::size_t i = 0; i < n; ++i) {
    if (!keep[i]) continue;
    rec_at.push_back(recs.size());
    pack_record(recs, i);
    row_at.push_back(brs.size());
    const bool mine = owner[i] == comm.rank();
    std::uint32_t row_len = 0;
    if (mine) {  // own rows come in increasing id, as the particles here
      for (std::uint64_t k = rows.offsets[q]; k < rows.offsets[q + 1]; ++k) {
        BondRec br{};
        br.nb = rows.neighbor[k];
        br.L = rows.length[k], br.omega = rows.omega[k], br.shear = rows.shear_omega[k];
        br.vol = rows.volume[k], br.plastic = rows.plastic[k];
        br.intact = rows.intact[k], br.lane = rows.lane[k];
        brs.push_back(br);
      }
      row_len = std::uint32_t(rows.offsets[q + 1] - rows.offsets[q]);
    }
    entries.push_back(
        {i, owner[i], nullptr, nullptr, row_len, mine ? rows.dense[q] : std::uint8_t(1)});
    q += mine;
  }
  rows = PdBonds();
  for (std::size_t k = 0; k < entries.size(); ++k) {
    entries[k].rec = recs.data() + rec_at[k];
    entries[k].row = entries[k].owner == comm.rank() ? brs.data() + row_at[k] : nullptr;
  }
  // The critical step's start vector: the single process's draw over every particle.
  const std::vector<Vec3> start_all = probe_start();
  settings_.compact_fraction = 0;  // as distribute()
  region.emplace(space.profiler(), "pd.setup_assemble");
  assemble_local(space, entries, ranks, true);
  std::vector<char>().swap(recs);
  std::vector<BondRec>().swap(brs);
  mirror_distributed();
  bonds_initial_ = comm.sum(std::uint64_t(bonds_.size()));
  initialized_ = true;
  region.emplace(space.profiler(), "pd.setup_contact");
  build_contact_list(space);
  region.emplace(space.profiler(), "pd.setup_critical_dt");
  std::vector<Vec3> start(particles_.size());
  for (std::size_t i = 0; i < start.size(); ++i) start[i] = start_all[ranks_->gid[i]];
  crit_dt_ = critical_dt(space, &start);
  // Initial accelerations (velocity Verlet needs a^0), as a step's passes and exchanges.
  region.emplace(space.profiler(), "pd.setup_first_forces");
  compute_dilatation(space);
  share(particles_.real(attr_.theta));
  share(q_.data());
  compute_forces(space);
  contact_forces(space);
  update_damage(space);
  kick(space, 0);
  // Every ghost holds its owner's values, as when distribute() takes them from the whole state.
  for (int a = 0; a < particles_.attribute_count(); ++a)
    share_bytes(particles_.words(a), std::size_t(particles_.words_per_particle(a)) * 4);
  region.reset();
  dist_stats_.step_bytes = dist_stats_.step_messages = 0;
  dist_stats_.setup_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ++version_;
}

void PdSolver::mirror_distributed() {
  const std::size_t nb = bonds_.size();
  std::vector<Real> both(2 * nb);
  const std::vector<Real>* from[2] = {&bonds_.omega, &bonds_.shear_omega};
  std::vector<Real>* to[2] = {&bonds_.omega_r, &bonds_.shear_omega_r};
  for (int f = 0; f < 2; ++f) {
    std::copy(from[f]->begin(), from[f]->end(), both.begin());
    ranks_->bond_halo.exchange(both.data());
    for (std::uint64_t k = 0; k < nb; ++k) {
      const std::uint64_t rv = bonds_.reverse[k];
      (*to[f])[k] = rv != kNoReverse ? (*from[f])[rv] : both[nb + k];
    }
  }
  for (std::uint64_t k = 0; k < nb; ++k)
    if (bonds_.reverse[k] != kNoReverse) bonds_.plastic_r[k] = bonds_.plastic[bonds_.reverse[k]];
  if (!params().plastic) {  // the bond halo and reverse indices serve plastic materials only
    bonds_.reverse.assign(nb, kNoReverse);  // (as assemble_local leaves them without)
    auto rk = std::make_shared<Ranks>(*ranks_);
    rk->bond_halo = dist::HaloPlan();
    ranks_ = std::move(rk);
  } else {
    share_plastic();
  }
  share(constants_.m.data()), share(constants_.a.data()), share(constants_.b.data());
  share(constants_.kappa.data()), share(constants_.bonds0.data()), share(constants_.fitted.data());
}

bool PdSolver::restore_distributed(const exec::Space& space, const ParticleSet& all,
                                   const std::vector<std::uint64_t>& offsets,
                                   const std::vector<std::uint32_t>& neighbor,
                                   const std::vector<Real>& plastic,
                                   const std::vector<std::uint8_t>& intact) {
  const dist::Comm& comm = dist::Comm::world();
  const Ranks& rk = *ranks_;
  const std::uint64_t N = rk.n_global;
  bool bad = all.size() != N || offsets.size() != N + 1 || offsets[0] != 0 ||
             offsets[N] != neighbor.size() || plastic.size() != neighbor.size() ||
             intact.size() != neighbor.size() ||
             all.attribute_count() != particles_.attribute_count();
  std::vector<std::uint8_t> keep(bonds_.size(), 0);
  if (!bad) {
    for (int a = 0; a < particles_.attribute_count(); ++a) {  // every local particle's state
      const std::size_t wa = std::size_t(particles_.words_per_particle(a));
      for (std::size_t i = 0; i < particles_.size(); ++i)
        std::memcpy(particles_.words(a) + i * wa, all.words(a) + rk.gid[i] * wa, wa * 4);
    }
    // Own rows: the checkpoint's row (global ids) must be a sorted subsequence of the row here.
    for (std::uint32_t i : rk.own) {
      const std::uint64_t g = rk.gid[i];
      std::uint64_t k = bonds_.offsets[i];
      const std::uint64_t k1 = bonds_.offsets[i + 1];
      if (offsets[g] > offsets[g + 1] || offsets[g + 1] > neighbor.size()) {
        bad = true;
        break;
      }
      for (std::uint64_t c = offsets[g]; c < offsets[g + 1] && !bad; ++c) {
        while (k < k1 && rk.gid[bonds_.neighbor[k]] < neighbor[c]) ++k;
        if (k == k1 || rk.gid[bonds_.neighbor[k]] != neighbor[c]) {
          bad = true;
          break;
        }
        keep[k] = 1;
        bonds_.plastic[k] = plastic[c];
        bonds_.intact[k] = intact[c];
        ++k;
      }
    }
  }
  if (comm.max(std::int64_t(bad)) > 0) return false;
  // The kept rows migrate nowhere (the cuts stay), the ghosts are chosen from the restored
  // positions, then the far ends' plastic extensions and the contact list.
  relocal(space, false, &keep);
  for (std::uint64_t k = 0; k < bonds_.size(); ++k)
    if (bonds_.reverse[k] != kNoReverse) bonds_.plastic_r[k] = bonds_.plastic[bonds_.reverse[k]];
  share_plastic();
  contact_list_ = PdContactList();
  build_contact_list(space);
  const Real d = settings_.contact ? contact_distance() : Real(0);
  intact_ = kept_broken_ = 0;
  for (std::size_t k = 0; k < bonds_.size(); ++k) {
    intact_ += bonds_.intact[k];
    kept_broken_ += !bonds_.intact[k] && pd_contact_reads_broken_bond(bonds_.length[k], d);
  }
  meshes_intact_ = intact_;
  return true;
}

// The local state from its entries (sorted here by global id): particles, constants, the rows
// renumbered to local indices, the ghost plan, the drives.
void PdSolver::assemble_local(const exec::Space& space, std::vector<LocalEntry>& entries,
                              std::shared_ptr<Ranks> ranks, bool bond_plan) {
  const dist::Comm& comm = dist::Comm::world();
  std::sort(entries.begin(), entries.end(),
            [](const LocalEntry& a, const LocalEntry& b) { return a.gid < b.gid; });
  const std::size_t n = entries.size();
  const RecordLayout L = record_layout(particles_);
  ParticleSet ps;
  for (int a = 0; a < particles_.attribute_count(); ++a)
    ps.add(particles_.name(a), particles_.type(a), particles_.width(a));
  ps.resize(n);
  PdConstants c;
  c.m.resize(n), c.a.resize(n), c.b.resize(n), c.kappa.resize(n), c.bonds0.resize(n);
  c.fitted.resize(n);
  q_.assign(n, Real(0));
  ranks->gid.resize(n), ranks->owned.assign(n, 0), ranks->owner.resize(n), ranks->own.clear();
  std::vector<std::uint64_t> off(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i) {
    const LocalEntry& e = entries[i];
    for (int a = 0; a < ps.attribute_count(); ++a) {
      const std::size_t wa = std::size_t(ps.words_per_particle(a));
      std::memcpy(ps.words(a) + i * wa, e.rec + L.attr_offset[std::size_t(a)], wa * 4);
    }
    const char* p = e.rec + L.constants;
    c.m[i] = get<Real>(p), c.a[i] = get<Real>(p), c.b[i] = get<Real>(p);
    c.kappa[i] = get<Real>(p), q_[i] = get<Real>(p), c.bonds0[i] = get<std::int32_t>(p);
    c.fitted[i] = get<std::uint8_t>(p);
    ranks->gid[i] = e.gid;
    ranks->owner[i] = e.owner;
    if (e.row) ranks->owned[i] = 1, ranks->own.push_back(std::uint32_t(i));
    off[i + 1] = off[i] + (e.row ? e.len : 0);
  }
  PdBonds bd;
  const std::uint64_t nb = off[n];
  bd.offsets = off;
  bd.neighbor.resize(nb), bd.reverse.assign(nb, kNoReverse), bd.length.resize(nb);
  bd.omega.resize(nb), bd.shear_omega.resize(nb), bd.volume.resize(nb), bd.plastic.resize(nb);
  bd.intact.resize(nb), bd.omega_r.resize(nb), bd.shear_omega_r.resize(nb);
  bd.plastic_r.resize(nb), bd.lane.resize(nb), bd.dense.resize(n);
  const std::vector<std::uint64_t>& gid = ranks->gid;
  std::vector<int> missing(n, 0);
  exec::parallel_for(space, "pd.dist_rows", exec::Index(n), [&](exec::Index ii) {
    const std::size_t i = std::size_t(ii);
    const LocalEntry& e = entries[i];
    bd.dense[i] = e.row ? e.dense : 1;
    if (!e.row) return;
    for (std::uint32_t m = 0; m < e.len; ++m) {
      const BondRec& br = e.row[m];
      const std::uint64_t k = off[i] + m;
      const auto it = std::lower_bound(gid.begin(), gid.end(), br.nb);
      if (it == gid.end() || *it != br.nb) {
        missing[i] = 1;
        continue;
      }
      bd.neighbor[k] = std::uint32_t(it - gid.begin());
      bd.length[k] = br.L, bd.omega[k] = br.omega, bd.shear_omega[k] = br.shear;
      bd.volume[k] = br.vol, bd.plastic[k] = br.plastic, bd.omega_r[k] = br.omega_r;
      bd.shear_omega_r[k] = br.shear_r, bd.plastic_r[k] = br.plastic_r;
      bd.intact[k] = br.intact, bd.lane[k] = br.lane;
    }
  });
  for (std::size_t i = 0; i < n; ++i)
    if (missing[i])
      throw std::logic_error("distributed peridynamics: rank " + std::to_string(comm.rank()) +
                             " lacks a bond neighbour of particle " + std::to_string(gid[i]));
  // Reverse bonds within this rank's rows (pd_dilatation writes their plastic_r); the others'
  // come through the bond halo. A rank asks the far end's owner for bond (j, i) only when j is a
  // ghost here, and there i is then a ghost: so only the own bonds to ghosts are offered.
  const bool plastic = params().plastic || bond_plan;
  std::vector<std::uint64_t> bond_own_ids, bond_ghost_ids;
  std::vector<std::uint32_t> bond_own_slots, bond_ghost_slots;
  std::vector<int> bond_ghost_owner;
  const std::uint64_t N = ranks->n_global;
  if (plastic)
    exec::parallel_for(space, "pd.dist_reverse", exec::Index(n), [&](exec::Index ii) {
      const std::size_t i = std::size_t(ii);
      const auto b = bd.neighbor.begin();
      for (std::uint64_t k = off[i]; k < off[i + 1]; ++k) {
        const std::uint32_t j = bd.neighbor[k];
        if (!entries[j].row) continue;
        const auto it = std::lower_bound(b + std::ptrdiff_t(off[j]), b + std::ptrdiff_t(off[j + 1]),
                                         std::uint32_t(i));
        if (it != b + std::ptrdiff_t(off[j + 1]) && *it == i) bd.reverse[k] = std::uint64_t(it - b);
      }
    });
  for (std::size_t i = 0; i < n && plastic; ++i)
    for (std::uint64_t k = off[i]; k < off[i + 1]; ++k) {
      const std::uint32_t j = bd.neighbor[k];
      if (entries[j].row) continue;
      bond_own_ids.push_back(gid[i] * N + gid[j]), bond_own_slots.push_back(std::uint32_t(k));
      bond_ghost_ids.push_back(gid[j] * N + gid[i]);
      bond_ghost_slots.push_back(std::uint32_t(nb + k));
      bond_ghost_owner.push_back(entries[j].owner);
    }
  if (nb * 2 > std::uint64_t(UINT32_MAX))
    throw std::runtime_error("distributed peridynamics: over 2^31 bonds on one rank");
  std::size_t bat = 0;
  ranks->bond_halo = dist::HaloPlan(bond_own_ids, bond_own_slots, bond_ghost_ids, bond_ghost_slots,
                                    [&](std::uint64_t) { return bond_ghost_owner[bat++]; });
  // The ghost plan: own ids and slots; ghosts with their owners.
  std::vector<std::uint64_t> own_ids, ghost_ids;
  std::vector<std::uint32_t> own_slots, ghost_slots;
  std::vector<int> ghost_owner;
  for (std::size_t i = 0; i < n; ++i) {
    if (ranks->owned[i]) {
      own_ids.push_back(gid[i]), own_slots.push_back(std::uint32_t(i));
    } else {
      ghost_ids.push_back(gid[i]), ghost_slots.push_back(std::uint32_t(i));
      ghost_owner.push_back(ranks->owner[i]);
    }
  }
  std::size_t at = 0;  // the owner_of calls come in ghost order
  ranks->halo = dist::HaloPlan(own_ids, own_slots, ghost_ids, ghost_slots,
                               [&](std::uint64_t) { return ghost_owner[at++]; });
  particles_ = std::move(ps);
  constants_ = std::move(c);
  bonds_ = std::move(bd);
  force_.assign(n, Vec3::Zero());
  ranks_ = std::move(ranks);
  global_stored_ = dist::Comm::world().sum(std::uint64_t(bonds_.size()));
  dist_stats_.owned = own_ids.size();
  dist_stats_.ghosts = ghost_ids.size();
  select_drives();
  ++version_;
}

void PdSolver::select_drives() {
  const Vec3* x0 = particles_.vec3(attr_.x0);
  for (Drive& d : drives_) {
    d.particles.clear();
    for (std::size_t i = 0; i < particles_.size(); ++i)
      if ((x0[i].array() >= d.lo.array()).all() && (x0[i].array() <= d.hi.array()).all())
        d.particles.push_back(std::uint32_t(i));
  }
}

void PdSolver::build_contact_list(const exec::Space& space) {
  if (!settings_.contact) return;
  const Real skin =
      settings_.contact_skin > 0 ? settings_.contact_skin : Real(0.5) * settings_.spacing;
  pd_build_contact_list(space, particles_.vec3(attr_.x), particles_.size(),
                        contact_distance() + skin, contact_list_);
  ++contact_builds_;
}

void PdSolver::exchange_positions(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  const Ranks& rk = *ranks_;
  bool rebuild = false;
  if (settings_.contact) {
    // Every rank's largest displacement since the list was built, as an exact maximum.
    Real mine = 0;
    const bool fresh = contact_list_.x_built.size() != particles_.size();
    if (!fresh) {
      const Vec3* x = particles_.vec3(attr_.x);
      for (std::uint32_t i : rk.own)
        mine = std::max(mine, (x[i] - contact_list_.x_built[i]).norm());
    }
    const Real skin =
        settings_.contact_skin > 0 ? settings_.contact_skin : Real(0.5) * settings_.spacing;
    rebuild = comm.max(fresh ? 1e300 : double(mine)) > double(skin / 2);
  }
  bool repartition = false;
  static const long long forced = [] {
    const char* e = std::getenv("AMALGAM_TEST_REPARTITION_EVERY");
    return e ? std::atoll(e) : 0LL;
  }();
  if (forced > 0) {
    repartition = steps_ % std::uint64_t(forced) == std::uint64_t(forced) - 1;
  } else if (rebuild && steps_ >= rk.last_cut_step + kRepartitionGap) {
    // Work per rank: the own rows' bonds and contact candidates.
    std::uint64_t work = bonds_.size() + rk.own.size();
    if (settings_.contact && contact_list_.offsets.size() == particles_.size() + 1)
      for (std::uint32_t i : rk.own)
        work += contact_list_.offsets[i + 1] - contact_list_.offsets[i];
    const double mx = double(comm.max(std::int64_t(work)));
    const double mean = double(comm.sum(work)) / double(comm.size());
    repartition = mean > 0 && mx / mean > kImbalance && mx / mean > 1.1 * dist_stats_.imbalance;
  }
  if (rebuild || repartition) {
    relocal(space, repartition);
    build_contact_list(space);
    return;
  }
  const auto t0 = std::chrono::steady_clock::now();
  share(particles_.vec3(attr_.x));
  share(particles_.vec3(attr_.x_lo));
  dist_stats_.comm_seconds +=
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void PdSolver::share_plastic() {
  if (!ranks_ || !params().plastic) return;
  const auto t0 = std::chrono::steady_clock::now();
  const std::size_t nb = bonds_.size();
  // Slots 0..nb-1: this rank's bonds' plastic extensions (sent); nb + k: bond k's far end's.
  std::vector<Real> both(2 * nb);
  std::copy(bonds_.plastic.begin(), bonds_.plastic.end(), both.begin());
  ranks_->bond_halo.exchange(both.data());
  for (std::uint64_t k = 0; k < nb; ++k)
    if (bonds_.reverse[k] == kNoReverse) bonds_.plastic_r[k] = both[nb + k];
  dist_stats_.step_bytes += ranks_->bond_halo.sent() * sizeof(Real);
  dist_stats_.step_messages += ranks_->bond_halo.messages();
  dist_stats_.comm_seconds +=
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void PdSolver::share_bytes(void* data, std::size_t bytes) const {
  const auto t0 = std::chrono::steady_clock::now();
  ranks_->halo.exchange(data, bytes);
  DistStats& st = dist_stats_;  // mutable: counters only
  st.step_bytes += ranks_->halo.sent() * bytes;
  st.step_messages += ranks_->halo.messages();
  st.comm_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void PdSolver::relocal(const exec::Space& space, bool repartition,
                       const std::vector<std::uint8_t>* keep) {
  const auto t0 = std::chrono::steady_clock::now();
  const dist::Comm& comm = dist::Comm::world();
  const Ranks& old = *ranks_;
  const RecordLayout L = record_layout(particles_);
  const Vec3* x0 = particles_.vec3(attr_.x0);
  const Vec3* x = particles_.vec3(attr_.x);
  const std::size_t R = std::size_t(comm.size());
  auto ranks = std::make_shared<Ranks>();
  ranks->n_global = old.n_global;
  ranks->last_cut_step = old.last_cut_step;
  // 1. The cuts: kept, or made anew from the own particles (weighted by their rows).
  if (repartition) {
    std::vector<std::uint64_t> ids;
    std::vector<double> xyz;
    std::vector<float> w;
    for (std::uint32_t i : old.own) {
      double p[3];
      own_point(x0[i], old.gid[i], settings_.spacing, p);
      ids.push_back(old.gid[i]);
      xyz.insert(xyz.end(), p, p + 3);
      w.push_back(float(1 + bonds_.offsets[i + 1] - bonds_.offsets[i]));
    }
    ranks->cuts = dist::RcbCuts::partition(ids, xyz, w);
    ranks->last_cut_step = steps_;
    ++dist_stats_.repartitions;
  } else {
    ranks->cuts = old.cuts;
  }
  // 2. Own particles to their (new) owners with their rows: gid, record, row length, dense,
  // bonds (neighbours by global id).
  std::vector<std::vector<char>> mig(R);
  for (std::uint32_t i : old.own) {
    int to = comm.rank();
    if (repartition) {
      double p[3];
      own_point(x0[i], old.gid[i], settings_.spacing, p);
      to = ranks->cuts.owner(p);
    }
    std::vector<char>& b = mig[std::size_t(to)];
    put(b, old.gid[i]);
    pack_record(b, i);
    const std::uint64_t k0 = bonds_.offsets[i], k1 = bonds_.offsets[i + 1];
    std::uint32_t len = 0;  // the row's bonds that stay (a restriction keeps a subsequence)
    for (std::uint64_t k = k0; k < k1; ++k) len += !keep || (*keep)[k];
    put(b, len);
    put(b, std::uint8_t(bonds_.dense[i] && len == k1 - k0));
    for (std::uint64_t k = k0; k < k1; ++k)
      if (!keep || (*keep)[k]) put(b, bond_record(k, old.gid[bonds_.neighbor[k]]));
  }
  std::vector<std::vector<char>> got;
  if (repartition) {
    got = comm.alltoall(mig);
  } else {
    got.assign(R, {});
    got[std::size_t(comm.rank())] = std::move(mig[std::size_t(comm.rank())]);
  }
  // Parse: entries of the own particles (records and rows stay in `got`; rows copied aligned).
  std::vector<LocalEntry> entries;
  std::vector<std::vector<BondRec>> rows;
  for (std::size_t r = 0; r < R; ++r) {
    const char* p = got[r].data();
    const char* end = p + got[r].size();
    while (p < end) {
      LocalEntry e{};
      e.gid = get<std::uint64_t>(p);
      e.owner = comm.rank();
      e.rec = p;
      p += L.bytes;
      e.len = get<std::uint32_t>(p);
      e.dense = get<std::uint8_t>(p);
      rows.emplace_back(e.len);
      if (e.len) std::memcpy(rows.back().data(), p, e.len * sizeof(BondRec));
      p += e.len * sizeof(BondRec);
      entries.push_back(e);
    }
  }
  for (std::size_t k = 0; k < entries.size(); ++k) entries[k].row = rows[k].data();
  // 3. Ghosts pushed by their owners: to the ranks whose cut boxes meet the particle's horizon
  // box (reference configuration), and to those whose own particles' bounding box, widened by
  // the contact reach, holds it (current configuration).
  auto rec_vec3 = [&](const char* rec, ParticleSet::Id a) {
    Vec3 v;
    std::memcpy(v.data(), rec + L.attr_offset[std::size_t(a)], sizeof(Vec3));
    return v;
  };
  double box[6] = {1e300, 1e300, 1e300, -1e300, -1e300, -1e300};
  for (const LocalEntry& e : entries) {
    const Vec3 xe = rec_vec3(e.rec, attr_.x);
    for (int a = 0; a < 3; ++a)
      box[a] = std::min(box[a], double(xe[a])), box[3 + a] = std::max(box[3 + a], double(xe[a]));
  }
  const std::vector<double> boxes = dist::from_bytes<double>(
      comm.allgather(dist::as_bytes(std::vector<double>(box, box + 6)), nullptr));
  const double reach = settings_.contact ? contact_reach() : -1;
  const double hb = 1.001 * double(settings_.horizon) + 0.2 * double(settings_.spacing);
  auto in_box = [&](const Vec3& p, std::size_t r) {
    bool in = reach >= 0;
    for (int a = 0; a < 3; ++a)
      in &=
          double(p[a]) >= boxes[6 * r + a] - reach && double(p[a]) <= boxes[6 * r + 3 + a] + reach;
    return in;
  };
  std::vector<std::vector<char>> push(R);
  std::vector<int> to;
  for (const LocalEntry& e : entries) {
    double pt[3], lo[3], hi[3];
    own_point(rec_vec3(e.rec, attr_.x0), e.gid, settings_.spacing, pt);
    for (int a = 0; a < 3; ++a) lo[a] = pt[a] - hb, hi[a] = pt[a] + hb;
    to = ranks->cuts.ranks_in_box(lo, hi);
    const Vec3 xe = rec_vec3(e.rec, attr_.x);
    for (std::size_t r = 0; r < R; ++r)
      if (in_box(xe, r)) to.push_back(int(r));
    std::sort(to.begin(), to.end());
    to.erase(std::unique(to.begin(), to.end()), to.end());
    for (int r : to) {
      if (r == comm.rank()) continue;
      put(push[std::size_t(r)], e.gid);
      push[std::size_t(r)].insert(push[std::size_t(r)].end(), e.rec, e.rec + L.bytes);
    }
  }
  const std::vector<std::vector<char>> ghosts = comm.alltoall(push);
  // Keep the ghosts a row names or within contact reach of this rank's own particles.
  std::vector<std::uint64_t> named;
  for (const auto& row : rows)
    for (const BondRec& br : row) named.push_back(br.nb);
  std::sort(named.begin(), named.end());
  named.erase(std::unique(named.begin(), named.end()), named.end());
  for (std::size_t r = 0; r < R; ++r) {
    const char* p = ghosts[r].data();
    const char* end = p + ghosts[r].size();
    while (p < end) {
      LocalEntry e{};
      e.gid = get<std::uint64_t>(p);
      e.owner = int(r);
      e.rec = p;
      e.dense = 1;
      p += L.bytes;
      if (std::binary_search(named.begin(), named.end(), e.gid) ||
          in_box(rec_vec3(e.rec, attr_.x), std::size_t(comm.rank())))
        entries.push_back(e);
    }
  }
  assemble_local(space, entries, ranks);
  ++dist_stats_.reghosts;
  // Bond work balance after this cut, for the next decision.
  if (repartition || dist_stats_.reghosts == 1) {
    const std::uint64_t work = bonds_.size() + ranks_->own.size();
    const double mean = double(comm.sum(work)) / double(comm.size());
    dist_stats_.imbalance = mean > 0 ? double(comm.max(std::int64_t(work))) / mean : 1.0;
  }
  dist_stats_.comm_seconds +=
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

PdSolver::CrossRank PdSolver::cross_rank() const {
  CrossRank c;
  if (!ranks_) return c;
  const Ranks& rk = *ranks_;
  const Vec3* x = particles_.vec3(attr_.x);
  const Real d = contact_distance();
  const bool list = settings_.contact && contact_list_.offsets.size() == particles_.size() + 1;
  for (std::uint32_t i : rk.own) {
    const std::uint64_t k0 = bonds_.offsets[i], k1 = bonds_.offsets[i + 1];
    for (std::uint64_t k = k0; k < k1; ++k)
      c.broken += !bonds_.intact[k] && !rk.owned[bonds_.neighbor[k]];
    if (!list) continue;
    for (std::uint64_t m = contact_list_.offsets[i]; m < contact_list_.offsets[i + 1]; ++m) {
      const std::uint32_t j = contact_list_.neighbor[m];
      if (rk.owned[j]) continue;
      const Real r2 = (x[j] - x[i]).squaredNorm();
      Real dij = d;  // pd_contact_forces's rule
      const std::uint32_t* row = bonds_.neighbor.data();
      const std::uint32_t* b = std::lower_bound(row + k0, row + k1, j);
      if (b != row + k1 && *b == j) {
        const std::uint64_t k = std::uint64_t(b - row);
        if (bonds_.intact[k]) continue;
        dij = pd_broken_pair_distance(bonds_.length[k], d);
      }
      c.contacts += r2 < dij * dij && r2 > 0;
    }
  }
  return c;
}

std::uint64_t PdSolver::global_sum(std::uint64_t v) const {
  return ranks_ ? dist::Comm::world().sum(v) : v;
}

std::vector<std::uint32_t> PdSolver::owned_local() const {
  if (ranks_) return ranks_->own;
  std::vector<std::uint32_t> all(particles_.size());
  for (std::size_t i = 0; i < all.size(); ++i) all[i] = std::uint32_t(i);
  return all;
}

std::vector<std::uint64_t> PdSolver::global_ids() const {
  if (ranks_) return ranks_->gid;
  std::vector<std::uint64_t> all(particles_.size());
  for (std::size_t i = 0; i < all.size(); ++i) all[i] = i;
  return all;
}

std::size_t PdSolver::global_particle_count() const {
  return ranks_ ? std::size_t(ranks_->n_global) : particles_.size();
}

std::vector<char> PdSolver::gather_owned(const void* data, std::size_t bytes) const {
  const char* base = static_cast<const char*>(data);
  if (!ranks_) return std::vector<char>(base, base + particles_.size() * bytes);
  const dist::Comm& comm = dist::Comm::world();
  std::vector<char> mine;
  for (std::uint32_t i : ranks_->own) {
    put(mine, ranks_->gid[i]);
    mine.insert(mine.end(), base + std::size_t(i) * bytes, base + (std::size_t(i) + 1) * bytes);
  }
  const std::vector<char> all = comm.gather(mine, nullptr);
  if (!comm.root()) return {};
  const std::size_t stride = sizeof(std::uint64_t) + bytes, n = all.size() / stride;
  if (n != ranks_->n_global) throw std::logic_error("gather_owned: particles lost or repeated");
  std::vector<char> out(n * bytes);
  std::vector<std::uint8_t> seen(n, 0);
  for (std::size_t k = 0; k < n; ++k) {
    std::uint64_t g;
    std::memcpy(&g, all.data() + k * stride, sizeof g);
    if (g >= n || seen[g]) throw std::logic_error("gather_owned: particles lost or repeated");
    seen[g] = 1;
    std::memcpy(out.data() + g * bytes, all.data() + k * stride + sizeof g, bytes);
  }
  return out;
}

void PdSolver::gather_particles(ParticleSet& out) const {
  if (!ranks_) {
    out = particles_;
    return;
  }
  const RecordLayout L = record_layout(particles_);
  const std::size_t words = L.constants;  // the attributes' bytes of a record
  std::vector<char> rec(particles_.size() * words);
  for (std::size_t i = 0; i < particles_.size(); ++i)
    for (int a = 0; a < particles_.attribute_count(); ++a) {
      const std::size_t wa = std::size_t(particles_.words_per_particle(a));
      std::memcpy(rec.data() + i * words + L.attr_offset[std::size_t(a)],
                  particles_.words(a) + i * wa, wa * 4);
    }
  const std::vector<char> all = gather_owned(rec.data(), words);
  out = ParticleSet();
  for (int a = 0; a < particles_.attribute_count(); ++a)
    out.add(particles_.name(a), particles_.type(a), particles_.width(a));
  if (!dist::Comm::world().root()) return;
  const std::size_t n = all.size() / std::max<std::size_t>(1, words);
  out.resize(n);
  for (std::size_t i = 0; i < n; ++i)
    for (int a = 0; a < out.attribute_count(); ++a) {
      const std::size_t wa = std::size_t(out.words_per_particle(a));
      std::memcpy(out.words(a) + i * wa, all.data() + i * words + L.attr_offset[std::size_t(a)],
                  wa * 4);
    }
}

void PdSolver::gather_bonds(std::vector<std::uint64_t>& offsets,
                            std::vector<std::uint32_t>& neighbor, std::vector<Real>& plastic,
                            std::vector<std::uint8_t>& intact) const {
  if (!ranks_) {
    offsets = bonds_.offsets, neighbor = bonds_.neighbor, plastic = bonds_.plastic;
    intact = bonds_.intact;
    return;
  }
  const dist::Comm& comm = dist::Comm::world();
  // This rank's rows: (global id, length) pairs, then their bonds (neighbour ids, state).
  std::vector<std::uint64_t> rows;
  std::vector<std::uint32_t> nb;
  for (std::uint32_t i : ranks_->own) {
    rows.insert(rows.end(), {ranks_->gid[i], bonds_.offsets[i + 1] - bonds_.offsets[i]});
    for (std::uint64_t k = bonds_.offsets[i]; k < bonds_.offsets[i + 1]; ++k)
      nb.push_back(std::uint32_t(ranks_->gid[bonds_.neighbor[k]]));
  }
  std::vector<Real> pl;
  std::vector<std::uint8_t> in;
  for (std::uint32_t i : ranks_->own)
    for (std::uint64_t k = bonds_.offsets[i]; k < bonds_.offsets[i + 1]; ++k)
      pl.push_back(bonds_.plastic[k]), in.push_back(bonds_.intact[k]);
  std::vector<std::size_t> row_bytes;
  const std::vector<char> all_rows = comm.gather(dist::as_bytes(rows), &row_bytes);
  const std::vector<char> all_nb = comm.gather(dist::as_bytes(nb), nullptr);
  const std::vector<char> all_pl = comm.gather(dist::as_bytes(pl), nullptr);
  const std::vector<char> all_in = comm.gather(dist::as_bytes(in), nullptr);
  offsets.clear(), neighbor.clear(), plastic.clear(), intact.clear();
  if (!comm.root()) return;
  const std::size_t n = ranks_->n_global;
  const std::vector<std::uint64_t> rl = dist::from_bytes<std::uint64_t>(all_rows);
  std::vector<std::uint64_t> len(n, 0), from(n, 0);
  std::uint64_t at = 0;  // each row's first bond in the gathered arrays
  for (std::size_t k = 0; k + 1 < rl.size(); k += 2)
    len[rl[k]] = rl[k + 1], from[rl[k]] = at, at += rl[k + 1];
  offsets.assign(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i) offsets[i + 1] = offsets[i] + len[i];
  neighbor.resize(offsets[n]);
  plastic.resize(offsets[n]);
  intact.resize(offsets[n]);
  for (std::size_t i = 0; i < n; ++i) {
    if (!len[i]) continue;
    std::memcpy(neighbor.data() + offsets[i], all_nb.data() + from[i] * sizeof(std::uint32_t),
                len[i] * sizeof(std::uint32_t));
    std::memcpy(plastic.data() + offsets[i], all_pl.data() + from[i] * sizeof(Real),
                len[i] * sizeof(Real));
    std::memcpy(intact.data() + offsets[i], all_in.data() + from[i], len[i]);
  }
}

}  // namespace amalgam
