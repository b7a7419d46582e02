// Peridynamics across MPI ranks (issue 28): PdSolver::distribute and what it needs. A first
// step of the spatial decomposition the issue asks for: the bonds (the memory and the work, ~120
// per particle) are split by Zoltan's RCB, each rank computing the rows of the particles it owns;
// the per-particle state stays whole on every rank, the owners' values copied to the others after
// each pass (core/dist/halo.hpp), so every pass reads exactly the bits a single process reads.
// Later steps keep only a halo of ghosts within the horizon and contact distance.
#include <cstring>
#include <limits>
#include <string>

#include "core/dist/comm.hpp"
#include "core/dist/halo.hpp"
#include "core/errors.hpp"
#include "solvers/pd_solver.hpp"

namespace amalgam {

struct PdSolver::Ranks {
  std::vector<int> owner;           // per particle
  std::vector<std::uint8_t> owned;  // per particle: 1 on its owner
  dist::HaloPlan halo;              // every particle this rank does not own is a ghost
};

void PdSolver::share_bytes(void* data, std::size_t bytes) const {
  ranks_->halo.exchange(data, bytes);
}

std::uint64_t PdSolver::global_sum(std::uint64_t v) const {
  return ranks_ ? dist::Comm::world().sum(v) : v;
}

void PdSolver::distribute(const exec::Space& space) {
  const dist::Comm& comm = dist::Comm::world();
  if (comm.size() == 1 || ranks_) return;
  if (!initialized_) throw std::logic_error("PdSolver: distribute() before initialize()");
  if (!meshes_.empty())
    throw InputError(
        "peridynamics on several MPI ranks: embedded tet_mesh crack surfaces are not distributed "
        "yet (issue 28); run one rank");
  for (const PdMaterial& m : materials_)
    if (m.psi0 < std::numeric_limits<Real>::infinity())
      throw InputError(
          "peridynamics on several MPI ranks: plastic materials (a yield stress) are not "
          "distributed yet (issue 28); run one rank");
  const std::size_t n = particles_.size();
  const std::uint64_t r = std::uint64_t(comm.rank()), R = std::uint64_t(comm.size());
  // Each rank hands Zoltan a contiguous slice of the particles, weighted by their bonds (the
  // work of their rows).
  const std::uint64_t b = n * r / R, e = n * (r + 1) / R;
  const Vec3* x0 = particles_.vec3(attr_.x0);
  std::vector<std::uint64_t> ids;
  std::vector<double> xyz;
  std::vector<float> w;
  for (std::uint64_t i = b; i < e; ++i) {
    ids.push_back(i);
    for (int a = 0; a < 3; ++a) xyz.push_back(double(x0[i][a]));
    w.push_back(float(1 + bonds_.offsets[i + 1] - bonds_.offsets[i]));
  }
  const std::vector<int> mine = dist::partition_rcb(ids, xyz, w);
  auto ranks = std::make_shared<Ranks>();
  ranks->owner = dist::from_bytes<int>(comm.allgather(dist::as_bytes(mine), nullptr));
  if (ranks->owner.size() != n) throw std::runtime_error("distribute: owners of the wrong count");
  ranks->owned.assign(n, 0);
  std::vector<std::uint64_t> own_ids, ghost_ids;
  std::vector<std::uint32_t> own_slots, ghost_slots;
  for (std::size_t i = 0; i < n; ++i) {
    const bool o = ranks->owner[i] == comm.rank();
    ranks->owned[i] = o;
    (o ? own_ids : ghost_ids).push_back(i);
    (o ? own_slots : ghost_slots).push_back(std::uint32_t(i));
  }
  const std::vector<int>& owner = ranks->owner;
  ranks->halo = dist::HaloPlan(own_ids, own_slots, ghost_ids, ghost_slots,
                               [&](std::uint64_t id) { return owner[id]; });
  pd_keep_rows(space, bonds_, ranks->owned);
  // Compaction changes no result (broken bonds add exact zeros in their lanes) but rebuilds the
  // reverse indices, which need the other ranks' rows: off when distributed.
  settings_.compact_fraction = 0;
  ranks_ = std::move(ranks);
}

void PdSolver::gather_bonds(std::vector<std::uint64_t>& offsets,
                            std::vector<std::uint32_t>& neighbor, std::vector<Real>& plastic,
                            std::vector<std::uint8_t>& intact) const {
  const dist::Comm& comm = dist::Comm::world();
  const std::size_t n = particles_.size();
  // This rank's rows in order: (row, length) pairs, then their bonds.
  std::vector<std::uint64_t> rows;
  for (std::size_t i = 0; i < n; ++i)
    if (ranks_->owned[i]) rows.insert(rows.end(), {i, bonds_.offsets[i + 1] - bonds_.offsets[i]});
  std::vector<std::size_t> row_bytes, nb_bytes, pl_bytes, in_bytes;
  const std::vector<char> all_rows = comm.gather(dist::as_bytes(rows), &row_bytes);
  const std::vector<char> all_nb = comm.gather(dist::as_bytes(bonds_.neighbor), &nb_bytes);
  const std::vector<char> all_pl = comm.gather(dist::as_bytes(bonds_.plastic), &pl_bytes);
  const std::vector<char> all_in = comm.gather(dist::as_bytes(bonds_.intact), &in_bytes);
  offsets.clear(), neighbor.clear(), plastic.clear(), intact.clear();
  if (!comm.root()) return;
  const std::vector<std::uint64_t> rl = dist::from_bytes<std::uint64_t>(all_rows);
  std::vector<std::uint64_t> len(n, 0);
  for (std::size_t k = 0; k + 1 < rl.size(); k += 2) len[rl[k]] = rl[k + 1];
  offsets.assign(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i) offsets[i + 1] = offsets[i] + len[i];
  neighbor.resize(offsets[n]);
  plastic.resize(offsets[n]);
  intact.resize(offsets[n]);
  // Rank by rank: its rows in increasing order, their bonds in the same order.
  std::size_t row_at = 0, nb_at = 0, pl_at = 0, in_at = 0;
  for (int q = 0; q < comm.size(); ++q) {
    const std::size_t nrows = row_bytes[std::size_t(q)] / (2 * sizeof(std::uint64_t));
    for (std::size_t k = 0; k < nrows; ++k, row_at += 2) {
      const std::uint64_t i = rl[row_at], m = rl[row_at + 1];
      if (m == 0) continue;
      std::memcpy(neighbor.data() + offsets[i], all_nb.data() + nb_at, m * sizeof(std::uint32_t));
      std::memcpy(plastic.data() + offsets[i], all_pl.data() + pl_at, m * sizeof(Real));
      std::memcpy(intact.data() + offsets[i], all_in.data() + in_at, m);
      nb_at += m * sizeof(std::uint32_t), pl_at += m * sizeof(Real), in_at += m;
    }
  }
}

// Per-rank output (issue 28, helper distio): the owned particles are the rank's part.
const std::vector<std::uint8_t>* PdSolver::owned_mask() const {
  return ranks_ ? &ranks_->owned : nullptr;
}

}  // namespace amalgam
